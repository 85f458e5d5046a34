"""Sequence replay for recurrent Q-learning: whole trials (or chunks of them) in preallocated arrays.

The paper trains its recurrent policies "with a simplified version of the methods in Kapturowski
et al. (2019) by storing a replay buffer with up to 16000 sequences of 50 consecutive timesteps"
(Appendix B.4). :class:`SequenceReplayBuffer` stores one row per sequence: a trial that fits in
``sequence_length`` steps is one sequence starting at the trial's first step; a longer one is cut
into consecutive chunks. Rows are sampled uniformly and returned as padded ``[B, T, ...]`` tensors
(``T`` = the longest sampled sequence) with a loss mask.

R2D2's options (off by default, as in the paper): ``burn_in`` cuts chunks with an overlap of
``burn_in`` steps whose only use is to warm up the LSTM state (masked out of the loss), and a
``lstm_state_shape`` makes the buffer store the LSTM state the actor had at each chunk's first
step ("stored state"); without it a chunk's unroll starts from zeros, which is exact for chunks
that start a trial.
"""

from __future__ import annotations

from typing import Any, Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.vec_env import VecNormalize

try:  # only used to warn about buffers larger than the free memory, as SB3 does
    import psutil
except ImportError:  # pragma: no cover
    psutil = None


class SequenceReplayBufferSamples(NamedTuple):
    """A padded batch of ``B`` sequences, ``T`` steps each (the longest sampled one).

    ``observations[k]`` holds ``T + 1`` observations per sequence: step t's observation is
    ``[:, t]`` and the observation its transition leads to is ``[:, t + 1]``, so one unroll over
    ``[:, :T + 1]`` gives both Q(s_t) and Q(s_{t+1}).
    """

    observations: Dict[str, th.Tensor]  # [B, T + 1, *shape]
    actions: th.Tensor  # [B, T] long
    rewards: th.Tensor  # [B, T] float
    dones: th.Tensor  # [B, T] float: 1 where the next observation is terminal (no bootstrap)
    mask: th.Tensor  # [B, T] float: 1 on the steps to train on (not padding, not burn-in)
    lengths: th.Tensor  # [B] long: valid steps of each sequence
    lstm_states: Optional[Tuple[th.Tensor, th.Tensor]]  # stored initial (h, c), [layers, B, H], or None
    burn_in_mask: Optional[th.Tensor]  # [B] bool: sequences whose first burn_in steps are burn-in


