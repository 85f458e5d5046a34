"""Recurrent Q-learning parts shared by RL2DQN and DREAM's exploration policy.

* :class:`DuelingHead`: Q = V + A - mean_a A (Wang et al., 2016), the head of every Q-network of
  the paper.
* :class:`LinearEpsilonSchedule`: epsilon-greedy rate decayed linearly over a number of env steps
  (paper: 1 -> 0.01 over 500k steps for RL², 250k per policy for DREAM).
* LSTM state helpers: zero states, resets at trial starts, a fused ``[B, T]`` unroll with an
  R2D2-style burn-in whose gradient is cut (:func:`unroll_lstm`).
* :func:`double_dqn_targets` and :func:`masked_td_loss`: double-DQN targets over padded sequences;
  :func:`n_step_targets`: their n-step form over the same padded sequences.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch as th
from torch import nn
from torch.nn import functional as F

from dream_envs.checks import check_positive_int

LSTMStates = Tuple[th.Tensor, th.Tensor]
TD_LOSSES = ("mse", "huber")


class DuelingHead(nn.Module):
    """Two linear heads, value V (1 unit) and advantage A (``n_actions`` units): Q = V + A - mean A."""

    def __init__(self, in_dim: int, n_actions: int) -> None:
        super().__init__()
        self.value = nn.Linear(in_dim, 1)
        self.advantage = nn.Linear(in_dim, n_actions)

    def forward(self, x: th.Tensor) -> th.Tensor:
        adv = self.advantage(x)
        return self.value(x) + adv - adv.mean(dim=-1, keepdim=True)


class LinearEpsilonSchedule:
    """Epsilon decayed linearly from ``initial`` to ``final`` over ``steps`` env steps, then constant.

    Unlike SB3's DQN (a fraction of the ``learn`` call's total), the paper counts the decay in
    absolute env steps, so a run's schedule does not depend on how long it is.
    """

    def __init__(
        self,
        initial: float = 1.0,
        final: float = 0.01,
        steps: int = 500_000,
        names: Tuple[str, str, str] = ("exploration_initial_eps", "exploration_final_eps", "exploration_steps"),
    ) -> None:
        """``names``: the arguments the three values came from, for the error messages."""
        for name, value in zip(names[:2], (initial, final)):
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value!r}")
        if steps < 0:
            raise ValueError(f"{names[2]} must be >= 0, got {steps!r}")
        self.initial, self.final, self.steps = float(initial), float(final), int(steps)

    def __call__(self, num_timesteps: int) -> float:
        if self.steps == 0 or num_timesteps >= self.steps:
            return self.final
        return self.initial + (self.final - self.initial) * num_timesteps / self.steps


def zero_lstm_states(num_layers: int, batch: int, hidden: int, device: th.device | str = "cpu") -> LSTMStates:
    """``(h, c)`` of zeros, each ``[num_layers, batch, hidden]`` (the initial state of a trial)."""
    h = th.zeros(num_layers, batch, hidden, device=device)
    return h, th.zeros_like(h)


def reset_lstm_states(states: LSTMStates, episode_start: th.Tensor) -> LSTMStates:
    """Zero the states of the batch entries whose ``episode_start`` (``[batch]``) is set."""
    keep = (1.0 - episode_start.float()).view(1, -1, 1)
    return states[0] * keep, states[1] * keep


def unroll_lstm(
    lstm: nn.LSTM,
    x: th.Tensor,
    states: LSTMStates,
    burn_in: int = 0,
    burn_in_mask: Optional[th.Tensor] = None,
) -> tuple[th.Tensor, LSTMStates]:
    """Run a ``batch_first`` LSTM fused over ``x`` (``[B, T, F]``) from ``states``.

    With ``burn_in > 0`` and a ``burn_in_mask`` (``[B]`` bool), the unroll is split after ``burn_in``
    steps and the state of the masked sequences is detached there, so their first ``burn_in``
    steps only warm the state up (R2D2's burn-in: no gradient flows into them). Sequences outside
    the mask keep the gradient through the whole unroll. Padding after a sequence's end needs no
    packing: the LSTM is causal, so padded steps never change the outputs of earlier steps.
    """
    if burn_in <= 0 or burn_in_mask is None or burn_in >= x.shape[1]:
        return lstm(x, states)
    head, mid = lstm(x[:, :burn_in], states)
    cut = burn_in_mask.view(1, -1, 1)
    mid = (th.where(cut, mid[0].detach(), mid[0]), th.where(cut, mid[1].detach(), mid[1]))
    tail, last = lstm(x[:, burn_in:], mid)
    return th.cat([head, tail], dim=1), last


def double_dqn_targets(
    next_q_online: th.Tensor,
    next_q_target: th.Tensor,
    rewards: th.Tensor,
    dones: th.Tensor,
    gamma: float,
) -> th.Tensor:
    """Double-DQN targets r + gamma (1 - done) Q_target(s', argmax_a Q_online(s', a)).

    :param next_q_online: ``[..., A]`` online Q-values of the next observations (picks the action).
    :param next_q_target: ``[..., A]`` target-network Q-values of the next observations (evaluates it).
    :param rewards: ``[...]``.
    :param dones: ``[...]``, 1 where the next observation is terminal (no bootstrap).
    """
    best = next_q_online.argmax(dim=-1, keepdim=True)
    next_value = next_q_target.gather(-1, best).squeeze(-1)
    return rewards + gamma * (1.0 - dones) * next_value


def n_step_targets(
    next_q_online: th.Tensor,
    next_q_target: th.Tensor,
    rewards: th.Tensor,
    dones: th.Tensor,
    mask: th.Tensor,
    gamma: float,
    n: int,
) -> th.Tensor:
    """n-step double-DQN targets over padded sequences (n = 1: exactly :func:`double_dqn_targets`).

    Step t of a sequence is the transition (s_t, a_t, r_t, s_{t+1}). Its target sums the rewards of
    the next m_t steps and bootstraps once, at s_{t+m_t}, with the double-DQN value:

        y_t = sum_{k=0}^{m_t-1} gamma^k r_{t+k}
              + gamma^{m_t} (1 - d_{t+m_t-1}) Q_target(s_{t+m_t}, argmax_a Q_online(s_{t+m_t}, a)),

    where the window is cut short at the sequence's end: m_t is the smallest of n, the steps from t
    to the first terminal one (d = 1) included, and the valid steps left from t. A window ending on
    a terminal step adds no bootstrap; one ending at the last valid step without a terminal (a time
    limit that bootstraps, an episode still being collected) bootstraps at that step's s'. Padding
    (``mask`` 0) gets a target of 0, to be masked out of the loss. The Q-values are the ones the
    one-step targets take (at every s_{t+1}), so a longer n costs no further network pass.

    :param next_q_online: ``[B, T, A]`` online Q-values at s_{t+1} of each step (pick the action).
    :param next_q_target: ``[B, T, A]`` target-network Q-values at s_{t+1} (evaluate it).
    :param rewards: ``[B, T]``.
    :param dones: ``[B, T]``, 1 where s_{t+1} is terminal.
    :param mask: ``[B, T]``, 1 on each sequence's valid steps, a prefix of it (padding after).
    :param n: steps summed before bootstrapping, an integer >= 1.
    :return: ``[B, T]``.
    """
    n = check_positive_int("n", n)
    if n == 1:  # the one-step target, the same arithmetic bit for bit
        return double_dqn_targets(next_q_online, next_q_target, rewards, dones, gamma)
    best = next_q_online.argmax(dim=-1, keepdim=True)
    bootstrap = next_q_target.gather(-1, best).squeeze(-1) * (1.0 - dones)  # the value of s_{t+1}, 0 if terminal
    valid = mask.to(rewards.dtype)
    t_max = rewards.shape[-1]
    # Zeros after the last step: a window running past it meets invalid steps and stops there.
    pad = lambda x: F.pad(x, (0, n))  # noqa: E731
    r, d, m, v = pad(rewards * valid), pad(dones.to(rewards.dtype)), pad(valid), pad(bootstrap)
    returns, tail = th.zeros_like(rewards), th.zeros_like(rewards)
    alive = valid  # 1 where steps t .. t+k-1 are valid and non-terminal and step t+k is valid
    for k in range(n):
        returns = returns + gamma**k * alive * r[..., k : k + t_max]
        if k < n - 1:
            following = alive * (1.0 - d[..., k : k + t_max]) * m[..., k + 1 : k + 1 + t_max]
        else:
            following = th.zeros_like(alive)
        ends = alive - following  # 1 where the window's last step is t+k: bootstrap at s_{t+k+1}
        tail = tail + gamma ** (k + 1) * ends * v[..., k : k + t_max]
        alive = following
    return returns + tail


def masked_td_loss(q: th.Tensor, targets: th.Tensor, mask: th.Tensor, kind: str = "mse") -> th.Tensor:
    """Mean TD loss over the steps where ``mask`` is 1 (padding and burn-in excluded).

    :param kind: ``"mse"`` (squared TD error, what the authors ran) or ``"huber"`` (SB3 DQN's).
    """
    if kind == "mse":
        err = F.mse_loss(q, targets, reduction="none")
    elif kind == "huber":
        err = F.smooth_l1_loss(q, targets, reduction="none")
    else:
        raise ValueError(f"td_loss={kind!r} is not valid; accepted values: {', '.join(map(repr, TD_LOSSES))}")
    mask = mask.float()
    return (err * mask).sum() / mask.sum().clamp(min=1.0)
