"""``python -m dream_envs``: play the optimal scripted agent and a random agent on every env.

Prints, per env and split, the mean execution return (with a 95% confidence half-width) of each agent
and the oracle's exploration-episode length; an env that cannot be built here (SignNav3D-v0 without
OpenGL) is listed as unavailable, with the reason. Example::

    python -m dream_envs --trials 100
    python -m dream_envs --env MetaCook-v0 --split test --trials 200
"""

from __future__ import annotations

import argparse
import time
from typing import Optional

import gymnasium as gym
import numpy as np

import dream_envs
from dream_envs import RandomAgent, play_trial
from dream_envs.sign_nav import opengl_available

# Env IDs with the constructor kwargs of each variant worth listing.
DEFAULT_VARIANTS = [
    ("MetaBus-v0", {}),
    ("MetaBus-v0", {"variant": "map"}),
    ("MetaCook-v0", {}),
    ("SignNav3D-v0", {}),
    ("MetaBandit-v0", {}),
]


def unavailable(env_id: str) -> Optional[str]:
    """Why ``env_id`` cannot be built on this machine, or None if it can."""
    if env_id == "SignNav3D-v0":
        available, reason = opengl_available()
        return None if available else reason
    return None


def mean_ci(values: list[float]) -> tuple[float, float]:
    arr = np.asarray(values, dtype=np.float64)
    half = 1.96 * arr.std(ddof=1) / np.sqrt(len(arr)) if len(arr) > 1 else 0.0
    return float(arr.mean()), float(half)


def evaluate(env_id: str, kwargs: dict, split: str, trials: int, seed: int) -> dict:
    env = gym.make(env_id, split=split, **kwargs)
    oracle, random = dream_envs.make_oracle(env), RandomAgent(env.action_space, seed=seed)
    start = time.perf_counter()
    best = [play_trial(env, oracle, seed=seed + k) for k in range(trials)]
    rand = [play_trial(env, random, seed=seed + k) for k in range(trials)]
    env.close()
    return {
        "oracle": mean_ci([np.mean(r["execution_returns"]) for r in best]),
        "random": mean_ci([np.mean(r["execution_returns"]) for r in rand]),
        "explore_len": float(np.mean([r["exploration_length"] for r in best])),
        "seconds": time.perf_counter() - start,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", choices=list(dream_envs.ENV_IDS), help="only this env (default: all)")
    parser.add_argument(
        "--split", default="test", choices=dream_envs.all_splits(), help="envs without this split are skipped"
    )
    parser.add_argument("--trials", type=int, default=50, help="trials per agent (default 50)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.trials < 1:
        parser.error("--trials must be >= 1")

    rows = [(e, kw) for e, kw in DEFAULT_VARIANTS if args.env in (None, e) and args.split in dream_envs.env_splits(e)]
    if not rows:
        offered = ", ".join(dream_envs.env_splits(args.env))
        parser.error(f"--split {args.split} is not a split of {args.env}; accepted values: {offered}")
    print(f"{'env':<28}{'split':<18}{'oracle return':>18}{'random return':>18}{'oracle explore len':>20}")
    for env_id, kwargs in rows:
        name = env_id + "".join(f" {k}={v}" for k, v in kwargs.items())
        reason = unavailable(env_id)
        if reason is not None:
            print(f"{name:<28}{args.split:<18}unavailable: {reason}")
            continue
        r = evaluate(env_id, kwargs, args.split, args.trials, args.seed)
        (om, oh), (rm, rh) = r["oracle"], r["random"]
        print(f"{name:<28}{args.split:<18}{om:>11.3f} ±{oh:5.3f}{rm:>11.3f} ±{rh:5.3f}{r['explore_len']:>20.1f}")


if __name__ == "__main__":
    main()
