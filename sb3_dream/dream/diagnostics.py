"""Where a DREAM model stands: is its return limited by exploration (and the decoder) or by execution?

DREAM factorises meta-test into two parts, and each can be checked on its own with the privileged
problem ID (never available at meta-test, so this is a diagnostic, not an evaluation):

* the **execution policy** alone: run it with z = f(T), the encoder's code of the true problem,
  instead of the decoder's g(tau^exp). Its return is what a perfect explorer and decoder would give;
* **exploration and the decoder**: how far g(tau^exp) lands from f(T) (``decoder_error``), next to
  how far apart the codes of different problems are (``f_spread``);
* **the encoder's content**: how much of f's variance over the split's problems each dimension of
  the problem's representation explains (``f_variance_by_feature``). The information bottleneck
  should leave none to the parts that do not matter for execution (MetaBus's gray buses); what is
  left there, the exploration reward pays the explorer to find.

``return_f`` close to ``return_g`` and both low: execution is what limits the model.
``return_f`` well above ``return_g``: exploration (or the decoder) is. Both runs use the same
problems, instructions and env seeds, and greedy policies, so the exploration trajectories are the
same in both.

``return_g_optimal_exploration`` tells the explorer from the decoder when ``return_f`` is well above
``return_g``: the trials once more with the env's scripted optimal explorer (its ``oracle()``) in
place of the exploration policy, the decoder reading that trajectory and execution acting on its
g. Close to ``return_f``: the decoder reads what an optimal exploration finds, and the exploration
policy is what falls short (it does not look where it should). Close to ``return_g``: the decoder
does not use what the optimal exploration shows either (it never learned to: a decoder trains only
on the exploration policy's own trajectories). ``decoder_error_optimal_exploration`` is its
||g - f(T)||^2. ``None`` for an env without a scripted oracle.

:func:`exploration_gains` looks inside the exploration reward: the reward of Equation 5 that each
step of the model's own explorations earns from its current f and g, as its training relabels them.
Which steps pay (a fridge opened, a bus ridden) and how much says why an explorer prefers one route
to another; a step that finds something yet earns little points at the decoder (it does not read
that step) or at the encoder (f keeps little of what the step finds, see
``f_variance_by_feature``).

``return_f_noisy`` runs the execution policy a third time, on z ~ N(f(T), rho^2 I): the code that
half of its training (Equation 2's f branch) gives it. Well below ``return_f``, the bottleneck's
noise hides much of the code from the execution policy (rho^2 per dimension against the spread
of f between problems). ``None`` without the noise (``bottleneck=False`` or rho^2 = 0).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

import gymnasium as gym
import numpy as np
import torch as th

from dream_envs import EXPLORATION, ScriptedAgent, SingleTrialAgent, make_oracle
from dream_envs.checks import check_choice
from sb3_dream.common.agents import TrialNumbering
from sb3_dream.common.codes import mean_pair_sq_distance
from sb3_dream.dream.acting import DreamBatchTrialAgent
from sb3_dream.dream.dream import DREAM
from sb3_dream.evaluation import privileged_trials


@dataclass
class DreamDiagnosis:
    """Mean results over ``n_trials`` trials (execution returns averaged over execution episodes)."""

    return_g: float  # meta-test: z = g(tau^exp)
    return_f: float  # the execution policy given z = f(T) (privileged)
    return_f_noisy: Optional[float]  # ... given z ~ N(f(T), rho^2 I), as in training; None without noise
    decoder_error: float  # ||g(tau^exp) - f(T)||^2
    f_norm_sq: float  # ||f(T)||^2
    f_spread: float  # ||f(T) - f(T')||^2 over pairs of the split's problems
    f_variance_by_feature: List[float]  # per problem-feature dimension, see f_variance_by_feature()
    exploration_length: float
    n_trials: int
    # the env's scripted optimal explorer, then z = g of its trajectory; None without an oracle
    return_g_optimal_exploration: Optional[float] = None
    decoder_error_optimal_exploration: Optional[float] = None
    # the exploration reward of every step of the z = g trials (what exploration_gains() computes for
    # the same trials, without playing them again); not part of as_dict()
    exploration_gains: Optional["ExplorationGains"] = field(default=None, repr=False, compare=False)

    def as_dict(self) -> Dict[str, Any]:
        """The scalar results (JSON-ready): every field but ``exploration_gains``."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "exploration_gains"}

    def returns_text(self) -> str:
        """The three returns in words, for logs."""
        text = f"return with z = g {self.return_g:.3f}, with z = f(T) {self.return_f:.3f}"
        if self.return_f_noisy is not None:
            text += f", with z ~ N(f(T), rho^2 I) {self.return_f_noisy:.3f}"
        if self.return_g_optimal_exploration is not None:
            text += f", with z = g of the optimal exploration {self.return_g_optimal_exploration:.3f}"
        return text


