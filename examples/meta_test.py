"""Meta-test a saved model on the held-out problems, next to the optimal and a random agent.

    python examples/meta_test.py --model dream_metabus.zip --trials 500
    python examples/meta_test.py --model rl2dqn_bus.zip --env MetaBus-v0 --n-exec-episodes 3
    python examples/meta_test.py --model dream_map.zip --env-kwargs variant=map --exhaustive
    python examples/meta_test.py --model dream_map.zip --env-kwargs variant=map --diagnose
    python examples/meta_test.py --model dream_metabus.zip --exploration
    python examples/meta_test.py --model dream_cook.zip --env MetaCook-v0 --split train --exploration
    python examples/meta_test.py --model snapshots/dream_seed0_*_steps.zip --exploration  # one line each
    python examples/meta_test.py --model dream_cook.zip --env MetaCook-v0 --split train --trace 3
    python examples/meta_test.py --model dream_cook.zip --env MetaCook-v0 --gains

A meta-test trial: a held-out problem (``--split test``) the model never trained on; one
reward-free exploration episode; then ``--n-exec-episodes`` execution episodes, each with an
instruction. The score is the mean execution return per episode, with a 95% confidence interval
over trials. The problem ID never reaches the model: it sees observations only (DREAM also the
exploration's last state from ``info["final_obs"]``). ``--exhaustive`` plays every (problem,
instruction) pair of the split instead of drawing trials, in whole passes of at least ``--trials``
trials, and weights each pair by its probability under the split's sampling: the split's expected
return, exact for a greedy model (the envs are deterministic once the pair is pinned; SignNav3D's
start is not). Every other report then plays the same pairs, unweighted.

``--diagnose`` (DREAM only) also runs :func:`sb3_dream.dream.diagnose`: the same trials once more
with the execution policy given the privileged z = f(T), to tell whether exploration (and the
decoder) or execution limits the model, once more with z ~ N(f(T), rho^2 I), the noisy code
the execution policy trains on, and once more with the env's scripted optimal explorer in place of
the exploration policy and z = g of its trajectory, to tell the explorer from the decoder. With
``--exploration`` too, the behaviour report is also made for that privileged agent (z = f(T)):
what execution does when the code is exactly right. For an IMPORT model ``--diagnose`` runs
:func:`sb3_dream.import_dqn.diagnose`: the trials once more with z = e(T), the problem's embedding,
and how far the history's embedding e(tau_:t) stays from it.

``--exploration`` reports what each agent does, as the paper's Figures 7 and 8 show it. MetaBus-v0:
colored and gray routes ridden while exploring, whether it read the map
(:func:`dream_envs.bus.exploration_report`). MetaCook-v0: fridges opened while exploring, and per
execution episode whether the recipe was finished, the dish ruined, and how many steps undid a
stage, with the held-out recipes' shares one by one (:func:`dream_envs.cook.behaviour_report`).
SignNav3D-v0: in how many explorations the sign was read (at least 20 pixels of its letters in one
view) and the agent got past the barrier, with the execution return of the trials that read the
sign and of those that did not, and per target object (the sign's colour, the instruction's type)
how the execution episodes ended: right, wrong object, end action, or timed out
(:func:`dream_envs.sign_nav.exploration_report`).

``--gains`` (DREAM only) runs :func:`sb3_dream.dream.exploration_gains` on the same trials (with
``--diagnose``, on the trials diagnose already played, not a second time): the
exploration reward of Equation 5 that each step of the greedy explorations earns from the model's
current encoder and decoder, per step and, on MetaCook-v0, at each fridge's first opening by the
order the fridges were opened in (:func:`dream_envs.cook.opening_rewards`), on MetaBus-v0 by what
the step found: a colored or a gray route, a route ridden again, the map
(:func:`dream_envs.bus.discovery_rewards`): which steps pay the explorer, and how much.
``--gains-explorer oracle|random`` rewards the scripted optimal or a random agent's explorations
instead: what the model's reward would pay for steps its own explorer does not take.

``--trace K`` prints the actions of the first K trials' exploration episodes, by name where the
env names its actions (MetaBus, MetaCook, SignNav3D): e.g. a greedy exploration policy stuck
repeating a no-op from the start, which every trial begins the same way.

The model's algorithm (DREAM, RL2DQN, IMPORT or VariBAD) is read from the saved file. Several ``--model`` files
(e.g. the runner's ``--snapshot-freq`` snapshots of one run) are meta-tested on the same trials,
in the order given, with the optimal and the random agent once.
"""

from __future__ import annotations

import argparse
import itertools
import os
from typing import Any

import gymnasium as gym

import dream_envs
from dream_envs import RandomAgent, play_trials
from sb3_dream.evaluation import as_trial_agent, evaluate_meta, exhaustive_cases
from sb3_dream.experiments import parse_kwargs


