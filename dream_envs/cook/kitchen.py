"""MetaCook's kitchen: its layout, problems (the fridges' contents), recipes, splits and rules.

A 3x3 kitchen: the pot in the middle, three fridges on the right whose ingredients (the problem)
are hidden until the agent uses "pickup" at them. Each instruction is a two-ingredient recipe:
put the first ingredient in the pot, then the second. Held-out problems and recipes test
generalisation (the paper's Figure 6, middle).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

# The grid actions and the object codes are MetaBus's (the ride-bus action does nothing in a kitchen).
from dream_envs.bus import DROP, FRIDGE, MOVES, NO_OBJECT, PICKUP, POT
from dream_envs.trial_env import SPLITS

GRID_SIZE = 3
N_INGREDIENTS = 7
N_FRIDGES = 3
N_PROBLEMS = N_INGREDIENTS**N_FRIDGES  # 343
START = POT_POS = (1, 1)
FRIDGE_POS: Tuple[Tuple[int, int], ...] = ((2, 0), (2, 1), (2, 2))  # fridge k stands at (2, k)

STEP_REWARD = -0.1
STAGE_REWARD = 0.25
# Undoing a stage costs the step's -0.1 plus the paper's "penalty of -0.25" (Appendix B.1), as in the
# authors' code. Without the step's share (-0.25 in all), advancing then undoing nets 0 over two
# steps against idling's -0.2, and DQN learns to loop pickup/drop at a fridge (see MetaCookEnv).
UNDO_REWARD = STEP_REWARD - 0.25
DONE_STAGE, RUINED = 4, -1

# Held out for the test split (paper, Appendix B.1): 3 of the 49 recipes (1-based ingredients) and
# round(1% of 343) = 3 problems, drawn once by np.random.default_rng(HELD_OUT_SEED).
HELD_OUT_INSTRUCTIONS: Tuple[Tuple[int, int], ...] = ((3, 6), (7, 1), (5, 4))
HELD_OUT_SEED = 0
N_HELD_OUT_PROBLEMS = round(0.01 * N_PROBLEMS)
HELD_OUT_PROBLEMS: Tuple[int, ...] = tuple(
    sorted(int(k) for k in np.random.default_rng(HELD_OUT_SEED).choice(N_PROBLEMS, N_HELD_OUT_PROBLEMS, replace=False))
)  # (175, 217, 290), i.e. fridges (1, 5, 4), (1, 4, 5), (4, 7, 6)


# The held-out split and its two parts, to tell the two kinds of generalisation apart: an unseen
# kitchen with familiar recipes, and an unseen recipe in a familiar kitchen.
COOK_SPLITS = (*SPLITS, "test_problems", "test_instructions")


def fridge_contents(problem_id: int) -> Tuple[int, int, int]:
    """The problem's triple: fridge ``k`` holds ingredient ``1 + digit k of problem_id in base 7``.

    Digits are least significant first, so ``problem_id = sum_k (contents[k] - 1) * 7**k``.
    """
    return tuple(1 + (int(problem_id) // N_INGREDIENTS**k) % N_INGREDIENTS for k in range(N_FRIDGES))


def problem_id_of(contents: Sequence[int]) -> int:
    """Inverse of :func:`fridge_contents`."""
    if len(contents) != N_FRIDGES or not all(1 <= int(c) <= N_INGREDIENTS for c in contents):
        raise ValueError(f"contents={tuple(contents)!r} must be {N_FRIDGES} ingredients in 1..{N_INGREDIENTS}")
    return sum((int(c) - 1) * N_INGREDIENTS**k for k, c in enumerate(contents))


def valid_instructions(problem_id: int) -> list[Tuple[int, int]]:
    """All recipes of a problem: ordered pairs (repeats allowed) of the ingredients in its fridges."""
    present = sorted(set(fridge_contents(problem_id)))
    return [(a, b) for a in present for b in present]


def recipe_stage(inventory: int, pot: Tuple[int, int], instruction: Sequence[int]) -> int:
    """How far the recipe ``(A, B)`` is: the stage machine's state, a function of the inner state.

    0 nothing done; 1 holding A over an empty pot; 2 A in the pot; 3 A in the pot and holding B;
    4 the pot holds (A, B) (done); -1 ``RUINED``: the pot holds anything else, which no action of
    the episode can undo.
    """
    a, b = int(instruction[0]), int(instruction[1])
    if pot == (0, 0):
        return 1 if inventory == a else 0
    if pot == (a, 0):
        return 3 if inventory == b else 2
    if pot == (a, b):
        return DONE_STAGE
    return RUINED


def cook_transition(
    state: Tuple[int, int, int, int, int],
    action: int,
    contents: Sequence[int],
    instruction: Optional[Sequence[int]],
    undo_reward: float = UNDO_REWARD,
) -> Tuple[Tuple[int, int, int, int, int], float, bool]:
    """The inner MDP: ``(x, y, inventory, pot1, pot2), action -> (next state, reward, done)``.

    Pure, so that tests can search the MDP exhaustively. Not for the end-episode action (handled by
    :class:`~dream_envs.trial_env.TrialEnv`). With ``instruction=None`` (reward-free) the reward is 0 and
    ``done`` is False. ``undo_reward`` is the reward of a step that sets the recipe back.
    """
    x, y, inventory, pot1, pot2 = state
    if action in MOVES:
        dx, dy = MOVES[action]
        x, y = min(max(x + dx, 0), GRID_SIZE - 1), min(max(y + dy, 0), GRID_SIZE - 1)
    elif action == PICKUP:
        if x == 2:  # fridge k is at (2, k); a fridge never runs out, the held ingredient is let go
            inventory = int(contents[y])
    elif action == DROP and inventory:
        if (x, y) == POT_POS:
            if pot1 == 0:
                pot1, inventory = inventory, 0
            elif pot2 == 0:
                pot2, inventory = inventory, 0
            # a full pot takes nothing: the ingredient stays in the inventory
        else:
            inventory = 0  # discarded (putting it back into a fridge is the same: fridges never run out)
    next_state = (x, y, inventory, pot1, pot2)
    if instruction is None:
        return next_state, 0.0, False
    before = recipe_stage(state[2], (state[3], state[4]), instruction)
    after = recipe_stage(inventory, (pot1, pot2), instruction)
    if after > before:
        reward = STAGE_REWARD
    elif after < before:
        reward = undo_reward
    else:
        reward = STEP_REWARD
    return next_state, reward, after == DONE_STAGE


def object_at(x: int, y: int) -> int:
    if (x, y) == POT_POS:
        return POT
    if x == 2:
        return FRIDGE
    return NO_OBJECT


def fridge_picked(x: int, y: int, action: int) -> Optional[int]:
    """The fridge that ``action`` picks from at position (x, y), or None (not a pickup at a fridge)."""
    return y if action == PICKUP and object_at(x, y) == FRIDGE else None


def first_openings(states: np.ndarray, actions: np.ndarray) -> List[Tuple[int, int]]:
    """The (step, fridge) pairs at which an exploration trajectory (``states`` s_0.. with the
    position first, ``actions`` a_0..) first picks from each fridge, in the order it opens them."""
    opened: Dict[int, int] = {}
    for t, action in enumerate(actions):
        k = fridge_picked(int(states[t][0]), int(states[t][1]), int(action))
        if k is not None and k not in opened:
            opened[k] = t
    return [(t, k) for k, t in opened.items()]


def opening_rewards(
    trajectories: Sequence[Tuple[np.ndarray, np.ndarray]], rewards: Sequence[np.ndarray]
) -> Dict[Tuple[int, int], np.ndarray]:
    """The reward of each fridge's first opening over exploration trajectories (states, actions)
    and their per-step ``rewards`` (DREAM's: ``sb3_dream.dream.exploration_gains``), keyed by
    (fridge, order): order j for the (j+1)-th fridge a trajectory opened. Sorted by key."""
    found: Dict[Tuple[int, int], List[float]] = {}
    for (states, actions), reward in zip(trajectories, rewards):
        for order, (t, k) in enumerate(first_openings(states, actions)):
            found.setdefault((k, order), []).append(float(reward[t]))
    return {key: np.array(found[key]) for key in sorted(found)}


def distance_to_fridge(k: int) -> int:
    """Steps from the pot to fridge ``k`` (Manhattan: the grid has no walls)."""
    return abs(FRIDGE_POS[k][0] - POT_POS[0]) + abs(FRIDGE_POS[k][1] - POT_POS[1])


def optimal_execution_return(problem_id: int, instruction: Sequence[int]) -> float:
    """Return of the optimal execution episode with the fridges' contents known (default rewards).

    Fetch each ingredient from the nearest fridge holding it and carry it back: with ``d_X`` = 1
    if the middle fridge (2, 1) holds X, else 2 (the corner fridges), the episode takes
    ``4 + 2 (d_A + d_B)`` steps (8, 10 or 12) and returns ``4 * 0.25 - 0.1 * 2 (d_A + d_B)``,
    i.e. 0.6, 0.4 or 0.2. (Needs a horizon of at least 12 steps.)
    """
    contents = fridge_contents(problem_id)
    d = [min(distance_to_fridge(k) for k in range(N_FRIDGES) if contents[k] == int(i)) for i in instruction]
    return 4 * STAGE_REWARD + 2 * STEP_REWARD * sum(d)


@lru_cache(maxsize=None)
def split_tables() -> Dict[str, Tuple[np.ndarray, Dict[int, Tuple[Tuple[int, int], ...]]]]:
    """Per split: the sorted problem IDs and each problem's instructions."""
    held_problems, held_instr = set(HELD_OUT_PROBLEMS), set(HELD_OUT_INSTRUCTIONS)
    tables = {}
    for split in COOK_SPLITS:
        instructions: Dict[int, Tuple[Tuple[int, int], ...]] = {}
        for k in range(N_PROBLEMS):
            valid = valid_instructions(k)
            if split == "all":
                chosen = valid
            elif split == "train":
                chosen = [] if k in held_problems else [i for i in valid if i not in held_instr]
            elif split == "test":
                chosen = valid if k in held_problems else [i for i in valid if i in held_instr]
            elif split == "test_problems":
                chosen = [i for i in valid if i not in held_instr] if k in held_problems else []
            else:  # "test_instructions"
                chosen = [] if k in held_problems else [i for i in valid if i in held_instr]
            if chosen:
                instructions[k] = tuple(chosen)
        tables[split] = (np.array(sorted(instructions), dtype=np.int64), instructions)
    return tables
