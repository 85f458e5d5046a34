"""The Ray backend: each run of an experiment as a Ray task, on a running cluster or a local Ray.

:class:`RayBackend` is a :class:`~sb3_dream.experiments.backends.Backend`: it connects to the
cluster at ``address`` (``ray start --head`` prints it; ``"auto"``: the cluster of this machine or
``RAY_ADDRESS``; ``None``: a Ray started for the experiment on this machine, stopped at its end),
submits every due run as a task that reserves ``cpus_per_run`` CPUs and ``gpus_per_run`` GPUs, and
yields each run's record as it arrives, printing a line per run.

**Files.** The tasks write the runs' files (curves, records, checkpoints, models) straight into
``out``, which must therefore be the same path on every node: one machine, or a shared filesystem
(NFS, a cluster's home or scratch) mounted at the same place everywhere. The driver resolves
``out`` to an absolute path, and each task first checks that it sees this runner's lock file
there; a node that does not fails the run with an error that says so, instead of writing where
the driver never looks. The summary and the figure are made by the driver at the end, from
``out``, as with the local pool.

**Failures.** A task whose worker process dies (killed, out of memory, its node lost) is retried
by Ray up to ``max_retries`` times; with ``--checkpoint-freq`` the retry goes on from the run's
last checkpoint (:mod:`~sb3_dream.experiments.checkpoints`), losing at most the env steps since
it. An exception in a run is not retried: it is the run's "failed" record, with its traceback, as
with the local pool. Ray ends the tasks of a driver that ends, however it ends, so none trains on
unseen into ``out``.

Ray is an optional dependency: ``pip install "sb3-dream[ray]"``.
"""

from __future__ import annotations

import pathlib
import socket
import time
from typing import Any, Dict, Iterator, Optional, Sequence, Tuple

from sb3_dream.experiments.backends import run_worker
from sb3_dream.experiments.config import Run, RunConfig
from sb3_dream.experiments.lock import LOCK_NAME, read_holder, worker_lock

DEFAULT_PORT = 6379  # Ray's head port when an address names no port


class RayUnavailable(ConnectionError):
    """Ray is not installed, or the cluster at the address given cannot be reached."""


def _host_port(address: str) -> Optional[Tuple[str, int]]:
    """The (host, port) that ``address`` names (``HOST[:PORT]`` or ``ray://HOST[:PORT]``), or None
    for ``"auto"`` and ``"local"`` (Ray's own look-ups)."""
    if address in ("auto", "local"):
        return None
    bare = address.split("://", 1)[-1].rstrip("/")
    host, sep, port = bare.rpartition(":")
    if not sep:
        return bare, 10001 if address.startswith("ray://") else DEFAULT_PORT
    try:
        return host.strip("[]"), int(port)
    except ValueError:
        raise RayUnavailable(f"ray address {address!r} is not valid: expected HOST:PORT or ray://HOST:PORT") from None


def check_reachable(address: str, timeout_s: float = 10.0) -> None:
    """Raise :class:`RayUnavailable` unless something listens at ``address``'s host and port
    (Ray itself waits minutes on an address where nothing answers)."""
    target = _host_port(address)
    if target is None:
        return
    try:
        with socket.create_connection(target, timeout=timeout_s):
            pass
    except OSError as error:
        raise RayUnavailable(
            f"cannot reach a Ray cluster at {address!r} ({error}): start one with `ray start --head` and pass "
            "the address it prints (HOST:PORT), or leave --ray-address out for a Ray on this machine"
        ) from None


def _ray_task(
    run: Run, config: RunConfig, out: pathlib.Path, concurrent_runs: int, holder: Optional[Dict[str, Any]]
) -> Dict[str, Any]:
    """One run on a Ray worker: :func:`run_worker` in ``out`` while holding its workers lock,
    after checking that this node sees the runner's lock record ``holder`` there."""
    host = socket.gethostname()
    if holder is not None and read_holder(out / LOCK_NAME) != holder:
        return {
            "run": run,
            "status": "failed",
            "error": f"{out} on {host} is not the runner's folder (no lock of pid {holder.get('pid')} on "
            f"{holder.get('host')} there): the Ray backend needs --out on a filesystem that every node "
            "shares, at the same path",
            "traceback": "",
            "host": host,
        }
    with worker_lock(out):
        record = run_worker(run, config, out, concurrent_runs)
    record["host"] = host
    return record


