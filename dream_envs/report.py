"""Behaviour reports: play an agent's trials through a :class:`TrialRecorder` and gather what it did.

Each env's report (:func:`dream_envs.bus.exploration_report`, :func:`dream_envs.cook.behaviour_report`,
:func:`dream_envs.sign_nav.exploration_report`) defines a recorder, which notes what the agent does
in each trial and turns each finished trial into rows, and a dataclass that summarises the rows;
:func:`record_trials` plays the trials and stacks the rows into columns.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, Dict, List, Optional, Sequence, Tuple, Type, TypeVar

import gymnasium as gym
import numpy as np

from dream_envs.agents import ScriptedAgent
from dream_envs.play import play_trials
from dream_envs.trial_env import TrialEnv

Env = TypeVar("Env", bound=TrialEnv)


class TrialRecorder(ScriptedAgent, ABC):
    """Plays ``agent``'s actions unchanged and notes what happens, trial by trial.

    The agent sees only what it would see anyway; the recorder may also read the (unwrapped) ``env``,
    e.g. the agent's pose, which the agent never sees.
    """

    def __init__(self, agent: ScriptedAgent, env: TrialEnv) -> None:
        self.agent, self.env = agent, env

    def reset(self) -> None:
        self.agent.reset()
        self.start_trial()

    def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
        action = self.agent.act(obs, info)
        self.note(obs, info, action)
        return action

    @abstractmethod
    def start_trial(self) -> None:
        """Forget the notes of the trial before: a new trial starts."""

    @abstractmethod
    def note(self, obs: Dict[str, Any], info: Dict[str, Any], action: int) -> None:
        """Note that the agent took ``action`` at ``obs`` (with its public ``info``)."""

    @abstractmethod
    def trial_row(self, result: Dict[str, Any]) -> Tuple[Any, ...]:
        """What the report keeps of a finished trial, given :func:`~dream_envs.play.play_trial`'s ``result``."""

    def episode_rows(self, result: Dict[str, Any]) -> List[Tuple[Any, ...]]:
        """What the report keeps of each execution episode of a finished trial (default: nothing)."""
        return []


def unwrap(env: gym.Env, env_class: Type[Env], env_id: str) -> Env:
    """``env.unwrapped``, or a ``ValueError`` unless it is an ``env_class`` (named ``env_id``)."""
    unwrapped = env.unwrapped
    if not isinstance(unwrapped, env_class):
        raise ValueError(f"env must be a {env_id} env, got {type(unwrapped).__name__}")
    return unwrapped


def record_trials(
    env: gym.Env,
    recorder: TrialRecorder,
    n_trials: int,
    seed: int = 0,
    problem_ids: Optional[Sequence[int]] = None,
    instructions: Optional[Sequence[Any]] = None,
) -> Tuple[Tuple[np.ndarray, ...], Tuple[np.ndarray, ...]]:
    """Play ``n_trials`` trials of the recorder's agent in ``env`` (pinned as in
    :func:`~dream_envs.play.play_trials`) and return the columns of the recorder's
    :meth:`~TrialRecorder.trial_row` rows (one entry per trial) and of its
    :meth:`~TrialRecorder.episode_rows` (one entry per execution episode; none if it keeps none)."""
    trial_rows: List[Tuple[Any, ...]] = []
    episode_rows: List[Tuple[Any, ...]] = []
    for result in play_trials(env, recorder, n_trials, seed, problem_ids, instructions):
        trial_rows.append(recorder.trial_row(result))
        episode_rows.extend(recorder.episode_rows(result))
    return _columns(trial_rows), _columns(episode_rows)


def _columns(rows: List[Tuple[Any, ...]]) -> Tuple[np.ndarray, ...]:
    return tuple(np.array(column) for column in zip(*rows))
