"""DREAM acting in trials: what it remembers of each env's current trial, and one batched step.

During a trial's exploration episode the exploration policy Q^exp acts on its own history (an LSTM
state) and the trajectory tau^exp is recorded; when the episode ends, z is set: g(tau^exp), or
during training on alternate trials z ~ F(z | T) (Algorithm 1, line 11). The execution policy
Q^exe(s, i, z) then acts on it. :func:`act` does one step of ``n`` envs with one forward per
policy; :class:`DreamBatchTrialAgent` plays a model at meta-test, reading the exploration episode's
last state from ``info["final_obs"]``.
"""

from __future__ import annotations

from dataclasses import dataclass
import warnings
from typing import TYPE_CHECKING, Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch as th
from gymnasium import spaces

from dream_envs import EXECUTION, EXPLORATION, BatchTrialAgent, ScriptedAgent, SingleTrialAgent
from sb3_dream.dream.policies import DreamPolicy

if TYPE_CHECKING:
    from sb3_dream.dream.dream import DREAM

# The observation keys acting reads (the trial contract, see dream_envs.TrialEnv).
REQUIRED_KEYS = ("obs", "instruction", "phase", "prev_action", "prev_reward")


@dataclass
class TrialState:
    """What DREAM remembers about the current trial of each of ``n`` envs while acting."""

    hidden: Tuple[th.Tensor, th.Tensor]  # exploration LSTM state, each [1, n, hidden]
    states: np.ndarray  # [n, H+1, ...] exploration states s_0 .. s_T
    actions: np.ndarray  # [n, H]
    prev_actions: np.ndarray  # [n, H+1]
    prev_rewards: np.ndarray  # [n, H+1]
    length: np.ndarray  # [n] exploration steps taken
    z: np.ndarray  # [n, z_dim] the trial's z for execution (valid where z_ready)
    z_ready: np.ndarray  # [n] bool
    execution_step: np.ndarray  # [n] the step within the current execution episode
    # execution LSTM state, each [1, n, size] (size 0 for the paper's feed-forward execution Q)
    execution_hidden: Tuple[th.Tensor, th.Tensor]

    @classmethod
    def zeros(cls, policy: DreamPolicy, n_envs: int, horizon: int, state_dtype: np.dtype) -> "TrialState":
        """The state of ``n_envs`` trials that have not started."""
        zeros = lambda size: th.zeros(1, n_envs, size, device=policy.device)  # noqa: E731
        hidden_size, execution_size = policy.exploration_q.hidden_size, policy.execution_q.recurrent_size
        return cls(
            hidden=(zeros(hidden_size), zeros(hidden_size)),
            states=np.zeros((n_envs, horizon + 1, *policy.observation_space["obs"].shape), dtype=state_dtype),
            actions=np.zeros((n_envs, horizon), dtype=np.int64),
            prev_actions=np.zeros((n_envs, horizon + 1), dtype=np.int64),
            prev_rewards=np.zeros((n_envs, horizon + 1), dtype=np.float32),
            length=np.zeros(n_envs, dtype=np.int64),
            z=np.zeros((n_envs, policy.z_dim), dtype=np.float32),
            z_ready=np.zeros(n_envs, dtype=bool),
            execution_step=np.zeros(n_envs, dtype=np.int64),
            execution_hidden=(zeros(execution_size), zeros(execution_size)),
        )

    def reset(self, idx: np.ndarray) -> None:
        """Forget the trials of envs ``idx``: a new trial starts there."""
        for hidden in (*self.hidden, *self.execution_hidden):
            hidden[:, idx] = 0.0
        self.length[idx] = 0
        self.z_ready[idx] = False
        self.execution_step[idx] = 0
        self.prev_actions[idx] = 0
        self.prev_rewards[idx] = 0.0

    def as_tuple(self) -> Tuple[np.ndarray, ...]:
        """The state as numpy arrays (``predict``'s ``state``)."""
        h, c, exe_h, exe_c = (t.detach().cpu().numpy() for t in (*self.hidden, *self.execution_hidden))
        rest = (self.states, self.actions, self.prev_actions, self.prev_rewards, self.length)
        return (h, c, *rest, self.z, self.z_ready, self.execution_step, exe_h, exe_c)

    @classmethod
    def from_tuple(cls, state: Tuple[np.ndarray, ...], device: th.device) -> "TrialState":
        h, c, *rest, exe_h, exe_c = state
        tensor = lambda a: th.as_tensor(a, device=device).clone()  # noqa: E731
        return cls((tensor(h), tensor(c)), *(np.array(a, copy=True) for a in rest), (tensor(exe_h), tensor(exe_c)))


