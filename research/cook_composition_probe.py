"""Can DREAM's execution Q-network cook a recipe it never saw, if it is taught the optimal Q?

    python research/cook_composition_probe.py --seeds 0 1 2 --out research/cook_composition_probe.csv

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
directly), and ``wider_parts`` (body (256, 256), without the MLP). Each (variant, seed) takes
about 2.5 minutes on one core (``wider_parts`` about 4). Three more variants change the
``wide_parts`` network in one place each, as levers for composition (see :func:`q_network`):
``film_parts`` (a product of the recipe's and the rest's projections in the first layer),
``shared_parts`` (one ingredient table for both parts of the recipe) and ``state_parts`` (no MLP
over the state either).

Closer to what DQN does: ``--targets bootstrapped`` regresses onto r + gamma max_a' Q(s', a') of
the network itself, recomputed every ``--target-update`` steps (a target network's hard sync),
instead of Q*; ``--actions one`` teaches one uniformly drawn action per sampled state (a replay
transition) instead of all; ``--lr`` and ``--batch-size`` set Adam's step and the batch (DREAM's
are 1e-4 and 32); ``--weight-decay`` adds AdamW's decoupled weight decay (DREAM's option
``execution_weight_decay`` decays the execution Q-network alone). What then still differs from a
DREAM run: the data (every state of every training pair here, the states the agent visits there),
z (exact here; f(T) with noise or the decoder's g there) and the time input.
"""

from __future__ import annotations

import argparse
import csv
import os
import time
from typing import Dict, List, Sequence, Tuple

import gymnasium as gym
import numpy as np
import torch as th

import dream_envs  # noqa: F401  (registers the envs)
from dream_envs import cook
from sb3_dream.common.embedders import MultiDiscreteEmbedder, relu_mlp
from sb3_dream.dream.policies import ExecutionQNetwork, ProblemEncoder

GAMMA = 0.99
Z_DIM = 64  # DREAM's z (the paper's size), from the encoder f into the execution Q-network
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
    "wider_parts": dict(hidden_sizes=(256, 256), instruction_mlp=False),
}
# Other ways into the wide_parts network for the recipe, tried as levers for composition (this
# probe's only; not options of DREAM). See :func:`q_network`.
FUSIONS = ("film_parts", "shared_parts", "state_parts")
SPLITS = ("train", "test_problems", "test_instructions")
Pair = Tuple[int, Tuple[int, int]]


def split_pairs(env: cook.MetaCookEnv, split: str) -> List[Pair]:
    """Every (problem, recipe) trial of ``split``."""
    return [(k, tuple(i)) for k in range(cook.N_PROBLEMS) for i in env.instructions(k, split)]


def kitchen_mdp(problem_id: int, recipe: Tuple[int, int]) -> Tuple[List[tuple], np.ndarray, np.ndarray, np.ndarray]:
    """The states of an unfinished, unruined dish (pot empty or holding A, any position and anything
    in hand from this kitchen) and, per state and action in :data:`ACTIONS`: the next state's index,
    the reward, and the value after a step that ends or ruins the dish (NaN where the dish goes on)."""
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
    fixed = np.full((len(states), len(ACTIONS)), np.nan)
    for j, s in enumerate(states):
        for n, action in enumerate(ACTIONS):
            s2, reward[j, n], done = cook.cook_transition(s, action, contents, recipe)
            if done:
                fixed[j, n] = 0.0
            elif cook.recipe_stage(s2[2], s2[3:5], recipe) == cook.RUINED:
                fixed[j, n] = RUINED_VALUE
            else:
                next_index[j, n] = index[s2]
    return states, next_index, reward, fixed


def bellman_targets(value: np.ndarray, next_index: np.ndarray, reward: np.ndarray, fixed: np.ndarray) -> np.ndarray:
    """r + gamma * V(s'), with the fixed value where the step ends or ruins the dish."""
    return reward + GAMMA * np.where(np.isnan(fixed), value[next_index], fixed)


def value_iteration(next_index: np.ndarray, reward: np.ndarray, fixed: np.ndarray) -> np.ndarray:
    """Q* of a :func:`kitchen_mdp`."""
    value = np.zeros(len(next_index))
    for _ in range(200):  # gamma^200 < 0.14 of a reward's size; the rankings settle long before
        q = bellman_targets(value, next_index, reward, fixed)
        value = q.max(axis=1)
    return q


def optimal_q(problem_id: int, recipe: Tuple[int, int]) -> Tuple[List[tuple], np.ndarray]:
    """The states of :func:`kitchen_mdp` and their Q*."""
    states, *transitions = kitchen_mdp(problem_id, recipe)
    return states, value_iteration(*transitions)


def observation(state: tuple) -> List[int]:
    """MetaCook's inner observation of ``(x, y, held, pot1, pot2)``."""
    x, y, held, pot1, pot2 = state
    return [x, y, cook.object_at(x, y), held, pot1, pot2]


