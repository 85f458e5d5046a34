"""VariBAD's networks in the DREAM paper's DQN form (Appendix B.3): the Q-network, the decoders and the policy."""

from __future__ import annotations

from typing import Any, Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space
from torch import nn
from torch.autograd.function import once_differentiable
from torch.nn import functional as F

from sb3_dream.common.conditioned import ConditionedQNetwork, ConditionedQPolicy
from sb3_dream.common.embedders import make_state_embedder
from sb3_dream.rl2dqn.policies import CnnLstmPolicy as RL2CnnLstmPolicy


def is_image_observation(observation_space: spaces.Space) -> bool:
    """Whether the trial env's ``obs`` is an image (VariBAD then drops its state decoder by default)."""
    space = observation_space.spaces.get("obs") if isinstance(observation_space, spaces.Dict) else None
    return space is not None and is_image_space(space, check_channels=False)


#: about how many hidden activations (sequences x prefixes x transitions x units) a chunk of
#: PairSquaredErrors holds: 2^17 floats (512 KiB) per tensor, so that a chunk's few tensors stay
#: near a core's L2 cache. Measured on MetaBus (decoder loss and its backward, one thread):
#: 2^17 and 2^18 were fastest, 2^15 and 2^19 about 10% slower, 2^13 30% slower.
PAIR_CHUNK_ELEMENTS = 2**17


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

    def hidden_z(self, z: th.Tensor) -> th.Tensor:
        """The first layer's z part: ``[*batch, z_dim]`` -> ``[*batch, H]`` (no bias)."""
        return F.linear(z, self.hidden.weight[:, : self.z_dim])

    def hidden_sa(self, states: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """The first layer's (s, a) part, with its bias: ``[*batch, ...]``, ``[*batch]`` -> ``[*batch, H]``."""
        sa = th.cat([self.state_embedder(states), self.action_embedder(actions.long())], dim=-1)
        return F.linear(sa, self.hidden.weight[:, self.z_dim :], self.hidden.bias)

    def fused_heads(self) -> Tuple[th.Tensor, th.Tensor]:
        """``(w_out [K, H], b_out [K])``: the second layer composed with the reward head and the
        state head (K = 1 + state_dim; 1 without a state head). No activation follows the second
        layer, so the composition is the same function, and per pair it costs K x H products
        instead of H x H more (the gradients reach both layers through the product)."""
        heads = [self.reward_head] + ([] if self.state_head is None else [self.state_head])
        w_heads = th.cat([head.weight for head in heads])  # [K, H]
        b_heads = th.cat([head.bias for head in heads])
        return w_heads @ self.hidden2.weight, w_heads @ self.hidden2.bias + b_heads

    def forward_pairs(
        self, z: th.Tensor, states: th.Tensor, actions: th.Tensor
    ) -> Tuple[th.Tensor, Optional[th.Tensor]]:
        """:meth:`forward` for every (prefix, transition) pair of each sequence, all at once.

        :param z: ``[B, P, z_dim]``, the z of P prefixes.
        :param states: ``[B, T, ...]`` and ``actions`` ``[B, T]``: T transitions.
        :return: rewards ``[B, P, T]`` and next states ``[B, P, T, state_dim]`` (or None).

        The first layer over ``[z; e(s); e(a)]`` is split into its z part and its (s, a) part,
        each computed once and added per pair (:meth:`hidden_z`, :meth:`hidden_sa`): the same
        function as concatenating every pair, without building ``B x P x T`` inputs. It still
        builds ``[B, P, T, H]`` hidden activations; a loss over the pairs costs less through
        :meth:`pair_squared_errors`, which never holds them.
        """
        h_z, h_sa = self.hidden_z(z), self.hidden_sa(states, actions)  # [B, P, H], [B, T, H]
        w_out, b_out = self.fused_heads()
        out = F.linear(F.relu(h_z.unsqueeze(2) + h_sa.unsqueeze(1)), w_out, b_out)  # [B, P, T, K]
        return out[..., 0], None if self.state_head is None else out[..., 1:]

    def pair_squared_errors(
        self,
        z: th.Tensor,
        states: th.Tensor,
        actions: th.Tensor,
        targets: th.Tensor,
        weights: th.Tensor,
        chunk_elements: int = PAIR_CHUNK_ELEMENTS,
    ) -> th.Tensor:
        """Per output, the weighted sum over every (prefix, transition) pair of the squared error of
        :meth:`forward_pairs`: the same values and gradients, computed by :class:`PairSquaredErrors`
        a few sequences at a time, on the pairs of nonzero weight only.

        :param z: ``[B, P, z_dim]``; ``states`` ``[B, T, ...]``; ``actions`` ``[B, T]``.
        :param targets: ``[B, T, K]``: per transition, the reward then the state target (K = 1 +
            state_dim; 1 without a state head).
        :param weights: ``[B, P, T]``, each pair's weight w (a constant: no gradient reaches it).
        :param chunk_elements: about how many hidden activations (sequences x prefixes x
            transitions x H; or outputs, where K > H) to hold at a time.
        :return: ``[K]``: ``sum_{b, p, t} w[b, p, t] (y_hat[b, p, t, k] - targets[b, t, k])^2``.
        """
        plan = PairPlan.of(weights, max(self.hidden.out_features, targets.shape[-1]), chunk_elements)
        # The first layer only on the prefixes and transitions inside a sequence's box: the other
        # rows stay 0, and a chunk's box reads them only in pairs of weight 0 (nothing to the loss
        # or to a gradient).
        if plan.chunks:
            h_z = _scatter_rows(self.hidden_z(z[plan.rows]), plan.rows)
            h_sa = _scatter_rows(self.hidden_sa(states[plan.cols], actions[plan.cols]), plan.cols)
        else:  # no pair to decode (the embedders take no empty batch): zero sums, zero gradients
            h_z, h_sa = self.hidden_z(z), self.hidden_sa(states, actions)
        w_out, b_out = self.fused_heads()
        return PairSquaredErrors.apply(h_z, h_sa, w_out, b_out, targets, weights, plan)


def _scatter_rows(values: th.Tensor, where: th.Tensor) -> th.Tensor:
    """``[n, H]`` values at the n true entries of ``where`` ``[B, L]``, zeros elsewhere: ``[B, L, H]``."""
    out = values.new_zeros(*where.shape, values.shape[-1])
    out[where] = values
    return out


class PairPlan(NamedTuple):
    """Which (prefix, transition) pairs :class:`PairSquaredErrors` computes, in which chunks.

    Each sequence is cropped to the box of its pairs of nonzero weight: prefixes ``0..p - 1`` and
    transitions ``lo..hi - 1`` (padding, and the prefixes past a sequence's length, weigh 0).
    Sequences with no such pair are left out; the others, sorted by their box's size (largest
    first: ``order``), are cut into chunks of consecutive sequences, each cropped to the box
    holding all of its sequences, while that box holds at most ``chunk_elements`` floats
    (sequences x prefixes x transitions x ``width``; at least one sequence per chunk).
    """

    order: th.Tensor  # [B'] long: the sequences computed, chunk by chunk
    rows: th.Tensor  # [B, P] bool: the prefixes inside each sequence's box
    cols: th.Tensor  # [B, T] bool: the transitions inside each sequence's box
    chunks: List[Tuple[int, int, int, int, int]]  # (start, stop) in order, then the box (p, lo, hi)

    @classmethod
    def of(cls, weights: th.Tensor, width: int, chunk_elements: int) -> "PairPlan":
        """The plan for pair weights ``[B, P, T]`` (read on the host: one device sync), with
        ``width`` floats per pair (the hidden units, or the outputs where there are more)."""
        nonzero = weights != 0
        prefixes, transitions = nonzero.any(2), nonzero.any(1)  # [B, P], [B, T]
        P, T = prefixes.shape[1], transitions.shape[1]
        p_to = (prefixes * th.arange(1, P + 1, device=weights.device)).amax(1)
        t_to = (transitions * th.arange(1, T + 1, device=weights.device)).amax(1)
        t_from = th.where(transitions, th.arange(T, device=weights.device), T).amin(1)
        boxes = [(p, lo, hi, b) for b, (p, lo, hi) in enumerate(zip(p_to.tolist(), t_from.tolist(), t_to.tolist()))]
        boxes = sorted((box for box in boxes if box[0]), key=lambda box: box[0] * (box[2] - box[1]), reverse=True)
        chunks: List[Tuple[int, int, int, int, int]] = []
        for p, lo, hi, _ in boxes:
            if chunks:
                start, stop, chunk_p, chunk_lo, chunk_hi = chunks[-1]
                grown = (max(chunk_p, p), min(chunk_lo, lo), max(chunk_hi, hi))
                if (stop - start + 1) * grown[0] * (grown[2] - grown[1]) * width <= chunk_elements:
                    chunks[-1] = (start, stop + 1, *grown)
                    continue
            stop = chunks[-1][1] if chunks else 0
            chunks.append((stop, stop + 1, p, lo, hi))
        steps_p, steps_t = th.arange(P, device=weights.device), th.arange(T, device=weights.device)
        return cls(
            order=th.tensor([box[3] for box in boxes], dtype=th.long, device=weights.device),
            rows=steps_p < p_to.unsqueeze(1),
            cols=(steps_t >= t_from.unsqueeze(1)) & (steps_t < t_to.unsqueeze(1)),
            chunks=chunks,
        )


class PairSquaredErrors(th.autograd.Function):
    """``sum_{b, p, t} w[b, p, t] (w_out @ relu(h_z[b, p] + h_sa[b, t]) + b_out - y[b, t])^2``, per
    output, with its gradient derived by hand; a chunk of sequences at a time (a
    :class:`PairPlan`), never storing the ``[B, P, T, H]`` activations.

    Autograd over the dense form (:meth:`TransitionDecoder.forward_pairs`) stores the hidden
    activations of every pair and reads and writes them several times (add, ReLU, its backward,
    the matmuls): memory-bound work. Here each chunk is computed while it fits in cache, and the
    backward recomputes it. With ``a = h_z[p] + h_sa[t]``, ``h = relu(a)``, the error ``e = w_out
    h + b_out - y[t]`` and, per output k, ``g_k = 2 grad_k w e_k`` (``grad`` the gradient of the
    ``[K]`` result): ``dL/dw_out = sum g h^T``, ``dL/db_out = sum g``, ``dL/dy[t] = -sum_p g``
    and, with ``d = (w_out^T g) * [a > 0]``, ``dL/dh_z[p] = sum_t d``, ``dL/dh_sa[t] = sum_p d``
    (sums over the pairs of each sequence). The weights are constants (no gradient). Once
    differentiable.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        h_z: th.Tensor,
        h_sa: th.Tensor,
        w_out: th.Tensor,
        b_out: th.Tensor,
        targets: th.Tensor,
        weights: th.Tensor,
        plan: PairPlan,
    ) -> th.Tensor:
        if weights.requires_grad:
            raise ValueError("PairSquaredErrors takes no gradient with respect to the pair weights")
        # the computed sequences in chunk order, once, so that each chunk is a slice of them
        h_z, h_sa = h_z[plan.order], h_sa[plan.order]
        targets, weights = targets[plan.order], weights[plan.order]
        sums = h_z.new_zeros(w_out.shape[0])
        weighted_errors = []  # w e per chunk, [c, p, t, K]: what the backward needs besides h
        for start, stop, p, lo, hi in plan.chunks:
            h = _chunk_hidden(h_z, h_sa, start, stop, p, lo, hi)
            errors = th.addmm(b_out, h.view(-1, h.shape[-1]), w_out.t()).view(*h.shape[:-1], -1)
            errors -= targets[start:stop, lo:hi].unsqueeze(1)
            weighted = errors * weights[start:stop, :p, lo:hi].unsqueeze(-1)
            sums += (weighted * errors).sum((0, 1, 2))
            weighted_errors.append(weighted)
        ctx.save_for_backward(h_z, h_sa, w_out)
        ctx.plan, ctx.weighted_errors, ctx.target_shape = plan, weighted_errors, targets.shape
        return sums

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad_sums: th.Tensor) -> Tuple[Optional[th.Tensor], ...]:
        h_z, h_sa, w_out = ctx.saved_tensors  # h_z, h_sa: the computed sequences, in chunk order
        plan: PairPlan = ctx.plan
        g_hz, g_hsa = th.zeros_like(h_z), th.zeros_like(h_sa)
        g_w, g_b = th.zeros_like(w_out), th.zeros_like(w_out[:, 0])
        g_y = h_z.new_zeros(ctx.target_shape) if ctx.needs_input_grad[4] else None
        scale = 2 * grad_sums
        for (start, stop, p, lo, hi), weighted in zip(plan.chunks, ctx.weighted_errors):
            h = _chunk_hidden(h_z, h_sa, start, stop, p, lo, hi)  # recomputed: cheaper than storing it
            g = weighted * scale  # dL/dy_hat, [c, p, t, K]
            g_flat, h_flat = g.view(-1, g.shape[-1]), h.view(-1, h.shape[-1])
            g_w.addmm_(g_flat.t(), h_flat)
            g_b += g_flat.sum(0)
            if g_y is not None:
                g_y[start:stop, lo:hi] = -g.sum(1)
            d = th.ops.aten.threshold_backward(g_flat @ w_out, h_flat, 0).view(h.shape)  # ReLU's backward
            g_hz[start:stop, :p] = d.sum(2)
            g_hsa[start:stop, lo:hi] = d.sum(1)
        # back to the batch's order; the sequences left out get 0
        g_hz = g_hz.new_zeros(len(plan.rows), *g_hz.shape[1:]).index_copy_(0, plan.order, g_hz)
        g_hsa = g_hsa.new_zeros(len(plan.cols), *g_hsa.shape[1:]).index_copy_(0, plan.order, g_hsa)
        if g_y is not None:
            g_y = g_y.new_zeros(len(plan.cols), *g_y.shape[1:]).index_copy_(0, plan.order, g_y)
        return g_hz, g_hsa, g_w, g_b, g_y, None, None


def _chunk_hidden(h_z: th.Tensor, h_sa: th.Tensor, start: int, stop: int, p: int, lo: int, hi: int) -> th.Tensor:
    """``relu(h_z[b, q] + h_sa[b, t])`` for ``start <= b < stop``, ``q < p``, ``lo <= t < hi``: ``[c, p, t, H]``."""
    return th.add(h_z[start:stop, :p].unsqueeze(2), h_sa[start:stop, lo:hi].unsqueeze(1)).relu_()


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
