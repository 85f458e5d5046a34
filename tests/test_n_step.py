"""n-step TD targets: ``n_step_targets`` by hand, n = 1 as the paper's one-step targets, and DREAM's
``execution_n_step`` / ``exploration_n_step`` options against a loop over a sampled batch."""

from __future__ import annotations

from typing import List

import numpy as np
import pytest
import torch as th

from sb3_dream import DREAM
from sb3_dream.common.recurrent import double_dqn_targets, n_step_targets
from sb3_dream.dream import losses, updates
from test_dream import FAST


def loop_targets(
    q_online: th.Tensor,
    q_target: th.Tensor,
    rewards: th.Tensor,
    dones: th.Tensor,
    lengths: List[int],
    gamma: float,
    n: int,
) -> th.Tensor:
    """n-step double-DQN targets written as the textbook loop, one step at a time."""
    out = th.zeros_like(rewards)
    for b, length in enumerate(lengths):
        for t in range(length):
            total, k = 0.0, 0
            while True:
                total += gamma**k * float(rewards[b, t + k])
                last = t + k
                k += 1
                if dones[b, last] or k == n or last + 1 == length:
                    break
            if not dones[b, last]:
                best = int(q_online[b, last].argmax())
                total += gamma**k * float(q_target[b, last, best])
            out[b, t] = total
    return out


def test_n_step_targets_by_hand():
    gamma = 0.5
    # Sequence 0: 3 steps, the last terminal (the episode ends inside the window), then padding
    # whose rewards must not count; sequence 1: 5 steps without a terminal (it bootstraps at its
    # last s'), one step of padding.
    rewards = th.tensor([[1.0, 2, 4, 100, 100, 100], [1, 2, 4, 8, 16, 100]])
    dones = th.tensor([[0.0, 0, 1, 0, 0, 0], [0, 0, 0, 0, 0, 0]])
    mask = th.tensor([[1.0, 1, 1, 0, 0, 0], [1, 1, 1, 1, 1, 0]])
    q_target = th.arange(24.0).view(2, 6, 2)
    q_online = th.zeros(2, 6, 2)
    q_online[..., 1] = 1.0  # the online network picks action 1 everywhere: v = q_target[..., 1]
    v = q_target[..., 1]  # [[1, 3, 5, 7, 9, 11], [13, 15, 17, 19, 21, 23]]
    expected = th.tensor(
        [
            [1 + 0.5 * 2 + 0.25 * 4, 2 + 0.5 * 4, 4, 0, 0, 0],  # no bootstrap after the terminal step
            [
                1 + 0.5 * 2 + 0.25 * 4 + 0.125 * v[1, 2],  # gamma^3 at s_3
                2 + 0.5 * 4 + 0.25 * 8 + 0.125 * v[1, 3],
                4 + 0.5 * 8 + 0.25 * 16 + 0.125 * v[1, 4],
                8 + 0.5 * 16 + 0.25 * v[1, 4],  # cut at the sequence's end: gamma^2 at its last s'
                16 + 0.5 * v[1, 4],
                0,
            ],
        ]
    )
    got = n_step_targets(q_online, q_target, rewards, dones, mask, gamma, 3)
    th.testing.assert_close(got, expected)
    # a window longer than every sequence: sequence 0's discounted return, Monte Carlo
    assert float(n_step_targets(q_online, q_target, rewards, dones, mask, gamma, 10)[0, 0]) == 3.0


@pytest.mark.parametrize("n", [2, 3, 5])
def test_n_step_targets_match_the_loop_on_random_padded_batches(n):
    gen = th.Generator().manual_seed(n)
    lengths = [7, 1, 4, 6]
    b, t, a = len(lengths), 7, 3
    q_online, q_target = th.randn(b, t, a, generator=gen), th.randn(b, t, a, generator=gen)
    rewards = th.randn(b, t, generator=gen)
    mask = (th.arange(t)[None] < th.tensor(lengths)[:, None]).float()
    dones = th.zeros(b, t)
    dones[0, 6] = dones[2, 3] = 1.0  # sequences 0 and 2 end terminal; 1 and 3 are cut (they bootstrap)
    dones[3, 2] = 1.0  # and a terminal inside a sequence: no window reaches past it
    got = n_step_targets(q_online, q_target, rewards, dones, mask, 0.9, n)
    expected = loop_targets(q_online, q_target, rewards, dones, lengths, 0.9, n)
    th.testing.assert_close(got * mask, expected)
    assert (got[mask == 0] == 0).all()


