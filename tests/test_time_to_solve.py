"""benchmarks/time_to_solve.py: the first held-out evaluation at a return, per seed and for the mean."""

from __future__ import annotations

import csv
import importlib.util
import pathlib

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("time_to_solve", ROOT / "benchmarks" / "time_to_solve.py")
time_to_solve = importlib.util.module_from_spec(spec)
spec.loader.exec_module(time_to_solve)


def test_mean_over_seeds_waits_for_the_slowest_seed():
    curves = {
        0: {"env_steps": np.array([0, 10, 20]), "wall_clock_s": np.array([0, 60, 120]), "mean": np.array([-1, 0.8, 1])},
        1: {"env_steps": np.array([0, 10]), "wall_clock_s": np.array([0, 90]), "mean": np.array([-1, 0.6])},
    }
    mean = time_to_solve.mean_over_seeds(curves)
    np.testing.assert_array_equal(mean["env_steps"], [0, 10])  # the steps every seed reached
    np.testing.assert_allclose(mean["mean"], [-1.0, 0.7])
    np.testing.assert_array_equal(mean["wall_clock_s"], [0, 90])


def test_a_tiny_grid_is_trained_then_read(tmp_path, capsys):
    out = tmp_path / "grid"
    argv = ["--algos", "dream", "--envs", "MetaBandit-v0", "--seeds", "0", "1", "--steps", "120", "--eval-freq", "60",
            "--eval-trials", "4", "--jobs", "1", "--out", str(out), "--dream-kwargs", "exploration_learning_starts=1",
            "execution_learning_starts=1"]  # fmt: skip
    time_to_solve.main([*argv, "--threshold", "-10", "--minutes", "60"])
    printed = capsys.readouterr().out.splitlines()
    # every evaluation reaches -10: the first is the one before training, at 0 env steps
    assert [line.split()[:2] for line in printed[-3:]] == [["seed", "0"], ["seed", "1"], ["mean", "of"]]
    assert all("at 0K env steps" in line and "within budget" in line for line in printed[-3:])
    # the same runs read again, training nothing; a return none reached says so, with the last one
    time_to_solve.main(["--report-only", "--out", str(out), "--threshold", "2"])
    report = capsys.readouterr().out
    assert report.count("not reached") == 3
    with open(out / "MetaBandit-v0" / "dream_seed0.csv") as f:
        last = list(csv.DictReader(f))[-1]
    assert f"last {float(last['mean']):.3f} at 0.12K" in report
    with pytest.raises(SystemExit, match="holds no finished run"):
        time_to_solve.main(["--report-only", "--out", str(tmp_path / "empty"), "--threshold", "0"])
