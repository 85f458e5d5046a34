"""The Ray backend: each run of an experiment as a Ray task, on a running cluster or a local Ray.

:class:`RayBackend` is a :class:`~sb3_dream.experiments.backends.Backend`: it connects to the
cluster at ``address`` (``ray start --head`` prints it; ``"auto"``: the cluster of this machine or
``RAY_ADDRESS``; ``None``: a Ray started for the experiment on this machine, stopped at its end),
submits every due run as a task that reserves ``cpus_per_run`` CPUs and ``gpus_per_run`` GPUs, and
yields each run's record as it arrives, printing a line per run.

**Files.** With ``files="shared"`` (the default) the tasks write the runs' files (curves,
records, checkpoints, models) straight into ``out``, which must therefore be the same path on
every node: one machine, or a shared filesystem (NFS, a cluster's home or scratch) mounted at the
same place everywhere. The driver resolves ``out`` to an absolute path, and each task first checks
that it sees this runner's lock file there; a node that does not fails the run with an error that
says so, instead of writing where the driver never looks. With ``files="driver"`` no filesystem is
shared: the driver sends each run's checkpoint (if any) with its task, the task trains in a folder
of its node (:data:`SCRATCH`) and sends every file of the run back in its result, and the driver
writes them into ``out`` (the held-out curve, the completion mark, last) and the node's folder is
removed. Either way the summary and the figure are made by the driver at the end, from ``out``.

**Failures.** A task whose worker process dies (killed, out of memory, its node lost) is retried
by Ray up to ``max_retries`` times; with ``--checkpoint-freq`` the retry goes on from the run's
last checkpoint (:mod:`~sb3_dream.experiments.checkpoints`), losing at most the env steps since
it. (With ``files="driver"``, a retry on the same node goes on from the checkpoint left in the
node's folder; on another node, from the checkpoint the driver sent at the start.) An exception in
a run is not retried: it is the run's "failed" record, with its traceback, as with the local
pool. Ray ends the tasks of a driver that ends, however it ends, so none trains on unseen into
``out``.

Ray is an optional dependency: ``pip install "sb3-dream[ray]"``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import pathlib
import shutil
import socket
import tempfile
import time
from typing import Any, Dict, Iterator, Optional, Sequence, Tuple

from sb3_dream.common.files import atomic_target
from sb3_dream.experiments.backends import run_worker
from sb3_dream.experiments.checkpoints import Checkpointer
from sb3_dream.experiments.config import Run, RunConfig
from sb3_dream.experiments.lock import LOCK_NAME, read_holder, worker_lock

FILES = ("shared", "driver")  # where the runs' files are written: RayBackend(files=...)
DEFAULT_PORT = 6379  # Ray's head port when an address names no port
# Each node's folder for the runs of files="driver" (--ray-files driver).
SCRATCH = pathlib.Path(tempfile.gettempdir()) / "sb3-dream-ray"


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


def _run_files(run: Run, out: pathlib.Path) -> Dict[str, bytes]:
    """Every file of ``run`` under ``out`` (curves, record, model, checkpoint, best model,
    snapshots, TensorBoard log), by path relative to ``out``; unfinished ``.partial`` files left out."""
    folder = run.folder(out)
    paths = [
        *folder.glob(f"{run.name}.*"),
        *folder.glob(f"{run.name}_*.csv"),
        *(folder / "checkpoints").glob(f"{run.name}.*"),
        *(folder / "snapshots").glob(f"{run.name}_*"),
        *(folder / "tensorboard").glob(f"{run.name}_*/*"),
        *(p for p in run.best_folder(out).rglob("*")),
    ]
    return {
        str(path.relative_to(out)): path.read_bytes()
        for path in paths
        if path.is_file() and ".partial" not in path.name
    }


def _checkpoint_files(run: Run, config: RunConfig, out: pathlib.Path) -> Dict[str, bytes]:
    """The files of ``run``'s last checkpoint under ``out`` (relative path -> bytes), if it has
    one made with ``config``'s settings, for a task that goes on from it elsewhere."""
    checkpointer = Checkpointer(run, config, out)
    if not config.checkpoint_freq or checkpointer.load() is None:
        return {}
    return {
        rel: data for rel, data in _run_files(run, out).items() if pathlib.PurePath(rel).parent.name == "checkpoints"
    }


def _write_files(files: Dict[str, bytes], out: pathlib.Path) -> None:
    """Write ``files`` (relative path -> bytes) under ``out``, each replaced atomically; the
    checkpoint's JSON after its model and buffers, the held-out curve (the completion mark) last."""

    def order(rel: str) -> Tuple[int, str]:
        path = pathlib.PurePath(rel)
        is_record = path.parent.name == "checkpoints" and path.suffix == ".json"
        is_curve = path.suffix == ".csv" and path.parent.name != "snapshots"
        return (2 if is_curve else 1 if is_record else 0), rel

    for rel in sorted(files, key=order):
        target = out / rel
        with atomic_target(target, target.suffix[1:]) as tmp:
            tmp.write_bytes(files[rel])


