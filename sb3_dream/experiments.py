"""Experiment runner: algorithms x envs x seeds -> learning curves, a summary table and figures.

Each run trains one algorithm on one env with one seed for ``--steps`` env steps and evaluates it
on the held-out split every ``--eval-freq`` steps (``--eval-trials`` meta-test trials, greedy; with
``--eval-exhaustive`` every (problem, instruction) pair of the split, weighted) with
:class:`sb3_dream.evaluation.MetaEvalCallback`, which writes the run's learning curve as a CSV
(``env_steps, wall_clock_s, mean, ci, exploration_length``). Runs go to parallel processes, up to
``--jobs`` (default: the machine's cores) at once. DREAM's ``parallel_updates`` (the second update
thread) is chosen per run unless ``--dream-kwargs`` set it: its ``"auto"`` for a run alone, off
when several runs share the cores (it changes the speed, not the results).

**Resumable.** A run writes ``<name>.csv.partial`` and renames it to ``<name>.csv`` only when it
is complete, so a finished run is skipped when the command is run again (whatever the other
options: use ``--force`` or a new ``--out`` to redo it). An interrupted run starts over, unless
``--checkpoint-freq N`` is given: then, right after an evaluation and at least every N env steps,
the run saves its model (with optimizer states and counters) and replay buffers under
``<env>/checkpoints/``, and the same command later goes on from the last checkpoint, keeping the
learning curve and wall-clock so far (the envs start fresh trials; nothing else is lost). This is
how budgets longer than one sitting (the paper's millions of steps) are run on a laptop. Its
worker processes end with the runner however it is stopped (Ctrl-C, ``kill``, ``kill -9``), so
none trains on unseen into ``--out``.
A complete run keeps its last checkpoint (at its final step), so the same command with a larger
``--steps`` later *extends* it from there instead of skipping it; ``--force`` deletes it and
starts over. Delete ``<env>/checkpoints/`` to free the space once no run needs extending.

**Going on with other settings.** ``--init-from DIR`` starts each run that has no checkpoint of its
own from the kept final checkpoint of the same run (algorithm, env, seed) under ``DIR``, with this
command's preset and overrides applied to the loaded model (SB3's ``load(**kwargs)``; the networks,
``policy_kwargs`` included, must stay the same). Its learning curve and wall-clock carry over, so
the new run's curve starts where the parent's ended: e.g. a run made to 1M steps with one target
sync interval goes on to 1.2M with another, into its own ``--out``. The run's JSON records the
parent (``init_from``: its ``--out`` and env steps), also once the run is resumed or extended from
its own checkpoints.

**Outputs** under ``--out``::

    <env>/<algo>_seed<k>.csv          learning curve on the held-out split (--eval-splits test)
    <env>/<algo>_seed<k>_train.csv    ... on the training split, with --eval-splits test train
                                      (likewise _<split>.csv for any split the env offers, e.g.
                                      MetaCook's test_problems and test_instructions)
    <env>/<algo>_seed<k>.json         the run's settings and final numbers (DREAM: also the final
                                      model's :func:`sb3_dream.dream.diagnose` and
                                      :func:`sb3_dream.dream.exploration_gains`)
    <env>/<algo>_seed<k>.zip          the trained model, with --save-models
    <env>/oracle_<split>.json         the env's scripted optimal agent on that split (oracle_<split>_exhaustive.json
                                      with --eval-exhaustive)
    <env>/checkpoints/                each run's last checkpoint, with --checkpoint-freq
    <env>/snapshots/                  the model every N env steps, with --snapshot-freq N (SB3's
                                      CheckpointCallback: <algo>_seed<k>_<steps>_steps.zip, no
                                      replay buffers), to meta-test how a policy changes
    <env>/best/<algo>_seed<k>/best_model.zip
                                      with --select-on SPLIT: the model at the evaluation on SPLIT
                                      with the highest return so far, the latest of equal ones
                                      (--select-ties; MetaEvalCallback's best_model_save_path); the
                                      run's JSON records its steps and its return on the held-out
                                      split ("best")
    summary.csv, summary.md           final return mean +- std over seeds, the mean over each run's
                                      last tenth of env steps, env steps, wall-clock
    curves.png                        return vs env steps, mean +- std over seeds, a panel per env
                                      (and split), like the paper's Figures 5 and 6

The summary and the figure cover the runs asked for and every other finished run under ``--out``
(runs made by other commands into it: other seeds, envs or sittings); ``--summary-only`` makes
them without training anything.

**Algorithms:** ``dream`` (:class:`~sb3_dream.DREAM`), ``dream_no_bottleneck``
(``DREAM(bottleneck=False)``, the paper's ablation) and ``rl2dqn``
(:class:`~sb3_dream.rl2dqn.RL2DQN`, the paper's RL² baseline). ``--preset paper`` keeps every
default (the paper's); ``--preset fast`` applies :data:`sb3_dream.presets.PRESETS` ``["fast"]``
to DREAM and :data:`RL2DQN_PRESETS` ``["fast"]`` (the matching schedule changes) to RL2DQN.

**Envs** are registered IDs with optional constructor arguments after colons, e.g.
``MetaBus-v0:variant=map`` or ``MetaCook-v0:n_exec_episodes=2``. ``split`` there sets the
training split only; evaluation uses ``--eval-splits``.

Figure 5 (distracting bus and map) on a laptop-sized budget::

    python -m sb3_dream.experiments --envs MetaBus-v0 MetaBus-v0:variant=map \\
        --algos dream dream_no_bottleneck rl2dqn --seeds 0 1 2 --steps 200000 --preset fast \\
        --out results/figure5

matplotlib (a dev extra) is needed for the figure only; without it the figure is skipped.
"""

from __future__ import annotations

import argparse
import ast
import concurrent.futures
import csv
import dataclasses
import importlib
import inspect
import json
import multiprocessing
import os
import pathlib
import shutil
import threading
import time
import traceback
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from dream_envs import all_splits, env_splits
from dream_envs.checks import check_choice
from sb3_dream.evaluation import BEST_TIES, CURVE_COLUMNS, format_mean_ci
from sb3_dream.presets import RL2DQN_PRESETS

DREAM_ALGOS = ("dream", "dream_no_bottleneck")  # the runs that train sb3_dream.DREAM
ALGOS = (*DREAM_ALGOS, "rl2dqn")
PRESET_NAMES = ("paper", "fast")


