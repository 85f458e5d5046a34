"""sb3_dream.experiments: env specs, validation, the models, and a tiny resumable parallel experiment."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import shutil
import time
import zipfile

import numpy as np
import pytest
from stable_baselines3.common.env_util import make_vec_env

from sb3_dream import experiments
from sb3_dream.evaluation import CURVE_COLUMNS
from sb3_dream.experiments import (
    EnvSpec,
    Run,
    RunConfig,
    check_eval_splits,
    load_curve,
    make_model,
    parse_kwargs,
    plan_runs,
)

TINY_DREAM = [
    "exploration_learning_starts=5", "execution_learning_starts=5", "buffer_size=200", "execution_buffer_size=1000"
]  # fmt: skip


def test_env_spec_parses_id_and_arguments():
    spec = EnvSpec.parse("MetaBus-v0:variant=map:n_exec_episodes=2")
    assert spec.env_id == "MetaBus-v0" and spec.env_kwargs == {"variant": "map", "n_exec_episodes": 2}
    assert spec.n_exec_episodes == 2 and spec.eval_kwargs == {"variant": "map"}
    assert spec.tag == "MetaBus-v0_n_exec_episodes-2_variant-map"
    assert spec.label == "MetaBus-v0 (n_exec_episodes=2, variant=map)"
    module_form = EnvSpec.parse("dream_envs:MetaBandit-v0:horizon=2:split='all'")
    assert module_form.env_id == "dream_envs:MetaBandit-v0" and module_form.env_kwargs == {"horizon": 2, "split": "all"}
    assert module_form.eval_kwargs == {"horizon": 2}  # split is the training split only
    assert EnvSpec.parse("MetaBus-v0") == EnvSpec("MetaBus-v0")
    for bad in ("variant=map", "MetaBus-v0::variant=map", ""):
        with pytest.raises(ValueError, match="envs entry"):
            EnvSpec.parse(bad)
    with pytest.raises(ValueError, match="key=value"):
        parse_kwargs(["buffer_size"], "--dream-kwargs")


def test_bad_settings_are_rejected():
    with pytest.raises(ValueError, match="preset='slow' is not valid"):
        RunConfig(preset="slow")
    with pytest.raises(ValueError, match="steps must be an integer >= 1"):
        RunConfig(steps=0)
    with pytest.raises(ValueError, match="eval_splits"):
        RunConfig(eval_splits=("valid",))
    # MetaCook's own splits are accepted for MetaCook only.
    cook_parts = RunConfig(eval_splits=("test_problems", "test_instructions"))
    check_eval_splits(plan_runs(["dream"], [EnvSpec.parse("MetaCook-v0")], [0]), cook_parts)
    with pytest.raises(ValueError, match=r"eval_splits=\['test_problems', 'test_instructions'\] is not valid for"):
        check_eval_splits(plan_runs(["dream"], [EnvSpec.parse("MetaBus-v0:variant=map")], [0]), cook_parts)
    with pytest.raises(ValueError, match="bottleneck"):
        RunConfig(dream_kwargs=(("bottleneck", False),))
    with pytest.raises(ValueError, match="checkpoint_freq must be an integer >= 0"):
        RunConfig(checkpoint_freq=-1)
    with pytest.raises(ValueError, match="snapshot_freq must be an integer >= 0"):
        RunConfig(snapshot_freq=-1)
    with pytest.raises(ValueError, match="algo='ppo' is not valid"):
        experiments.algorithm_class("ppo")
    with pytest.raises(ValueError, match="algos=.*accepted values: 'dream', 'dream_no_bottleneck', 'rl2dqn'"):
        plan_runs(["ppo"], [EnvSpec("MetaBus-v0")], [0])
    with pytest.raises(ValueError, match="seeds"):
        plan_runs(["dream"], [EnvSpec("MetaBus-v0")], [])
    with pytest.raises(ValueError, match="jobs"):
        experiments.run_experiments([], RunConfig(), "unused", jobs=0)
    with pytest.raises(SystemExit, match="envs entry"):
        experiments.main(["--envs", "=map"])


def test_models_of_each_algorithm_and_preset():
    small = (("buffer_size", 50), ("execution_buffer_size", 100), ("learning_starts", 50))  # SB3's names too
    fast = RunConfig(preset="fast", dream_kwargs=small)
    dream = make_model("dream", "MetaBandit-v0", fast, seed=0)
    ablation = make_model("dream_no_bottleneck", "MetaBandit-v0", fast, seed=0)
    assert dream.bottleneck and not ablation.bottleneck
    assert (dream.exploration_learning_starts, dream.eps_decay_steps, dream.buffer_size) == (100, 30_000, 50)
    assert dream.learning_starts == ablation.learning_starts == 50
    rl2 = make_model("rl2dqn", "MetaBandit-v0", RunConfig(preset="fast", rl2dqn_kwargs=(("buffer_size", 50),)), seed=0)
    assert (rl2.learning_starts, rl2.exploration_steps, rl2.target_update_interval) == (4000, 60_000, 1000)
    paper = make_model("rl2dqn", "MetaBandit-v0", RunConfig(), seed=0)
    assert (paper.learning_starts, paper.exploration_steps) == (16_000, 500_000)
    from sb3_dream import IMPORT, VariBAD

    for algo, cls, field in [("import_dqn", IMPORT, "import_kwargs"), ("varibad", VariBAD, "varibad_kwargs")]:
        model = make_model(algo, "MetaBandit-v0", RunConfig(preset="fast", **{field: (("buffer_size", 50),)}), seed=0)
        assert type(model) is cls and model.buffer_size == 50
        assert (model.learning_starts, model.exploration_steps, model.target_update_interval) == (4000, 60_000, 1000)
    assert plan_runs(["dream", "rl2dqn"], [EnvSpec("A-v0"), EnvSpec("B-v0")], [0, 1])[:3] == [
        Run("dream", EnvSpec("A-v0"), 0), Run("dream", EnvSpec("A-v0"), 1), Run("rl2dqn", EnvSpec("A-v0"), 0)
    ]  # fmt: skip


def test_an_algorithm_is_added_by_registering_its_spec(monkeypatch, tmp_path):
    from sb3_dream.dream import DREAM
    from sb3_dream.experiments import ALGORITHMS, AlgorithmSpec, register_algorithm

    spec = AlgorithmSpec(
        "dream_sync100", load_class=lambda: DREAM, presets={"paper": {"target_update_interval": 100}},
        overrides="dream_kwargs",
    )  # fmt: skip
    monkeypatch.setitem(ALGORITHMS, spec.name, spec)  # as register_algorithm does, undone after the test
    assert register_algorithm(spec) is spec  # the same spec again: nothing changes
    with pytest.raises(ValueError, match="an algorithm named 'dream_sync100' is already registered"):
        register_algorithm(dataclasses.replace(spec, presets={}))
    (run,) = plan_runs([spec.name], [EnvSpec("MetaBandit-v0")], [0])
    small = RunConfig(dream_kwargs=(("buffer_size", 50), ("execution_buffer_size", 100)))
    model = make_model(run.algo, "MetaBandit-v0", small, seed=0)
    assert (model.target_update_interval, model.buffer_size) == (100, 50)  # its preset, then the overrides
    with pytest.raises(ValueError, match="preset='fast' is not defined for dream_sync100; its presets: 'paper'"):
        make_model(spec.name, "MetaBandit-v0", RunConfig(preset="fast"), seed=0)
    with pytest.raises(SystemExit, match="preset='fast' is not defined for dream_sync100"):
        experiments.main(["--algos", "dream", spec.name, "--preset", "fast", "--out", str(tmp_path)])
    with pytest.raises(ValueError, match="must not set bottleneck: choose the algorithm dream or dream_no_bottleneck"):
        RunConfig(dream_kwargs=(("bottleneck", True),))


def test_runs_go_to_the_backend_given(tmp_path, capsys):
    from test_runner_lock import Recording

    runs, backend = plan_runs(["dream", "rl2dqn"], [EnvSpec("MetaBandit-v0")], [0]), Recording()
    records = experiments.run_experiments(runs, RunConfig(), tmp_path, backend=backend)
    assert backend.runs == runs and [r["status"] for r in records] == ["done", "done"]
    assert "running 2 run(s), 2 at a time" in capsys.readouterr().out
    with pytest.raises(ValueError, match="give jobs or backend, not both"):
        experiments.run_experiments(runs, RunConfig(), tmp_path, jobs=2, backend=backend)


def test_tiny_experiment_runs_in_parallel_then_resumes(tmp_path, capsys):
    out = tmp_path / "results"
    argv = [
        "--algos", "dream", "--envs", "MetaBandit-v0", "--seeds", "0", "1", "--steps", "120", "--eval-freq", "60",
        "--eval-trials", "4", "--jobs", "2", "--out", str(out), "--dream-kwargs", *TINY_DREAM,
    ]  # fmt: skip
    records = experiments.main(argv)
    assert sorted(r["status"] for r in records) == ["done", "done"]
    first = capsys.readouterr().out
    assert "running 2 run(s), 2 at a time" in first

    folder = out / "MetaBandit-v0"
    curves = [load_curve(folder / f"dream_seed{s}.csv") for s in (0, 1)]
    for curve in curves:
        np.testing.assert_array_equal(curve["env_steps"], [0, 60, 120])  # at the start, every 60 steps, the end
        assert np.all((curve["mean"] >= 0) & (curve["mean"] <= 1)) and np.all(np.diff(curve["wall_clock_s"]) >= 0)
    assert not list(folder.glob("*.partial"))
    info = json.loads((folder / "dream_seed0.json").read_text())
    assert info["settings"]["steps"] == 120 and info["final"]["test"]["env_steps"] == 120
    diagnosis = info["diagnosis"]  # DREAM runs end with sb3_dream.dream.diagnose of the final model
    assert diagnosis["n_trials"] == 4 and 0 <= diagnosis["return_g"] <= 1 and 0 <= diagnosis["return_f"] <= 1
    assert 0 <= diagnosis["return_g_optimal_exploration"] <= 1 and diagnosis["decoder_error_optimal_exploration"] > 0
    gains = info["exploration_gains"]  # ... and sb3_dream.dream.exploration_gains on the same trials
    # MetaBandit explores for one step: the information gain of a trial is that step's reward plus c
    assert len(gains["reward_by_step"]) == 1 and gains["reward_penalty"] == 0.01
    assert gains["information_gain"] == pytest.approx(gains["reward_by_step"][0] + 0.01)

    with open(out / "summary.csv") as f:
        (row,) = list(csv.DictReader(f))
    finals = [c["mean"][-1] for c in curves]
    assert (row["algo"], row["split"], row["seeds"], row["env_steps"]) == ("dream", "test", "2", "120")
    assert float(row["final_return_mean"]) == pytest.approx(np.mean(finals))
    assert float(row["final_return_std"]) == pytest.approx(np.std(finals))
    assert float(row["oracle_return"]) == 1.0  # the bandit's optimal scripted agent
    assert "| MetaBandit-v0 | dream | test | 2 |" in first and (out / "summary.md").read_text() in first
    pytest.importorskip("matplotlib")
    assert (out / "curves.png").stat().st_size > 0

    # Summarize only, asking for a seed that was never run: nothing is trained, the table counts two.
    assert experiments.main([*argv, "--seeds", "0", "1", "2", "--summary-only", "--no-plot"]) == []
    assert "| MetaBandit-v0 | dream | test | 2 |" in capsys.readouterr().out
    assert not (folder / "dream_seed2.csv").exists() and not (folder / "dream_seed2.csv.partial").exists()
    # A command about another env still tables (and plots) every finished run under --out.
    other = ["--envs", "MetaBandit-v0:n_exec_episodes=2", "--seeds", "7", "--summary-only", "--no-oracle"]
    assert experiments.main([*argv, *other]) == []
    table = capsys.readouterr().out
    assert "| MetaBandit-v0 (n_exec_episodes=2) | dream | test | 0 |" in table
    assert "| MetaBandit-v0 | dream | test | 2 |" in table
    assert experiments.finished_runs(out) == [Run("dream", EnvSpec("MetaBandit-v0"), s) for s in (0, 1)]

    # Run again: both runs are finished, nothing is trained, nothing is rewritten.
    stamps = {p: p.stat().st_mtime_ns for p in folder.glob("dream_seed*.csv")}
    records = experiments.main(argv)
    assert [r["status"] for r in records] == ["skipped", "skipped"]
    assert {p: p.stat().st_mtime_ns for p in folder.glob("dream_seed*.csv")} == stamps
    assert "running" not in capsys.readouterr().out


def test_exhaustive_evaluations_cover_every_pair_of_the_split(tmp_path, capsys):
    out = tmp_path / "results"
    argv = [
        "--algos", "dream", "--envs", "MetaBandit-v0", "--steps", "40", "--eval-freq", "40", "--eval-trials", "3",
        "--eval-exhaustive", "--jobs", "1", "--out", str(out), "--no-plot", "--dream-kwargs", *TINY_DREAM,
    ]  # fmt: skip
    (record,) = experiments.main(argv)
    folder = out / "MetaBandit-v0"
    info = json.loads((folder / "dream_seed0.json").read_text())
    assert info["settings"]["eval_exhaustive"] is True and "eval_exhaustive" not in RunConfig().settings("dream")
    assert info["diagnosis"]["n_trials"] == 8  # the bandit's 8 problems, one instruction each: one pass
    oracle = json.loads((folder / "oracle_test_exhaustive.json").read_text())
    assert (oracle["mean"], oracle["n_trials"], oracle["exhaustive"]) == (1.0, 8, True)  # 3 trials: one pass of 8
    assert np.isnan(oracle["ci"])  # a single pass measures no spread
    assert not (folder / "oracle_test.json").exists()
    # an exhaustive curve of a deterministic greedy model is exact: no draw, so no half-width after one pass
    assert np.isnan(load_curve(folder / "dream_seed0.csv")["ci"]).all()
    printed = capsys.readouterr().out
    assert "test return 0.125  exploration length" in printed and "nan" not in printed


def test_interrupted_run_starts_over_and_train_split_gets_its_own_curve(tmp_path):
    out = tmp_path / "results"
    config = RunConfig(
        steps=40, eval_freq=40, eval_trials=2, eval_splits=("test", "train"), n_envs=2, snapshot_freq=16,
        dream_kwargs=tuple(sorted(parse_kwargs(TINY_DREAM, "dream").items())),
    )  # fmt: skip
    run = Run("dream_no_bottleneck", EnvSpec.parse("MetaBandit-v0:n_exec_episodes=2"), 3)
    stale = run.curve_path(out, "test").with_name(run.curve_path(out, "test").name + ".partial")
    stale.parent.mkdir(parents=True)
    stale.write_text("env_steps,wall_clock_s,mean,ci,exploration_length\n999,0,0,0,0\n")  # a killed run's rows
    assert not run.is_complete(out, config)
    (record,) = experiments.run_experiments([run], config, out, jobs=1)
    assert record["status"] == "done" and run.is_complete(out, config) and not stale.exists()
    np.testing.assert_array_equal(load_curve(run.curve_path(out, "test"))["env_steps"], [0, 40])
    assert run.curve_path(out, "train").name == "dream_no_bottleneck_seed3_train.csv"
    assert load_curve(run.curve_path(out, "train"))["env_steps"].tolist() == [0, 40]
    # --snapshot-freq 16 with 2 envs: a model every 16 env steps, loadable, not part of the settings
    snapshots = sorted(run.folder(out).glob("snapshots/*.zip"), key=lambda p: int(p.stem.split("_")[-2]))
    assert [p.name for p in snapshots] == [f"dream_no_bottleneck_seed3_{k}_steps.zip" for k in (16, 32)]
    assert experiments.algorithm_class("dream").load(snapshots[-1]).num_timesteps == 32
    assert "snapshot_freq" not in config.settings("dream")


@pytest.mark.parametrize(
    "concurrent_runs, given, expected", [(1, None, "auto"), (2, None, False), (2, True, True), (1, False, False)]
)
def test_runner_turns_parallel_updates_off_when_runs_share_the_cores(tmp_path, concurrent_runs, given, expected):
    from stable_baselines3.common.save_util import load_from_zip_file

    kwargs = TINY_DREAM + ([] if given is None else [f"parallel_updates={given}"])
    config = RunConfig(
        steps=40, eval_freq=40, eval_trials=2, save_models=True,
        dream_kwargs=tuple(sorted(parse_kwargs(kwargs, "dream").items())),
    )  # fmt: skip
    run = Run("dream", EnvSpec.parse("MetaBandit-v0"), 0)
    assert experiments.run_one(run, config, tmp_path, concurrent_runs)["status"] == "done"
    saved, _, _ = load_from_zip_file(run.model_path(tmp_path), device="cpu")
    assert saved["parallel_updates"] == expected  # the user's choice wins; else "auto" for a run alone
    assert ("parallel_updates" in config.settings("dream")["algo_kwargs"]) == (given is not None)


@pytest.mark.parametrize("algo", ["dream", "rl2dqn", "import_dqn", "e_varibad"])
def test_checkpointed_run_resumes_where_it_was_interrupted(tmp_path, monkeypatch, algo):
    out = tmp_path / "results"
    small_recurrent = (("buffer_size", 50), ("learning_starts", 50))
    config = RunConfig(
        steps=400, eval_freq=100, eval_trials=2, checkpoint_freq=200,
        dream_kwargs=tuple(sorted(parse_kwargs(TINY_DREAM, "dream").items())),
        rl2dqn_kwargs=small_recurrent, import_kwargs=small_recurrent, varibad_kwargs=small_recurrent,
    )  # fmt: skip
    run = Run(algo, EnvSpec.parse("MetaBus-v0:variant=map"), 0)
    from sb3_dream.evaluation import MetaEvalCallback

    evaluate = MetaEvalCallback._evaluate

    def interrupted(self):
        if self.num_timesteps >= 300:
            raise KeyboardInterrupt  # killed between the checkpoint at 200 and the next one
        evaluate(self)

    monkeypatch.setattr(MetaEvalCallback, "_evaluate", interrupted)
    from dream_envs.bus import MetaBusEnv

    train_seeds = []  # the seeds the training envs are reset with (evaluation uses the test split)
    reset = MetaBusEnv.reset

    def recording_reset(self, *, seed=None, options=None):
        if seed is not None and self.split == "train":
            train_seeds.append(seed)
        return reset(self, seed=seed, options=options)

    monkeypatch.setattr(MetaBusEnv, "reset", recording_reset)
    with pytest.raises(KeyboardInterrupt):
        experiments.run_one(run, config, out)
    assert train_seeds == [0]  # make_vec_env: the run's seed (+ the env's index; one env here)
    checkpoint = json.loads(run.checkpoint_path(out).read_text())
    assert checkpoint["env_steps"] == 200 and not run.is_complete(out, config)
    assert sorted(p.suffix for p in run.checkpoint_path(out).parent.iterdir()) == [".json", ".pkl", ".zip"]

    monkeypatch.setattr(MetaEvalCallback, "_evaluate", evaluate)
    record = experiments.run_one(run, config, out)
    # Resumed at 200 steps with new seeds: not the problems and instructions of step 0 again.
    assert train_seeds == [0, 200]
    curve = load_curve(run.curve_path(out))
    assert curve["env_steps"].tolist() == [0, 100, 200, 300, 400]  # kept rows, then the new ones
    assert np.all(np.diff(curve["wall_clock_s"]) > 0)
    info = json.loads(run.info_path(out).read_text())
    assert info["resumed_from"] == 200 and record["seconds"] >= checkpoint["train_seconds"]
    if algo == "import_dqn":  # IMPORT runs end with sb3_dream.import_dqn.diagnose of the final model
        assert info["diagnosis"]["n_trials"] == 2 and info["diagnosis"]["problem_spread"] > 0
    # The complete run keeps one checkpoint, at its final step (for a later, larger budget).
    assert json.loads(run.checkpoint_path(out).read_text())["env_steps"] == 400
    assert sorted(p.name for p in run.checkpoint_path(out).parent.iterdir()) == [
        f"{run.name}.400.pkl", f"{run.name}.400.zip", f"{run.name}.json"
    ]  # fmt: skip


def test_a_complete_run_is_extended_by_a_larger_budget_and_redone_by_force(tmp_path, capsys):
    out = tmp_path / "results"
    # policy_kwargs too, parsed afresh for each command as on the command line: the model must not
    # change them, or the checkpoint's settings would not match the next command's.
    dream_kwargs = TINY_DREAM + ["policy_kwargs={'execution_hidden_sizes':(32,)}"]

    def config(steps, checkpoint_freq=100):
        kwargs = tuple(sorted(parse_kwargs(dream_kwargs, "dream").items()))
        return RunConfig(
            steps=steps, eval_freq=100, eval_trials=2, checkpoint_freq=checkpoint_freq, dream_kwargs=kwargs
        )

    run = Run("dream", EnvSpec.parse("MetaBus-v0:variant=map"), 0)
    experiments.run_experiments([run], config(200), out, jobs=1)
    first = load_curve(run.curve_path(out))
    assert first["env_steps"].tolist() == [0, 100, 200]

    # The same budget: finished, skipped.
    (record,) = experiments.run_experiments([run], config(200), out, jobs=1)
    assert record["status"] == "skipped"

    # A larger budget goes on from the kept checkpoint at 200: the first rows are kept as they were.
    (record,) = experiments.run_experiments([run], config(400), out, jobs=1)
    assert record["status"] == "done" and "extend dream" in capsys.readouterr().out
    curve = load_curve(run.curve_path(out))
    assert curve["env_steps"].tolist() == [0, 100, 200, 300, 400]
    assert curve["mean"][:3].tolist() == first["mean"].tolist()
    assert curve["wall_clock_s"][:3].tolist() == first["wall_clock_s"].tolist()
    assert json.loads(run.info_path(out).read_text())["resumed_from"] == 200

    # Without checkpoints a larger budget cannot extend it (it would start over): skipped, warned.
    (record,) = experiments.run_experiments([run], config(600, checkpoint_freq=0), out, jobs=1)
    assert record["status"] == "skipped" and "other settings (steps)" in capsys.readouterr().out

    # --force redoes it from scratch, not from the kept checkpoint.
    (record,) = experiments.run_experiments([run], config(200), out, jobs=1, force=True)
    assert record["status"] == "done"
    assert json.loads(run.info_path(out).read_text())["resumed_from"] is None
    assert load_curve(run.curve_path(out))["env_steps"].tolist() == [0, 100, 200]


def _tensorboard_scalars(folder):
    """{tag: [(step, value), ...]} over the event files in ``folder``."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(folder))
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def test_tensorboard_logs_each_split_under_its_own_keys_and_an_extended_run_goes_on_in_its_log(tmp_path, capsys):
    pytest.importorskip("tensorboard")
    out = tmp_path / "results"

    def config(steps, tensorboard=True):
        return RunConfig(
            steps=steps, eval_freq=20, eval_trials=2, eval_splits=("test", "train"), n_envs=2, checkpoint_freq=20,
            tensorboard=tensorboard, dream_kwargs=tuple(sorted(parse_kwargs(TINY_DREAM, "dream").items())),
        )  # fmt: skip

    run = Run("dream_no_bottleneck", EnvSpec.parse("MetaBandit-v0"), 1)
    experiments.run_experiments([run], config(40), out, jobs=1)
    logs = run.tensorboard_folder(out)
    assert [p.name for p in logs.iterdir()] == [f"{run.name}_1"]
    scalars = _tensorboard_scalars(logs / f"{run.name}_1")
    # the held-out split as SB3's eval/, the training split beside it, each the value its curve has
    for key, split in (("eval", "test"), ("eval_train", "train")):
        curve = load_curve(run.curve_path(out, split))
        logged = scalars[f"{key}/execution_return"]
        assert [step for step, _ in logged] == curve["env_steps"].tolist() == [0, 20, 40]
        np.testing.assert_allclose([value for _, value in logged], curve["mean"], rtol=1e-6)
    assert "train/decoder_loss" in scalars  # the model's own keys (rollout/ too, every log_interval trials)
    assert "tensorboard" not in config(40).settings("dream_no_bottleneck")  # how it is watched, not trained

    # A larger budget goes on from the kept checkpoint, in the same log.
    experiments.run_experiments([run], config(60), out, jobs=1)
    assert [p.name for p in logs.iterdir()] == [f"{run.name}_1"]
    steps = [step for step, _ in _tensorboard_scalars(logs / f"{run.name}_1")["eval/execution_return"]]
    assert steps == [0, 20, 40, 60]
    # and where it goes on without its log (on another node, as with --backend ray), still in _1
    shutil.rmtree(logs)
    experiments.run_experiments([run], config(80), out, jobs=1)
    assert [p.name for p in logs.iterdir()] == [f"{run.name}_1"]
    assert [step for step, _ in _tensorboard_scalars(logs / f"{run.name}_1")["eval/execution_return"]] == [80]

    # Started over (--force): a fresh log in place of the old one.
    experiments.run_experiments([run], config(20), out, jobs=1, force=True)
    assert [p.name for p in logs.iterdir()] == [f"{run.name}_1"]
    steps = [step for step, _ in _tensorboard_scalars(logs / f"{run.name}_1")["eval/execution_return"]]
    assert steps == [0, 20]


