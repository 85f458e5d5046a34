"""DREAM: Decoupled Reward-free ExplorAtion and execution in Meta-reinforcement learning.

Liu, Raghunathan, Liang, Finn: "Explore then Execute: Adapting without Rewards via Factorized
Meta-Reinforcement Learning" (ICML 2021), Section 4 and Algorithm 1 (Appendix A).

Per training trial (one Gymnasium episode of a :class:`dream_envs.TrialEnv`):

1. the exploration policy Q^exp(s_t, tau_:t) rolls out the reward-free exploration episode; its
   trajectory tau^exp goes to the exploration buffer (Algorithm 1, lines 7-9);
2. the trial's z is drawn alternately from the problem encoder, z ~ N(f(T), rho^2 I), or from the
   decoder, z = g(tau^exp) (line 11); the execution policy Q^exe(s, i, z) rolls out the execution
   episodes; their transitions go to the execution buffer with a reference to tau^exp (lines 12-13).

Every ``train_freq`` env steps, one update of each part (lines 14-23):

* exploration DDQN on the information-gain reward, recomputed with the current f and g
  (Equation 5): r_t = ||f(T) - g(tau_:t)||^2 - ||f(T) - g(tau_:t+1)||^2 - c;
* execution DDQN twice, with z = g(tau^exp) (trains theta, omega) and with z ~ N(f(T), rho^2 I)
  (trains theta, psi);
* the information bottleneck on f (Equation 3): lambda * max(||f(T)||^2, K), so only norms above K
  are pushed down;
* the decoder regression of every prefix g(tau_:t) toward stop-gradient f(T) (Equation 4).

At meta-test the execution policy always uses z = g(tau^exp): the problem ID is never needed.
"""

from __future__ import annotations

import io
import os
import pathlib
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Dict, List, Optional, Sequence, Tuple, Type, TypeVar, Union

import numpy as np
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.save_util import load_from_pkl
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, RolloutReturn, Schedule, TrainFreq
from stable_baselines3.common.utils import safe_mean
from stable_baselines3.common.vec_env import VecEnv

from dream_envs import EXECUTION, EXPLORATION, BatchTrialAgent, ScriptedAgent, SingleTrialAgent
from dream_envs.checks import check_choice, check_non_negative, check_positive_int
from sb3_dream.common.off_policy import TrialOffPolicyAlgorithm
from sb3_dream.common.recurrent import LinearEpsilonSchedule
from sb3_dream.dream.buffers import (
    DreamReplayBuffer,
    ExecutionBatch,
    ExecutionBuffer,
    ExplorationBuffer,
    TrajectoryBatch,
)
from sb3_dream.dream.policies import DreamPolicy, ExecutionQNetwork

SelfDREAM = TypeVar("SelfDREAM", bound="DREAM")

REQUIRED_KEYS = ("obs", "instruction", "phase", "prev_action", "prev_reward")
# What the execution Q's target conditions on (DREAM(execution_target_z=...)).
EXECUTION_TARGET_Z = ("own", "encoder")
EXECUTION_SAMPLING = ("transitions", "episodes")
PARALLEL_UPDATES = (True, False, "auto")


