"""DREAM's two replay buffers (Algorithm 1, lines 1, 8-9 and 13).

* :class:`ExplorationBuffer` (B_exp): whole exploration trajectories tau^exp = (s_0, a_0, ..., s_T)
  with their problem, in preallocated arrays, one trajectory per slot (the paper's "sequences";
  capacity 16000). Exploration Q-learning samples whole padded sequences from it, and the
  decoder reads its trajectories.
* :class:`ExecutionBuffer` (B_exe): execution transitions (s, i, a, r, s', done) that keep a
  reference (slot and generation) to their trial's exploration trajectory in B_exp (capacity
  100K). A transition whose trajectory was overwritten is never sampled. Each transition also
  links to the next one of its execution episode, so whole episodes can be sampled
  (``DREAM(execution_sampling="episodes")``), or a transition with the ones after it (n-step
  targets, ``DREAM(execution_n_step=n)``).

Both are plain numpy ring buffers, so pickling them (``save_replay_buffer``) saves everything.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, NamedTuple, Optional, Tuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space

from sb3_dream.common.embedders import DistinctFrames, distinct_frame_index


class TrajectoryBatch(NamedTuple):
    states: th.Tensor  # [B, T+1, ...] s_0 .. s_T (padded after the trajectory's end)
    actions: th.Tensor  # [B, T] a_0 .. a_{T-1}
    prev_actions: th.Tensor  # [B, T+1] the observation's prev_action at each s_t
    prev_rewards: th.Tensor  # [B, T+1, 1]
    lengths: th.Tensor  # [B] number of transitions T_b
    problem_features: th.Tensor  # [B, P]
    # image states: each distinct frame of s_0 .. s_{T_b} once, and which one each position holds
    # (padding after s_{T_b} holds none); what the networks embed in updates (None otherwise)
    frames: Optional[DistinctFrames] = None


class ExecutionBatch(NamedTuple):
    states: th.Tensor
    instructions: th.Tensor
    actions: th.Tensor  # [B]
    rewards: th.Tensor  # [B]
    next_states: th.Tensor
    dones: th.Tensor  # [B] 1.0 where s' is terminal (not a time limit)
    slots: np.ndarray  # [N] the exploration-buffer slots of the batch's trials, one per trajectory to read
    steps: th.Tensor  # [B] the step of s within its execution episode (s' is at steps + 1)
    trajectories: th.Tensor  # [B] which of ``slots`` holds each transition's exploration trajectory
    # image states: the distinct frames of s and of s' (see ExecutionBuffer.batch; None otherwise)
    state_frames: Optional[DistinctFrames] = None
    next_state_frames: Optional[DistinctFrames] = None
    shared_frames: int = 0  # frames both some s and some s': state_frames' last, next_state_frames' first
    # n-step windows of sampled transitions (DREAM(execution_n_step=n > 1) with "transitions"
    # sampling; None otherwise): the rewards, terminals and validity of each transition and of the
    # n - 1 that follow it in its execution episode, [B, n]; ``next_states`` (and ``next_steps``,
    # the step of that state) are then those of each window's last valid transition.
    window_rewards: Optional[th.Tensor] = None
    window_dones: Optional[th.Tensor] = None
    window_mask: Optional[th.Tensor] = None
    next_steps: Optional[th.Tensor] = None


def _image_states(space: spaces.Space) -> bool:
    """Whether the networks embed these states with the CNN (uint8 images), so batches carry their
    distinct frames."""
    return isinstance(space, spaces.Box) and is_image_space(space, check_channels=False, normalized_image=False)


def _state_dtype(space: spaces.Space) -> np.dtype:
    return np.uint8 if space.dtype == np.uint8 else np.int64 if np.issubdtype(space.dtype, np.integer) else np.float32


class ExplorationBuffer:
    """Ring buffer of exploration trajectories of at most ``max_length`` transitions.

    With image states, :meth:`get` also gives each distinct frame of the trajectories once
    (``TrajectoryBatch.frames``): every network's CNN then runs once per distinct frame, and not
    over the padding after each trajectory's end, whose states no loss reads.
    ``distinct_frames = False`` (on the class or a buffer) gives every position's frame instead.
    """

    distinct_frames = True
    image_states = False  # set from the state space (False for buffers pickled before it existed)

    def __init__(
        self, capacity: int, max_length: int, state_space: spaces.Space, n_problem_features: int, device: th.device
    ) -> None:
        self.capacity, self.max_length, self.device = capacity, max_length, device
        shape, dtype = state_space.shape, _state_dtype(state_space)
        self.states = np.zeros((capacity, max_length + 1, *shape), dtype=dtype)
        self.actions = np.zeros((capacity, max_length), dtype=np.int64)
        self.prev_actions = np.zeros((capacity, max_length + 1), dtype=np.int64)
        self.prev_rewards = np.zeros((capacity, max_length + 1, 1), dtype=np.float32)
        self.lengths = np.zeros(capacity, dtype=np.int64)
        self.problem_features = np.zeros((capacity, n_problem_features), dtype=np.int64)
        self.generation = np.zeros(capacity, dtype=np.int64)  # bumped when a slot is overwritten
        self.pos, self.full = 0, False
        self.image_states = _image_states(state_space)

    def __len__(self) -> int:
        return self.capacity if self.full else self.pos

    def add(
        self,
        states: np.ndarray,
        actions: np.ndarray,
        prev_actions: np.ndarray,
        prev_rewards: np.ndarray,
        length: int,
        problem_features: np.ndarray,
    ) -> tuple[int, int]:
        """Store one trajectory (arrays padded to ``max_length``); return its (slot, generation)."""
        slot = self.pos
        self.states[slot] = states
        self.actions[slot] = actions
        self.prev_actions[slot] = prev_actions
        self.prev_rewards[slot, :, 0] = prev_rewards
        self.lengths[slot] = length
        self.problem_features[slot] = problem_features
        self.generation[slot] += 1
        self.pos = (self.pos + 1) % self.capacity
        self.full = self.full or self.pos == 0
        return slot, int(self.generation[slot])

    def get(self, slots: np.ndarray) -> TrajectoryBatch:
        """The trajectories in ``slots``, cut to the longest of them."""
        t = int(self.lengths[slots].max())
        to = lambda a: th.as_tensor(a, device=self.device)  # noqa: E731
        states, frames = self.states[slots, : t + 1], None
        if self.image_states and self.distinct_frames:
            lengths = self.lengths[slots]
            valid = np.arange(t + 1)[None] <= lengths[:, None]  # s_0 .. s_{T_b}; later ones are padding
            held = states[valid]
            first, inverse = distinct_frame_index(held)
            index = np.full(valid.shape, len(first), dtype=np.int64)
            index[valid] = inverse
            frames = DistinctFrames(to(held[first]), to(index))
        return TrajectoryBatch(
            states=to(states),
            actions=to(self.actions[slots, :t]),
            prev_actions=to(self.prev_actions[slots, : t + 1]),
            prev_rewards=to(self.prev_rewards[slots, : t + 1]),
            lengths=to(self.lengths[slots]),
            problem_features=to(self.problem_features[slots]),
            frames=frames,
        )


class ExecutionBuffer:
    """Ring buffer of execution transitions, each pointing at its trial's exploration trajectory.

    With image states, :meth:`batch` also gives the distinct frames of s and s' (see there);
    ``distinct_frames = False`` (on the class or a buffer) leaves them out.
    """

    distinct_frames = True
    image_states = False  # set from the state space (False for buffers pickled before it existed)

    def __init__(self, capacity: int, observation_space: spaces.Dict, device: th.device) -> None:
        self.capacity, self.device = capacity, device
        state_space = observation_space["obs"]
        shape, dtype = state_space.shape, _state_dtype(state_space)
        self.states = np.zeros((capacity, *shape), dtype=dtype)
        self.next_states = np.zeros((capacity, *shape), dtype=dtype)
        self.instructions = np.zeros((capacity, *observation_space["instruction"].shape), dtype=np.int64)
        self.actions = np.zeros(capacity, dtype=np.int64)
        self.rewards = np.zeros(capacity, dtype=np.float32)
        self.dones = np.zeros(capacity, dtype=np.float32)
        self.slots = np.zeros(capacity, dtype=np.int64)
        self.generations = np.zeros(capacity, dtype=np.int64)
        self.steps = np.zeros(capacity, dtype=np.int64)
        self.next_in_episode = np.full(capacity, -1, dtype=np.int64)  # the episode's next transition, or -1
        self._last_index = np.full(0, -1, dtype=np.int64)  # per env: where its last transition went
        self.pos, self.full = 0, False
        self.image_states = _image_states(state_space)

    def __setstate__(self, state: Dict[str, object]) -> None:
        # Buffers pickled before the execution step was stored: all steps unknown, taken as 0.
        self.__dict__.update(state)
        if "steps" not in state:
            self.steps = np.zeros(len(self.actions), dtype=np.int64)
        if "next_in_episode" not in state:  # pickled before episodes were linked: link them now
            self.next_in_episode = self.episode_links()
            self._last_index = np.full(0, -1, dtype=np.int64)

    def __len__(self) -> int:
        return self.capacity if self.full else self.pos

    def add(self, transitions: Dict[str, np.ndarray], envs: Optional[np.ndarray] = None) -> None:
        """Add a batch of transitions (arrays with a leading dim, one row per env; ``envs``: which
        env each row comes from, default ``0..n-1``), linking each to its episode's previous one."""
        n = len(transitions["actions"])
        idx = (self.pos + np.arange(n)) % self.capacity
        envs = np.arange(n) if envs is None else np.asarray(envs, dtype=np.int64)
        if len(self._last_index) <= envs.max(initial=-1):
            grown = np.full(envs.max() + 1, -1, dtype=np.int64)
            grown[: len(self._last_index)] = self._last_index
            self._last_index = grown
        # The env's last transition continues into this one when it is the previous step of the
        # same trial's execution episode (checked before the write, which may reuse its row).
        prev, steps = self._last_index[envs], np.asarray(transitions["steps"])
        safe = np.maximum(prev, 0)
        linked = (
            (prev >= 0)
            & (steps > 0)
            & (self.slots[safe] == transitions["slots"])
            & (self.generations[safe] == transitions["generations"])
            & (self.steps[safe] == steps - 1)
        )
        for key, value in transitions.items():
            getattr(self, key)[idx] = value
        self.next_in_episode[idx] = -1
        self.next_in_episode[prev[linked]] = idx[linked]
        self._last_index[envs] = idx
        self.full = self.full or self.pos + n >= self.capacity
        self.pos = int((self.pos + n) % self.capacity)

    def episode_links(self) -> np.ndarray:
        """``next_in_episode`` rebuilt from the stored transitions alone (for buffers saved before
        the links were kept): within a trial, a transition continues the one written before it
        when its step is the next."""
        n = len(self)
        age = (np.arange(n) - (self.pos if self.full else 0)) % self.capacity
        order = np.lexsort((age, self.generations[:n], self.slots[:n]))  # by trial, then by writing order
        links = np.full(self.capacity, -1, dtype=np.int64)
        a, b = order[:-1], order[1:]
        same = (
            (self.slots[a] == self.slots[b])
            & (self.generations[a] == self.generations[b])
            & (self.steps[b] == self.steps[a] + 1)
        )
        links[a[same]] = b[same]
        return links

    def windows(self, idx: np.ndarray, n_step: int) -> np.ndarray:
        """Each transition of ``idx`` and the ``n_step - 1`` that follow it in its execution episode,
        ``[B, n_step]`` rows of the buffer, -1 after a terminal transition or the last one stored."""
        rows = np.full((len(idx), n_step), -1, dtype=np.int64)
        rows[:, 0] = idx
        for k in range(1, n_step):
            previous = rows[:, k - 1]
            going = (previous >= 0) & (self.dones[np.maximum(previous, 0)] == 0)  # no step after a terminal
            rows[:, k] = np.where(going, self.next_in_episode[np.maximum(previous, 0)], -1)
        return rows

    def batch(self, idx: np.ndarray, slots: np.ndarray, trajectories: np.ndarray, n_step: int = 1) -> ExecutionBatch:
        """Transitions ``idx``; transition j reads trajectory ``trajectories[j]`` of ``slots``.

        ``n_step > 1``: with each transition's n-step window (``window_*``): s' is then the last
        state of the window, where its target bootstraps.

        With image states, the distinct frames of s and s' are laid out once, as [frames only some
        s holds, frames both some s and some s' hold, frames only some s' holds]: ``state_frames``
        are the first two groups, ``next_state_frames`` the last two (views of one tensor), and
        ``shared_frames`` the middle group's size, so the online network embeds s' by reusing its
        s pass where it can (:meth:`~sb3_dream.common.embedders.ImageEmbedder.embed_pair`).
        """
        to = lambda a: th.as_tensor(a, device=self.device)  # noqa: E731
        ends, windows = idx, {}
        if n_step > 1:
            rows = self.windows(idx, n_step)
            valid = rows >= 0
            ends = rows[np.arange(len(idx)), valid.sum(axis=1) - 1]  # each window's last transition
            safe = np.maximum(rows, 0)
            windows = dict(
                window_rewards=to(np.where(valid, self.rewards[safe], 0.0).astype(np.float32)),
                window_dones=to(np.where(valid, self.dones[safe], 0.0).astype(np.float32)),
                window_mask=to(valid.astype(np.float32)),
                next_steps=to(self.steps[ends] + 1),
            )
        states, next_states = self.states[idx], self.next_states[ends]
        frames: Dict[str, Any] = {}
        if self.image_states and self.distinct_frames:
            n = len(idx)
            both = np.concatenate([states, next_states])
            first, inverse = distinct_frame_index(both)
            in_current, in_following = np.zeros(len(first), bool), np.zeros(len(first), bool)
            in_current[inverse[:n]], in_following[inverse[n:]] = True, True
            group = np.where(in_current, np.where(in_following, 1, 0), 2)
            order = np.argsort(group, kind="stable")
            rank = np.empty_like(order)
            rank[order] = np.arange(len(order))
            inverse = rank[inverse]
            only_current, shared = int((group == 0).sum()), int((group == 1).sum())
            distinct = to(both[first[order]])
            frames = dict(
                state_frames=DistinctFrames(distinct[: only_current + shared], to(inverse[:n])),
                next_state_frames=DistinctFrames(distinct[only_current:], to(inverse[n:] - only_current)),
                shared_frames=shared,
            )
        return ExecutionBatch(
            states=to(states),
            instructions=to(self.instructions[idx]),
            actions=to(self.actions[idx]),
            rewards=to(self.rewards[idx]),
            next_states=to(next_states),
            dones=to(self.dones[idx]),
            slots=slots,
            steps=to(self.steps[idx]),
            trajectories=to(trajectories),
            **frames,
            **windows,
        )


