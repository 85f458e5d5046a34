"""IMPORT (Kamienny et al., 2020) as the DREAM paper's recurrent dueling double DQN baseline."""

from __future__ import annotations

from typing import Any, ClassVar, Dict, List, NamedTuple, Optional, Tuple, Type, TypeVar, Union

import numpy as np
import torch as th
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper

from dream_envs.checks import check_non_negative
from sb3_dream.common.buffers import SequenceReplayBuffer, SequenceReplayBufferSamples
from sb3_dream.common.conditioned import conditioned_double_dqn_loss
from sb3_dream.common.recurrent import reset_lstm_states
from sb3_dream.import_dqn.policies import CnnLstmPolicy, IMPORTPolicy, IMPORTQNetwork, MultiInputLstmPolicy
from sb3_dream.rl2dqn.rl2dqn import RL2DQN

SelfIMPORT = TypeVar("SelfIMPORT", bound="IMPORT")


class ProblemSequenceSamples(NamedTuple):
    """:class:`~sb3_dream.common.buffers.SequenceReplayBufferSamples` plus each sequence's trial
    problem and the z its trial used."""

    observations: Dict[str, th.Tensor]
    actions: th.Tensor
    rewards: th.Tensor
    dones: th.Tensor
    mask: th.Tensor
    lengths: th.Tensor
    lstm_states: Optional[Tuple[th.Tensor, th.Tensor]]
    burn_in_mask: Optional[th.Tensor]
    problem_ids: th.Tensor  # [B] long: the problem ID of the sequence's trial
    use_problem: th.Tensor  # [B] bool: the trial acted on z = e(T) (else z = e(tau_:t))


class ProblemSequenceReplayBuffer(SequenceReplayBuffer):
    """Sequence replay that also keeps, per sequence, its trial's problem ID and z choice.

    ``add`` takes them per env (``problem_ids``, ``use_problem``, ``[n_envs]``), constant over a
    trial; every chunk of a trial stores its trial's. An update then recomputes the z the trial
    acted on and the auxiliary loss's target e(T).
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.problem_ids = np.zeros(self.buffer_size, dtype=np.int64)
        self.use_problem = np.zeros(self.buffer_size, dtype=bool)

    def _allocate_staging(self, n_envs: int) -> None:
        super()._allocate_staging(n_envs)
        self._stage_problem_ids = np.zeros(n_envs, dtype=np.int64)
        self._stage_use_problem = np.zeros(n_envs, dtype=bool)

    def add(  # type: ignore[override]
        self,
        obs: Dict[str, np.ndarray],
        next_obs: Dict[str, np.ndarray],
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: List[Dict[str, Any]],
        episode_start: Optional[np.ndarray] = None,
        lstm_states: Optional[Tuple[np.ndarray, np.ndarray]] = None,
        problem_ids: Optional[np.ndarray] = None,
        use_problem: Optional[np.ndarray] = None,
    ) -> None:
        """:meth:`SequenceReplayBuffer.add` with the trial's ``problem_ids`` and ``use_problem`` per env."""
        if problem_ids is None or use_problem is None:
            raise ValueError("problem_ids and use_problem are required: this buffer stores each trial's problem and z")
        if episode_start is not None:  # trials cut short keep their own problem: store them first
            for e in np.flatnonzero(np.asarray(episode_start, dtype=bool).reshape(self.n_envs) & (self._stage_pos > 0)):
                self._commit(int(e), trial_over=True)
        self._stage_problem_ids[:] = np.asarray(problem_ids).reshape(self.n_envs)
        self._stage_use_problem[:] = np.asarray(use_problem, dtype=bool).reshape(self.n_envs)
        super().add(obs, next_obs, action, reward, done, infos, episode_start, lstm_states)

    def _commit(self, e: int, trial_over: bool) -> None:
        row = self.pos
        self.problem_ids[row] = self._stage_problem_ids[e]
        self.use_problem[row] = self._stage_use_problem[e]
        super()._commit(e, trial_over)

    def _get_samples(self, batch_inds: np.ndarray, env: Any = None) -> ProblemSequenceSamples:  # type: ignore[override]
        base = super()._get_samples(batch_inds, env)
        return ProblemSequenceSamples(
            *base,
            problem_ids=self._as_tensor(self.problem_ids[batch_inds]),
            use_problem=self._as_tensor(self.use_problem[batch_inds]),
        )


def import_aux_loss(history: th.Tensor, e_problem: th.Tensor, mask: th.Tensor) -> th.Tensor:
    """IMPORT's auxiliary loss: the squared distance of e(tau_:t) to e(T), a fixed target.

    As in the authors' code, ``((g(tau_:t) - f(T).detach())**2)`` is averaged over the batch and
    summed over the embedding and the sequence's valid steps (``mask``): the problem embedding is
    trained by the Q-loss only, and the recurrent one is pulled towards it.

    :param history: ``[B, T(+1), z]`` the history embeddings (the first ``T`` steps are used).
    :param e_problem: ``[B, z]`` the problem embeddings (detached here).
    :param mask: ``[B, T]`` 1 on the steps to train on.
    """
    T = mask.shape[1]
    distance = ((history[:, :T] - e_problem.detach().unsqueeze(1)) ** 2).sum(dim=-1)  # [B, T]
    return (distance * mask).sum() / mask.shape[0]