def test_one_step_is_double_dqn_exactly():
    gen = th.Generator().manual_seed(0)
    q_online, q_target = th.randn(4, 6, 5, generator=gen), th.randn(4, 6, 5, generator=gen)
    rewards, dones = th.randn(4, 6, generator=gen), (th.rand(4, 6, generator=gen) < 0.3).float()
    mask = th.ones(4, 6)
    assert th.equal(
        n_step_targets(q_online, q_target, rewards, dones, mask, 0.99, 1),
        double_dqn_targets(q_online, q_target, rewards, dones, 0.99),
    )


@pytest.mark.parametrize("n", [0, -1, 1.5, True, "2"])
def test_n_step_targets_reject_bad_n(n):
    x = th.zeros(1, 2, 2)
    with pytest.raises(ValueError, match="n must be an integer >= 1"):
        n_step_targets(x, x, x[..., 0], x[..., 0], x[..., 0] + 1, 0.9, n)


@pytest.mark.parametrize("name", ["execution_n_step", "exploration_n_step"])
@pytest.mark.parametrize("value", [0, 2.0, True])
def test_dream_rejects_bad_n_step(name, value):
    with pytest.raises(ValueError, match=f"{name} must be an integer >= 1, got {value!r}"):
        DREAM("MetaBandit-v0", execution_sampling="episodes", **{name: value})


def test_defaults_are_one_step():
    model = DREAM("MetaBandit-v0")
    assert (model.execution_n_step, model.exploration_n_step) == (1, 1)


def test_n_step_with_sampled_transitions_is_the_loop_over_the_buffer():
    # Algorithm 1's sampling: each transition's window follows B_exe's links to the next transitions
    # of its execution episode, and its target bootstraps at the window's last s'.
    gamma, n = 0.9, 3
    model = DREAM(
        "MetaBus-v0",
        seed=2,
        gamma=gamma,
        execution_n_step=n,
        exploration_n_step=n,
        parallel_updates=False,
        policy_kwargs=dict(execution_time_input=True),  # s' at the window's end has its own step
        **FAST,
    )
    model.learn(500)
    assert model._n_updates > 0
    buffer, policy = model.replay_buffer.execution, model.policy
    replay = model.replay_buffer
    idx = np.random.default_rng(0).integers(len(buffer), size=16)  # the rows the sampler draws first
    assert not replay.stale(idx).any()  # so it draws no others
    exe, traj = replay.sample_execution(16, np.random.default_rng(0), n_step=n)
    lengths = exe.window_mask.sum(1)
    assert (lengths < n).any() and (lengths == n).any()  # some windows cut by their episode's end
    net, target_net = policy.execution_q, policy.execution_q_target
    with th.no_grad():
        z_g = policy.decoder(traj.states, traj.actions)[th.arange(16), traj.lengths]
        z_target = policy.decoder_target(traj.states, traj.actions, traj.lengths)
        q = net(exe.states, exe.instructions, z_g, exe.steps)[0].gather(1, exe.actions[:, None]).squeeze(1)
    errors = []
    for j, row in enumerate(idx):  # walk the episode's links by hand
        total, k = 0.0, 0
        while True:
            total += gamma**k * float(buffer.rewards[row])
            k += 1
            following = buffer.next_in_episode[row]
            if buffer.dones[row] or k == n or following < 0:
                break
            row = following
        assert float(lengths[j]) == k
        if not buffer.dones[row]:
            s_next = th.as_tensor(buffer.next_states[[row]])
            i, t = exe.instructions[[j]], th.as_tensor(buffer.steps[[row]] + 1)
            with th.no_grad():
                best = int(net(s_next, i, z_g[[j]], t)[0].argmax())
                total += gamma**k * float(target_net(s_next, i, z_target[[j]], t)[0][0, best])
        errors.append((float(q[j]) - total) ** 2)
    stats = updates.execution_update(model, exe, traj)
    assert stats["execution_loss_traj"] == pytest.approx(np.mean(errors), rel=1e-5)


