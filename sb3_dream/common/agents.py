"""Model -> trial agent adapters: how the trial runners of :mod:`dream_envs` play an SB3 model.

A model plays through ``predict(obs, state, episode_start, deterministic)`` (:class:`PolicyBatchAgent`),
or through its own agent where it reads more than the observation (``as_trial_agent`` /
``as_batch_trial_agent``, e.g. DREAM's, which reads ``info["final_obs"]``).
"""

from __future__ import annotations

from typing import Any, Dict, Optional, Sequence

import numpy as np

from dream_envs import BatchTrialAgent, ScriptedAgent, SingleTrialAgent

__all__ = ["PolicyAgent", "PolicyBatchAgent", "TrialNumbering", "as_batch_trial_agent", "as_trial_agent"]


class PolicyBatchAgent(BatchTrialAgent):
    """Plays an SB3 model through ``predict(obs, state, episode_start, deterministic)`` in
    ``n_envs`` trial envs side by side.

    Each slot's recurrent state is reset at its trial's start (``episode_start`` set on the
    trial's first step) and carried across the trial's inner episodes.
    """

    def __init__(self, model: Any, deterministic: bool = True) -> None:
        self.model, self.deterministic = model, deterministic
        self.reset(1)

    def reset(self, n_envs: int) -> None:
        self.state: Any = None
        self.episode_start = np.ones(n_envs, dtype=bool)

    def start_trials(self, idx: np.ndarray) -> None:
        self.episode_start[idx] = True

    def observation(self, obs: Dict[str, np.ndarray], infos: Sequence[Dict[str, Any]]) -> Dict[str, np.ndarray]:
        """What ``predict`` is given (a hook: a model may read more of ``info``)."""
        return obs

    def act(self, obs: Dict[str, np.ndarray], infos: Sequence[Dict[str, Any]]) -> np.ndarray:
        action, self.state = self.model.predict(
            self.observation(obs, infos),
            state=self.state,
            episode_start=self.episode_start.copy(),
            deterministic=self.deterministic,
        )
        self.episode_start[:] = False
        return np.asarray(action).reshape(-1)


class TrialNumbering:
    """Numbers the trials a batch agent plays, 0, 1, ... in the order they start (counted at their
    first action, in the order :func:`~dream_envs.play_trials_batched` starts them), from the
    agent's construction on: ``trial[i]`` is slot i's. A diagnostic that hands its agent trial k's
    problem (``problem_ids[k]``, the trial runner's ``problem_ids=``) reads it this way."""

    _trials_started = 0

    def reset_numbering(self, n_envs: int) -> None:
        self.trial = np.full(n_envs, -1, dtype=np.int64)
        self._starting = list(range(n_envs))

    def note_starts(self, idx: np.ndarray) -> None:
        self._starting.extend(int(i) for i in idx)

    def number_new_trials(self) -> None:
        """Give the trials started since the last call their numbers (call at the start of ``act``)."""
        for i in self._starting:
            self.trial[i], self._trials_started = self._trials_started, self._trials_started + 1
        self._starting = []


class PolicyAgent(SingleTrialAgent):
    """:class:`PolicyBatchAgent` one trial at a time (a :class:`~dream_envs.ScriptedAgent`)."""

    def __init__(self, model: Any, deterministic: bool = True) -> None:
        super().__init__(PolicyBatchAgent(model, deterministic))


def _not_an_agent(agent: Any) -> TypeError:
    return TypeError(
        "agent must be a dream_envs.ScriptedAgent, a dream_envs.BatchTrialAgent or a model with predict(), "
        f"got {type(agent).__name__}"
    )


def as_trial_agent(agent: Any, deterministic: bool = True) -> ScriptedAgent:
    """A :class:`~dream_envs.ScriptedAgent` for ``agent``: itself if it is one, a
    :class:`~dream_envs.BatchTrialAgent` playing one trial at a time, the model's own
    ``as_trial_agent(deterministic)`` if it defines one (a model that uses ``info["final_obs"]``),
    else a :class:`PolicyAgent` around ``predict``."""
    if isinstance(agent, ScriptedAgent):
        return agent
    if isinstance(agent, BatchTrialAgent):
        return SingleTrialAgent(agent)
    if hasattr(agent, "as_trial_agent"):
        return agent.as_trial_agent(deterministic=deterministic)
    if hasattr(agent, "predict"):
        return PolicyAgent(agent, deterministic=deterministic)
    raise _not_an_agent(agent)


def as_batch_trial_agent(agent: Any, deterministic: bool = True) -> Optional[BatchTrialAgent]:
    """A :class:`~dream_envs.BatchTrialAgent` for ``agent``, or None where it plays one trial at a
    time (a :class:`~dream_envs.ScriptedAgent`): itself if it is one, the model's own
    ``as_batch_trial_agent(deterministic)`` if it defines one, else a :class:`PolicyBatchAgent`."""
    if isinstance(agent, BatchTrialAgent):
        return agent
    if isinstance(agent, ScriptedAgent):
        return None
    if hasattr(agent, "as_batch_trial_agent"):
        return agent.as_batch_trial_agent(deterministic=deterministic)
    if hasattr(agent, "predict"):
        return PolicyBatchAgent(agent, deterministic=deterministic)
    raise _not_an_agent(agent)
