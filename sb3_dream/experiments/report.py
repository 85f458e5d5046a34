"""Reports of an experiment: its finished runs, the oracle's return, PEARL-UB, the summary table,
the figure (each file replaced atomically)."""

from __future__ import annotations

import csv
import functools
import json
import pathlib
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from dream_envs import all_splits
from sb3_dream.common.files import atomic_target
from sb3_dream.evaluation import CURVE_COLUMNS
from sb3_dream.experiments.algorithms import ALGORITHMS, REWARDED_EXPLORATION_PREFIX
from sb3_dream.experiments.config import EnvSpec, Run, RunConfig


def finished_runs(out: pathlib.Path) -> List[Run]:
    """Every finished run under ``out``, whichever command made it, from the runs' JSON records
    (sorted by env folder, algorithm and seed)."""
    found = []
    for path in sorted(pathlib.Path(out).glob("*/*.json")):
        try:
            info = json.loads(path.read_text())
            # JSON turned tuples into lists; EnvSpec must stay hashable.
            kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in info["env_kwargs"].items()}
            run = Run(info["algo"], EnvSpec(info["env"], tuple(sorted(kwargs.items()))), int(info["seed"]))
        except (ValueError, KeyError, TypeError, AttributeError):
            continue  # not a run's record (an oracle's, say)
        if run.info_path(out) == path and any(run.curve_path(out, split).exists() for split in all_splits()):
            found.append(run)
    return sorted(found, key=_report_order)


def _report_order(run: Run) -> Tuple[str, int, int]:
    """Runs sort by env folder, then in the order the algorithms are registered, then by seed."""
    order = list(ALGORITHMS)
    return run.env.tag, order.index(run.algo) if run.algo in order else len(order), run.seed


def with_finished_runs(runs: Sequence[Run], out: pathlib.Path) -> List[Run]:
    """``runs`` followed by the other finished runs under ``out`` (one per set of files)."""
    merged: Dict[Tuple[str, str, int], Run] = {}
    for run in [*runs, *finished_runs(out)]:
        merged.setdefault((run.env.tag, run.algo, run.seed), run)
    return list(merged.values())


def parse_folder_spec(spec: str) -> Tuple[pathlib.Path, Tuple[str, ...]]:
    """``"DIR"`` or ``"DIR:ALGO,ALGO"`` -> ``(DIR, algorithms)`` (empty: every algorithm)."""
    folder, colon, names = spec.partition(":")
    algos = tuple(a for a in names.split(",") if a)
    if not folder or (colon and not algos):
        raise ValueError(f"--also takes DIR or DIR:ALGO[,ALGO...], got {spec!r}")
    if not pathlib.Path(folder).is_dir():
        raise ValueError(f"--also {spec!r}: no such folder {folder!r}")
    unknown = [a for a in algos if a not in ALGORITHMS]
    if unknown:
        raise ValueError(f"--also {spec!r}: unknown algorithm {unknown[0]!r}; known: {', '.join(ALGORITHMS)}")
    return pathlib.Path(folder), algos


def report_folders(
    runs: Sequence[Run], out: pathlib.Path, also: Sequence[Tuple[pathlib.Path, Sequence[str]]] = ()
) -> Dict[Run, pathlib.Path]:
    """The runs a report covers, each with the folder its files are under: ``runs`` and the other
    finished runs under ``out`` (:func:`with_finished_runs`), and the finished runs under each
    ``(folder, algorithms)`` of ``also`` (every algorithm's where none is named), so that one
    figure compares runs made into several folders (e.g. DREAM's long runs beside the baselines');
    sorted as :func:`finished_runs` sorts them.

    A run asked for but absent from ``out`` is taken from the folder that has it; a run (env,
    algorithm, seed) finished in two folders is an error naming both: name the algorithms to take
    from each folder with ``DIR:ALGO``."""
    folders: Dict[Tuple[str, str, int], Tuple[Run, pathlib.Path]] = {}
    for run in with_finished_runs(runs, out):
        folders[(run.env.tag, run.algo, run.seed)] = (run, pathlib.Path(out))
    for folder, algos in also:
        if not pathlib.Path(folder).is_dir():
            raise FileNotFoundError(f"no such folder: {folder}")
        for run in finished_runs(folder):
            if algos and run.algo not in algos:
                continue
            key = (run.env.tag, run.algo, run.seed)
            if key in folders and _has_curve(*folders[key]):
                raise ValueError(
                    f"{run.algo} seed {run.seed} on {run.env.label} is finished under both {folders[key][1]} and "
                    f"{folder}: name the algorithms to take from each with DIR:ALGO"
                )
            folders[key] = (run, pathlib.Path(folder))
    return dict(sorted(folders.values(), key=lambda item: _report_order(item[0])))