def innermost_reset_infos(env: VecEnv) -> List[Dict[str, Any]]:
    """The ``info`` of each sub-env's last ``reset`` (VecEnv wrappers keep empty copies of their own)."""
    while isinstance(env, VecEnvWrapper):
        env = env.venv
    return list(env.reset_infos)


class IMPORT(RL2DQN):
    """IMPORT as a recurrent dueling double DQN (the DREAM paper's baseline, Appendix B.3).

    Q(s_t, i, z, a) reads ``[e(s_t); e(i); z]`` (linear 64 + ReLU, then a dueling head;
    :class:`~sb3_dream.import_dqn.policies.IMPORTQNetwork`). The history embedding e(tau_:t) is
    RL²'s (:class:`~sb3_dream.rl2dqn.RL2DQN`'s per-step embeddings -> linear 64 -> LSTM 64).
    During meta-training, trials alternate between z = e(T), an embedding of the trial's problem
    ID (read from ``info["problem_id"]``, never from the observation), and z = e(tau_:t); an
    auxiliary loss ``aux_loss_coef * ||e(tau_:t) - sg(e(T))||^2`` (:func:`import_aux_loss`)
    pulls the history embedding towards the problem's, so that what the policy learns with the
    problem ID transfers to the history. At meta-test, and in :meth:`predict`, z is always e(tau_:t).

    **Alternation.** Trials take the two z in turn in the order they start (over all envs:
    trial 0 e(T), trial 1 e(tau_:t), ...); the replay stores each trial's problem ID and choice
    (:class:`ProblemSequenceReplayBuffer`), so an update evaluates each sequence with the z its
    trial acted on, in the online and the target network. The auxiliary loss applies to every
    sequence (both choices), as in the authors' code.

    Everything else (environment, defaults, the sequence replay, ``predict`` with an LSTM state,
    :meth:`as_trial_agent` for :func:`~sb3_dream.evaluation.evaluate_meta`, trial-spec checks) is
    :class:`~sb3_dream.rl2dqn.RL2DQN`'s, whose parameters it takes; the env must be a trial env
    (:class:`dream_envs.TrialEnv`: ``problem_feature_table`` and ``info["problem_id"]``). With
    ``reward_free_exploration=False`` the exploration episode's instruction and rewards are part
    of the history, as in E-RL².

    :param aux_loss_coef: weight of the auxiliary loss (the authors': 1).
    The other parameters are :class:`~sb3_dream.rl2dqn.RL2DQN`'s.
    """

    policy_aliases: ClassVar[Dict[str, Type[BasePolicy]]] = {
        "MultiInputLstmPolicy": MultiInputLstmPolicy,
        "CnnLstmPolicy": CnnLstmPolicy,
    }
    policy: IMPORTPolicy
    replay_buffer: ProblemSequenceReplayBuffer
    q_net: IMPORTQNetwork
    q_net_target: IMPORTQNetwork

    def __init__(
        self,
        policy: Union[str, Type[IMPORTPolicy], GymEnv] = "MultiInputLstmPolicy",
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
        aux_loss_coef: float = 1.0,
        replay_buffer_class: Optional[Type[ProblemSequenceReplayBuffer]] = None,
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
        self.aux_loss_coef = check_non_negative("aux_loss_coef", aux_loss_coef)
        if replay_buffer_class is not None and not issubclass(replay_buffer_class, ProblemSequenceReplayBuffer):
            raise ValueError(
                "replay_buffer_class must be a subclass of sb3_dream.import_dqn.ProblemSequenceReplayBuffer "
                "(IMPORT stores each trial's problem ID and z choice)"
            )
        self.problem_table: Optional[np.ndarray] = None
        self._n_trials_started = 0  # trials begun in training: their parity picks z
        self._trial_problem_ids: Optional[np.ndarray] = None  # per env: the running trial's problem
        self._trial_use_problem: Optional[np.ndarray] = None  # per env: the running trial acts on e(T)
        super().__init__(
            policy,
            env,
            learning_rate,
            buffer_size,
            learning_starts,
            batch_size,
            tau,
            gamma,
            train_freq,
            gradient_steps,
            target_update_interval,
            exploration_initial_eps,
            exploration_final_eps,
            exploration_steps,
            max_grad_norm,
            sequence_length,
            burn_in,
            stored_state,
            td_loss,
            consume_final_obs,
            zero_exploration_rewards,
            replay_buffer_class or ProblemSequenceReplayBuffer,
            replay_buffer_kwargs,
            stats_window_size,
            tensorboard_log,
            policy_kwargs,
            verbose,
            seed,
            device,
            _init_setup_model,
            **sb3_kwargs,
        )

    # ------------------------------------------------------------------ setup
    def _setup_model(self) -> None:
        if self.problem_table is None:  # a new model (a loaded one brings its table)
            self.problem_table = self._problem_table_of_env()
        self.policy_kwargs = {**self.policy_kwargs, "problem_nvec": [int(n) for n in self.trial_spec["problem_nvec"]]}
        super()._setup_model()
        self._trial_problem_ids = self._trial_use_problem = None

    def _problem_table_of_env(self) -> np.ndarray:
        """``[n_problems, len(problem_nvec)]``: the env's problem features, which e(T) embeds."""
        if self.trial_spec is None or self.env is None or not self.env.has_attr("problem_feature_table"):
            raise ValueError(
                f"{type(self).__name__} needs a trial env (dream_envs.TrialEnv, e.g. 'MetaBus-v0'): its problem "
                "features (problem_feature_table, trial_spec()['problem_nvec']) and info['problem_id'] train e(T)"
            )
        return np.asarray(self.env.env_method("problem_feature_table", indices=[0])[0], dtype=np.int64)

    def _excluded_save_params(self) -> List[str]:
        return [*super()._excluded_save_params(), "_trial_problem_ids", "_trial_use_problem"]

    # ------------------------------------------------------------------ acting (meta-training)
    def _begin_trials(self, envs: np.ndarray, n_envs: int) -> None:
        """Read the problem of the trials starting in ``envs`` from their reset ``info`` and give
        them z = e(T) and z = e(tau_:t) in turn."""
        if self._trial_problem_ids is None or len(self._trial_problem_ids) != n_envs:
            self._trial_problem_ids = np.zeros(n_envs, dtype=np.int64)
            self._trial_use_problem = np.zeros(n_envs, dtype=bool)
        assert self.env is not None and self._trial_use_problem is not None
        infos = innermost_reset_infos(self.env)
        for e in envs:
            if "problem_id" not in infos[e]:
                raise ValueError(
                    f"{type(self).__name__} reads each trial's problem from info['problem_id'] at reset; "
                    f"sub-env {e}'s reset info has {sorted(infos[e])}"
                )
            self._trial_problem_ids[e] = int(infos[e]["problem_id"])
            self._trial_use_problem[e] = self._n_trials_started % 2 == 0
            self._n_trials_started += 1

    def _act_step(
        self, obs: Dict[str, th.Tensor], states: Tuple[th.Tensor, th.Tensor], trial_start: th.Tensor
    ) -> Tuple[th.Tensor, Tuple[th.Tensor, th.Tensor], Tuple[th.Tensor, th.Tensor]]:
        n_envs = int(trial_start.shape[0])
        starting = np.flatnonzero(trial_start.cpu().numpy() > 0)
        if len(starting) or self._trial_problem_ids is None or len(self._trial_problem_ids) != n_envs:
            self._begin_trials(starting if self._trial_problem_ids is not None else np.arange(n_envs), n_envs)
        assert self._trial_problem_ids is not None and self._trial_use_problem is not None
        states = reset_lstm_states(states, trial_start)
        history, next_states = self.q_net.encode_step(obs, states)
        z = self.q_net.choose_z(
            history,
            self._problem_features(self._trial_problem_ids),
            th.as_tensor(self._trial_use_problem, device=self.device),
        )
        return self.q_net.q_values(obs, z), states, next_states

    def _problem_features(self, problem_ids: Union[np.ndarray, th.Tensor]) -> th.Tensor:
        assert self.problem_table is not None
        ids = problem_ids.cpu().numpy() if isinstance(problem_ids, th.Tensor) else np.asarray(problem_ids)
        return th.as_tensor(self.problem_table[ids], device=self.device)

    def _replay_add_kwargs(self) -> Dict[str, Any]:
        assert self._trial_problem_ids is not None and self._trial_use_problem is not None
        return {"problem_ids": self._trial_problem_ids.copy(), "use_problem": self._trial_use_problem.copy()}

    # ------------------------------------------------------------------ learning
    def learn(
        self: SelfIMPORT,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "IMPORT",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfIMPORT:
        """Train for ``total_timesteps`` env steps (over all envs); ``log_interval`` counts trials."""
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def _loss(self, batch: SequenceReplayBufferSamples) -> Tuple[th.Tensor, Dict[str, th.Tensor]]:
        """Double-DQN loss with each sequence's own z, plus ``aux_loss_coef`` x :func:`import_aux_loss`."""
        assert isinstance(batch, ProblemSequenceSamples)
        features = self._problem_features(batch.problem_ids)
        td, q_mean, history, _ = conditioned_double_dqn_loss(
            self.q_net,
            self.q_net_target,
            batch,
            lambda net, h: net.choose_z(h, features, batch.use_problem),
            self.gamma,
            self.td_loss,
            self.burn_in,
        )
        aux = import_aux_loss(history, self.q_net.problem_embedder(features), batch.mask)
        loss = td + self.aux_loss_coef * aux
        return loss, {"loss": loss.detach(), "td_loss": td.detach(), "aux_loss": aux.detach(), "q_mean": q_mean}
