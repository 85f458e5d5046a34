"""Train DREAM on MetaBus-v0, watch its held-out return, and save the model.

    python examples/train_dream_metabus.py --variant map --steps 100000 --out dream_metabus_map.zip

Every ``--eval-freq`` env steps, :class:`sb3_dream.MetaEvalCallback` runs ``--eval-trials``
meta-test trials on the *held-out* problems (``split="test"``): explore reward-free for one
episode, then execute one instruction with z decoded from that exploration. The optimal return is
0.8 (3 steps: step onto the right bus stop, ride, step to the goal); an agent that learned nothing
about the buses walks there for 0.3, and a random one gets about -2.

``--preset fast`` (the default here; ``paper`` for the paper's schedules) starts learning after
100 trials and decays epsilon over 30K steps of each policy (:mod:`sb3_dream.presets`); the
map variant (24 problems) learns sooner than the default distracting-bus one (576 problems).
Next: ``examples/watch_dream.py`` makes a video of the saved model, ``examples/meta_test.py``
scores it.
"""

from __future__ import annotations

import argparse

import torch as th
from stable_baselines3.common.env_util import make_vec_env

import dream_envs  # noqa: F401  (registers MetaBus-v0 and the other trial envs)
from sb3_dream import DREAM, MetaEvalCallback, evaluate_meta
from sb3_dream.presets import PRESETS
from sb3_dream.experiments import parse_kwargs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variant", default="distracting", choices=["distracting", "map", "vanilla"])
    parser.add_argument("--steps", type=int, default=100_000, help="env steps of training")
    parser.add_argument("--preset", default="fast", choices=sorted(PRESETS))
    parser.add_argument("--n-envs", type=int, default=1, help="envs stepped together (one batched forward)")
    parser.add_argument("--eval-freq", type=int, default=10_000, help="env steps between evaluations")
    parser.add_argument("--eval-trials", type=int, default=100, help="meta-test trials per evaluation")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest for these small nets)")
    parser.add_argument("--out", default="dream_metabus.zip", help="where to save the model")
    parser.add_argument(
        "--dream-kwargs",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="more DREAM arguments, e.g. buffer_size=2000 (values are Python literals)",
    )
    args = parser.parse_args()
    th.set_num_threads(args.threads)

    env_kwargs = {"variant": args.variant}
    env = make_vec_env("MetaBus-v0", n_envs=args.n_envs, seed=args.seed, env_kwargs=env_kwargs)
    extra = parse_kwargs(args.dream_kwargs, "--dream-kwargs")
    model = DREAM(env, seed=args.seed, verbose=0, **{**PRESETS[args.preset], **extra})

    evaluation = MetaEvalCallback(
        "MetaBus-v0",
        eval_freq=args.eval_freq,
        n_trials=args.eval_trials,
        split="test",
        env_kwargs=env_kwargs,
        verbose=1,  # one line per evaluation: steps, seconds, held-out return, exploration length
    )
    model.learn(total_timesteps=args.steps, callback=evaluation)
    model.save(args.out)
    print(f"saved {args.out}")

    # Meta-test the saved model on the held-out problems, as examples/meta_test.py does.
    loaded = DREAM.load(args.out)
    result = evaluate_meta(loaded, "MetaBus-v0", n_trials=args.eval_trials, split="test", env_kwargs=env_kwargs)
    print("held-out:", result.summary())


if __name__ == "__main__":
    main()
