"""VariBAD's networks in the DREAM paper's DQN form (Appendix B.3): the Q-network, the decoders and the policy."""

from __future__ import annotations

from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space
from torch import nn
from torch.nn import functional as F

from sb3_dream.common.conditioned import ConditionedQNetwork, ConditionedQPolicy
from sb3_dream.common.embedders import make_state_embedder
from sb3_dream.rl2dqn.policies import CnnLstmPolicy as RL2CnnLstmPolicy


def is_image_observation(observation_space: spaces.Space) -> bool:
    """Whether the trial env's ``obs`` is an image (VariBAD then drops its state decoder by default)."""
    space = observation_space.spaces.get("obs") if isinstance(observation_space, spaces.Dict) else None
    return space is not None and is_image_space(space, check_channels=False)


class TransitionDecoder(nn.Module):
    """VariBAD's reward decoder R(r | s, a, z) and state decoder T(s' | s, a, z) (paper, Appendix B.3).

    ``[e(s); e(a); z]`` -> linear 128 + ReLU -> linear 128 -> a reward head (1) and a state head
    (the flattened next state), read with a mean-squared error. e(s) is the paper's state embedder
    (learned anew here), e(a) an embedding matrix of 32 units. The second linear layer has no
    activation, as in the authors' code.

    :param state_space: the ``obs`` space.
    :param predict_states: build the state head (the paper drops it for images).
    """

    def __init__(
        self,
        state_space: spaces.Space,
        n_actions: int,
        z_dim: int,
        action_embed_dim: int = 32,
        hidden_dim: int = 128,
        predict_states: bool = True,
        per_dim: int = 32,
        state_hidden_dims: Sequence[int] = (256, 64),
        image_embed_dim: int = 128,
        normalize_images: bool = True,
    ) -> None:
        super().__init__()
        self.state_shape = tuple(state_space.shape or ())
        self.image = is_image_space(state_space, check_channels=False) if isinstance(state_space, spaces.Box) else False
        self.normalize_images = normalize_images
        self.state_embedder = make_state_embedder(
            state_space, per_dim, state_hidden_dims, image_embed_dim, name="obs", normalize_images=normalize_images
        )
        self.action_embedder = nn.Embedding(n_actions, action_embed_dim)
        self.z_dim = z_dim
        self.hidden = nn.Linear(z_dim + int(self.state_embedder.embed_dim) + action_embed_dim, hidden_dim)
        self.hidden2 = nn.Linear(hidden_dim, hidden_dim)
        self.reward_head = nn.Linear(hidden_dim, 1)
        self.state_dim = int(np.prod(self.state_shape)) if self.state_shape else 1
        self.state_head: Optional[nn.Linear] = nn.Linear(hidden_dim, self.state_dim) if predict_states else None

    def state_targets(self, states: th.Tensor) -> th.Tensor:
        """The state head's target: the state as a flat float vector (images scaled to [0, 1])."""
        flat = states.reshape(*states.shape[: states.dim() - len(self.state_shape)], self.state_dim).float()
        return flat / 255.0 if self.image and self.normalize_images else flat

    def _heads(self, h: th.Tensor) -> Tuple[th.Tensor, Optional[th.Tensor]]:
        h = self.hidden2(h)
        return self.reward_head(h).squeeze(-1), None if self.state_head is None else self.state_head(h)

    def forward(self, z: th.Tensor, states: th.Tensor, actions: th.Tensor) -> Tuple[th.Tensor, Optional[th.Tensor]]:
        """Predicted reward ``[*batch]`` and next state ``[*batch, state_dim]`` (or None) of taking
        ``actions`` in ``states`` under z, all with the same leading dims."""
        x = th.cat([z, self.state_embedder(states), self.action_embedder(actions.long())], dim=-1)
        return self._heads(F.relu(self.hidden(x)))

    def forward_pairs(
        self, z: th.Tensor, states: th.Tensor, actions: th.Tensor
    ) -> Tuple[th.Tensor, Optional[th.Tensor]]:
        """:meth:`forward` for every (prefix, transition) pair of each sequence.

        :param z: ``[B, P, z_dim]``, the z of P prefixes.
        :param states: ``[B, T, ...]`` and ``actions`` ``[B, T]``: T transitions.
        :return: rewards ``[B, P, T]`` and next states ``[B, P, T, state_dim]`` (or None).

        The first layer over ``[z; e(s); e(a)]`` is split into its z part and its (s, a) part,
        each computed once and added per pair: the same function as concatenating every pair,
        without building ``B x P x T`` inputs.
        """
        w, b = self.hidden.weight, self.hidden.bias
        h_z = F.linear(z, w[:, : self.z_dim])  # [B, P, H]
        sa = th.cat([self.state_embedder(states), self.action_embedder(actions.long())], dim=-1)
        h_sa = F.linear(sa, w[:, self.z_dim :], b)  # [B, T, H]
        h = F.relu(h_z.unsqueeze(2) + h_sa.unsqueeze(1))  # [B, P, T, H]
        # No activation follows the second layer, so it composes with the heads into one linear map:
        # per pair, (1 + state_dim) x H products instead of H x H more (the same function; the
        # gradients reach both layers through the product).
        heads = [self.reward_head] + ([] if self.state_head is None else [self.state_head])
        w_heads = th.cat([head.weight for head in heads])  # [1 + D, H]
        b_heads = th.cat([head.bias for head in heads])
        out = F.linear(h, w_heads @ self.hidden2.weight, w_heads @ self.hidden2.bias + b_heads)
        return out[..., 0], None if self.state_head is None else out[..., 1:]


