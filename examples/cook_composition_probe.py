"""Can DREAM's execution Q-network cook a recipe it never saw, if it is taught the optimal Q?

    python examples/cook_composition_probe.py --seeds 0 1 2 --out results/cook_composition_probe.csv

MetaCook-v0 holds out the recipes (3, 6), (7, 1) and (5, 4): each ingredient appears in training
recipes, first or second, but never these pairs. A DREAM model's execution return on them stays
far below its return on training recipes. This probe asks whether that is the network's function
class or the reinforcement learning: it takes :class:`~sb3_dream.dream.policies.ExecutionQNetwork`
and a :class:`~sb3_dream.dream.policies.ProblemEncoder` (the privileged z = f(T), trained with it),
regresses Q(s, i, f(T), a) onto the optimal Q* (value iteration over the kitchen's inner MDP,
gamma 0.99) for every (problem, recipe) pair of the training split and every state on the way to
the dish, and then runs the greedy policy from the start on each split's pairs (20 steps). No
exploration and no decoder: z is exact, the target is exact, so a recipe the greedy policy does
not cook is one the network does not generalise to.

Architectures compared (``--variants``): ``paper`` (body (64,), the instruction embedded with the
paper's MLP), ``wide`` (body (128, 128), the runs' setting), and each with ``_parts``
(``execution_instruction_mlp=False``: the per-dimension embeddings of the recipe enter the body
directly). Each (variant, seed) takes about 2.5 minutes on one core.
"""

from __future__ import annotations

import argparse
import csv
import time
from typing import Dict, List, Sequence, Tuple

import gymnasium as gym
import numpy as np
import torch as th

import dream_envs  # noqa: F401  (registers the envs)
from dream_envs import cook
from sb3_dream.dream.policies import ExecutionQNetwork, ProblemEncoder

GAMMA = 0.99
HORIZON = 20
# The end-episode, no-op and ride-bus actions never help cook: left out of the targets and argmax.
ACTIONS = [a for a in range(cook.N_ACTIONS) if a not in (cook.END_EPISODE, cook.NOOP, cook.RIDE_BUS)]
# A ruined dish earns nothing more: -0.1 per step left; value it as if 10 steps were left (only the
# ranking of actions matters to the greedy policy, and a ruined dish ranks below every other state).
RUINED_VALUE = cook.STEP_REWARD * sum(GAMMA**t for t in range(10))
VARIANTS = {
    "paper": dict(hidden_sizes=(64,), instruction_mlp=True),
    "paper_parts": dict(hidden_sizes=(64,), instruction_mlp=False),
    "wide": dict(hidden_sizes=(128, 128), instruction_mlp=True),
    "wide_parts": dict(hidden_sizes=(128, 128), instruction_mlp=False),
}
SPLITS = ("train", "test_problems", "test_instructions")
Pair = Tuple[int, Tuple[int, int]]


def split_pairs(env: cook.MetaCookEnv, split: str) -> List[Pair]:
    """Every (problem, recipe) trial of ``split``."""
    return [(k, tuple(i)) for k in range(cook.N_PROBLEMS) for i in env.instructions(k, split)]


def optimal_q(problem_id: int, recipe: Tuple[int, int]) -> Tuple[List[tuple], np.ndarray]:
    """Q* over the states of an unfinished, unruined dish: pot empty or holding A, any position and
    anything in hand from this kitchen."""
    contents = cook.fridge_contents(problem_id)
    a = recipe[0]
    states = [
        (x, y, held, *pot)
        for x in range(cook.GRID_SIZE)
        for y in range(cook.GRID_SIZE)
        for held in sorted({0, *contents})
        for pot in ((0, 0), (a, 0))
    ]
    index = {s: j for j, s in enumerate(states)}
    next_index = np.zeros((len(states), len(ACTIONS)), dtype=np.int64)
    reward = np.zeros((len(states), len(ACTIONS)))
    fixed = np.full((len(states), len(ACTIONS)), np.nan)  # the value after a step that ends or ruins the dish
    for j, s in enumerate(states):
        for n, action in enumerate(ACTIONS):
            s2, reward[j, n], done = cook.cook_transition(s, action, contents, recipe)
            if done:
                fixed[j, n] = 0.0
            elif cook.recipe_stage(s2[2], s2[3:5], recipe) == cook.RUINED:
                fixed[j, n] = RUINED_VALUE
            else:
                next_index[j, n] = index[s2]
    value = np.zeros(len(states))
    for _ in range(200):  # gamma^200 < 0.14 of a reward's size; the rankings settle long before
        q = reward + GAMMA * np.where(np.isnan(fixed), value[next_index], fixed)
        value = q.max(axis=1)
    return states, q


