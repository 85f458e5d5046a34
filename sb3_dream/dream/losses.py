"""DREAM's objectives as pure functions of network outputs (paper, Section 4 and Appendix A).

* :func:`execution_td_losses`: the execution Q's double-DQN losses (Equation 2's RL term), one for
  z from the decoder and one for z from the encoder, or one of them (``execution_z="alternate"``)
  (one-step targets, the paper's, or n-step: over whole episodes, :func:`execution_n_step_targets`,
  or over each sampled transition's window, :func:`window_n_step_targets`);
* :func:`bottleneck_loss`: the information bottleneck on f (Equation 3, with the authors'
  threshold K);
* :func:`decoder_loss`: the decoder's regression of every prefix g(tau_:t) toward f(T) (Equation 4);
* :func:`exploration_rewards`: the information-gain reward of each exploration step (Equation 5);
* :func:`exploration_td_loss`: the recurrent exploration Q's double-DQN loss on those rewards
  (one-step targets, the paper's, or n-step).

Shapes: B trajectories (or transitions), T transitions per padded trajectory, z the code's size,
A actions.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch as th
from torch.nn import functional as F

from sb3_dream.common.recurrent import double_dqn_targets, masked_td_loss, n_step_targets


def execution_td_losses(
    q: th.Tensor,
    next_q_online: th.Tensor,
    next_q_target: th.Tensor,
    rewards: th.Tensor,
    dones: th.Tensor,
    gamma: float,
    n_rows: int,
    n_step: int = 1,
    episodes: Optional[th.Tensor] = None,
    steps: Optional[th.Tensor] = None,
    windows: Optional[Tuple[th.Tensor, th.Tensor, th.Tensor]] = None,
) -> Tuple[th.Tensor, ...]:
    """Equation 2's DDQN losses on one batch of execution transitions evaluated once per z source.

    :param q: ``[kB]`` Q(s, a, z) of the taken actions, k copies of the batch, one per z source:
        with both of Algorithm 1's, rows ``[0, B)`` with z = g(tau^exp) and rows ``[B, 2B)`` with
        z ~ F(z | T); with ``execution_z="alternate"`` one copy with one of them.
    :param next_q_online: ``[kB, A]`` the online Q at s' (picks the next action).
    :param next_q_target: ``[kB, A]`` the target Q at s' (evaluates it).
    :param rewards: ``[kB]``; ``dones``: ``[kB]``, 1 where s' is terminal.
    :param n_rows: B.
    :param n_step: 1 (the paper's one-step targets) or n > 1: n-step targets, from the batch's
        whole episodes (``episodes`` and ``steps``, :func:`execution_n_step_targets`) or from each
        sampled transition's window (``windows``, :func:`window_n_step_targets`).
    :param episodes: ``[B]``, for a batch of whole episodes: the episode of each transition
        (0 .. E-1, ``ExecutionBatch.trajectories``).
    :param steps: ``[B]``, for a batch of whole episodes: each transition's step within its episode.
    :param windows: for a batch of single transitions, ``[B, n]`` each: the rewards, terminals and
        validity of each transition's window (``ExecutionBatch.window_*``); s' is then the window's
        last state.
    :return: the mean squared TD error of each copy's rows, in the copies' order.
    """
    copies = len(q) // n_rows
    with th.no_grad():
        if n_step == 1:
            target = double_dqn_targets(next_q_online, next_q_target, rewards, dones, gamma)
        elif windows is not None:
            target = window_n_step_targets(
                next_q_online, next_q_target, *(w.repeat(copies, 1) for w in windows), gamma, n_step
            )
        else:
            if episodes is None or steps is None:
                raise ValueError("n-step execution targets need each transition's episode and step, or its window")
            # The copies' rows hold copies of the batch's episodes: E .. 2E-1 for the second.
            n_episodes = int(episodes.max()) + 1
            every = th.cat([episodes + c * n_episodes for c in range(copies)])
            target = execution_n_step_targets(
                next_q_online, next_q_target, rewards, dones, every, steps.repeat(copies), gamma, n_step
            )
    td = F.mse_loss(q, target, reduction="none")
    return tuple(rows.mean() for rows in td.split(n_rows))


def execution_n_step_targets(
    next_q_online: th.Tensor,
    next_q_target: th.Tensor,
    rewards: th.Tensor,
    dones: th.Tensor,
    episodes: th.Tensor,
    steps: th.Tensor,
    gamma: float,
    n_step: int,
) -> th.Tensor:
    """n-step double-DQN targets (:func:`~sb3_dream.common.recurrent.n_step_targets`) of execution
    transitions that come as whole episodes in any order.

    Each transition j is step ``steps[j]`` of episode ``episodes[j]``; every episode's steps are
    0 .. L_e - 1 (``execution_sampling="episodes"``). The rows are laid out as one padded
    ``[E, L]`` sequence per episode, the targets computed there, and read back per row.

    :param next_q_online: ``[N, A]``; ``next_q_target``: ``[N, A]``; ``rewards``, ``dones``: ``[N]``.
    :return: ``[N]``.
    """
    n_episodes, length = int(episodes.max()) + 1, int(steps.max()) + 1
    cell = episodes * length + steps  # each row's place in the [E, L] layout

    def lay_out(values: th.Tensor) -> th.Tensor:
        grid = values.new_zeros((n_episodes * length, *values.shape[1:]))
        return grid.index_copy(0, cell, values).view(n_episodes, length, *values.shape[1:])

    mask = lay_out(th.ones_like(rewards))
    targets = n_step_targets(
        lay_out(next_q_online), lay_out(next_q_target), lay_out(rewards), lay_out(dones), mask, gamma, n_step
    )
    return targets.reshape(-1)[cell]


def window_n_step_targets(
    next_q_online: th.Tensor,
    next_q_target: th.Tensor,
    window_rewards: th.Tensor,
    window_dones: th.Tensor,
    window_mask: th.Tensor,
    gamma: float,
    n_step: int,
) -> th.Tensor:
    """n-step double-DQN targets (:func:`~sb3_dream.common.recurrent.n_step_targets`) of single
    transitions, each sampled with the ones after it in its episode (its window).

    :param next_q_online: ``[N, A]`` the online Q at each window's last state, where it bootstraps;
        ``next_q_target``: ``[N, A]`` the target Q there.
    :param window_rewards: ``[N, n]``; ``window_dones``: ``[N, n]``; ``window_mask``: ``[N, n]``, 1 on
        the window's transitions (a prefix: it stops after a terminal or the last stored one).
    :return: ``[N]``, the target of each window's first transition.
    """
    n_rows, width = window_rewards.shape
    end = window_mask.sum(dim=1).long() - 1  # the window's last transition: the bootstrap's column
    rows = th.arange(n_rows, device=end.device)

    def at_end(values: th.Tensor) -> th.Tensor:  # the Q-values in the end's column; no other is read
        grid = values.new_zeros(n_rows, width, values.shape[-1])
        grid[rows, end] = values
        return grid

    targets = n_step_targets(
        at_end(next_q_online), at_end(next_q_target), window_rewards, window_dones, window_mask, gamma, n_step
    )
    return targets[:, 0]


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
    n_step: int = 1,
) -> Tuple[th.Tensor, th.Tensor, th.Tensor]:
    """The exploration Q's DDQN loss over whole padded trajectories (Algorithm 1, lines 14-16).

    :param q_all: ``[B, T+1, A]`` the online Q at every state s_0 .. s_T (one fused unroll).
    :param q_target_all: ``[B, T+1, A]`` the target Q at the same states.
    :param actions: ``[B, T]``; ``rewards``: ``[B, T]`` from :func:`exploration_rewards`.
    :param lengths: ``[B]``: the exploration episode ends after step T_b - 1 (no bootstrap there).
    :param n_step: 1 (the paper's one-step targets) or n > 1: each target sums the next n
        information gains before bootstrapping (:func:`~sb3_dream.common.recurrent.n_step_targets`).
    :return: the loss, Q of the taken actions ``[B, T]`` and the mask of valid steps ``[B, T]``.
    """
    t_max = actions.shape[1]
    q = q_all[:, :t_max].gather(2, actions[..., None]).squeeze(2)
    with th.no_grad():
        steps = th.arange(t_max, device=q.device)[None]
        last = (steps == (lengths[:, None] - 1)).float()
        valid = (steps < lengths[:, None]).float()
        # n_step_targets with n = 1 is double_dqn_targets itself: the paper's targets, bit for bit.
        target = n_step_targets(q_all[:, 1:], q_target_all[:, 1:], rewards, last, valid, gamma, n_step)
    return masked_td_loss(q, target, valid), q, valid