@dataclass
class ExecutionRewardCounts:
    """What B_exe holds per (problem, instruction): one row per pair present in it.

    Execution learns only from the rewards its replay holds; a pair with no positive reward in
    B_exe is one the execution Q-network cannot learn to reach (sparse-reward envs: SignNav3D).
    """

    problem_features: np.ndarray  # [k, P] the problem's features (as B_exp stores them)
    instructions: np.ndarray  # [k, I]
    transitions: np.ndarray  # [k]
    episodes: np.ndarray  # [k] execution episodes (transitions at step 0 of theirs)
    positive: np.ndarray  # [k] transitions with reward > 0
    negative: np.ndarray  # [k] transitions with reward < 0
    reward_sum: np.ndarray  # [k]
    unlinked: int  # transitions whose exploration trajectory was overwritten (problem unknown, never sampled)


class DreamReplayBuffer:
    """Both buffers together, so SB3's ``save_replay_buffer``/``load_replay_buffer`` carry them."""

    def __init__(self, exploration: ExplorationBuffer, execution: ExecutionBuffer) -> None:
        self.exploration, self.execution = exploration, execution
        self.trial_spec: Optional[Dict[str, Any]] = None  # the trial shape it is filled in (set by DREAM)

    def sample_trajectories(self, batch_size: int, rng: np.random.Generator) -> TrajectoryBatch:
        """``batch_size`` exploration trajectories drawn uniformly from B_exp."""
        return self.exploration.get(rng.integers(len(self.exploration), size=batch_size))

    def sample_execution(
        self, batch_size: int, rng: np.random.Generator, episodes: bool = False, n_step: int = 1
    ) -> Tuple[ExecutionBatch, TrajectoryBatch]:
        """An execution batch and the exploration trajectories its transitions read.

        ``episodes=False`` (Algorithm 1): ``batch_size`` transitions drawn uniformly among those
        whose exploration trajectory is still stored, each with its own trajectory.
        ``episodes=True`` (the authors' code samples its replay as whole episodes): every stored
        transition of ``batch_size`` execution episodes, drawn uniformly among the episodes whose
        start and exploration trajectory are still stored; one trajectory per episode.
        ``n_step > 1`` with transitions: each comes with its n-step window (see
        :meth:`ExecutionBuffer.batch`); a batch of whole episodes holds its windows already.
        """
        if episodes:
            execution = self.sample_episodes(batch_size, rng)
        else:
            execution = self.sample_transitions(batch_size, rng, n_step)
        return execution, self.exploration.get(execution.slots)

    def sample_transitions(self, batch_size: int, rng: np.random.Generator, n_step: int = 1) -> ExecutionBatch:
        exe = self.execution
        idx = rng.integers(len(exe), size=batch_size)
        for _ in range(100):
            stale = self.stale(idx)
            if not stale.any():
                break
            idx[stale] = rng.integers(len(exe), size=int(stale.sum()))
        else:
            raise RuntimeError("the execution buffer references no stored exploration trajectory: grow buffer_size")
        return exe.batch(idx, exe.slots[idx], np.arange(batch_size), n_step)

    def sample_episodes(self, n_episodes: int, rng: np.random.Generator) -> ExecutionBatch:
        exe = self.execution
        starts = np.flatnonzero(exe.steps[: len(exe)] == 0)
        starts = starts[~self.stale(starts)]
        if not len(starts):
            raise RuntimeError("the execution buffer holds no episode start whose exploration trajectory is stored")
        heads = starts[rng.integers(len(starts), size=n_episodes)]
        rows, owners = [], []
        current, owner = heads, np.arange(n_episodes)
        while len(current):  # one step of every episode at a time: at most the horizon's length
            rows.append(current)
            owners.append(owner)
            following = exe.next_in_episode[current]
            current, owner = following[following >= 0], owner[following >= 0]
        return exe.batch(np.concatenate(rows), exe.slots[heads], np.concatenate(owners))

    def stale(self, idx: np.ndarray) -> np.ndarray:
        """Whether each execution transition's exploration trajectory has been overwritten (such a
        transition is never sampled)."""
        exe = self.execution
        return self.exploration.generation[exe.slots[idx]] != exe.generations[idx]

    def execution_reward_counts(self) -> ExecutionRewardCounts:
        """Count B_exe's transitions and their rewards per (problem, instruction) of their trial."""
        exe, n = self.execution, len(self.execution)
        linked = ~self.stale(np.arange(n))
        problems = self.exploration.problem_features[exe.slots[:n][linked]]
        instructions, rewards = exe.instructions[:n][linked], exe.rewards[:n][linked]
        starts = exe.steps[:n][linked] == 0
        pairs, which = np.unique(np.concatenate([problems, instructions], axis=1), axis=0, return_inverse=True)
        which = which.reshape(-1)  # numpy 2.0.x gave it the input's dimensions
        count = lambda weights=None: np.bincount(which, weights, minlength=len(pairs))  # noqa: E731
        n_features = problems.shape[1]
        return ExecutionRewardCounts(
            problem_features=pairs[:, :n_features],
            instructions=pairs[:, n_features:],
            transitions=count(),
            episodes=count(starts).astype(np.int64),
            positive=count(rewards > 0).astype(np.int64),
            negative=count(rewards < 0).astype(np.int64),
            reward_sum=count(rewards),
            unlinked=int(n - linked.sum()),
        )

    @property
    def device(self) -> th.device:
        return self.exploration.device

    @device.setter
    def device(self, device: th.device) -> None:
        self.exploration.device = self.execution.device = device
