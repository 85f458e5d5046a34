"""Backends: where the runs of an experiment execute.

:func:`~sb3_dream.experiments.runner.run_experiments` decides which runs are due and hands them to a
:class:`Backend`, which runs each with :func:`run_worker` and yields its record. :class:`LocalPool`
runs them in parallel processes of this machine; a backend that runs them elsewhere implements
the same two methods.
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import os
import pathlib
import threading
import time
import traceback
from typing import Any, Dict, Iterator, Optional, Protocol, Sequence

from sb3_dream.experiments.config import Run, RunConfig
from sb3_dream.experiments.lock import hold_worker_lock
from sb3_dream.experiments.training import run_one


class Backend(Protocol):
    """Executes runs of an experiment."""

    def slots(self, n_runs: int) -> int:
        """How many of ``n_runs`` runs execute at once."""

    def run(self, runs: Sequence[Run], config: RunConfig, out: pathlib.Path) -> Iterator[Dict[str, Any]]:
        """Execute ``runs``, yielding each one's :func:`run_worker` record as it ends (in any order)."""


def run_worker(run: Run, config: RunConfig, out: pathlib.Path, concurrent_runs: int = 1) -> Dict[str, Any]:
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


class LocalPool:
    """The runs in parallel processes of this machine, up to ``jobs`` at once (default: its cores);
    with one at a time, one after the other in this process.

    Each worker process ends with the runner however the runner is stopped (Ctrl-C, ``kill``,
    ``kill -9``), so that none trains on unseen into the experiment's folder.
    """

    def __init__(self, jobs: Optional[int] = None) -> None:
        if jobs is not None and (isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1):
            raise ValueError(f"jobs must be an integer >= 1 or None (the machine's cores), got {jobs!r}")
        self.jobs = jobs

    def slots(self, n_runs: int) -> int:
        return min(self.jobs or os.cpu_count() or 1, max(n_runs, 1))

    def run(self, runs: Sequence[Run], config: RunConfig, out: pathlib.Path) -> Iterator[Dict[str, Any]]:
        jobs = self.slots(len(runs))
        if jobs == 1:
            for run in runs:
                yield run_worker(run, config, out)
        elif runs:
            # "spawn": fresh interpreters, no forked torch thread pools.
            context = multiprocessing.get_context("spawn")
            with concurrent.futures.ProcessPoolExecutor(
                max_workers=jobs, mp_context=context, initializer=_init_worker, initargs=(os.getpid(), out)
            ) as pool:
                futures = [pool.submit(run_worker, run, config, out, jobs) for run in runs]
                for future in concurrent.futures.as_completed(futures):
                    yield future.result()


def _init_worker(parent_pid: int, out: pathlib.Path) -> None:
    """Worker-process initializer: :func:`_exit_with_parent`, and hold ``out``'s workers lock
    (:func:`~sb3_dream.experiments.lock.hold_worker_lock`) while this worker lives."""
    hold_worker_lock(out)
    _exit_with_parent(parent_pid)


def _exit_with_parent(parent_pid: int, poll_seconds: float = 1.0) -> None:
    """In a worker process: end it soon after the runner that started it ends.

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
