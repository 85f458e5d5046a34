"""The experiment runner on Ray: a head on 127.0.0.1 with 2 CPUs, started and stopped here."""

from __future__ import annotations

import csv
import json
import os
import pathlib
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from test_experiments import TINY_DREAM

from sb3_dream import experiments
from sb3_dream.experiments import load_curve, ray_backend

ray = pytest.importorskip("ray")

TINY_RL2 = ["learning_starts=20", "buffer_size=200"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def ray_address(tmp_path_factory):
    """``HOST:PORT`` of a Ray head with 2 CPUs, ended (with its workers) after the module's tests."""
    port = _free_port()
    log_path = tmp_path_factory.mktemp("ray") / "head.log"
    log = open(log_path, "w")
    head = subprocess.Popen(
        [
            sys.executable, "-m", "ray.scripts.scripts", "start", "--head", "--block",  # the `ray` command
            "--node-ip-address=127.0.0.1", f"--port={port}", "--num-cpus=2", "--num-gpus=0",
            "--include-dashboard=false", "--disable-usage-stats", "--object-store-memory=80000000",
        ],  # fmt: skip
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        env={**os.environ, "RAY_AUTH_MODE": "disabled"},
    )
    address = f"127.0.0.1:{port}"
    # The same for the runner here: a token in ~/.ray (which a local Ray may have made) would
    # otherwise turn token authentication on for the head but not for a driver given its address.
    patch = pytest.MonkeyPatch()
    patch.setenv("RAY_AUTH_MODE", "disabled")
    try:
        deadline = time.monotonic() + 120
        # `ray start --block` says so once the node's processes are up.
        while "will now block forever" not in log_path.read_text():
            assert head.poll() is None and time.monotonic() < deadline, log_path.read_text()
            time.sleep(0.2)
        yield address
    finally:
        patch.undo()
        head.send_signal(signal.SIGTERM)  # `ray start --block` stops the node's processes on SIGTERM
        try:
            head.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)
            head.wait()
        log.close()


def _argv(out, seeds, steps, algos=("dream",), *more):
    return [
        "--algos", *algos, "--envs", "MetaBandit-v0", "--seeds", *map(str, seeds), "--steps", str(steps),
        "--eval-freq", "100", "--eval-trials", "4", "--out", str(out), "--no-plot", "--no-oracle",
        "--dream-kwargs", *TINY_DREAM, "--rl2dqn-kwargs", *TINY_RL2, *more,
    ]  # fmt: skip


def _summary(out):
    with open(out / "summary.csv", newline="") as f:
        return [{k: v for k, v in row.items() if k != "wall_clock_s"} for row in csv.DictReader(f)]


def test_the_grid_on_ray_gives_the_local_pool_s_summary(ray_address, tmp_path, capsys):
    local, on_ray = tmp_path / "local", tmp_path / "ray"
    grid = dict(seeds=[0, 1], steps=200, algos=("dream", "rl2dqn"))
    assert [r["status"] for r in experiments.main(_argv(local, *grid.values(), "--jobs", "2"))] == ["done"] * 4
    capsys.readouterr()
    sent_back = tmp_path / "sent_back"  # --ray-files driver: the tasks send the runs' files back
    for out, files in ((on_ray, "shared"), (sent_back, "driver")):
        argv = _argv(out, *grid.values(), "--backend", "ray", "--ray-address", ray_address, "--ray-files", files)
        assert [r["status"] for r in experiments.main(argv)] == ["done"] * 4
        printed = capsys.readouterr().out
        assert "running 4 run(s), 2 at a time" in printed
        assert all(f"[{k}/4] done " in printed for k in range(1, 5))  # a line per run as it arrives
        assert _summary(out) == _summary(local) and len(_summary(local)) == 2
        for path in (local / "MetaBandit-v0").glob("*.csv"):
            np.testing.assert_array_equal(load_curve(path)["mean"], load_curve(out / path.relative_to(local))["mean"])
        assert sorted(p.name for p in (out / "MetaBandit-v0").iterdir()) == sorted(
            p.name for p in (local / "MetaBandit-v0").iterdir()
        )
        assert not ray.is_initialized()  # the runner disconnected

    # Run again: every run is finished, skipped without starting anything.
    again = experiments.main(_argv(on_ray, *grid.values(), "--backend", "ray", "--ray-address", ray_address))
    assert [r["status"] for r in again] == ["skipped"] * 4