class RayBackend:
    """The runs as Ray tasks on the cluster at ``address`` (None: a Ray started on this machine).

    :param address: ``HOST:PORT`` of a running head (``ray start --head``), ``ray://HOST:PORT``
        (Ray Client), ``"auto"``, or None for a local Ray stopped at the end of :meth:`run`
    :param cpus_per_run: CPUs each run reserves (its torch threads: the runner's ``--threads``)
    :param gpus_per_run: GPUs each run reserves (fractions share one GPU); 0: none
    :param max_retries: how many times Ray reruns a run whose worker process died
    :param init_kwargs: more arguments of ``ray.init`` (e.g. ``num_cpus`` of a local Ray)
    """

    def __init__(
        self,
        address: Optional[str] = None,
        cpus_per_run: float = 1,
        gpus_per_run: float = 0,
        max_retries: int = 3,
        init_kwargs: Optional[Dict[str, Any]] = None,
    ) -> None:
        if isinstance(cpus_per_run, bool) or not isinstance(cpus_per_run, (int, float)) or cpus_per_run <= 0:
            raise ValueError(f"cpus_per_run must be a number > 0, got {cpus_per_run!r}")
        if isinstance(gpus_per_run, bool) or not isinstance(gpus_per_run, (int, float)) or gpus_per_run < 0:
            raise ValueError(f"gpus_per_run must be a number >= 0, got {gpus_per_run!r}")
        if isinstance(max_retries, bool) or not isinstance(max_retries, int) or max_retries < 0:
            raise ValueError(f"max_retries must be an integer >= 0, got {max_retries!r}")
        self.address, self.cpus_per_run, self.gpus_per_run = address, cpus_per_run, gpus_per_run
        self.max_retries, self.init_kwargs = max_retries, dict(init_kwargs or {})
        self._connected_here = False

    def connect(self) -> None:
        """Connect to the cluster (once); :class:`RayUnavailable` if Ray is missing or the address
        cannot be reached."""
        try:
            import ray
        except ImportError:
            raise RayUnavailable('the Ray backend needs Ray: pip install "sb3-dream[ray]"') from None
        if ray.is_initialized():
            return
        kwargs: Dict[str, Any] = {"include_dashboard": False, "log_to_driver": True, **self.init_kwargs}
        kwargs["address"] = "local"  # a new Ray on this machine, whatever RAY_ADDRESS says
        if self.address is not None:
            check_reachable(self.address)
            kwargs["address"] = self.address
            for key in ("include_dashboard", "num_cpus", "num_gpus", "object_store_memory"):
                kwargs.pop(key, None)  # the cluster's, set by `ray start`
        try:
            ray.init(**kwargs)
        except ConnectionError as error:
            raise RayUnavailable(f"cannot connect to Ray at {self.address!r}: {error}") from None
        self._connected_here = True

    def close(self) -> None:
        """Disconnect from the cluster (a local Ray stops), if :meth:`connect` connected."""
        if self._connected_here:
            import ray

            ray.shutdown()
            self._connected_here = False

    def _capacity(self) -> int:
        """How many runs the cluster's resources hold at once (at least one)."""
        import ray

        resources = ray.cluster_resources()
        fits = [int(resources.get("CPU", 0) // self.cpus_per_run)]
        if self.gpus_per_run:
            fits.append(int(resources.get("GPU", 0) // self.gpus_per_run))
        return max(min(fits), 1)

    def slots(self, n_runs: int) -> int:
        self.connect()
        return min(self._capacity(), max(n_runs, 1))

    def run(self, runs: Sequence[Run], config: RunConfig, out: pathlib.Path) -> Iterator[Dict[str, Any]]:
        if not runs:
            return
        self.connect()
        try:
            yield from self._run(runs, config, pathlib.Path(out).resolve())
        finally:
            self.close()

    def _run(self, runs: Sequence[Run], config: RunConfig, out: pathlib.Path) -> Iterator[Dict[str, Any]]:
        import ray

        task = ray.remote(num_cpus=self.cpus_per_run, num_gpus=self.gpus_per_run, max_retries=self.max_retries)(
            _ray_task
        )
        # DREAM's second update thread only where the run reserved a second CPU.
        concurrent_runs = 1 if self.cpus_per_run >= 2 else 2
        holder = read_holder(out / LOCK_NAME)
        pending = {
            task.options(name=f"{run.algo} {run.env.tag} seed {run.seed}").remote(
                run, config, out, concurrent_runs, holder
            ): (run, time.perf_counter())
            for run in runs
        }
        done = 0
        while pending:
            (ref,), _ = ray.wait(list(pending), num_returns=1)
            run, start = pending.pop(ref)
            try:
                record = ray.get(ref)
            except ray.exceptions.RayError as error:  # the worker died more than max_retries times
                record = {
                    "run": run,
                    "status": "failed",
                    "error": f"{type(error).__name__} after {self.max_retries} retries: {str(error).splitlines()[0]}",
                    "traceback": str(error),
                }
            done += 1
            where = f" on {record['host']}" if record.get("host") else ""
            print(
                f"[{done}/{len(runs)}] {record['status']} {run.algo} {run.env.label} seed {run.seed}{where} "
                f"after {time.perf_counter() - start:.0f}s",
                flush=True,
            )
            yield record


__all__ = ["RayBackend", "RayUnavailable", "check_reachable"]