def test_tensorboard_flag_says_what_to_install_when_tensorboard_is_missing(monkeypatch, tmp_path):
    import sys

    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # import fails as if not installed
    with pytest.raises(SystemExit, match="--tensorboard needs tensorboard: pip install tensorboard"):
        experiments.main(["--algos", "rl2dqn", "--envs", "MetaBandit-v0", "--tensorboard", "--out", str(tmp_path)])
    assert not any(tmp_path.iterdir())  # no run started


def test_init_from_goes_on_from_another_runs_checkpoint_with_other_settings(tmp_path):
    from sb3_dream.dream import DREAM

    parent_out, out = tmp_path / "parent", tmp_path / "child"
    # policy_kwargs parsed as on the command line: the saved ones also hold what DREAM derived.
    given = TINY_DREAM + ["policy_kwargs={'execution_hidden_sizes':(16,)}"]
    kwargs = tuple(sorted(parse_kwargs(given, "dream").items()))
    run = Run("dream", EnvSpec.parse("MetaBus-v0:variant=map"), 0)
    parent = RunConfig(steps=200, eval_freq=100, eval_trials=2, checkpoint_freq=100, dream_kwargs=kwargs)
    experiments.run_experiments([run], parent, parent_out, jobs=1)
    parent_curve = load_curve(run.curve_path(parent_out))

    overrides = tuple(sorted({**dict(kwargs), "target_update_interval": 7, "reward_penalty": 0.1}.items()))
    child = dataclasses.replace(parent, steps=300, dream_kwargs=overrides, init_from=str(parent_out), save_models=True)
    (record,) = experiments.run_experiments([run], child, out, jobs=1)
    assert record["status"] == "done"
    curve = load_curve(run.curve_path(out))
    assert curve["env_steps"].tolist() == [0, 100, 200, 300]  # the parent's rows, then its own
    assert curve["mean"][:3].tolist() == parent_curve["mean"].tolist()
    info = json.loads(run.info_path(out).read_text())
    assert info["init_from"] == {"out": str(parent_out), "env_steps": 200} and info["resumed_from"] is None
    assert info["settings"]["init_from"] == str(parent_out)
    model = DREAM.load(run.model_path(out))
    assert model.num_timesteps == 300 and model.target_update_interval == 7 and model.reward_penalty == 0.1
    # The parent is left as it was.
    assert load_curve(run.curve_path(parent_out))["env_steps"].tolist() == [0, 100, 200]
    # Extended from its own checkpoint, the run still records where it began.
    (record,) = experiments.run_experiments([run], dataclasses.replace(child, steps=400), out, jobs=1)
    assert record["status"] == "done"
    info = json.loads(run.info_path(out).read_text())
    assert info["init_from"] == {"out": str(parent_out), "env_steps": 200} and info["resumed_from"] == 300

    # An option newer than a checkpoint (absent from its saved data) can be set when going on from it.
    checkpoint = run.model_path(out)
    with zipfile.ZipFile(checkpoint) as saved:
        files = {name: saved.read(name) for name in saved.namelist()}
    data = json.loads(files["data"])
    del data["execution_final_eps"]
    files["data"] = json.dumps(data).encode()
    older = tmp_path / "older.zip"
    with zipfile.ZipFile(older, "w") as doctored:
        for name, content in files.items():
            doctored.writestr(name, content)
    newer = tuple(sorted({**dict(overrides), "execution_final_eps": 0.2}.items()))
    env = make_vec_env(run.env.env_id, n_envs=1, seed=0, env_kwargs=run.env.env_kwargs)
    model = experiments.load_with_overrides("dream", older, env, dataclasses.replace(child, dream_kwargs=newer))
    assert model.execution_final_eps == 0.2 and model.target_update_interval == 7
    with pytest.raises(ValueError, match="no_such_option cannot be changed"):
        experiments.load_with_overrides(
            "dream", older, env, dataclasses.replace(child, dream_kwargs=(*newer, ("no_such_option", 1)))
        )

    # What cannot go on: other networks, other evaluation settings, no parent checkpoint.
    wide = tuple(sorted({**dict(kwargs), "policy_kwargs": {"execution_hidden_sizes": (32,)}}.items()))
    with pytest.raises(ValueError, match="policy_kwargs"):
        experiments.run_one(run, dataclasses.replace(child, dream_kwargs=wide), tmp_path / "wide")
    with pytest.raises(ValueError, match="other eval_trials"):
        experiments.run_one(run, dataclasses.replace(child, eval_trials=3), tmp_path / "trials")
    with pytest.raises(FileNotFoundError, match="no checkpoint of dream_seed1"):
        experiments.run_one(Run("dream", run.env, 1), child, tmp_path / "seed1")


