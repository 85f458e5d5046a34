"""Playing trials: one at a time (:func:`play_trial`, :func:`play_trials`) or side by side in copies of
a trial env (:func:`play_trials_batched`). Agents only ever see :func:`~dream_envs.trial_env.public_info`."""

from __future__ import annotations

from typing import Any, Dict, Iterator, List, Optional, Sequence, SupportsFloat

import gymnasium as gym
import numpy as np

from dream_envs.agents import BatchTrialAgent, ScriptedAgent
from dream_envs.checks import check_positive_int
from dream_envs.trial_env import EXPLORATION, public_info


class _TrialRecord:
    """What :func:`play_trial` returns about one trial, filled in step by step."""

    def __init__(self, info: Dict[str, Any]) -> None:
        self.result: Dict[str, Any] = {"problem_id": info["problem_id"], "trial_return": 0.0, "exploration_actions": []}

    def step(self, obs: Dict[str, Any], action: int, reward: SupportsFloat, info: Dict[str, Any]) -> None:
        """Record ``action`` taken at ``obs`` and the ``reward`` and ``info`` that followed."""
        if int(obs["phase"]) == EXPLORATION:
            self.result["exploration_actions"].append(int(action))
        self.result["trial_return"] += float(reward)
        if info.get("episode_end") and info["episode_phase"] == EXPLORATION:
            self.result["exploration_length"] = info["episode_length"]

    def finish(self, info: Dict[str, Any]) -> Dict[str, Any]:
        self.result["execution_returns"] = info["execution_returns"]
        return self.result


def play_trial(
    env: gym.Env,
    agent: ScriptedAgent,
    seed: Optional[int] = None,
    options: Optional[Dict[str, Any]] = None,
) -> Dict[str, Any]:
    """Run one trial of ``agent`` in ``env``; the agent only ever sees :func:`public_info`.

    Returns a dict with ``problem_id``, ``execution_returns`` (one per execution episode),
    ``exploration_length``, ``exploration_actions`` (the actions of the exploration episode) and
    ``trial_return`` (the sum of the step rewards).
    """
    agent.reset()
    obs, info = env.reset(seed=seed, options=options)
    record = _TrialRecord(info)
    terminated = truncated = False
    while not (terminated or truncated):
        action = agent.act(obs, public_info(info))
        next_obs, reward, terminated, truncated, info = env.step(action)
        record.step(obs, action, reward, info)
        obs = next_obs
    return record.finish(info)


def _trial_options(
    k: int, problem_ids: Optional[Sequence[int]], instructions: Optional[Sequence[Any]] = None
) -> Optional[Dict[str, Any]]:
    """``reset`` options of trial k: pinned to ``problem_ids[k % len(problem_ids)]`` if given, and
    then to ``instructions[k % len(problem_ids)]`` if given."""
    if problem_ids is None:
        return None
    j = k % len(problem_ids)
    options: Dict[str, Any] = {"problem_id": int(problem_ids[j])}
    if instructions is not None:
        options["instruction"] = np.asarray(instructions[j], dtype=np.int64)
    return options


def _check_trials(n_trials: int, problem_ids: Optional[Sequence[int]], instructions: Optional[Sequence[Any]]) -> int:
    n_trials = check_positive_int("n_trials", n_trials)
    if problem_ids is not None and len(problem_ids) == 0:
        raise ValueError("problem_ids must not be empty")
    if instructions is not None and (problem_ids is None or len(instructions) != len(problem_ids)):
        raise ValueError("instructions must come with problem_ids, one instruction per problem ID")
    return n_trials


def play_trials(
    env: gym.Env,
    agent: ScriptedAgent,
    n_trials: int,
    seed: int = 0,
    problem_ids: Optional[Sequence[int]] = None,
    instructions: Optional[Sequence[Any]] = None,
) -> Iterator[Dict[str, Any]]:
    """:func:`play_trial` ``n_trials`` times, trial k seeded ``seed + k``; with ``problem_ids``,
    trial k is pinned to ``problem_ids[k % len(problem_ids)]``, and with ``instructions`` (one per
    problem ID) every execution episode of it to ``instructions[k % len(problem_ids)]``.
    Arguments are checked at the call."""
    n_trials = _check_trials(n_trials, problem_ids, instructions)

    def trials() -> Iterator[Dict[str, Any]]:
        for k in range(n_trials):
            yield play_trial(env, agent, seed=seed + k, options=_trial_options(k, problem_ids, instructions))

    return trials()


def play_trials_batched(
    envs: Sequence[gym.Env],
    agent: BatchTrialAgent,
    n_trials: int,
    seed: int = 0,
    problem_ids: Optional[Sequence[int]] = None,
    instructions: Optional[Sequence[Any]] = None,
) -> List[Dict[str, Any]]:
    """The same trials as :func:`play_trials` (trial k seeded ``seed + k``, pinned likewise), played
    side by side in ``envs`` (copies of one trial env) by a :class:`BatchTrialAgent`: each env
    takes the next trial as soon as its own ends. Returns :func:`play_trial`'s dicts in trial order.

    With an agent that acts on each trial alone (a trained model acting greedily), every trial's
    result is the one :func:`play_trials` gives, up to the rounding of batched matrix products.
    """
    n_trials = _check_trials(n_trials, problem_ids, instructions)
    if len(envs) == 0:
        raise ValueError("envs must not be empty")
    n_envs = min(len(envs), n_trials)
    agent.reset(n_envs)
    trial = np.full(n_envs, -1)  # the trial each env plays (-1: none left)
    records: List[Optional[_TrialRecord]] = [None] * n_envs
    obs: List[Dict[str, Any]] = [{}] * n_envs
    infos: List[Dict[str, Any]] = [{}] * n_envs
    results: List[Optional[Dict[str, Any]]] = [None] * n_trials
    next_trial = 0

    def start(i: int) -> None:
        nonlocal next_trial
        trial[i] = next_trial
        options = _trial_options(next_trial, problem_ids, instructions)
        obs[i], info = envs[i].reset(seed=seed + next_trial, options=options)
        records[i], infos[i] = _TrialRecord(info), public_info(info)
        next_trial += 1

    for i in range(n_envs):
        start(i)
    while (trial >= 0).any():
        stacked = {key: np.stack([np.asarray(o[key]) for o in obs]) for key in obs[int(np.argmax(trial >= 0))]}
        actions = np.asarray(agent.act(stacked, infos)).reshape(n_envs)
        restarted = []
        for i in np.flatnonzero(trial >= 0):
            next_obs, reward, terminated, truncated, info = envs[i].step(int(actions[i]))
            records[i].step(obs[i], int(actions[i]), reward, info)  # type: ignore[union-attr]
            obs[i], infos[i] = next_obs, public_info(info)
            if terminated or truncated:
                results[trial[i]] = records[i].finish(info)  # type: ignore[union-attr]
                if next_trial < n_trials:
                    start(i)
                    restarted.append(i)
                else:
                    trial[i], infos[i] = -1, {}
        if restarted:
            agent.start_trials(np.asarray(restarted))
    return results  # type: ignore[return-value]
