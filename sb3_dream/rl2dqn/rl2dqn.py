"""RL2DQN: RL² (Duan et al., 2016) trained as a recurrent dueling double DQN, as in the DREAM paper."""

from __future__ import annotations

from typing import Any, ClassVar, Dict, List, Optional, Sequence, Tuple, Type, TypeVar, Union

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import obs_as_tensor, polyak_update
from stable_baselines3.common.vec_env import VecEnv

import dream_envs  # noqa: F401  (registers the trial envs so their IDs resolve in gym.make)
from dream_envs import BatchTrialAgent, ScriptedAgent, SingleTrialAgent
from dream_envs.checks import check_choice, check_non_negative, check_positive_int
from sb3_dream.common.buffers import SequenceReplayBuffer, SequenceReplayBufferSamples
from sb3_dream.common.off_policy import TrialOffPolicyAlgorithm, check_tau
from sb3_dream.common.recurrent import TD_LOSSES, LinearEpsilonSchedule, double_dqn_targets, masked_td_loss
from sb3_dream.common.wrappers import FinalObsWrapper, final_obs_entry
from sb3_dream.common.agents import PolicyBatchAgent
from sb3_dream.rl2dqn.policies import CnnLstmPolicy, MultiInputLstmPolicy, RL2DQNPolicy, RL2QNetwork

SelfRL2DQN = TypeVar("SelfRL2DQN", bound="RL2DQN")


def recurrent_double_dqn_loss(
    q_net: RL2QNetwork,
    q_net_target: RL2QNetwork,
    batch: SequenceReplayBufferSamples,
    gamma: float,
    td_loss: str = "mse",
    burn_in: int = 0,
) -> Tuple[th.Tensor, th.Tensor]:
    """Masked double-DQN loss over a padded batch of sequences; returns ``(loss, mean Q(s, a))``.

    One fused unroll of each network over the ``T + 1`` observations gives Q(s_t) (``[:, :T]``) and
    Q(s_{t+1}) (``[:, 1:]``); the online network picks argmax_a Q(s_{t+1}, a), the target network
    evaluates it. Both unrolls start from the stored state if the buffer has one, else from zeros.
    """
    states = initial_batch_states(q_net, batch)
    q_all, _ = q_net(batch.observations, states, burn_in, batch.burn_in_mask)  # [B, T + 1, A]
    with th.no_grad():
        q_next_target, _ = q_net_target(batch.observations, states)
    return double_dqn_loss_from_q_values(q_all, q_next_target, batch, gamma, td_loss)


def initial_batch_states(q_net: RL2QNetwork, batch: SequenceReplayBufferSamples) -> Tuple[th.Tensor, th.Tensor]:
    """Where the unrolls over ``batch`` start: the stored LSTM states if the buffer has them, else zeros."""
    if batch.lstm_states is not None:
        return batch.lstm_states
    return q_net.initial_states(batch.actions.shape[0], batch.actions.device)


def double_dqn_loss_from_q_values(
    q_all: th.Tensor,
    q_target_all: th.Tensor,
    batch: SequenceReplayBufferSamples,
    gamma: float,
    td_loss: str = "mse",
) -> Tuple[th.Tensor, th.Tensor]:
    """The masked double-DQN loss and mean Q(s, a) from the online (``q_all``) and target
    (``q_target_all``, no gradient) Q-values of the ``T + 1`` observations, ``[B, T + 1, A]`` each."""
    with th.no_grad():
        targets = double_dqn_targets(q_all[:, 1:].detach(), q_target_all[:, 1:], batch.rewards, batch.dones, gamma)
    q_taken = q_all[:, :-1].gather(-1, batch.actions.unsqueeze(-1)).squeeze(-1)
    loss = masked_td_loss(q_taken, targets, batch.mask, td_loss)
    q_mean = (q_taken.detach() * batch.mask).sum() / batch.mask.sum().clamp(min=1.0)
    return loss, q_mean