Z_SOURCES = ("g", "f", "f_noisy")


class PrivilegedBatchAgent(DreamBatchTrialAgent, TrialNumbering):
    """Greedy DREAM that records g(tau^exp) per trial and, with ``z_source`` "f" or "f_noisy", acts on
    f(T) or on z ~ N(f(T), rho^2 I) (noise drawn from ``seed``) of trial k's problem
    ``problem_ids[k % len(problem_ids)]``: a diagnostic (it is handed the problem IDs), never a
    meta-test agent. Play the trials in order on those problems (the trial runners'
    ``problem_ids=``); trial k is the k-th trial the agent starts (counted at its first action, in
    the order :func:`~dream_envs.play_trials_batched` starts them), from its construction on.

    With ``explorers`` (scripted agents, e.g. the env's oracle, one per slot) they take the
    exploration actions instead of the exploration policy, and the decoder reads their trajectory.
    """

    def __init__(
        self,
        model: DREAM,
        problem_ids: Sequence[int],
        z_source: str = "f",
        seed: int = 0,
        explorers: Optional[Sequence[ScriptedAgent]] = None,
    ) -> None:
        self.z_source = check_choice("z_source", z_source, Z_SOURCES)
        self.explorers = None if explorers is None else list(explorers)
        generator = th.Generator(device=model.device).manual_seed(seed)
        # trial k's code: f(T) of its problem (noisy for "f_noisy")
        ids = np.asarray(problem_ids, dtype=np.int64)
        self.f = model.encode(ids, noisy=z_source == "f_noisy", generator=generator)
        self.g: Dict[int, np.ndarray] = {}  # trial -> g(tau^exp)
        self.trajectories: Dict[int, Tuple[np.ndarray, np.ndarray]] = {}  # trial -> (s_0..s_T, a_0..a_T-1)
        super().__init__(model, deterministic=True)

    def reset(self, n_envs: int) -> None:
        if self.explorers is not None and len(self.explorers) < n_envs:
            raise ValueError(f"explorers has {len(self.explorers)} agents for {n_envs} slots: pass one per slot")
        super().reset(n_envs)
        self.reset_numbering(n_envs)
        for explorer in (self.explorers or [])[:n_envs]:
            explorer.reset()

    def start_trials(self, idx: np.ndarray) -> None:
        super().start_trials(idx)
        self.note_starts(idx)
        if self.explorers is not None:
            for i in idx:
                self.explorers[i].reset()

    def act(self, obs: Dict[str, np.ndarray], infos: Sequence[Dict[str, Any]]) -> np.ndarray:
        self.number_new_trials()
        actions, explored = self.step(obs, infos)
        for i in explored:
            k = int(self.trial[i])
            self.g[k] = self.state.z[i].copy()
            n = int(self.state.length[i])
            self.trajectories[k] = (self.state.states[i, : n + 1].copy(), self.state.actions[i, :n].copy())
            if self.z_source != "g":
                self.state.z[i] = self.f[k % len(self.f)]
        if self.explorers is not None:
            phases = np.asarray(obs["phase"]).reshape(len(infos), -1)[:, 0]
            for i in np.flatnonzero(phases == EXPLORATION):
                if infos[i]:  # a slot with no trial left has an empty info
                    # the explorer's action replaces the policy's in the trajectory the decoder reads
                    actions[i] = int(self.explorers[i].act({key: v[i] for key, v in obs.items()}, infos[i]))
                    self.state.actions[i, self.state.length[i] - 1] = actions[i]
        return actions

    def codes(self) -> np.ndarray:
        """g(tau^exp) of the trials played so far, in trial order [n, z]."""
        return np.stack([self.g[k] for k in sorted(self.g)])


class PrivilegedAgent(SingleTrialAgent):
    """:class:`PrivilegedBatchAgent` one trial at a time (a :class:`~dream_envs.ScriptedAgent`, for
    reports that play trials in order): its arguments (``model, problem_ids, z_source, seed``), with
    one ``explorer``."""

    def __init__(self, *args: Any, explorer: Optional[ScriptedAgent] = None, **kwargs: Any) -> None:
        super().__init__(PrivilegedBatchAgent(*args, explorers=None if explorer is None else [explorer], **kwargs))

    @property
    def state(self) -> Any:
        """The model's trial state (the trajectory the decoder reads, z)."""
        return self.agent.state


