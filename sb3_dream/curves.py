"""Read a learning curve the way the results record does: per window, first crossings.

Single greedy evaluations of a value-based agent swing (a 100-trial evaluation's 95% interval is
about ±0.2 on MetaCook), so the record in ``docs/results/`` describes a run by the mean and the
median of its evaluations over windows of env steps, by the first evaluation at or above a
return, and by how many evaluations in a window reach it. This module computes those numbers
from the runner's curve CSVs (finished ``*.csv``, stopped ``*_stopped_at_*.csv`` or a run still
going, ``*.csv.partial``), so that each one in the record can be reproduced::

    python -m sb3_dream.curves results/cook_wd_lr1e5/MetaCook-v0/dream_seed2.csv \\
        results/cook_256_c001_lr1e5/MetaCook-v0/dream_seed2.csv --window 100000 --threshold 0.3

A window ``(a, b]`` holds the evaluations after ``a`` env steps up to and including ``b`` (the
evaluation at 0 steps, before any training, counts in none), so "300K-400K" is the ten
evaluations at 310K, ..., 400K of a run evaluated every 10K steps.
"""

from __future__ import annotations

import argparse
import pathlib
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence

import numpy as np

from sb3_dream.experiments import load_curve


@dataclass(frozen=True)
class Window:
    """The evaluations of one curve with ``start < env_steps <= end``."""

    start: int
    end: int
    n: int
    mean: float
    median: float
    lowest: float
    reaching: int  # evaluations at or above the threshold


def windows(curve: Dict[str, np.ndarray], size: int, threshold: float) -> List[Window]:
    """The curve's windows of ``size`` env steps from 0 to its last evaluation (empty ones left out)."""
    if size <= 0:
        raise ValueError(f"window must be a positive number of env steps, got {size}")
    steps, returns = curve["env_steps"], curve["mean"]
    out = []
    for start in range(0, int(steps[-1]), size):
        inside = returns[(steps > start) & (steps <= start + size)]
        if inside.size:
            out.append(
                Window(
                    start=start,
                    end=start + size,
                    n=int(inside.size),
                    mean=float(inside.mean()),
                    median=float(np.median(inside)),
                    lowest=float(inside.min()),
                    reaching=int((inside >= threshold).sum()),
                )
            )
    return out


def first_reaching(curve: Dict[str, np.ndarray], threshold: float) -> Optional[Dict[str, float]]:
    """The first evaluation at or above ``threshold``: its env steps, wall-clock and return (None if none)."""
    hits = np.flatnonzero(curve["mean"] >= threshold)
    if not hits.size:
        return None
    i = int(hits[0])
    return {
        "env_steps": float(curve["env_steps"][i]),
        "wall_clock_s": float(curve["wall_clock_s"][i]),
        "mean": float(curve["mean"][i]),
    }


def _steps(n: float) -> str:
    """Env steps as the record writes them: 560K, 1.4M."""
    if n >= 1_000_000:
        return f"{n / 1_000_000:g}M"
    return f"{n / 1000:g}K" if n else "0"


def report(path: pathlib.Path, size: int, threshold: float) -> str:
    """The text ``python -m sb3_dream.curves`` prints for one curve."""
    curve = load_curve(path)
    last = len(curve["mean"]) - 1
    lines = [
        f"{path}: {last + 1} evaluations, last at {_steps(curve['env_steps'][last])} env steps "
        f"({curve['wall_clock_s'][last] / 60:.1f} min): {curve['mean'][last]:.3f}"
    ]
    first = first_reaching(curve, threshold)
    crossing = "none"
    if first:
        crossing = f"{_steps(first['env_steps'])} ({first['wall_clock_s'] / 60:.1f} min, {first['mean']:.3f})"
    lines.append(f"  first >= {threshold:g}: {crossing}")
    lines.append(f"  {'window':>12}  {'n':>3}  {'mean':>7}  {'median':>7}  {'lowest':>7}  >= {threshold:g}")
    for w in windows(curve, size, threshold):
        span = f"{_steps(w.start)}-{_steps(w.end)}"
        numbers = f"{w.n:>3}  {w.mean:>7.3f}  {w.median:>7.3f}  {w.lowest:>7.3f}"
        lines.append(f"  {span:>12}  {numbers}  {w.reaching} of {w.n}")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("curves", nargs="+", type=pathlib.Path, help="learning-curve CSVs written by the runner")
    parser.add_argument("--window", type=int, default=100_000, help="env steps per window (default 100000)")
    parser.add_argument("--threshold", type=float, default=0.75, help="the return to count and to find first")
    args = parser.parse_args(argv)
    try:
        print("\n\n".join(report(path, args.window, args.threshold) for path in args.curves))
    except (OSError, ValueError, KeyError) as error:
        raise SystemExit(f"error: {error}")


if __name__ == "__main__":
    main()
