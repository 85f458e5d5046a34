"""SequenceReplayBuffer: trial sequences, chunking with burn-in, padding and masks (hand-fed data)."""

import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from sb3_dream.common.buffers import SequenceReplayBuffer

OBS_SPACE = spaces.Dict({"obs": spaces.Box(-1e6, 1e6, shape=(2,), dtype=np.float32), "flag": spaces.Discrete(2)})
ACTION_SPACE = spaces.Discrete(3)


def make_buffer(n_envs=1, **kwargs):
    kwargs.setdefault("buffer_size", 10)
    return SequenceReplayBuffer(
        kwargs.pop("buffer_size"), OBS_SPACE, ACTION_SPACE, device="cpu", n_envs=n_envs, **kwargs
    )


def obs_at(step, env=0, trial=0):
    """An observation that encodes (trial, env, step) so every stored value can be checked."""
    return np.array([1000 * trial + 100 * env + step, step], dtype=np.float32)


def feed(buffer, lengths, trial_ids=None, states=False, truncated_at=()):
    """Feed ``n_envs`` trials of the given lengths step by step (envs that finished idle in new trials)."""
    E = buffer.n_envs
    t = np.zeros(E, dtype=int)
    trial = np.array(trial_ids if trial_ids is not None else range(E))
    starts = np.ones(E, dtype=bool)
    for _ in range(max(lengths)):
        obs = {"obs": np.stack([obs_at(t[e], e, trial[e]) for e in range(E)]), "flag": (t == 0).astype(np.int64)}
        nxt = {"obs": np.stack([obs_at(t[e] + 1, e, trial[e]) for e in range(E)]), "flag": np.zeros(E, np.int64)}
        done = np.array([t[e] + 1 == lengths[e] for e in range(E)])
        infos = [{"TimeLimit.truncated": bool(done[e] and e in truncated_at)} for e in range(E)]
        lstm = None
        if states:  # a recognisable "actor state": h = c = step index
            h = np.stack([np.full(4, t[e], np.float32) for e in range(E)])[None]
            lstm = (h, h + 0.5)
        active = t < np.array(lengths)
        if not active.all():
            break  # keep the test simple: feed until the shortest trial ends
        buffer.add(obs, nxt, t % 3, (t + 1).astype(np.float32), done, infos, episode_start=starts, lstm_states=lstm)
        starts = done
        t += 1


def test_whole_trials_become_padded_sequences():
    buf = make_buffer(n_envs=2, sequence_length=8)
    feed(buf, [5, 5])  # both envs finish a 5-step trial
    assert buf.size() == 2
    np.testing.assert_array_equal(buf.lengths[:2], [5, 5])
    for row in range(2):
        env = int(buf.observations["obs"][row, 0, 0]) // 100
        # T + 1 observations: step t and the one its transition led to
        np.testing.assert_array_equal(buf.observations["obs"][row, :6, 1], np.arange(6))
        assert buf.observations["obs"][row, 0, 0] == 100 * env
        np.testing.assert_array_equal(buf.actions[row, :5], np.arange(5) % 3)
        np.testing.assert_array_equal(buf.rewards[row, :5], np.arange(1, 6))
        np.testing.assert_array_equal(buf.dones[row, :5], [0, 0, 0, 0, 1])
        # padding is zeros
        assert not buf.observations["obs"][row, 6:].any() and not buf.actions[row, 5:].any()
        assert not buf.rewards[row, 5:].any() and not buf.dones[row, 5:].any()


def test_sample_trims_to_longest_and_masks_padding():
    buf = make_buffer(n_envs=1, sequence_length=10)
    feed(buf, [3], trial_ids=[0])
    feed(buf, [6], trial_ids=[1])
    batch = buf._get_samples(np.array([0, 1, 0]))
    assert batch.observations["obs"].shape == (3, 7, 2)  # T = 6, T + 1 observations
    assert batch.observations["flag"].shape == (3, 7)
    assert batch.actions.shape == batch.rewards.shape == batch.dones.shape == batch.mask.shape == (3, 6)
    assert batch.actions.dtype == th.long
    expected = th.tensor([[1, 1, 1, 0, 0, 0], [1, 1, 1, 1, 1, 1], [1, 1, 1, 0, 0, 0]], dtype=th.float32)
    assert th.equal(batch.mask, expected)
    assert th.equal(batch.lengths, th.tensor([3, 6, 3]))
    assert batch.lstm_states is None and batch.burn_in_mask is None
    sampled = buf.sample(16)
    assert sampled.actions.shape[0] == 16 and sampled.actions.shape[1] in (3, 6)


