"""The cost of one DREAM update against its batch size: what "fewer, larger updates" buys.

Builds one model with a preset, fills its replay by acting (no updates), then times
``model.train(gradient_steps, batch_size)`` for each ``--batch-sizes`` in interleaved rounds (so
that the machine's drift falls on every size alike) and prints the median milliseconds per update,
per sampled trajectory, and the cost per env step when the samples per env step are kept (batch B
every B / 8 env steps: the paper's 32 every 4).

    python benchmarks/update_shapes.py --preset laptop --env-kwargs variant=map --batch-sizes 32 64 128 256
"""

from __future__ import annotations

import argparse

import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env

import dream_envs  # noqa: F401  (registers the envs)
from sb3_dream import DREAM, PRESETS
from sb3_dream.experiments import parse_kwargs
from timing import interleaved_rounds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MetaBus-v0")
    parser.add_argument("--env-kwargs", nargs="*", default=[], metavar="KEY=VALUE")
    parser.add_argument("--preset", default="laptop", choices=sorted(PRESETS))
    parser.add_argument("--batch-sizes", nargs="+", type=int, default=[32, 64, 128, 256])
    parser.add_argument("--fill", type=int, default=4000, help="env steps of acting that fill the replay")
    parser.add_argument("--updates", type=int, default=10, help="updates per size per round")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (parallel_updates adds one)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if any(b < 1 for b in args.batch_sizes):
        parser.error(f"--batch-sizes must be integers >= 1, got {args.batch_sizes}")
    th.set_num_threads(args.threads)
    env_kwargs = parse_kwargs(args.env_kwargs, "--env-kwargs")
    env = make_vec_env(args.env, n_envs=4, seed=args.seed, env_kwargs=env_kwargs)
    # Act without updating until the replay holds --fill env steps, then let every part learn.
    model = DREAM(env, **PRESETS[args.preset], learning_starts=args.fill + 1, seed=args.seed)
    model.learn(args.fill)
    model.exploration_learning_starts = model.execution_learning_starts = 0
    for b in args.batch_sizes:
        model.train(2, b)  # warm-up: first-call allocations
    entries = [(str(b), lambda b=b: model.train(args.updates, b)) for b in args.batch_sizes]
    times = {int(name): values for name, values in interleaved_rounds(entries, args.rounds, args.updates).items()}
    base = args.batch_sizes[0]
    base_ms = np.median(times[base])
    print(
        f"{args.env} {env_kwargs or ''} preset {args.preset}, {args.threads} torch thread(s), "
        f"parallel updates {model.updates_in_parallel}; medians of {args.rounds} interleaved rounds"
    )
    print(f"{'batch':>6} {'ms/update':>10} {'us/sample':>10} {'x batch ' + str(base):>12} {'cost per env step':>18}")
    for b in args.batch_sizes:
        ms = np.median(times[b])
        per_step = (ms / base_ms) * (base / b)  # same samples per env step: an update every b / 8 env steps
        print(f"{b:>6} {ms:>10.1f} {ms / b * 1e3:>10.0f} {ms / base_ms:>12.2f} {per_step:>18.2f}")


if __name__ == "__main__":
    main()
