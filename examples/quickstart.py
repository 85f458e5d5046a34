"""Quickstart: train DREAM on the MetaBus map and meta-test it on held-out trials.

    python examples/quickstart.py                                  # 200K env steps
    python examples/quickstart.py --steps 20000 --seed 1 --save dream_map.zip

Every 10K env steps it prints the held-out meta-test return (explore one episode reward-free,
then execute an instruction with what the exploration found): the optimal return is 0.8, an
agent that walks to the goal without using the buses gets 0.3, and a random one about -1.9.
The settings are the `laptop` preset (`sb3_dream.PRESETS["laptop"]`): the `fast` schedules
(learning starts after 100 trials, not the paper's 8000) with a wider, recurrent execution
Q-network learning from whole execution episodes; the README says what each changes.

What it prints at each step, and how long it takes: the README's Quickstart.
"""

import argparse

import gymnasium as gym
import torch as th
from stable_baselines3.common.env_util import make_vec_env

import dream_envs
from sb3_dream import DREAM, PRESETS, MetaEvalCallback, evaluate_meta

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--steps", type=int, default=200_000, help="env steps of training")
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--save", metavar="PATH", help="save the trained model (no replay buffers) here")
args = parser.parse_args()
th.set_num_threads(1)  # the networks are small: one thread is fastest

env_kwargs = {"variant": "map"}
env = make_vec_env("MetaBus-v0", n_envs=4, seed=args.seed, env_kwargs=env_kwargs)
# The laptop preset: the fast schedules with a wider, recurrent execution Q-network learning from
# whole execution episodes (sb3_dream.presets says what each setting changes).
model = DREAM("DreamPolicy", env, **PRESETS["laptop"], seed=args.seed, verbose=1)
held_out = MetaEvalCallback("MetaBus-v0", eval_freq=10_000, split="test", env_kwargs=env_kwargs, verbose=1)
model.learn(total_timesteps=args.steps, callback=held_out, log_interval=1000, progress_bar=True)
if args.save:
    model.save(args.save)

result = evaluate_meta(model, "MetaBus-v0", split="test", n_trials=100, env_kwargs=env_kwargs)
oracle = dream_envs.make_oracle(gym.make("MetaBus-v0", split="test", **env_kwargs))
optimal = evaluate_meta(oracle, "MetaBus-v0", split="test", n_trials=100, env_kwargs=env_kwargs)
print(f"held-out return after {model.num_timesteps} env steps: {result.mean:.3f} (optimal {optimal.mean:.3f})")
