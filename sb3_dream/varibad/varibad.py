"""VariBAD (Zintgraf et al., 2019) in the DREAM paper's DQN form (Appendix B.3)."""

from __future__ import annotations

from typing import Any, ClassVar, Dict, Optional, Tuple, Type, TypeVar, Union

import torch as th
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule

from dream_envs.checks import check_choice, check_non_negative
from sb3_dream.common.buffers import SequenceReplayBuffer, SequenceReplayBufferSamples
from sb3_dream.common.conditioned import ConditionedQNetwork, conditioned_double_dqn_loss
from sb3_dream.rl2dqn.rl2dqn import RL2DQN
from sb3_dream.varibad.policies import (
    PAIR_CHUNK_ELEMENTS,
    CnnLstmPolicy,
    MultiInputLstmPolicy,
    TransitionDecoder,
    VariBADPolicy,
    VariBADQNetwork,
    is_image_observation,
)

SelfVariBAD = TypeVar("SelfVariBAD", bound="VariBAD")


#: the implementations of :func:`varibad_decoder_loss`
DECODER_LOSS_METHODS = ("auto", "chunked", "dense")


def varibad_decoder_loss(
    decoder: TransitionDecoder,
    z: th.Tensor,
    batch: SequenceReplayBufferSamples,
    method: str = "auto",
    chunk_elements: int = PAIR_CHUNK_ELEMENTS,
) -> Tuple[th.Tensor, th.Tensor, Optional[th.Tensor]]:
    """VariBAD's reconstruction loss: from the z of every prefix of each sampled sequence, decode
    the reward and next state of every transition of that sequence (as the authors' code does).

    With ``T`` transitions, prefixes ``t = 0..T`` (z after observing ``t`` transitions, ``z[:, t]``)
    and transitions ``j`` on the loss mask: the mean over all valid (prefix, transition) pairs of
    ``(r_hat - r_j)^2`` (reward loss) and of the mean over state dimensions of
    ``(s_hat - s_{j+1})^2`` (state loss, when the decoder has a state head); ``loss`` is their sum.

    :param z: ``[B, T + 1, z_dim]``, the z of each prefix (prefix t is valid while ``t <= length``).
    :param method: ``"chunked"`` (:meth:`~TransitionDecoder.pair_squared_errors`: a few sequences
        at a time, valid pairs only, nothing of size ``B x P x T x H`` kept for the backward) or
        ``"dense"`` (:meth:`~TransitionDecoder.forward_pairs` on every pair at once, through
        autograd: the reference); the same values and gradients, to float rounding. ``"auto"``:
        chunked on CPU (where the dense form is bound by memory traffic), dense elsewhere (the
        chunk plan reads the mask on the host, which would make a GPU wait).
    :param chunk_elements: the chunked method's chunk size (hidden activations).
    :return: ``(loss, reward_loss, state_loss or None)``.
    """
    check_choice("method", method, DECODER_LOSS_METHODS)
    T = batch.actions.shape[1]
    obs = batch.observations["obs"]
    prefixes = th.arange(T + 1, device=z.device)
    prefix_valid = (prefixes.unsqueeze(0) <= batch.lengths.unsqueeze(1)).float()  # [B, T + 1]
    pairs = prefix_valid.unsqueeze(2) * batch.mask.unsqueeze(1)  # [B, T + 1, T]
    n_pairs = pairs.sum().clamp(min=1.0)
    if method == "auto":
        method = "chunked" if z.device.type == "cpu" else "dense"
    if method == "chunked":
        targets = batch.rewards.unsqueeze(-1).float()  # [B, T, 1 (+ D)]
        if decoder.state_head is not None:
            targets = th.cat([targets, decoder.state_targets(obs[:, 1 : T + 1])], dim=-1)
        sums = decoder.pair_squared_errors(z[:, : T + 1], obs[:, :T], batch.actions, targets, pairs, chunk_elements)
        reward_loss = sums[0] / n_pairs
        if decoder.state_head is None:
            return reward_loss, reward_loss, None
        state_loss = sums[1:].sum() / (decoder.state_dim * n_pairs)
        return reward_loss + state_loss, reward_loss, state_loss
    r_hat, s_hat = decoder.forward_pairs(z[:, : T + 1], obs[:, :T], batch.actions)  # [B, T + 1, T]
    reward_loss = (((r_hat - batch.rewards.unsqueeze(1)) ** 2) * pairs).sum() / n_pairs
    if s_hat is None:
        return reward_loss, reward_loss, None
    targets = decoder.state_targets(obs[:, 1 : T + 1]).unsqueeze(1)  # [B, 1, T, D]
    state_loss = (((s_hat - targets) ** 2).mean(dim=-1) * pairs).sum() / n_pairs
    return reward_loss + state_loss, reward_loss, state_loss


