"""benchmarks/timing.py: the interleaved rounds the per-update benchmarks share."""

from __future__ import annotations

import importlib.util
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("timing", ROOT / "benchmarks" / "timing.py")
timing = importlib.util.module_from_spec(spec)
spec.loader.exec_module(timing)


class FakeClock:
    """perf_counter that each entry's run() advances by a known number of seconds."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_every_entry_runs_once_per_round_in_order_with_its_set_up_first(monkeypatch):
    clock = FakeClock()
    monkeypatch.setattr(timing.time, "perf_counter", clock)
    calls = []

    def work(name, seconds):
        def run():
            calls.append(name)
            clock.now += seconds

        return run

    entries = [("a", work("a", 0.010)), ("b", work("b", 0.030), lambda: calls.append("set b"))]
    times = timing.interleaved_rounds(entries, rounds=3, units=10)
    assert calls == ["a", "set b", "b"] * 3
    assert times.keys() == {"a", "b"}
    assert times["a"] == pytest.approx([1.0] * 3)  # 10 ms per run, 10 units: 1 ms per unit
    assert times["b"] == pytest.approx([3.0] * 3)
    assert timing.summary([3.0, 1.0, 2.0]) == (2.0, 1.0, 3.0)


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="rounds and units must be >= 1, got rounds=0"):
        timing.interleaved_rounds([("a", lambda: None)], rounds=0)
    with pytest.raises(ValueError, match="entry names must be distinct, got \\['a', 'a'\\]"):
        timing.interleaved_rounds([("a", lambda: None), ("a", lambda: None)], rounds=1)