def _parse_value(text: str) -> Any:
    """A Python literal if ``text`` is one (``3``, ``0.5``, ``True``, ``'map'``), else the string."""
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def parse_kwargs(items: Sequence[str], name: str) -> Dict[str, Any]:
    """``["a=1", "b=map"]`` -> ``{"a": 1, "b": "map"}``; a ValueError naming ``name`` otherwise."""
    kwargs: Dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.isidentifier():
            raise ValueError(f"{name} entries must look like key=value, got {item!r}")
        kwargs[key] = _parse_value(value)
    return kwargs


@dataclasses.dataclass(frozen=True)
class EnvSpec:
    """A registered env ID and constructor arguments: ``"MetaBus-v0:variant=map:n_exec_episodes=2"``.

    Colon-separated parts with ``=`` are arguments; the others form the ID, so the
    ``"dream_envs:MetaBus-v0"`` form also works.
    """

    env_id: str
    kwargs: Tuple[Tuple[str, Any], ...] = ()

    @classmethod
    def parse(cls, text: str) -> "EnvSpec":
        parts = text.split(":")
        id_parts = [p for p in parts if "=" not in p]
        if not id_parts or not all(id_parts):
            raise ValueError(
                f"envs entry {text!r} is not valid: expected ENV_ID[:key=value...], e.g. MetaBus-v0:variant=map"
            )
        kwargs = parse_kwargs([p for p in parts if "=" in p], f"envs entry {text!r}")
        return cls(":".join(id_parts), tuple(sorted(kwargs.items())))

    @property
    def env_kwargs(self) -> Dict[str, Any]:
        """Arguments of the training env (all of them)."""
        return dict(self.kwargs)

    @property
    def eval_kwargs(self) -> Dict[str, Any]:
        """Arguments of the evaluation env (``split`` and ``n_exec_episodes`` are set separately)."""
        return {k: v for k, v in self.kwargs if k not in ("split", "n_exec_episodes")}

    @property
    def n_exec_episodes(self) -> int:
        return int(self.env_kwargs.get("n_exec_episodes", 1))

    @property
    def tag(self) -> str:
        """A folder name: ``MetaBus-v0_variant-map``."""
        name = self.env_id.split(":")[-1]
        return "_".join([name, *(f"{k}-{v}" for k, v in self.kwargs)]).replace("/", "-").replace(" ", "")

    @property
    def label(self) -> str:
        """A title: ``MetaBus-v0 (variant=map)``."""
        name = self.env_id.split(":")[-1]
        return name + (" (" + ", ".join(f"{k}={v}" for k, v in self.kwargs) + ")" if self.kwargs else "")


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Settings shared by every run of an experiment."""

    steps: int = 100_000
    n_envs: int = 1
    preset: str = "paper"
    eval_freq: int = 10_000
    eval_trials: int = 100
    eval_splits: Tuple[str, ...] = ("test",)
    eval_exhaustive: bool = False
    threads: int = 1
    device: str = "auto"
    save_models: bool = False
    checkpoint_freq: int = 0
    snapshot_freq: int = 0
    select_on: str = ""
    select_ties: str = "last"
    dream_kwargs: Tuple[Tuple[str, Any], ...] = ()
    rl2dqn_kwargs: Tuple[Tuple[str, Any], ...] = ()
    init_from: str = ""

    def __post_init__(self) -> None:
        for name in ("steps", "n_envs", "eval_freq", "eval_trials", "threads"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if self.preset not in PRESET_NAMES:
            raise ValueError(
                f"preset={self.preset!r} is not valid; accepted values: {', '.join(map(repr, PRESET_NAMES))}"
            )
        known = all_splits()
        if not self.eval_splits or any(s not in known for s in self.eval_splits):
            raise ValueError(
                f"eval_splits={self.eval_splits!r} is not valid; accepted values: {', '.join(map(repr, known))}"
            )
        for name in ("checkpoint_freq", "snapshot_freq"):
            freq = getattr(self, name)
            if isinstance(freq, bool) or not isinstance(freq, int) or freq < 0:
                raise ValueError(f"{name} must be an integer >= 0 (0: off), got {freq!r}")
        if self.select_on and self.select_on not in self.eval_splits:
            raise ValueError(
                f"select_on={self.select_on!r} is not valid; accepted values: the evaluated splits "
                f"{', '.join(map(repr, self.eval_splits))} (add it to eval_splits), or '' (off)"
            )
        check_choice("select_ties", self.select_ties, BEST_TIES)
        if "bottleneck" in dict(self.dream_kwargs):
            raise ValueError("dream_kwargs must not set bottleneck: choose the algorithm dream or dream_no_bottleneck")

    def settings(self, algo: str) -> Dict[str, Any]:
        """What a finished run of ``algo`` records, to warn when a later command asks for other settings."""
        data = dataclasses.asdict(self)
        unrecorded = ("threads", "device", "save_models", "checkpoint_freq", "snapshot_freq")
        unrecorded += ("select_on", "select_ties")  # which model is kept, not how it trains
        for key in (*unrecorded, "dream_kwargs", "rl2dqn_kwargs"):
            data.pop(key)
        data["algo_kwargs"] = dict(self.rl2dqn_kwargs if algo == "rl2dqn" else self.dream_kwargs)
        data["eval_splits"] = list(self.eval_splits)
        for key in ("init_from", "eval_exhaustive"):
            if not data[key]:
                data.pop(key)  # records made before the option compare equal
        return data


@dataclasses.dataclass(frozen=True)
class Run:
    """One (algorithm, env, seed) run and where its files go."""

    algo: str
    env: EnvSpec
    seed: int

    @property
    def name(self) -> str:
        return f"{self.algo}_seed{self.seed}"

    def folder(self, out: pathlib.Path) -> pathlib.Path:
        return out / self.env.tag

    def curve_path(self, out: pathlib.Path, split: str = "test") -> pathlib.Path:
        suffix = "" if split == "test" else f"_{split}"
        return self.folder(out) / f"{self.name}{suffix}.csv"

    def info_path(self, out: pathlib.Path) -> pathlib.Path:
        return self.folder(out) / f"{self.name}.json"

    def model_path(self, out: pathlib.Path) -> pathlib.Path:
        return self.folder(out) / f"{self.name}.zip"

    def best_folder(self, out: pathlib.Path) -> pathlib.Path:
        """Where ``--select-on`` keeps the run's best model (``best_model.zip``)."""
        return self.folder(out) / "best" / self.name

    def checkpoint_path(self, out: pathlib.Path) -> pathlib.Path:
        """The JSON that names a run's last checkpoint (written last, so it is never half made)."""
        return self.folder(out) / "checkpoints" / f"{self.name}.json"

    def is_complete(self, out: pathlib.Path, config: RunConfig) -> bool:
        return all(self.curve_path(out, split).exists() for split in config.eval_splits)