def dataset(pairs: Sequence[Pair]) -> Dict[str, th.Tensor]:
    """Every state of every pair's :func:`kitchen_mdp`, its Q* and its transitions (next-state rows
    index the whole dataset)."""
    columns: Dict[str, list] = {key: [] for key in ("obs", "recipes", "problems", "targets", "next", "reward", "fixed")}
    offset = 0
    for k, recipe in pairs:
        states, next_index, reward, fixed = kitchen_mdp(k, recipe)
        columns["obs"] += [observation(s) for s in states]
        columns["recipes"] += [recipe] * len(states)
        columns["problems"] += [np.array(cook.fridge_contents(k)) - 1] * len(states)
        columns["targets"].append(value_iteration(next_index, reward, fixed))
        columns["next"].append(next_index + offset)
        columns["reward"].append(reward)
        columns["fixed"].append(fixed)
        offset += len(states)
    data = {key: th.as_tensor(np.array(columns[key])) for key in ("obs", "recipes", "problems")}
    data.update({key: np.concatenate(columns[key]) for key in ("next", "reward", "fixed")})
    data["targets"] = th.as_tensor(np.concatenate(columns["targets"]), dtype=th.float32)
    return data


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
        actions = q_net(obs, recipes, z)[0][:, ACTIONS].argmax(dim=1).tolist()
        for j, (k, recipe) in enumerate(pairs):
            if not done[j]:
                states[j], r, done[j] = cook.cook_transition(states[j], ACTIONS[actions[j]], contents[j], recipe)
                returns[j] += r
    return returns


def dataset_q(q_net: ExecutionQNetwork, encoder: ProblemEncoder, data, rows: th.Tensor) -> th.Tensor:
    """Q(s, i, f(T), a) of the dataset's ``rows``, for the actions in :data:`ACTIONS`."""
    return q_net(data["obs"][rows], data["recipes"][rows], encoder(data["problems"][rows]))[0][:, ACTIONS]


@th.no_grad()
def bootstrapped_targets(q_net: ExecutionQNetwork, encoder: ProblemEncoder, data) -> th.Tensor:
    """r + gamma * max_a' Q(s', a') under the networks as they are now: a DQN target network's
    targets, for every state and action of the dataset at once."""
    rows = th.arange(len(data["obs"]))
    value = th.cat([dataset_q(q_net, encoder, data, chunk).max(dim=1).values for chunk in rows.split(65536)])
    return th.as_tensor(bellman_targets(value.numpy(), data["next"], data["reward"], data["fixed"]), dtype=th.float32)


class SharedIngredients(th.nn.Module):
    """Both recipe parts looked up in one ingredient table, concatenated in recipe order."""

    def __init__(self, n_values: int, per_dim: int = 32) -> None:
        super().__init__()
        self.embedding = th.nn.Embedding(n_values, per_dim)
        self.embed_dim = 2 * per_dim

    def forward(self, recipes: th.Tensor) -> th.Tensor:
        return self.embedding(recipes.long()).flatten(-2)


class FilmQNetwork(ExecutionQNetwork):
    """The first body layer gains a product term: ReLU(W [e(s); e(i); z] + (A [e(s); z]) * (B e(i)))."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        first = self.body[0]
        recipe_dim = self.instruction_embed.embed_dim
        self.film_state = th.nn.Linear(first.in_features - recipe_dim, first.out_features)
        self.film_recipe = th.nn.Linear(recipe_dim, first.out_features)

    def q_values(self, embedding: th.Tensor, z: th.Tensor) -> th.Tensor:
        start, stop = self.state_embed.embed_dim, self.state_embed.embed_dim + self.instruction_embed.embed_dim
        rest = th.cat([embedding[..., :start], embedding[..., stop:], z], dim=-1)
        product = self.film_state(rest) * self.film_recipe(embedding[..., start:stop])
        hidden = th.relu(self.body[0](th.cat([embedding, z], dim=-1)) + product)
        return self.head(self.body[2:](hidden))


def q_network(variant: str, observation_space) -> ExecutionQNetwork:
    """The execution Q-network of ``variant``: one of :data:`VARIANTS`, or of :data:`FUSIONS`, each
    the ``wide_parts`` network changed in one place: ``film_parts`` multiplies in the recipe
    (:class:`FilmQNetwork`), ``shared_parts`` looks both parts up in one ingredient table, and
    ``state_parts`` drops the state's MLP too (its per-dimension embeddings enter the body)."""
    if variant in VARIANTS:
        return ExecutionQNetwork(observation_space, cook.N_ACTIONS, Z_DIM, **VARIANTS[variant])
    kwargs = VARIANTS["wide_parts"]
    if variant == "film_parts":
        return FilmQNetwork(observation_space, cook.N_ACTIONS, Z_DIM, **kwargs)
    q_net = ExecutionQNetwork(observation_space, cook.N_ACTIONS, Z_DIM, **kwargs)
    if variant == "shared_parts":
        q_net.instruction_embed = SharedIngredients(int(observation_space["instruction"].nvec.max()))
    elif variant == "state_parts":
        q_net.state_embed = MultiDiscreteEmbedder(observation_space["obs"].nvec, hidden_dims=())
        in_dim = q_net.state_embed.embed_dim + q_net.instruction_embed.embed_dim + Z_DIM
        q_net.body, _ = relu_mlp(in_dim, kwargs["hidden_sizes"])
    else:
        raise ValueError(f"variant={variant!r} is not one of {[*VARIANTS, *FUSIONS]}")
    return q_net


