"""RL2DQN (the paper's RL² baseline) on MetaBus-v0: learning curve and training throughput.

Trains with the paper's hyperparameters (``RL2DQN`` defaults) on the train split and evaluates
the greedy policy every ``--eval-freq`` env steps on ``--n-eval`` meta-test trials of the test
split (:func:`sb3_dream.evaluation.evaluate_meta`). Writes one CSV row per evaluation:
``seed, env_steps, train_seconds, wall_seconds, mean_execution_return, ci95, exploration_length``
(``train_seconds`` excludes evaluation time). Prints the training throughput in env steps per
second, before learning starts (acting only) and after (acting + one update per 4 env steps).

    python benchmarks/rl2dqn_bus.py --variant map --steps 20000 --seeds 0 --out rl2dqn_map.csv
    python benchmarks/rl2dqn_bus.py --variant distracting --steps 2000000 --seeds 0 1 2 --n-envs 8

For reference (paper, Figure 5): optimal execution return 0.8 on both variants, 0.3 without
information; RL² stays well below optimal.
"""

from __future__ import annotations

import argparse
import csv
import os
import time
from typing import List

import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

import dream_envs  # noqa: F401  (registers MetaBus-v0)
from sb3_dream.evaluation import evaluate_meta
from sb3_dream.rl2dqn import RL2DQN

FIELDS = ["seed", "env_steps", "train_seconds", "wall_seconds", "mean_execution_return", "ci95", "exploration_length"]


class CurveCallback(BaseCallback):
    """Evaluates on the test split every ``eval_freq`` env steps; times training apart from evaluation."""

    def __init__(self, seed: int, variant: str, eval_freq: int, n_eval: int, rows: List[dict]) -> None:
        super().__init__()
        self.seed, self.variant, self.eval_freq, self.n_eval, self.rows = seed, variant, eval_freq, n_eval, rows
        self.eval_seconds = 0.0
        self.learning_started_at = None  # (steps, train seconds) when the first update happens
        self._next_eval = 0

    def _on_training_start(self) -> None:
        self.start = time.perf_counter()
        self._evaluate()

    def train_seconds(self) -> float:
        return time.perf_counter() - self.start - self.eval_seconds

    def _on_step(self) -> bool:
        if self.learning_started_at is None and self.num_timesteps > self.model.learning_starts:
            self.learning_started_at = (self.num_timesteps, self.train_seconds())
        if self.num_timesteps >= self._next_eval:
            self._evaluate()
        return True

    def _on_training_end(self) -> None:
        self.train_end = self.train_seconds()
        if not self.rows or self.rows[-1]["env_steps"] != self.num_timesteps:
            self._evaluate()

    def _evaluate(self) -> None:
        t0 = time.perf_counter()
        train_s = t0 - self.start - self.eval_seconds
        result = evaluate_meta(
            self.model,
            "MetaBus-v0",
            n_trials=self.n_eval,
            split="test",
            seed=10_000,
            env_kwargs={"variant": self.variant},
        )
        self.eval_seconds += time.perf_counter() - t0
        self._next_eval = self.num_timesteps + self.eval_freq
        row = dict(
            seed=self.seed,
            env_steps=self.num_timesteps,
            train_seconds=round(train_s, 2),
            wall_seconds=round(time.perf_counter() - self.start, 2),
            mean_execution_return=round(result.mean, 4),
            ci95=round(result.ci, 4),
            exploration_length=round(result.mean_exploration_length, 2),
        )
        self.rows.append(row)
        print(
            f"[seed {self.seed}] {row['env_steps']:>8} steps  train {row['train_seconds']:>7.1f}s  "
            f"test return {row['mean_execution_return']:+.3f} ± {row['ci95']:.3f}",
            flush=True,
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variant", choices=["map", "distracting"], default="map")
    parser.add_argument("--steps", type=int, default=20_000, help="env steps per seed (over all envs)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--n-envs", type=int, default=1)
    parser.add_argument("--eval-freq", type=int, default=5_000, help="env steps between evaluations")
    parser.add_argument("--n-eval", type=int, default=100, help="test trials per evaluation")
    parser.add_argument("--out", default="rl2dqn_bus.csv", help="CSV learning curve")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (1 is fastest for these small nets)")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--learning-starts", type=int, default=None, help="override the paper's 16000 env steps")
    args = parser.parse_args()
    th.set_num_threads(args.threads)

    rows: List[dict] = []
    for seed in args.seeds:
        env = make_vec_env("MetaBus-v0", n_envs=args.n_envs, seed=seed, env_kwargs={"variant": args.variant})
        extra = {} if args.learning_starts is None else {"learning_starts": args.learning_starts}
        model = RL2DQN(env, seed=seed, device=args.device, **extra)
        cb = CurveCallback(seed, args.variant, args.eval_freq, args.n_eval, rows)
        model.learn(args.steps, callback=cb)
        total_sps = model.num_timesteps / cb.train_end
        msg = f"[seed {seed}] {args.variant}, n_envs={args.n_envs}, device={model.device}: "
        msg += f"{total_sps:.0f} env steps/s overall"
        if cb.learning_started_at is not None:
            s0, t0 = cb.learning_started_at
            acting_sps = s0 / max(t0, 1e-9)
            learning_sps = (model.num_timesteps - s0) / max(cb.train_end - t0, 1e-9)
            msg += f"; {acting_sps:.0f} before learning starts, {learning_sps:.0f} while learning"
            msg += f" ({model._n_updates} updates)"
        print(msg, flush=True)

    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {len(rows)} rows to {args.out}")


if __name__ == "__main__":
    main()