def test_summary_averages_the_last_tenth_of_each_run_besides_its_final_evaluation(tmp_path):
    env = EnvSpec.parse("MetaBandit-v0")
    finals = {0: [0.0, 0.2, 0.6, 0.8], 1: [0.0, 0.4, 1.0, 0.0]}  # at env steps 0, 50, 90, 100
    for seed, values in finals.items():
        path = Run("dream", env, seed).curve_path(tmp_path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(CURVE_COLUMNS)
            writer.writerows([[step, 1.0, value, 0.0, 5.0] for step, value in zip((0, 50, 90, 100), values)])
    runs = plan_runs(["dream"], [env], [0, 1])
    (row,) = experiments.summarize(runs, RunConfig(), tmp_path)
    assert row["final_return_mean"] == pytest.approx(0.4) and row["final_return_std"] == pytest.approx(0.4)
    assert row["last_tenth_mean"] == pytest.approx(np.mean([(0.6 + 0.8) / 2, (1.0 + 0.0) / 2]))
    table = experiments.write_summary([row], tmp_path)
    # no oracle given; PEARL-UB of the bandit at |A| = 8: 1/8 + 7/8 x 1/8
    assert "| MetaBandit-v0 | dream | test | 2 | 0.400 ± 0.400 | 0.600 | - | 0.234 | 100 |" in table


def _finished_run(out, run, returns, splits=("test",)):
    """A finished run's record and curves under ``out``: ``returns`` at env steps 0, 100, ..."""
    run.info_path(out).parent.mkdir(parents=True, exist_ok=True)
    record = {"algo": run.algo, "env": run.env.env_id, "env_kwargs": run.env.env_kwargs, "seed": run.seed}
    run.info_path(out).write_text(json.dumps(record))
    for split in splits:
        with open(run.curve_path(out, split), "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(CURVE_COLUMNS)
            writer.writerows([[100 * k, k, value, 0.0, 5.0] for k, value in enumerate(returns)])


def test_also_reports_the_runs_of_other_folders_beside_those_under_out(tmp_path, capsys):
    env = EnvSpec.parse("MetaBandit-v0")
    out, long, old = tmp_path / "baselines", tmp_path / "long", tmp_path / "old"
    _finished_run(out, Run("rl2dqn", env, 0), [0.0, 0.2])
    _finished_run(long, Run("dream", env, 0), [0.0, 0.5, 0.7, 0.9])  # a longer run
    _finished_run(long, Run("dream", env, 1), [0.0, 0.5, 0.7, 0.7])
    _finished_run(old, Run("dream", env, 0), [0.0, -1.0])  # another DREAM seed 0: not taken
    _finished_run(old, Run("varibad", env, 0), [0.0, 0.1])
    argv = ["--envs", "MetaBandit-v0", "--algos", "dream", "--seeds", "0", "1", "--summary-only", "--no-oracle"]
    argv += ["--no-plot", "--out", str(out)]

    experiments.main([*argv, "--also", str(long), f"{old}:varibad"])
    rows = {row["algo"]: row for row in csv.DictReader(open(out / "summary.csv"))}
    assert set(rows) == {"dream", "rl2dqn", "varibad"}
    assert rows["dream"]["seeds"] == "2" and float(rows["dream"]["final_return_mean"]) == pytest.approx(0.8)
    assert rows["dream"]["env_steps"] == "300" and rows["rl2dqn"]["env_steps"] == "100"
    assert float(rows["varibad"]["final_return_mean"]) == pytest.approx(0.1)
    assert not (out / env.tag / "dream_seed0.csv").exists()  # read, not copied
    folders = experiments.report_folders([], out, [(long, ()), (old, ("varibad",))])
    assert folders[Run("dream", env, 1)] == long and folders[Run("rl2dqn", env, 0)] == out
    # in the registry's order, whichever folder a run came from
    assert [(r.algo, r.seed) for r in folders] == [("dream", 0), ("dream", 1), ("rl2dqn", 0), ("varibad", 0)]

    # DREAM seed 0 is finished in two of the folders: which one is meant must be said.
    with pytest.raises(SystemExit, match="dream seed 0 on MetaBandit-v0 is finished under both"):
        experiments.main([*argv, "--also", str(long), str(old)])
    for bad, match in ((f"{old}:", "DIR or DIR:ALGO"), (f"{old}:dreamy", "unknown algorithm 'dreamy'"),
                       (str(tmp_path / "none"), "no such folder")):  # fmt: skip
        with pytest.raises(SystemExit, match=match):
            experiments.main([*argv, "--also", bad])

    pytest.importorskip("matplotlib")
    plt = pytest.importorskip("matplotlib.pyplot")
    figures = []
    close = plt.close
    try:
        plt.close = lambda fig=None: figures.append(fig)
        experiments.plot_curves(list(folders), RunConfig(), out, folders=folders)
    finally:
        plt.close = close
    lines = {line.get_label(): line for line in figures[0].axes[0].get_lines()}
    np.testing.assert_allclose(lines["dream (2 seeds)"].get_ydata(), [0.0, 0.5, 0.7, 0.8])
    np.testing.assert_allclose(lines["varibad (1 seed)"].get_ydata(), [0.0, 0.1])


def test_finished_runs_are_found_from_their_records_whatever_split_they_evaluated(tmp_path):
    train_only = Run("rl2dqn", EnvSpec.parse("MetaBus-v0:variant=map"), 3)
    unfinished = Run("dream", EnvSpec.parse("MetaBus-v0"), 0)  # a record without any curve
    for run in (train_only, unfinished):
        run.info_path(tmp_path).parent.mkdir(parents=True, exist_ok=True)
        record = {"algo": run.algo, "env": run.env.env_id, "env_kwargs": run.env.env_kwargs, "seed": run.seed}
        run.info_path(tmp_path).write_text(json.dumps(record))
    train_only.curve_path(tmp_path, "train").write_text("env_steps,wall_clock_s,mean,ci,exploration_length\n")
    (tmp_path / "MetaBus-v0" / "oracle_test.json").write_text(json.dumps({"mean": 0.8}))
    assert experiments.finished_runs(tmp_path) == [train_only]


def _scripted_evaluations(monkeypatch, means):
    """Make every meta-test of a model return ``means[(split, env_steps of the model)]`` (a real
    evaluation is run and its returns replaced), so that which evaluation is best is known in
    advance. The end-of-run diagnosis's privileged agents are played as they are."""
    import sb3_dream.evaluation as evaluation

    real = evaluation.evaluate_meta

    def scripted(agent, env, n_trials=100, split="test", **kwargs):
        result = real(agent, env, n_trials=n_trials, split=split, **kwargs)
        if hasattr(agent, "num_timesteps"):  # a model, not a diagnosis's agent
            result.returns = np.full_like(result.returns, means[(split, agent.num_timesteps)])
        return result

    monkeypatch.setattr(evaluation, "evaluate_meta", scripted)


def test_select_on_keeps_the_best_model_across_an_interruption(tmp_path, monkeypatch):
    out = tmp_path / "results"
    config = RunConfig(
        steps=400, eval_freq=100, eval_trials=2, eval_splits=("test", "train"), checkpoint_freq=200,
        select_on="train", dream_kwargs=tuple(sorted(parse_kwargs(TINY_DREAM, "dream").items())),
    )  # fmt: skip
    assert "select_on" not in config.settings("dream")
    run = Run("dream", EnvSpec.parse("MetaBus-v0:variant=map"), 0)
    train = {0: -1.0, 100: 0.5, 200: 0.2, 300: 0.3, 400: 0.1}
    means = {("train", k): v for k, v in train.items()}
    means.update({("test", k): v / 2 for k, v in train.items()})  # the held-out return of each model
    _scripted_evaluations(monkeypatch, means)
    from sb3_dream.evaluation import MetaEvalCallback

    evaluate = MetaEvalCallback._evaluate

    def interrupted(self):
        if self.num_timesteps >= 300:
            raise KeyboardInterrupt  # killed after the checkpoint at 200
        evaluate(self)

    monkeypatch.setattr(MetaEvalCallback, "_evaluate", interrupted)
    with pytest.raises(KeyboardInterrupt):
        experiments.run_one(run, config, out)
    best_file = run.best_folder(out) / "best_model.zip"
    assert experiments.algorithm_class("dream").load(best_file).num_timesteps == 100
    checkpoint = json.loads(run.checkpoint_path(out).read_text())
    assert checkpoint["best"] == {"model": "dream_seed0.200.best.zip", "split": "train", "env_steps": 100, "mean": 0.5}

    best_file.unlink()  # lost with the interruption: the checkpoint's copy brings it back
    monkeypatch.setattr(MetaEvalCallback, "_evaluate", evaluate)
    experiments.run_one(run, config, out)
    info = json.loads(run.info_path(out).read_text())
    assert info["best"]["selected_on"] == "train"
    # None of the evaluations after the resume beats the one at 100 steps, made before it.
    assert info["best"]["env_steps"] == 100 and info["best"]["mean_on_selection_split"] == pytest.approx(0.5)
    assert info["best"]["test"]["mean"] == pytest.approx(0.25)  # the 100-step model, meta-tested again
    assert experiments.algorithm_class("dream").load(best_file).num_timesteps == 100
    assert info["final"]["train"]["mean"] == pytest.approx(0.1)


def test_select_on_keeps_the_latest_of_equal_best_evaluations(tmp_path, monkeypatch):
    """The training split saturates (as MetaCook's does at the oracle): the latest model at the best
    return is kept by default, the first with ``select_ties="first"``."""
    train = {0: -1.0, 100: 0.5, 200: 0.2, 300: 0.5, 400: 0.1}
    means = {("train", k): v for k, v in train.items()}
    means.update({("test", k): k / 1000 for k in train})  # the held-out return of each model
    _scripted_evaluations(monkeypatch, means)
    run = Run("dream", EnvSpec.parse("MetaBus-v0:variant=map"), 0)
    for ties, expected in (("last", 300), ("first", 100)):
        config = RunConfig(
            steps=400, eval_freq=100, eval_trials=2, eval_splits=("test", "train"), select_on="train",
            select_ties=ties, dream_kwargs=tuple(sorted(parse_kwargs(TINY_DREAM, "dream").items())),
        )  # fmt: skip
        experiments.run_one(run, config, tmp_path / ties)
        best = json.loads(run.info_path(tmp_path / ties).read_text())["best"]
        assert (best["ties"], best["env_steps"]) == (ties, expected)
        assert best["test"]["mean"] == pytest.approx(expected / 1000)  # that model, meta-tested again
    assert RunConfig().select_ties == "last" and experiments.build_parser().parse_args([]).select_ties == "last"
    with pytest.raises(ValueError, match="select_ties='middle' is not valid; accepted values: 'first', 'last'"):
        RunConfig(select_ties="middle")


def test_select_on_must_be_an_evaluated_split():
    with pytest.raises(ValueError, match="select_on='train' is not valid; accepted values: the evaluated splits"):
        RunConfig(select_on="train")
    assert RunConfig(select_on="train", eval_splits=("test", "train")).select_on == "train"


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads the process table from /proc")
def test_workers_stop_when_the_runner_is_killed(tmp_path):
    """``kill -9`` of the runner (no Ctrl-C reaching its process group) ends its worker processes
    too, instead of leaving them training on into --out."""
    import signal
    import subprocess
    import sys

    argv = [
        sys.executable, "-m", "sb3_dream.experiments", "--algos", "dream", "--envs", "MetaBandit-v0", "--seeds", "0",
        "1", "--steps", "10000000", "--eval-freq", "1000000", "--jobs", "2", "--out", str(tmp_path), "--no-plot",
        "--dream-kwargs", *TINY_DREAM,
    ]  # fmt: skip
    runner = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)

    def workers() -> list:
        found = []
        for entry in os.listdir("/proc"):
            try:
                with open(f"/proc/{entry}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except (OSError, IndexError):
                continue
            if int(fields[1]) == runner.pid and fields[0] != "Z" and b"spawn_main" in _cmdline(int(entry)):
                found.append(int(entry))  # a live child of the runner that is a pool worker
        return found

    started: list = []
    try:
        deadline = time.time() + 120
        while len(workers()) < 2 and time.time() < deadline:
            time.sleep(0.5)
        started = workers()
        assert len(started) >= 2, "the runner started no worker processes"
        runner.send_signal(signal.SIGKILL)
        runner.wait()
        deadline = time.time() + 30
        alive = started
        while alive and time.time() < deadline:
            time.sleep(0.5)
            alive = [pid for pid in started if os.path.exists(f"/proc/{pid}") and _state(pid) != "Z"]
        assert not alive, f"workers {alive} outlived the runner"
    finally:
        if runner.poll() is None:
            runner.kill()
        for pid in set(started + workers()):
            if os.path.exists(f"/proc/{pid}") and b"spawn_main" in _cmdline(pid):
                os.kill(pid, signal.SIGKILL)


def _cmdline(pid: int) -> bytes:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read()
    except OSError:
        return b""


def _state(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "Z"


def test_rewarded_exploration_variants_are_specs_of_their_algorithm():
    from sb3_dream.experiments import ALGORITHMS, register_rewarded_exploration_variant, rewarded_exploration_variant

    e_rl2 = ALGORITHMS["e_rl2dqn"]  # E-RL²: the paper's dashed RL² line
    rl2 = ALGORITHMS["rl2dqn"]
    assert e_rl2.env_kwargs == {"reward_free_exploration": False} and e_rl2.rewarded_exploration
    assert (e_rl2.load_class, e_rl2.presets, e_rl2.overrides, e_rl2.variant_of) == (
        rl2.load_class, rl2.presets, rl2.overrides, "rl2dqn"
    )  # fmt: skip
    assert not rl2.rewarded_exploration and not rl2.env_kwargs
    variant = rewarded_exploration_variant(ALGORITHMS["dream"])  # any algorithm has one
    assert variant.name == "e_dream" and variant.fixed_kwargs == {"bottleneck": True} and "e_dream" not in ALGORITHMS
    with pytest.raises(ValueError, match="already explores with rewards"):
        rewarded_exploration_variant(e_rl2)
    with pytest.raises(ValueError, match="already registered"):
        register_rewarded_exploration_variant("rl2dqn")
    with pytest.raises(ValueError, match="algo='nope' is not valid"):
        register_rewarded_exploration_variant("nope")
    # A run's envs get the arguments its name fixes, the env entry (its folder, its tag) does not.
    run = Run("e_rl2dqn", EnvSpec.parse("MetaBus-v0:variant=map:n_exec_episodes=2"), 0)
    assert run.env_kwargs == {"variant": "map", "n_exec_episodes": 2, "reward_free_exploration": False}
    assert run.eval_kwargs == {"variant": "map", "reward_free_exploration": False}
    assert run.env.tag == "MetaBus-v0_n_exec_episodes-2_variant-map"
    assert Run("rl2dqn", run.env, 0).env_kwargs == run.env.env_kwargs
    assert plan_runs(["e_rl2dqn"], [EnvSpec.parse("MetaBus-v0:reward_free_exploration=False")], [0])
    with pytest.raises(ValueError, match="e_rl2dqn runs with reward_free_exploration=False"):
        plan_runs(["e_rl2dqn"], [EnvSpec.parse("MetaBus-v0:reward_free_exploration=True")], [0])
    # The overrides field is shared: --rl2dqn-kwargs sets both.
    config = RunConfig(rl2dqn_kwargs=(("buffer_size", 50),))
    assert config.overrides("e_rl2dqn") == config.overrides("rl2dqn") == {"buffer_size": 50}


def test_e_rl2dqn_trains_and_evaluates_with_rewarded_exploration(tmp_path, monkeypatch):
    from dream_envs.bandit import MetaBanditEnv

    seen = []  # (algo, split, reward_free_exploration, exploration instruction) of every exploration step
    step = MetaBanditEnv.step

    def recording_step(self, action):
        if self.phase == 0:
            seen.append(
                (current[0], self.split, self.reward_free_exploration, int(self._observation()["instruction"][0]))
            )
        return step(self, action)

    monkeypatch.setattr(MetaBanditEnv, "step", recording_step)
    config = RunConfig(
        steps=40, eval_freq=40, eval_trials=4, rl2dqn_kwargs=(("buffer_size", 50), ("learning_starts", 10))
    )
    out = tmp_path / "results"
    current = [None]
    for algo in ("e_rl2dqn", "rl2dqn"):
        current[0] = algo
        run = Run(algo, EnvSpec.parse("MetaBandit-v0"), 0)
        record = experiments.run_one(run, config, out)
        assert record["status"] == "done" and 0 <= record["final"]["test"]["mean"] <= 1  # execution returns
    rewarded = {(split, free, instruction) for algo, split, free, instruction in seen if algo == "e_rl2dqn"}
    # Training (train split) and the held-out evaluations (test split) alike: an instruction and
    # rewards in the exploration episode; the plain RL² run explores reward-free.
    assert rewarded == {("train", False, 1), ("test", False, 1)}
    plain = {(split, free, instruction) for algo, split, free, instruction in seen if algo == "rl2dqn"}
    assert plain == {("train", True, 0), ("test", True, 0)}
    folder = out / "MetaBandit-v0"  # both in one env folder, one panel of the figure
    info = json.loads((folder / "e_rl2dqn_seed0.json").read_text())
    assert info["algo_env_kwargs"] == {"reward_free_exploration": False} and info["env_kwargs"] == {}
    assert "algo_env_kwargs" not in json.loads((folder / "rl2dqn_seed0.json").read_text())
    assert [r.algo for r in experiments.finished_runs(out)] == ["rl2dqn", "e_rl2dqn"]
    rows = experiments.summarize(experiments.finished_runs(out), config, out)
    pearl = {row["algo"]: row["pearl_ub"] for row in rows}
    assert pearl == {"rl2dqn": pytest.approx(15 / 64), "e_rl2dqn": pytest.approx(22 / 64)}  # |A| = 8, H = 1


def test_figures_draw_pearl_ub_per_split_and_dash_rewarded_exploration(tmp_path, monkeypatch):
    plt = pytest.importorskip("matplotlib.pyplot")
    from dream_envs import pearl_ub

    out = tmp_path / "results"
    config = RunConfig(eval_splits=("test", "train"))
    env = EnvSpec.parse("MetaBus-v0")  # the distracting bus: its train and test splits differ
    runs = [Run(algo, env, 0) for algo in ("dream", "rl2dqn", "e_rl2dqn")]
    for run in runs:
        for split in config.eval_splits:
            path = run.curve_path(out, split)
            path.parent.mkdir(parents=True, exist_ok=True)
            with open(path, "w", newline="") as f:
                writer = csv.writer(f)
                writer.writerow(CURVE_COLUMNS)
                for k, steps in enumerate((0, 100)):
                    writer.writerow({"env_steps": steps, "wall_clock_s": k, "mean": 0.1 * k, "ci": 0.0,
                                     "exploration_length": 1}.get(c, 0) for c in CURVE_COLUMNS)  # fmt: skip
    figures = []
    monkeypatch.setattr(plt, "close", lambda fig=None: figures.append(fig))
    experiments.plot_curves(runs, config, out, oracles={(env.tag, "test"): 0.8})
    (fig,) = figures
    test_ax, train_ax = fig.axes[:2]
    import gymnasium as gym

    bus = gym.make("MetaBus-v0")
    for ax, split in ((test_ax, "test"), (train_ax, "train")):
        lines = {line.get_label(): line for line in ax.get_lines()}
        assert lines["PEARL-UB"].get_ydata()[0] == pytest.approx(pearl_ub(bus, split))
        assert lines["PEARL-UB"].get_linestyle() == ":"
        # The distracting bus's rewarded value is the same: no second line.
        assert "PEARL-UB (rewarded exploration)" not in lines
        e_line, plain = lines["e_rl2dqn (1 seed)"], lines["rl2dqn (1 seed)"]
        assert e_line.get_linestyle() == "--" and plain.get_linestyle() == "-"
        assert e_line.get_color() == plain.get_color() != lines["dream (1 seed)"].get_color()
    assert pearl_ub(bus, "train") != pytest.approx(pearl_ub(bus, "test"), abs=1e-3)
    assert "optimal" in {line.get_label() for line in test_ax.get_lines()}

    # MetaCook: the rewarded value differs, so a panel with an e_ run shows both.
    cook = EnvSpec.parse("MetaCook-v0")
    cook_runs = [Run("e_rl2dqn", cook, 0)]
    path = cook_runs[0].curve_path(out, "test")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text((out / env.tag / "rl2dqn_seed0.csv").read_text())
    experiments.plot_curves(cook_runs, RunConfig(), out)
    labels = {line.get_label(): line.get_ydata()[0] for line in figures[-1].axes[0].get_lines()}
    made = gym.make("MetaCook-v0")
    assert labels["PEARL-UB"] == pytest.approx(pearl_ub(made, "test", rewarded_exploration=False))
    assert labels["PEARL-UB (rewarded exploration)"] == pytest.approx(pearl_ub(made, "test", rewarded_exploration=True))
    # Without PEARL-UB support (CartPole is no trial env) there is no line, and nothing fails.
    assert experiments.pearl_ub_return(EnvSpec.parse("CartPole-v1"), "test") is None
