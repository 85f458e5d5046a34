"""Time to a held-out return: the wall-clock (and env steps) a setting takes to solve a trial env.

Runs the experiment runner's grid (resumable: finished runs are skipped; every flag but the three
below is the runner's, see ``python -m sb3_dream.experiments --help``), then reads each finished
run's held-out curve: the first evaluation at or above ``--threshold``, in env steps and minutes
of the run's wall-clock (evaluations included), and whether that came within ``--minutes``; then
the same for the mean over seeds at each evaluation step.

    python benchmarks/time_to_solve.py --envs MetaBus-v0:variant=map --algos dream --seeds 0 1 2 \\
        --steps 200000 --preset fast --threshold 0.78 --minutes 8 --out results/time_to_solve_map
    python benchmarks/time_to_solve.py --report-only --out results/time_to_solve_map --threshold 0.78

Measure settings side by side with one ``--out`` each, alone on the machine (``--jobs 1``), so
that the minutes compare; the curves' wall-clock is each run's own.
"""

from __future__ import annotations

import argparse
import pathlib
from collections import defaultdict
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from sb3_dream import experiments
from sb3_dream.curves import first_reaching

Key = Tuple[str, str]  # (env folder, algorithm)


def held_out_curves(out: pathlib.Path) -> Dict[Key, Dict[int, Dict[str, np.ndarray]]]:
    """The held-out curve of every finished run under ``out``, by (env folder, algorithm) and seed."""
    curves: Dict[Key, Dict[int, Dict[str, np.ndarray]]] = defaultdict(dict)
    for run in experiments.finished_runs(out):
        path = run.curve_path(out, "test")
        if path.exists():
            curves[(run.env.tag, run.algo)][run.seed] = experiments.load_curve(path)
    return curves


def mean_over_seeds(by_seed: Dict[int, Dict[str, np.ndarray]]) -> Dict[str, np.ndarray]:
    """The seeds' mean return at each evaluation step they all reached, and the slowest seed's
    wall-clock there (the time at which every seed had got that far)."""
    steps = sorted(set.intersection(*(set(c["env_steps"].tolist()) for c in by_seed.values())))
    rows = [[np.flatnonzero(c["env_steps"] == s)[0] for s in steps] for c in by_seed.values()]
    means = np.mean([c["mean"][r] for c, r in zip(by_seed.values(), rows)], axis=0)
    clocks = np.max([c["wall_clock_s"][r] for c, r in zip(by_seed.values(), rows)], axis=0)
    return {"env_steps": np.asarray(steps, dtype=float), "wall_clock_s": clocks, "mean": means}


def _line(label: str, curve: Dict[str, np.ndarray], threshold: float, minutes: Optional[float]) -> str:
    first = first_reaching(curve, threshold)
    last = f"last {curve['mean'][-1]:.3f} at {curve['env_steps'][-1] / 1000:g}K"
    if first is None:
        return f"  {label:<14} not reached ({last}, {curve['wall_clock_s'][-1] / 60:.1f} min)"
    took = first["wall_clock_s"] / 60
    verdict = "" if minutes is None else ("  within budget" if took <= minutes else "  OVER budget")
    return (
        f"  {label:<14} {first['mean']:.3f} at {first['env_steps'] / 1000:g}K env steps, "
        f"{took:.1f} min ({last}){verdict}"
    )


def report(out: pathlib.Path, threshold: float, minutes: Optional[float]) -> str:
    """Per (env, algorithm): each seed's first evaluation at or above ``threshold``, then the mean's."""
    curves = held_out_curves(out)
    if not curves:
        raise ValueError(f"{out} holds no finished run")
    budget = "" if minutes is None else f", budget {minutes:g} min"
    lines: List[str] = []
    for (env, algo), by_seed in sorted(curves.items()):
        lines.append(f"{env} {algo}: first held-out evaluation >= {threshold:g}{budget}")
        for seed, curve in sorted(by_seed.items()):
            lines.append(_line(f"seed {seed}", curve, threshold, minutes))
        if len(by_seed) > 1:
            lines.append(_line(f"mean of {len(by_seed)}", mean_over_seeds(by_seed), threshold, minutes))
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threshold", type=float, required=True, help="the held-out return that counts as solved")
    parser.add_argument("--minutes", type=float, default=None, help="the wall-clock budget a run should solve in")
    parser.add_argument("--report-only", action="store_true", help="read the runs under --out, train nothing")
    parser.add_argument("--out", type=pathlib.Path, required=True, help="the runner's --out")
    args, runner_args = parser.parse_known_args(argv)
    if not args.report_only:
        experiments.main([*runner_args, "--out", str(args.out), "--no-plot"])
    elif runner_args:
        parser.error(f"--report-only reads --out only; unused: {' '.join(runner_args)}")
    try:
        print(report(args.out, args.threshold, args.minutes))
    except (OSError, ValueError) as error:
        raise SystemExit(f"error: {error}")


if __name__ == "__main__":
    main()
