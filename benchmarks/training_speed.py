"""Env steps per second of whole training, as the experiment runner trains: acting, the envs and the
updates, for any of the runner's algorithms.

Each entry is one model of ``--algo`` (a runner name: ``dream``, ``rl2dqn``, ``import_dqn``,
``varibad``, ``e_rl2dqn``, ...) with ``--preset`` on ``make_vec_env(--env, n_envs=--n-envs)``,
which, like every Stable-Baselines3 path from an env ID, makes the envs with
``render_mode="rgb_array"``. Every model first learns ``--warmup`` env steps (past its learning
start, so that every timed step pays for its updates), then ``model.learn(--steps)`` of each entry
is timed in ``--rounds`` interleaved rounds (the machine's drift falls on every entry alike), and
the median env steps per second is printed, with its ratio to the first entry's and the slowest
and fastest rounds.

Entries (``--variants``, ``+`` combines):

* ``default``: the library's defaults;
* ``final-frames``: the envs draw ``info["final_frame"]`` at each inner episode's end
  (``final_frames=True``), as every env built from an ID did before that became an option;
* ``loop-adam``: ``optimizer_kwargs=dict(fused=False)``, Adam's per-parameter loop.

    python benchmarks/training_speed.py --algo rl2dqn --variants default final-frames loop-adam final-frames+loop-adam
    python benchmarks/training_speed.py --algo dream --preset laptop --env-kwargs variant=map \\
        --variants default final-frames
"""

from __future__ import annotations

import argparse
import copy
from typing import Any, Callable, Dict, List, Tuple

import torch as th
from stable_baselines3.common.env_util import make_vec_env

import dream_envs  # noqa: F401  (registers the envs)
from sb3_dream.experiments.algorithms import algorithm_class, algorithm_env_kwargs, algorithm_spec
from sb3_dream.experiments.config import parse_kwargs
from timing import interleaved_rounds, summary

VARIANT_PARTS = ("default", "final-frames", "loop-adam")


def variant_kwargs(variant: str) -> Tuple[Dict[str, Any], Dict[str, Any]]:
    """(env kwargs, model kwargs) of a ``+``-joined variant."""
    parts = variant.split("+")
    unknown = [p for p in parts if p not in VARIANT_PARTS]
    if unknown:
        raise ValueError(f"--variants: unknown part(s) {unknown} of {variant!r}; accepted: {', '.join(VARIANT_PARTS)}")
    env_kwargs = {"render_mode": "rgb_array", "final_frames": True} if "final-frames" in parts else {}
    policy_kwargs = {"optimizer_kwargs": {"fused": False}} if "loop-adam" in parts else {}
    return env_kwargs, ({"policy_kwargs": policy_kwargs} if policy_kwargs else {})


def build(args: argparse.Namespace, variant: str) -> Any:
    """The entry's model after ``--warmup`` env steps of learning."""
    env_kwargs, model_kwargs = variant_kwargs(variant)
    preset = copy.deepcopy(algorithm_spec(args.algo).presets[args.preset])
    kwargs = {**preset, **args.kwargs}
    if "policy_kwargs" in model_kwargs:  # merged into the preset's (or --kwargs') network arguments
        model_kwargs = {"policy_kwargs": {**kwargs.get("policy_kwargs", {}), **model_kwargs["policy_kwargs"]}}
    kwargs.update(model_kwargs)
    env = make_vec_env(
        args.env,
        n_envs=args.n_envs,
        seed=args.seed,
        env_kwargs={**algorithm_env_kwargs(args.algo), **args.env_kwargs, **env_kwargs},
    )
    model = algorithm_class(args.algo)(env=env, seed=args.seed, **kwargs)
    model.learn(args.warmup)
    assert model._n_updates > 0, "--warmup ends before learning starts: every timed step must pay for its updates"
    return model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", default="rl2dqn", help="a runner name (python -m sb3_dream.experiments --help)")
    parser.add_argument("--env", default="MetaBus-v0")
    parser.add_argument("--env-kwargs", nargs="*", default=[], help="env arguments, name=value")
    parser.add_argument("--kwargs", nargs="*", default=[], help="model arguments, name=value (over the preset)")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--n-envs", type=int, default=4)
    parser.add_argument("--warmup", type=int, default=6000, help="env steps of learning before the timing")
    parser.add_argument("--steps", type=int, default=2000, help="env steps per entry per round")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--variants", nargs="+", default=["default", "final-frames"])
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    args.env_kwargs = parse_kwargs(args.env_kwargs, "--env-kwargs")
    args.kwargs = parse_kwargs(args.kwargs, "--kwargs")
    th.set_num_threads(args.threads)

    models = {variant: build(args, variant) for variant in args.variants}

    def run(model: Any) -> Callable[[], None]:
        return lambda: model.learn(args.steps, reset_num_timesteps=False)

    entries: List[Tuple[str, Callable[[], None]]] = [(v, run(m)) for v, m in models.items()]
    times = interleaved_rounds(entries, rounds=args.rounds, units=args.steps)
    first = summary(times[args.variants[0]])[0]
    env = f"{args.env} {args.env_kwargs}" if args.env_kwargs else args.env
    print(f"{args.algo} on {env}, preset {args.preset}, {args.n_envs} envs, {args.threads} torch thread(s)")
    print(f"{'variant':<28}{'env steps/s':>12}{'x first':>9}   (slowest - fastest round)")
    for variant in args.variants:
        median, fastest, slowest = summary(times[variant])
        print(f"{variant:<28}{1e3 / median:>12.0f}{first / median:>9.2f}   ({1e3 / slowest:.0f} - {1e3 / fastest:.0f})")


if __name__ == "__main__":
    main()
