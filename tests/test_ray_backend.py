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
from sb3_dream.experiments import load_curve

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
    log = open(tmp_path_factory.mktemp("ray") / "head.log", "w")
    head = subprocess.Popen(
        [
            os.path.join(os.path.dirname(sys.executable), "ray"), "start", "--head", "--block",
            "--node-ip-address=127.0.0.1", f"--port={port}", "--num-cpus=2", "--num-gpus=0",
            "--include-dashboard=false", "--disable-usage-stats", "--object-store-memory=80000000",
        ],  # fmt: skip
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    address = f"127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while subprocess.run(
            [os.path.join(os.path.dirname(sys.executable), "ray"), "status", "--address", address],
            capture_output=True,
        ).returncode:
            assert head.poll() is None and time.monotonic() < deadline, "the Ray head did not start"
            time.sleep(0.5)
        yield address
    finally:
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
    records = experiments.main(_argv(on_ray, *grid.values(), "--backend", "ray", "--ray-address", ray_address))
    assert [r["status"] for r in records] == ["done"] * 4
    printed = capsys.readouterr().out
    assert "running 4 run(s), 2 at a time" in printed
    assert all(f"[{k}/4] done " in printed for k in range(1, 5))  # a line per run as it arrives
    assert _summary(on_ray) == _summary(local) and len(_summary(local)) == 2
    for path in (local / "MetaBandit-v0").glob("*.csv"):
        np.testing.assert_array_equal(load_curve(path)["mean"], load_curve(on_ray / path.relative_to(local))["mean"])
    assert not ray.is_initialized()  # the runner disconnected

    # Run again: every run is finished, skipped without starting anything.
    again = experiments.main(_argv(on_ray, *grid.values(), "--backend", "ray", "--ray-address", ray_address))
    assert [r["status"] for r in again] == ["skipped"] * 4


def _kill_after_checkpoint(checkpoint: pathlib.Path, title: str, killed: list) -> None:
    """Kill -9 the process titled ``title`` (the Ray worker of a run) once ``checkpoint`` is past 100 steps."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            steps = json.loads(checkpoint.read_text())["env_steps"]
        except (OSError, ValueError, KeyError):
            steps = 0
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
def test_a_killed_worker_is_retried_and_goes_on_from_its_checkpoint(ray_address, tmp_path):
    out = tmp_path / "ray"
    run = experiments.Run("dream", experiments.EnvSpec("MetaBandit-v0"), 0)
    killed: list = []
    killer = threading.Thread(
        target=_kill_after_checkpoint,
        args=(run.checkpoint_path(out), "ray::dream MetaBandit-v0 seed 0", killed),
        daemon=True,
    )
    killer.start()
    argv = _argv(out, [0], 1500, ("dream",), "--backend", "ray", "--ray-address", ray_address)
    (record,) = experiments.main([*argv, "--checkpoint-freq", "100"])
    killer.join()
    assert killed, "the run ended before its worker was killed"
    assert record["status"] == "done"
    info = json.loads(run.info_path(out).read_text())
    assert info["resumed_from"] is not None and killed[0] <= info["resumed_from"] < 1500
    # Every evaluation once, in order: none lost with the worker, none repeated by the retry.
    np.testing.assert_array_equal(load_curve(run.curve_path(out))["env_steps"], np.arange(0, 1501, 100))


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