def _has_curve(run: Run, folder: pathlib.Path) -> bool:
    return any(run.curve_path(folder, split).exists() for split in all_splits())


def load_curve(path: pathlib.Path) -> Dict[str, np.ndarray]:
    """A learning-curve CSV as arrays, one per column."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{path} holds no evaluation")
    return {k: np.array([float(r[k]) for r in rows]) for k in CURVE_COLUMNS}


def oracle_return(
    env: EnvSpec, split: str, n_trials: int, out: pathlib.Path, exhaustive: bool = False
) -> Optional[float]:
    """Mean execution return of the env's scripted optimal agent on ``split`` (cached as JSON;
    ``exhaustive``: over every (problem, instruction) pair, see :func:`evaluate_meta`)."""
    import gymnasium as gym

    import dream_envs
    from sb3_dream.evaluation import evaluate_meta

    path = out / env.tag / f"oracle_{split}{'_exhaustive' if exhaustive else ''}.json"
    if path.exists():
        return float(json.loads(path.read_text())["mean"])
    try:
        made = gym.make(env.env_id, split=split, n_exec_episodes=env.n_exec_episodes, **env.eval_kwargs)
        result = evaluate_meta(
            dream_envs.make_oracle(made),
            made,
            n_trials=n_trials,
            split=split,
            n_exec_episodes=env.n_exec_episodes,
            exhaustive=exhaustive,
        )
        made.close()
    except (AttributeError, NotImplementedError):  # an env without an oracle
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"mean": result.mean, "ci": result.ci, "n_trials": result.n_trials}
    with atomic_target(path, "json") as tmp:
        tmp.write_text(json.dumps({**record, "exhaustive": True} if exhaustive else record))
    return result.mean


def pearl_ub_return(env: EnvSpec, split: str, rewarded_exploration: Optional[bool] = None) -> Optional[float]:
    """PEARL-UB (:func:`dream_envs.pearl_ub`) of ``env`` on ``split``, in the env entry's
    exploration setting or (``rewarded_exploration`` True or False) the one given; None for an env
    it does not know or cannot make here (SignNav3D without OpenGL). Exact and quick to compute;
    kept for the process."""
    return _pearl_ub_cached(env, split, rewarded_exploration)


@functools.lru_cache(maxsize=None)
def _pearl_ub_cached(env: EnvSpec, split: str, rewarded_exploration: Optional[bool]) -> Optional[float]:
    import gymnasium as gym

    from dream_envs.pearl_ub import pearl_ub, supports

    try:
        made = gym.make(env.env_id, split=split, **env.eval_kwargs)
    except Exception:  # noqa: BLE001 - an env that cannot be made here has no line, the report goes on
        return None
    try:
        return pearl_ub(made, split, rewarded_exploration) if supports(made) else None
    except (TypeError, ValueError):  # e.g. a horizon too short for the derivation
        return None
    finally:
        made.close()


def _rewarded(algo: str) -> bool:
    """Whether ``algo`` explores with an instruction and rewards (an ``e_`` variant); judged from its
    registered spec, else from its name (a finished run's record of a variant not registered here)."""
    spec = ALGORITHMS.get(algo)
    return spec.rewarded_exploration if spec is not None else algo.startswith(REWARDED_EXPLORATION_PREFIX)


def _base_algo(algo: str) -> str:
    """The algorithm ``algo`` is a variant of (itself if none): both are drawn in one colour."""
    spec = ALGORITHMS.get(algo)
    if spec is not None:
        return spec.variant_of or algo
    return algo[len(REWARDED_EXPLORATION_PREFIX) :] if algo.startswith(REWARDED_EXPLORATION_PREFIX) else algo


def summarize(
    runs: Sequence[Run],
    config: RunConfig,
    out: pathlib.Path,
    oracles: Optional[Dict[Tuple[str, str], float]] = None,
    pearl_ub: bool = True,
    folders: Optional[Dict[Run, pathlib.Path]] = None,
) -> List[Dict[str, Any]]:
    """One row per (env, algo, split): the final return's mean and std over the finished seeds
    (numpy's std, ddof=0, as the figures' bands), the final env steps and the mean wall-clock,
    and (``pearl_ub``, where :func:`dream_envs.pearl_ub` knows the env) PEARL-UB in the
    algorithm's exploration setting (rewarded for the ``e_`` variants).

    ``last_tenth_mean`` averages each seed's evaluations over the last tenth of its env steps, then
    the seeds: single greedy evaluations of a value-based agent swing, and one of them can
    misrepresent where a run ended.

    Each run's files are under ``out``, or under ``folders[run]`` where given
    (:func:`report_folders`)."""
    rows = []
    groups: Dict[Tuple[EnvSpec, str], List[Run]] = {}
    for run in runs:
        groups.setdefault((run.env, run.algo), []).append(run)
    for (env, algo), group in groups.items():
        for split in config.eval_splits:
            curves = _curves(group, split, out, folders)
            row: Dict[str, Any] = {"env": env.label, "algo": algo, "split": split, "seeds": len(curves)}
            if curves:
                finals = np.array([c["mean"][-1] for c in curves])
                last_tenth = [c["mean"][c["env_steps"] >= 0.9 * c["env_steps"][-1]].mean() for c in curves]
                row.update(
                    final_return_mean=float(finals.mean()),
                    final_return_std=float(finals.std()),
                    last_tenth_mean=float(np.mean(last_tenth)),
                    env_steps=int(np.mean([c["env_steps"][-1] for c in curves])),
                    wall_clock_s=float(np.mean([c["wall_clock_s"][-1] for c in curves])),
                )
            if oracles and (env.tag, split) in oracles:
                row["oracle_return"] = oracles[(env.tag, split)]
            if pearl_ub:
                value = pearl_ub_return(env, split, True if _rewarded(algo) else None)
                if value is not None:
                    row["pearl_ub"] = value  # in the algorithm's exploration setting
            rows.append(row)
    return rows


def _curves(
    runs: Sequence[Run], split: str, out: pathlib.Path, folders: Optional[Dict[Run, pathlib.Path]]
) -> List[Dict[str, np.ndarray]]:
    """The ``split`` curves of those of ``runs`` that have one (under ``folders[run]`` or ``out``)."""
    paths = [run.curve_path((folders or {}).get(run, out), split) for run in runs]
    return [load_curve(path) for path in paths if path.exists()]


SUMMARY_COLUMNS = (
    "env",
    "algo",
    "split",
    "seeds",
    "final_return_mean",
    "final_return_std",
    "last_tenth_mean",
    "env_steps",
    "wall_clock_s",
    "oracle_return",
    "pearl_ub",
)


def write_summary(rows: Sequence[Dict[str, Any]], out: pathlib.Path) -> str:
    """Write ``summary.csv`` and ``summary.md`` under ``out``; return the markdown table."""
    with atomic_target(out / "summary.csv", "csv") as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=SUMMARY_COLUMNS)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: row.get(k, "") for k in SUMMARY_COLUMNS})
    lines = [
        "| env | algo | split | seeds | final return (mean ± std) | mean over the last tenth | optimal | PEARL-UB "
        "| env steps | wall-clock |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        ret = f"{row['final_return_mean']:.3f} ± {row['final_return_std']:.3f}" if row["seeds"] else "-"
        last_tenth = f"{row['last_tenth_mean']:.3f}" if row["seeds"] else "-"
        optimal = f"{row['oracle_return']:.3f}" if "oracle_return" in row else "-"
        pearl = f"{row['pearl_ub']:.3f}" if "pearl_ub" in row else "-"
        steps = f"{row['env_steps']:,}" if row["seeds"] else "-"
        clock = _format_seconds(row["wall_clock_s"]) if row["seeds"] else "-"
        cells = [row["env"], row["algo"], row["split"], str(row["seeds"]), ret, last_tenth, optimal, pearl]
        cells += [steps, clock]
        lines.append("| " + " | ".join(cells) + " |")
    table = "\n".join(lines) + "\n"
    with atomic_target(out / "summary.md", "md") as tmp:
        tmp.write_text(table)
    return table


def _format_seconds(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


def plot_curves(
    runs: Sequence[Run],
    config: RunConfig,
    out: pathlib.Path,
    oracles: Optional[Dict[Tuple[str, str], float]] = None,
    pearl_ub: bool = True,
    folders: Optional[Dict[Run, pathlib.Path]] = None,
) -> pathlib.Path:
    """``curves.png``: execution return vs env steps, mean +- std over seeds, one panel per env and
    split (the paper's Figures 5 and 6): the optimal return as a thin black line, and (``pearl_ub``,
    where :func:`dream_envs.pearl_ub` knows the env) PEARL-UB of the panel's split as a gray dotted
    line. As in the paper, the rewarded-exploration variants (``e_rl2dqn``: E-RL²) are dashed, in
    their algorithm's colour; a panel with one also gets PEARL-UB with rewarded exploration,
    dash-dotted, where it differs. The runs' files are found as :func:`summarize` finds them; the
    figure is written under ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    envs = list(dict.fromkeys(run.env for run in runs))
    algos = list(dict.fromkeys(run.algo for run in runs))
    bases = list(dict.fromkeys(_base_algo(algo) for algo in algos))
    panels = [(env, split) for env in envs for split in config.eval_splits]
    n_cols = min(len(panels), 3)
    n_rows = -(-len(panels) // n_cols)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(5 * n_cols, 3.6 * n_rows), squeeze=False)
    for ax, (env, split) in zip(axes.flat, panels):
        for algo in algos:
            curves = _curves([r for r in runs if r.env == env and r.algo == algo], split, out, folders)
            if not curves:
                continue
            n = min(len(c["mean"]) for c in curves)
            steps = curves[0]["env_steps"][:n]
            values = np.stack([c["mean"][:n] for c in curves])
            mean, std = values.mean(axis=0), values.std(axis=0)
            color = f"C{bases.index(_base_algo(algo))}"
            ax.plot(
                steps,
                mean,
                color=color,
                ls="--" if _rewarded(algo) else "-",
                label=f"{algo} ({len(curves)} seed{'s' if len(curves) > 1 else ''})",
            )
            ax.fill_between(steps, mean - std, mean + std, color=color, alpha=0.2, linewidth=0)
        if oracles and (env.tag, split) in oracles:
            ax.axhline(oracles[(env.tag, split)], color="k", ls="-", lw=0.8, label="optimal")
        if pearl_ub:
            _draw_pearl_ub(ax, env, split, any(_rewarded(r.algo) for r in runs if r.env == env))
        ax.set_title(f"{env.label}" + ("" if split == "test" else f", {split} split"))
        ax.set_xlabel("env steps")
        ax.set_ylabel("execution return" + (" (held-out)" if split == "test" else ""))
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="best", fontsize="small")
        else:
            ax.text(0.5, 0.5, "no finished run", ha="center", va="center", transform=ax.transAxes)
    for ax in list(axes.flat)[len(panels):]:  # fmt: skip
        ax.axis("off")
    fig.tight_layout()
    path = out / "curves.png"
    with atomic_target(path, "png") as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
    return path


def _draw_pearl_ub(ax: Any, env: EnvSpec, split: str, rewarded_runs: bool) -> None:
    """PEARL-UB of ``env`` on ``split`` as horizontal lines: reward-free exploration (dotted), and
    with ``rewarded_runs`` the rewarded-exploration value (dash-dotted) where it differs."""
    value = pearl_ub_return(env, split)
    if value is not None:
        ax.axhline(value, color="gray", ls=":", lw=1.2, label="PEARL-UB")
    if rewarded_runs:
        rewarded = pearl_ub_return(env, split, rewarded_exploration=True)
        if rewarded is not None and (value is None or not np.isclose(rewarded, value)):
            ax.axhline(rewarded, color="gray", ls="-.", lw=1.2, label="PEARL-UB (rewarded exploration)")