def available_cores() -> int:
    """CPU cores this process may run on (its affinity where the OS tells it)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


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
        h, c, exe_h, exe_c = (t.detach().cpu().numpy() for t in (*self.hidden, *self.execution_hidden))
        return (
            h,
            c,
            self.states,
            self.actions,
            self.prev_actions,
            self.prev_rewards,
            self.length,
            self.z,
            self.z_ready,
            self.execution_step,
            exe_h,
            exe_c,
        )

    @classmethod
    def from_tuple(cls, state: Tuple[np.ndarray, ...], device: th.device) -> "TrialState":
        h, c, *rest, exe_h, exe_c = state
        tensor = lambda a: th.as_tensor(a, device=device).clone()  # noqa: E731
        return cls((tensor(h), tensor(c)), *(np.array(a, copy=True) for a in rest), (tensor(exe_h), tensor(exe_c)))


class DREAM(TrialOffPolicyAlgorithm):
    """DREAM for trial envs (:mod:`dream_envs`), following the paper's Algorithm 1 and Appendix B.

    Defaults are the paper's (Table 1 and Appendix B.4); where the paper is silent, the authors'
    implementation's (learning starts, bottleneck threshold K).

    :param policy: "DreamPolicy" (default), or the env when it is the only argument:
        ``DREAM("MetaBus-v0")``.
    :param env: a trial env (or its ID, or a VecEnv of them).
    :param learning_rate: Adam learning rate of every network.
    :param buffer_size: exploration trajectories kept (the paper's 16000 sequences).
    :param execution_buffer_size: execution transitions kept (the paper's 100K experiences).
    :param batch_size: trajectories per exploration update and transitions per execution update.
    :param gamma: discount factor of both policies.
    :param train_freq: env steps (summed over envs) per update of each part (the paper's 4).
    :param target_update_interval: updates between target-network syncs (the paper's 5000).
    :param exploration_learning_starts: trials collected before the exploration policy learns.
    :param execution_learning_starts: trials collected before the execution side learns.
    :param exploration_initial_eps: epsilon of both policies at the start.
    :param exploration_final_eps: epsilon of both policies after the decay (of the exploration
        policy alone when ``execution_final_eps`` is set).
    :param eps_decay_steps: steps of *each* policy over which its epsilon decays (250K each).
    :param execution_final_eps: the execution policy's own final epsilon; None (default) is
        ``exploration_final_eps``, the paper's shared schedule. A deviation for envs whose execution
        learns from rare rewards long after its epsilon has decayed (SignNav3D's pickups, see
        docs/results.md), leaving the exploration policy's trajectories as they were.
    :param execution_eps_decay_steps: execution steps over which the execution epsilon decays; None
        (default) is ``eps_decay_steps``.
    :param reward_penalty: c in Equation 5, subtracted from every exploration reward.
    :param encoder_variance: rho^2 of F(z | T) = N(f(T), rho^2 I).
    :param bottleneck: False gives the paper's "DREAM (no bottleneck)" ablation: no noise on f
        and no penalty on its norm.
    :param bottleneck_threshold: K: only ||f(T)||^2 above K is penalised.
    :param bottleneck_weight: lambda, the weight of the bottleneck penalty.
    :param max_grad_norm: gradient-norm clip of each optimizer.
    :param z_dim: dimension of z.
    :param bootstrap_at_horizon: if False (default), an execution episode cut by the inner-episode
        horizon is terminal for the TD targets, as an episode "done" in the authors' DQN: the grid
        worlds' episodes *are* 20 steps long and their states hold no clock. True bootstraps there,
        treating the horizon as a time limit (SB3's ``handle_timeout_termination``).
    :param parallel_updates: run each step's exploration update, with the no-gradient passes
        (the exploration rewards' f and g, the target decoder's z), in a second thread while this
        one runs the execution update (their networks and optimizers are disjoint once the rewards
        are computed; the execution step waits for that). The same computations and the same
        results as sequential updates (tested), so it changes the speed only: about 1.2-1.6x
        faster updates when a second CPU core is free for this run (see docs/speed.md),
        slower when it is not (several runs sharing the cores: the experiment runner
        turns it off when it runs more than one at once). ``"auto"`` (default): on when the
        networks are on the CPU and this process may run on more than one core.
    :param execution_target_z: the z the execution Q's double-DQN target conditions on. ``"own"``
        (default): each loss's own source through the target networks, the target decoder's
        g(tau^exp) for the loss with z from g and the target encoder's f(T) for the loss with z from
        f. ``"encoder"``: the target encoder's f(T) for both, as in the authors' code (their target
        network always embedded the problem ID); it saves the target decoder's LSTM pass over the
        execution batch's trajectories (see docs/speed.md).
    :param execution_sampling: what one execution update learns from. ``"transitions"`` (default,
        the paper's Algorithm 1): ``batch_size`` transitions drawn uniformly from B_exe, each with
        its own trial's exploration trajectory. ``"episodes"`` (the authors' code, which samples its
        replay as whole episodes): ``batch_size`` execution episodes drawn uniformly, every stored
        transition of each; the decoder still reads ``batch_size`` trajectories (one per episode,
        shared by its transitions), so an update learns from up to the horizon's length times more
        execution transitions for a modest increase in its cost (the execution Q-network's passes
        grow, the decoder's do not; see docs/speed.md). The bottleneck and the decoder
        loss see the same ``batch_size`` trials either way.
    :param policy_kwargs: :class:`DreamPolicy` options: ``execution_hidden_sizes`` (the execution
        Q-network's body, the paper's ``(64,)``), ``execution_time_input`` (the execution Q also
        sees the step within its episode, so a greedy policy need not repeat itself on a second
        visit to a state; default False, the paper's network), ``execution_instruction_mlp``
        (default True, the paper's network; False lets the execution Q compose unseen recipes from
        their parts, see :class:`~sb3_dream.dream.policies.ExecutionQNetwork`),
        ``execution_recurrent`` (default False, the paper's feed-forward network; True runs an LSTM
        of 64 over each execution episode, as the authors' final code does, and needs
        ``execution_sampling="episodes"``), ``execution_weight_decay`` (default 0, the paper's Adam; > 0 decays the execution
        Q-network's weights, AdamW-style, see :class:`~sb3_dream.dream.policies.DreamPolicy`),
        ``z_dim``.
    """

    policy_aliases: ClassVar[Dict[str, Type[DreamPolicy]]] = {"DreamPolicy": DreamPolicy}
    policy: DreamPolicy
    replay_buffer: DreamReplayBuffer  # type: ignore[assignment]

    def __init__(
        self,
        policy: Union[str, Type[DreamPolicy], GymEnv] = "DreamPolicy",
        env: Union[GymEnv, str, None] = None,
        learning_rate: Union[float, Schedule] = 1e-4,
        buffer_size: int = 16_000,
        execution_buffer_size: int = 100_000,
        batch_size: int = 32,
        gamma: float = 0.99,
        train_freq: int = 4,
        target_update_interval: int = 5000,
        exploration_learning_starts: int = 8000,
        execution_learning_starts: int = 500,
        exploration_initial_eps: float = 1.0,
        exploration_final_eps: float = 0.01,
        eps_decay_steps: int = 250_000,
        execution_final_eps: Optional[float] = None,
        execution_eps_decay_steps: Optional[int] = None,
        reward_penalty: float = 0.01,
        encoder_variance: float = 0.1,
        bottleneck: bool = True,
        bottleneck_threshold: float = 10.0,
        bottleneck_weight: float = 1.0,
        max_grad_norm: float = 10.0,
        z_dim: int = 64,
        bootstrap_at_horizon: bool = False,
        parallel_updates: Union[bool, str] = "auto",
        execution_target_z: str = "own",
        execution_sampling: str = "transitions",
        stats_window_size: int = 100,
        tensorboard_log: Optional[str] = None,
        policy_kwargs: Optional[Dict[str, Any]] = None,
        verbose: int = 0,
        seed: Optional[int] = None,
        device: Union[th.device, str] = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        if env is None and not (isinstance(policy, type) or policy in self.policy_aliases):
            policy, env = "DreamPolicy", policy  # DREAM("MetaBus-v0"): the env is the only argument
        if env is None and _init_setup_model:
            raise ValueError("env is required: a trial env, its ID (e.g. 'MetaBus-v0') or a VecEnv of trial envs")
        for name, value, minimum in [
            ("buffer_size", buffer_size, 1),
            ("execution_buffer_size", execution_buffer_size, 1),
            ("batch_size", batch_size, 1),
            ("train_freq", train_freq, 1),
            ("target_update_interval", target_update_interval, 1),
            ("exploration_learning_starts", exploration_learning_starts, 0),
            ("execution_learning_starts", execution_learning_starts, 0),
            ("eps_decay_steps", eps_decay_steps, 0),
            ("z_dim", z_dim, 1),
        ]:
            check_positive_int(name, value, minimum)
        for name, value in [
            ("encoder_variance", encoder_variance),
            ("bottleneck_threshold", bottleneck_threshold),
            ("bottleneck_weight", bottleneck_weight),
            ("max_grad_norm", max_grad_norm),
        ]:
            check_non_negative(name, value)
        check_choice("execution_target_z", execution_target_z, EXECUTION_TARGET_Z)
        check_choice("parallel_updates", parallel_updates, PARALLEL_UPDATES)
        check_choice("execution_sampling", execution_sampling, EXECUTION_SAMPLING)

        super().__init__(
            policy,
            env,
            learning_rate,
            buffer_size=buffer_size,
            learning_starts=0,
            batch_size=batch_size,
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=1,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            support_multi_env=True,
            seed=seed,
            sde_support=False,
            supported_action_spaces=(spaces.Discrete,),
        )
        self._train_freq_steps = train_freq
        self.execution_buffer_size = execution_buffer_size
        self.target_update_interval = target_update_interval
        self.exploration_learning_starts = exploration_learning_starts
        self.execution_learning_starts = execution_learning_starts
        self.exploration_initial_eps = exploration_initial_eps
        self.exploration_final_eps = exploration_final_eps
        self.eps_decay_steps = eps_decay_steps
        self.execution_final_eps = execution_final_eps
        self.execution_eps_decay_steps = execution_eps_decay_steps
        self.reward_penalty = reward_penalty
        self.encoder_variance = encoder_variance
        self.bottleneck = bottleneck
        self.bottleneck_threshold = bottleneck_threshold
        self.bottleneck_weight = bottleneck_weight
        self.max_grad_norm = max_grad_norm
        self.z_dim = z_dim
        self.bootstrap_at_horizon = bootstrap_at_horizon
        self.parallel_updates = parallel_updates
        self.execution_target_z = execution_target_z
        self.execution_sampling = execution_sampling
        self._update_thread: Optional[ThreadPoolExecutor] = None

        if self.env is not None:
            self._check_trial_env(self.observation_space)
            # What the networks need to know about the problem family, kept with the model so that
            # loading needs no env: the structured problem representation and the exploration horizon.
            self.problem_table = np.asarray(self.env.env_method("problem_feature_table", indices=[0])[0])
            self.problem_nvec = np.asarray(self.env.get_attr("problem_nvec", indices=[0])[0])
            self.exploration_horizon = int(self.env.get_attr("horizon", indices=[0])[0])

        # Counters (saved with the model).
        self._n_trials = 0  # exploration trajectories collected
        self._n_exploration_steps = 0
        self._n_execution_steps = 0
        self._steps_since_update = 0
        self._z_from_encoder: Optional[np.ndarray] = None  # per env: this trial's z source
        if _init_setup_model:
            self._setup_model()

    # ------------------------------------------------------------------ set-up
    @staticmethod
    def _check_trial_env(observation_space: spaces.Space) -> None:
        if not isinstance(observation_space, spaces.Dict):
            raise TypeError(
                f"DREAM needs a trial env with a Dict observation (keys {', '.join(REQUIRED_KEYS)}), "
                f"got {type(observation_space).__name__}"
            )
        missing = [k for k in REQUIRED_KEYS if k not in observation_space.spaces]
        if missing:
            raise ValueError(f"the observation space lacks the trial keys {missing} (see dream_envs.TrialEnv)")

    def _setup_model(self) -> None:
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)
        shared = ("exploration_initial_eps", "exploration_final_eps", "eps_decay_steps")
        self._epsilon_schedule = LinearEpsilonSchedule(
            self.exploration_initial_eps, self.exploration_final_eps, self.eps_decay_steps, names=shared
        )
        # A shared value here was checked just above, so an error here names an execution option.
        own_final, own_steps = self.execution_final_eps, self.execution_eps_decay_steps
        self._execution_epsilon_schedule = LinearEpsilonSchedule(
            self.exploration_initial_eps,
            self.exploration_final_eps if own_final is None else own_final,
            self.eps_decay_steps if own_steps is None else own_steps,
            names=(shared[0], "execution_final_eps", "execution_eps_decay_steps"),
        )
        self._rng = np.random.default_rng(self.seed)
        # A new dict: the caller's policy_kwargs stay as given (the experiment runner compares them).
        self.policy_kwargs = {
            **self.policy_kwargs,
            "problem_nvec": self.problem_nvec,
            "z_dim": self.z_dim,
            "horizon": self.exploration_horizon,
        }
        self.policy = self.policy_class(
            self.observation_space, self.action_space, self.lr_schedule, **self.policy_kwargs
        )
        self.policy = self.policy.to(self.device)
        if self.policy.execution_recurrent and self.execution_sampling != "episodes":
            raise ValueError(
                "policy_kwargs execution_recurrent=True needs execution_sampling='episodes' (a recurrent "
                f"execution Q learns from whole execution episodes), got execution_sampling={self.execution_sampling!r}"
            )
        exploration = ExplorationBuffer(
            self.buffer_size,
            self.exploration_horizon,
            self.observation_space["obs"],
            len(self.problem_nvec),
            self.device,
        )
        execution = ExecutionBuffer(self.execution_buffer_size, self.observation_space, self.device)
        self.replay_buffer = DreamReplayBuffer(exploration, execution)
        self.train_freq = TrainFreq(1, "step")  # type: ignore[assignment]  # we count env steps ourselves
        self._trial_state: Optional[TrialState] = None

    def _excluded_save_params(self) -> List[str]:
        return [*super()._excluded_save_params(), "_trial_state", "_update_thread"]

    def _get_torch_save_params(self) -> Tuple[List[str], List[str]]:
        return ["policy", "policy.optimizer", "policy.exploration_optimizer"], []

    def load_replay_buffer(
        self, path: Union[str, pathlib.Path, io.BufferedIOBase], truncate_last_traj: bool = True
    ) -> None:
        buffer = load_from_pkl(path, self.verbose)
        if not isinstance(buffer, DreamReplayBuffer):
            raise TypeError(f"{path} does not hold a DREAM replay buffer (got {type(buffer).__name__})")
        buffer.device = self.device
        self.replay_buffer = buffer

    def new_trial_state(self, n_envs: int) -> TrialState:
        h = self.exploration_horizon
        obs_space = self.observation_space["obs"]
        zeros = lambda size: th.zeros(1, n_envs, size, device=self.device)  # noqa: E731
        hidden_size, execution_size = self.policy.exploration_q.hidden_size, self.policy.execution_q.recurrent_size
        return TrialState(
            hidden=(zeros(hidden_size), zeros(hidden_size)),
            states=np.zeros((n_envs, h + 1, *obs_space.shape), dtype=self.replay_buffer.exploration.states.dtype),
            actions=np.zeros((n_envs, h), dtype=np.int64),
            prev_actions=np.zeros((n_envs, h + 1), dtype=np.int64),
            prev_rewards=np.zeros((n_envs, h + 1), dtype=np.float32),
            length=np.zeros(n_envs, dtype=np.int64),
            z=np.zeros((n_envs, self.z_dim), dtype=np.float32),
            z_ready=np.zeros(n_envs, dtype=bool),
            execution_step=np.zeros(n_envs, dtype=np.int64),
            execution_hidden=(zeros(execution_size), zeros(execution_size)),
        )

    # ------------------------------------------------------------------ epsilons
    @property
    def exploration_epsilon(self) -> float:
        """Epsilon of the exploration policy (decays with exploration-episode steps)."""
        return self._epsilon_schedule(self._n_exploration_steps)

    @property
    def execution_epsilon(self) -> float:
        """Epsilon of the execution policy (decays with execution-episode steps)."""
        return self._execution_epsilon_schedule(self._n_execution_steps)

    # ------------------------------------------------------------------ acting
    def _obs_tensor(self, x: np.ndarray) -> th.Tensor:
        return th.as_tensor(np.asarray(x), device=self.device)

    @th.no_grad()
    def _decode(self, state: TrialState, idx: np.ndarray, n_transitions: np.ndarray) -> np.ndarray:
        """g(tau_:n) for envs ``idx`` from their stored exploration trajectories (one fused pass)."""
        t = int(max(1, n_transitions.max()))
        g = self.policy.decoder(
            self._obs_tensor(state.states[idx, : t + 1]),
            self._obs_tensor(state.actions[idx, :t]),
            th.as_tensor(n_transitions, device=self.device),
        )  # [k, z]
        return g.cpu().numpy()

    @th.no_grad()
    def _encode(self, problem_ids: np.ndarray, noisy: bool, generator: Optional[th.Generator] = None) -> np.ndarray:
        """z ~ N(f(T), rho^2 I) (or f(T) without the bottleneck's noise); the noise from ``generator``
        (default: torch's global one)."""
        f = self.policy.encoder(self._obs_tensor(self.problem_table[problem_ids]))
        return (self._add_encoder_noise(f, generator) if noisy else f).cpu().numpy()

    @property
    def encoder_noise(self) -> bool:
        """Whether z from the encoder is noisy: with the bottleneck and rho^2 > 0."""
        return self.bottleneck and self.encoder_variance > 0

    def _add_encoder_noise(self, f: th.Tensor, generator: Optional[th.Generator] = None) -> th.Tensor:
        """f + N(0, rho^2 I) where the encoder is noisy (Equation 2's f branch), else f unchanged."""
        if not self.encoder_noise:
            return f
        noise = th.randn(f.shape, generator=generator, dtype=f.dtype, device=f.device)
        return f + noise * float(np.sqrt(self.encoder_variance))

    @th.no_grad()
    def _act(
        self, obs: Dict[str, np.ndarray], state: TrialState, exploration_eps: float, execution_eps: float
    ) -> np.ndarray:
        """One batched forward per policy for ``n`` envs; records the exploration steps in ``state``."""
        n = len(obs["phase"])
        phase = np.asarray(obs["phase"]).reshape(n)
        actions = np.zeros(n, dtype=np.int64)
        n_actions = int(self.action_space.n)

        explore = np.flatnonzero(phase == EXPLORATION)
        if len(explore):
            t = state.length[explore]
            state.states[explore, t] = obs["obs"][explore]
            state.prev_actions[explore, t] = np.asarray(obs["prev_action"]).reshape(n)[explore]
            state.prev_rewards[explore, t] = np.asarray(obs["prev_reward"]).reshape(n)[explore]
            hidden = (state.hidden[0][:, explore], state.hidden[1][:, explore])
            q, (h, c) = self.policy.exploration_q(
                self._obs_tensor(obs["obs"][explore])[:, None],
                self._obs_tensor(state.prev_actions[explore, t])[:, None],
                self._obs_tensor(state.prev_rewards[explore, t])[:, None, None],
                hidden,
                self._obs_tensor(t)[:, None] if self.policy.exploration_time_input else None,
            )
            state.hidden[0][:, explore], state.hidden[1][:, explore] = h, c
            chosen = q[:, 0].argmax(dim=-1).cpu().numpy()
            chosen = self._epsilon_greedy(chosen, exploration_eps, n_actions)
            actions[explore] = chosen
            state.actions[explore, np.minimum(t, self.exploration_horizon - 1)] = chosen
            state.length[explore] = np.minimum(t + 1, self.exploration_horizon)

        execute = np.flatnonzero(phase == EXECUTION)
        if len(execute):
            missing = execute[~state.z_ready[execute]]
            if len(missing):
                # The last exploration state is unknown here (only info["final_obs"] holds it):
                # use g of the trajectory without its last transition.
                state.z[missing] = self._decode(state, missing, np.maximum(state.length[missing] - 1, 0))
                state.z_ready[missing] = True
            first = None
            if "episode_start" in obs:  # the step within the execution episode
                first = np.asarray(obs["episode_start"]).reshape(n)[execute].astype(bool)
                state.execution_step[execute] = np.where(first, 0, state.execution_step[execute] + 1)
            net = self.policy.execution_q
            embedding = net.embed(
                self._obs_tensor(obs["obs"][execute]),
                self._obs_tensor(obs["instruction"][execute]),
                self._obs_tensor(state.execution_step[execute]) if self.policy.execution_time_input else None,
            )
            if net.recurrent:  # one LSTM step, from zeros where an execution episode starts
                assert first is not None  # _batch_observation requires episode_start
                keep = self._obs_tensor(~first)[None, :, None].to(embedding.dtype)
                hidden = tuple(h[:, execute] * keep for h in state.execution_hidden)
                out, (h, c) = net.recur(embedding[:, None], hidden)
                state.execution_hidden[0][:, execute], state.execution_hidden[1][:, execute] = h, c
                embedding = out[:, 0]
            q = net.q_values(embedding, self._obs_tensor(state.z[execute]))
            chosen = q.argmax(dim=-1).cpu().numpy()
            actions[execute] = self._epsilon_greedy(chosen, execution_eps, n_actions)
        return actions

    def _epsilon_greedy(self, greedy: np.ndarray, eps: float, n_actions: int) -> np.ndarray:
        if eps <= 0:
            return greedy
        explore = self._rng.random(len(greedy)) < eps
        return np.where(explore, self._rng.integers(n_actions, size=len(greedy)), greedy)

    def end_exploration(
        self, state: TrialState, idx: np.ndarray, final_obs: np.ndarray, problem_ids: Optional[np.ndarray] = None
    ) -> None:
        """Close the exploration episodes of envs ``idx`` with their last states ``final_obs`` and set z.

        With ``problem_ids`` (training) the trajectories are stored and z alternates between the
        encoder and the decoder per trial; without (meta-test) z = g(tau^exp).
        """
        state.states[idx, state.length[idx]] = self._model_states(final_obs)
        use_encoder = np.zeros(len(idx), dtype=bool)
        if problem_ids is not None:
            assert self._z_from_encoder is not None
            use_encoder = self._z_from_encoder[idx]
            for k, e in enumerate(idx):
                slot, generation = self.replay_buffer.exploration.add(
                    state.states[e],
                    state.actions[e],
                    state.prev_actions[e],
                    state.prev_rewards[e],
                    int(state.length[e]),
                    self.problem_table[problem_ids[k]],
                )
                self._slots[e], self._generations[e] = slot, generation
            self._n_trials += len(idx)
            self._exploration_lengths.extend(state.length[idx].tolist())
        z = self._decode(state, idx, state.length[idx])
        if use_encoder.any():
            z[use_encoder] = self._encode(problem_ids[use_encoder], noisy=True)
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
        trial) is set. ``deterministic=False`` acts epsilon-greedily with the current epsilons.
        ``predict`` sees observations only, so the exploration episode's last state (in
        ``info["final_obs"]``) is not available to the decoder here; :meth:`as_trial_agent`
        (used by :func:`sb3_dream.evaluation.evaluate_meta`) passes it.
        """
        self.policy.set_training_mode(False)
        obs, vectorized = self._batch_observation(observation)
        n = len(obs["phase"])
        trial = self.new_trial_state(n) if state is None else TrialState.from_tuple(state, self.device)
        starts = np.ones(n, bool) if episode_start is None else np.asarray(episode_start, dtype=bool).reshape(n)
        if state is None:
            starts[:] = True
        trial.reset(np.flatnonzero(starts))
        eps = (0.0, 0.0) if deterministic else (self.exploration_epsilon, self.execution_epsilon)
        actions = self._act(obs, trial, *eps)
        return (actions if vectorized else actions[0:1].reshape(())), trial.as_tuple()

    def _model_states(self, states: np.ndarray) -> np.ndarray:
        """States in the model's layout: SB3 stores images channel-first (``VecTransposeImage``),
        while a raw env and ``info["final_obs"]`` give them channel-last."""
        shape = self.observation_space["obs"].shape
        states = np.asarray(states)
        if len(shape) == 3 and states.shape[-3:] != shape and states.shape[-3:] == (shape[1], shape[2], shape[0]):
            return np.moveaxis(states, -1, -3)
        return states

    def _batch_observation(self, observation: Dict[str, Any]) -> Tuple[Dict[str, np.ndarray], bool]:
        needs_start = self.policy.execution_time_input or self.policy.execution_recurrent
        required = REQUIRED_KEYS + (("episode_start",) if needs_start else ())
        if not isinstance(observation, dict) or any(k not in observation for k in required):
            raise ValueError(f"observation must be a dict with the trial keys {required}")
        obs = {k: np.asarray(v) for k, v in observation.items()}
        obs["obs"] = self._model_states(obs["obs"])
        vectorized = obs["obs"].shape != self.observation_space["obs"].shape
        if vectorized:
            return obs, True
        return {k: v[None] for k, v in obs.items()}, False

    def as_trial_agent(self, deterministic: bool = True) -> ScriptedAgent:
        """A trial agent that also reads ``info["final_obs"]`` (see :mod:`sb3_dream.evaluation`)."""
        return DreamTrialAgent(self, deterministic)

    def as_batch_trial_agent(self, deterministic: bool = True) -> BatchTrialAgent:
        """:meth:`as_trial_agent` for trials played side by side (see :mod:`sb3_dream.evaluation`)."""
        return DreamBatchTrialAgent(self, deterministic)

    def _meta_test_act(
        self, state: TrialState, observation: Dict[str, Any], infos: Sequence[Dict[str, Any]], deterministic: bool
    ) -> Tuple[np.ndarray, np.ndarray]:
        """The actions of the envs in ``state`` at meta-test, and the envs whose exploration episode
        ``infos`` say just ended: their z is set first, g of the whole trajectory with
        ``info["final_obs"]`` as its last state."""
        self.policy.set_training_mode(False)
        obs, _ = self._batch_observation(observation)
        explored = np.array(
            [k for k, info in enumerate(infos) if info.get("episode_end") and info.get("episode_phase") == EXPLORATION],
            dtype=np.int64,
        )
        if len(explored):
            final_obs = np.stack([np.asarray(infos[k]["final_obs"]) for k in explored])
            self.end_exploration(state, explored, final_obs)
        eps = (0.0, 0.0) if deterministic else (self.exploration_epsilon, self.execution_epsilon)
        return self._act(obs, state, *eps), explored

    # ------------------------------------------------------------------ collecting
    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> Tuple[int, BaseCallback]:
        total_timesteps, callback = super()._setup_learn(
            total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar
        )
        assert self.env is not None
        n = self.env.num_envs
        self._trial_state = self.new_trial_state(n)
        if self._z_from_encoder is None or len(self._z_from_encoder) != n:
            self._z_from_encoder = np.arange(n) % 2 == 0
        self._slots = np.zeros(n, dtype=np.int64)
        self._generations = np.zeros(n, dtype=np.int64)
        self._exploration_lengths: deque = deque(maxlen=self._stats_window_size)
        self._returns_by_source: Dict[str, deque] = {
            "f": deque(maxlen=self._stats_window_size),
            "g": deque(maxlen=self._stats_window_size),
        }
        return total_timesteps, callback

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        train_freq: TrainFreq,
        replay_buffer: ReplayBuffer,
        action_noise: Optional[ActionNoise] = None,
        learning_starts: int = 0,
        log_interval: Optional[int] = None,
    ) -> RolloutReturn:
        """Step all envs until ``train_freq`` env steps have passed since the last update."""
        assert self._trial_state is not None and self._z_from_encoder is not None
        self.policy.set_training_mode(False)
        state, n = self._trial_state, env.num_envs
        callback.on_rollout_start()
        n_steps, n_trials = 0, 0
        while self._steps_since_update < self.train_freq_steps:
            obs = self._last_obs
            phase = np.asarray(obs["phase"]).reshape(n)
            actions = self._act(obs, state, self.exploration_epsilon, self.execution_epsilon)
            new_obs, rewards, dones, infos = env.step(actions)

            self.num_timesteps += n
            n_steps += 1
            self._steps_since_update += n
            self._n_exploration_steps += int((phase == EXPLORATION).sum())
            self._n_execution_steps += int((phase == EXECUTION).sum())
            callback.update_locals(locals())
            if not callback.on_step():
                return RolloutReturn(n_steps * n, n_trials, continue_training=False)
            self._update_info_buffer(infos, dones)
            self._store_step(obs, actions, rewards, new_obs, dones, infos, phase)
            self._update_current_progress_remaining(self.num_timesteps, self._total_timesteps)
            self._last_obs = new_obs

            for e in np.flatnonzero(dones):
                n_trials += 1
                self._episode_num += 1
                state.reset(np.array([e]))
                self._z_from_encoder[e] = not self._z_from_encoder[e]  # alternate z sources across trials
                if log_interval is not None and self._episode_num % log_interval == 0:
                    self.dump_logs()
        callback.on_rollout_end()
        return RolloutReturn(n_steps * n, n_trials, continue_training=True)

    @property
    def train_freq_steps(self) -> int:
        return int(self._train_freq_steps)

    def _store_step(
        self,
        obs: Dict[str, np.ndarray],
        actions: np.ndarray,
        rewards: np.ndarray,
        new_obs: Dict[str, np.ndarray],
        dones: np.ndarray,
        infos: List[Dict[str, Any]],
        phase: np.ndarray,
    ) -> None:
        state = self._trial_state
        assert state is not None
        ended = np.array([bool(info.get("episode_end")) for info in infos])
        # exploration episodes that just ended: store tau^exp, set the trial's z
        explored = np.flatnonzero((phase == EXPLORATION) & ended)
        if len(explored):
            final = np.stack([infos[e]["final_obs"] for e in explored])
            problem_ids = np.array([infos[e]["problem_id"] for e in explored])
            self.end_exploration(state, explored, final, problem_ids)
        # execution transitions, each pointing at its trial's exploration trajectory
        executed = np.flatnonzero(phase == EXECUTION)
        if len(executed):
            next_states = np.array(new_obs["obs"][executed], copy=True)
            for k, e in enumerate(executed):
                if ended[e]:
                    next_states[k] = self._model_states(infos[e]["final_obs"])
                    source = "f" if self._z_from_encoder[e] else "g"
                    self._returns_by_source[source].append(infos[e]["episode_return"])
            truncated = np.array([bool(infos[e].get("episode_truncated", False)) for e in executed])
            terminal = ended[executed] & ~(truncated & self.bootstrap_at_horizon)
            self.replay_buffer.execution.add(
                {
                    "states": obs["obs"][executed],
                    "instructions": obs["instruction"][executed],
                    "actions": actions[executed],
                    "rewards": rewards[executed],
                    "next_states": next_states,
                    "dones": terminal.astype(np.float32),
                    "slots": self._slots[executed],
                    "generations": self._generations[executed],
                    "steps": state.execution_step[executed],
                },
                envs=executed,
            )

    def learn(
        self: SelfDREAM,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 100,
        tb_log_name: str = "DREAM",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfDREAM:
        """Train for ``total_timesteps`` env steps (``log_interval`` counts trials)."""
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def _updates_due(self, rollout: RolloutReturn) -> int:
        """One update of each part per ``train_freq`` env steps, summed over envs (Algorithm 1)."""
        n_updates = self._steps_since_update // self.train_freq_steps
        self._steps_since_update -= n_updates * self.train_freq_steps
        return n_updates

    # ------------------------------------------------------------------ training
    def train(self, gradient_steps: int, batch_size: int = 32) -> None:
        # Buffers are checked too: after `load` without `load_replay_buffer` the
        # trial counter is restored but the buffers start empty.
        buffers = self.replay_buffer
        exploration_ready = self._n_trials >= max(1, self.exploration_learning_starts) and len(buffers.exploration) > 0
        execution_ready = self._n_trials >= max(1, self.execution_learning_starts) and len(buffers.execution) > 0
        if not (exploration_ready or execution_ready) or gradient_steps <= 0:
            return
        self.policy.set_training_mode(True)
        self._update_learning_rate([self.policy.optimizer, self.policy.exploration_optimizer])
        stats: Dict[str, List[float]] = {}
        for _ in range(gradient_steps):
            for key, value in self._update(batch_size, exploration_ready, execution_ready).items():
                stats.setdefault(key, []).append(value)
            self._n_updates += 1
            if self._n_updates % self.target_update_interval == 0:
                self.policy.sync_targets()
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in stats.items():
            self.logger.record(f"train/{key}", float(np.mean(values)))

    def _update(self, batch_size: int, exploration_ready: bool, execution_ready: bool) -> Dict[str, float]:
        """One gradient step of each part that is ready, in Algorithm 1's order: exploration
        (lines 14-16), then execution, bottleneck and decoder on the execution samples (17-21)."""
        buffers, stats = self.replay_buffer, {}
        if exploration_ready:
            explored = buffers.exploration.get(self._rng.integers(len(buffers.exploration), size=batch_size))
        if execution_ready:
            exe, traj = self._sample_execution(batch_size)
        if self.updates_in_parallel and exploration_ready and execution_ready:
            return self._parallel_update(explored, exe, traj)
        if exploration_ready:
            stats.update(self._exploration_update(explored, *self._reward_codes(explored)))
        if execution_ready:
            stats.update(self._execution_losses(exe, traj))
        return stats

    def _sample_execution(self, batch_size: int) -> Tuple[ExecutionBatch, TrajectoryBatch]:
        """An execution batch (``execution_sampling``) and the exploration trajectories it reads."""
        buffers = self.replay_buffer
        if self.execution_sampling == "episodes":
            exe = buffers.execution.sample_episodes(batch_size, buffers.exploration, self._rng)
        else:
            exe = buffers.execution.sample(batch_size, buffers.exploration, self._rng)
        return exe, buffers.exploration.get(exe.slots)

    @th.no_grad()
    def _reward_codes(self, traj: TrajectoryBatch) -> Tuple[th.Tensor, th.Tensor]:
        """g of every prefix and f(T) for the exploration rewards: the current networks, as targets."""
        return self.policy.decoder(traj.states, traj.actions), self.policy.encoder(traj.problem_features)

    @th.no_grad()
    def _target_decoder_z(self, traj: TrajectoryBatch) -> th.Tensor:
        """The target decoder's g(tau^exp) of each trajectory (the "own" target z of the loss with z = g)."""
        return self.policy.decoder_target(traj.states, traj.actions, traj.lengths)

    @property
    def updates_in_parallel(self) -> bool:
        """Whether the exploration update runs in a second thread (``parallel_updates``, "auto" resolved)."""
        if isinstance(self.parallel_updates, str):  # "auto"
            return self.device.type == "cpu" and available_cores() > 1
        return bool(self.parallel_updates)

    def _parallel_update(self, explored: TrajectoryBatch, exe: ExecutionBatch, traj: TrajectoryBatch) -> Dict[str, float]:
        """``parallel_updates``: the no-gradient passes and the exploration update run in a second
        thread beside the execution update, with the same inputs, so with the same results.

        The worker runs, in order, the target decoder's pass for the execution targets (with
        ``execution_target_z="own"``), the reward pass of the current f and g over the exploration
        batch, and the exploration DDQN step. The execution update waits for the first before its
        targets, and for the second before its optimizer step changes f and g.
        """
        if self._update_thread is None:
            self._update_thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dream-exploration")
        worker = self._update_thread
        target_z_g = worker.submit(self._target_decoder_z, traj) if self.execution_target_z == "own" else None
        codes = worker.submit(self._reward_codes, explored)
        exploration = worker.submit(lambda: self._exploration_update(explored, *codes.result()))
        stats = self._execution_losses(
            exe, traj, target_z_g=None if target_z_g is None else target_z_g.result, before_step=codes.result
        )
        return {**exploration.result(), **stats}

    def _execution_losses(
        self,
        exe: ExecutionBatch,
        traj: TrajectoryBatch,
        target_z_g: Optional[Callable[[], th.Tensor]] = None,
        before_step: Optional[Callable[[], Any]] = None,
    ) -> Dict[str, float]:
        """Execution DDQN with z from g and from F, the bottleneck and the decoder loss, one step.

        Everything here is computed on the same execution samples (Appendix A: the bottleneck and
        the decoder are updated "from the same execution replay buffer samples"): g of every prefix
        of the batch's exploration trajectories ``traj`` (one decoder pass), and f(T); transition j
        reads trajectory ``exe.trajectories[j]``.
        ``target_z_g`` gives the target decoder's z when another thread computes it;
        ``before_step`` is called before the optimizer changes the networks.
        """
        policy = self.policy
        g_all = policy.decoder(traj.states, traj.actions)  # [N, T+1, z]: every prefix in one pass
        f = policy.encoder(traj.problem_features)  # [N, z]
        n_exe, owner = len(exe.actions), exe.trajectories
        z_g = g_all[th.arange(len(g_all), device=self.device), traj.lengths][owner]  # g(tau^exp) of each trial
        z_f = self._add_encoder_noise(f[owner])

        # Both DDQN losses in one forward: rows [0, B) use z from g, rows [B, 2B) z from f.
        z = th.cat([z_g, z_f])
        actions, rewards, dones = exe.actions.repeat(2), exe.rewards.repeat(2), exe.dones.repeat(2)
        net, next_embedding = policy.execution_q, None
        if net.recurrent:  # one LSTM pass gives both s's and s''s inputs
            embedding, next_embedding = self._episode_embeddings(net, exe)
            next_embedding = next_embedding.detach()
        else:
            embedding = net.embed(exe.states, exe.instructions, exe.steps)
        q = net.q_values(embedding.repeat(2, 1), z).gather(1, actions[:, None]).squeeze(1)
        with th.no_grad():
            if next_embedding is None:
                next_embedding = self._next_embedding(net, exe)
            next_online = net.q_values(next_embedding.repeat(2, 1), z)
            z_f_target = policy.encoder_target(traj.problem_features)[owner]
            if self.execution_target_z == "own":
                z_g_target = target_z_g() if target_z_g is not None else self._target_decoder_z(traj)
                z_target = th.cat([z_g_target[owner], z_f_target])
            else:  # "encoder": the authors' code, no decoder pass
                z_target = z_f_target.repeat(2, 1)
            next_target = policy.execution_q_target.q_values(
                self._next_embedding(policy.execution_q_target, exe).repeat(2, 1), z_target
            )
            best = next_online.argmax(dim=1, keepdim=True)
            target = rewards + self.gamma * (1.0 - dones) * next_target.gather(1, best).squeeze(1)
        td = F.mse_loss(q, target, reduction="none")
        loss_traj, loss_prob = td[:n_exe].mean(), td[n_exe:].mean()

        f_norm = f.pow(2).sum(dim=1)
        bottleneck = self.bottleneck_loss(f)
        # Decoder regression (Equation 4) toward stop-gradient f over every valid prefix t = 0..T.
        n_prefix = g_all.shape[1]
        valid = (th.arange(n_prefix, device=self.device)[None] <= traj.lengths[:, None]).float()
        sq = (g_all - f.detach()[:, None]).pow(2).sum(dim=-1)
        decoder_loss = (sq * valid).sum() / valid.sum()

        loss = loss_traj + loss_prob + self.bottleneck_weight * bottleneck + decoder_loss
        policy.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        params = [p for group in policy.optimizer.param_groups for p in group["params"]]
        th.nn.utils.clip_grad_norm_(params, self.max_grad_norm)
        if before_step is not None:
            before_step()
        policy.optimizer.step()
        return {
            "execution_loss_traj": loss_traj.item(),
            "execution_loss_prob": loss_prob.item(),
            "execution_q_mean": q.mean().item(),
            "decoder_loss": decoder_loss.item(),
            "f_norm_sq": f_norm.mean().item(),
            "bottleneck_loss": float(bottleneck.item()),
        }

    def _next_embedding(self, net: ExecutionQNetwork, exe: ExecutionBatch) -> th.Tensor:
        """What ``net`` feeds its body for each transition's s' ([B, D])."""
        if net.recurrent:
            return self._episode_embeddings(net, exe)[1]
        return net.embed(exe.next_states, exe.instructions, exe.steps + 1)

    @staticmethod
    def _episode_embeddings(net: ExecutionQNetwork, exe: ExecutionBatch) -> Tuple[th.Tensor, th.Tensor]:
        """A recurrent ``net``'s LSTM outputs for each transition's s and s' ([B, D] each).

        The batch holds whole episodes (``execution_sampling="episodes"``: transition j is step
        ``steps[j]`` of episode ``trajectories[j]``), so each episode's states s_0 .. s_L (s_L: its
        last transition's s') are laid out as one [E, L+1] sequence, and one fused LSTM pass from
        zeros gives h_t for s_t and h_{t+1} for s'.
        """
        episode, step = exe.trajectories, exe.steps
        n_episodes, horizon = int(episode.max()) + 1, int(step.max()) + 1
        length = th.zeros(n_episodes, dtype=step.dtype, device=step.device).scatter_reduce(
            0, episode, step + 1, reduce="amax"
        )
        last = step + 1 == length[episode]  # where s' is the episode's last state, no later s holds it
        embedding = net.embed(exe.states, exe.instructions, step)
        last_state = net.embed(exe.next_states[last], exe.instructions[last], step[last] + 1)
        sequence = embedding.new_zeros(n_episodes, horizon + 1, embedding.shape[1])
        sequence = sequence.index_put((episode, step), embedding)
        sequence = sequence.index_put((episode[last], step[last] + 1), last_state)
        out, _ = net.recur(sequence)
        return out[episode, step], out[episode, step + 1]

    def bottleneck_loss(self, f: th.Tensor) -> th.Tensor:
        """Equation 3 with the threshold K: mean of max(||f(T)||^2, K), so only norms above K get a
        gradient (0 without the bottleneck)."""
        if not self.bottleneck:
            return f.new_zeros(())
        return th.clamp(f.pow(2).sum(dim=-1), min=self.bottleneck_threshold).mean()

    def exploration_rewards(self, g: th.Tensor, f: th.Tensor, lengths: th.Tensor) -> th.Tensor:
        """Equation 5: r_t = ||f - g(tau_:t)||^2 - ||f - g(tau_:t+1)||^2 - c, for t < T (else 0).

        ``g`` [B, T+1, z] holds every prefix (prefix t has t transitions), ``f`` [B, z].
        Returns [B, T].
        """
        d = (f[:, None] - g).pow(2).sum(dim=-1)  # [B, T+1]
        r = d[:, :-1] - d[:, 1:] - self.reward_penalty
        valid = th.arange(r.shape[1], device=r.device)[None] < lengths[:, None]
        return r * valid

    def _exploration_update(self, traj: TrajectoryBatch, g: th.Tensor, f: th.Tensor) -> Dict[str, float]:
        """Exploration DDQN over whole trajectories (fused LSTM unroll) on relabelled rewards."""
        policy = self.policy
        states, actions, prev_actions = traj.states, traj.actions, traj.prev_actions
        prev_rewards, lengths = traj.prev_rewards, traj.lengths
        t_max = actions.shape[1]
        rewards = self.exploration_rewards(g, f, lengths)  # [B, T]
        clock = None  # the step of each state within its exploration episode, with exploration_time_input
        if policy.exploration_time_input:
            clock = th.arange(t_max + 1, device=self.device).expand(len(actions), -1)
        q_all, _ = policy.exploration_q(states, prev_actions, prev_rewards, None, clock)  # [B, T+1, A]
        q = q_all[:, :t_max].gather(2, actions[..., None]).squeeze(2)
        with th.no_grad():
            q_target_all, _ = policy.exploration_q_target(states, prev_actions, prev_rewards, None, clock)
            best = q_all[:, 1:].argmax(dim=2, keepdim=True)
            next_q = q_target_all[:, 1:].gather(2, best).squeeze(2)  # [B, T]
            steps = th.arange(t_max, device=self.device)[None]
            last = steps == (lengths[:, None] - 1)  # the exploration episode ends after its last step
            target = rewards + self.gamma * (~last).float() * next_q
            valid = (steps < lengths[:, None]).float()
        loss = ((q - target).pow(2) * valid).sum() / valid.sum()
        policy.exploration_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        th.nn.utils.clip_grad_norm_(policy.exploration_q.parameters(), self.max_grad_norm)
        policy.exploration_optimizer.step()
        return {
            "exploration_loss": loss.item(),
            "exploration_q_mean": ((q * valid).sum() / valid.sum()).item(),
            "exploration_reward": ((rewards * valid).sum() / valid.sum()).item(),
        }

    # ------------------------------------------------------------------ logging
    def dump_logs(self) -> None:
        """SB3's rollout/time keys plus DREAM's: both epsilons, exploration length, and the
        execution return of the trials whose z came from the encoder f and from the decoder g."""
        self.logger.record("rollout/exploration_epsilon", self.exploration_epsilon)
        self.logger.record("rollout/execution_epsilon", self.execution_epsilon)
        if self._exploration_lengths:
            self.logger.record("rollout/exploration_length", safe_mean(list(self._exploration_lengths)))
        for source, returns in self._returns_by_source.items():
            if returns:
                self.logger.record(f"rollout/execution_return_z_{source}", safe_mean(list(returns)))
        super().dump_logs()


class DreamBatchTrialAgent(BatchTrialAgent):
    """DREAM at meta-test in ``n_envs`` trial envs side by side, given ``info["final_obs"]`` at
    each exploration's end (what :func:`sb3_dream.evaluation.evaluate_meta` plays)."""

    def __init__(self, model: DREAM, deterministic: bool = True) -> None:
        self.model, self.deterministic = model, deterministic
        self.reset(1)

    def reset(self, n_envs: int) -> None:
        self.state = self.model.new_trial_state(n_envs)

    def start_trials(self, idx: np.ndarray) -> None:
        self.state.reset(idx)

    def act(self, obs: Dict[str, np.ndarray], infos: Sequence[Dict[str, Any]]) -> np.ndarray:
        return self.model._meta_test_act(self.state, obs, infos, self.deterministic)[0]


class DreamTrialAgent(SingleTrialAgent):
    """:class:`DreamBatchTrialAgent` one trial at a time (a :class:`~dream_envs.ScriptedAgent`)."""

    def __init__(self, model: DREAM, deterministic: bool = True) -> None:
        super().__init__(DreamBatchTrialAgent(model, deterministic))
