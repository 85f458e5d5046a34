"""Steps per second of each trial env alone and under ``make_vec_env(n_envs=8)`` (random actions).

python benchmarks/env_speed.py [--steps 20000] [--n-envs 8] [--env MetaBus-v0]
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

import dream_envs


def single_env_sps(env_id: str, steps: int) -> float:
    env = gym.make(env_id)
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    start = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
        if terminated or truncated:
            env.reset()
    sps = steps / (time.perf_counter() - start)
    env.close()
    return sps


def vec_env_sps(env_id: str, steps: int, n_envs: int, vec_env_cls) -> float:
    vec = make_vec_env(f"dream_envs:{env_id}", n_envs=n_envs, seed=0, vec_env_cls=vec_env_cls)
    rng = np.random.default_rng(0)
    vec.reset()
    n_calls = max(1, steps // n_envs)
    start = time.perf_counter()
    for _ in range(n_calls):
        vec.step(rng.integers(vec.action_space.n, size=n_envs))
    sps = n_calls * n_envs / (time.perf_counter() - start)
    vec.close()
    return sps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=20000, help="env steps per measurement (3D env: a tenth)")
    parser.add_argument("--n-envs", type=int, default=8)
    parser.add_argument("--env", choices=list(dream_envs.ENV_IDS), help="only this env (default: all)")
    args = parser.parse_args()
    dummy, subproc = f"Dummy x{args.n_envs}", f"Subproc x{args.n_envs}"
    print(f"{'env':<16}{'single':>12}{dummy:>14}{subproc:>16}  (env steps/s)")
    for env_id in dream_envs.ENV_IDS:
        if args.env not in (None, env_id):
            continue
        steps = args.steps // 10 if env_id == "SignNav3D-v0" else args.steps
        single = single_env_sps(env_id, steps)
        dummy = vec_env_sps(env_id, steps, args.n_envs, DummyVecEnv)
        subproc = vec_env_sps(env_id, steps, args.n_envs, SubprocVecEnv)
        print(f"{env_id:<16}{single:>12.0f}{dummy:>14.0f}{subproc:>16.0f}")


if __name__ == "__main__":
    main()