def algorithm_class(algo: str) -> type:
    """The class that trains ``algo``: DREAM for both DREAM variants, RL2DQN for rl2dqn."""
    if algo in DREAM_ALGOS:
        from sb3_dream.dream import DREAM

        return DREAM
    if algo == "rl2dqn":
        from sb3_dream.rl2dqn import RL2DQN

        return RL2DQN
    raise ValueError(f"algo={algo!r} is not valid; accepted values: {', '.join(map(repr, ALGOS))}")


def algorithm_kwargs(algo: str, config: RunConfig) -> Dict[str, Any]:
    """The constructor arguments of ``algo`` that ``config`` sets: its preset, then its overrides."""
    if algo == "rl2dqn":
        return {**RL2DQN_PRESETS[config.preset], **dict(config.rl2dqn_kwargs)}
    from sb3_dream.presets import PRESETS

    return {**PRESETS[config.preset], **dict(config.dream_kwargs), "bottleneck": algo == "dream"}


def make_model(algo: str, env: Any, config: RunConfig, seed: int) -> Any:
    """The model of ``algo`` on ``env`` with the preset and the per-algorithm overrides of ``config``."""
    return algorithm_class(algo)(env, seed=seed, device=config.device, **algorithm_kwargs(algo, config))


def load_with_overrides(algo: str, path: pathlib.Path, env: Any, config: RunConfig) -> Any:
    """``algo``'s model saved at ``path``, with the hyperparameters that ``config`` sets to other
    values than the saved ones (set before the model is set up, as SB3's ``load(**kwargs)`` does).

    Only plain saved values (numbers, flags, strings) can change; the networks cannot.
    """
    from stable_baselines3.common.save_util import load_from_zip_file

    saved, _, _ = load_from_zip_file(path, load_data=True, device="cpu")
    wanted = algorithm_kwargs(algo, config)
    changed: Dict[str, Any] = {}
    for key, value in wanted.items():
        if key == "policy_kwargs":
            # The saved ones also hold what the algorithm derived from the env: compare the given keys.
            stored = saved.get(key) or {}
            given = {k: stored.get(k) for k in value}
            if json.dumps(value, default=str) != json.dumps(given, default=str):
                raise ValueError(f"policy_kwargs={value!r} differs from the checkpoint's {given!r}")
        elif key not in saved:
            # An option newer than the checkpoint: the checkpoint was made with its default.
            parameter = inspect.signature(algorithm_class(algo)).parameters.get(key)
            if parameter is None or parameter.default is inspect.Parameter.empty:
                raise ValueError(f"{key} cannot be changed when going on from a checkpoint")
            if parameter.default != value:
                changed[key] = value
        elif not isinstance(saved[key], (bool, int, float, str, type(None))):
            raise ValueError(f"{key} cannot be changed when going on from a checkpoint")
        elif saved[key] != value:
            changed[key] = value
    return algorithm_class(algo).load(path, env=env, device=config.device, **changed)


def init_checkpoint(run: Run, config: RunConfig) -> Tuple[pathlib.Path, Dict[str, Any]]:
    """The folder and record of the checkpoint that ``--init-from`` starts ``run`` from.

    It must be the same run's kept checkpoint, made with the same evaluation settings, so that the
    learning curve goes on comparably; anything else is an error that names what differs.
    """
    parent = Checkpointer(run, config, pathlib.Path(config.init_from))
    record = parent._record()
    if record is None or not (parent.folder / record.get("model", "")).is_file():
        raise FileNotFoundError(
            f"init_from={config.init_from!r}: no checkpoint of {run.name} at {parent.path} (the parent run "
            "needs --checkpoint-freq; a complete run keeps its final checkpoint)"
        )
    wanted = json.loads(json.dumps(config.settings(run.algo), default=str))
    recorded = dict(record.get("settings", {}))
    same = ("n_envs", "eval_freq", "eval_trials", "eval_splits", "eval_exhaustive")
    changed = sorted(key for key in same if recorded.get(key) != wanted.get(key))
    if changed:
        raise ValueError(f"init_from={config.init_from!r}: {run.name} was made with other {', '.join(changed)}")
    if int(record["env_steps"]) >= config.steps:
        raise ValueError(
            f"init_from={config.init_from!r}: {run.name} is already at {record['env_steps']} env steps; "
            f"steps must be larger, got {config.steps}"
        )
    return parent.folder, record


def _meta_test_kwargs(run: Run, config: RunConfig) -> Dict[str, Any]:
    """The trials of every meta-test of a run (curves, best model): seed 0, so that every run and
    evaluation meets the same problems, a paired comparison."""
    return {
        "n_trials": config.eval_trials,
        "exhaustive": config.eval_exhaustive,
        "n_exec_episodes": run.env.n_exec_episodes,
        "seed": 0,
        "env_kwargs": run.env.eval_kwargs,
    }


def _make_progress_callback(tag: str, **kwargs: Any) -> Any:
    """A :class:`MetaEvalCallback` that prints one tagged line per evaluation (runs share a terminal)."""
    from sb3_dream.evaluation import MetaEvalCallback

    class TaggedMetaEvalCallback(MetaEvalCallback):
        def _evaluate(self) -> None:
            super()._evaluate()
            row = self.results[-1]
            print(
                f"[{tag}] {row['env_steps']:>8} steps {row['wall_clock_s']:7.0f}s  {self.split} return "
                f"{format_mean_ci(row['mean'], row['ci'])}  exploration length {row['exploration_length']:.1f}",
                flush=True,
            )

    return TaggedMetaEvalCallback(**kwargs)


def _partial(path: pathlib.Path) -> pathlib.Path:
    return path.with_name(path.name + ".partial")


