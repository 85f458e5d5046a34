"""RL2DQN on CartPole with the velocities masked out: memory turns a POMDP back into an MDP.

The observation keeps only the cart position x and the pole angle theta; the velocities must be
inferred from consecutive observations, which the LSTM does. The plain env is wrapped with
:class:`sb3_dream.common.wrappers.RL2ObservationWrapper` (Dict ``obs``, ``prev_action``,
``prev_reward``), so one CartPole episode plays the role of a trial. Episodes last up to 500
steps: they are replayed in sequences of 50 with R2D2's stored state and a 10-step burn-in.
Small settings, not the paper's: lr 1e-3, Huber TD loss, target sync every 100 updates, epsilon
1 -> 0.02 over 20k steps.

    python examples/rl2dqn_masked_cartpole.py --steps 60000 --out masked_cartpole.png

Saves a learning curve (training episode returns and periodic greedy evaluations) to ``--out``.
On a shared 2-core CPU, 60k steps take about 4 minutes and the greedy return climbs from ~20 to
~100-300 (max 500), noisily, as DQN-style learners do on CartPole; a frequent failure mode is a
balanced pole on a cart that drifts off the track, since the cart's velocity must be inferred.
"""

from __future__ import annotations

import argparse
import time
from typing import List, Tuple

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_dream.common.files import atomic_target, with_suffix
from sb3_dream.common.wrappers import RL2ObservationWrapper
from sb3_dream.rl2dqn import RL2DQN


class MaskVelocity(gym.ObservationWrapper):
    """CartPole's observation without the velocities: ``[x, theta]``, scaled by the termination
    thresholds (2.4 and 12 degrees) to lie in [-1, 1] while the pole is up."""

    SCALE = np.array([2.4, 12 * 2 * np.pi / 360], dtype=np.float32)

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float32)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return (observation[[0, 2]] / self.SCALE).astype(np.float32)


def make_masked_cartpole() -> gym.Env:
    return RL2ObservationWrapper(MaskVelocity(gym.make("CartPole-v1")))


class Curve(BaseCallback):
    """Collects training episode returns and evaluates the greedy policy every ``eval_freq`` steps."""

    def __init__(self, eval_freq: int, n_eval: int) -> None:
        super().__init__()
        self.eval_freq, self.n_eval = eval_freq, n_eval
        self.train_points: List[Tuple[int, float]] = []
        self.eval_points: List[Tuple[int, float, float]] = []
        self._next = eval_freq

    def _on_training_start(self) -> None:
        self.start = time.perf_counter()

    def _on_step(self) -> bool:
        for info in self.locals["infos"]:
            if "episode" in info:
                self.train_points.append((self.num_timesteps, float(info["episode"]["r"])))
        if self.num_timesteps >= self._next:
            self._next += self.eval_freq
            mean, _ = evaluate_policy(self.model, make_vec_env(make_masked_cartpole, n_envs=4, seed=123), self.n_eval)
            elapsed = time.perf_counter() - self.start
            self.eval_points.append((self.num_timesteps, mean, elapsed))
            print(f"{self.num_timesteps:>7} steps  {elapsed:6.0f}s  greedy return {mean:6.1f}", flush=True)
        return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=60_000)
    parser.add_argument("--n-envs", type=int, default=4)
    parser.add_argument("--eval-freq", type=int, default=5_000)
    parser.add_argument("--n-eval", type=int, default=8, help="evaluation episodes")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--out", default="masked_cartpole.png")
    args = parser.parse_args()
    th.set_num_threads(1)  # small networks: extra threads only contend

    env = make_vec_env(make_masked_cartpole, n_envs=args.n_envs, seed=args.seed)
    model = RL2DQN(
        env,
        learning_rate=args.lr,
        buffer_size=5_000,
        learning_starts=2_000,
        batch_size=32,
        train_freq=4,
        target_update_interval=100,
        td_loss="huber",
        exploration_steps=20_000,
        exploration_final_eps=0.02,
        sequence_length=50,
        burn_in=10,
        stored_state=True,
        policy_kwargs=dict(embed_kwargs=dict(state_hidden_dims=(64, 64))),
        seed=args.seed,
    )
    curve = Curve(args.eval_freq, args.n_eval)
    start = time.perf_counter()
    model.learn(args.steps, callback=curve)
    elapsed = time.perf_counter() - start
    final, final_std = evaluate_policy(model, make_vec_env(make_masked_cartpole, n_envs=4, seed=7), n_eval_episodes=20)
    print(f"trained {args.steps} steps in {elapsed:.0f}s; greedy return {final:.1f} ± {final_std:.1f} (max 500)")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    if curve.train_points:
        steps, returns = np.array(curve.train_points).T
        ax.plot(steps, returns, ".", alpha=0.3, label="training episodes (epsilon-greedy)")
    if curve.eval_points:
        steps, means, _ = np.array(curve.eval_points).T
        ax.plot(steps, means, "o-", label="greedy evaluation")
    ax.set_xlabel("env steps")
    ax.set_ylabel("episode return")
    ax.set_title(f"RL2DQN, CartPole without velocities ({elapsed:.0f}s)")
    ax.legend()
    fig.tight_layout()
    out = with_suffix(args.out, "png")  # matplotlib's format when --out names none
    with atomic_target(out, out.suffix[1:]) as tmp:  # written beside out, renamed over it once complete
        fig.savefig(tmp, dpi=100)
    print(f"saved {out}")


if __name__ == "__main__":
    main()
