"""What an agent's SignNav3D trials showed it: :func:`exploration_report`."""

from __future__ import annotations

import dataclasses
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from dream_envs.agents import ScriptedAgent
from dream_envs.checks import check_positive_int
from dream_envs.report import TrialRecorder, record_trials, unwrap
from dream_envs.sign_nav.env import SignNav3DEnv
from dream_envs.sign_nav.layout import (
    END_EPISODE,
    EXECUTION_OUTCOMES,
    EXECUTION_TARGETS,
    LOWER_ROOMS_Z,
    READ_MIN_PIXELS,
    execution_target,
)
from dream_envs.trial_env import EXPLORATION


@dataclasses.dataclass
class SignExplorationReport:
    """What an agent's SignNav3D exploration episodes showed it, one entry per trial: the most pixels
    of the sign's letters in one view (what DREAM's decoder needs to tell the problems apart) and
    whether the agent got past the barrier at all. The sign counts as *read* in a trial whose
    exploration showed at least ``min_pixels`` of them in one view (default :data:`READ_MIN_PIXELS`,
    as many strongly coloured pixels as :func:`sign_colour_from_image` needs). The sign can be read from the top room
    too: from its southern edge, facing east, through the opening to the left room (e.g. from (4, 6)),
    as in the authors' layout.

    Counted over the states the agent acted in during exploration; the last state of an exploration
    that the horizon or a touch ended is not among them (it is when the end-episode action ends it).

    Each execution episode is also recorded by its *target* (the object of the sign's colour and the
    instruction's type) and how it ended (:data:`EXECUTION_OUTCOMES`): which objects an execution
    policy reaches, and whether the others time out (it wanders) or are given up (end action).
    """

    sign_pixels: np.ndarray  # [n_trials] the most letter pixels in one exploration view
    past_barrier: np.ndarray  # [n_trials] bool
    exploration_lengths: np.ndarray  # [n_trials]
    execution_returns: np.ndarray  # [n_trials] mean over the trial's execution episodes
    min_pixels: int = READ_MIN_PIXELS
    execution_targets: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, int))  # [n_episodes]
    execution_outcomes: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, int))  # [n_episodes]

    def outcome_counts(self) -> Dict[Tuple[str, str], Dict[str, int]]:
        """``{(colour, type): {outcome: execution episodes}}`` for every target that was drawn."""
        counts: Dict[Tuple[str, str], Dict[str, int]] = {}
        for target, outcome in zip(self.execution_targets, self.execution_outcomes):
            per_target = counts.setdefault(EXECUTION_TARGETS[target], dict.fromkeys(EXECUTION_OUTCOMES, 0))
            per_target[EXECUTION_OUTCOMES[outcome]] += 1
        return dict(sorted(counts.items(), key=lambda item: EXECUTION_TARGETS.index(item[0])))

    @property
    def sign_seen(self) -> np.ndarray:
        """[n_trials] bool: the exploration showed at least ``min_pixels`` of the sign's letters."""
        return self.sign_pixels >= self.min_pixels

    def summary(self) -> str:
        by_sight = "; ".join(
            f"{label}: {self.execution_returns[mask].mean():.3f} ({int(mask.sum())} trials)"
            for label, mask in (("read", self.sign_seen), ("not read", ~self.sign_seen))
            if mask.any()
        )
        return (
            f"sign read (>= {self.min_pixels} pixels of its letters in a view) in {self.sign_seen.mean():.0%} of "
            f"explorations (any of them in view: {np.mean(self.sign_pixels > 0):.0%}), past the barrier in "
            f"{self.past_barrier.mean():.0%}, exploration length {self.exploration_lengths.mean():.1f}, "
            f"execution return {self.execution_returns.mean():.3f}; execution return with the sign {by_sight}"
            + self.outcomes_summary()
        )

    def outcomes_summary(self) -> str:
        """``; execution by target (right/wrong/ended/timed out): blue ball 0/0/1/13, ...``, or ""."""
        counts = self.outcome_counts()
        if not counts:
            return ""
        per_target = ", ".join(
            f"{colour} {kind} " + "/".join(str(n) for n in per_outcome.values())
            for (colour, kind), per_outcome in counts.items()
        )
        return f"; execution by target ({'/'.join(EXECUTION_OUTCOMES)}): {per_target}"


class _SignViewRecorder(TrialRecorder):
    """Notes, in exploration, the most pixels of the sign in one view and whether the agent is past
    the barrier (read from the env, which the agent does not see), and each execution episode's
    target and last action."""

    env: SignNav3DEnv

    def start_trial(self) -> None:
        self.sign_pixels, self.past_barrier = 0, False
        self.execution_targets: List[int] = []  # per execution episode of the trial
        self.last_actions: List[int] = []

    def note(self, obs: Dict[str, Any], info: Dict[str, Any], action: int) -> None:
        if int(obs["phase"]) == EXPLORATION:
            self.sign_pixels = max(self.sign_pixels, self.env.sign_pixels())
            self.past_barrier = self.past_barrier or bool(self.env.agent_position[1] > LOWER_ROOMS_Z[0])
        elif int(obs["episode_start"]):
            target = execution_target(self.env.problem_id, obs["instruction"])
            self.execution_targets.append(EXECUTION_TARGETS.index(target))
            self.last_actions.append(int(action))
        else:
            self.last_actions[-1] = int(action)

    def trial_row(self, result: Dict[str, Any]) -> Tuple[Any, ...]:
        returns = result["execution_returns"]
        return self.sign_pixels, self.past_barrier, result["exploration_length"], np.mean(returns)

    def episode_rows(self, result: Dict[str, Any]) -> List[Tuple[Any, ...]]:
        """Each execution episode's target and how it ended, told by its return (a touch gives +-1)."""
        outcomes = [
            "right" if r > 0 else "wrong" if r < 0 else "ended" if last == END_EPISODE else "timed out"
            for r, last in zip(result["execution_returns"], self.last_actions)
        ]
        return [
            (target, EXECUTION_OUTCOMES.index(outcome)) for target, outcome in zip(self.execution_targets, outcomes)
        ]


def exploration_report(
    env: SignNav3DEnv,
    agent: ScriptedAgent,
    n_trials: int = 100,
    seed: int = 0,
    problem_ids: Optional[Sequence[int]] = None,
    instructions: Optional[Sequence[Any]] = None,
    min_pixels: int = READ_MIN_PIXELS,
) -> SignExplorationReport:
    """Play ``n_trials`` trials of ``agent`` (a :class:`~dream_envs.agents.ScriptedAgent`; for a model
    use ``sb3_dream.evaluation.as_trial_agent(model)``) and report what its explorations saw.
    ``problem_ids`` and ``instructions`` pin trials as in :func:`~dream_envs.play.play_trials`."""
    sign_nav = unwrap(env, SignNav3DEnv, "SignNav3D-v0")
    min_pixels = check_positive_int("min_pixels", min_pixels)
    trials, episodes = record_trials(env, _SignViewRecorder(agent, sign_nav), n_trials, seed, problem_ids, instructions)
    pixels, past, lengths, returns = trials
    targets, outcomes = episodes
    return SignExplorationReport(
        pixels, past.astype(bool), lengths, returns.astype(float), min_pixels, targets, outcomes
    )
