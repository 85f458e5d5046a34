"""Where an IMPORT model stands: does what it learned with the problem ID carry over to its history?

IMPORT trains one policy on two codes z, the problem's embedding e(T) and the history's e(tau_:t),
and an auxiliary loss pulls e(tau_:t) towards e(T), so that what the policy learns with the
privileged problem ID serves it at meta-test, where z is always e(tau_:t). :func:`diagnose` plays
the same greedy meta-test trials twice and compares:

* ``return_history``: meta-test, z = e(tau_:t) (what :func:`~sb3_dream.evaluation.evaluate_meta` measures);
* ``return_problem``: z = e(T) of the trial's true problem at every step (privileged, as the
  policy acts in half of its training trials);
* ``distance_exploration`` and ``distance_execution``: ||e(tau_:t) - e(T)||^2 averaged over each
  z = e(tau_:t) trial's exploration steps and over its execution steps, then over the trials as
  the returns are (uniformly, or by each (problem, instruction) pair's probability with
  ``exhaustive``), read against ``problem_spread``, ||e(T) - e(T')||^2 averaged over pairs of the
  split's problems.

``return_problem`` well above ``return_history`` with distances of the order of the spread: the
history embedding has not come near the problem's, and the policy's skill with e(T) does not carry
over. The paper (Section 6.1) reports this of IMPORT on its cooking task: it "successfully cooks
conditioned on the problem ID, but it fails on many recipes conditioned on its recurrent state and
we observe the recurrent state and problem ID embeddings become far apart". Both low: the policy
has not learned the task with either code. A diagnostic: it reads each trial's problem ID.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Dict, List, Optional, Sequence, Union

import gymnasium as gym
import numpy as np
import torch as th

from dream_envs import EXPLORATION
from sb3_dream.common.agents import TrialNumbering
from sb3_dream.common.codes import mean_pair_sq_distance
from sb3_dream.common.recurrent import reset_lstm_states
from sb3_dream.evaluation import privileged_trials
from sb3_dream.import_dqn.import_dqn import IMPORT
from sb3_dream.rl2dqn.rl2dqn import RL2BatchTrialAgent


@dataclass
class IMPORTDiagnosis:
    """Mean results over ``n_trials`` trials (see the module docstring)."""

    return_history: float  # meta-test: z = e(tau_:t)
    return_problem: float  # z = e(T) (privileged)
    distance_exploration: float  # ||e(tau_:t) - e(T)||^2 over the exploration steps
    distance_execution: float  # ... over the execution steps
    problem_spread: float  # ||e(T) - e(T')||^2 over pairs of the split's problems
    exploration_length: float
    n_trials: int

    def as_dict(self) -> Dict[str, Any]:
        """The results as a dict (JSON-ready)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def text(self) -> str:
        """The results in words, for logs."""
        return (
            f"return with z = e(tau) {self.return_history:.3f}, with z = e(T) {self.return_problem:.3f}; "
            f"||e(tau) - e(T)||^2 {self.distance_exploration:.3f} exploring, {self.distance_execution:.3f} executing, "
            f"against ||e(T) - e(T')||^2 {self.problem_spread:.3f}"
        )


