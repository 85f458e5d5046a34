"""Interleaved rounds: the timing loop the per-update benchmarks share.

This machine's speed drifts by a third within an hour, so timing one setting after another
compares the hours, not the settings. Instead every entry runs once per round, the rounds repeat,
and each entry's median over the rounds is compared: the drift falls on every entry alike.

    times = interleaved_rounds([("a", run_a), ("b", run_b)], rounds=5, units=10)
    summary(times["a"])  # (median, min, max) milliseconds per unit

Imported by ``dream_speed.py``, ``update_shapes.py`` and ``baseline_updates.py`` (run as
``python benchmarks/NAME.py``, which puts this folder on ``sys.path``).
"""

from __future__ import annotations

import statistics
import time
from typing import Callable, Dict, List, Optional, Sequence, Tuple

# (name, run) or (name, run, set_up): run() does ``units`` units of the timed work; set_up(), if
# given, runs untimed right before it in every round (e.g. switching a shared model's option).
Entry = Tuple  # Tuple[str, Callable[[], None]] | Tuple[str, Callable[[], None], Callable[[], None]]


def interleaved_rounds(entries: Sequence[Entry], rounds: int, units: int = 1) -> Dict[str, List[float]]:
    """Milliseconds per unit of each entry's ``run()`` in each of ``rounds`` rounds, every entry once per round,
    in the given order. ``units`` is how many units (updates, frames) one ``run()`` does."""
    if rounds < 1 or units < 1:
        raise ValueError(f"rounds and units must be >= 1, got rounds={rounds}, units={units}")
    names = [entry[0] for entry in entries]
    if len(set(names)) != len(names):
        raise ValueError(f"entry names must be distinct, got {names}")
    times: Dict[str, List[float]] = {name: [] for name in names}
    for _ in range(rounds):
        for name, run, *rest in entries:
            set_up: Optional[Callable[[], None]] = rest[0] if rest else None
            if set_up is not None:
                set_up()
            start = time.perf_counter()
            run()
            times[name].append((time.perf_counter() - start) / units * 1e3)
    return times


def summary(values: Sequence[float]) -> Tuple[float, float, float]:
    """(median, min, max) of one entry's times."""
    return statistics.median(values), min(values), max(values)
