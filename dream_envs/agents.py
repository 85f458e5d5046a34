"""The trial agents' protocols: a :class:`ScriptedAgent` plays one trial at a time, a
:class:`BatchTrialAgent` plays several side by side (see :mod:`dream_envs.play`)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, Dict, Optional, Sequence

import numpy as np
from gymnasium import spaces


class ScriptedAgent(ABC):
    """A scripted trial agent (the envs' oracles, the random baseline).

    :meth:`act` sees the observation and the *public* part of the ``info`` returned with it (so it
    can read ``final_obs`` at inner-episode boundaries), never the problem ID.
    """

    def reset(self) -> None:
        """Forget everything: a new trial starts."""

    @abstractmethod
    def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
        """The action for ``obs``."""


class RandomAgent(ScriptedAgent):
    """Uniformly random actions (the end-episode action included), seeded."""

    def __init__(self, action_space: spaces.Discrete, seed: Optional[int] = None) -> None:
        self.action_space = action_space
        self.rng = np.random.default_rng(seed)

    def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
        return int(self.rng.integers(self.action_space.n))


class BatchTrialAgent(ABC):
    """A trial agent that plays ``n_envs`` trials side by side, one batched decision per step
    (what :func:`play_trials_batched` runs; e.g. a trained model's meta-test agent).

    Like :class:`ScriptedAgent`, it sees observations and the *public* part of each ``info``.
    """

    @abstractmethod
    def reset(self, n_envs: int) -> None:
        """Forget everything: ``n_envs`` slots, each about to start a trial."""

    @abstractmethod
    def start_trials(self, idx: np.ndarray) -> None:
        """A new trial starts in slots ``idx`` (their next observation is the trial's first).

        :func:`play_trials_batched` gives slots 0..n_envs-1 its first trials at :meth:`reset`, then
        each slot in ``idx`` the next trial in that order (an agent handed the trials' problems, such
        as a diagnostic one, can count them)."""

    @abstractmethod
    def act(self, obs: Dict[str, np.ndarray], infos: Sequence[Dict[str, Any]]) -> np.ndarray:
        """The actions [n_envs] for the stacked observations of every slot (each key [n_envs, ...])
        and each slot's public ``info``; a slot with no trial left has an empty ``info`` and its
        action is ignored."""


class SingleTrialAgent(ScriptedAgent):
    """A :class:`ScriptedAgent` that plays one trial at a time through a :class:`BatchTrialAgent`
    of one slot (so one agent class serves both trial runners)."""

    def __init__(self, agent: BatchTrialAgent) -> None:
        self.agent = agent
        self.reset()

    def reset(self) -> None:
        self.agent.reset(1)

    def act(self, obs: Dict[str, Any], info: Dict[str, Any]) -> int:
        stacked = {key: np.asarray(value)[None] for key, value in obs.items()}
        return int(np.asarray(self.agent.act(stacked, [info])).reshape(-1)[0])
