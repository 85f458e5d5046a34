"""Steps per second of SignNav3D-v0 alone (uniformly random actions, no learning).

Usage: ``python benchmarks/sign_nav_speed.py [--steps 3000] [--seed 0] [--trials 20] [--copies 16]``

With ``--trials N`` (default 20, 0 to skip) it also prints the mean execution return of the env's
oracle and of a uniformly random agent over N trials. With ``--copies N`` it first prints the
memory (resident set) that one copy and N copies add to a fresh process, made and reset, as the
side-by-side evaluations make them (``evaluate_meta(..., n_envs=16)``).

Every step renders the agent's 80x60 view with OpenGL (Miniworld); off-screen through Mesa's EGL
on a headless machine, so the number mostly measures the software rasteriser of that machine.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
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


def resident_mb() -> float:
    """This process's resident set size in MB (Linux)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def added_memory_mb(copies: int) -> float:
    """MB that ``copies`` SignNav3D-v0 envs, made and reset, add to this process."""
    before = resident_mb()
    envs = [gym.make("SignNav3D-v0", split="test") for _ in range(copies)]
    for i, env in enumerate(envs):
        env.reset(seed=i)
    return resident_mb() - before


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
    parser.add_argument("--copies", type=int, default=0, help="also print the memory of 1 and N copies; 0: skip")
    parser.add_argument("--memory-of", type=int, default=0, help=argparse.SUPPRESS)  # the fresh process's part
    args = parser.parse_args()
    if args.memory_of:
        print(f"{added_memory_mb(args.memory_of):.0f}")
        return
    if args.steps < 1:
        parser.error("--steps must be >= 1")
    if args.copies > 0:
        added = {  # each in a fresh process, so the renderer's one-off cost counts in both
            n: subprocess.run([sys.executable, __file__, "--memory-of", str(n)], capture_output=True, text=True,
                              check=True).stdout.split()[-1]
            for n in sorted({1, args.copies})
        }  # fmt: skip
        print("memory added by SignNav3D-v0 copies (made and reset): "
              + ", ".join(f"{n}: {mb} MB" for n, mb in added.items()))  # fmt: skip
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