def model_states(states: np.ndarray, state_space: spaces.Space) -> np.ndarray:
    """States in the model's layout: SB3 stores images channel-first (``VecTransposeImage``),
    while a raw env and ``info["final_obs"]`` give them channel-last."""
    shape = state_space.shape
    states = np.asarray(states)
    if len(shape) == 3 and states.shape[-3:] != shape and states.shape[-3:] == (shape[1], shape[2], shape[0]):
        return np.moveaxis(states, -1, -3)
    return states


def batch_observation(observation: Dict[str, Any], policy: DreamPolicy) -> Tuple[Dict[str, np.ndarray], bool]:
    """``observation`` of one env or of a batch, as a batch, and whether it was a batch."""
    needs_start = policy.execution_time_input or policy.execution_recurrent
    required = REQUIRED_KEYS + (("episode_start",) if needs_start else ())
    if not isinstance(observation, dict) or any(k not in observation for k in required):
        raise ValueError(f"observation must be a dict with the trial keys {required}")
    state_space = policy.observation_space["obs"]
    obs = {k: np.asarray(v) for k, v in observation.items()}
    obs["obs"] = model_states(obs["obs"], state_space)
    if obs["obs"].shape != state_space.shape:
        return obs, True
    return {k: v[None] for k, v in obs.items()}, False


def epsilon_greedy(greedy: np.ndarray, eps: float, n_actions: int, rng: np.random.Generator) -> np.ndarray:
    """Each action replaced by a uniformly random one with probability ``eps``."""
    if eps <= 0:
        return greedy
    explore = rng.random(len(greedy)) < eps
    return np.where(explore, rng.integers(n_actions, size=len(greedy)), greedy)


@th.no_grad()
def decode(policy: DreamPolicy, state: TrialState, idx: np.ndarray, n_transitions: np.ndarray) -> np.ndarray:
    """g(tau_:n) for envs ``idx`` from their recorded exploration trajectories (one fused pass)."""
    tensor = lambda a: th.as_tensor(np.asarray(a), device=policy.device)  # noqa: E731
    t = int(max(1, n_transitions.max()))
    g = policy.decoder(tensor(state.states[idx, : t + 1]), tensor(state.actions[idx, :t]), tensor(n_transitions))
    return g.cpu().numpy()  # [k, z]


