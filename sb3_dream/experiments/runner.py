"""The experiment runner: algorithms x envs x seeds, each run done once, on a backend."""

from __future__ import annotations

import json
import pathlib
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

from dream_envs import env_splits
from sb3_dream.experiments.algorithms import ALGORITHMS, algorithm_kwargs
from sb3_dream.experiments.backends import Backend, LocalPool
from sb3_dream.experiments.checkpoints import Checkpointer, extendable
from sb3_dream.experiments.config import EnvSpec, Run, RunConfig
from sb3_dream.experiments.lock import runner_lock


def plan_runs(algos: Sequence[str], envs: Sequence[EnvSpec], seeds: Sequence[int]) -> List[Run]:
    """Every (env, algo, seed) combination, validated."""
    unknown = [a for a in algos if a not in ALGORITHMS]
    if unknown or not algos:
        accepted = ", ".join(map(repr, ALGORITHMS))
        raise ValueError(f"algos={list(algos)!r} is not valid; accepted values: {accepted}")
    if not envs:
        raise ValueError("envs must name at least one env")
    if not seeds or any(isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 0 for s in seeds):
        raise ValueError(f"seeds must be a non-empty list of integers >= 0, got {list(seeds)!r}")
    runs = [Run(algo, env, int(seed)) for env in envs for algo in dict.fromkeys(algos) for seed in dict.fromkeys(seeds)]
    for run in runs:
        run.check_env_kwargs()
    return runs


def check_eval_splits(runs: Sequence[Run], config: RunConfig) -> None:
    """Raise a ``ValueError`` unless every env of ``runs`` offers every split of ``config.eval_splits``."""
    for env in dict.fromkeys(run.env for run in runs):
        offered = env_splits(env.env_id)
        missing = [split for split in config.eval_splits if split not in offered]
        if missing:
            accepted = ", ".join(map(repr, offered))
            raise ValueError(f"eval_splits={missing!r} is not valid for {env.label}; accepted values: {accepted}")


def check_presets(runs: Sequence[Run], config: RunConfig) -> None:
    """Raise a ``ValueError`` unless every algorithm of ``runs`` defines the preset ``config.preset``."""
    for algo in dict.fromkeys(run.algo for run in runs):
        algorithm_kwargs(algo, config)


def run_experiments(
    runs: Sequence[Run],
    config: RunConfig,
    out: pathlib.Path,
    jobs: Optional[int] = None,
    force: bool = False,
    backend: Optional[Backend] = None,
) -> List[Dict[str, Any]]:
    """Run every unfinished run of ``runs`` on ``backend`` (default: :class:`LocalPool` of ``jobs``,
    up to that many at once, default the machine's cores; ``jobs=1`` runs them one after the other
    in this process).

    Returns one record per run with ``status`` "done", "skipped" or "failed". Holds ``out``'s lock
    (:func:`~sb3_dream.experiments.lock.runner_lock`) throughout: raises
    :class:`~sb3_dream.experiments.lock.FolderLocked`, naming the holder, if another runner trains
    into ``out``.
    """
    if backend is None:
        backend = LocalPool(jobs)
    elif jobs is not None:
        raise ValueError("jobs is the local pool's: give jobs or backend, not both")
    check_eval_splits(runs, config)
    check_presets(runs, config)
    out = pathlib.Path(out)
    with runner_lock(out):
        return _run_due(runs, config, out, force, backend)


def _run_due(
    runs: Sequence[Run], config: RunConfig, out: pathlib.Path, force: bool, backend: Backend
) -> List[Dict[str, Any]]:
    records: List[Dict[str, Any]] = []
    pending: List[Run] = []
    for run in runs:
        checkpointer = Checkpointer(run, config, out)
        if not run.is_complete(out, config):
            pending.append(run)
        elif force:
            checkpointer.remove()  # redo from scratch, not from the kept final checkpoint
            pending.append(run)
        elif extendable(config, checkpointer):
            print(f"extend {run.algo} {run.env.label} seed {run.seed} to {config.steps} env steps", flush=True)
            pending.append(run)
        else:
            _warn_if_settings_differ(run, config, out)
            print(f"skip {run.algo} {run.env.label} seed {run.seed}: finished ({run.curve_path(out)})", flush=True)
            records.append({"run": run, "status": "skipped"})
    if pending:
        slots = backend.slots(len(pending))
        print(f"running {len(pending)} run(s), {slots} at a time, {config.steps} env steps each", flush=True)
        records += backend.run(pending, config, out)
    for record in records:
        if record["status"] == "failed":
            run = record["run"]
            print(
                f"FAILED {run.algo} {run.env.label} seed {run.seed}: {record['error']}\n{record['traceback']}",
                flush=True,
            )
    return records


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