class SequenceReplayBuffer(ReplayBuffer):
    """Replay of trial sequences for recurrent Q-networks (Dict observations, Discrete actions).

    ``add`` takes one vectorised env step, like SB3's replay buffers; each env writes into its own
    staging row, which is copied into the buffer when the trial ends or the row holds
    ``sequence_length`` steps. Only complete sequences are sampled.

    :param buffer_size: the number of *sequences* kept (paper: 16000), over all envs.
    :param observation_space: a Dict space.
    :param action_space: a Discrete space.
    :param device: where sampled tensors go.
    :param n_envs: number of envs ``add`` receives steps from.
    :param optimize_memory_usage: not supported (must be False); kept for SB3's constructor call.
    :param handle_timeout_termination: if True, a ``TimeLimit.truncated`` end is not terminal (the
        target bootstraps from the truncation observation), as in SB3.
    :param sequence_length: the most steps per sequence (paper: 50).
    :param burn_in: overlap between consecutive chunks of a trial, used only to warm up the LSTM.
    :param lstm_state_shape: ``(num_layers, hidden_size)`` to store the actor's LSTM state at each
        chunk's start (R2D2's stored state); ``None`` stores none (the unroll starts from zeros).
    """

    observation_space: spaces.Dict
    observations: Dict[str, np.ndarray]  # type: ignore[assignment]

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        sequence_length: int = 50,
        burn_in: int = 0,
        lstm_state_shape: Optional[Sequence[int]] = None,
    ) -> None:
        # ReplayBuffer.__init__ allocates flat transition arrays: skip it, as DictReplayBuffer does
        super(ReplayBuffer, self).__init__(buffer_size, observation_space, action_space, device, n_envs=n_envs)
        if not isinstance(observation_space, spaces.Dict):
            raise ValueError(f"observation_space must be a gymnasium.spaces.Dict, got {observation_space}")
        if not isinstance(action_space, spaces.Discrete):
            raise ValueError(f"action_space must be gymnasium.spaces.Discrete, got {action_space}")
        if isinstance(buffer_size, bool) or not isinstance(buffer_size, (int, np.integer)) or buffer_size < 1:
            raise ValueError(f"buffer_size must be an integer >= 1 (a number of sequences), got {buffer_size!r}")
        if (
            isinstance(sequence_length, bool)
            or not isinstance(sequence_length, (int, np.integer))
            or sequence_length < 1
        ):
            raise ValueError(f"sequence_length must be an integer >= 1, got {sequence_length!r}")
        if (
            isinstance(burn_in, bool)
            or not isinstance(burn_in, (int, np.integer))
            or not 0 <= burn_in < sequence_length
        ):
            raise ValueError(
                f"burn_in must be an integer in [0, sequence_length - 1] = [0, {sequence_length - 1}], got {burn_in!r}"
            )
        if optimize_memory_usage:
            raise ValueError("optimize_memory_usage=True is not supported by SequenceReplayBuffer")
        self.optimize_memory_usage = False
        self.handle_timeout_termination = handle_timeout_termination
        self.buffer_size = int(buffer_size)  # sequences over all envs (SB3's buffers count per env)
        self.sequence_length = L = int(sequence_length)
        self.burn_in = int(burn_in)
        self.lstm_state_shape = None if lstm_state_shape is None else tuple(int(s) for s in lstm_state_shape)
        self.keys: List[str] = list(observation_space.spaces.keys())

        N, E = self.buffer_size, self.n_envs
        self.observations = {k: self._zeros_obs(k, (N, L + 1)) for k in self.keys}
        self.actions = np.zeros((N, L), dtype=np.int64)
        self.rewards = np.zeros((N, L), dtype=np.float32)
        self.dones = np.zeros((N, L), dtype=np.float32)
        self.lengths = np.zeros(N, dtype=np.int64)
        self.train_from = np.zeros(N, dtype=np.int64)
        self.states = None if self.lstm_state_shape is None else np.zeros((N, 2, *self.lstm_state_shape), np.float32)

        self._allocate_staging(E)
        self.n_sequences_added = 0

        if psutil is not None:
            nbytes = sum(a.nbytes for a in self.observations.values()) + self.actions.nbytes * 3
            if nbytes > psutil.virtual_memory().available:
                import warnings

                warnings.warn(f"the sequence replay buffer needs {nbytes / 1e9:.2f} GB, more than the free memory")

    def _allocate_staging(self, n_envs: int) -> None:
        """Staging rows, one per env: the sequence each env is collecting."""
        E, L = n_envs, self.sequence_length
        self._stage_obs = {k: self._zeros_obs(k, (E, L + 1)) for k in self.keys}
        self._stage_actions = np.zeros((E, L), dtype=np.int64)
        self._stage_rewards = np.zeros((E, L), dtype=np.float32)
        self._stage_dones = np.zeros((E, L), dtype=np.float32)
        self._stage_states = (
            None if self.lstm_state_shape is None else np.zeros((E, L, 2, *self.lstm_state_shape), np.float32)
        )
        self._stage_pos = np.zeros(E, dtype=np.int64)
        self._stage_train_from = np.zeros(E, dtype=np.int64)
        self._env_idx = np.arange(E)

    def set_n_envs(self, n_envs: int) -> None:
        """Collect from ``n_envs`` envs from now on (e.g. after ``model.set_env``); sequences being
        collected are stored as they are."""
        if n_envs == self.n_envs:
            return
        for e in np.flatnonzero(self._stage_pos > 0):
            self._commit(int(e), trial_over=True)
        self.n_envs = int(n_envs)
        self._allocate_staging(self.n_envs)

    def _zeros_obs(self, key: str, lead: Tuple[int, ...]) -> np.ndarray:
        space = self.observation_space.spaces[key]
        return np.zeros((*lead, *space.shape), dtype=space.dtype)

    # ------------------------------------------------------------------ writing
    def add(  # type: ignore[override]
        self,
        obs: Dict[str, np.ndarray],
        next_obs: Dict[str, np.ndarray],
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: List[Dict[str, Any]],
        episode_start: Optional[np.ndarray] = None,
        lstm_states: Optional[Tuple[np.ndarray, np.ndarray]] = None,
    ) -> None:
        """Append one vectorised step (``n_envs`` transitions).

        :param obs: the observations acted on, ``obs[k]`` of shape ``[n_envs, *shape]``.
        :param next_obs: the observations the transitions led to (the terminal one where ``done``).
        :param done: the trial (gym episode) ended.
        :param episode_start: ``[n_envs]``, set where ``obs`` is a trial's first observation; a
            trial interrupted before its end (e.g. by a new ``learn`` call resetting the envs) is
            then stored as it is, bootstrapping from its last observation.
        :param lstm_states: the LSTM state ``(h, c)`` (``[layers, n_envs, hidden]`` each) the actor
            used on ``obs``, needed only with ``lstm_state_shape``.
        """
        E, idx = self.n_envs, self._env_idx
        done = np.asarray(done, dtype=bool).reshape(E)
        if episode_start is not None:
            for e in np.flatnonzero(np.asarray(episode_start, dtype=bool).reshape(E) & (self._stage_pos > 0)):
                self._commit(int(e), trial_over=True)
        p = self._stage_pos
        for k in self.keys:
            shape = self._stage_obs[k].shape[2:]
            self._stage_obs[k][idx, p] = np.asarray(obs[k]).reshape(E, *shape)
            self._stage_obs[k][idx, p + 1] = np.asarray(next_obs[k]).reshape(E, *shape)
        self._stage_actions[idx, p] = np.asarray(action).reshape(E)
        self._stage_rewards[idx, p] = np.asarray(reward).reshape(E)
        terminal = done.copy()
        if self.handle_timeout_termination:
            terminal &= ~np.array([bool(info.get("TimeLimit.truncated", False)) for info in infos])
        self._stage_dones[idx, p] = terminal
        if self._stage_states is not None:
            if lstm_states is None:
                raise ValueError("lstm_states is required: this buffer stores LSTM states (lstm_state_shape is set)")
            h, c = (np.asarray(s, dtype=np.float32).swapaxes(0, 1) for s in lstm_states)  # [E, layers, H]
            self._stage_states[idx, p, 0] = h
            self._stage_states[idx, p, 1] = c
        self._stage_pos += 1
        for e in np.flatnonzero(done | (self._stage_pos == self.sequence_length)):
            self._commit(int(e), trial_over=bool(done[e]))

    def _commit(self, e: int, trial_over: bool) -> None:
        """Copy env ``e``'s staging row into the buffer; keep the overlap if its trial goes on."""
        n, s, L = int(self._stage_pos[e]), self.pos, self.sequence_length
        n_obs = n + 1  # the observations of the n steps and the one the last step led to
        for k in self.keys:
            self.observations[k][s, :n_obs] = self._stage_obs[k][e, :n_obs]
            self.observations[k][s, n_obs:] = 0
        for dst, src in (
            (self.actions, self._stage_actions),
            (self.rewards, self._stage_rewards),
            (self.dones, self._stage_dones),
        ):
            dst[s, :n] = src[e, :n]
            dst[s, n:] = 0
        self.lengths[s] = n
        self.train_from[s] = self._stage_train_from[e]
        if self.states is not None:
            self.states[s] = self._stage_states[e, 0]
        self.pos += 1
        self.n_sequences_added += 1
        if self.pos == self.buffer_size:
            self.full, self.pos = True, 0

        if trial_over:
            self._stage_pos[e] = 0
            self._stage_train_from[e] = 0
            return
        # the trial goes on: the next chunk starts burn_in steps before this one's end
        keep = self.burn_in
        start, end = L - keep, L + 1
        for k in self.keys:
            self._stage_obs[k][e, : end - start] = self._stage_obs[k][e, start:end].copy()
        for arr in (self._stage_actions, self._stage_rewards, self._stage_dones):
            arr[e, :keep] = arr[e, start:L].copy()
        if self._stage_states is not None and keep > 0:
            self._stage_states[e, :keep] = self._stage_states[e, start:L].copy()
        self._stage_pos[e] = keep
        self._stage_train_from[e] = keep

    def reset(self) -> None:
        super().reset()
        self._stage_pos[:] = 0
        self._stage_train_from[:] = 0
        self.n_sequences_added = 0

    # ------------------------------------------------------------------ sampling
    def sample(  # type: ignore[override]
        self, batch_size: int, env: Optional[VecNormalize] = None
    ) -> SequenceReplayBufferSamples:
        """``batch_size`` sequences drawn uniformly (with replacement) from the stored ones."""
        if self.size() == 0:
            raise RuntimeError("the sequence replay buffer holds no complete sequence yet")
        batch_inds = np.random.randint(0, self.size(), size=batch_size)
        return self._get_samples(batch_inds, env=env)

    def _get_samples(  # type: ignore[override]
        self, batch_inds: np.ndarray, env: Optional[VecNormalize] = None
    ) -> SequenceReplayBufferSamples:
        if env is not None:
            raise ValueError("VecNormalize is not supported by SequenceReplayBuffer")
        lengths = self.lengths[batch_inds]
        T = max(int(lengths.max()), 1)
        train_from = self.train_from[batch_inds]
        steps = np.arange(T)
        mask = (steps < lengths[:, None]) & (steps >= train_from[:, None])
        as_t = self._as_tensor
        states = None
        if self.states is not None:
            st = self.states[batch_inds]  # [B, 2, layers, H]
            states = (as_t(st[:, 0].swapaxes(0, 1)), as_t(st[:, 1].swapaxes(0, 1)))
        burn_in_mask = None
        if self.burn_in > 0 and bool((train_from > 0).any()):
            burn_in_mask = as_t(train_from > 0)
        return SequenceReplayBufferSamples(
            observations={k: as_t(v[batch_inds, : T + 1]) for k, v in self.observations.items()},
            actions=as_t(self.actions[batch_inds, :T]),
            rewards=as_t(self.rewards[batch_inds, :T]),
            dones=as_t(self.dones[batch_inds, :T]),
            mask=as_t(mask.astype(np.float32)),
            lengths=as_t(lengths),
            lstm_states=states,
            burn_in_mask=burn_in_mask,
        )

    def _as_tensor(self, array: np.ndarray) -> th.Tensor:
        # fancy indexing already copied the data: no second copy on the CPU
        return th.as_tensor(np.ascontiguousarray(array), device=self.device)
