"""DREAM's objectives as pure functions of network outputs (paper, Section 4 and Appendix A).

* :func:`execution_td_losses`: the execution Q's double-DQN losses (Equation 2's RL term), one for
  z from the decoder and one for z from the encoder;
* :func:`bottleneck_loss`: the information bottleneck on f (Equation 3, with the authors'
  threshold K);
* :func:`decoder_loss`: the decoder's regression of every prefix g(tau_:t) toward f(T) (Equation 4);
* :func:`exploration_rewards`: the information-gain reward of each exploration step (Equation 5);
* :func:`exploration_td_loss`: the recurrent exploration Q's double-DQN loss on those rewards.

Shapes: B trajectories (or transitions), T transitions per padded trajectory, z the code's size,
A actions.
"""

from __future__ import annotations

from typing import Tuple

import torch as th
from torch.nn import functional as F

from sb3_dream.common.recurrent import double_dqn_targets, masked_td_loss


def execution_td_losses(
    q: th.Tensor,
    next_q_online: th.Tensor,
    next_q_target: th.Tensor,
    rewards: th.Tensor,
    dones: th.Tensor,
    gamma: float,
    n_rows: int,
) -> Tuple[th.Tensor, th.Tensor]:
    """Equation 2's two DDQN losses on one batch of execution transitions evaluated twice.

    :param q: ``[2B]`` Q(s, a, z) of the taken actions; rows ``[0, B)`` with z = g(tau^exp),
        rows ``[B, 2B)`` with z ~ F(z | T).
    :param next_q_online: ``[2B, A]`` the online Q at s' (picks the next action).
    :param next_q_target: ``[2B, A]`` the target Q at s' (evaluates it).
    :param rewards: ``[2B]``; ``dones``: ``[2B]``, 1 where s' is terminal.
    :param n_rows: B.
    :return: the mean squared TD errors of the decoder's rows and of the encoder's rows.
    """
    with th.no_grad():
        target = double_dqn_targets(next_q_online, next_q_target, rewards, dones, gamma)
    td = F.mse_loss(q, target, reduction="none")
    return td[:n_rows].mean(), td[n_rows:].mean()


def bottleneck_loss(f: th.Tensor, threshold: float) -> th.Tensor:
    """Equation 3 with the threshold K: mean over the batch of max(||f(T)||^2, K), so only norms
    above K get a gradient. ``f``: ``[B, z]``."""
    return th.clamp(f.pow(2).sum(dim=-1), min=threshold).mean()


def decoder_loss(g: th.Tensor, f: th.Tensor, lengths: th.Tensor) -> th.Tensor:
    """Equation 4: mean ||g(tau_:t) - sg(f(T))||^2 over every valid prefix t = 0 .. T_b.

    :param g: ``[B, T+1, z]`` the decoder's code of every prefix (prefix t holds t transitions).
    :param f: ``[B, z]`` the encoder's code; no gradient flows into it from here.
    :param lengths: ``[B]`` transitions in each trajectory (later prefixes are padding).
    """
    n_prefix = g.shape[1]
    valid = (th.arange(n_prefix, device=g.device)[None] <= lengths[:, None]).float()
    sq = (g - f.detach()[:, None]).pow(2).sum(dim=-1)
    return (sq * valid).sum() / valid.sum()


def exploration_rewards(g: th.Tensor, f: th.Tensor, lengths: th.Tensor, reward_penalty: float) -> th.Tensor:
    """Equation 5: r_t = ||f - g(tau_:t)||^2 - ||f - g(tau_:t+1)||^2 - c for t < T_b, else 0.

    :param g: ``[B, T+1, z]`` the decoder's code of every prefix; ``f``: ``[B, z]``.
    :param lengths: ``[B]`` transitions in each trajectory.
    :param reward_penalty: c, the price of a step.
    :return: ``[B, T]``.
    """
    d = (f[:, None] - g).pow(2).sum(dim=-1)  # [B, T+1]
    r = d[:, :-1] - d[:, 1:] - reward_penalty
    valid = th.arange(r.shape[1], device=r.device)[None] < lengths[:, None]
    return r * valid


def exploration_td_loss(
    q_all: th.Tensor,
    q_target_all: th.Tensor,
    actions: th.Tensor,
    rewards: th.Tensor,
    lengths: th.Tensor,
    gamma: float,
) -> Tuple[th.Tensor, th.Tensor, th.Tensor]:
    """The exploration Q's DDQN loss over whole padded trajectories (Algorithm 1, lines 14-16).

    :param q_all: ``[B, T+1, A]`` the online Q at every state s_0 .. s_T (one fused unroll).
    :param q_target_all: ``[B, T+1, A]`` the target Q at the same states.
    :param actions: ``[B, T]``; ``rewards``: ``[B, T]`` from :func:`exploration_rewards`.
    :param lengths: ``[B]``: the exploration episode ends after step T_b - 1 (no bootstrap there).
    :return: the loss, Q of the taken actions ``[B, T]`` and the mask of valid steps ``[B, T]``.
    """
    t_max = actions.shape[1]
    q = q_all[:, :t_max].gather(2, actions[..., None]).squeeze(2)
    with th.no_grad():
        steps = th.arange(t_max, device=q.device)[None]
        last = (steps == (lengths[:, None] - 1)).float()
        target = double_dqn_targets(q_all[:, 1:], q_target_all[:, 1:], rewards, last, gamma)
        valid = (steps < lengths[:, None]).float()
    return masked_td_loss(q, target, valid), q, valid
