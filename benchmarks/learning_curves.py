"""Learning curves of DREAM, DREAM (no bottleneck) and RL² on a trial env, like the paper's Figure 5.

Each (algorithm, seed) run trains for ``--steps`` env steps and evaluates on the held-out split
every ``--eval-freq`` steps (``--eval-trials`` meta-test trials, greedy). Writes one CSV per run
(``env_steps, wall_clock_s, mean, ci, exploration_length``) under ``--out`` and, with
``--plot``, a figure of mean +- std over seeds.

    python benchmarks/learning_curves.py --env MetaBus-v0 --variant map --algos dream rl2dqn \\
        --seeds 0 1 2 --steps 100000 --preset fast --out results/metabus_map --plot
"""

from __future__ import annotations

import argparse
import csv
import pathlib
import time
from typing import Dict, List

import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_dream import DREAM
from sb3_dream.dream.presets import PRESETS
from sb3_dream.evaluation import MetaEvalCallback

ALGOS = ("dream", "dream_no_bottleneck", "rl2dqn")


def make_model(algo: str, env, preset: str, seed: int):
    if algo in ("dream", "dream_no_bottleneck"):
        return DREAM(env, seed=seed, bottleneck=algo == "dream", **PRESETS[preset])
    from sb3_dream.rl2dqn import RL2DQN

    kwargs = {} if preset == "paper" else dict(learning_starts=2000, exploration_steps=50_000, target_update_interval=1000)
    return RL2DQN(env, seed=seed, **kwargs)


def run(args: argparse.Namespace, algo: str, seed: int, out: pathlib.Path) -> pathlib.Path:
    path = out / f"{algo}_seed{seed}.csv"
    if path.exists() and args.resume:
        print(f"skip {path} (exists)")
        return path
    env_kwargs = {"variant": args.variant} if args.variant else {}
    env = make_vec_env(args.env, n_envs=args.n_envs, seed=seed, env_kwargs=env_kwargs)
    model = make_model(algo, env, args.preset, seed)
    tmp = path.with_suffix(".partial")
    tmp.unlink(missing_ok=True)
    callback = MetaEvalCallback(
        args.env, eval_freq=args.eval_freq, n_trials=args.eval_trials, split="test", env_kwargs=env_kwargs, csv_path=str(tmp)
    )
    start = time.perf_counter()
    model.learn(args.steps, callback=callback)
    tmp.replace(path)  # a run counts as done only once complete
    print(f"{algo} seed {seed}: {time.perf_counter() - start:.0f}s, final return {callback.results[-1]['mean']:.3f}")
    return path


def load_curve(path: pathlib.Path) -> Dict[str, np.ndarray]:
    with open(path) as f:
        rows = list(csv.DictReader(f))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}


def plot(out: pathlib.Path, algos: List[str], seeds: List[int], title: str, optimal: float | None) -> pathlib.Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for algo in algos:
        curves = [load_curve(out / f"{algo}_seed{s}.csv") for s in seeds if (out / f"{algo}_seed{s}.csv").exists()]
        if not curves:
            continue
        n = min(len(c["mean"]) for c in curves)
        steps = curves[0]["env_steps"][:n]
        values = np.stack([c["mean"][:n] for c in curves])
        mean, std = values.mean(0), values.std(0)
        ax.plot(steps, mean, label=f"{algo} ({len(curves)} seeds)")
        ax.fill_between(steps, mean - std, mean + std, alpha=0.2)
    if optimal is not None:
        ax.axhline(optimal, color="k", ls="--", lw=1, label="optimal")
    ax.set_xlabel("env steps")
    ax.set_ylabel("held-out execution return")
    ax.set_title(title)
    ax.legend(loc="lower right")
    fig.tight_layout()
    path = out / "curves.png"
    fig.savefig(path, dpi=120)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MetaBus-v0")
    parser.add_argument("--variant", default=None)
    parser.add_argument("--algos", nargs="+", default=["dream"], choices=ALGOS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--steps", type=int, default=100_000)
    parser.add_argument("--n-envs", type=int, default=1)
    parser.add_argument("--preset", default="paper", choices=sorted(PRESETS))
    parser.add_argument("--eval-freq", type=int, default=10_000)
    parser.add_argument("--eval-trials", type=int, default=100)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--out", default="results/curves")
    parser.add_argument("--resume", action="store_true", help="skip runs whose CSV exists")
    parser.add_argument("--plot", action="store_true")
    parser.add_argument("--optimal", type=float, default=None, help="draw the optimal return")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for algo in args.algos:
        for seed in args.seeds:
            run(args, algo, seed, out)
    if args.plot:
        title = f"{args.env}" + (f" ({args.variant})" if args.variant else "")
        print("wrote", plot(out, args.algos, args.seeds, title, args.optimal))


if __name__ == "__main__":
    main()
