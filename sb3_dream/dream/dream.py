"""DREAM: Decoupled Reward-free ExplorAtion and execution in Meta-reinforcement learning.

Liu, Raghunathan, Liang, Finn: "Explore then Execute: Adapting without Rewards via Factorized
Meta-Reinforcement Learning" (ICML 2021), Section 4 and Algorithm 1 (Appendix A).

Per training trial (one Gymnasium episode of a :class:`dream_envs.TrialEnv`):

1. the exploration policy Q^exp(s_t, tau_:t) rolls out the reward-free exploration episode; its
   trajectory tau^exp goes to the exploration buffer (Algorithm 1, lines 7-9);
2. the trial's z is drawn alternately from the problem encoder, z ~ N(f(T), rho^2 I), or from the
   decoder, z = g(tau^exp) (line 11); the execution policy Q^exe(s, i, z) rolls out the execution
   episodes; their transitions go to the execution buffer with a reference to tau^exp (lines 12-13).

Every ``train_freq`` env steps (summed over envs), ``gradient_steps`` updates of each part (lines 14-23):

* exploration DDQN on the information-gain reward, recomputed with the current f and g
  (Equation 5): r_t = ||f(T) - g(tau_:t)||^2 - ||f(T) - g(tau_:t+1)||^2 - c;
* execution DDQN twice, with z = g(tau^exp) (trains theta, omega) and with z ~ N(f(T), rho^2 I)
  (trains theta, psi);
* the information bottleneck on f (Equation 3): lambda * max(||f(T)||^2, K), so only norms above K
  are pushed down;
* the decoder regression of every prefix g(tau_:t) toward stop-gradient f(T) (Equation 4).

At meta-test the execution policy always uses z = g(tau^exp): the problem ID is never needed.

This module orchestrates; each concept has its own: :mod:`~sb3_dream.dream.acting` (the trial
state, acting, ``predict`` and the meta-test agents), :mod:`~sb3_dream.dream.policies` (the four
networks), :mod:`~sb3_dream.dream.buffers` (B_exp and B_exe), :mod:`~sb3_dream.dream.losses`
(Equations 2-5) and :mod:`~sb3_dream.dream.updates` (one optimizer step of each part).
"""

from __future__ import annotations

import io
import os
import pathlib
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Any, ClassVar, Dict, List, Optional, Tuple, Type, TypeVar, Union

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.save_util import load_from_pkl
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import safe_mean

from dream_envs import EXECUTION, EXPLORATION
from dream_envs.checks import check_choice, check_non_negative, check_positive_int
from sb3_dream.common.off_policy import TrialOffPolicyAlgorithm, check_tau
from sb3_dream.common.recurrent import LinearEpsilonSchedule
from sb3_dream.dream import losses, updates
from sb3_dream.dream.acting import REQUIRED_KEYS, DreamActing, TrialState, act, model_states
from sb3_dream.dream.buffers import (
    DreamReplayBuffer,
    ExecutionBatch,
    ExecutionBuffer,
    ExplorationBuffer,
    TrajectoryBatch,
)
from sb3_dream.dream.policies import DreamPolicy

SelfDREAM = TypeVar("SelfDREAM", bound="DREAM")

# What the execution Q's target conditions on (DREAM(execution_target_z=...)).
EXECUTION_TARGET_Z = ("own", "encoder")
EXECUTION_SAMPLING = ("transitions", "episodes")
EXECUTION_Z = ("both", "alternate")
PARALLEL_UPDATES = (True, False, "auto")


