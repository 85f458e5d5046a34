"""Seconds per meta-test evaluation (``evaluate_meta``) with trials one at a time and side by side.

    python benchmarks/meta_test_speed.py [--env MetaCook-v0] [--trials 100] [--n-envs 1 4 16 100]
        [--algo dream|rl2dqn] [--model PATH] [--repeats 3]

Without ``--model`` it times a freshly made model of ``--algo`` (its policies run every trial
to the horizons, the longest trials); with one, that model. Each setting is timed ``--repeats``
times in turn; the best time is printed, with the check that every setting played the same
trials (the same returns).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch as th

import dream_envs  # noqa: F401  (registers the envs)
from sb3_dream import DREAM, RL2DQN, evaluate_meta


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MetaCook-v0")
    parser.add_argument("--split", default="test")
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--n-envs", type=int, nargs="+", default=[1, 4, 16, 100])
    parser.add_argument("--algo", choices=("dream", "rl2dqn"), default="dream")
    parser.add_argument("--model", help="a saved model of --algo to time instead of a fresh one")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    th.set_num_threads(args.threads)

    cls = {"dream": DREAM, "rl2dqn": RL2DQN}[args.algo]
    model = cls.load(args.model) if args.model else cls(args.env, seed=0)
    best = {n: np.inf for n in args.n_envs}
    returns = {}
    for _ in range(args.repeats):
        for n in args.n_envs:
            start = time.perf_counter()
            result = evaluate_meta(model, args.env, n_trials=args.trials, split=args.split, n_envs=n)
            best[n] = min(best[n], time.perf_counter() - start)
            returns[n] = result.returns
    print(f"{args.algo} on {args.env} ({args.split}), {args.trials} trials, best of {args.repeats}:")
    for n in args.n_envs:
        same = np.array_equal(returns[n], returns[args.n_envs[0]])
        print(
            f"  n_envs {n:4d}: {best[n]:6.2f} s  ({best[args.n_envs[0]] / best[n]:4.1f}x n_envs {args.n_envs[0]}), "
            f"mean return {returns[n].mean():.3f}, same trials as n_envs {args.n_envs[0]}: {same}"
        )


if __name__ == "__main__":
    main()