def load_model(path: str, device: str = "cpu") -> Any:
    """Load a saved DREAM, RL2DQN, IMPORT or VariBAD model, whichever the file holds."""
    from sb3_dream.loading import load_model as load

    return load(path, device=device)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--model", required=True, nargs="+", help="saved DREAM, RL2DQN, IMPORT or VariBAD models (.zip)"
    )
    parser.add_argument("--env", default="MetaBus-v0")
    parser.add_argument(
        "--env-kwargs", nargs="*", default=[], metavar="KEY=VALUE", help="as in training, e.g. variant=map"
    )
    parser.add_argument("--split", default="test", choices=dream_envs.all_splits(), help="test = held-out problems")
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--n-exec-episodes", type=int, default=1)
    parser.add_argument(
        "--exhaustive",
        action="store_true",
        help="play every (problem, instruction) pair of the split (whole passes of at least --trials trials) "
        "and weight each by its probability: the split's expected return, not a draw's",
    )
    parser.add_argument(
        "--seed",
        type=int,
        default=0,
        help="trial k is seeded SEED + k, so seeds fewer than --trials apart replay some of the same trials "
        "(0 and 1: all but one); for a draw of its own take e.g. --seed 1000. --diagnose draws its "
        "problems from SEED another way (sb3_dream.dream.trial_problem_ids)",
    )
    parser.add_argument(
        "--diagnose",
        action="store_true",
        help="DREAM: also meta-test on z = f(T), on z ~ N(f(T), rho^2 I) and on g of the optimal exploration; "
        "IMPORT: also on z = e(T), with the distance of e(tau) to e(T)",
    )
    parser.add_argument(
        "--exploration",
        action="store_true",
        help="MetaBus-v0, MetaCook-v0, SignNav3D-v0: what each agent explores and does",
    )
    parser.add_argument(
        "--gains",
        action="store_true",
        help="DREAM: the exploration reward (Equation 5) of each step of its explorations; "
        "MetaCook-v0: of each fridge's first opening; MetaBus-v0: by what the step found",
    )
    parser.add_argument(
        "--gains-explorer",
        default="model",
        choices=("model", "oracle", "random"),
        help="--gains: whose explorations the model's reward pays (default: its own)",
    )
    parser.add_argument(
        "--outcomes",
        action="store_true",
        help="also print the shares of execution episodes with a positive, negative and zero return",
    )
    parser.add_argument("--trace", type=int, default=0, metavar="K", help="print the first K explorations' actions")
    args = parser.parse_args()
    if args.trace < 0:
        parser.error(f"--trace must be a number of trials >= 0, got {args.trace}")
    missing = [path for path in args.model if not os.path.isfile(path)]
    if missing:
        parser.error(f"--model: no such file: {', '.join(missing)}")

    env_kwargs = parse_kwargs(args.env_kwargs, "--env-kwargs")
    env = gym.make(args.env, split=args.split, n_exec_episodes=args.n_exec_episodes, **env_kwargs)
    # --exhaustive: the split's (problem, instruction) pairs pinned, in the order evaluate_meta plays them
    problem_ids, instructions = None, None
    if args.exhaustive:
        problem_ids, instructions, _ = exhaustive_cases(env, args.split, args.trials)
    n_trials = args.trials if problem_ids is None else len(problem_ids)
    models = {path: load_model(path) for path in args.model}
    names = {path: type(m).__name__ if len(models) == 1 else path for path, m in models.items()}
    agents = {
        **{names[path]: m for path, m in models.items()},
        "optimal (scripted)": dream_envs.make_oracle(env),
        "random": RandomAgent(env.action_space, seed=args.seed),
    }
    n_problems = len(env.unwrapped.problem_ids(args.split))
    label = args.env + "".join(f" {k}={v!r}" for k, v in env_kwargs.items())
    print(f"{label} split={args.split} ({n_problems} problems), {n_trials} trials")
    for name, agent in agents.items():
        result = evaluate_meta(  # by ID: a model plays 16 trials side by side (the env object: one at a time)
            agent,
            env if name == "optimal (scripted)" else args.env,  # the oracle reads its own env (SignNav3D's pose)
            n_trials=args.trials,
            split=args.split,
            n_exec_episodes=args.n_exec_episodes,
            seed=args.seed,
            env_kwargs=env_kwargs,
            exhaustive=args.exhaustive,
        )
        print(f"  {name:>20}: {result.summary()}")
        if args.outcomes:
            above, below, zero = result.return_shares()
            print(f"  {'':>20}  return > 0 in {above:.0%}, < 0 in {below:.0%}, 0 in {zero:.0%} of execution episodes")
    if args.trace:
        action_names = env.unwrapped.action_names
        for name, agent in agents.items():
            trials = play_trials(env, as_trial_agent(agent), args.trace, args.seed, problem_ids, instructions)
            for k, trial in enumerate(trials):
                actions = [str(a) if action_names is None else action_names[a] for a in trial["exploration_actions"]]
                print(f"  {name:>20} trial {k}, problem {trial['problem_id']}: {' '.join(actions)}")
    if args.exploration:
        from dream_envs import bus, cook, sign_nav

        reports = {
            "MetaBus-v0": bus.exploration_report,
            "MetaCook-v0": cook.behaviour_report,
            "SignNav3D-v0": sign_nav.exploration_report,
        }
        if args.env not in reports:
            raise SystemExit(f"--exploration needs --env {', '.join(reports)}, got {args.env}")
        for name, agent in agents.items():
            report = reports[args.env](env, as_trial_agent(agent), n_trials, args.seed, problem_ids, instructions)
            print(f"  {name:>20} exploring: {report.summary()}")
        if args.diagnose:  # the same report with execution on the privileged z = f(T)
            from sb3_dream.dream import DREAM, PrivilegedAgent, trial_problem_ids

            split_ids = env.unwrapped.problem_ids(args.split)
            ids = trial_problem_ids(split_ids, n_trials, args.seed, problem_ids)  # diagnose()'s trials
            for name, model in zip(names.values(), models.values()):
                if isinstance(model, DREAM):
                    agent = PrivilegedAgent(model, ids)
                    report = reports[args.env](env, agent, n_trials, args.seed, ids, instructions)
                    print(f"  {name:>20} with z = f(T): {report.summary()}")
    diagnoses = {}  # path -> DreamDiagnosis, whose z = g trials --gains reuses
    if args.diagnose:
        from sb3_dream import IMPORT
        from sb3_dream.dream import DREAM, diagnose
        from sb3_dream.import_dqn import diagnose as diagnose_import

        for path, model in models.items():
            prefix = "" if len(models) == 1 else f"{path} "
            if isinstance(model, IMPORT):
                d = diagnose_import(
                    model, args.env, args.trials, args.split, args.seed, env_kwargs, exhaustive=args.exhaustive
                )
                print(f"  {prefix}diagnosis: {d.text()}")
                continue
            if not isinstance(model, DREAM):
                raise SystemExit(f"--diagnose needs DREAM or IMPORT models, got {type(model).__name__} ({path})")
            d = diagnoses[path] = diagnose(  # one execution episode per trial
                model, args.env, args.trials, args.split, args.seed, env_kwargs=env_kwargs, exhaustive=args.exhaustive
            )
            print(
                f"  {prefix}diagnosis: {d.returns_text()}; "
                f"||g - f||^2 {d.decoder_error:.3f}"
                + (
                    f" (optimal exploration: {d.decoder_error_optimal_exploration:.3f})"
                    if d.decoder_error_optimal_exploration is not None
                    else ""
                )
                + f" (||f||^2 {d.f_norm_sq:.2f}, ||f(T) - f(T')||^2 {d.f_spread:.2f}); "
                "variance of f explained by each problem feature: "
                + ", ".join(f"{v:.2f}" for v in d.f_variance_by_feature)
            )

    if args.gains:
        from dream_envs.bus import discovery_rewards
        from dream_envs.cook import opening_rewards
        from sb3_dream.dream import DREAM, exploration_gains

        for path, model in models.items():
            if not isinstance(model, DREAM):
                raise SystemExit(f"--gains needs DREAM models, got {type(model).__name__} ({path})")
            seeds = itertools.count(args.seed)  # one random explorer per env slot, each its own seed
            explorer = {
                "model": None,
                "oracle": dream_envs.make_oracle,
                "random": lambda e: RandomAgent(e.action_space, seed=next(seeds)),
            }[args.gains_explorer]
            if explorer is None and path in diagnoses:  # the same trials, already played by diagnose
                gains = diagnoses[path].exploration_gains
            else:
                gains = exploration_gains(
                    model,
                    args.env,
                    args.trials,
                    args.split,
                    args.seed,
                    env_kwargs,
                    explorer=explorer,
                    exhaustive=args.exhaustive,
                )
            label = names[path] + ("" if explorer is None else f" ({args.gains_explorer} explorations)")
            print(
                f"  {label} exploration reward per step (Equation 5, c = {gains.reward_penalty:g}; "
                f"mean over the trials that took it): {' '.join(f'{r:+.2f}' for r in gains.by_step())}; "
                f"information gain per trial {gains.information_gain().mean():.2f}"
            )
            if args.env == "MetaCook-v0":
                openings = opening_rewards(gains.trajectories, gains.rewards)
                ordinals = ("first", "second", "third")
                print(
                    f"  {label} exploration reward of a fridge's first opening: "
                    + "; ".join(
                        f"fridge {k} opened {ordinals[order]} in {len(openings[k, order])} trials: "
                        f"{openings[k, order].mean():+.2f}"
                        for order, k in sorted((order, k) for k, order in openings)
                    )
                    + ("no fridge opened" if not openings else "")
                )
            elif args.env == "MetaBus-v0":
                found = discovery_rewards(env, gains.trajectories, gains.rewards, gains.problem_ids)
                print(
                    f"  {label} exploration reward by what the step found: "
                    + "; ".join(f"{kind} {r.mean():+.2f} ({len(r)} steps)" for kind, r in found.items())
                )


if __name__ == "__main__":
    main()
