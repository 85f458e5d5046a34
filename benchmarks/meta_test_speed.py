"""Seconds per meta-test evaluation (``evaluate_meta``) with trials one at a time and side by side.

    python benchmarks/meta_test_speed.py [--env MetaCook-v0] [--trials 100] [--n-envs 1 4 16 100]
        [--algo dream|rl2dqn] [--model PATH] [--repeats 3] [--diagnose]

Without ``--model`` it times a freshly made model of ``--algo`` (its policies run every trial
to the horizons, the longest trials); with one, that model. Each setting is timed ``--repeats``
times in turn; the best time is printed, with the check that every setting played the same
trials (the same returns). ``--diagnose`` times :func:`sb3_dream.dream.diagnose` (DREAM: the
same trials three or four times, with z = g, z = f(T), noisy f(T) and the oracle's exploration)
and checks that every setting gives the same diagnosis.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch as th

import dream_envs  # noqa: F401  (registers the envs)
from sb3_dream import DREAM, RL2DQN, evaluate_meta
from sb3_dream.dream import diagnose


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
    parser.add_argument("--diagnose", action="store_true", help="time diagnose() instead (--algo dream)")
    args = parser.parse_args()
    if args.diagnose and args.algo != "dream":
        parser.error("--diagnose needs --algo dream")
    th.set_num_threads(args.threads)

    cls = {"dream": DREAM, "rl2dqn": RL2DQN}[args.algo]
    model = cls.load(args.model) if args.model else cls(args.env, seed=0)
    best = {n: np.inf for n in args.n_envs}
    returns = {}
    for _ in range(args.repeats):
        for n in args.n_envs:
            start = time.perf_counter()
            if args.diagnose:
                d = diagnose(model, args.env, n_trials=args.trials, split=args.split, n_envs=n)
                returns[n] = np.array([v for v in d.as_dict().values() if isinstance(v, float)])
            else:
                returns[n] = evaluate_meta(model, args.env, n_trials=args.trials, split=args.split, n_envs=n).returns
            best[n] = min(best[n], time.perf_counter() - start)
    what = "diagnose" if args.diagnose else "meta-test"
    print(f"{args.algo} {what} on {args.env} ({args.split}), {args.trials} trials, best of {args.repeats}:")
    for n in args.n_envs:
        first = returns[args.n_envs[0]]
        # the diagnosis holds batched decoder codes (rounding); the returns of the trials are exact
        if args.diagnose:
            same = np.allclose(returns[n], first, rtol=1e-5, atol=1e-6)
        else:
            same = np.array_equal(returns[n], first)
        print(
            f"  n_envs {n:4d}: {best[n]:6.2f} s  ({best[args.n_envs[0]] / best[n]:4.1f}x n_envs {args.n_envs[0]}), "
            f"mean return {returns[n][0] if args.diagnose else returns[n].mean():.3f}, "
            f"same {'diagnosis' if args.diagnose else 'trials'} as n_envs {args.n_envs[0]}: {same}"
        )


if __name__ == "__main__":
    main()
