"""The experiment runner's lock: one runner at a time trains into a --out folder."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time

import pytest
from test_experiments import TINY_DREAM

from sb3_dream import experiments
from sb3_dream.experiments import EnvSpec, RunConfig, plan_runs
from sb3_dream.experiments.lock import LOCK_NAME, WORKERS_LOCK_NAME, FolderLocked, read_holder, runner_lock

fcntl = pytest.importorskip("fcntl")


def _argv(out, seeds, steps):
    return [
        "--algos", "dream", "--envs", "MetaBandit-v0", "--seeds", *map(str, seeds), "--steps", str(steps),
        "--eval-freq", str(min(steps, 60)), "--eval-trials", "4", "--jobs", "1", "--out", str(out), "--no-plot",
        "--dream-kwargs", *TINY_DREAM,
    ]  # fmt: skip


class Recording:
    """A backend that trains nothing and says which runs it was given."""

    def __init__(self):
        self.runs = []

    def slots(self, n_runs):
        return n_runs

    def run(self, runs, config, out):
        self.runs += runs
        for run in runs:
            yield {"run": run, "status": "done"}


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_a_second_runner_on_a_folder_in_use_stops_and_the_finished_curve_stays(tmp_path, capsys):
    """Two runners on one --out: the second stops at once naming the first, whose runs and the
    finished ones stay intact; summaries still work; once the first is killed, its lock is taken over."""
    out = tmp_path / "results"
    assert [r["status"] for r in experiments.main(_argv(out, [0], 120))] == ["done"]
    finished = out / "MetaBandit-v0" / "dream_seed0.csv"
    curve = finished.read_bytes()
    assert not (out / LOCK_NAME).exists()  # released at the end
    capsys.readouterr()

    # A first runner trains seed 1 for a long time.
    first = subprocess.Popen(
        [sys.executable, "-m", "sb3_dream.experiments", *_argv(out, [1], 10_000_000), "--eval-freq", "1000000"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        deadline = time.time() + 120
        partial = out / "MetaBandit-v0" / "dream_seed1.csv.partial"
        while time.time() < deadline and first.poll() is None:
            if (read_holder(out / LOCK_NAME) or {}).get("pid") == first.pid or partial.exists():
                break
            time.sleep(0.2)
        assert first.poll() is None, "the first runner ended early"

        # A second runner on the same folder, about the same run: it stops, naming the first.
        with pytest.raises(SystemExit, match=rf"in use by another runner \(pid {first.pid} on ") as stopped:
            experiments.main(_argv(out, [0, 1], 120))
        message = str(stopped.value.code)
        assert str(out) in message and "since " in message and "sb3_dream" in message
        runs = plan_runs(["dream"], [EnvSpec("MetaBandit-v0")], [1])
        with pytest.raises(FolderLocked) as error:
            experiments.run_experiments(runs, RunConfig(steps=120), out, backend=Recording())
        assert error.value.holder["pid"] == first.pid and error.value.holder["host"] == socket.gethostname()
        assert finished.read_bytes() == curve and not (out / "MetaBandit-v0" / "dream_seed1.csv").exists()

        # Summaries only read: they work while the first runner trains.
        assert experiments.main([*_argv(out, [0, 1], 120), "--summary-only"]) == []
        assert "| MetaBandit-v0 | dream | test | 1 |" in capsys.readouterr().out
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait()

    # Killed, the first runner left its record behind: the next runner takes the folder over.
    assert read_holder(out / LOCK_NAME)["pid"] == first.pid
    records = experiments.main(_argv(out, [0], 120))
    assert [r["status"] for r in records] == ["skipped"]
    taken_over = f"taking over the lock of a runner that ended without releasing it (pid {first.pid}"
    assert taken_over in capsys.readouterr().err
    assert finished.read_bytes() == curve and not (out / LOCK_NAME).exists()


def test_a_stale_lock_of_a_dead_process_is_taken_over(tmp_path, capsys):
    stale = {"pid": _dead_pid(), "host": socket.gethostname(), "started": "2020-01-01T00:00:00", "command": "old"}
    (tmp_path / LOCK_NAME).write_text(json.dumps(stale))
    runs, backend = plan_runs(["dream"], [EnvSpec("MetaBandit-v0")], [0]), Recording()
    records = experiments.run_experiments(runs, RunConfig(steps=120), tmp_path, backend=backend)
    assert [r["status"] for r in records] == ["done"] and backend.runs == runs
    err = capsys.readouterr().err
    assert f"taking over the lock of a runner that ended without releasing it (pid {stale['pid']}" in err
    assert "since 2020-01-01T00:00:00, command: old" in err
    assert not (tmp_path / LOCK_NAME).exists() and not (tmp_path / WORKERS_LOCK_NAME).exists()


def test_the_lock_names_its_holder_and_is_released_on_errors(tmp_path):
    with runner_lock(tmp_path) as record:
        assert read_holder(tmp_path / LOCK_NAME) == record
        assert record["pid"] == os.getpid() and record["host"] == socket.gethostname() and record["started"]
        with pytest.raises(FolderLocked, match=rf"{tmp_path} is in use by another runner \(pid {os.getpid()}"):
            with runner_lock(tmp_path):
                pass
    assert not (tmp_path / LOCK_NAME).exists()
    with pytest.raises(KeyboardInterrupt):
        with runner_lock(tmp_path):
            raise KeyboardInterrupt
    with runner_lock(tmp_path):  # released by the interrupted block
        pass


def test_a_runner_taking_over_waits_for_the_workers_of_one_that_ended(tmp_path):
    """Workers of a killed runner outlive it by about a second: the next runner waits for them."""
    fd = os.open(tmp_path / WORKERS_LOCK_NAME, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_SH)  # as a worker process holds it
        with pytest.raises(FolderLocked, match="worker processes of a runner that ended still write into"):
            with runner_lock(tmp_path, worker_wait_s=0.3):
                pass
        assert not (tmp_path / LOCK_NAME).exists()
    finally:
        os.close(fd)
    with runner_lock(tmp_path, worker_wait_s=0.3):
        pass
    assert not (tmp_path / WORKERS_LOCK_NAME).exists()