def available_cores() -> int:
    """CPU cores this process may run on (its affinity where the OS tells it)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


class DREAM(DreamActing, TrialOffPolicyAlgorithm):
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
    :param learning_starts: env steps (summed over envs) before any update (SB3's meaning; 0 by
        default: the paper's starts count trials, ``exploration_learning_starts`` and
        ``execution_learning_starts``).
    :param train_freq: env steps (summed over envs) per round of updates (the paper's 4): an int or
        SB3's ``(n, "step")``.
    :param gradient_steps: updates of each part per round (the paper's 1).
    :param target_update_interval: updates between target-network syncs (the paper's 5000).
    :param tau: SB3's target update coefficient at each sync: 1 (default) copies the online networks
        into their targets (the paper's hard updates); tau < 1 moves each target parameter that
        fraction of the way to its online one (Polyak averaging), usually with
        ``target_update_interval=1``. All four targets (encoder, decoder, both Q-networks) alike.
    :param exploration_learning_starts: trials collected before the exploration policy learns.
    :param execution_learning_starts: trials collected before the execution side learns.
    :param exploration_initial_eps: epsilon of both policies at the start.
    :param exploration_final_eps: epsilon of both policies after the decay (of the exploration
        policy alone when ``execution_final_eps`` is set).
    :param eps_decay_steps: steps of *each* policy over which its epsilon decays (250K each).
    :param execution_final_eps: the execution policy's own final epsilon; None (default) is
        ``exploration_final_eps``, the paper's shared schedule. A deviation for envs whose execution
        learns from rare rewards long after its epsilon has decayed (SignNav3D's pickups, see
        docs/results/signnav3d.md), leaving the exploration policy's trajectories as they were.
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
    :param parallel_updates: run each step's exploration update (with the no-gradient passes it
        needs) in a second thread beside the execution update: the same results (tested), faster
        with a free second core, slower without (docs/speed.md). ``"auto"`` (default): on when the
        networks are on the CPU and this process may run on more than one core.
    :param execution_target_z: the z the execution Q's double-DQN target conditions on: ``"own"``
        (default), each loss's own source through the target networks (target decoder for z = g,
        target encoder for z from F); ``"encoder"``, the target encoder's f(T) for both, as in the
        authors' code, which saves the target decoder's pass.
    :param execution_z: the z the execution Q learns with in one update: ``"both"`` (default,
        Algorithm 1's lines 18-19), one DDQN loss with z = g(tau^exp) and one with z ~ F(z | T) on
        the same samples; ``"alternate"`` (the authors' code, where the execution Q learns with
        the z its current trial acts with), one of them per update, the decoder's and the
        encoder's in turn. The bottleneck and the decoder loss are in every update either way.
        Halves the execution Q's rows per update; each source then has half the updates.
    :param execution_sampling: what one execution update learns from: ``"transitions"`` (default,
        Algorithm 1), ``batch_size`` transitions drawn uniformly from B_exe; ``"episodes"`` (the
        authors' code), every transition of ``batch_size`` execution episodes. The decoder, the
        bottleneck and the decoder loss read ``batch_size`` trials either way.
    :param execution_n_step: n of the execution Q's TD targets (Equation 2's RL term): 1 (default)
        is the paper's one-step double-DQN target r + gamma Q'(s'); n > 1 sums the next n rewards of
        the execution episode and bootstraps once, gamma^n Q'(s_{t+n}), cut short at the episode's
        end (no bootstrap after a terminal step; with ``bootstrap_at_horizon`` the horizon's last
        s' bootstraps). A reward reaches the values n steps back per update instead of one, for
        faster learning from few samples, at the price of bias from the off-policy (epsilon-greedy,
        older) actions inside the window (:func:`sb3_dream.common.recurrent.n_step_targets`). With
        ``execution_sampling="episodes"`` the batch holds the following transitions already; with
        ``"transitions"`` each sampled transition comes with the n - 1 after it in its episode
        (B_exe links them) and s' is the window's last state, so the update's cost is unchanged.
    :param exploration_n_step: the same for the exploration Q's targets over its trajectories,
        whose rewards are Equation 5's information gains: 1 (default) is the paper's; n > 1 sums the
        next n gains (the exploration episode's end is terminal).
    :param execution_update_ratio: execution updates (Equations 2-4 on a fresh execution batch each)
        per exploration update: 1 (default) is Algorithm 1's one of each. With k > 1 every one of the
        ``gradient_steps`` updates of a round runs the exploration update and the first execution
        update as before (side by side with ``parallel_updates``), then k - 1 more execution
        updates; the targets are synced once per such update, so ``target_update_interval`` keeps
        counting exploration updates. For envs where execution, not exploration, is what the
        learning curve waits for.
    :param policy_kwargs: :class:`DreamPolicy` options, each a documented deviation from the paper's
        networks: ``execution_hidden_sizes``, ``execution_time_input``, ``exploration_time_input``,
        ``execution_instruction_mlp``, ``execution_recurrent`` (needs
        ``execution_sampling="episodes"``), ``execution_weight_decay`` and ``image_downsample``.
    """

    policy_aliases: ClassVar[Dict[str, Type[DreamPolicy]]] = {"DreamPolicy": DreamPolicy}
    sb3_equivalents: ClassVar[Dict[str, str]] = {
        "exploration_fraction": "its epsilons decay over env steps: eps_decay_steps (execution_eps_decay_steps "
        "for the execution policy's own)",
        "replay_buffer_class": "it keeps two buffers of its own, sized by buffer_size (exploration trajectories) "
        "and execution_buffer_size (execution transitions)",
        "replay_buffer_kwargs": "its buffers are sized by buffer_size and execution_buffer_size",
        "optimize_memory_usage": "its buffers store each state once per step already",
        "action_noise": "its actions are discrete: exploration is epsilon-greedy (exploration_initial_eps, "
        "exploration_final_eps, eps_decay_steps)",
    }
    policy: DreamPolicy
    replay_buffer: DreamReplayBuffer  # type: ignore[assignment]
    # What models saved before these options load with.
    execution_update_ratio: int = 1
    execution_z: str = "both"
    _n_execution_updates: int = 0

    def __init__(
        self,
        policy: Union[str, Type[DreamPolicy], GymEnv] = "DreamPolicy",
        env: Union[GymEnv, str, None] = None,
        learning_rate: Union[float, Schedule] = 1e-4,
        buffer_size: int = 16_000,
        execution_buffer_size: int = 100_000,
        batch_size: int = 32,
        gamma: float = 0.99,
        learning_starts: int = 0,
        train_freq: Union[int, Tuple[int, str]] = 4,
        gradient_steps: int = 1,
        target_update_interval: int = 5000,
        tau: float = 1.0,
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
        execution_n_step: int = 1,
        exploration_n_step: int = 1,
        execution_update_ratio: int = 1,
        execution_z: str = "both",
        stats_window_size: int = 100,
        tensorboard_log: Optional[str] = None,
        policy_kwargs: Optional[Dict[str, Any]] = None,
        verbose: int = 0,
        seed: Optional[int] = None,
        device: Union[th.device, str] = "auto",
        _init_setup_model: bool = True,
        **sb3_kwargs: Any,
    ) -> None:
        self.reject_sb3_arguments(sb3_kwargs)
        if env is None and not (isinstance(policy, type) or policy in self.policy_aliases):
            policy, env = "DreamPolicy", policy  # DREAM("MetaBus-v0"): the env is the only argument
        if env is None and _init_setup_model:
            raise ValueError("env is required: a trial env, its ID (e.g. 'MetaBus-v0') or a VecEnv of trial envs")
        for name, value, minimum in [
            ("buffer_size", buffer_size, 1),
            ("execution_buffer_size", execution_buffer_size, 1),
            ("batch_size", batch_size, 1),
            ("target_update_interval", target_update_interval, 1),
            ("exploration_learning_starts", exploration_learning_starts, 0),
            ("execution_learning_starts", execution_learning_starts, 0),
            ("eps_decay_steps", eps_decay_steps, 0),
            ("z_dim", z_dim, 1),
            ("execution_n_step", execution_n_step, 1),
            ("exploration_n_step", exploration_n_step, 1),
            ("execution_update_ratio", execution_update_ratio, 1),
        ]:
            check_positive_int(name, value, minimum)
        for name, value in [
            ("encoder_variance", encoder_variance),
            ("bottleneck_threshold", bottleneck_threshold),
            ("bottleneck_weight", bottleneck_weight),
            ("max_grad_norm", max_grad_norm),
            ("reward_penalty", reward_penalty),
        ]:
            check_non_negative(name, value)
        check_choice("execution_target_z", execution_target_z, EXECUTION_TARGET_Z)
        check_choice("parallel_updates", parallel_updates, PARALLEL_UPDATES)
        check_choice("execution_sampling", execution_sampling, EXECUTION_SAMPLING)
        check_choice("execution_z", execution_z, EXECUTION_Z)
        if policy_kwargs and "z_dim" in policy_kwargs and policy_kwargs["z_dim"] != z_dim:
            raise ValueError(
                f"z_dim is DREAM's argument: pass z_dim={policy_kwargs['z_dim']!r} to DREAM, not in policy_kwargs "
                f"(got policy_kwargs z_dim={policy_kwargs['z_dim']!r} and z_dim={z_dim!r})"
            )

        super().__init__(
            policy,
            env,
            learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            tau=tau,  # SB3 sets it through the tau property, which checks it
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
        self.execution_n_step = int(execution_n_step)
        self.exploration_n_step = int(exploration_n_step)
        self.execution_update_ratio = int(execution_update_ratio)
        self.execution_z = execution_z
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
        self._z_from_encoder: Optional[np.ndarray] = None  # per env: this trial's z source
        self._n_execution_updates = 0
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
        if "_train_freq_steps" in self.__dict__:  # a model saved before train_freq moved to the shared base
            self.train_every = self.__dict__.pop("_train_freq_steps")
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
        self.replay_buffer.trial_spec = self.trial_spec
        self._trial_state: Optional[TrialState] = None

    def _excluded_save_params(self) -> List[str]:
        return [*super()._excluded_save_params(), "_trial_state", "_update_thread", "_warned_stateless_predict"]

    @property
    def tau(self) -> float:
        """SB3's target update coefficient (see the constructor). Saved as ``_target_tau``: saves made
        before DREAM took ``tau`` hold SB3's unused default (0.005) under ``tau`` and load with 1,
        the hard updates they were trained with."""
        return self._target_tau

    @tau.setter
    def tau(self, value: float) -> None:
        self._target_tau = check_tau(value)

    @classmethod
    def load(  # type: ignore[override]
        cls, path: Any, env: Optional[GymEnv] = None, *args: Any, **kwargs: Any
    ) -> "DREAM":
        """SB3's ``load``; a ``tau`` among ``kwargs`` goes through :attr:`tau` (SB3 sets them raw)."""
        model = super().load(path, env, *args, **kwargs)
        model.__dict__.pop("tau", None)  # an older save's SB3 default, or a raw kwarg: the property holds tau
        if "tau" in kwargs:
            model.tau = kwargs["tau"]
        return model

    def _get_torch_save_params(self) -> Tuple[List[str], List[str]]:
        return ["policy", "policy.optimizer", "policy.exploration_optimizer"], []

    def load_replay_buffer(
        self, path: Union[str, pathlib.Path, io.BufferedIOBase], truncate_last_traj: bool = True
    ) -> None:
        buffer = load_from_pkl(path, self.verbose)
        if not isinstance(buffer, DreamReplayBuffer):
            raise TypeError(f"{path} does not hold a DREAM replay buffer (got {type(buffer).__name__})")
        self.check_replay_buffer(buffer, path)
        if buffer.exploration.max_length != self.exploration_horizon:  # a buffer saved before trial specs
            raise ValueError(
                f"the replay buffer in {path} does not match the model: its exploration horizon is "
                f"{buffer.exploration.max_length}, the model's is {self.exploration_horizon}"
            )
        buffer.device = self.device
        self.replay_buffer = buffer

    # ------------------------------------------------------------------ collecting (SB3's hooks)
    def _store_explorations(self, state: TrialState, idx: np.ndarray, problem_ids: np.ndarray) -> None:
        """Store the just-ended exploration trajectories of envs ``idx`` in B_exp (Algorithm 1, line 9)."""
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

    def _sample_action(
        self, learning_starts: int, action_noise: Optional[ActionNoise] = None, n_envs: int = 1
    ) -> Tuple[np.ndarray, np.ndarray]:
        """Both policies' epsilon-greedy actions for all envs, one forward each (Algorithm 1, lines 7 and 12)."""
        assert self._trial_state is not None
        actions = act(
            self.policy, self._last_obs, self._trial_state, self.exploration_epsilon, self.execution_epsilon, self._rng
        )
        return actions, actions

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: Dict[str, np.ndarray],  # type: ignore[override]
        reward: np.ndarray,
        dones: np.ndarray,
        infos: List[Dict[str, Any]],
    ) -> None:
        """Store tau^exp where an exploration episode ended (and set the trial's z), each execution
        transition with a link to its trial's tau^exp (Algorithm 1, lines 9 and 13); start new trials."""
        state, obs = self._trial_state, self._last_obs
        assert state is not None and self._z_from_encoder is not None and isinstance(obs, dict)
        phase = np.asarray(obs["phase"]).reshape(len(dones))
        self._n_exploration_steps += int((phase == EXPLORATION).sum())
        self._n_execution_steps += int((phase == EXECUTION).sum())
        ended = np.array([bool(info.get("episode_end")) for info in infos])
        explored = np.flatnonzero((phase == EXPLORATION) & ended)
        if len(explored):
            final = np.stack([infos[e]["final_obs"] for e in explored])
            problem_ids = np.array([infos[e]["problem_id"] for e in explored])
            self.end_exploration(state, explored, final, problem_ids)
        executed = np.flatnonzero(phase == EXECUTION)
        if len(executed):
            next_states = np.array(new_obs["obs"][executed], copy=True)
            for k, e in enumerate(executed):
                if ended[e]:
                    next_states[k] = model_states(infos[e]["final_obs"], self.observation_space["obs"])
                    source = "f" if self._z_from_encoder[e] else "g"
                    self._returns_by_source[source].append(infos[e]["episode_return"])
            truncated = np.array([bool(infos[e].get("episode_truncated", False)) for e in executed])
            terminal = ended[executed] & ~(truncated & self.bootstrap_at_horizon)
            self.replay_buffer.execution.add(
                {
                    "states": obs["obs"][executed],
                    "instructions": obs["instruction"][executed],
                    "actions": buffer_action[executed],
                    "rewards": reward[executed],
                    "next_states": next_states,
                    "dones": terminal.astype(np.float32),
                    "slots": self._slots[executed],
                    "generations": self._generations[executed],
                    "steps": state.execution_step[executed],
                },
                envs=executed,
            )
        self._last_obs = new_obs
        for e in np.flatnonzero(dones):
            state.reset(np.array([e]))
            self._z_from_encoder[e] = not self._z_from_encoder[e]  # alternate z sources across trials

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
            for update_stats in self._update(batch_size, exploration_ready, execution_ready):
                for key, value in update_stats.items():
                    stats.setdefault(key, []).append(value)
            self._n_updates += 1
            if self._n_updates % self.target_update_interval == 0:
                self.policy.sync_targets(self.tau)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in stats.items():
            self.logger.record(f"train/{key}", float(np.mean(values)))

    def _update(self, batch_size: int, exploration_ready: bool, execution_ready: bool) -> List[Dict[str, float]]:
        """One gradient step of each part that is ready, in Algorithm 1's order: exploration
        (lines 14-16), then execution, bottleneck and decoder on the execution samples (17-21);
        then ``execution_update_ratio - 1`` more execution steps, each on its own batch. The
        statistics of each step, for :meth:`train` to average."""
        buffers, stats = self.replay_buffer, {}
        if exploration_ready:
            explored = buffers.sample_trajectories(batch_size, self._rng)
        if execution_ready:
            exe, traj = self._sample_execution(batch_size)
        if self.updates_in_parallel and exploration_ready and execution_ready:
            stats = updates.parallel_update(self, explored, exe, traj, self._execution_z_sources())
        else:
            if exploration_ready:
                stats.update(updates.exploration_update(self, explored, *updates.reward_codes(self.policy, explored)))
            if execution_ready:
                stats.update(updates.execution_update(self, exe, traj, sources=self._execution_z_sources()))
        more = self.execution_update_ratio - 1 if execution_ready else 0  # the ratio's further updates, alone
        return [stats] + [
            updates.execution_update(self, *self._sample_execution(batch_size), sources=self._execution_z_sources())
            for _ in range(more)
        ]

    def _execution_z_sources(self) -> Tuple[str, ...]:
        """The z sources of the next execution update (``execution_z``), counting the updates."""
        turn, self._n_execution_updates = self._n_execution_updates, self._n_execution_updates + 1
        if self.execution_z == "both":
            return updates.Z_SOURCES
        return (updates.Z_SOURCES[turn % 2],)

    def _sample_execution(self, batch_size: int) -> Tuple[ExecutionBatch, TrajectoryBatch]:
        """An execution batch and the trajectories its trials explored (``execution_sampling``)."""
        return self.replay_buffer.sample_execution(
            batch_size, self._rng, episodes=self.execution_sampling == "episodes", n_step=self.execution_n_step
        )

    @property
    def updates_in_parallel(self) -> bool:
        """Whether the exploration update runs in a second thread (``parallel_updates``, "auto" resolved)."""
        if isinstance(self.parallel_updates, str):  # "auto"
            return self.device.type == "cpu" and available_cores() > 1
        return bool(self.parallel_updates)

    def exploration_rewards(self, g: th.Tensor, f: th.Tensor, lengths: th.Tensor) -> th.Tensor:
        """Equation 5 with this model's c (:func:`sb3_dream.dream.losses.exploration_rewards`)."""
        return losses.exploration_rewards(g, f, lengths, self.reward_penalty)

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
