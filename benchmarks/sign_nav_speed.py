"""Steps per second of SignNav3D-v0 alone (uniformly random actions, no learning).

Usage: ``python benchmarks/sign_nav_speed.py [--steps 3000] [--seed 0] [--trials 20]``

With ``--trials N`` (default 20, 0 to skip) it also prints the mean execution return of the env's
oracle and of a uniformly random agent over N trials.

Every step renders the agent's 80x60 view with OpenGL (Miniworld); off-screen through Mesa's EGL
on a headless machine, so the number mostly measures the software rasteriser of that machine.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np

import dream_envs  # registers SignNav3D-v0
from dream_envs import RandomAgent, play_trial


def measure(steps: int, seed: int) -> dict:
    start = time.perf_counter()
    env = gym.make("SignNav3D-v0")
    build_s = time.perf_counter() - start
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    trials = 0
    start = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
        if terminated or truncated:
            trials += 1
            env.reset()
    elapsed = time.perf_counter() - start
    env.close()
    return {"steps_per_s": steps / elapsed, "steps": steps, "trials": trials, "build_s": build_s}


def mean_returns(trials: int, seed: int) -> dict:
    env = gym.make("SignNav3D-v0")
    agents = {"oracle": dream_envs.make_oracle(env), "random": RandomAgent(env.action_space, seed=seed)}
    result = {
        name: float(np.mean([play_trial(env, agent, seed=seed + i)["execution_returns"] for i in range(trials)]))
        for name, agent in agents.items()
    }
    env.close()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000, help="env steps to time")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--trials", type=int, default=20, help="trials for the returns of the oracle and random agent")
    args = parser.parse_args()
    if args.steps < 1:
        parser.error("--steps must be >= 1")
    result = measure(args.steps, args.seed)
    print(
        f"SignNav3D-v0: {result['steps_per_s']:.0f} steps/s over {result['steps']} random steps "
        f"({result['trials']} trials; building the env took {result['build_s']:.2f} s)"
    )
    if args.trials > 0:
        returns = mean_returns(args.trials, args.seed)
        print(
            f"mean execution return over {args.trials} trials: oracle {returns['oracle']:.3f}, "
            f"random agent {returns['random']:.3f}"
        )


if __name__ == "__main__":
    main()