class RL2DQN(TrialOffPolicyAlgorithm):
    """RL² as a recurrent dueling double DQN with trial-structured sequence replay.

    The paper's RL² baseline (Appendix B.3, B.4): per-step embeddings of the state, the previous
    action (16), the previous reward (16, linear), the episode-start flag (16) and the instruction
    (64) -> linear 64 + ReLU -> LSTM 64 -> dueling head (V + A - mean A), trained with double-DQN
    targets on sequences of up to ``sequence_length`` steps from a replay of whole trials.

    **Environment.** One gym episode is one trial (see :mod:`dream_envs.trial_env`): the observation is a
    Dict with at least ``obs``; ``instruction``, ``episode_start``, ``prev_action``, ``prev_reward``
    are embedded when present (``phase`` is ignored: the episode-start flags imply it). The
    LSTM state is carried across the inner episodes of a trial and reset only when a trial (gym
    episode) starts, never at an inner episode's start. The action space must be Discrete.
    Plain envs can be wrapped with :class:`sb3_dream.common.wrappers.RL2ObservationWrapper`.

    **The exploration episode's last state.** A trial env returns the next episode's first
    observation at an inner episode's end; the last state lives only in ``info["final_obs"]``. By
    default RL2DQN never sees it: its input is the per-step observation, as the paper describes RL²
    (so in MetaBandit-v0 with horizon 1, whose reveal is visible only there, it stays at chance).
    ``consume_final_obs=True`` wraps a trial env in
    :class:`~sb3_dream.common.wrappers.FinalObsWrapper`, which adds it as a ``final_obs`` key,
    embedded by the state embedder on the next episode's first step. Pass a VecEnv already wrapped
    (``make_vec_env(..., wrapper_class=FinalObsWrapper)``) when vectorising yourself, and to
    ``load``. :meth:`as_trial_agent` plays such a model on bare trial envs (``evaluate_meta``).

    **Defaults** are the paper's (Table 1 and Appendix B.4): Adam lr 1e-4, batch 32 sequences,
    gamma 0.99, target sync every 5000 *updates*, one update per 4 env steps, gradient-norm
    clipping 10, epsilon 1 -> 0.01 over 500k env steps, 16000 sequences of up to 50 steps,
    no burn-in and zero initial states. ``learning_starts=16_000`` env steps stands for "after 800
    episodes" (the authors' RL²): 800 inner episodes of the grid envs' horizon of 20 steps.
    The TD error is squared (what the authors ran; the paper does not say); ``td_loss="huber"``
    gives SB3 DQN's.

    **Speed.** Acting is one batched forward per vectorised step (per-env LSTM states stay on the
    device); an update unrolls the online and target networks once each over the padded
    ``[B, T + 1]`` batch. On a CPU most of an update goes to the embedding MLPs and the backward
    pass; these networks are small, so ``torch.set_num_threads(1)`` is usually fastest, and much
    faster on a loaded machine.

    :param policy: ``"MultiInputLstmPolicy"`` (default), ``"CnnLstmPolicy"`` (image ``obs``), or a
        policy class. ``RL2DQN(env)`` with the env (or its ID) as the only argument uses the default.
    :param env: the env, its registered ID (``import dream_envs`` registers the trial envs), or a
        VecEnv (``n_envs > 1`` acts with one batched forward per step).
    :param learning_rate: Adam's learning rate (or a schedule of the remaining progress).
    :param buffer_size: the number of *sequences* the replay keeps.
    :param learning_starts: env steps of uniformly random acting before the first update.
    :param batch_size: sequences per update.
    :param tau: target update coefficient at each sync (1 = hard copy).
    :param gamma: discount factor.
    :param train_freq: env steps (summed over the envs) per ``gradient_steps`` updates.
    :param gradient_steps: updates per ``train_freq`` env steps.
    :param target_update_interval: updates between target-network syncs.
    :param exploration_initial_eps: epsilon at step 0.
    :param exploration_final_eps: epsilon after ``exploration_steps``.
    :param exploration_steps: env steps of the linear epsilon decay.
    :param max_grad_norm: gradient-norm clipping.
    :param sequence_length: the most steps per replayed sequence; longer trials are cut in chunks.
    :param burn_in: R2D2 burn-in: chunks of a long trial overlap by this many steps, which only warm
        up the LSTM state (no loss, no gradient). 0 (paper) disables it.
    :param stored_state: R2D2 stored state: start each chunk's unroll from the LSTM state the actor
        had there, instead of zeros (paper: zeros; exact for chunks that start a trial).
    :param td_loss: ``"mse"`` or ``"huber"``.
    :param consume_final_obs: feed the exploration episode's last state (see above).
    :param zero_exploration_rewards: zero the rewards of the exploration episode (``phase`` 0) for
        learning, as the authors' RL² did; a no-op in the default reward-free trial envs.
    :param replay_buffer_class: a :class:`~sb3_dream.common.buffers.SequenceReplayBuffer` subclass.
    :param replay_buffer_kwargs: extra keyword arguments of the replay buffer.
    :param stats_window_size: window of the rollout statistics (trials).
    :param tensorboard_log: TensorBoard log folder.
    :param policy_kwargs: arguments of the policy (e.g. ``lstm_hidden_size``, ``embed_kwargs``).
    :param verbose: 0, 1 or 2.
    :param seed: random seed.
    :param device: torch device ("auto" picks CUDA when available).
    """

    policy_aliases: ClassVar[Dict[str, Type[BasePolicy]]] = {
        "MultiInputLstmPolicy": MultiInputLstmPolicy,
        "CnnLstmPolicy": CnnLstmPolicy,
    }
    sb3_equivalents: ClassVar[Dict[str, str]] = {
        "exploration_fraction": "its epsilon decays over env steps: exploration_steps",
        "optimize_memory_usage": "its sequence replay stores each observation once already",
        "action_noise": "its actions are discrete: exploration is epsilon-greedy (exploration_initial_eps, "
        "exploration_final_eps, exploration_steps)",
    }
    policy: RL2DQNPolicy
    replay_buffer: SequenceReplayBuffer
    q_net: RL2QNetwork
    q_net_target: RL2QNetwork

    def __init__(
        self,
        policy: Union[str, Type[RL2DQNPolicy], GymEnv] = "MultiInputLstmPolicy",
        env: Union[GymEnv, str, None] = None,
        learning_rate: Union[float, Schedule] = 1e-4,
        buffer_size: int = 16_000,
        learning_starts: int = 16_000,
        batch_size: int = 32,
        tau: float = 1.0,
        gamma: float = 0.99,
        train_freq: Union[int, Tuple[int, str]] = 4,
        gradient_steps: int = 1,
        target_update_interval: int = 5000,
        exploration_initial_eps: float = 1.0,
        exploration_final_eps: float = 0.01,
        exploration_steps: int = 500_000,
        max_grad_norm: float = 10.0,
        sequence_length: int = 50,
        burn_in: int = 0,
        stored_state: bool = False,
        td_loss: str = "mse",
        consume_final_obs: bool = False,
        zero_exploration_rewards: bool = False,
        replay_buffer_class: Optional[Type[SequenceReplayBuffer]] = None,
        replay_buffer_kwargs: Optional[Dict[str, Any]] = None,
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
        # RL2DQN(env) / RL2DQN("MetaBus-v0"): the env as the only argument, default policy
        if env is None and (
            isinstance(policy, (gym.Env, VecEnv)) or (isinstance(policy, str) and policy not in self.policy_aliases)
        ):
            policy, env = "MultiInputLstmPolicy", policy
        if isinstance(policy, str) and policy not in self.policy_aliases:
            raise ValueError(
                f"policy={policy!r} is not valid; accepted values: "
                f"{', '.join(map(repr, self.policy_aliases))} or a policy class"
            )
        if env is None and _init_setup_model:
            raise ValueError("env is required: pass an env, a VecEnv or a registered env ID (e.g. 'MetaBus-v0')")
        self.sequence_length = check_positive_int("sequence_length", sequence_length, 1)
        self.burn_in = check_positive_int("burn_in", burn_in, 0)
        if self.burn_in >= self.sequence_length:
            raise ValueError(f"burn_in must be smaller than sequence_length={sequence_length}, got {burn_in}")
        check_choice("td_loss", td_loss, TD_LOSSES)
        check_non_negative("max_grad_norm", max_grad_norm)
        check_tau(tau)
        check_positive_int("buffer_size", buffer_size, 1)
        check_positive_int("batch_size", batch_size, 1)
        self.target_update_interval = check_positive_int("target_update_interval", target_update_interval, 1)
        if replay_buffer_class is not None and not issubclass(replay_buffer_class, SequenceReplayBuffer):
            raise ValueError("replay_buffer_class must be a subclass of sb3_dream.common.buffers.SequenceReplayBuffer")

        self.consume_final_obs = bool(consume_final_obs)
        if self.consume_final_obs and env is not None and not isinstance(env, VecEnv):
            if isinstance(env, str):
                env = gym.make(env)
            if "final_obs" not in getattr(env.observation_space, "spaces", {}):
                env = FinalObsWrapper(env)

        super().__init__(
            policy,
            env,  # type: ignore[arg-type]
            learning_rate,
            buffer_size=buffer_size,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            learning_starts=learning_starts,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            action_noise=None,
            replay_buffer_class=replay_buffer_class or SequenceReplayBuffer,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=False,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            seed=seed,
            sde_support=False,
            supported_action_spaces=None,  # checked below with a ValueError
            support_multi_env=True,
        )
        self.exploration_initial_eps = exploration_initial_eps
        self.exploration_final_eps = exploration_final_eps
        self.exploration_steps = check_positive_int("exploration_steps", exploration_steps, 0)
        self.exploration_schedule = LinearEpsilonSchedule(
            exploration_initial_eps, exploration_final_eps, exploration_steps
        )
        self.exploration_rate = exploration_initial_eps
        self.max_grad_norm = max_grad_norm
        self.stored_state = bool(stored_state)
        self.td_loss = td_loss
        self.zero_exploration_rewards = bool(zero_exploration_rewards)
        self._lstm_states: Optional[Tuple[th.Tensor, th.Tensor]] = None
        self._last_input_states: Optional[Tuple[np.ndarray, np.ndarray]] = None

        if self.env is not None:
            self._check_env_spaces(self.observation_space, self.action_space)
        if _init_setup_model:
            self._setup_model()

    # ------------------------------------------------------------------ setup
    def _check_env_spaces(self, observation_space: spaces.Space, action_space: spaces.Space) -> None:
        if not isinstance(action_space, spaces.Discrete):
            raise ValueError(f"{type(self).__name__} needs a Discrete action space, got {action_space}")
        policy_class = self.policy_class if isinstance(self.policy_class, type) else RL2DQNPolicy
        if issubclass(policy_class, RL2DQNPolicy):
            policy_class.check_spaces(observation_space, action_space)
        if self.consume_final_obs and "final_obs" not in observation_space.spaces:  # type: ignore[attr-defined]
            raise ValueError(
                "consume_final_obs=True needs a 'final_obs' observation key: wrap each env with "
                "sb3_dream.common.wrappers.FinalObsWrapper before vectorising it"
            )
        if self.zero_exploration_rewards and "phase" not in observation_space.spaces:  # type: ignore[attr-defined]
            raise ValueError("zero_exploration_rewards=True needs the 'phase' observation key of a trial env")

    def _setup_model(self) -> None:
        self.replay_buffer_kwargs = dict(self.replay_buffer_kwargs)
        self.replay_buffer_kwargs.update(sequence_length=self.sequence_length, burn_in=self.burn_in)
        if self.stored_state:
            layers = self.policy_kwargs.get("n_lstm_layers", 1)
            hidden = self.policy_kwargs.get("lstm_hidden_size", 64)
            self.replay_buffer_kwargs["lstm_state_shape"] = (layers, hidden)
        super()._setup_model()
        self.replay_buffer.trial_spec = self.trial_spec  # type: ignore[attr-defined]  # checked at load
        self.q_net = self.policy.q_net
        self.q_net_target = self.policy.q_net_target
        self._lstm_states = None

    def _excluded_save_params(self) -> List[str]:
        return [*super()._excluded_save_params(), "q_net", "q_net_target", "_lstm_states", "_last_input_states"]

    def _get_torch_save_params(self) -> Tuple[List[str], List[str]]:
        return ["policy", "policy.optimizer"], []

    # ------------------------------------------------------------------ acting
    def predict(  # type: ignore[override]
        self,
        observation: Dict[str, np.ndarray],
        state: Optional[Tuple[np.ndarray, ...]] = None,
        episode_start: Optional[np.ndarray] = None,
        deterministic: bool = False,
    ) -> Tuple[np.ndarray, Tuple[np.ndarray, np.ndarray]]:
        """Action(s) and the next LSTM state, sb3-contrib style (see :class:`RL2DQNPolicy`).

        With ``deterministic=False`` each env's action is replaced by a uniformly random one with
        probability ``exploration_rate`` (the state is still updated with the observation).
        """
        actions, state = self.policy.predict(observation, state, episode_start, deterministic)
        if not deterministic and self.exploration_rate > 0:
            flat = np.asarray(actions).reshape(-1)
            explore = np.random.rand(flat.size) < self.exploration_rate
            if explore.any():
                flat = np.where(explore, np.random.randint(int(self.action_space.n), size=flat.size), flat)
                actions = flat.reshape(np.shape(actions))
        return actions, state

    def as_trial_agent(self, deterministic: bool = True) -> ScriptedAgent:
        """A :class:`dream_envs.ScriptedAgent` playing this model on a bare trial env (no wrappers):
        it keeps the LSTM state over the trial and, with ``consume_final_obs``, builds the
        ``final_obs`` key from ``info`` (used by :func:`sb3_dream.evaluation.evaluate_meta`)."""
        return RL2TrialAgent(self, deterministic)

    def as_batch_trial_agent(self, deterministic: bool = True) -> BatchTrialAgent:
        """:meth:`as_trial_agent` for trials played side by side (see :mod:`sb3_dream.evaluation`)."""
        return RL2BatchTrialAgent(self, deterministic)

    def _sample_action(
        self, learning_starts: int, action_noise: Any = None, n_envs: int = 1
    ) -> Tuple[np.ndarray, np.ndarray]:
        """Epsilon-greedy actions for all envs from one batched forward (which also advances the
        per-env LSTM states, reset where a trial starts)."""
        assert self._last_obs is not None and self._last_episode_starts is not None
        if self._lstm_states is None or self._lstm_states[0].shape[1] != n_envs:
            self._lstm_states = self.q_net.initial_states(n_envs, self.device)
        obs = obs_as_tensor(self._last_obs, self.device)  # type: ignore[arg-type]
        starts = th.as_tensor(np.asarray(self._last_episode_starts, dtype=np.float32), device=self.device)
        self.policy.set_training_mode(False)
        with th.no_grad():
            q, input_states, self._lstm_states = self._act_step(obs, self._lstm_states, starts)
        if self.stored_state:
            self._last_input_states = (input_states[0].cpu().numpy(), input_states[1].cpu().numpy())
        eps = 1.0 if self.num_timesteps < learning_starts else self.exploration_rate
        greedy = q.argmax(dim=-1).cpu().numpy()
        explore = np.random.rand(n_envs) < eps
        actions = np.where(explore, np.random.randint(int(self.action_space.n), size=n_envs), greedy)
        return actions, actions

    def _act_step(
        self, obs: Dict[str, th.Tensor], states: Tuple[th.Tensor, th.Tensor], trial_start: th.Tensor
    ) -> Tuple[th.Tensor, Tuple[th.Tensor, th.Tensor], Tuple[th.Tensor, th.Tensor]]:
        """The Q-values the actor acts on during training (a hook: IMPORT conditions some trials
        on the problem ID); returns ``(q, input_states, next_states)`` as ``q_net.step``."""
        return self.q_net.step(obs, states, trial_start)

    def _replay_add_kwargs(self) -> Dict[str, Any]:
        """Extra per-step arguments of the replay buffer's ``add`` (a hook for subclasses)."""
        return {}

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: Union[np.ndarray, Dict[str, np.ndarray]],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: List[Dict[str, Any]],
    ) -> None:
        assert isinstance(new_obs, dict) and isinstance(self._last_obs, dict)
        if replay_buffer.n_envs != len(dones):  # a new env (set_env) or a loaded buffer
            replay_buffer.set_n_envs(len(dones))  # type: ignore[attr-defined]
        next_obs = new_obs
        ended = [i for i in np.flatnonzero(dones) if infos[i].get("terminal_observation") is not None]
        if ended:  # VecEnvs reset at once: the transition leads to the terminal observation
            next_obs = {k: np.array(v, copy=True) for k, v in new_obs.items()}
            for i in ended:
                for k in next_obs:
                    next_obs[k][i] = infos[i]["terminal_observation"][k]
        if self.zero_exploration_rewards:
            reward = reward * (np.asarray(self._last_obs["phase"]).reshape(-1) != 0)
        replay_buffer.add(  # type: ignore[call-arg]
            self._last_obs,  # type: ignore[arg-type]
            next_obs,  # type: ignore[arg-type]
            buffer_action,
            reward,
            dones,
            infos,
            episode_start=self._last_episode_starts,
            lstm_states=self._last_input_states,
            **self._replay_add_kwargs(),
        )
        self._last_obs = new_obs
        # the next observation starts a trial where one ended: reset those LSTM states only
        self._last_episode_starts = np.asarray(dones, dtype=bool).copy()

    def _on_step(self) -> None:
        self.exploration_rate = self.exploration_schedule(self.num_timesteps)
        self.logger.record("rollout/exploration_rate", self.exploration_rate)

    # ------------------------------------------------------------------ learning
    def learn(
        self: SelfRL2DQN,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "RL2DQN",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfRL2DQN:
        """Train for ``total_timesteps`` env steps (over all envs); ``log_interval`` counts trials."""
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def train(self, gradient_steps: int, batch_size: int = 32) -> None:
        if self.replay_buffer.size() == 0:
            return
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)  # logs train/learning_rate
        stats: Dict[str, List[th.Tensor]] = {}
        for _ in range(gradient_steps):
            batch = self.replay_buffer.sample(batch_size)
            loss, logged = self._loss(batch)
            self.policy.optimizer.zero_grad()
            loss.backward()
            th.nn.utils.clip_grad_norm_(self.policy.trained_parameters(), self.max_grad_norm)
            self.policy.optimizer.step()
            self._n_updates += 1
            if self._n_updates % self.target_update_interval == 0:
                polyak_update(self.q_net.parameters(), self.q_net_target.parameters(), self.tau)
            for key, value in logged.items():
                stats.setdefault(key, []).append(value)
        self.policy.set_training_mode(False)
        # one host sync per call, not per update
        means = th.stack([th.stack(values).mean() for values in stats.values()]).cpu().numpy()
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, value in zip(stats, means):
            self.logger.record(f"train/{key}", float(value))

    def _loss(self, batch: SequenceReplayBufferSamples) -> Tuple[th.Tensor, Dict[str, th.Tensor]]:
        """One update's loss on a sampled batch and the detached values to log as ``train/<key>``
        (a hook: IMPORT and VariBAD add their auxiliary losses)."""
        loss, q_mean = recurrent_double_dqn_loss(
            self.q_net, self.q_net_target, batch, self.gamma, self.td_loss, self.burn_in
        )
        return loss, {"loss": loss.detach(), "q_mean": q_mean}


class RL2BatchTrialAgent(PolicyBatchAgent):
    """Plays an :class:`RL2DQN` on bare trial envs through ``predict``, trials side by side.

    Each slot's LSTM state is reset at its trial's first step only. If the model consumes
    ``final_obs``, the key is built from the ``info`` that comes with each observation, as
    :class:`~sb3_dream.common.wrappers.FinalObsWrapper` would.
    """

    def observation(self, obs: Dict[str, np.ndarray], infos: Sequence[Dict[str, Any]]) -> Dict[str, np.ndarray]:
        space = self.model.observation_space
        if "final_obs" in space.spaces and "final_obs" not in obs:
            entries = [final_obs_entry(space["obs"], info) for info in infos]
            obs = {**obs, "final_obs": np.stack(entries)}
        return obs


class RL2TrialAgent(SingleTrialAgent):
    """:class:`RL2BatchTrialAgent` one trial at a time (a :class:`~dream_envs.ScriptedAgent`)."""

    def __init__(self, model: RL2DQN, deterministic: bool = True) -> None:
        super().__init__(RL2BatchTrialAgent(model, deterministic))
