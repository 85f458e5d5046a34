"""Observation embedders of the paper's networks (Appendix B.3), one per Dict key.

Every embedder maps a raw observation tensor with any leading batch dimensions
``[*batch, *space.shape]`` (integers for ``Discrete``/``MultiDiscrete``, uint8 for images, floats for
``Box``) to ``[*batch, embed_dim]``. They do the preprocessing themselves (embedding lookups instead
of SB3's one-hot encoding, division by 255 for images), so they take observations as stored in the
replay buffer, without :func:`stable_baselines3.common.preprocessing.preprocess_obs`.

* ``MultiDiscrete`` (grid states, instructions, problem IDs): each dimension is embedded
  independently with an embedding matrix of dimension 32, the embeddings are concatenated and two
  linear layers of 256 and 64 units with ReLU activations follow (paper, "State, instruction, and
  problem ID embeddings").
* uint8 images (the 3D sign env): 3 convolutions with 32 channels, kernels 5, 5, 4 and stride 2,
  ReLU activations, then a linear layer of 128 units (paper, after Chevalier-Boisvert, 2018).
* ``Discrete`` (previous action, episode-start flag): one embedding matrix (16 units in RL²).
* ``Box`` vectors: a linear layer (the previous reward: 16 units in RL²) or, for states, the same
  256 -> 64 MLP as ``MultiDiscrete`` states.
"""

from __future__ import annotations

from typing import Dict, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first
from torch import nn

from dream_envs.checks import check_positive_int


def _flatten_batch(x: th.Tensor, event_shape: Sequence[int]) -> tuple[th.Tensor, tuple[int, ...]]:
    """Split ``x`` into its leading batch dims and its event dims; return ``x`` as ``[N, *event]``."""
    n_event = len(event_shape)
    batch_shape = tuple(x.shape[: x.dim() - n_event]) if n_event else tuple(x.shape)
    return x.reshape(-1, *event_shape), batch_shape


class DistinctFrames(NamedTuple):
    """A batch of image states given as its distinct frames and, for each position, which one it holds.

    :class:`ImageEmbedder` runs its CNN over ``frames`` alone and indexes the result, so a frame the
    batch holds many times (a blocked move, a revisited view, a trajectory sampled twice) costs one
    forward and one backward pass, and positions no loss reads (a padded trajectory's tail) none.
    The embeddings are the same function of each frame; only float summation order differs
    (the gradient of a frame held k times is summed before the CNN's backward, not after).
    """

    frames: th.Tensor  # [U, *frame] each distinct frame once, in the order of first appearance
    index: th.Tensor  # [*batch] long: the row of ``frames`` at each position; U: no frame (embeds as 0)


# Odd multipliers of the frame hash, one per 8-byte word (drawn once; any fixed draw works).
_HASH_WEIGHTS: Dict[int, np.ndarray] = {}