def f_variance_by_feature(f: np.ndarray, features: np.ndarray) -> List[float]:
    """The variance of the codes ``f`` [n, z] (summed over z) that each column of ``features``
    [n, d] explains: the variance of the mean code of the problems that share that column's value.

    For problems that are the product of independent parts (MetaBus: the colored permutation and
    each gray bus), these add up to the total variance when f is additive over the parts.
    """
    centred = f - f.mean(axis=0)
    shares = []
    for column in features.T:
        values, groups = np.unique(column, return_inverse=True)
        means = np.zeros((len(values), f.shape[1]))
        np.add.at(means, groups, centred)
        means /= np.bincount(groups)[:, None]
        shares.append(float((means[groups] ** 2).sum(axis=1).mean()))
    return shares


def _check_dream(model: Any) -> None:
    if not isinstance(model, DREAM):
        raise TypeError(f"model must be a DREAM model, got {type(model).__name__}")


def diagnose(
    model: DREAM,
    env: Union[str, gym.Env],
    n_trials: int = 100,
    split: str = "test",
    seed: int = 0,
    env_kwargs: Optional[Dict[str, Any]] = None,
    problem_ids: Optional[Sequence[int]] = None,
    n_envs: int = 16,
    exhaustive: bool = False,
) -> DreamDiagnosis:
    """Meta-test ``model`` on the same ``n_trials`` trials of ``split`` with z = g(tau^exp), with
    z = f(T) and (if the model's encoder is noisy) with z ~ N(f(T), rho^2 I); see the module
    docstring for how to read the result. Its ``exploration_gains`` rewards the z = g trials'
    exploration steps (Equation 5), as :func:`exploration_gains` with the same arguments does.

    :param problem_ids: trial k's problem is ``problem_ids[k % len(problem_ids)]``; by default
        problems are drawn uniformly from ``split`` with ``seed``.
    :param n_envs: trials played side by side (an env ID is made that many times; a single env is
        played alone, a list of envs side by side, as in :func:`~sb3_dream.evaluation.evaluate_meta`).
        The same trials with any ``n_envs``, up to the rounding of batched matrix products.
    :param exhaustive: every (problem, instruction) pair of the split, in whole passes of at least
        ``n_trials`` trials, and every mean weighted by the pairs' probabilities, as
        :func:`~sb3_dream.evaluation.evaluate_meta` does (``n_trials`` of the result: the trials played).
    """
    _check_dream(model)
    with privileged_trials(env, n_trials, split, seed, env_kwargs, problem_ids, n_envs, exhaustive) as trials:
        problem_ids, split_ids, trial_env = trials.problem_ids, trials.split_ids, trials.envs[0].unwrapped
        results, agents = {}, {}
        for source in Z_SOURCES if model.encoder_noise else Z_SOURCES[:2]:
            agents[source] = PrivilegedBatchAgent(model, problem_ids, source, seed)
            results[source] = trials.play(agents[source])
        if hasattr(trial_env, "oracle"):  # custom trial envs may have none
            explorers = [make_oracle(e) for e in trials.envs]
            agents["optimal_exploration"] = PrivilegedBatchAgent(model, problem_ids, "g", seed, explorers=explorers)
            results["optimal_exploration"] = trials.play(agents["optimal_exploration"])
        features = trial_env.problem_feature_table()[split_ids]
    n_trials = len(problem_ids)

    f = agents["g"].f
    weights = results["g"].trial_weights  # uniform, or the pairs' probabilities when exhaustive

    def decoder_error(agent: PrivilegedBatchAgent) -> float:  # mean ||g(tau^exp) - f(T)||^2 over the trials
        return float(weights @ ((agent.codes() - f) ** 2).sum(axis=1))

    optimal = results.get("optimal_exploration")
    f_split = model.encode(split_ids, noisy=False)
    return DreamDiagnosis(
        return_g=results["g"].mean,
        return_f=results["f"].mean,
        return_f_noisy=results["f_noisy"].mean if "f_noisy" in results else None,
        decoder_error=decoder_error(agents["g"]),
        f_norm_sq=float(weights @ (f**2).sum(axis=1)),
        f_spread=mean_pair_sq_distance(f_split),
        f_variance_by_feature=f_variance_by_feature(f_split, features),
        exploration_length=results["g"].mean_exploration_length,
        n_trials=n_trials,
        return_g_optimal_exploration=None if optimal is None else optimal.mean,
        decoder_error_optimal_exploration=None if optimal is None else decoder_error(agents["optimal_exploration"]),
        exploration_gains=_rewarded(model, problem_ids, agents["g"]),
    )


