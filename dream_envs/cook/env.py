"""MetaCook-v0: the paper's cooking domain (Section 6.1, Figure 4b, Appendix B.1), as a trial env."""

from __future__ import annotations

import numbers
from typing import Optional, Tuple

import cv2
import numpy as np
from gymnasium import spaces

from dream_envs.bus import ACTION_NAMES as GRID_ACTION_NAMES
from dream_envs.bus import END_EPISODE, N_ACTIONS
from dream_envs.checks import check_choice, check_positive_int
from dream_envs.cook.kitchen import (
    COOK_SPLITS,
    FRIDGE_POS,
    GRID_SIZE,
    N_FRIDGES,
    N_INGREDIENTS,
    N_PROBLEMS,
    POT_POS,
    RUINED,
    START,
    STEP_REWARD,
    UNDO_REWARD,
    cook_transition,
    fridge_contents,
    object_at,
    recipe_stage,
    split_tables,
    valid_instructions,
)
from dream_envs.cook.oracle import CookOracle
from dream_envs.rendering import COLORS, PALETTE, GridCanvas
from dream_envs.trial_env import EXPLORATION, TrialEnv


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
    such a loop costs only discounting, and an execution policy can settle on looping pickup/drop
    at a fridge until the horizon (the MetaCook results in the docs show it).

    **Termination.** An inner episode ends when the recipe is done (stage 4), on the end-episode
    action, or after ``horizon`` steps. In reward-free exploration only the last two apply. The
    trial ends after the last execution episode.

    **Returns.** With the contents known, the optimal execution return is
    ``1 - 0.2 (d_A + d_B)`` with ``d_X`` = 1 if the middle fridge holds X, else 2: 0.6, 0.4 or
    0.2 (:func:`optimal_execution_return`; needs a horizon of 12 or more). The mean over the
    split's trials is 0.364 on "train", 0.343 on "test" (0.328 on "test_problems", 0.343 on
    "test_instructions"). The optimal explorer opens the three fridges in 7 steps and ends the episode
    (:meth:`oracle`).

    :param split: "train", "test", "all", "test_problems" or "test_instructions" (see above).
    :param n_exec_episodes: execution episodes per trial.
    :param horizon: inner-episode horizon (default 20, the paper's).
    :param reward_free_exploration: see :class:`~dream_envs.trial_env.TrialEnv`.
    :param undo_reward: the reward of a step that sets the recipe back (default -0.35, see above).
    :param render_mode: ``None`` or ``"rgb_array"``.
    :param final_frames: see :class:`~dream_envs.trial_env.TrialEnv` (pictures of each inner episode's
        last state in ``info``).
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
        final_frames: bool = False,
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
            final_frames=final_frames,
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
        return split_tables()[split][0].copy()

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
        return list(split_tables()[split][1].get(int(problem_id), ()))

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
