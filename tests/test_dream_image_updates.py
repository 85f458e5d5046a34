"""DREAM's updates on image states embed each distinct frame once per network pass: the same
losses, gradients and steps as embedding every frame where it appears (to float rounding).

A small synthetic image trial env (no OpenGL): 32 x 32 frames of a one-dimensional corridor, so
blocked moves and "stay" repeat frames, and the end-episode action makes explorations of
different lengths (padded batches).
"""

from __future__ import annotations

import copy
from typing import Dict, List, Tuple

import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from dream_envs.trial_env import TrialEnv
from sb3_dream import DREAM
from sb3_dream.common.embedders import (
    DistinctFrames,
    ImageEmbedder,
    distinct_frame_index,
    distinct_frame_index_exact,
)
from sb3_dream.dream import updates
from sb3_dream.dream.buffers import ExecutionBuffer, ExplorationBuffer


class CorridorImageEnv(TrialEnv):
    """A 5-cell corridor seen as a 32 x 32 RGB frame: the agent's cell lit in red, the problem's
    cue (0 or 1) lit in green while the agent stands on cell 4 during exploration.

    Actions: 0 left, 1 right, 2 stay, 3 end the inner episode. Execution: reaching the cell
    ``1 + 2 * problem`` earns 1 and ends the episode. Walls block moves at both ends.
    """

    def __init__(self, **kwargs) -> None:
        super().__init__(
            inner_observation_space=spaces.Box(0, 255, (32, 32, 3), np.uint8),
            instruction_nvec=[2],
            n_actions=4,
            end_episode_action=3,
            horizon=6,
            **kwargs,
        )

    n_problems = 2  # type: ignore[assignment]

    def _split_problem_ids(self, split: str) -> np.ndarray:
        return np.arange(2)

    def _sample_instruction(self, problem_id: int, split: str) -> np.ndarray:
        return np.array([1])

    def _set_problem(self, problem_id: int) -> None:
        self.cue = problem_id

    def _frame(self) -> np.ndarray:
        img = np.zeros((32, 32, 3), np.uint8)
        img[:8, 6 * self.cell : 6 * self.cell + 6, 0] = 255
        if self.instruction is None and self.cell == 4:
            img[16:, 16 * self.cue : 16 * self.cue + 16, 1] = 200
        return img

    def _inner_reset(self) -> np.ndarray:
        self.cell = 2
        return self._frame()

    def _inner_step(self, action: int) -> Tuple[np.ndarray, float, bool]:
        if action in (0, 1):
            self.cell = int(np.clip(self.cell + (1 if action == 1 else -1), 0, 4))
        done = self.instruction is not None and self.cell == 1 + 2 * self.cue
        return self._frame(), float(done), done

    def _render_frame(self) -> np.ndarray:
        return self._frame()


SMALL = dict(
    exploration_learning_starts=5,
    execution_learning_starts=5,
    buffer_size=50,
    execution_buffer_size=500,
    batch_size=8,
    parallel_updates=False,
)


def _model(**kwargs) -> DREAM:
    model = DREAM(CorridorImageEnv(), seed=0, **{**SMALL, **kwargs})
    model.learn(250)
    return model


def _set_distinct_frames(model: DREAM, on: bool) -> None:
    model.replay_buffer.exploration.distinct_frames = on
    model.replay_buffer.execution.distinct_frames = on


def _one_update(model: DREAM, seed: int, distinct: bool) -> Tuple[Dict[str, float], List[th.Tensor], List[th.Tensor]]:
    """One exploration and one execution update (sequential) from the model's current state:
    the stats, every gradient before the steps and every parameter after them."""
    _set_distinct_frames(model, distinct)
    rng = np.random.default_rng(seed)
    buffers, policy = model.replay_buffer, model.policy
    explored = buffers.sample_trajectories(model.batch_size, rng)
    exe, traj = buffers.sample_execution(model.batch_size, rng, episodes=model.execution_sampling == "episodes")
    assert (explored.frames is not None) == distinct and (exe.state_frames is not None) == distinct
    th.manual_seed(seed)  # the z sampled from F
    stats = updates.exploration_update(model, explored, *updates.reward_codes(policy, explored))
    grads: List[th.Tensor] = []

    def keep_grads() -> None:
        grads.extend(p.grad.clone() for p in policy.optimizer.param_groups[0]["params"] if p.grad is not None)

    stats.update(updates.execution_update(model, exe, traj, before_step=keep_grads))
    grads.extend(p.grad.clone() for p in policy.exploration_q.parameters() if p.grad is not None)
    params = [p.detach().clone() for p in policy.parameters()]
    return stats, grads, params


def _close(a: th.Tensor, b: th.Tensor, rtol: float = 1e-4) -> bool:
    return bool((a - b).abs().max() <= rtol * b.abs().max() + 1e-7)


@pytest.mark.parametrize(
    "kwargs",
    [
        {},
        {"execution_sampling": "episodes"},
        {"execution_sampling": "episodes", "policy_kwargs": {"execution_recurrent": True}},
        {"execution_target_z": "encoder"},
    ],
    ids=["transitions", "episodes", "recurrent-execution", "encoder-target"],
)
def test_distinct_frame_updates_equal_embedding_every_frame(kwargs):
    model = _model(**kwargs)
    policy = model.policy
    optimizers = (policy.optimizer, policy.exploration_optimizer)
    saved = copy.deepcopy((policy.state_dict(), *(optimizer.state_dict() for optimizer in optimizers)))

    def restore() -> None:  # copies: the optimizers keep the loaded state tensors and step them in place
        weights, execution, exploration = copy.deepcopy(saved)
        policy.load_state_dict(weights)
        policy.optimizer.load_state_dict(execution)
        policy.exploration_optimizer.load_state_dict(exploration)

    for seed in (1, 2):
        restore()
        every = _one_update(model, seed, distinct=False)
        restore()
        distinct = _one_update(model, seed, distinct=True)
        assert distinct[0].keys() == every[0].keys()
        for key in every[0]:
            assert distinct[0][key] == pytest.approx(every[0][key], rel=1e-5, abs=1e-7), key
        assert len(distinct[1]) == len(every[1]) and len(distinct[2]) == len(every[2])
        # equal up to float summation order: a repeated frame's gradient is summed before the CNN's backward
        assert all(_close(g, g_ref) for g, g_ref in zip(distinct[1], every[1]))
        # Adam moves each weight by about the learning rate (1e-4) at most: the steps agree to 1% of that
        assert max((p - p_ref).abs().max().item() for p, p_ref in zip(distinct[2], every[2])) <= 1e-6