def test_long_trials_are_cut_into_consecutive_chunks():
    buf = make_buffer(sequence_length=3)
    feed(buf, [7])
    assert buf.size() == 3
    np.testing.assert_array_equal(buf.lengths[:3], [3, 3, 1])
    np.testing.assert_array_equal(buf.train_from[:3], [0, 0, 0])
    # chunk k holds steps 3k .. and the observation after its last step
    np.testing.assert_array_equal(buf.observations["obs"][0, :, 1], [0, 1, 2, 3])
    np.testing.assert_array_equal(buf.observations["obs"][1, :, 1], [3, 4, 5, 6])
    np.testing.assert_array_equal(buf.observations["obs"][2, :2, 1], [6, 7])
    np.testing.assert_array_equal(buf.dones[:3].sum(axis=1), [0, 0, 1])


def test_burn_in_overlap_mask_and_stored_states():
    buf = make_buffer(sequence_length=4, burn_in=2, lstm_state_shape=(1, 4))
    feed(buf, [8], states=True)
    # chunks start at steps 0, 2, 4 (each overlaps the previous one by 2 burn-in steps)
    assert buf.size() == 3
    np.testing.assert_array_equal(buf.lengths[:3], [4, 4, 4])
    np.testing.assert_array_equal(buf.train_from[:3], [0, 2, 2])
    for row, first in enumerate([0, 2, 4]):
        np.testing.assert_array_equal(buf.observations["obs"][row, :, 1], np.arange(first, first + 5))
        np.testing.assert_array_equal(buf.actions[row, :4], np.arange(first, first + 4) % 3)
        # stored state = the actor's state at the chunk's first step
        assert np.all(buf.states[row, 0] == first) and np.all(buf.states[row, 1] == first + 0.5)
    batch = buf._get_samples(np.array([0, 1, 2]))
    assert th.equal(batch.mask[0], th.ones(4)) and th.equal(batch.mask[1], th.tensor([0.0, 0, 1, 1]))
    assert th.equal(batch.burn_in_mask, th.tensor([False, True, True]))
    assert batch.lstm_states[0].shape == (1, 3, 4)
    assert th.all(batch.lstm_states[0][0, 1] == 2) and th.all(batch.lstm_states[1][0, 2] == 4.5)
    # every step is trained exactly once over the chunks
    trained = [s for row, first in enumerate([0, 2, 4]) for s in range(first, first + 4) if batch.mask[row, s - first]]
    assert sorted(trained) == list(range(8))


def test_interrupted_trial_is_committed_and_timeouts_bootstrap():
    buf = make_buffer(sequence_length=10)
    feed(buf, [4], truncated_at=(0,))
    assert buf.dones[0, 3] == 0  # a time-limit end is not terminal: the target bootstraps
    # a trial cut short by a reset (episode_start with a half-filled staging row) is kept as it is
    obs = {"obs": obs_at(0)[None], "flag": np.ones(1, np.int64)}
    nxt = {"obs": obs_at(1)[None], "flag": np.zeros(1, np.int64)}
    buf.add(obs, nxt, np.array([1]), np.array([0.0]), np.array([False]), [{}], episode_start=np.array([True]))
    buf.add(obs, nxt, np.array([1]), np.array([0.0]), np.array([False]), [{}], episode_start=np.array([True]))
    assert buf.size() == 2 and buf.lengths[1] == 1 and buf.dones[1, 0] == 0


def test_circular_overwrite_counts_sequences():
    buf = make_buffer(buffer_size=3, sequence_length=5)
    for trial in range(5):
        feed(buf, [2], trial_ids=[trial])
    assert buf.full and buf.size() == 3 and buf.pos == 2
    # rows hold trials 3, 4, 2 (the oldest ones were overwritten)
    np.testing.assert_array_equal(buf.observations["obs"][:3, 0, 0] // 1000, [3, 4, 2])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(sequence_length=0), "sequence_length"),
        (dict(sequence_length=4, burn_in=4), "burn_in"),
        (dict(buffer_size=0), "buffer_size"),
    ],
)
def test_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_buffer(**kwargs)


def test_bad_spaces():
    with pytest.raises(ValueError, match="Dict"):
        SequenceReplayBuffer(4, spaces.Box(0, 1, (2,)), ACTION_SPACE, device="cpu")
    with pytest.raises(ValueError, match="Discrete"):
        SequenceReplayBuffer(4, OBS_SPACE, spaces.Box(-1, 1, (2,)), device="cpu")
    with pytest.raises(RuntimeError, match="no complete sequence"):
        make_buffer().sample(2)