def _scratch(holder: Optional[Dict[str, Any]], out: pathlib.Path, run: Run) -> pathlib.Path:
    """This node's folder for ``run`` of the experiment ``out`` in the driver session ``holder``
    (a new session starts from the checkpoint the driver sends, never from one left here)."""
    session = json.dumps([holder, str(out), run.env.tag, run.name], sort_keys=True, default=str)
    return SCRATCH / hashlib.sha256(session.encode()).hexdigest()[:16]


def _ray_task_sending_files(
    run: Run,
    config: RunConfig,
    out: pathlib.Path,
    concurrent_runs: int,
    holder: Optional[Dict[str, Any]],
    inputs: Dict[str, bytes],
) -> Dict[str, Any]:
    """One run on a Ray worker in a folder of its node, from the run's files ``inputs`` (its
    checkpoint, sent by the driver); its record carries every file of the run back (``files``).

    A rerun on the same node after its worker died goes on from the newer checkpoint it left there;
    on another node, from the checkpoint the driver sent."""
    scratch = _scratch(holder, out, run)
    record_path = str(run.checkpoint_path(pathlib.Path()))  # relative to the experiment's folder
    shipped = json.loads(inputs[record_path])["env_steps"] if record_path in inputs else -1
    left_here = Checkpointer(run, config, scratch).saved_steps()
    if left_here is None or shipped > left_here:
        Checkpointer(run, config, scratch).remove()
        _write_files(inputs, scratch)
    record = run_worker(run, config, scratch, concurrent_runs)
    record["host"] = socket.gethostname()
    record["files"] = _run_files(run, scratch)  # a failed run's checkpoint too, to go on from next time
    shutil.rmtree(scratch, ignore_errors=True)
    with contextlib.suppress(OSError):
        SCRATCH.rmdir()  # unless other runs use it
    return record


class RayBackend:
    """The runs as Ray tasks on the cluster at ``address`` (None: a Ray started on this machine).

    :param address: ``HOST:PORT`` of a running head (``ray start --head``), ``ray://HOST:PORT``
        (Ray Client), ``"auto"``, or None for a local Ray stopped at the end of :meth:`run`
    :param cpus_per_run: CPUs each run reserves (its torch threads: the runner's ``--threads``)
    :param gpus_per_run: GPUs each run reserves (fractions share one GPU); 0: none
    :param max_retries: how many times Ray reruns a run whose worker process died
    :param files: ``"shared"``: the tasks write into ``out``, a folder every node sees at the same
        path; ``"driver"``: each task trains in a folder of its node, from the run's checkpoint that
        the driver sends, and sends every file of the run back, written into ``out`` by the driver
    :param init_kwargs: more arguments of ``ray.init`` (e.g. ``num_cpus`` of a local Ray)
    """

    def __init__(
        self,
        address: Optional[str] = None,
        cpus_per_run: float = 1,
        gpus_per_run: float = 0,
        max_retries: int = 3,
        files: str = "shared",
        init_kwargs: Optional[Dict[str, Any]] = None,
    ) -> None:
        if files not in FILES:
            raise ValueError(f"files={files!r} is not valid; accepted values: {', '.join(map(repr, FILES))}")
        self.files = files
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
        except (ConnectionError, RuntimeError) as error:
            hint = ""
            if self.address is not None and "RAY_AUTH_MODE" not in os.environ:
                hint = " (a cluster with token authentication needs RAY_AUTH_MODE=token and its token here)"
            raise RayUnavailable(f"cannot connect to Ray at {self.address!r}: {error}{hint}") from None
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

        if self.files == "driver" and config.init_from:
            raise ValueError("init_from needs the runs' files on a shared filesystem (files='shared')")
        function = _ray_task if self.files == "shared" else _ray_task_sending_files
        task = ray.remote(num_cpus=self.cpus_per_run, num_gpus=self.gpus_per_run, max_retries=self.max_retries)(
            function
        )
        # DREAM's second update thread only where the run reserved a second CPU.
        concurrent_runs = 1 if self.cpus_per_run >= 2 else 2
        holder = read_holder(out / LOCK_NAME)
        pending = {}
        for run in runs:
            args = (run, config, out, concurrent_runs, holder)
            if self.files == "driver":
                args += (ray.put(_checkpoint_files(run, config, out)),)
            name = f"{run.algo} {run.env.tag} seed {run.seed}"
            pending[task.options(name=name).remote(*args)] = (run, time.perf_counter())
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
            files = record.pop("files", None)
            if files is not None:
                _write_files(files, out)
                # older checkpoint files of the run, no longer named by its checkpoint record
                for path in (run.folder(out) / "checkpoints").glob(f"{run.name}.*"):
                    if str(path.relative_to(out)) not in files:
                        path.unlink(missing_ok=True)
            done += 1
            where = f" on {record['host']}" if record.get("host") else ""
            print(
                f"[{done}/{len(runs)}] {record['status']} {run.algo} {run.env.label} seed {run.seed}{where} "
                f"after {time.perf_counter() - start:.0f}s",
                flush=True,
            )
            yield record


__all__ = ["RayBackend", "RayUnavailable", "check_reachable"]