def distinct_frame_index(frames: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Where each distinct frame of ``frames`` ``[N, *frame]`` first appears, and which one each is.

    :return: ``first`` ``[U]`` (increasing) and ``inverse`` ``[N]`` with ``frames[first[inverse]]``
        equal to ``frames`` byte for byte.

    Frames are hashed as sums of their 8-byte words times fixed odd multipliers (modulo 2^64), then
    every repeat is compared with its representative byte for byte; should two different frames
    share a hash, whole frames are compared instead (exact either way, and the hash is cheaper than
    sorting whole frames).
    """
    n = len(frames)
    flat = np.ascontiguousarray(frames).reshape(n, -1)
    if n == 0 or flat.shape[1] % 8:
        return distinct_frame_index_exact(flat)
    words = flat.view(np.uint64)
    weights = _HASH_WEIGHTS.get(words.shape[1])
    if weights is None:
        weights = np.random.default_rng(0).integers(0, 2**63, size=words.shape[1], dtype=np.uint64)
        weights = weights * np.uint64(2) + np.uint64(1)
        _HASH_WEIGHTS[words.shape[1]] = weights
    keys = (words * weights).sum(axis=1, dtype=np.uint64)
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)  # numpy 2.0.x gave it the input's dimensions
    repeat = first[inverse] != np.arange(n)
    if not np.array_equal(flat[repeat], flat[first[inverse[repeat]]]):
        return distinct_frame_index_exact(flat)  # two frames shared a hash
    return _in_order_of_appearance(first, inverse)


def distinct_frame_index_exact(frames: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """:func:`distinct_frame_index` by sorting whole frames (no hash)."""
    flat = np.ascontiguousarray(frames).reshape(len(frames), -1)
    keys = flat.view(np.dtype((np.void, flat.shape[1])))[:, 0] if flat.shape[1] else np.zeros(len(flat))
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    return _in_order_of_appearance(first, inverse.reshape(-1))


def _in_order_of_appearance(first: np.ndarray, inverse: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """``np.unique``'s ``first`` and ``inverse`` with the distinct values renumbered by first appearance."""
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return first[order], rank[inverse]


def relu_mlp(in_dim: int, hidden_dims: Sequence[int]) -> tuple[nn.Sequential, int]:
    """Linear + ReLU layers of ``hidden_dims`` after ``in_dim`` inputs, and their output size."""
    layers: list[nn.Module] = []
    for out_dim in hidden_dims:
        layers += [nn.Linear(in_dim, out_dim), nn.ReLU()]
        in_dim = out_dim
    return nn.Sequential(*layers), in_dim


class MultiDiscreteEmbedder(nn.Module):
    """Per-dimension embeddings (``per_dim`` units each), concatenated, then a ReLU MLP.

    The per-dimension tables are stored as one ``nn.Embedding`` with offsets (one lookup for all
    dimensions), which is the same function as one table per dimension.

    :param nvec: the ``MultiDiscrete`` sizes (any shape; flattened).
    :param per_dim: embedding size of each dimension (paper: 32).
    :param hidden_dims: the MLP's layer sizes (paper: ``(256, 64)``); the last one is ``embed_dim``.
    """

    def __init__(self, nvec: np.ndarray, per_dim: int = 32, hidden_dims: Sequence[int] = (256, 64)) -> None:
        super().__init__()
        nvec = np.asarray(nvec, dtype=np.int64)
        self.event_shape = tuple(nvec.shape)
        flat = nvec.reshape(-1)
        offsets = np.concatenate([[0], np.cumsum(flat)[:-1]])
        self.register_buffer("offsets", th.as_tensor(offsets, dtype=th.long), persistent=False)
        self.embedding = nn.Embedding(int(flat.sum()), per_dim)
        self.mlp, self.embed_dim = relu_mlp(per_dim * len(flat), hidden_dims)

        # Mixed-radix weights giving each value one integer key (when they fit in int64): training
        # batches repeat few distinct values (MetaBus: 672 states per batch, 50-70 distinct), so
        # the MLP runs on the distinct ones only; the output is the same function of x.
        sizes = [int(n) for n in flat]
        radix = np.concatenate([np.cumprod(sizes[::-1])[::-1][1:], [1]]) if sizes else np.ones(0)
        self.distinct_keys = bool(np.prod([float(n) for n in sizes]) < 2.0**62)
        self.register_buffer("radix", th.as_tensor(radix.astype(np.int64), dtype=th.long), persistent=False)

    #: batches with at least this many rows go through the MLP once per distinct value
    dedup_min_rows = 256

    def forward(self, x: th.Tensor) -> th.Tensor:
        flat, batch_shape = _flatten_batch(x, self.event_shape)
        values = flat.reshape(flat.shape[0], self.offsets.numel()).long()  # explicit width: batches may be empty
        if self.distinct_keys and values.shape[0] >= self.dedup_min_rows:
            keys, inverse = th.unique(values @ self.radix, return_inverse=True)
            distinct = th.empty(len(keys), values.shape[1], dtype=th.long, device=values.device)
            distinct[inverse] = values
            out = self._embed(distinct)[inverse]
        else:
            out = self._embed(values)
        return out.reshape(*batch_shape, self.embed_dim)

    def _embed(self, values: th.Tensor) -> th.Tensor:
        """[N, n_dims] values -> [N, embed_dim]."""
        return self.mlp(self.embedding(values + self.offsets).flatten(1))


class DiscreteEmbedder(nn.Module):
    """A learned embedding matrix for a ``Discrete(n)`` value (paper: 16 units for actions and flags)."""

    def __init__(self, n: int, embed_dim: int = 16, start: int = 0) -> None:
        super().__init__()
        self.start = int(start)
        self.embedding = nn.Embedding(int(n), embed_dim)
        self.embed_dim = embed_dim

    def forward(self, x: th.Tensor) -> th.Tensor:
        return self.embedding(x.long() - self.start)


class LinearEmbedder(nn.Module):
    """A linear layer over a flattened ``Box`` (paper: the previous reward, 16 units)."""

    def __init__(self, shape: Sequence[int], embed_dim: int = 16) -> None:
        super().__init__()
        self.event_shape = tuple(shape)
        self.linear = nn.Linear(int(np.prod(shape)) if len(shape) else 1, embed_dim)
        self.embed_dim = embed_dim

    def forward(self, x: th.Tensor) -> th.Tensor:
        flat, batch_shape = _flatten_batch(x.float(), self.event_shape)
        return self.linear(flat.reshape(flat.shape[0], -1)).reshape(*batch_shape, self.embed_dim)


class BoxMLPEmbedder(nn.Module):
    """A ReLU MLP over a flattened ``Box`` state (the 256 -> 64 MLP of the discrete states)."""

    def __init__(self, shape: Sequence[int], hidden_dims: Sequence[int] = (256, 64)) -> None:
        super().__init__()
        self.event_shape = tuple(shape)
        self.mlp, self.embed_dim = relu_mlp(int(np.prod(shape)) if len(shape) else 1, hidden_dims)

    def forward(self, x: th.Tensor) -> th.Tensor:
        flat, batch_shape = _flatten_batch(x.float(), self.event_shape)
        return self.mlp(flat.reshape(flat.shape[0], -1)).reshape(*batch_shape, self.embed_dim)


class ImageEmbedder(nn.Module):
    """The paper's 3D-navigation CNN: 3 x (conv 32 channels, stride 2, kernels 5/5/4) + linear 128.

    Takes uint8 images, channel-first ``[*batch, C, H, W]`` (SB3 transposes channel-last image
    observations with ``VecTransposeImage``; a channel-last space is transposed here too).
    ReLU follows every layer (the paper says "in between" the convolutions; a ReLU after the last
    convolution and after the linear layer makes the stack a proper nonlinear feature extractor).

    The convolutions run on channels-last tensors: the same arithmetic, and on a CPU (oneDNN) faster
    than channel-first for these frames, forward and backward (``benchmarks/image_embedder_speed.py``).

    Given a :class:`DistinctFrames` instead of a tensor, it runs the CNN over each distinct frame
    once and indexes the result (DREAM's update batches on image states come so); :meth:`embed_pair`
    embeds a batch's s and s' with the CNN once per distinct frame of both.

    ``downsample`` > 1 (an option; the paper's CNN sees the full frame) average-pools each frame by
    that factor before the convolutions (2: 80 x 60 -> 40 x 30), which cuts the convolutions'
    arithmetic about 4x; colours, such as the sign's, survive the averaging.
    """

    MIN_SIDE = 25  # the fewest pixels per side the three strided convolutions take

    def __init__(
        self,
        space: spaces.Box,
        channels: int = 32,
        embed_dim: int = 128,
        normalize: bool = True,
        downsample: int = 1,
    ) -> None:
        super().__init__()
        shape = tuple(space.shape)
        self.channels_first = bool(is_image_space_channels_first(space))
        self.event_shape = shape
        c = shape[0] if self.channels_first else shape[-1]
        self.normalize = normalize
        self.downsample = check_positive_int("image_downsample", downsample)
        self.pool: nn.Module = nn.AvgPool2d(self.downsample) if self.downsample > 1 else nn.Identity()
        self.cnn = nn.Sequential(
            nn.Conv2d(c, channels, kernel_size=5, stride=2),
            nn.ReLU(),
            nn.Conv2d(channels, channels, kernel_size=5, stride=2),
            nn.ReLU(),
            nn.Conv2d(channels, channels, kernel_size=4, stride=2),
            nn.ReLU(),
            nn.Flatten(),
        )
        chw = self._chw(shape)
        pooled = (chw[1] // self.downsample, chw[2] // self.downsample)
        if min(pooled) < self.MIN_SIDE:
            raise ValueError(
                f"image_downsample={self.downsample} leaves {pooled[1]} x {pooled[0]} pixels of the "
                f"{chw[2]} x {chw[1]} frames, too few for the CNN (it needs {self.MIN_SIDE} on each side): "
                "use a smaller factor"
            )
        with th.no_grad():
            probe = th.zeros(1, *chw)
            n_flat = self.cnn(self.pool(probe)).shape[1]
        self.linear = nn.Sequential(nn.Linear(n_flat, embed_dim), nn.ReLU())
        self.embed_dim = embed_dim

    def _chw(self, shape: Sequence[int]) -> tuple[int, ...]:
        return tuple(shape) if self.channels_first else (shape[2], shape[0], shape[1])

    def forward(self, x: Union[th.Tensor, DistinctFrames]) -> th.Tensor:
        """Frames ``[*batch, *frame]`` (uint8), or a :class:`DistinctFrames` of them -> ``[*batch, embed_dim]``."""
        if isinstance(x, DistinctFrames):
            return self.index(self.embed_frames(x.frames), x.index)
        flat, batch_shape = _flatten_batch(x, self.event_shape)
        return self.embed_frames(flat).reshape(*batch_shape, self.embed_dim)

    def embed_frames(self, flat: th.Tensor) -> th.Tensor:
        """The CNN and the linear layer over frames ``[N, *frame]`` -> ``[N, embed_dim]``."""
        if not len(flat):
            return self.linear[0].weight.new_zeros(0, self.embed_dim)
        if not self.channels_first:
            flat = flat.permute(0, 3, 1, 2)
        if self.downsample > 1:  # pool first: the copy below then moves a fraction of the pixels
            flat = self.pool(flat.float())
        flat = flat.to(dtype=th.float32, memory_format=th.channels_last)
        if self.normalize:
            flat = flat / 255.0
        return self.linear(self.cnn(flat))

    @staticmethod
    def index(embeddings: th.Tensor, index: th.Tensor) -> th.Tensor:
        """Row ``index`` of ``embeddings`` ``[U, D]`` at each position, zeros where ``index`` is U."""
        return th.cat([embeddings, embeddings.new_zeros(1, embeddings.shape[1])])[index]

    def embed_pair(
        self, current: DistinctFrames, following: DistinctFrames, shared: int
    ) -> Tuple[th.Tensor, th.Tensor]:
        """The embeddings of a batch's states s (with gradient) and next states s' (without), each
        distinct frame through the CNN once: a frame that is both some row's s and some row's s'
        (a blocked move, consecutive transitions of an episode) reuses its s pass.

        ``current`` and ``following`` share their first and last ``shared`` frames: those of
        ``current.frames[-shared:]`` are ``following.frames[:shared]`` (how
        :meth:`~sb3_dream.dream.buffers.ExecutionBuffer.batch` lays them out).
        """
        e_current = self.embed_frames(current.frames)
        with th.no_grad():
            reused = e_current[len(e_current) - shared :].detach()
            e_following = th.cat([reused, self.embed_frames(following.frames[shared:])])
        return self.index(e_current, current.index), self.index(e_following, following.index)


def make_state_embedder(
    space: spaces.Space,
    per_dim: int = 32,
    hidden_dims: Sequence[int] = (256, 64),
    image_embed_dim: int = 128,
    image_channels: int = 32,
    discrete_embed_dim: Optional[int] = None,
    name: str = "obs",
    normalize_images: bool = True,
    image_downsample: int = 1,
) -> nn.Module:
    """The paper's embedder for a state-like space (``obs``, ``instruction``, a problem ID).

    ``MultiDiscrete`` -> :class:`MultiDiscreteEmbedder`; ``Discrete(n)`` -> the same with ``nvec=[n]``
    (or a plain embedding of ``discrete_embed_dim`` units if given); uint8 image ``Box`` ->
    :class:`ImageEmbedder`; other ``Box``/``MultiBinary`` -> :class:`BoxMLPEmbedder`.
    The returned module has an ``embed_dim`` attribute.

    :param name: the Dict key (only used in error messages).
    :param image_downsample: images only: average-pool each frame by this factor first (see
        :class:`ImageEmbedder`; 1, the paper's CNN, by default).
    """
    if isinstance(space, spaces.MultiDiscrete):
        if np.any(np.asarray(space.start) != 0):
            raise ValueError(
                f"observation_space[{name!r}]: MultiDiscrete spaces with a non-zero start are not supported"
            )
        return MultiDiscreteEmbedder(space.nvec, per_dim, hidden_dims)
    if isinstance(space, spaces.Discrete):
        if discrete_embed_dim is not None:
            return DiscreteEmbedder(int(space.n), discrete_embed_dim, start=int(space.start))
        if int(space.start) != 0:
            raise ValueError(f"observation_space[{name!r}]: Discrete spaces with a non-zero start are not supported")
        emb = MultiDiscreteEmbedder(np.array([int(space.n)]), per_dim, hidden_dims)
        emb.event_shape = ()  # a Discrete value has no event dims
        return emb
    if isinstance(space, spaces.Box) and is_image_space(space, check_channels=False, normalized_image=False):
        return ImageEmbedder(
            space,
            channels=image_channels,
            embed_dim=image_embed_dim,
            normalize=normalize_images,
            downsample=image_downsample,
        )
    if isinstance(space, (spaces.Box, spaces.MultiBinary)):
        return BoxMLPEmbedder(space.shape, hidden_dims)
    raise ValueError(
        f"observation_space[{name!r}] is {space}: accepted spaces are MultiDiscrete, Discrete, "
        "Box (uint8 HxWxC or CxHxW images, or float vectors) and MultiBinary"
    )


def embed_dict(embedders: nn.ModuleDict, obs: Dict[str, th.Tensor]) -> th.Tensor:
    """Embed every key of ``obs`` that has an embedder and concatenate along the last dim."""
    return th.cat([embedders[k](obs[k]) for k in embedders.keys()], dim=-1)


# Keys of the trial envs' Dict observation (see dream_envs.trial_env) that the recurrent Q-networks embed.
TRIAL_KEYS = ("obs", "instruction", "episode_start", "prev_action", "prev_reward", "final_obs")
# Keys that may be present but are not embedded: the phase is implied by the episode-start flags.
IGNORED_KEYS = ("phase",)


class TrialInputEmbedder(nn.Module):
    """Embeds one step of a trial env's Dict observation: the RL² input of the paper (Appendix B.3).

    ``e(s)`` (``obs``: :func:`make_state_embedder`, 64 units, 128 for images), ``e(i)``
    (``instruction``: 64), ``e(a)`` (``prev_action``: embedding matrix, 16), ``e(r)``
    (``prev_reward``: linear, 16), ``e(d)`` (``episode_start``: embedding matrix, 16), concatenated.
    Only ``obs`` is required; the other keys are embedded when the space has them and ``keys``
    lists them. The optional ``final_obs`` key (see :class:`sb3_dream.common.wrappers.FinalObsWrapper`)
    goes through the *same* state embedder as ``obs`` and is multiplied by the ``episode_start``
    flag, as it only holds a state on the first step of an inner episode.

    :param observation_space: a Dict space with at least an ``obs`` key.
    :param keys: which keys to embed if present (default: all of :data:`TRIAL_KEYS`).
    :param normalize_images: divide image observations by 255.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        keys: Sequence[str] = TRIAL_KEYS,
        per_dim: int = 32,
        state_hidden_dims: Sequence[int] = (256, 64),
        image_embed_dim: int = 128,
        instruction_embed_dim: int = 64,
        action_embed_dim: int = 16,
        reward_embed_dim: int = 16,
        done_embed_dim: int = 16,
        normalize_images: bool = True,
    ) -> None:
        super().__init__()
        check_trial_observation_space(observation_space, keys)
        sp = observation_space.spaces
        self.keys = [k for k in keys if k in sp]
        self.embedders = nn.ModuleDict()
        self.embedders["obs"] = make_state_embedder(
            sp["obs"],
            per_dim,
            state_hidden_dims,
            image_embed_dim=image_embed_dim,
            name="obs",
            normalize_images=normalize_images,
        )
        if "instruction" in self.keys:
            self.embedders["instruction"] = make_state_embedder(
                sp["instruction"], per_dim, (state_hidden_dims[0], instruction_embed_dim), name="instruction"
            )
        if "prev_action" in self.keys:
            self.embedders["prev_action"] = DiscreteEmbedder(
                int(sp["prev_action"].n), action_embed_dim, start=int(sp["prev_action"].start)
            )
        if "prev_reward" in self.keys:
            self.embedders["prev_reward"] = LinearEmbedder(sp["prev_reward"].shape, reward_embed_dim)
        if "episode_start" in self.keys:
            self.embedders["episode_start"] = DiscreteEmbedder(
                int(sp["episode_start"].n), done_embed_dim, start=int(sp["episode_start"].start)
            )
        self.use_final_obs = "final_obs" in self.keys
        self.embed_dim = sum(int(m.embed_dim) for m in self.embedders.values())
        if self.use_final_obs:
            self.embed_dim += int(self.embedders["obs"].embed_dim)

    def forward(self, obs: Dict[str, th.Tensor]) -> th.Tensor:
        """``obs[k]``: ``[*batch, *space[k].shape]`` -> ``[*batch, embed_dim]``."""
        parts = [self.embedders[k](obs[k]) for k in self.embedders.keys()]
        if self.use_final_obs:
            e_final = self.embedders["obs"](obs["final_obs"])
            if "episode_start" in obs:
                e_final = e_final * obs["episode_start"].reshape(e_final.shape[:-1]).unsqueeze(-1).float()
            parts.append(e_final)
        return th.cat(parts, dim=-1)


_EXPECTED_KEY_SPACES = {
    "instruction": (spaces.MultiDiscrete, spaces.Discrete),
    "episode_start": (spaces.Discrete,),
    "prev_action": (spaces.Discrete,),
    "prev_reward": (spaces.Box,),
}


def check_trial_observation_space(observation_space: spaces.Space, keys: Sequence[str] = TRIAL_KEYS) -> None:
    """Raise a ``ValueError`` unless ``observation_space`` is a Dict the trial embedders can handle."""
    accepted = ", ".join(repr(k) for k in (*TRIAL_KEYS, *IGNORED_KEYS))
    if not isinstance(observation_space, spaces.Dict):
        raise ValueError(
            f"observation_space must be a gymnasium.spaces.Dict with at least the key 'obs' (accepted keys: "
            f"{accepted}), got {observation_space}. Wrap a plain env with "
            "sb3_dream.common.wrappers.RL2ObservationWrapper (adds prev_action, prev_reward)."
        )
    sp = observation_space.spaces
    if "obs" not in sp:
        raise ValueError(f"observation_space is missing the key 'obs' (has {sorted(sp)}; accepted keys: {accepted})")
    unknown = sorted(set(sp) - set(TRIAL_KEYS) - set(IGNORED_KEYS))
    if unknown:
        raise ValueError(f"observation_space has unsupported keys {unknown}; accepted keys: {accepted}")
    for key, types in _EXPECTED_KEY_SPACES.items():
        if key in sp and key in keys and not isinstance(sp[key], types):
            names = " or ".join(t.__name__ for t in types)
            raise ValueError(f"observation_space[{key!r}] must be {names}, got {sp[key]}")
    if "final_obs" in sp and sp["final_obs"] != sp["obs"]:
        raise ValueError(f"observation_space['final_obs'] must equal observation_space['obs'], got {sp['final_obs']}")
