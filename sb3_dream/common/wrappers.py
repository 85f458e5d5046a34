"""Observation wrappers that give recurrent agents what the trial envs hand over only in ``info``.

* :class:`FinalObsWrapper`: adds a ``final_obs`` key to a trial env's Dict observation. A trial
  env's step that ends an inner episode already returns the *next* episode's first observation,
  so the state the last action reached lives only in ``info["final_obs"]`` (in MetaBandit-v0 the
  reveal is visible only there). The key holds that state on the first step of the next inner
  episode and zeros elsewhere.
* :class:`RL2ObservationWrapper`: turns a plain env (Box, Discrete, MultiDiscrete or image
  observations, Discrete actions) into the RL² Dict ``{obs, prev_action, prev_reward}``.
"""

from __future__ import annotations

from typing import Any, Dict, Optional

import gymnasium as gym
import numpy as np
from gymnasium import spaces


def final_obs_entry(space: spaces.Space, info: Dict[str, Any], terminated: bool = False) -> np.ndarray:
    """The ``final_obs`` key's value for the observation returned with ``info``.

    The previous inner episode's last state if that step ended an inner episode but not the trial,
    else zeros of ``space``.
    """
    final = info.get("final_obs")
    if final is not None and info.get("episode_end") and not terminated:
        return np.asarray(final, dtype=space.dtype).reshape(space.shape)
    return np.zeros(space.shape, dtype=space.dtype)


class FinalObsWrapper(gym.Wrapper):
    """Adds ``final_obs`` (the previous inner episode's last state, on an inner episode's first
    step; zeros otherwise) to a trial env's Dict observation. Apply it before vectorising.

    :param env: an env with a Dict observation space that has an ``obs`` key.
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        space = env.observation_space
        if not isinstance(space, spaces.Dict) or "obs" not in space.spaces:
            raise ValueError(f"FinalObsWrapper needs a Dict observation space with an 'obs' key, got {space}")
        if "final_obs" in space.spaces:
            raise ValueError("the observation space already has a 'final_obs' key")
        self._obs_space = space.spaces["obs"]
        self.observation_space = spaces.Dict({**space.spaces, "final_obs": self._obs_space})

    def reset(self, *, seed: Optional[int] = None, options: Optional[Dict[str, Any]] = None):
        obs, info = self.env.reset(seed=seed, options=options)
        return {**obs, "final_obs": np.zeros(self._obs_space.shape, dtype=self._obs_space.dtype)}, info

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        entry = final_obs_entry(self._obs_space, info, terminated or truncated)
        return {**obs, "final_obs": entry}, reward, terminated, truncated, info


class RL2ObservationWrapper(gym.Wrapper):
    """RL²'s input for a plain env: ``{"obs": observation, "prev_action", "prev_reward"}``.

    ``prev_action`` is ``Discrete(n + 1)`` (0 at the episode's start, else the previous action + 1)
    and ``prev_reward`` a ``Box(1,)`` holding the previous reward (0 at the start), as in the trial
    envs. One gym episode is then one trial with a single inner episode.

    :param env: an env with a non-Dict observation space and a Discrete action space.
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        if isinstance(env.observation_space, spaces.Dict):
            raise ValueError(
                "RL2ObservationWrapper wraps non-Dict observation spaces; Dict envs need an 'obs' key instead"
            )
        if not isinstance(env.action_space, spaces.Discrete):
            raise ValueError(f"RL2ObservationWrapper needs a Discrete action space, got {env.action_space}")
        self._n_actions = int(env.action_space.n)
        self._start = int(env.action_space.start)
        self.observation_space = spaces.Dict(
            {
                "obs": env.observation_space,
                "prev_action": spaces.Discrete(self._n_actions + 1),
                "prev_reward": spaces.Box(-np.inf, np.inf, shape=(1,), dtype=np.float32),
            }
        )

    def _dict(self, obs: Any, prev_action: int, prev_reward: float) -> Dict[str, Any]:
        return {"obs": obs, "prev_action": prev_action, "prev_reward": np.array([prev_reward], dtype=np.float32)}

    def reset(self, *, seed: Optional[int] = None, options: Optional[Dict[str, Any]] = None):
        obs, info = self.env.reset(seed=seed, options=options)
        return self._dict(obs, 0, 0.0), info

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        prev_action = int(np.asarray(action).item()) - self._start + 1
        return self._dict(obs, prev_action, float(reward)), reward, terminated, truncated, info