class VariBADQNetwork(ConditionedQNetwork):
    """Q(s_t, i, z, a) over ``[e(s_t); e(i); z]`` with z around mu = e(tau_:t).

    The encoder enc(z | tau_:t) is RL²'s history embedding (mu, 64 units, as in the authors' code).
    The decoders are not part of it: the policy holds them (:attr:`VariBADPolicy.decoder`), so the
    target network, a copy of this one, holds only what the TD target reads.
    The parameters are :class:`~sb3_dream.common.conditioned.ConditionedQNetwork`'s.
    """


#: the arguments of the policy's :class:`TransitionDecoder`, with their defaults (the paper's sizes)
DECODER_DEFAULTS: Dict[str, Any] = {"decoder_hidden_dim": 128, "decoder_action_embed_dim": 32, "predict_states": True}


class VariBADPolicy(ConditionedQPolicy):
    """Policy of :class:`~sb3_dream.varibad.VariBAD`: an online and a target :class:`VariBADQNetwork`,
    and the :class:`TransitionDecoder` ``decoder``.

    The decoder is trained with the online network (one optimizer, one gradient clipping, one
    save); the TD target never reads it, so it has no target copy. ``predict`` acts on z = mu =
    e(tau_:t), the posterior mean. ``policy_kwargs`` may set the network's sizes (``q_hidden_dim``,
    ...) and the decoder's: ``decoder_hidden_dim`` (paper: 128), ``decoder_action_embed_dim``
    (paper: 32), ``predict_states`` (build the state decoder; VariBAD fills it: not for image states).
    """

    q_network_class = VariBADQNetwork
    decoder: TransitionDecoder

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.register_load_state_dict_pre_hook(_move_decoder_out_of_q_networks)

    def _build_networks(self, observation_space: spaces.Dict, n_actions: int, network_kwargs: Dict[str, Any]) -> None:
        """The Q-networks from the network arguments, then the decoder from its own."""
        network_kwargs = dict(network_kwargs)
        decoder_kwargs = {key: network_kwargs.pop(key, default) for key, default in DECODER_DEFAULTS.items()}
        super()._build_networks(observation_space, n_actions, network_kwargs)
        ek = network_kwargs.get("embed_kwargs") or {}
        # built after the Q-network, as when it was its last module: the same order of random draws
        self.decoder = TransitionDecoder(
            observation_space.spaces["obs"],
            n_actions,
            self.q_net.z_dim,
            action_embed_dim=decoder_kwargs["decoder_action_embed_dim"],
            hidden_dim=decoder_kwargs["decoder_hidden_dim"],
            predict_states=decoder_kwargs["predict_states"],
            per_dim=ek.get("per_dim", 32),
            state_hidden_dims=ek.get("state_hidden_dims", (256, 64)),
            image_embed_dim=ek.get("image_embed_dim", 128),
            normalize_images=ek.get("normalize_images", True),
        )

    def trained_parameters(self) -> List[nn.Parameter]:
        """The online Q-network's parameters, then the decoder's."""
        return [*self.q_net.parameters(), *self.decoder.parameters()]


def _move_decoder_out_of_q_networks(
    module: nn.Module, state_dict: Dict[str, Any], prefix: str, local_metadata: Any, strict: bool, *args: Any
) -> None:
    """Read a policy saved when the decoder lived in the Q-network: its online copy becomes
    ``decoder``, the target's unused copy is dropped. The parameter order the optimizer saw is the
    same (the Q-network's, then the decoder's), so the saved optimizer state still matches."""
    for key in list(state_dict):
        if key.startswith(f"{prefix}q_net.decoder."):
            state_dict[f"{prefix}decoder." + key[len(f"{prefix}q_net.decoder.") :]] = state_dict.pop(key)
        elif key.startswith(f"{prefix}q_net_target.decoder."):
            del state_dict[key]


class MultiInputLstmPolicy(VariBADPolicy):
    """:class:`VariBADPolicy` for Dict observations (the default: grid trial envs)."""


class CnnLstmPolicy(VariBADPolicy, RL2CnnLstmPolicy):
    """:class:`VariBADPolicy` whose ``obs`` key must be an image (uint8 HxWxC or CxHxW): the CNN embedder."""
