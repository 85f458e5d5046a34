"""What an agent did in MetaCook trials: :func:`behaviour_report`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from dream_envs.agents import ScriptedAgent
from dream_envs.bus import END_EPISODE
from dream_envs.cook.env import MetaCookEnv
from dream_envs.cook.kitchen import (
    DONE_STAGE,
    HELD_OUT_INSTRUCTIONS,
    N_FRIDGES,
    RUINED,
    START,
    cook_transition,
    fridge_contents,
    fridge_picked,
    optimal_execution_return,
    recipe_stage,
)
from dream_envs.report import TrialRecorder, record_trials, unwrap
from dream_envs.trial_env import EXPLORATION


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
        per_recipe = (
            ""
            if not held_out
            else "; held-out recipes finished (optimally): "
            + ", ".join(f"{recipe} {share}" for recipe, share in held_out.items())
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