@th.no_grad()
def act(
    policy: DreamPolicy,
    obs: Dict[str, np.ndarray],
    state: TrialState,
    exploration_eps: float,
    execution_eps: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Actions of ``n`` envs (a batch from :func:`batch_observation`): one forward per policy.
    Records the exploration steps in ``state``."""
    tensor = lambda a: th.as_tensor(np.asarray(a), device=policy.device)  # noqa: E731
    n = len(obs["phase"])
    phase = np.asarray(obs["phase"]).reshape(n)
    actions = np.zeros(n, dtype=np.int64)
    n_actions, horizon = int(policy.action_space.n), state.actions.shape[1]

    explore = np.flatnonzero(phase == EXPLORATION)
    if len(explore):
        t = state.length[explore]
        state.states[explore, t] = obs["obs"][explore]
        state.prev_actions[explore, t] = np.asarray(obs["prev_action"]).reshape(n)[explore]
        state.prev_rewards[explore, t] = np.asarray(obs["prev_reward"]).reshape(n)[explore]
        hidden = (state.hidden[0][:, explore], state.hidden[1][:, explore])
        q, (h, c) = policy.exploration_q(
            tensor(obs["obs"][explore])[:, None],
            tensor(state.prev_actions[explore, t])[:, None],
            tensor(state.prev_rewards[explore, t])[:, None, None],
            hidden,
            tensor(t)[:, None] if policy.exploration_time_input else None,
        )
        state.hidden[0][:, explore], state.hidden[1][:, explore] = h, c
        chosen = epsilon_greedy(q[:, 0].argmax(dim=-1).cpu().numpy(), exploration_eps, n_actions, rng)
        actions[explore] = chosen
        state.actions[explore, np.minimum(t, horizon - 1)] = chosen
        state.length[explore] = np.minimum(t + 1, horizon)

    execute = np.flatnonzero(phase == EXECUTION)
    if len(execute):
        missing = execute[~state.z_ready[execute]]
        if len(missing):
            # The last exploration state is unknown here (only info["final_obs"] holds it):
            # use g of the trajectory without its last transition.
            state.z[missing] = decode(policy, state, missing, np.maximum(state.length[missing] - 1, 0))
            state.z_ready[missing] = True
        first = None
        if "episode_start" in obs:  # the step within the execution episode
            first = np.asarray(obs["episode_start"]).reshape(n)[execute].astype(bool)
            state.execution_step[execute] = np.where(first, 0, state.execution_step[execute] + 1)
        net = policy.execution_q
        hidden = None
        if net.recurrent:  # batch_observation requires episode_start for a recurrent network
            hidden = (state.execution_hidden[0][:, execute], state.execution_hidden[1][:, execute])
        q, hidden = net(
            tensor(obs["obs"][execute]),
            tensor(obs["instruction"][execute]),
            tensor(state.z[execute]),
            tensor(state.execution_step[execute]) if policy.execution_time_input else None,
            hidden,
            None if first is None else tensor(first),
        )
        if hidden is not None:
            state.execution_hidden[0][:, execute], state.execution_hidden[1][:, execute] = hidden
        actions[execute] = epsilon_greedy(q.argmax(dim=-1).cpu().numpy(), execution_eps, n_actions, rng)
    return actions


class DreamActing:
    """How DREAM acts in trials: the epsilons, z from the encoder or the decoder, the end of an
    exploration episode, ``predict`` and the meta-test agents. Part of :class:`~sb3_dream.DREAM`
    (which provides the networks, the counters and the hyperparameters these read)."""

    policy: DreamPolicy
    _warned_stateless_predict = False

    def new_trial_state(self, n_envs: int) -> TrialState:
        """The acting state of ``n_envs`` trials that have not started."""
        state_dtype = self.replay_buffer.exploration.states.dtype
        return TrialState.zeros(self.policy, n_envs, self.exploration_horizon, state_dtype)

    @property
    def exploration_epsilon(self) -> float:
        """Epsilon of the exploration policy (decays with exploration-episode steps)."""
        return self._epsilon_schedule(self._n_exploration_steps)

    @property
    def execution_epsilon(self) -> float:
        """Epsilon of the execution policy (decays with execution-episode steps)."""
        return self._execution_epsilon_schedule(self._n_execution_steps)

    @property
    def encoder_noise(self) -> bool:
        """Whether z from the encoder is noisy: with the bottleneck and rho^2 > 0."""
        return self.bottleneck and self.encoder_variance > 0

    def sample_encoder_z(self, f: th.Tensor, generator: Optional[th.Generator] = None) -> th.Tensor:
        """z ~ F(z | T) = N(f(T), rho^2 I) where the encoder is noisy (Equation 2's f branch), else f;
        the noise from ``generator`` (default: torch's global one)."""
        if not self.encoder_noise:
            return f
        noise = th.randn(f.shape, generator=generator, dtype=f.dtype, device=f.device)
        return f + noise * float(np.sqrt(self.encoder_variance))

    @th.no_grad()
    def encode(self, problem_ids: np.ndarray, noisy: bool, generator: Optional[th.Generator] = None) -> np.ndarray:
        """The encoder's z of problems ``problem_ids``: sampled from F(z | T) if ``noisy``, else f(T)."""
        f = self.policy.encoder(th.as_tensor(self.problem_table[problem_ids], device=self.device))
        return (self.sample_encoder_z(f, generator) if noisy else f).cpu().numpy()

    @th.no_grad()
    def decode_prefixes(self, trajectories: Sequence[Tuple[np.ndarray, np.ndarray]]) -> List[np.ndarray]:
        """The decoder's g(tau_:t) for every prefix of each exploration trajectory: what DREAM makes
        of an exploration after each of its steps.

        :param trajectories: one ``(states, actions)`` pair per exploration, ``states``
            ``[T_k + 1, ...]`` (s_0 .. s_T, image states channel-first or channel-last) and
            ``actions`` ``[T_k]``; the lengths ``T_k`` may differ (``T_k = 0``: nothing explored).
        :return: one array ``[T_k + 1, z_dim]`` per trajectory, in order: row t is g of the first t
            transitions, row 0 g of the empty trajectory and the last row g(tau^exp), the z the
            execution policy acts on at meta-test.
        """
        if len(trajectories) == 0:
            raise ValueError("trajectories is empty: pass at least one (states, actions) pair")
        space = self.observation_space["obs"]
        pairs = [(model_states(states, space), np.asarray(actions)) for states, actions in trajectories]
        for k, (states, actions) in enumerate(pairs):
            if actions.ndim != 1 or len(states) != len(actions) + 1 or states.shape[1:] != space.shape:
                raise ValueError(
                    f"trajectory {k}: states must be [T + 1, *{space.shape}] and actions [T], "
                    f"got {states.shape} and {actions.shape}"
                )
        lengths = [len(actions) for _, actions in pairs]
        # One decoder pass over the padded batch: prefix t reads only the first t transitions, so
        # the padding after a shorter trajectory never reaches its prefixes. At least one
        # transition is padded in, as the LSTM takes no empty sequence.
        width = max(1, max(lengths))
        states = np.zeros((len(pairs), width + 1, *space.shape), dtype=pairs[0][0].dtype)
        actions = np.zeros((len(pairs), width), dtype=np.int64)
        for k, (s, a) in enumerate(pairs):
            states[k, : len(s)], actions[k, : len(a)] = s, a
        tensor = lambda a: th.as_tensor(a, device=self.device)  # noqa: E731
        g = self.policy.decoder(tensor(states), tensor(actions)).cpu().numpy()  # [n, width + 1, z]
        return [g[k, : n + 1] for k, n in enumerate(lengths)]

    def end_exploration(
        self, state: TrialState, idx: np.ndarray, final_obs: np.ndarray, problem_ids: Optional[np.ndarray] = None
    ) -> None:
        """Close the exploration episodes of envs ``idx`` with their last states ``final_obs`` and set z.

        With ``problem_ids`` (training) the trajectories are stored and z alternates between the
        encoder and the decoder per trial; without (meta-test) z = g(tau^exp).
        """
        state.states[idx, state.length[idx]] = model_states(final_obs, self.observation_space["obs"])
        use_encoder = np.zeros(len(idx), dtype=bool)
        if problem_ids is not None:  # training: store tau^exp; z from the encoder on alternate trials
            self._store_explorations(state, idx, problem_ids)
            use_encoder = self._z_from_encoder[idx]
        z = decode(self.policy, state, idx, state.length[idx])
        if use_encoder.any():
            z[use_encoder] = self.encode(problem_ids[use_encoder], noisy=True)
        state.z[idx], state.z_ready[idx] = z, True

    def predict(
        self,
        observation: Dict[str, np.ndarray],
        state: Optional[Tuple[np.ndarray, ...]] = None,
        episode_start: Optional[np.ndarray] = None,
        deterministic: bool = False,
    ) -> Tuple[np.ndarray, Tuple[np.ndarray, ...]]:
        """Act at meta-test, following the sb3-contrib recurrent convention.

        ``state`` carries the trial: the exploration LSTM state, the exploration trajectory and,
        once exploration is over, z = g(tau^exp); it is reset where ``episode_start`` (a new
        trial) is set. Pass back the state each call returns: without it every call starts a new
        trial (a warning says so once). ``deterministic=False`` acts epsilon-greedily with the
        current epsilons. ``predict`` sees observations only, so the exploration episode's last
        state (in ``info["final_obs"]``) is not available to the decoder here;
        :meth:`as_trial_agent` (used by :func:`sb3_dream.evaluation.evaluate_meta`) passes it.
        """
        self.policy.set_training_mode(False)
        obs, vectorized = batch_observation(observation, self.policy)
        n = len(obs["phase"])
        if state is None:
            if np.any(np.asarray(obs["phase"]) != EXPLORATION) and not self._warned_stateless_predict:
                self._warned_stateless_predict = True
                warnings.warn(
                    "DREAM.predict was called without state in an execution episode: the state carries the "
                    "trial's exploration trajectory, from which the execution policy's z is decoded, so without "
                    "it execution acts on an empty exploration. Pass the state returned by the previous call.",
                    stacklevel=2,
                )
            trial = self.new_trial_state(n)
        else:
            trial = TrialState.from_tuple(state, self.device)
        starts = np.ones(n, bool) if episode_start is None else np.asarray(episode_start, dtype=bool).reshape(n)
        if state is None:
            starts[:] = True
        trial.reset(np.flatnonzero(starts))
        eps = (0.0, 0.0) if deterministic else (self.exploration_epsilon, self.execution_epsilon)
        actions = act(self.policy, obs, trial, *eps, self._rng)
        return (actions if vectorized else actions[0:1].reshape(())), trial.as_tuple()

    def as_trial_agent(self, deterministic: bool = True) -> ScriptedAgent:
        """A trial agent that also reads ``info["final_obs"]`` (see :mod:`sb3_dream.evaluation`)."""
        return DreamTrialAgent(self, deterministic)

    def as_batch_trial_agent(self, deterministic: bool = True) -> BatchTrialAgent:
        """:meth:`as_trial_agent` for trials played side by side (see :mod:`sb3_dream.evaluation`)."""
        return DreamBatchTrialAgent(self, deterministic)


class DreamBatchTrialAgent(BatchTrialAgent):
    """DREAM at meta-test in ``n_envs`` trial envs side by side, given ``info["final_obs"]`` at
    each exploration's end (what :func:`sb3_dream.evaluation.evaluate_meta` plays): z = g(tau^exp)
    of the whole trajectory."""

    def __init__(self, model: "DREAM", deterministic: bool = True) -> None:
        self.model, self.deterministic = model, deterministic
        self.reset(1)

    def reset(self, n_envs: int) -> None:
        self.state = self.model.new_trial_state(n_envs)

    def start_trials(self, idx: np.ndarray) -> None:
        self.state.reset(idx)

    def act(self, obs: Dict[str, np.ndarray], infos: Sequence[Dict[str, Any]]) -> np.ndarray:
        return self.step(obs, infos)[0]

    def step(self, observation: Dict[str, Any], infos: Sequence[Dict[str, Any]]) -> Tuple[np.ndarray, np.ndarray]:
        """The actions, and the envs whose exploration episode ``infos`` say just ended (their z is
        set first, with ``info["final_obs"]`` as the trajectory's last state)."""
        model = self.model
        model.policy.set_training_mode(False)
        obs, _ = batch_observation(observation, model.policy)
        explored = np.array(
            [k for k, info in enumerate(infos) if info.get("episode_end") and info.get("episode_phase") == EXPLORATION],
            dtype=np.int64,
        )
        if len(explored):
            final_obs = np.stack([np.asarray(infos[k]["final_obs"]) for k in explored])
            model.end_exploration(self.state, explored, final_obs)
        eps = (0.0, 0.0) if self.deterministic else (model.exploration_epsilon, model.execution_epsilon)
        return act(model.policy, obs, self.state, *eps, model._rng), explored


class DreamTrialAgent(SingleTrialAgent):
    """:class:`DreamBatchTrialAgent` one trial at a time (a :class:`~dream_envs.ScriptedAgent`)."""

    def __init__(self, model: "DREAM", deterministic: bool = True) -> None:
        super().__init__(DreamBatchTrialAgent(model, deterministic))
