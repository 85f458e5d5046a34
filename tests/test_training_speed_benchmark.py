"""benchmarks/training_speed.py: whole-training env steps/s of the runner's algorithms, per variant."""

from __future__ import annotations

import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "training_speed.py"


@pytest.fixture(scope="module")
def script():
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        import training_speed

        yield training_speed
    finally:
        sys.path.remove(str(SCRIPT.parent))


def test_variants_set_what_they_name(script):
    assert script.variant_kwargs("default") == ({}, {})
    env_kwargs, model_kwargs = script.variant_kwargs("final-frames+loop-adam")
    assert env_kwargs == {"render_mode": "rgb_array", "final_frames": True}
    assert model_kwargs == {"policy_kwargs": {"optimizer_kwargs": {"fused": False}}}
    with pytest.raises(ValueError, match="unknown part.*'fast-adam'.*accepted: default, final-frames, loop-adam"):
        script.variant_kwargs("default+fast-adam")


def test_entries_train_as_named_and_the_table_is_printed():
    out = subprocess.run(
        [sys.executable, str(SCRIPT), "--algo", "dream", "--env", "MetaBandit-v0", "--warmup", "300", "--steps", "40",
         "--rounds", "2", "--n-envs", "2", "--variants", "default", "final-frames+loop-adam"],
        capture_output=True, text=True, check=True, cwd=ROOT,
    ).stdout  # fmt: skip
    lines = out.strip().splitlines()
    assert lines[0] == "dream on MetaBandit-v0, preset fast, 2 envs, 1 torch thread(s)"
    assert [line.split()[0] for line in lines[2:]] == ["default", "final-frames+loop-adam"]
    assert float(lines[2].split()[2]) == 1.0  # the first entry's ratio to itself


def test_build_gives_each_variant_its_envs_and_optimizer(script):
    import argparse

    args = argparse.Namespace(algo="rl2dqn", preset="fast", kwargs={"learning_starts": 40}, env="MetaBandit-v0")
    args.env_kwargs, args.n_envs, args.seed, args.warmup = {}, 2, 0, 60
    default, changed = script.build(args, "default"), script.build(args, "final-frames+loop-adam")
    assert default.env.get_attr("final_frames") == [False, False]
    assert default.env.get_attr("render_mode") == ["rgb_array"] * 2  # as SB3 makes envs from an ID
    assert changed.env.get_attr("final_frames") == [True, True]
    assert default.policy.optimizer.param_groups[0]["fused"] is True
    assert not changed.policy.optimizer.param_groups[0]["fused"]
    assert changed.exploration_steps == 60_000  # the preset's schedule is kept under the variant's arguments
    args.algo, args.preset, args.kwargs = "dream", "laptop", {"policy_kwargs": {"execution_hidden_sizes": (32,)}}
    args.warmup = 300
    merged = script.build(args, "loop-adam").policy
    assert not merged.optimizer.param_groups[0]["fused"] and merged.execution_hidden_sizes == (32,)
    assert not merged.execution_recurrent  # --kwargs' policy_kwargs replace the preset's, as in the runner