class Checkpointer:
    """Saves a run's model, replay buffers and learning curve right after its evaluations, at
    least ``freq`` env steps apart (a callback placed after the evaluation callbacks).

    A checkpoint is ``<name>.<steps>.zip`` (model), ``<name>.<steps>.pkl`` (replay buffers) and
    the JSON :meth:`Run.checkpoint_path`, replaced atomically last, that names them; older files
    are removed only after it. An interruption at any moment leaves the previous checkpoint usable.
    """

    def __init__(self, run: Run, config: RunConfig, out: pathlib.Path) -> None:
        self.run, self.config, self.path = run, config, run.checkpoint_path(out)
        self.folder = self.path.parent
        # Where the run began with --init-from ({"out", "env_steps"}), kept in every checkpoint so
        # that a run resumed or extended from its own checkpoint still records its parent.
        self.init_from: Optional[Dict[str, Any]] = None

    def _record(self) -> Optional[Dict[str, Any]]:
        """The last checkpoint's JSON as written (whatever its settings), or None."""
        try:
            return json.loads(self.path.read_text())
        except (OSError, ValueError):
            return None

    def load(self) -> Optional[Dict[str, Any]]:
        """The last checkpoint's record, or None (none, or made with other settings)."""
        record = self._record()
        if record is None:
            return None
        # Any settings but the budget: an unfinished run may be given more steps.
        wanted = json.loads(json.dumps(self.config.settings(self.run.algo), default=str))
        recorded = dict(record.get("settings", {}))
        recorded.pop("steps", None), wanted.pop("steps", None)
        if recorded != wanted or not (self.folder / record["model"]).exists():
            print(f"warning: ignoring {self.path}: made with other settings or incomplete", flush=True)
            return None
        return record

    def save(
        self, model: Any, curves: Dict[str, List[Dict[str, float]]], train_seconds: float, best: Any = None
    ) -> None:
        """``best``: the ``--select-on`` evaluation callback, whose best model is kept with the
        checkpoint, so that a resumed run goes on selecting among all its evaluations."""
        self.folder.mkdir(parents=True, exist_ok=True)
        stem = f"{self.run.name}.{model.num_timesteps}"
        model.save(self.folder / f"{stem}.partial.zip")
        os.replace(self.folder / f"{stem}.partial.zip", self.folder / f"{stem}.zip")
        model.save_replay_buffer(self.folder / f"{stem}.partial.pkl")
        os.replace(self.folder / f"{stem}.partial.pkl", self.folder / f"{stem}.pkl")
        record = {
            "env_steps": model.num_timesteps,
            "model": f"{stem}.zip",
            "replay_buffer": f"{stem}.pkl",
            "train_seconds": train_seconds,
            "curves": curves,
            "settings": self.config.settings(self.run.algo),
            "init_from": self.init_from,
        }
        best_file = None if best is None else pathlib.Path(best.best_model_save_path) / "best_model.zip"
        if best_file is not None and best_file.exists() and best.best_env_steps is not None:
            shutil.copyfile(best_file, self.folder / f"{stem}.best.partial.zip")
            os.replace(self.folder / f"{stem}.best.partial.zip", self.folder / f"{stem}.best.zip")
            record["best"] = {
                "model": f"{stem}.best.zip",
                "split": best.split,
                "env_steps": best.best_env_steps,
                "mean": best.best_mean_reward,
            }
        tmp = self.path.with_suffix(".json.partial")
        tmp.write_text(json.dumps(record, default=str))
        os.replace(tmp, self.path)
        self.remove(keep=stem)

    def saved_steps(self) -> Optional[int]:
        """The env steps of the last checkpoint on disk (whatever its settings), or None."""
        record = self._record()
        if record is None:
            return None
        try:
            return int(record["env_steps"])
        except (KeyError, TypeError, ValueError):
            return None

    def remove(self, keep: Optional[str] = None) -> None:
        """Delete this run's checkpoint files (all, or all but the ``keep`` stem's)."""
        for path in self.folder.glob(f"{self.run.name}.*"):
            if keep is None or not path.name.startswith(keep + ".") and path != self.path:
                path.unlink(missing_ok=True)
        if keep is None:
            self.path.unlink(missing_ok=True)