def test_batches_hold_fewer_frames_than_positions_and_the_cnns_see_only_those():
    model = _model()
    rng = np.random.default_rng(0)
    explored = model.replay_buffer.sample_trajectories(model.batch_size, rng)
    frames = explored.frames
    positions = explored.states.shape[0] * explored.states.shape[1]
    valid = th.arange(explored.states.shape[1])[None] <= explored.lengths[:, None]
    # padding holds no frame; each held frame is the position's state, byte for byte
    assert ((frames.index == len(frames.frames)) == ~valid).all()
    assert th.equal(frames.frames[frames.index[valid]], explored.states[valid])
    assert len(frames.frames) < int(valid.sum()) < positions  # repeats (stays, walls) and padding

    seen: List[int] = []
    hooks = [
        getattr(model.policy, name).state_embed.cnn.register_forward_hook(lambda m, i, o: seen.append(len(i[0])))
        for name in ("decoder", "exploration_q", "exploration_q_target")
    ]
    updates.exploration_update(model, explored, *updates.reward_codes(model.policy, explored))
    for hook in hooks:
        hook.remove()
    assert seen == [len(frames.frames)] * 3


def test_execution_batch_lays_out_s_then_shared_then_next_frames():
    model = _model()
    exe, _ = model.replay_buffer.sample_execution(16, np.random.default_rng(3))
    current, following, shared = exe.state_frames, exe.next_state_frames, exe.shared_frames
    assert th.equal(current.frames[current.index], exe.states)
    assert th.equal(following.frames[following.index], exe.next_states)
    assert shared > 0  # some s' is some s (blocked moves and stays)
    assert th.equal(current.frames[len(current.frames) - shared :], following.frames[:shared])
    union = th.cat([current.frames, following.frames[shared:]]).flatten(1)
    assert len(th.unique(union, dim=0)) == len(union)  # each frame once


def test_embed_pair_equals_two_passes_and_reuses_the_shared_frames():
    th.manual_seed(0)
    emb = ImageEmbedder(spaces.Box(0, 255, (3, 32, 32), np.uint8))
    frames = th.randint(0, 256, (7, 3, 32, 32), dtype=th.uint8)
    current = DistinctFrames(frames[:5], th.tensor([0, 1, 2, 3, 4, 4, 1]))
    following = DistinctFrames(frames[3:], th.tensor([0, 1, 2, 3, 3, 0, 2]))  # frames 3, 4 shared
    calls: List[int] = []
    handle = emb.cnn.register_forward_hook(lambda m, i, o: calls.append(len(i[0])))
    e_current, e_following = emb.embed_pair(current, following, shared=2)
    handle.remove()
    assert calls == [5, 2] and e_current.requires_grad and not e_following.requires_grad
    th.testing.assert_close(e_current, emb(frames[:5][current.index]), rtol=1e-5, atol=1e-6)
    th.testing.assert_close(e_following, emb(frames[3:][following.index]), rtol=1e-5, atol=1e-6)
    padded = emb(DistinctFrames(frames[:2], th.tensor([[0, 1, 2], [1, 2, 2]])))
    assert padded.shape == (2, 3, 128) and (padded[0, 2] == 0).all() and (padded[1, 1:] == 0).all()


def test_distinct_frame_index_is_exact_and_in_order_of_appearance():
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (6, 3, 8, 8), dtype=np.uint8)
    base[5] = base[4]
    base[5, 2, 7, 7] ^= 1  # differs from frame 4 in one bit of its last byte
    frames = base[[3, 3, 0, 4, 5, 0, 1, 3]]
    for find in (distinct_frame_index, distinct_frame_index_exact):
        first, inverse = find(frames)
        np.testing.assert_array_equal(first, [0, 2, 3, 4, 6])
        np.testing.assert_array_equal(inverse, [0, 0, 1, 2, 3, 1, 4, 0])
        np.testing.assert_array_equal(frames[first[inverse]], frames)
    odd = rng.integers(0, 256, (4, 3, 5), dtype=np.uint8)[[0, 1, 0, 2]]  # not a whole number of 8-byte words
    first, inverse = distinct_frame_index(odd)
    np.testing.assert_array_equal(inverse, [0, 1, 0, 2])


def test_grid_states_carry_no_frames():
    buffer = ExplorationBuffer(4, 3, spaces.MultiDiscrete([3, 3]), 1, th.device("cpu"))
    buffer.add(np.zeros((4, 2)), np.zeros(3), np.zeros(4), np.zeros(4), 2, np.zeros(1))
    assert buffer.get(np.array([0])).frames is None and not buffer.image_states
    obs = spaces.Dict({"obs": spaces.Box(0, 255, (32, 32, 3), np.uint8), "instruction": spaces.MultiDiscrete([2])})
    assert ExecutionBuffer(4, obs, th.device("cpu")).image_states
