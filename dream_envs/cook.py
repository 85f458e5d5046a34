"""MetaCook-v0: the paper's cooking domain (Section 6.1, Figure 4b, Appendix B.1).

A 3x3 kitchen: the pot in the middle, three fridges on the right whose ingredients (the problem)
are hidden until the agent uses "pickup" at them. Each instruction is a two-ingredient recipe:
put the first ingredient in the pot, then the second. Held-out problems and recipes test
generalisation (the paper's Figure 6, middle).
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np
from gymnasium import spaces

from dream_envs.agents import ScriptedAgent

# The grid actions and the object codes are MetaBus's (the ride-bus action does nothing in a kitchen).
from dream_envs.bus import ACTION_NAMES as GRID_ACTION_NAMES
from dream_envs.bus import DOWN, DROP, END_EPISODE, FRIDGE, LEFT, MOVES, N_ACTIONS, NO_OBJECT, PICKUP, POT, RIGHT, UP
from dream_envs.bus import NOOP, RIDE as RIDE_BUS  # noqa: F401 (unused here: this module's names for all 9 actions)
from dream_envs.checks import check_choice, check_positive_int
from dream_envs.rendering import COLORS, PALETTE, GridCanvas
from dream_envs.report import TrialRecorder, record_trials, unwrap
from dream_envs.trial_env import EXPLORATION, SPLITS, TrialEnv

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
def _split_tables() -> Dict[str, Tuple[np.ndarray, Dict[int, Tuple[Tuple[int, int], ...]]]]:
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


class MetaCookEnv(TrialEnv):
    """Cooking in a kitchen whose fridges' contents are found only by opening them.

    **Kitchen.** A 3x3 grid, (0, 0) bottom-left. The pot is at (1, 1), where every inner episode
    starts (empty inventory, empty pot). Fridges 0, 1, 2 stand at (2, 0), (2, 1), (2, 2), each
    holding an unlimited supply of one of 7 ingredients (1..7; several fridges may hold the same).

    **Problems.** The 7^3 = 343 triples of fridge contents: fridge ``k`` holds ingredient
    ``1 + (problem_id // 7**k) % 7`` (base 7, least significant digit first; see
    :func:`fridge_contents` and :func:`problem_id_of`).

    **Instructions.** A recipe ``[A, B]`` (ingredients 1..7; ``[0, 0]`` = none, in reward-free
    exploration): put A in the pot, then B. Only recipes of ingredients present in the problem are
    sampled (repeats allowed, so a problem has 1, 4 or 9 recipes), uniformly among those of the
    split. A pinned ``options["instruction"]`` must be such a recipe (any split's).

    **Splits.** Held out: ``HELD_OUT_PROBLEMS`` = round(1% of 343) = 3 problems drawn by
    ``np.random.default_rng(0)`` (IDs 175, 217, 290) and the recipes ``HELD_OUT_INSTRUCTIONS`` =
    (3, 6), (7, 1), (5, 4). A trial is held out if its problem or its recipe is.

    * ``"train"``: the 340 other problems, each with its recipes that are not held out (every
      problem keeps its single-ingredient recipes (X, X), so none is empty): 2268 pairs.
    * ``"test"``: every held-out trial: the 3 held-out problems with any of their recipes, and the
      other problems holding both ingredients of a held-out recipe, with only those recipes: 109
      problems (36 triples hold both ingredients of a given held-out recipe, no triple holds two
      such pairs, and two of the held-out problems are among them), 133 (problem, recipe) pairs.
      Every test problem thus has a held-out recipe.
    * ``"all"``: the 343 problems with all their recipes (2401 pairs).
    * ``"test_problems"``: the part of ``"test"`` that tests an unseen kitchen alone: the 3 held-out
      problems with their recipes that are not held out (25 pairs).
    * ``"test_instructions"``: the part that tests an unseen recipe alone: the 106 training
      problems holding both ingredients of a held-out recipe, with only those recipes (106 pairs).
      ``"test"`` is these two and the 2 pairs that are both (a held-out recipe in a held-out
      kitchen); most of its trials are of ``"test_instructions"``.

    In every split a problem is drawn uniformly from the split's, then a recipe uniformly from the
    problem's recipes in the split.

    A problem pinned outside the split gets the split's recipes for it if it has any, else all of
    its recipes.

    **Actions.** ``Discrete(9)``: 0 left (x-1), 1 up (y+1), 2 right (x+1), 3 down (y-1) (moves
    stop at the border), 4 no-op, 5 ride bus (a no-op here: grid envs share actions), 6 end the
    inner episode, 7 pickup: at a fridge, the inventory becomes its ingredient (whatever was held is
    let go); elsewhere nothing, 8 drop: at the pot, the held ingredient goes into the first free
    slot (a full pot takes nothing and it stays held); elsewhere it is discarded (back into a
    fridge amounts to the same, fridges never run out); with nothing held, nothing.

    **Observation** ``obs`` = ``[x, y, object, inventory, pot slot 1, pot slot 2]``, MultiDiscrete
    ``[3, 3, 5, 8, 8, 8]``: the object under the agent is coded 0 none, 1 bus, 2 map, 3 pot,
    4 fridge (only 0, 3, 4 occur here); ingredients 1..7, 0 = empty. A fridge's content shows
    only as the inventory after a pickup there, so the first observation is the same in every
    problem.

    **Rewards** (the paper's shaped reward, Appendix B.1), a stage machine over the inner state,
    see :func:`recipe_stage`: stage 0, then (i) pick up A -> 1, (ii) drop it in the pot -> 2,
    (iii) pick up B -> 3, (iv) drop it in the pot -> 4. A step that advances the stage earns
    +0.25 (instead of -0.1); a step that sets it back costs -0.35 (the step's -0.1 and the paper's
    penalty of -0.25, as in the authors' code; ``undo_reward``): letting go of a needed ingredient
    (dropping it away from the pot, or picking up another one over it) returns to the previous
    stage, and a drop that puts a wrong ingredient into the pot ruins the dish (stage -1 until the
    episode ends: nothing more can be earned). Every other step costs -0.1.
    The end-episode action costs -0.1 for each step left (itself included): the same as idling to
    the horizon, so quitting is no escape from the step penalty. Exploration is reward-free by
    default (no instruction, reward 0, the dynamics unchanged). An advance followed by an undo
    nets -0.1 over two steps (idling: -0.2) and never raises the optimal return: every ingredient
    is within 2 steps of the pot, so finishing the recipe always pays more. With
    ``undo_reward=-0.25`` (the paper's penalty read as replacing the step's) the pair nets 0, so
    such a loop costs only discounting: a DQN execution policy trained that way learned to loop
    pickup/drop at a fridge until the horizon (see the MetaCook results in docs/results/metacook.md).

    **Termination.** An inner episode ends when the recipe is done (stage 4), on the end-episode
    action, or after ``horizon`` steps. In reward-free exploration only the last two apply. The
    trial ends after the last execution episode.

    **Returns.** With the contents known, the optimal execution return is
    ``1 - 0.2 (d_A + d_B)`` with ``d_X`` = 1 if the middle fridge holds X, else 2: 0.6, 0.4 or
    0.2 (:func:`optimal_execution_return`; needs a horizon of 12 or more). The mean over the
    split's trials is 0.364 on "train", 0.343 on "test" (0.328 on "test_problems", 0.343 on
    "test_instructions"); uniformly random actions get about
    -1.98. The optimal explorer opens the three fridges in 7 steps and ends the episode
    (:meth:`oracle`).

    :param split: "train", "test", "all", "test_problems" or "test_instructions" (see above).
    :param n_exec_episodes: execution episodes per trial.
    :param horizon: inner-episode horizon (default 20, the paper's).
    :param reward_free_exploration: see :class:`~dream_envs.trial_env.TrialEnv`.
    :param undo_reward: the reward of a step that sets the recipe back (default -0.35, see above).
    :param render_mode: ``None`` or ``"rgb_array"``.
    """

    splits = COOK_SPLITS
    action_names = GRID_ACTION_NAMES

    def __init__(
        self,
        split: str = "train",
        n_exec_episodes: int = 1,
        horizon: int = 20,
        reward_free_exploration: bool = True,
        undo_reward: float = UNDO_REWARD,
        render_mode: Optional[str] = None,
    ) -> None:
        horizon = check_positive_int("horizon", horizon)
        # numbers.Real, so numpy scalars (e.g. from a config array) pass; bool is no penalty
        if isinstance(undo_reward, bool) or not isinstance(undo_reward, numbers.Real) or not -1 <= undo_reward <= 0:
            raise ValueError(f"undo_reward={undo_reward!r} must be a penalty, a number in [-1, 0]")
        self.undo_reward = float(undo_reward)
        super().__init__(
            inner_observation_space=spaces.MultiDiscrete([GRID_SIZE, GRID_SIZE, 5] + [N_INGREDIENTS + 1] * 3),
            instruction_nvec=[N_INGREDIENTS + 1, N_INGREDIENTS + 1],
            n_actions=N_ACTIONS,
            end_episode_action=END_EPISODE,
            split=split,
            n_exec_episodes=n_exec_episodes,
            horizon=horizon,
            reward_free_exploration=reward_free_exploration,
            render_mode=render_mode,
            # the end-episode action can cost 0.1 per remaining step
            reward_bound=max(1.0, -STEP_REWARD * horizon),
        )
        self._contents: Tuple[int, int, int] = (0, 0, 0)
        self._state: Tuple[int, int, int, int, int] = (*START, 0, 0, 0)

    # ------------------------------------------------------------------ problem family
    @property
    def n_problems(self) -> int:
        return N_PROBLEMS

    def _split_problem_ids(self, split: str) -> np.ndarray:
        return _split_tables()[split][0].copy()

    @property
    def problem_nvec(self) -> np.ndarray:
        # Appendix B.1: the problem is the triple of the fridges' ingredients.
        return np.array([N_INGREDIENTS] * N_FRIDGES, dtype=np.int64)

    def problem_features(self, problem_id: int) -> np.ndarray:
        """The fridge triple, 0-based: ``[ingredient of fridge k - 1 for k in 0, 1, 2]``."""
        return np.array(fridge_contents(problem_id), dtype=np.int64) - 1

    def instructions(self, problem_id: int, split: Optional[str] = None) -> list[Tuple[int, int]]:
        """The recipes of ``problem_id`` in ``split`` (default: this env's split); empty if none."""
        split = self.split if split is None else check_choice("split", split, self.splits)
        return list(_split_tables()[split][1].get(int(problem_id), ()))

    def _instruction_choices(self, problem_id: int, split: str) -> np.ndarray:
        # A problem pinned outside the split has no recipe of it: fall back to all its recipes.
        return np.array(self.instructions(problem_id, split) or valid_instructions(problem_id), dtype=np.int64)

    def _check_instruction(self, problem_id: int, instruction: np.ndarray) -> None:
        present = sorted(set(fridge_contents(problem_id)))
        if not all(int(i) in present for i in instruction):
            raise ValueError(
                f"options['instruction']={instruction.tolist()!r} is not valid for problem {problem_id}: "
                f"both ingredients must be in its fridges {fridge_contents(problem_id)}; "
                f"accepted values: {[list(i) for i in valid_instructions(problem_id)]}"
            )

    def _set_problem(self, problem_id: int) -> None:
        self._contents = fridge_contents(problem_id)

    # ------------------------------------------------------------------ inner MDP
    def _inner_obs_array(self) -> np.ndarray:
        x, y, inventory, pot1, pot2 = self._state
        return np.array([x, y, object_at(x, y), inventory, pot1, pot2], dtype=np.int64)

    def _inner_reset(self) -> np.ndarray:
        self._state = (*START, 0, 0, 0)
        return self._inner_obs_array()

    def _inner_step(self, action: int) -> tuple[np.ndarray, float, bool]:
        self._state, reward, done = cook_transition(
            self._state, action, self._contents, self.instruction, self.undo_reward
        )
        return self._inner_obs_array(), reward, done

    def _end_episode_reward(self, steps_remaining: int) -> float:
        return STEP_REWARD * steps_remaining

    @property
    def stage(self) -> Optional[int]:
        """The recipe's stage (see :func:`recipe_stage`), ``None`` without an instruction."""
        if self.instruction is None:
            return None
        return recipe_stage(self._state[2], self._state[3:5], self.instruction)

    # ------------------------------------------------------------------ rendering
    def _render_frame(self) -> np.ndarray:
        cell = 80
        canvas = GridCanvas(GRID_SIZE, GRID_SIZE, cell=cell, caption_lines=3)
        image = canvas.image
        x, y, inventory, pot1, pot2 = self._state
        # Each cell: a label or the pot's slots in its upper half, the agent and what it holds below.
        canvas.fill(*POT_POS, COLORS["gray"], inset=6)
        px, py = canvas.center(*POT_POS)
        _label(image, "pot", (px, py - 26), (255, 255, 255))
        for slot, content in enumerate((pot1, pot2)):
            _ingredient(image, (px - 13 + 26 * slot, py - 6), content, outline=(255, 255, 255))
        # Fridges, coloured by their content (hidden from the agent), so the picture shows the problem.
        for k, (fx, fy) in enumerate(FRIDGE_POS):
            canvas.fill(fx, fy, PALETTE[self._contents[k] - 1], inset=6)
            fcx, fcy = canvas.center(fx, fy)
            _label(image, f"F{k}: {self._contents[k]}", (fcx, fcy - 20), (255, 255, 255))
        ax, ay = canvas.center(x, y)
        ax, ay = ax - 14, ay + 18
        r = 13
        triangle = np.array([[ax, ay - r], [ax - r, ay + r // 2 + 4], [ax + r, ay + r // 2 + 4]], np.int32)
        cv2.fillPoly(image, [triangle], COLORS["agent"], lineType=cv2.LINE_AA)
        cv2.polylines(image, [triangle], True, (255, 255, 255), 1, cv2.LINE_AA)
        if inventory:
            _ingredient(image, (ax + 28, ay + 1), inventory, outline=COLORS["agent"])
        phase = "explore" if self.phase == EXPLORATION else f"execute {self.episode_index}"
        canvas.caption(f"MetaCook {self.problem_id}: fridges {self._contents}")
        holding = f"holding {inventory}" if inventory else "empty-handed"
        if self.instruction is None:
            canvas.caption(f"{phase} t={self._t}, no recipe")
            canvas.caption(holding)
        else:
            a, b = (int(i) for i in self.instruction)
            stage = self.stage
            canvas.caption(f"{phase} t={self._t}, recipe {a} then {b}")
            canvas.caption(f"{holding}, stage {'ruined' if stage == RUINED else f'{stage}/4'}")
        return canvas.frame()

    # ------------------------------------------------------------------ oracle
    def oracle(self) -> "CookOracle":
        return CookOracle()


def _label(image: np.ndarray, text: str, center: Tuple[int, int], color) -> None:
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.4, 1)
    org = (center[0] - tw // 2, center[1] + th // 2)
    cv2.putText(image, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, color, 1, cv2.LINE_AA)


def _ingredient(image: np.ndarray, center: Tuple[int, int], content: int, outline) -> None:
    """A square in the ingredient's colour with its number; an empty outline for 0."""
    p0, p1 = (center[0] - 10, center[1] - 10), (center[0] + 10, center[1] + 10)
    if content:
        cv2.rectangle(image, p0, p1, PALETTE[content - 1], -1)
        _label(image, str(content), center, (255, 255, 255))
    cv2.rectangle(image, p0, p1, outline, 1)


def _step_towards(x: int, y: int, target: Tuple[int, int]) -> int:
    """First move of a shortest path (x first, then y)."""
    tx, ty = target
    if x != tx:
        return RIGHT if tx > x else LEFT
    return UP if ty > y else DOWN


class CookOracle(ScriptedAgent):
    """Optimal scripted agent: open every fridge, then cook from memory.

    Exploration: go to the nearest unopened fridge and pick up there (right, pickup, down, pickup,
    up, up, pickup: 7 steps), then the end-episode action. A pickup's result is read from the
    inventory of the next observation or, when that step ended the episode, from
    ``info["final_obs"]``. Execution: for each ingredient still needed, go to the nearest fridge
    known to hold it, pick up, return to the pot and drop; this is optimal (see
    :func:`optimal_execution_return`). If the exploration was cut short, an ingredient missing from
    the opened fridges is in an unopened one: the only one, or else the nearest is opened.

    (Opening the middle fridge and one corner one would already suffice for optimal execution:
    recipes use only present ingredients and both corners are 2 steps from the pot. The oracle
    opens all three, like DREAM's learned exploration in the paper's Figure 8.)
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.known: Dict[int, int] = {}  # fridge index -> ingredient

    def _observe(self, obs: Dict[str, Any], info: Dict[str, Any]) -> None:
        if int(obs["prev_action"]) - 1 != PICKUP:
            return
        # The state reached by the pickup: the episode's last one if that step ended it.
        state = info["final_obs"] if info.get("episode_end") else obs["obs"]
        x, y, obj, inventory = (int(v) for v in state[:4])
        if obj == FRIDGE and inventory:
            self.known[y] = inventory

    def _fridge_for(self, ingredient: int, x: int, y: int) -> Tuple[int, bool]:
        """The fridge to fetch ``ingredient`` from, and whether it is known to hold it."""
        dist = lambda k: abs(FRIDGE_POS[k][0] - x) + abs(FRIDGE_POS[k][1] - y)  # noqa: E731
        holding = [k for k, c in self.known.items() if c == ingredient]
        unknown = [k for k in range(N_FRIDGES) if k not in self.known]
        if holding:
            # Nearest to the pot, where every fetch starts and ends.
            return min(holding, key=distance_to_fridge), True
        if len(unknown) == 1:
            return unknown[0], True
        return min(unknown or range(N_FRIDGES), key=dist), False

    def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
        self._observe(obs, info)
        x, y, _, inventory, pot1, pot2 = (int(v) for v in obs["obs"])
        if int(obs["phase"]) == EXPLORATION:
            unknown = [k for k in range(N_FRIDGES) if k not in self.known]
            if not unknown:
                return END_EPISODE
            target = min(unknown, key=lambda k: abs(FRIDGE_POS[k][0] - x) + abs(FRIDGE_POS[k][1] - y))
            return PICKUP if (x, y) == FRIDGE_POS[target] else _step_towards(x, y, FRIDGE_POS[target])

        a, b = (int(i) for i in obs["instruction"])
        stage = recipe_stage(inventory, (pot1, pot2), (a, b))
        if stage in (1, 3):  # holding the next ingredient: bring it to the pot
            return DROP if (x, y) == POT_POS else _step_towards(x, y, POT_POS)
        if stage in (0, 2):  # fetch the next ingredient
            fridge, _ = self._fridge_for(a if stage == 0 else b, x, y)
            target = FRIDGE_POS[fridge]
            return PICKUP if (x, y) == target else _step_towards(x, y, target)
        return END_EPISODE  # ruined dish (never by this agent): nothing left to earn


# ---------------------------------------------------------------------------------- behaviour report
@dataclass
class CookReport:
    """What an agent did in MetaCook trials (the paper's Figure 8 in numbers).

    Per trial: how many fridges it opened (picked from) while exploring, and the exploration
    length. Per execution episode: its return next to the optimal one for its problem and recipe,
    the recipe stage it ended at (:func:`recipe_stage`: 4 finished, -1 ruined dish), and how many
    of its steps set the recipe back (an undo: letting go of a needed ingredient). Undos in
    episodes that end unfinished are the sign of a policy that loops pickup/drop instead of cooking.
    ``second_picks`` says what the agent fetched once A was in the pot: a policy that has learned
    recipes as whole pairs, not as "A, then B", fetches the second ingredient of a recipe it was
    trained on (A again, or another) when given an unseen pair (see :meth:`second_pick_counts`).
    """

    fridges_opened: np.ndarray  # [n_trials] 0..3
    exploration_lengths: np.ndarray  # [n_trials]
    execution_returns: np.ndarray  # [n_episodes]
    optimal_returns: np.ndarray  # [n_episodes]
    stages: np.ndarray  # [n_episodes] RUINED, 0..DONE_STAGE
    undos: np.ndarray  # [n_episodes] steps that set the recipe back
    instructions: np.ndarray  # [n_episodes, 2] the recipe (A, B)
    # [n_episodes] the ingredient of the first pickup once A was in the pot: 0 none, -1 A never was
    second_picks: np.ndarray

    @property
    def finished(self) -> np.ndarray:
        return self.stages == DONE_STAGE

    @property
    def finished_optimally(self) -> np.ndarray:
        """Per execution episode: its return is the optimal one (finished in the fewest steps)."""
        return np.isclose(self.execution_returns, self.optimal_returns)

    @property
    def ruined(self) -> np.ndarray:
        return self.stages == RUINED

    def stage_counts(self) -> Dict[int, int]:
        """How many execution episodes ended at each stage (RUINED, 0, ..., DONE_STAGE)."""
        return {stage: int((self.stages == stage).sum()) for stage in range(RUINED, DONE_STAGE + 1)}

    def second_pick_counts(self) -> Dict[str, int]:
        """Of the episodes that put A in the pot, how many then fetched B (right), A again, another
        ingredient, or none."""
        a, b, pick = self.instructions[:, 0], self.instructions[:, 1], self.second_picks
        reached = pick >= 0
        return {
            "B": int((reached & (pick == b)).sum()),
            "A": int((reached & (pick == a) & (pick != b)).sum()),
            "other": int((reached & (pick > 0) & (pick != a) & (pick != b)).sum()),
            "none": int((pick == 0).sum()),
        }

    def by_recipe(self, recipes: Sequence[Tuple[int, int]] = HELD_OUT_INSTRUCTIONS) -> Dict[Tuple[int, int], str]:
        """Per recipe among ``recipes`` that the episodes met (default: the held-out ones): the
        share of its episodes finished and, in brackets, finished optimally, e.g. ``"61% (28%)"``."""
        optimal = self.finished_optimally
        shares = {}
        for recipe in recipes:
            mine = (self.instructions == np.asarray(recipe)).all(axis=1)
            if mine.any():
                shares[tuple(recipe)] = f"{self.finished[mine].mean():.0%} ({optimal[mine].mean():.0%})"
        return shares

    def summary(self) -> str:
        counts = np.bincount(self.fridges_opened, minlength=N_FRIDGES + 1)
        held_out = self.by_recipe()
        per_recipe = "" if not held_out else "; held-out recipes finished (optimally): " + ", ".join(
            f"{recipe} {share}" for recipe, share in held_out.items()
        )
        return (
            f"fridges opened while exploring {self.fridges_opened.mean():.2f} (trials with 0..3: {counts.tolist()}), "
            f"exploration length {self.exploration_lengths.mean():.1f}, "
            f"execution return {self.execution_returns.mean():.3f} (optimal {self.optimal_returns.mean():.3f}); "
            f"recipe finished in {self.finished.mean():.0%} of execution episodes "
            f"({self.finished_optimally.mean():.0%} optimally), "
            f"dish ruined in {self.ruined.mean():.0%}, undos per episode {self.undos.mean():.2f} "
            f"(episodes with one: {(self.undos > 0).mean():.0%}); episodes ending at stage -1..4: "
            f"{list(self.stage_counts().values())}; with A in the pot, fetched next: {self.second_pick_counts()}"
            f"{per_recipe}"
        )


class _CookRecorder(TrialRecorder):
    """Notes the fridges the agent picks from while exploring and each execution episode's recipe
    and actions, and replays those with the trial's problem (never shown to the agent)."""

    def start_trial(self) -> None:
        self.opened: set = set()
        self.episodes: List[Tuple[Tuple[int, int], List[int]]] = []

    def note(self, obs: Dict[str, Any], info: Dict[str, Any], action: int) -> None:
        x, y = int(obs["obs"][0]), int(obs["obs"][1])
        if int(obs["phase"]) == EXPLORATION:
            if fridge_picked(x, y, action) is not None:
                self.opened.add(y)
        else:
            if int(obs["episode_start"]):
                self.episodes.append((tuple(int(i) for i in obs["instruction"]), []))
            self.episodes[-1][1].append(action)

    def trial_row(self, result: Dict[str, Any]) -> Tuple[Any, ...]:
        return len(self.opened), result["exploration_length"]

    def episode_rows(self, result: Dict[str, Any]) -> List[Tuple[Any, ...]]:
        problem_id = int(result["problem_id"])
        contents = fridge_contents(problem_id)
        rows = []
        for (instruction, actions), ret in zip(self.episodes, result["execution_returns"]):
            stage, undos, second_pick = _replay_execution(contents, instruction, actions)
            optimal = optimal_execution_return(problem_id, instruction)
            rows.append((ret, optimal, stage, undos, instruction, second_pick))
        return rows


def _replay_execution(
    contents: Sequence[int], instruction: Tuple[int, int], actions: Sequence[int]
) -> Tuple[int, int, int]:
    """The stage an execution episode's ``actions`` reach, how many of them set the recipe back, and
    the ingredient first picked up once A was in the pot (0 none, -1 if A never was)."""
    state, stage, undos, second_pick = (*START, 0, 0, 0), 0, 0, -1
    for action in actions:
        if action == END_EPISODE:
            break
        state, _, _ = cook_transition(state, action, contents, None)
        new_stage = recipe_stage(state[2], (state[3], state[4]), instruction)
        if second_pick == -1 and state[3] == instruction[0]:
            second_pick = 0  # A is in the pot (a wrong first drop ruins the dish and never gets here)
        elif second_pick == 0 and fridge_picked(state[0], state[1], action) is not None:
            second_pick = state[2]
        undos += new_stage < stage
        stage = new_stage
    return stage, undos, second_pick


def behaviour_report(
    env: MetaCookEnv,
    agent: ScriptedAgent,
    n_trials: int = 100,
    seed: int = 0,
    problem_ids: Optional[Sequence[int]] = None,
    instructions: Optional[Sequence[Any]] = None,
) -> CookReport:
    """Play ``n_trials`` trials of ``agent`` (a :class:`~dream_envs.agents.ScriptedAgent`; for a model
    use ``sb3_dream.evaluation.as_trial_agent(model)``) and report its exploration and execution.

    The problem ID is read from the env's ``info`` after each trial, to replay the execution
    episodes through :func:`cook_transition`; the agent never sees it. ``problem_ids`` pins trial k
    to ``problem_ids[k % len(problem_ids)]``, and ``instructions`` (one per problem ID) its
    execution episodes' instruction likewise.
    """
    cook = unwrap(env, MetaCookEnv, "MetaCook-v0")
    trials, episodes = record_trials(env, _CookRecorder(agent, cook), n_trials, seed, problem_ids, instructions)
    opened, lengths = trials
    returns, optimal, stages, undos, recipes, second_picks = episodes
    return CookReport(opened, lengths, returns, optimal, stages, undos, recipes, second_picks)
