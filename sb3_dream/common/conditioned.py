"""Q(s_t, i, z, a) over ``[e(s_t); e(i); z]``: the Q-network shape IMPORT and VariBAD share.

In the DREAM paper's baselines (Appendix B.3) both IMPORT and VariBAD embed the history tau_:t
exactly as RL² does (per-step embeddings -> linear 64 + ReLU -> LSTM 64, :class:`HistoryQNetwork`)
and read Q-values from a *separate* embedding of the current state and instruction concatenated
with a vector z: a linear layer of 64 units with ReLU over ``[e(s_t); e(i); z]``, then a dueling
head. They differ only in what z is (IMPORT: the problem embedding e(T) or the history e(tau_:t);
VariBAD: a sample around the history's embedding) and in their auxiliary losses, so this module
holds the network once, with :func:`conditioned_double_dqn_loss`, the double-DQN loss over a
sequence batch for a given choice of z.
"""

from __future__ import annotations

from typing import Any, Callable, Dict, Optional, Sequence, Tuple, Union

import torch as th
from gymnasium import spaces
from torch import nn

from dream_envs.checks import check_layer_sizes
from sb3_dream.common.buffers import SequenceReplayBufferSamples
from sb3_dream.common.embedders import TRIAL_KEYS, TrialInputEmbedder, relu_mlp
from sb3_dream.common.recurrent import DuelingHead
from sb3_dream.rl2dqn.policies import HistoryQNetwork, RL2DQNPolicy
from sb3_dream.rl2dqn.rl2dqn import double_dqn_loss_from_q_values, initial_batch_states

#: the keys of the current step that Q reads besides z: e(s_t) and e(i)
CURRENT_KEYS = ("obs", "instruction")

ChooseZ = Callable[["ConditionedQNetwork", th.Tensor], th.Tensor]


class ConditionedQNetwork(HistoryQNetwork):
    """RL²'s history encoder e(tau_:t) and a dueling Q-head over ``[e(s_t); e(i); z]``.

    The history encoder (``embedder``, ``fusion``, ``lstm``) is :class:`HistoryQNetwork`'s; its LSTM
    output, e(tau_:t), is z by default (:meth:`forward`, :meth:`step`: what the policy acts on
    at meta-test). ``current_embedder`` embeds the step's state (64 units, 128 for images) and
    instruction (64) anew, with the paper's state/instruction embedders (32 per dimension, then
    256 and 64); ``q_hidden`` is the linear layer of ``q_hidden_dim`` (paper: 64) with ReLU. No Q
    head over the history alone (RL²'s) is built: every parameter is one the Q-values read.

    :param n_actions: number of discrete actions.
    :param dueling: dueling head (paper) or a single linear Q head.
    :param q_hidden_dim: the layer over ``[e(s); e(i); z]``: its units (paper: 64), or a list of
        sizes for several linear + ReLU layers (e.g. ``(256, 256)``, the body of DREAM's measured
        MetaCook execution network), the head reading the last.
    The other parameters are :class:`HistoryQNetwork`'s; ``z``'s size is ``lstm_hidden_size``.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        n_actions: int,
        fusion_dim: int = 64,
        lstm_hidden_size: int = 64,
        n_lstm_layers: int = 1,
        dueling: bool = True,
        embed_keys: Sequence[str] = TRIAL_KEYS,
        embed_kwargs: Optional[Dict[str, Any]] = None,
        q_hidden_dim: Union[int, Sequence[int]] = 64,
    ) -> None:
        super().__init__(observation_space, fusion_dim, lstm_hidden_size, n_lstm_layers, embed_keys, embed_kwargs)
        self.z_dim = lstm_hidden_size
        # The head is registered right after the encoder, where it stood when it replaced RL²'s: the
        # parameters keep their order, so optimizer states saved before still match them.
        several = isinstance(q_hidden_dim, (list, tuple))
        sizes = check_layer_sizes("q_hidden_dim", q_hidden_dim if several else [q_hidden_dim])
        self.head = DuelingHead(sizes[-1], n_actions) if dueling else nn.Linear(sizes[-1], n_actions)
        keys = [k for k in CURRENT_KEYS if k in embed_keys]
        self.current_embedder = TrialInputEmbedder(observation_space, keys=keys, **(embed_kwargs or {}))
        self.q_hidden, _ = relu_mlp(self.current_embedder.embed_dim + self.z_dim, sizes)

    def q_values(self, obs: Dict[str, th.Tensor], z: th.Tensor) -> th.Tensor:
        """Q(s_t, i, z, .): ``obs[k]`` ``[*batch, ...]`` and ``z`` ``[*batch, z_dim]`` -> ``[*batch, A]``."""
        return self.head(self.q_hidden(th.cat([self.current_embedder(obs), z], dim=-1)))


class ConditionedQPolicy(RL2DQNPolicy):
    """:class:`~sb3_dream.rl2dqn.policies.RL2DQNPolicy` with a :class:`ConditionedQNetwork`
    (``policy_kwargs`` may set ``q_hidden_dim``); ``predict`` acts on z = e(tau_:t)."""

    q_network_class = ConditionedQNetwork


def conditioned_double_dqn_loss(
    q_net: ConditionedQNetwork,
    q_net_target: ConditionedQNetwork,
    batch: SequenceReplayBufferSamples,
    choose_z: ChooseZ,
    gamma: float,
    td_loss: str = "mse",
    burn_in: int = 0,
) -> Tuple[th.Tensor, th.Tensor, th.Tensor, th.Tensor]:
    """The masked double-DQN loss of Q(s_t, i, z, a) over a padded sequence batch.

    Each network unrolls its history encoder once over the ``T + 1`` observations; ``choose_z(net,
    history)`` turns that network's e(tau_:t) (``[B, T + 1, z_dim]``) into the z its Q reads
    (IMPORT: e(T) on some sequences; VariBAD: a sample). Targets as
    :func:`~sb3_dream.rl2dqn.rl2dqn.recurrent_double_dqn_loss`.

    :return: ``(loss, mean Q(s, a), the online history embedding, the online z)``.
    """
    states = initial_batch_states(q_net, batch)
    history, _ = q_net.encode(batch.observations, states, burn_in, batch.burn_in_mask)  # [B, T + 1, z]
    z = choose_z(q_net, history)
    q_all = q_net.q_values(batch.observations, z)
    with th.no_grad():
        target_history, _ = q_net_target.encode(batch.observations, states)
        q_target_all = q_net_target.q_values(batch.observations, choose_z(q_net_target, target_history))
    loss, q_mean = double_dqn_loss_from_q_values(q_all, q_target_all, batch, gamma, td_loss)
    return loss, q_mean, history, z