def probe(variant: str, seed: int, args: argparse.Namespace, data, env, pairs) -> List[dict]:
    th.manual_seed(seed)
    q_net = q_network(variant, env.observation_space)
    encoder = ProblemEncoder(env.problem_nvec, Z_DIM)
    # AdamW: Adam with decoupled weight decay; with --weight-decay 0 (the default) it is Adam.
    optimizer = th.optim.AdamW([*q_net.parameters(), *encoder.parameters()], lr=args.lr, weight_decay=args.weight_decay)
    generator = th.Generator().manual_seed(seed)
    targets = data["targets"]
    start = time.perf_counter()
    for step in range(args.steps):
        if args.targets == "bootstrapped" and step % args.target_update == 0:
            targets = bootstrapped_targets(q_net, encoder, data)
        rows = th.randint(len(data["obs"]), (args.batch_size,), generator=generator)
        error = (dataset_q(q_net, encoder, data, rows) - targets[rows]) ** 2
        if args.actions == "one":  # a replay transition teaches one action's value per state
            error = error.gather(1, th.randint(len(ACTIONS), (len(rows), 1), generator=generator))
        loss = error.mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    seconds = time.perf_counter() - start
    setting = dict(
        variant=variant,
        targets=args.targets,
        actions=args.actions,
        lr=args.lr,
        weight_decay=args.weight_decay,
        batch_size=args.batch_size,
        seed=seed,
        steps=args.steps,
        final_loss=f"{loss.item():.6f}",
    )
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
                dict(
                    **setting,
                    part=name,
                    pairs=int(rows.sum()),
                    greedy_return=f"{got[rows].mean():.3f}",
                    optimal_return=f"{best[rows].mean():.3f}",
                    cooked=f"{np.mean(got[rows] >= best[rows] - 1e-6):.3f}",
                    train_seconds=f"{seconds:.0f}",
                )
            )
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=[*VARIANTS, *FUSIONS])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=20000, help="gradient steps")
    parser.add_argument("--batch-size", type=int, default=512)
    parser.add_argument(
        "--weight-decay",
        type=float,
        default=0.0,
        help="decoupled weight decay (AdamW) on the Q-network and the encoder; 0 is plain Adam",
    )
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate")
    parser.add_argument(
        "--targets",
        default="optimal",
        choices=("optimal", "bootstrapped"),
        help="regress onto Q* (optimal) or onto r + gamma max Q(s') of the network itself, recomputed "
        "every --target-update steps (bootstrapped, as DQN with a target network)",
    )
    parser.add_argument(
        "--actions",
        default="all",
        choices=("all", "one"),
        help="regress every action's value per sampled state, or one uniformly drawn action's (as DQN's replay)",
    )
    parser.add_argument("--target-update", type=int, default=500, help="steps between bootstrapped targets")
    parser.add_argument("--out", default=None, help="CSV to append to (one row per variant, seed and part)")
    args = parser.parse_args()
    for option in ("steps", "batch_size", "target_update"):
        if getattr(args, option) < 1:
            parser.error(f"--{option.replace('_', '-')} must be positive, got {getattr(args, option)}")
    if not args.lr > 0:
        parser.error(f"--lr must be positive, got {args.lr}")
    if not args.weight_decay >= 0:
        parser.error(f"--weight-decay must be non-negative, got {args.weight_decay}")
    th.set_num_threads(1)
    env = gym.make("MetaCook-v0").unwrapped
    pairs = {split: split_pairs(env, split) for split in SPLITS}
    data = dataset(pairs["train"])
    rows = []
    for variant in args.variants:
        for seed in args.seeds:
            for row in probe(variant, seed, args, data, env, pairs):
                rows.append(row)
                print(" ".join(f"{k}={v}" for k, v in row.items()), flush=True)
    if args.out:  # appended to a table of the same columns, so several commands' rows gather in one file
        fields = list(rows[0])
        exists = os.path.exists(args.out) and os.path.getsize(args.out) > 0
        if exists:
            with open(args.out, newline="") as f:
                header = next(csv.reader(f))
            if header != fields:
                raise SystemExit(f"--out {args.out} has the columns {header}, not this script's {fields}")
        with open(args.out, "a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=fields)
            if not exists:
                writer.writeheader()
            writer.writerows(rows)


if __name__ == "__main__":
    main()