def observation(state: tuple) -> List[int]:
    """MetaCook's inner observation of ``(x, y, held, pot1, pot2)``."""
    x, y, held, pot1, pot2 = state
    return [x, y, cook.object_at(x, y), held, pot1, pot2]


def dataset(pairs: Sequence[Pair]) -> Dict[str, th.Tensor]:
    obs, recipes, problems, targets = [], [], [], []
    for k, recipe in pairs:
        states, q = optimal_q(k, recipe)
        obs += [observation(s) for s in states]
        recipes += [recipe] * len(states)
        problems += [np.array(cook.fridge_contents(k)) - 1] * len(states)
        targets.append(q)
    return dict(
        obs=th.as_tensor(np.array(obs)),
        recipes=th.as_tensor(np.array(recipes)),
        problems=th.as_tensor(np.array(problems)),
        targets=th.as_tensor(np.concatenate(targets), dtype=th.float32),
    )


@th.no_grad()
def greedy_returns(q_net: ExecutionQNetwork, encoder: ProblemEncoder, pairs: Sequence[Pair]) -> np.ndarray:
    """The greedy policy's execution return on each pair, all pairs stepped together."""
    contents = [cook.fridge_contents(k) for k, _ in pairs]
    z = encoder(th.as_tensor(np.array(contents) - 1))
    recipes = th.as_tensor(np.array([r for _, r in pairs]))
    states = [(*cook.START, 0, 0, 0)] * len(pairs)
    returns, done = np.zeros(len(pairs)), np.zeros(len(pairs), dtype=bool)
    for _ in range(HORIZON):
        obs = th.as_tensor(np.array([observation(s) for s in states]))
        actions = q_net(obs, recipes, z)[:, ACTIONS].argmax(dim=1).tolist()
        for j, (k, recipe) in enumerate(pairs):
            if not done[j]:
                states[j], r, done[j] = cook.cook_transition(states[j], ACTIONS[actions[j]], contents[j], recipe)
                returns[j] += r
    return returns


def probe(variant: str, seed: int, steps: int, batch_size: int, data, env, pairs) -> List[dict]:
    th.manual_seed(seed)
    q_net = ExecutionQNetwork(env.observation_space, cook.N_ACTIONS, 64, **VARIANTS[variant])
    encoder = ProblemEncoder(env.problem_nvec, 64)
    optimizer = th.optim.Adam([*q_net.parameters(), *encoder.parameters()], lr=1e-3)
    generator = th.Generator().manual_seed(seed)
    start = time.perf_counter()
    for _ in range(steps):
        rows = th.randint(len(data["obs"]), (batch_size,), generator=generator)
        q = q_net(data["obs"][rows], data["recipes"][rows], encoder(data["problems"][rows]))[:, ACTIONS]
        loss = ((q - data["targets"][rows]) ** 2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    seconds = time.perf_counter() - start
    results = []
    for split in SPLITS:
        got = greedy_returns(q_net, encoder, pairs[split])
        best = np.array([cook.optimal_execution_return(k, r) for k, r in pairs[split]])
        groups = {split: np.ones(len(got), dtype=bool)}
        if split == "test_instructions":  # and each held-out recipe alone
            recipes = [r for _, r in pairs[split]]
            for a, b in cook.HELD_OUT_INSTRUCTIONS:
                groups[f"recipe {a}{b}"] = np.array([r == (a, b) for r in recipes])
        for name, rows in groups.items():
            results.append(
                dict(variant=variant, seed=seed, steps=steps, final_loss=f"{loss.item():.6f}", part=name,
                     pairs=int(rows.sum()), greedy_return=f"{got[rows].mean():.3f}",
                     optimal_return=f"{best[rows].mean():.3f}",
                     cooked=f"{np.mean(got[rows] >= best[rows] - 1e-6):.3f}", train_seconds=f"{seconds:.0f}")
            )
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=20000, help="gradient steps (Adam, lr 1e-3)")
    parser.add_argument("--batch-size", type=int, default=512)
    parser.add_argument("--out", default=None, help="CSV to write (one row per variant, seed and part)")
    args = parser.parse_args()
    th.set_num_threads(1)
    env = gym.make("MetaCook-v0").unwrapped
    pairs = {split: split_pairs(env, split) for split in SPLITS}
    data = dataset(pairs["train"])
    rows = []
    for variant in args.variants:
        for seed in args.seeds:
            for row in probe(variant, seed, args.steps, args.batch_size, data, env, pairs):
                rows.append(row)
                print(" ".join(f"{k}={v}" for k, v in row.items()), flush=True)
    if args.out:
        with open(args.out, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


if __name__ == "__main__":
    main()
