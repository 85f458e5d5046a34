"""The window and first-crossing numbers the results record quotes (sb3_dream.curves)."""

import csv

import numpy as np
import pytest

from sb3_dream import curves
from sb3_dream.evaluation import CURVE_COLUMNS


def write_curve(path, returns, every=10_000):
    """A runner-style curve CSV: an evaluation at 0 steps, then one every ``every`` steps."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(CURVE_COLUMNS)
        for i, mean in enumerate(returns):
            writer.writerow([i * every, 6.0 * i, mean, 0.1, 20.0])
    return path


@pytest.fixture
def curve_path(tmp_path):
    # 0 steps: -2.0 (before training); 10K-30K one window, 40K-60K the next, 70K alone in a third.
    return write_curve(tmp_path / "dream_seed0.csv", [-2.0, 0.1, 0.8, 0.2, 0.5, 0.9, 0.7, 0.4])


def test_windows_hold_the_evaluations_after_their_start_up_to_their_end(curve_path):
    found = curves.windows(curves.load_curve(curve_path), size=30_000, threshold=0.5)
    assert [(w.start, w.end, w.n) for w in found] == [(0, 30_000, 3), (30_000, 60_000, 3), (60_000, 90_000, 1)]
    first, second, third = found
    # The evaluation at 0 steps (-2.0) is in no window.
    assert first.mean == pytest.approx((0.1 + 0.8 + 0.2) / 3)
    assert first.median == pytest.approx(0.2)
    assert first.lowest == pytest.approx(0.1)
    assert first.reaching == 1
    assert second.mean == pytest.approx((0.5 + 0.9 + 0.7) / 3)
    assert second.reaching == 3  # at or above the threshold counts
    assert (third.mean, third.lowest, third.reaching) == (pytest.approx(0.4), pytest.approx(0.4), 0)


def test_median_of_an_even_window_is_the_middle_twos_mean(tmp_path):
    path = write_curve(tmp_path / "c.csv", [0.0, 0.1, 0.9, 0.3, 0.5])
    (window,) = curves.windows(curves.load_curve(path), size=40_000, threshold=1.0)
    assert window.median == pytest.approx(0.4)


def test_first_reaching_is_the_first_evaluation_not_the_best(curve_path):
    curve = curves.load_curve(curve_path)
    first = curves.first_reaching(curve, 0.75)
    assert first == {"env_steps": 20_000.0, "wall_clock_s": 12.0, "mean": 0.8}
    assert curves.first_reaching(curve, 0.95) is None


def test_a_window_must_be_positive(curve_path):
    with pytest.raises(ValueError, match="window"):
        curves.windows(curves.load_curve(curve_path), size=0, threshold=0.5)


def test_the_command_line_prints_each_curve(curve_path, tmp_path, capsys):
    other = write_curve(tmp_path / "dream_seed1.csv.partial", list(np.linspace(-1.0, 0.4, 5)))
    curves.main([str(curve_path), str(other), "--window", "30000", "--threshold", "0.5"])
    text = capsys.readouterr().out
    assert f"{curve_path}: 8 evaluations, last at 70K env steps (0.7 min): 0.400" in text
    assert "first >= 0.5: 20K (0.2 min, 0.800)" in text
    assert "30K-60K    3    0.700    0.700    0.500  3 of 3" in text
    assert f"{other}: 5 evaluations" in text and "first >= 0.5: none" in text
    with pytest.raises(SystemExit, match="No such file"):
        curves.main([str(tmp_path / "missing.csv")])