class VariBAD(RL2DQN):
    """VariBAD as the DREAM paper runs it: a recurrent dueling double DQN over ``[e(s); e(i); z]``
    whose history encoder is also trained to predict rewards and next states.

    The encoder enc(z | tau_:t) embeds the history exactly as RL² does
    (:class:`~sb3_dream.rl2dqn.RL2DQN`: per-step embeddings -> linear 64 -> LSTM 64); its output
    is the mean mu (the authors' code uses it directly, 64 units) and z ~ N(mu, nu^2 I) with the
    paper's fixed nu^2 = ``latent_variance`` = 1e-5. Q(s_t, i, z, a) reads ``[e(s_t); e(i); z]``
    (linear 64 + ReLU, dueling head; :class:`~sb3_dream.varibad.policies.VariBADQNetwork`). The
    decoders (``policy.decoder``, a :class:`~sb3_dream.varibad.policies.TransitionDecoder`: e(a)
    32 and e(s) over ``[e(s); e(a); z]``, two linear layers of 128, a reward head and a state
    head; no target copy) add the mean-squared reconstruction loss :func:`varibad_decoder_loss`
    (weight ``decoder_loss_coef``) to the TD loss; both train the encoder.

    **Where it differs from the original VariBAD** (Zintgraf et al., 2019): the policy is a
    double DQN trained from sequence replay, not PPO on fresh rollouts; the posterior variance is
    fixed, not learned, and there is no KL term (the paper found VariBAD better without it); the
    decoders decode the sampled trajectory's own transitions (the authors' code: from the z of
    *every prefix*, every transition of that trajectory, where the original decodes the whole
    trial, past and future, from each belief); the Q-loss also trains the encoder.
    Updates sample z (online and target network alike); acting, :meth:`predict` and meta-testing
    use mu (the noise, of standard deviation about 0.003, would only blur a greedy policy).
    The decoder loss is computed chunk by chunk on CPU (``decoder_loss_method``, an attribute:
    :func:`varibad_decoder_loss`'s ``method``; the same function either way).

    The state decoder is dropped for image states (the paper, on the 3D sign env): ``predict_states``
    None picks that from the observation space; True or False overrides it.

    Everything else is :class:`~sb3_dream.rl2dqn.RL2DQN`'s (defaults: the paper's Table 1; the
    sequence replay; ``predict`` with an LSTM state; :meth:`as_trial_agent`; trial-spec checks).
    With ``reward_free_exploration=False`` the exploration episode's instruction and rewards enter
    the history and the reward decoder's targets.

    :param latent_variance: nu^2 of z ~ N(mu, nu^2 I) in updates (paper: 1e-5; 0: z = mu).
    :param decoder_loss_coef: weight of the decoders' loss (1).
    :param predict_states: keep the state decoder (None: unless ``obs`` is an image). Forced on
        for images, it predicts every pixel for every (prefix, transition) pair: memory grows as
        ``batch_size x sequence_length^2 x pixels``.
    The other parameters are :class:`~sb3_dream.rl2dqn.RL2DQN`'s.
    """

    policy_aliases: ClassVar[Dict[str, Type[BasePolicy]]] = {
        "MultiInputLstmPolicy": MultiInputLstmPolicy,
        "CnnLstmPolicy": CnnLstmPolicy,
    }
    #: how :meth:`_loss` computes :func:`varibad_decoder_loss` (its ``method``; the same function)
    decoder_loss_method: str = "auto"
    policy: VariBADPolicy
    q_net: VariBADQNetwork
    q_net_target: VariBADQNetwork

    def __init__(
        self,
        policy: Union[str, Type[VariBADPolicy], GymEnv] = "MultiInputLstmPolicy",
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
        latent_variance: float = 1e-5,
        decoder_loss_coef: float = 1.0,
        predict_states: Optional[bool] = None,
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
        self.latent_variance = check_non_negative("latent_variance", latent_variance)
        self.decoder_loss_coef = check_non_negative("decoder_loss_coef", decoder_loss_coef)
        if predict_states is not None and not isinstance(predict_states, bool):
            raise ValueError(f"predict_states must be None (automatic), True or False, got {predict_states!r}")
        self.predict_states = predict_states
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
            replay_buffer_class,
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

    def _setup_model(self) -> None:
        predict_states = self.predict_states
        if predict_states is None:  # the paper: no state decoder for image states
            predict_states = not is_image_observation(self.observation_space)
        self.policy_kwargs = {**self.policy_kwargs, "predict_states": predict_states}
        super()._setup_model()

    def sample_z(self, net: ConditionedQNetwork, mu: th.Tensor) -> th.Tensor:
        """z ~ N(mu, nu^2 I), reparametrised (the gradient reaches mu)."""
        if self.latent_variance == 0:
            return mu
        # Fresh noise in a contiguous tensor: mu comes from the LSTM transposed, and randn_like would
        # keep its strides, where torch draws normals one at a time (about 10x slower on CPU).
        noise = th.randn(mu.shape, dtype=mu.dtype, device=mu.device)
        return mu + self.latent_variance**0.5 * noise

    def learn(
        self: SelfVariBAD,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "VariBAD",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfVariBAD:
        """Train for ``total_timesteps`` env steps (over all envs); ``log_interval`` counts trials."""
        return super().learn(total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)

    def _loss(self, batch: SequenceReplayBufferSamples) -> Tuple[th.Tensor, Dict[str, th.Tensor]]:
        """Double-DQN loss on sampled z plus ``decoder_loss_coef`` x :func:`varibad_decoder_loss`."""
        td, q_mean, _, z = conditioned_double_dqn_loss(
            self.q_net, self.q_net_target, batch, self.sample_z, self.gamma, self.td_loss, self.burn_in
        )
        decoder_loss, reward_loss, state_loss = varibad_decoder_loss(
            self.policy.decoder, z, batch, self.decoder_loss_method
        )
        loss = td + self.decoder_loss_coef * decoder_loss
        logged = {"loss": loss.detach(), "td_loss": td.detach(), "reward_decoder_loss": reward_loss.detach()}
        if state_loss is not None:
            logged["state_decoder_loss"] = state_loss.detach()
        logged["q_mean"] = q_mean
        return loss, logged