def test_dream_n_step_losses_are_the_loop_computation(tmp_path):
    gamma, n = 0.9, 3
    model = DREAM(
        "MetaBus-v0",
        seed=0,
        gamma=gamma,
        execution_sampling="episodes",
        execution_n_step=n,
        exploration_n_step=n,
        parallel_updates=False,
        policy_kwargs=dict(execution_recurrent=True),
        **FAST,
    )
    model.learn(500)
    assert model._n_updates > 0
    model.save(tmp_path / "model.zip")
    loaded = DREAM.load(tmp_path / "model.zip")
    assert (loaded.execution_n_step, loaded.exploration_n_step) == (n, n)
    policy, rng = model.policy, np.random.default_rng(1)

    # Exploration: the loss over whole sequences of information gains (Equation 5).
    traj = model.replay_buffer.sample_trajectories(8, rng)
    g, f = updates.reward_codes(policy, traj)
    with th.no_grad():
        rewards = model.exploration_rewards(g, f, traj.lengths)
        inputs = (traj.states, traj.prev_actions, traj.prev_rewards)
        q_all, q_target_all = policy.exploration_q(*inputs)[0], policy.exploration_q_target(*inputs)[0]
    lengths = traj.lengths.tolist()
    assert max(lengths) > n  # some windows are full, some cut by the episode's end
    ends = th.zeros_like(rewards)
    for b, length in enumerate(lengths):
        ends[b, length - 1] = 1.0  # the exploration episode's end is terminal
    expected_targets = loop_targets(q_all[:, 1:], q_target_all[:, 1:], rewards, ends, lengths, gamma, n)
    q = q_all[:, :-1].gather(2, traj.actions[..., None]).squeeze(2)
    cells = [(b, t) for b, length in enumerate(lengths) for t in range(length)]
    expected = np.mean([float(q[c] - expected_targets[c]) ** 2 for c in cells])
    one_step = losses.exploration_td_loss(q_all, q_target_all, traj.actions, rewards, traj.lengths, gamma)[0]
    stats = updates.exploration_update(model, traj, g, f)  # the loss before its optimizer step
    assert stats["exploration_loss"] == pytest.approx(expected, rel=1e-5)
    assert float(one_step) != pytest.approx(expected, rel=1e-3)  # the option changes the targets

    # Execution: the loss with z = g(tau^exp) over whole execution episodes (Equation 2's RL term).
    exe, traj = model.replay_buffer.sample_execution(6, rng, episodes=True)
    net, target_net = policy.execution_q, policy.execution_q_target
    with th.no_grad():
        z_g = policy.decoder(traj.states, traj.actions)[th.arange(6), traj.lengths][exe.trajectories]
        z_target = policy.decoder_target(traj.states, traj.actions, traj.lengths)[exe.trajectories]
        inputs, next_inputs = net.transition_inputs(exe)
        q = net.q_values(inputs, z_g).gather(1, exe.actions[:, None]).squeeze(1)
        next_online = net.q_values(next_inputs, z_g)
        next_target = target_net.q_values(target_net.next_inputs(exe), z_target)
    episodes, steps = exe.trajectories.numpy(), exe.steps.numpy()
    assert steps.max() + 1 > n
    errors, one_step_errors = [], []
    for e in range(6):
        rows = np.flatnonzero(episodes == e)[np.argsort(steps[episodes == e])]
        assert (steps[rows] == np.arange(len(rows))).all()
        target = loop_targets(
            next_online[rows][None],
            next_target[rows][None],
            exe.rewards[rows][None],
            exe.dones[rows][None],
            [len(rows)],
            gamma,
            n,
        )[0]
        errors += (q[rows] - target).pow(2).tolist()
        one_step = double_dqn_targets(next_online[rows], next_target[rows], exe.rewards[rows], exe.dones[rows], gamma)
        one_step_errors += (q[rows] - one_step).pow(2).tolist()
    stats = updates.execution_update(model, exe, traj)
    assert stats["execution_loss_traj"] == pytest.approx(np.mean(errors), rel=1e-5)
    assert np.mean(one_step_errors) != pytest.approx(np.mean(errors), rel=1e-3)