class ProblemCodeBatchAgent(RL2BatchTrialAgent, TrialNumbering):
    """Greedy IMPORT that, with ``use_problem``, acts on z = e(T) of trial k's problem
    ``problem_ids[k % len(problem_ids)]`` instead of e(tau_:t), and records ||e(tau_:t) - e(T)||^2
    at every step: a diagnostic (it is handed the problem IDs), never a meta-test agent. Play the
    trials in order on those problems (the trial runners' ``problem_ids=``)."""

    def __init__(self, model: IMPORT, problem_ids: Sequence[int], use_problem: bool) -> None:
        self.problem_ids = np.asarray(problem_ids, dtype=np.int64)
        self.use_problem = bool(use_problem)
        # trial -> its steps' ||e(tau_:t) - e(T)||^2, by phase
        self.distances: Dict[str, Dict[int, List[float]]] = {"exploration": {}, "execution": {}}
        super().__init__(model, deterministic=True)

    def mean_distances(self, phase: str, weights: np.ndarray) -> float:
        """Each trial's mean distance over its ``phase`` steps, averaged with the trials' ``weights``."""
        per_trial = self.distances[phase]
        return float(sum(w * np.mean(per_trial[k]) for k, w in enumerate(weights) if k in per_trial))

    def reset(self, n_envs: int) -> None:
        super().reset(n_envs)
        self.reset_numbering(n_envs)

    def start_trials(self, idx: np.ndarray) -> None:
        super().start_trials(idx)
        self.note_starts(idx)

    @th.no_grad()
    def act(self, obs: Dict[str, np.ndarray], infos: Sequence[Dict[str, Any]]) -> np.ndarray:
        self.number_new_trials()
        model, policy = self.model, self.model.policy
        policy.set_training_mode(False)
        obs_tensor, _ = policy.obs_to_tensor(self.observation(obs, infos))
        n = len(infos)
        states = reset_lstm_states(
            policy.obs_to_states(self.state, n), th.as_tensor(self.episode_start, dtype=th.float32, device=model.device)
        )
        history, (h, c) = model.q_net.encode_step(obs_tensor, states)
        problems = self.problem_ids[np.maximum(self.trial, 0) % len(self.problem_ids)]
        e_problem = model.q_net.problem_embedder(model._problem_features(problems))
        q = model.q_net.q_values(obs_tensor, e_problem if self.use_problem else history)
        distance = ((history - e_problem) ** 2).sum(dim=-1).cpu().numpy()
        phases = np.asarray(obs["phase"]).reshape(n, -1)[:, 0]
        for i in range(n):
            if infos[i]:  # a slot with no trial left has an empty info
                phase = "exploration" if phases[i] == EXPLORATION else "execution"
                self.distances[phase].setdefault(int(self.trial[i]), []).append(float(distance[i]))
        self.state = (h.cpu().numpy(), c.cpu().numpy())
        self.episode_start[:] = False
        return q.argmax(dim=-1).cpu().numpy()


def diagnose(
    model: IMPORT,
    env: Union[str, gym.Env],
    n_trials: int = 100,
    split: str = "test",
    seed: int = 0,
    env_kwargs: Optional[Dict[str, Any]] = None,
    problem_ids: Optional[Sequence[int]] = None,
    n_envs: int = 16,
    exhaustive: bool = False,
) -> IMPORTDiagnosis:
    """Meta-test ``model`` on the same ``n_trials`` trials of ``split`` with z = e(tau_:t) and with
    z = e(T); see the module docstring for how to read the result.

    :param problem_ids: trial k's problem is ``problem_ids[k % len(problem_ids)]``; by default
        problems are drawn uniformly from ``split`` with ``seed``.
    :param n_envs: trials played side by side (an env ID is made that many times).
    :param exhaustive: every (problem, instruction) pair of the split, in whole passes of at least
        ``n_trials`` trials, every mean weighted by the pairs' probabilities, as
        :func:`~sb3_dream.evaluation.evaluate_meta` does.
    """
    if not isinstance(model, IMPORT):
        raise TypeError(f"model must be an IMPORT model, got {type(model).__name__}")
    with privileged_trials(env, n_trials, split, seed, env_kwargs, problem_ids, n_envs, exhaustive) as trials:
        agents = {z: ProblemCodeBatchAgent(model, trials.problem_ids, z) for z in (False, True)}
        results = {z: trials.play(agent) for z, agent in agents.items()}
    split_ids, problem_ids = trials.split_ids, trials.problem_ids
    with th.no_grad():
        e_split = model.q_net.problem_embedder(model._problem_features(split_ids)).cpu().numpy()
    meta_test, weights = agents[False], results[False].trial_weights
    return IMPORTDiagnosis(
        return_history=results[False].mean,
        return_problem=results[True].mean,
        distance_exploration=meta_test.mean_distances("exploration", weights),
        distance_execution=meta_test.mean_distances("execution", weights),
        problem_spread=mean_pair_sq_distance(e_split),
        exploration_length=results[False].mean_exploration_length,
        n_trials=len(problem_ids),
    )
