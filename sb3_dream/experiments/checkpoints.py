"""Checkpoints: a run's model, replay buffers and learning curve, saved so that it can go on.

A run with ``--checkpoint-freq`` saves them right after its evaluations and goes on from the last
one when the same command is run again (resumed), or with a larger ``--steps`` (extended); with
``--init-from`` a new run starts from another run's kept final checkpoint.
"""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import time
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from sb3_dream.common.files import atomic_target
from sb3_dream.experiments.config import Run, RunConfig


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
        # each file atomic whatever the algorithm: a checkpoint is never read half-written
        with atomic_target(self.folder / f"{stem}.zip", "zip") as tmp:
            model.save(tmp)
        with atomic_target(self.folder / f"{stem}.pkl", "pkl") as tmp:
            model.save_replay_buffer(tmp)
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
            with atomic_target(self.folder / f"{stem}.best.zip", "zip") as tmp:
                shutil.copyfile(best_file, tmp)
            record["best"] = {
                "model": f"{stem}.best.zip",
                "split": best.split,
                "env_steps": best.best_env_steps,
                "mean": best.best_mean_reward,
            }
        with atomic_target(self.path, "json") as tmp:
            tmp.write_text(json.dumps(record, default=str))
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


def make_checkpoint_callback(
    checkpointer: Checkpointer, evaluations: Sequence[Any], seconds_before: float, best: Any = None
) -> Any:
    """The callback that saves ``checkpointer``'s checkpoints right after ``evaluations`` (the
    run's evaluation callbacks); ``seconds_before``: the wall-clock of the sessions before this one."""
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


def resume_best(best: Any, record: Dict[str, Any], folder: pathlib.Path, tag: str) -> None:
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


def extendable(config: RunConfig, checkpointer: Checkpointer) -> bool:
    """Whether a complete run goes on to ``config.steps`` from its kept final checkpoint: with
    ``--checkpoint-freq``, a checkpoint short of ``config.steps``, made with the same settings but
    the budget."""
    steps = checkpointer.saved_steps()
    if not config.checkpoint_freq or steps is None or steps >= config.steps:
        return False
    return checkpointer.load() is not None