@dataclass
class ExplorationGains:
    """The exploration reward of every step of ``n`` greedy explorations (:func:`exploration_gains`)."""

    problem_ids: np.ndarray  # [n] trial k's problem
    trajectories: List[Tuple[np.ndarray, np.ndarray]]  # trial k's states s_0..s_T [T+1, ...] and actions [T]
    rewards: List[np.ndarray]  # trial k's r_0..r_T-1 (Equation 5, the penalty c included) [T]
    reward_penalty: float  # c

    def by_step(self) -> np.ndarray:
        """The mean reward of step t over the trials that took it [max T]."""
        longest = max(len(r) for r in self.rewards)
        padded = np.full((len(self.rewards), longest), np.nan)
        for k, r in enumerate(self.rewards):
            padded[k, : len(r)] = r
        return np.nanmean(padded, axis=0)

    def information_gain(self) -> np.ndarray:
        """Per trial, the sum of r_t + c: ||f(T) - g(tau_:0)||^2 - ||f(T) - g(tau^exp)||^2 [n]."""
        return np.array([float((r + self.reward_penalty).sum()) for r in self.rewards])


@th.no_grad()
def exploration_gains(
    model: DREAM,
    env: Union[str, gym.Env],
    n_trials: int = 100,
    split: str = "test",
    seed: int = 0,
    env_kwargs: Optional[Dict[str, Any]] = None,
    problem_ids: Optional[Sequence[int]] = None,
    n_envs: int = 16,
    explorer: Optional[Callable[[gym.Env], ScriptedAgent]] = None,
    exhaustive: bool = False,
) -> ExplorationGains:
    """Play ``n_trials`` greedy meta-test trials of ``model`` (the trials :func:`diagnose` plays, with
    the same arguments) and reward each exploration step as training relabels it (Equation 5):
    r_t = ||f(T) - g(tau_:t)||^2 - ||f(T) - g(tau_:t+1)||^2 - c, with the model's current encoder
    (no noise) and decoder. A diagnostic: it reads each trial's problem ID.

    :param explorer: makes a scripted explorer for an env (e.g. ``dream_envs.make_oracle``, or a
        random agent): its explorations instead of the model's, rewarded by the model's f and g
        (what the model's reward would pay for steps its own explorer does not take).
    :param exhaustive: the trials of :func:`diagnose` with ``exhaustive=True`` (every (problem,
        instruction) pair of the split; the gains themselves are not weighted).
    """
    _check_dream(model)
    with privileged_trials(env, n_trials, split, seed, env_kwargs, problem_ids, n_envs, exhaustive) as trials:
        explorers = None if explorer is None else [explorer(e) for e in trials.envs]
        agent = PrivilegedBatchAgent(model, trials.problem_ids, "g", seed, explorers=explorers)
        trials.play(agent)
    return _rewarded(model, trials.problem_ids, agent)


@th.no_grad()
def _rewarded(model: DREAM, problem_ids: np.ndarray, agent: PrivilegedBatchAgent) -> ExplorationGains:
    """Equation 5's reward of every exploration step of the trials ``agent`` played (trial k's
    problem ``problem_ids[k]``), from the model's current f and g."""
    trajectories = [agent.trajectories[k] for k in sorted(agent.trajectories)]
    lengths = np.array([len(actions) for _, actions in trajectories])
    longest = int(lengths.max())
    # one decoder pass over the padded batch: prefix t of a trajectory never reads its padding
    states = np.zeros((len(trajectories), longest + 1, *trajectories[0][0].shape[1:]), trajectories[0][0].dtype)
    actions = np.zeros((len(trajectories), longest), trajectories[0][1].dtype)
    for k, (s, a) in enumerate(trajectories):
        states[k, : len(s)], actions[k, : len(a)] = s, a
    tensor = lambda a: th.as_tensor(a, device=model.device)  # noqa: E731
    g = model.policy.decoder(tensor(states), tensor(actions))  # [n, T+1, z]
    f = model.policy.encoder(tensor(model.problem_table[problem_ids]))
    rewards = model.exploration_rewards(g, f, th.as_tensor(lengths, device=model.device)).cpu().numpy()
    return ExplorationGains(
        problem_ids=problem_ids,
        trajectories=trajectories,
        rewards=[rewards[k, :n] for k, n in enumerate(lengths)],
        reward_penalty=float(model.reward_penalty),
    )
