"""The cost of one update of each of the paper's baselines (RL², IMPORT, VariBAD) on MetaBus.

Builds one model per algorithm on ``gym.make(--env, variant=--variant)`` with the paper's
hyperparameters (batch 32, sequences of up to 50 steps) but ``learning_starts`` = ``--fill``:
``--fill`` env steps of acting fill the replay, 40 more with updates pay the first calls'
allocations. Then it times ``model.train(gradient_steps=--updates, batch_size=model.batch_size)``
in ``--rounds`` interleaved rounds (so that the machine's drift falls on every entry alike) and
prints, per entry, the median milliseconds per update, its ratio to the first entry's, and the
fastest and slowest rounds.

VariBAD's decoder loss has two implementations (:func:`sb3_dream.varibad.varibad_decoder_loss`,
``method``): ``chunked`` (``auto``'s choice on CPU) and ``dense`` (the reference: every (prefix,
transition) pair's hidden layer at once, through autograd). ``--variants`` times VariBAD once per
method, on the same model, in the same rounds.

    python benchmarks/baseline_updates.py                               # RL2DQN, IMPORT, VariBAD
    python benchmarks/baseline_updates.py --variants dense chunked --rounds 9
    python benchmarks/baseline_updates.py --algos VariBAD --variants dense chunked --profile 20

It prints one line per entry: ``ms/update`` (the median), ``x first`` and ``(min - max)`` over
the rounds. Measured results are in docs/baselines.md ("IMPORT and VariBAD").

``--profile N`` then runs N more updates of each entry under ``torch.profiler`` and prints its
operators by self CPU time (``--profile-rows`` rows).
"""

from __future__ import annotations

import argparse
from typing import Callable, Dict, List, Tuple

import gymnasium as gym
import torch as th

import dream_envs  # noqa: F401  (registers the envs)
from sb3_dream import IMPORT, RL2DQN, VariBAD
from sb3_dream.varibad.varibad import DECODER_LOSS_METHODS
from timing import interleaved_rounds, summary

ALGOS = {"RL2DQN": RL2DQN, "IMPORT": IMPORT, "VariBAD": VariBAD}


def build(algo: str, env_id: str, variant: str, fill: int, seed: int) -> RL2DQN:
    """``algo`` with the paper's defaults but ``learning_starts`` = ``fill``, after ``fill`` env steps
    of acting and 40 more of learning (10 updates: the first calls' allocations are paid)."""
    model = ALGOS[algo](gym.make(env_id, variant=variant), learning_starts=fill, seed=seed)
    model.learn(fill + 40)
    assert model._n_updates > 0
    return model


def entries(models: Dict[str, RL2DQN], variants: List[str]) -> List[Tuple[str, Callable[[], None]]]:
    """``(name, set-up)`` per timed entry: each algorithm, VariBAD once per ``variants`` method."""
    out: List[Tuple[str, Callable[[], None]]] = []
    for algo, model in models.items():
        if algo != "VariBAD":
            out.append((algo, lambda: None))
            continue
        for method in variants:
            out.append((f"VariBAD[{method}]", lambda m=model, method=method: setattr(m, "decoder_loss_method", method)))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MetaBus-v0")
    parser.add_argument("--variant", default="map", help="the env's variant argument")
    parser.add_argument("--algos", nargs="+", default=list(ALGOS), choices=list(ALGOS))
    parser.add_argument(
        "--variants",
        nargs="+",
        default=["auto"],
        choices=DECODER_LOSS_METHODS,
        help="VariBAD's decoder-loss methods to time",
    )
    parser.add_argument("--fill", type=int, default=2000, help="env steps of acting before learning starts")
    parser.add_argument("--updates", type=int, default=10, help="updates per entry per round")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--profile", type=int, default=0, metavar="N", help="profile N updates of each entry")
    parser.add_argument("--profile-rows", type=int, default=15)
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    models = {algo: build(algo, args.env, args.variant, args.fill, args.seed) for algo in args.algos}
    todo = entries(models, args.variants)

    def run(model: RL2DQN) -> Callable[[], None]:
        return lambda: model.train(gradient_steps=args.updates, batch_size=model.batch_size)

    timed = [(name, run(models[name.split("[")[0]]), set_up) for name, set_up in todo]
    times = interleaved_rounds(timed, args.rounds, args.updates)
    print(
        f"{args.env} variant={args.variant}, {args.threads} torch thread(s), batch "
        f"{next(iter(models.values())).batch_size}; medians of {args.rounds} interleaved rounds of "
        f"{args.updates} updates"
    )
    print(f"{'entry':<20} {'ms/update':>10} {'x first':>9}   (min - max)")
    first = summary(times[todo[0][0]])[0]
    for name, _ in todo:
        ms, low, high = summary(times[name])
        print(f"{name:<20} {ms:>10.1f} {ms / first:>9.2f}   ({low:.1f} - {high:.1f})")
    for name, set_up in todo if args.profile else []:
        set_up()
        model = models[name.split("[")[0]]
        with th.profiler.profile(activities=[th.profiler.ProfilerActivity.CPU]) as prof:
            model.train(gradient_steps=args.profile, batch_size=model.batch_size)
        print(f"\n{name}: {args.profile} updates under torch.profiler")
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.profile_rows))


if __name__ == "__main__":
    main()
