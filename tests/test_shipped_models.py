"""The trained models shipped in models/ load and score what models/README.md says, and the commands
that use them (and the Quickstart, on a tiny budget) run as written, from the repository root."""

from __future__ import annotations

import json
import pathlib
import re
import subprocess
import sys
import zipfile

import pytest

from sb3_dream.evaluation import evaluate_meta

ROOT = pathlib.Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"
SHIPPED = sorted(MODELS.glob("*.zip"))
DREAM_MAP = MODELS / "dream_metabus_map.zip"
RL2DQN_MAP = MODELS / "rl2dqn_metabus_map.zip"
MAP = {"variant": "map"}


def run(*args: str) -> str:
    """Run ``python ARGS...`` from the repository root, as the README's commands are; its stdout."""
    result = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=180)
    assert result.returncode == 0, f"python {' '.join(args)} failed:\n{result.stdout}\n{result.stderr}"
    return result.stdout


def load(path: pathlib.Path):
    with zipfile.ZipFile(path) as archive:
        module = json.loads(archive.read("data"))["policy_class"]["__module__"]
    if module.startswith("sb3_dream.dream"):
        from sb3_dream import DREAM

        return DREAM.load(path, device="cpu")
    from sb3_dream import RL2DQN

    return RL2DQN.load(path, device="cpu")


def test_the_map_models_are_shipped():
    assert DREAM_MAP in SHIPPED and RL2DQN_MAP in SHIPPED


@pytest.mark.parametrize("path", SHIPPED, ids=[p.name for p in SHIPPED])
def test_a_shipped_model_is_small_and_loads_without_replay_buffers(path):
    assert path.stat().st_size < 5_000_000
    with zipfile.ZipFile(path) as archive:
        assert not [n for n in archive.namelist() if "replay" in n or n.endswith(".pkl")]
    model = load(path)
    assert model.observation_space is not None and model.num_timesteps > 0


def test_the_map_model_scores_its_held_out_return():
    """Every held-out (problem, instruction) pair of the map once, weighted: the exact expected
    return of the greedy model (models/README.md); the scripted optimum is 0.8, random about -1.9."""
    result = evaluate_meta(load(DREAM_MAP), "MetaBus-v0", split="test", n_trials=96, env_kwargs=MAP, exhaustive=True)
    assert result.mean >= 0.75


def meta_test(model: str) -> dict:
    """``examples/meta_test.py`` on every held-out pair of the map; the returns it prints, by agent."""
    out = run("examples/meta_test.py", "--model", model, "--env-kwargs", "variant=map", "--trials", "96",
              "--exhaustive", "--exploration")  # fmt: skip
    returns = re.findall(r"^\s*(DREAM|RL2DQN|optimal \(scripted\)|random): execution return (-?[\d.]+)", out, re.M)
    maps = re.findall(r"^\s*(DREAM|RL2DQN) exploring: .*map read (\d+)%", out, re.M)
    return {**{agent: float(r) for agent, r in returns}, **{f"{agent} map read": int(m) for agent, m in maps}}


def test_meta_test_command_on_the_map_models():
    """DREAM reads the map in every exploration and rides the right bus (0.792 of 0.8); RL2DQN,
    trained 2.5 times as long, never reads it and walks to the goal (0.306)."""
    dream = meta_test("models/dream_metabus_map.zip")
    assert dream["DREAM"] >= 0.75 and dream["DREAM map read"] == 100
    assert dream["optimal (scripted)"] == pytest.approx(0.8) and dream["random"] < -1.5
    rl2dqn = meta_test("models/rl2dqn_metabus_map.zip")
    assert 0.2 <= rl2dqn["RL2DQN"] <= 0.4 and rl2dqn["RL2DQN map read"] == 0


def test_watch_command_on_the_map_model(tmp_path):
    """examples/watch_dream.py writes its video to a file (it has no window to show)."""
    video = tmp_path / "map.gif"
    out = run("examples/watch_dream.py", "--model", "models/dream_metabus_map.zip", "--env-kwargs", "variant=map",
              "--out", str(video))  # fmt: skip
    assert video.stat().st_size > 0
    match = re.search(r"exploration (\d+) steps, execution returns ([+-][\d.]+)", out)
    assert match and float(match.group(2)) >= 0.7  # the trial seeded 0: the bus ride, 0.8


def test_quickstart_runs_and_prints_its_return(tmp_path):
    out = run("examples/quickstart.py", "--steps", "300", "--seed", "1", "--save", str(tmp_path / "q.zip"))
    match = re.search(r"held-out return after (\d+) env steps: (-?[\d.]+) \(optimal ([\d.]+)\)", out)
    assert match, out
    assert int(match.group(1)) == 300 and float(match.group(3)) == pytest.approx(0.8)
    assert re.search(r"\[300 steps, \d+s\] test: execution return", out)  # the held-out evaluation's line
    assert load(tmp_path / "q.zip").num_timesteps == 300