def _kill_after_checkpoint(checkpoints, title: str, killed: list) -> None:
    """Kill -9 the process titled ``title`` (the Ray worker of a run) once one of the files that
    ``checkpoints()`` lists records 200 env steps or more."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        steps = 0
        for checkpoint in checkpoints():
            try:
                steps = max(steps, json.loads(checkpoint.read_text())["env_steps"])
            except (OSError, ValueError, KeyError):
                pass
        if steps >= 200:
            for proc in pathlib.Path("/proc").iterdir():
                try:
                    cmdline = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode().strip()
                except (OSError, ValueError):
                    continue
                if cmdline.startswith(title):
                    os.kill(int(proc.name), signal.SIGKILL)
                    killed.append(steps)
                    return
        time.sleep(0.05)


@pytest.mark.skipif(not pathlib.Path("/proc").is_dir(), reason="finds the worker under /proc")
@pytest.mark.parametrize("files", ["shared", "driver"])
def test_a_killed_worker_is_retried_and_goes_on_from_its_checkpoint(ray_address, tmp_path, files):
    """The worker is killed after a checkpoint: Ray reruns the run, which goes on from there
    (with --ray-files driver, from the checkpoint it left in its node's folder)."""
    out = tmp_path / "ray"
    run = experiments.Run("dream", experiments.EnvSpec("MetaBandit-v0"), 0)
    began = time.time()

    def checkpoints():
        if files == "shared":
            return [run.checkpoint_path(out)]
        found = ray_backend.SCRATCH.glob(f"*/{run.checkpoint_path(pathlib.Path())}")
        return [path for path in found if path.stat().st_mtime >= began]

    killed: list = []
    killer = threading.Thread(
        target=_kill_after_checkpoint, args=(checkpoints, "ray::dream MetaBandit-v0 seed 0", killed), daemon=True
    )
    killer.start()
    argv = _argv(out, [0], 1500, ("dream",), "--backend", "ray", "--ray-address", ray_address, "--ray-files", files)
    (record,) = experiments.main([*argv, "--checkpoint-freq", "100"])
    killer.join()
    assert killed, "the run ended before its worker was killed"
    assert record["status"] == "done"
    info = json.loads(run.info_path(out).read_text())
    assert info["resumed_from"] is not None and killed[0] <= info["resumed_from"] < 1500
    # Every evaluation once, in order: none lost with the worker, none repeated by the rerun.
    np.testing.assert_array_equal(load_curve(run.curve_path(out))["env_steps"], np.arange(0, 1501, 100))
    assert json.loads(run.checkpoint_path(out).read_text())["env_steps"] == 1500  # kept, to extend the run
    assert not list(ray_backend.SCRATCH.glob("*/MetaBandit-v0"))  # the node's folder of the run is gone


def test_an_address_where_no_ray_runs_is_a_clear_error(tmp_path):
    out = tmp_path / "ray"
    port = _free_port()
    start = time.monotonic()
    with pytest.raises(SystemExit, match=f"cannot reach a Ray cluster at '127.0.0.1:{port}'"):
        experiments.main(_argv(out, [0], 100, ("dream",), "--backend", "ray", "--ray-address", f"127.0.0.1:{port}"))
    assert time.monotonic() - start < 30 and not list(out.glob("*/*.csv"))
    with pytest.raises(SystemExit, match="--jobs is the local backend's"):
        experiments.main(_argv(out, [0], 100, ("dream",), "--backend", "ray", "--jobs", "2"))
    with pytest.raises(SystemExit, match="--ray-address needs --backend ray"):
        experiments.main(_argv(out, [0], 100, ("dream",), "--ray-address", "127.0.0.1:6379"))