def _make_checkpoint_callback(
    checkpointer: Checkpointer, evaluations: Sequence[Any], seconds_before: float, best: Any = None
) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    class CheckpointAfterEvaluation(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self._last = None

        def _on_training_start(self) -> None:
            self._start = time.perf_counter()
            self._last = self.num_timesteps

        def _on_step(self) -> bool:
            evaluated = all(cb.results and cb.results[-1]["env_steps"] == self.num_timesteps for cb in evaluations)
            if evaluated and self.num_timesteps - self._last >= checkpointer.config.checkpoint_freq:
                seconds = seconds_before + time.perf_counter() - self._start
                checkpointer.save(self.model, {cb.split: cb.results for cb in evaluations}, seconds, best)
                self._last = self.num_timesteps
            return True

    return CheckpointAfterEvaluation()


def run_one(run: Run, config: RunConfig, out: pathlib.Path, concurrent_runs: int = 1) -> Dict[str, Any]:
    """Train and evaluate one run; its files appear under their final names only once complete.

    With ``config.checkpoint_freq`` it goes on from the run's last checkpoint, if there is one.
    ``concurrent_runs``: how many runs share the machine's cores with this one.
    """
    import torch as th
    from stable_baselines3.common.callbacks import CallbackList
    from stable_baselines3.common.env_util import make_vec_env

    th.set_num_threads(config.threads)
    folder = run.folder(out)
    folder.mkdir(parents=True, exist_ok=True)
    partial = {split: _partial(run.curve_path(out, split)) for split in config.eval_splits}
    checkpointer = Checkpointer(run, config, out)
    resume = checkpointer.load() if config.checkpoint_freq else None
    if resume is None:
        for path in partial.values():
            path.unlink(missing_ok=True)  # an interrupted run starts over

    tag = f"{run.algo} {run.env.label} seed {run.seed}"
    init_from, resume_folder = None, checkpointer.folder  # init_from: starting from the parent now
    if resume is None and config.init_from:
        resume_folder, resume = init_checkpoint(run, config)
        init_from = {"out": config.init_from, "env_steps": int(resume["env_steps"])}
    checkpointer.init_from = init_from if init_from is not None else (resume or {}).get("init_from")
    env = make_vec_env(run.env.env_id, n_envs=config.n_envs, seed=run.seed, env_kwargs=run.env.env_kwargs)
    if resume is None:
        model, seconds_before = make_model(run.algo, env, config, run.seed), 0.0
    else:
        if init_from is None:
            model = algorithm_class(run.algo).load(resume_folder / resume["model"], env=env, device=config.device)
        else:
            model = load_with_overrides(run.algo, resume_folder / resume["model"], env, config)
        model.load_replay_buffer(resume_folder / resume["replay_buffer"])
        # make_vec_env seeded the envs as at step 0: without a seed of its own, the resumed run
        # would draw the same problems and instructions again, in the same order.
        model.env.seed(run.seed + model.num_timesteps)
        seconds_before = float(resume["train_seconds"])
        what = "its checkpoint" if init_from is None else f"the checkpoint under {config.init_from}"
        print(f"[{tag}] going on from {what} at {model.num_timesteps} env steps", flush=True)
    if run.algo in DREAM_ALGOS and "parallel_updates" not in dict(config.dream_kwargs):
        # How DREAM's updates run, not what they compute (like the device), so chosen here, each
        # time: a second thread only helps when no other run needs the second core.
        model.parallel_updates = "auto" if concurrent_runs == 1 else False
    callbacks = [
        _make_progress_callback(
            tag if len(config.eval_splits) == 1 else f"{tag} {split}",
            eval_env=run.env.env_id,
            eval_freq=config.eval_freq,
            split=split,
            csv_path=str(partial[split]),
            best_model_save_path=str(run.best_folder(out)) if split == config.select_on else None,
            best_ties=config.select_ties,
            **_meta_test_kwargs(run, config),
        )
        for split in config.eval_splits
    ]
    best = next((cb for cb in callbacks if cb.best_model_save_path is not None), None)
    if best is not None and resume is None:
        shutil.rmtree(run.best_folder(out), ignore_errors=True)  # a fresh run selects afresh
    if resume is not None:
        for callback in callbacks:
            callback.resume(resume["curves"][callback.split])
        if best is not None:
            _resume_best(best, resume, resume_folder, tag)
    callback_list = list(callbacks)
    if config.checkpoint_freq:
        callback_list.append(_make_checkpoint_callback(checkpointer, callbacks, seconds_before, best))
    if config.snapshot_freq:
        from stable_baselines3.common.callbacks import CheckpointCallback

        # save_freq counts calls, one per vec-env step of n_envs env steps
        callback_list.append(
            CheckpointCallback(max(config.snapshot_freq // config.n_envs, 1), str(folder / "snapshots"), run.name)
        )
    start = time.perf_counter()
    model.learn(
        max(config.steps - model.num_timesteps, 0) if resume else config.steps,
        callback=CallbackList(callback_list),
        reset_num_timesteps=resume is None,
    )
    seconds = seconds_before + time.perf_counter() - start
    env.close()

    if config.checkpoint_freq and checkpointer.saved_steps() != model.num_timesteps:
        # Kept once the run is complete, so that a larger budget later extends it.
        checkpointer.save(model, {cb.split: cb.results for cb in callbacks}, seconds, best)
    if config.save_models:
        tmp = run.model_path(out).with_name(run.name + ".partial.zip")
        model.save(tmp)
        os.replace(tmp, run.model_path(out))
    finals = {split: cb.results[-1] for split, cb in zip(config.eval_splits, callbacks)}
    info = {
        "algo": run.algo,
        "env": run.env.env_id,
        "env_kwargs": run.env.env_kwargs,
        "seed": run.seed,
        "settings": config.settings(run.algo),
        "train_seconds": seconds,
        "resumed_from": None if resume is None or init_from is not None else resume["env_steps"],
        "init_from": checkpointer.init_from,
        "final": finals,
    }
    if best is not None and best.best_env_steps is not None:
        info["best"] = _meta_test_best(run, config, best, tag)
    if run.algo in DREAM_ALGOS:
        from sb3_dream.dream import diagnose

        # Which side limits the final model: meta-test vs the execution policy given z = f(T)
        # (and vs the decoder reading the env's optimal exploration).
        diagnosis = diagnose(
            model,
            run.env.env_id,
            n_trials=config.eval_trials,
            env_kwargs=run.env.eval_kwargs,
            exhaustive=config.eval_exhaustive,
        )
        info["diagnosis"] = diagnosis.as_dict()
        # What its explorer is paid for, step by step (Equation 5), on the same trials.
        gains = diagnosis.exploration_gains
        info["exploration_gains"] = {
            "reward_by_step": gains.by_step().tolist(),
            "information_gain": float(gains.information_gain().mean()),
            "reward_penalty": gains.reward_penalty,
        }
        print(
            f"[{tag}] diagnosis: {diagnosis.returns_text()}; "
            f"||g - f||^2 {diagnosis.decoder_error:.2f} vs spread of f {diagnosis.f_spread:.2f}",
            flush=True,
        )
    tmp_info = run.info_path(out).with_suffix(".json.partial")
    tmp_info.write_text(json.dumps(info, indent=2, default=str))
    os.replace(tmp_info, run.info_path(out))
    # The held-out curve (the completion mark) is renamed last.
    for split in sorted(config.eval_splits, key=lambda s: s == "test"):
        os.replace(partial[split], run.curve_path(out, split))
    return {"run": run, "status": "done", "seconds": seconds, "final": finals}


def _resume_best(best: Any, record: Dict[str, Any], folder: pathlib.Path, tag: str) -> None:
    """Restore the ``--select-on`` best model kept with the checkpoint the run goes on from."""
    kept = record.get("best")
    if kept and kept.get("split") == best.split and (folder / kept["model"]).exists():
        os.makedirs(best.best_model_save_path, exist_ok=True)
        shutil.copyfile(folder / kept["model"], pathlib.Path(best.best_model_save_path) / "best_model.zip")
        best.best_mean_reward, best.best_env_steps = float(kept["mean"]), int(kept["env_steps"])
    else:
        # The checkpoint was made without --select-on: select among the evaluations from here on.
        best.best_mean_reward, best.best_env_steps = -np.inf, None
        print(f"[{tag}] the checkpoint keeps no best model: selecting from here on", flush=True)


def _meta_test_best(run: Run, config: RunConfig, best: Any, tag: str) -> Dict[str, Any]:
    """The ``--select-on`` best model's return on the held-out split (the same trials as the curve)."""
    from sb3_dream.evaluation import evaluate_meta

    model = algorithm_class(run.algo).load(pathlib.Path(best.best_model_save_path) / "best_model.zip")
    result = evaluate_meta(model, run.env.env_id, split="test", **_meta_test_kwargs(run, config))
    print(
        f"[{tag}] best on {best.split}: {best.best_mean_reward:.3f} at {best.best_env_steps} env steps; "
        f"held-out return {format_mean_ci(result.mean, result.ci)}",
        flush=True,
    )
    return {
        "selected_on": best.split,
        "ties": best.best_ties,
        "env_steps": best.best_env_steps,
        "mean_on_selection_split": best.best_mean_reward,
        "test": {"mean": result.mean, "ci": result.ci, "exploration_length": result.mean_exploration_length},
    }


def _run_worker(run: Run, config: RunConfig, out: pathlib.Path, concurrent_runs: int = 1) -> Dict[str, Any]:
    """:func:`run_one` for a worker process: a failure is reported, not raised, so the others go on."""
    try:
        return run_one(run, config, out, concurrent_runs)
    except Exception as error:  # noqa: BLE001  (reported with its traceback, the experiment goes on)
        return {
            "run": run,
            "status": "failed",
            "error": f"{type(error).__name__}: {error}",
            "traceback": traceback.format_exc(),
        }


def _exit_with_parent(parent_pid: int, poll_seconds: float = 1.0) -> None:
    """Worker-process initializer: end this worker soon after the runner that started it ends.

    A runner stopped by ``kill`` (SIGTERM or SIGKILL, unlike Ctrl-C, which reaches its whole
    process group) would otherwise leave its workers training on, writing checkpoints and curves
    that a later command then mistakes for its own. Exiting at once is safe: every file a run
    writes is replaced atomically, so the run goes on from its last checkpoint next time.
    """

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(poll_seconds)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def plan_runs(algos: Sequence[str], envs: Sequence[EnvSpec], seeds: Sequence[int]) -> List[Run]:
    """Every (env, algo, seed) combination, validated."""
    unknown = [a for a in algos if a not in ALGOS]
    if unknown or not algos:
        raise ValueError(f"algos={list(algos)!r} is not valid; accepted values: {', '.join(map(repr, ALGOS))}")
    if not envs:
        raise ValueError("envs must name at least one env")
    if not seeds or any(isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 0 for s in seeds):
        raise ValueError(f"seeds must be a non-empty list of integers >= 0, got {list(seeds)!r}")
    return [Run(algo, env, int(seed)) for env in envs for algo in dict.fromkeys(algos) for seed in dict.fromkeys(seeds)]


def finished_runs(out: pathlib.Path) -> List[Run]:
    """Every finished run under ``out``, whichever command made it, from the runs' JSON records
    (sorted by env folder, algorithm and seed)."""
    found = []
    for path in sorted(pathlib.Path(out).glob("*/*.json")):
        try:
            info = json.loads(path.read_text())
            # JSON turned tuples into lists; EnvSpec must stay hashable.
            kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in info["env_kwargs"].items()}
            run = Run(info["algo"], EnvSpec(info["env"], tuple(sorted(kwargs.items()))), int(info["seed"]))
        except (ValueError, KeyError, TypeError, AttributeError):
            continue  # not a run's record (an oracle's, say)
        if run.info_path(out) == path and any(run.curve_path(out, split).exists() for split in all_splits()):
            found.append(run)
    order = {algo: k for k, algo in enumerate(ALGOS)}
    return sorted(found, key=lambda r: (r.env.tag, order.get(r.algo, len(order)), r.seed))


def _with_finished(runs: Sequence[Run], out: pathlib.Path) -> List[Run]:
    """``runs`` followed by the other finished runs under ``out`` (one per set of files)."""
    merged: Dict[Tuple[str, str, int], Run] = {}
    for run in [*runs, *finished_runs(out)]:
        merged.setdefault((run.env.tag, run.algo, run.seed), run)
    return list(merged.values())


def check_eval_splits(runs: Sequence[Run], config: RunConfig) -> None:
    """Raise a ``ValueError`` unless every env of ``runs`` offers every split of ``config.eval_splits``."""
    for env in dict.fromkeys(run.env for run in runs):
        offered = env_splits(env.env_id)
        missing = [split for split in config.eval_splits if split not in offered]
        if missing:
            accepted = ", ".join(map(repr, offered))
            raise ValueError(f"eval_splits={missing!r} is not valid for {env.label}; accepted values: {accepted}")


def run_experiments(
    runs: Sequence[Run], config: RunConfig, out: pathlib.Path, jobs: Optional[int] = None, force: bool = False
) -> List[Dict[str, Any]]:
    """Run every unfinished run of ``runs``, up to ``jobs`` at once (default: the machine's cores).

    Returns one record per run with ``status`` "done", "skipped" or "failed". ``jobs=1`` runs them
    one after the other in this process.
    """
    check_eval_splits(runs, config)
    out = pathlib.Path(out)
    records: List[Dict[str, Any]] = []
    pending: List[Run] = []
    for run in runs:
        checkpointer = Checkpointer(run, config, out)
        if not run.is_complete(out, config):
            pending.append(run)
        elif force:
            checkpointer.remove()  # redo from scratch, not from the kept final checkpoint
            pending.append(run)
        elif _extendable(config, checkpointer):
            print(f"extend {run.algo} {run.env.label} seed {run.seed} to {config.steps} env steps", flush=True)
            pending.append(run)
        else:
            _warn_if_settings_differ(run, config, out)
            print(f"skip {run.algo} {run.env.label} seed {run.seed}: finished ({run.curve_path(out)})", flush=True)
            records.append({"run": run, "status": "skipped"})
    if jobs is not None and (isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1):
        raise ValueError(f"jobs must be an integer >= 1 or None (the machine's cores), got {jobs!r}")
    jobs = min(jobs or os.cpu_count() or 1, max(len(pending), 1))
    if pending:
        print(f"running {len(pending)} run(s), {jobs} at a time, {config.steps} env steps each", flush=True)
    if jobs == 1:
        records += [_run_worker(run, config, out) for run in pending]
    elif pending:
        # "spawn": fresh interpreters, no forked torch thread pools; the worker is named by its
        # module so that pickling works under ``python -m sb3_dream.experiments`` too.
        module = importlib.import_module("sb3_dream.experiments")
        worker = module._run_worker
        context = multiprocessing.get_context("spawn")
        with concurrent.futures.ProcessPoolExecutor(
            max_workers=jobs, mp_context=context, initializer=module._exit_with_parent, initargs=(os.getpid(),)
        ) as pool:
            futures = [pool.submit(worker, run, config, out, jobs) for run in pending]
            for future in concurrent.futures.as_completed(futures):
                records.append(future.result())
    for record in records:
        if record["status"] == "failed":
            run = record["run"]
            print(
                f"FAILED {run.algo} {run.env.label} seed {run.seed}: {record['error']}\n{record['traceback']}",
                flush=True,
            )
    return records


def _extendable(config: RunConfig, checkpointer: Checkpointer) -> bool:
    """Whether a complete run goes on to ``config.steps`` from its kept final checkpoint: with
    ``--checkpoint-freq``, a checkpoint short of ``config.steps``, made with the same settings but
    the budget."""
    steps = checkpointer.saved_steps()
    if not config.checkpoint_freq or steps is None or steps >= config.steps:
        return False
    return checkpointer.load() is not None


def _warn_if_settings_differ(run: Run, config: RunConfig, out: pathlib.Path) -> None:
    try:
        recorded = json.loads(run.info_path(out).read_text())["settings"]
    except (OSError, ValueError, KeyError):
        return
    wanted = json.loads(json.dumps(config.settings(run.algo), default=str))
    changed = sorted(k for k in wanted if recorded.get(k) != wanted[k])
    if changed:
        print(
            f"warning: {run.curve_path(out)} was made with other settings ({', '.join(changed)}); "
            "it is kept: use --force or another --out to redo it",
            flush=True,
        )


# ---------------------------------------------------------------------------------------------- results
def load_curve(path: pathlib.Path) -> Dict[str, np.ndarray]:
    """A learning-curve CSV as arrays, one per column."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{path} holds no evaluation")
    return {k: np.array([float(r[k]) for r in rows]) for k in CURVE_COLUMNS}


def oracle_return(
    env: EnvSpec, split: str, n_trials: int, out: pathlib.Path, exhaustive: bool = False
) -> Optional[float]:
    """Mean execution return of the env's scripted optimal agent on ``split`` (cached as JSON;
    ``exhaustive``: over every (problem, instruction) pair, see :func:`evaluate_meta`)."""
    import gymnasium as gym

    import dream_envs
    from sb3_dream.evaluation import evaluate_meta

    path = out / env.tag / f"oracle_{split}{'_exhaustive' if exhaustive else ''}.json"
    if path.exists():
        return float(json.loads(path.read_text())["mean"])
    try:
        made = gym.make(env.env_id, split=split, n_exec_episodes=env.n_exec_episodes, **env.eval_kwargs)
        result = evaluate_meta(
            dream_envs.make_oracle(made),
            made,
            n_trials=n_trials,
            split=split,
            n_exec_episodes=env.n_exec_episodes,
            exhaustive=exhaustive,
        )
        made.close()
    except (AttributeError, NotImplementedError):  # an env without an oracle
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"mean": result.mean, "ci": result.ci, "n_trials": result.n_trials}
    path.write_text(json.dumps({**record, "exhaustive": True} if exhaustive else record))
    return result.mean


def summarize(
    runs: Sequence[Run], config: RunConfig, out: pathlib.Path, oracles: Optional[Dict[Tuple[str, str], float]] = None
) -> List[Dict[str, Any]]:
    """One row per (env, algo, split): the final return's mean and std over the finished seeds
    (numpy's std, ddof=0, as the figures' bands), the final env steps and the mean wall-clock.

    ``last_tenth_mean`` averages each seed's evaluations over the last tenth of its env steps, then
    the seeds: single greedy evaluations of a value-based agent swing, and one of them can
    misrepresent where a run ended."""
    rows = []
    groups: Dict[Tuple[EnvSpec, str], List[Run]] = {}
    for run in runs:
        groups.setdefault((run.env, run.algo), []).append(run)
    for (env, algo), group in groups.items():
        for split in config.eval_splits:
            curves = [load_curve(r.curve_path(out, split)) for r in group if r.curve_path(out, split).exists()]
            row: Dict[str, Any] = {"env": env.label, "algo": algo, "split": split, "seeds": len(curves)}
            if curves:
                finals = np.array([c["mean"][-1] for c in curves])
                last_tenth = [c["mean"][c["env_steps"] >= 0.9 * c["env_steps"][-1]].mean() for c in curves]
                row.update(
                    final_return_mean=float(finals.mean()),
                    final_return_std=float(finals.std()),
                    last_tenth_mean=float(np.mean(last_tenth)),
                    env_steps=int(np.mean([c["env_steps"][-1] for c in curves])),
                    wall_clock_s=float(np.mean([c["wall_clock_s"][-1] for c in curves])),
                )
            if oracles and (env.tag, split) in oracles:
                row["oracle_return"] = oracles[(env.tag, split)]
            rows.append(row)
    return rows


SUMMARY_COLUMNS = (
    "env",
    "algo",
    "split",
    "seeds",
    "final_return_mean",
    "final_return_std",
    "last_tenth_mean",
    "env_steps",
    "wall_clock_s",
    "oracle_return",
)


def write_summary(rows: Sequence[Dict[str, Any]], out: pathlib.Path) -> str:
    """Write ``summary.csv`` and ``summary.md`` under ``out``; return the markdown table."""
    with open(out / "summary.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=SUMMARY_COLUMNS)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: row.get(k, "") for k in SUMMARY_COLUMNS})
    lines = [
        "| env | algo | split | seeds | final return (mean ± std) | mean over the last tenth | optimal | env steps "
        "| wall-clock |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        ret = f"{row['final_return_mean']:.3f} ± {row['final_return_std']:.3f}" if row["seeds"] else "-"
        last_tenth = f"{row['last_tenth_mean']:.3f}" if row["seeds"] else "-"
        optimal = f"{row['oracle_return']:.3f}" if "oracle_return" in row else "-"
        steps = f"{row['env_steps']:,}" if row["seeds"] else "-"
        clock = _format_seconds(row["wall_clock_s"]) if row["seeds"] else "-"
        cells = [row["env"], row["algo"], row["split"], str(row["seeds"]), ret, last_tenth, optimal, steps, clock]
        lines.append("| " + " | ".join(cells) + " |")
    table = "\n".join(lines) + "\n"
    (out / "summary.md").write_text(table)
    return table


def _format_seconds(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


def plot_curves(
    runs: Sequence[Run], config: RunConfig, out: pathlib.Path, oracles: Optional[Dict[Tuple[str, str], float]] = None
) -> pathlib.Path:
    """``curves.png``: execution return vs env steps, mean +- std over seeds, one panel per env and
    split, with the optimal return dashed (the paper's Figures 5 and 6)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    envs = list(dict.fromkeys(run.env for run in runs))
    algos = list(dict.fromkeys(run.algo for run in runs))
    panels = [(env, split) for env in envs for split in config.eval_splits]
    n_cols = min(len(panels), 3)
    n_rows = -(-len(panels) // n_cols)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(5 * n_cols, 3.6 * n_rows), squeeze=False)
    for ax, (env, split) in zip(axes.flat, panels):
        for k, algo in enumerate(algos):
            paths = [r.curve_path(out, split) for r in runs if r.env == env and r.algo == algo]
            curves = [load_curve(p) for p in paths if p.exists()]
            if not curves:
                continue
            n = min(len(c["mean"]) for c in curves)
            steps = curves[0]["env_steps"][:n]
            values = np.stack([c["mean"][:n] for c in curves])
            mean, std = values.mean(axis=0), values.std(axis=0)
            color = f"C{k}"
            ax.plot(steps, mean, color=color, label=f"{algo} ({len(curves)} seed{'s' if len(curves) > 1 else ''})")
            ax.fill_between(steps, mean - std, mean + std, color=color, alpha=0.2, linewidth=0)
        if oracles and (env.tag, split) in oracles:
            ax.axhline(oracles[(env.tag, split)], color="k", ls="--", lw=1, label="optimal")
        ax.set_title(f"{env.label}" + ("" if split == "test" else f", {split} split"))
        ax.set_xlabel("env steps")
        ax.set_ylabel("execution return" + (" (held-out)" if split == "test" else ""))
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="best", fontsize="small")
        else:
            ax.text(0.5, 0.5, "no finished run", ha="center", va="center", transform=ax.transAxes)
    for ax in list(axes.flat)[len(panels):]:  # fmt: skip
        ax.axis("off")
    fig.tight_layout()
    path = out / "curves.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m sb3_dream.experiments",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--algos", nargs="+", default=["dream"], help=f"any of {', '.join(ALGOS)}")
    parser.add_argument("--envs", nargs="+", default=["MetaBus-v0"], help="env IDs, optionally ID:key=value...")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--steps", type=int, default=100_000, help="env steps per run")
    parser.add_argument("--n-envs", type=int, default=1, help="vectorised envs per run")
    parser.add_argument("--preset", default="paper", choices=PRESET_NAMES)
    parser.add_argument("--eval-freq", type=int, default=10_000, help="env steps between evaluations")
    parser.add_argument("--eval-trials", type=int, default=100, help="meta-test trials per evaluation")
    parser.add_argument(
        "--eval-exhaustive",
        action="store_true",
        help="evaluate on every (problem, instruction) pair of the split, weighted by its probability "
        "(the split's expected return; --eval-trials is then a minimum, in whole passes over the pairs)",
    )
    parser.add_argument(
        "--eval-splits",
        nargs="+",
        default=["test"],
        choices=all_splits(),
        help="test = held-out problems and instructions; MetaCook also has its parts test_problems, test_instructions",
    )
    parser.add_argument("--dream-kwargs", nargs="*", default=[], metavar="KEY=VALUE", help="DREAM overrides")
    parser.add_argument("--rl2dqn-kwargs", nargs="*", default=[], metavar="KEY=VALUE", help="RL2DQN overrides")
    parser.add_argument("--jobs", type=int, default=None, help="parallel runs (default: the machine's cores)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per run")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--save-models", action="store_true", help="save each trained model next to its curve")
    parser.add_argument(
        "--checkpoint-freq",
        type=int,
        default=0,
        help="save model and replay buffers at least every N env steps (at evaluations) and resume from them; 0: off",
    )
    parser.add_argument(
        "--snapshot-freq",
        type=int,
        default=0,
        help="also save the model (no replay buffers) every N env steps under <env>/snapshots/; 0: off",
    )
    parser.add_argument(
        "--select-on",
        default="",
        choices=("", *all_splits()),
        metavar="SPLIT",
        help="keep the model of the best evaluation on SPLIT (one of --eval-splits; train: an honest "
        "choice) under <env>/best/ and meta-test it on the held-out split at the end",
    )
    parser.add_argument(
        "--select-ties",
        default="last",
        choices=BEST_TIES,
        help="which of several evaluations at the same best return --select-on keeps (default last: on a "
        "saturated split, e.g. MetaCook's training split at the oracle, the first is an early model)",
    )
    parser.add_argument(
        "--init-from",
        default="",
        metavar="DIR",
        help="start each run from the same run's final checkpoint under DIR, with this command's overrides",
    )
    parser.add_argument("--out", default="results/experiments")
    parser.add_argument("--force", action="store_true", help="redo finished runs")
    parser.add_argument("--no-plot", action="store_true", help="skip the figure")
    parser.add_argument(
        "--summary-only",
        action="store_true",
        help="train nothing: summarize and plot the finished runs under --out (e.g. runs made by several "
        "commands into it)",
    )
    parser.add_argument("--no-oracle", action="store_true", help="skip the optimal scripted agent's return")
    return parser


def main(argv: Optional[Sequence[str]] = None) -> List[Dict[str, Any]]:
    """Run the experiment described by ``argv`` (see ``--help``); return the run records."""
    args = build_parser().parse_args(argv)
    try:
        config = RunConfig(
            steps=args.steps,
            n_envs=args.n_envs,
            preset=args.preset,
            eval_freq=args.eval_freq,
            eval_trials=args.eval_trials,
            eval_exhaustive=args.eval_exhaustive,
            eval_splits=tuple(dict.fromkeys(args.eval_splits)),
            threads=args.threads,
            device=args.device,
            save_models=args.save_models,
            checkpoint_freq=args.checkpoint_freq,
            snapshot_freq=args.snapshot_freq,
            select_on=args.select_on,
            select_ties=args.select_ties,
            dream_kwargs=tuple(sorted(parse_kwargs(args.dream_kwargs, "--dream-kwargs").items())),
            rl2dqn_kwargs=tuple(sorted(parse_kwargs(args.rl2dqn_kwargs, "--rl2dqn-kwargs").items())),
            init_from=args.init_from,
        )
        runs = plan_runs(args.algos, [EnvSpec.parse(e) for e in args.envs], args.seeds)
        check_eval_splits(runs, config)
        if args.jobs is not None and args.jobs < 1:
            raise ValueError(f"jobs must be an integer >= 1, got {args.jobs}")
    except ValueError as error:
        raise SystemExit(f"error: {error}")

    import dream_envs  # noqa: F401  (registers the env IDs in this process)

    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    records = [] if args.summary_only else run_experiments(runs, config, out, jobs=args.jobs, force=args.force)

    # The table and the figure cover every finished run under --out, not only this command's.
    runs = _with_finished(runs, out)
    oracles: Dict[Tuple[str, str], float] = {}
    if not args.no_oracle:
        for env in dict.fromkeys(run.env for run in runs):
            for split in config.eval_splits:
                value = oracle_return(env, split, config.eval_trials, out, config.eval_exhaustive)
                if value is not None:
                    oracles[(env.tag, split)] = value
    table = write_summary(summarize(runs, config, out, oracles), out)
    print(f"\n{table}\nwrote {out / 'summary.csv'} and {out / 'summary.md'}")
    if not args.no_plot:
        try:
            print("wrote", plot_curves(runs, config, out, oracles))
        except ImportError:
            print("matplotlib is not installed: no figure (pip install matplotlib, or sb3-dream[dev])")
    failed = [r for r in records if r["status"] == "failed"]
    if failed:
        raise SystemExit(f"{len(failed)} run(s) failed")
    return records


if __name__ == "__main__":
    main()
