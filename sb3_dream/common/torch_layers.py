"""Embedders and heads shared by DREAM's networks (paper, Appendix B.3).

* MultiDiscrete states, instructions and problem IDs: each dimension gets its own 32-d embedding
  table; the concatenation goes through Linear 256 -> ReLU -> Linear 64 (-> ReLU).
* Images (uint8 HxWx3): 3 conv layers of 32 channels, kernels 5/5/4, stride 2, ReLU, then a
  linear layer to 128 (the architecture recommended for MiniWorld).
* Dueling head: Q = V + A - mean_a A.

Embedders take tensors with any number of leading batch dims (``[B, ...]`` or ``[B, T, ...]``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch as th
from gymnasium import spaces
from torch import nn


class MultiDiscreteEmbedder(nn.Module):
    """Per-dimension embedding tables (one fused table with offsets), then an MLP 256 -> ``out_dim``."""

    def __init__(
        self, nvec: Sequence[int], out_dim: int = 64, embed_dim: int = 32, hidden: int = 256, final_activation: bool = True
    ) -> None:
        super().__init__()
        nvec = np.asarray(nvec, dtype=np.int64).reshape(-1)
        self.register_buffer("offsets", th.as_tensor(np.concatenate([[0], np.cumsum(nvec)[:-1]]), dtype=th.long))
        self.table = nn.Embedding(int(nvec.sum()), embed_dim)
        layers = [nn.Linear(len(nvec) * embed_dim, hidden), nn.ReLU(), nn.Linear(hidden, out_dim)]
        self.mlp = nn.Sequential(*layers, *([nn.ReLU()] if final_activation else []))
        self.out_dim = out_dim

    def forward(self, x: th.Tensor) -> th.Tensor:
        e = self.table(x.long() + self.offsets)  # [..., D, embed_dim]
        return self.mlp(e.flatten(-2))


class ImageEmbedder(nn.Module):
    """uint8 ``[..., H, W, C]`` images -> 3 conv layers (32 ch, kernels 5/5/4, stride 2) -> Linear 128."""

    def __init__(self, shape: Sequence[int], out_dim: int = 128) -> None:
        super().__init__()
        h, w, c = shape
        self.conv = nn.Sequential(
            nn.Conv2d(c, 32, 5, stride=2), nn.ReLU(), nn.Conv2d(32, 32, 5, stride=2), nn.ReLU(),
            nn.Conv2d(32, 32, 4, stride=2), nn.ReLU(), nn.Flatten(),
        )
        with th.no_grad():
            n_flat = self.conv(th.zeros(1, c, h, w)).shape[1]
        self.linear = nn.Linear(n_flat, out_dim)
        self.shape, self.out_dim = tuple(shape), out_dim

    def forward(self, x: th.Tensor) -> th.Tensor:
        lead = x.shape[: -3]
        x = x.reshape(-1, *self.shape).permute(0, 3, 1, 2).float() / 255.0
        return self.linear(self.conv(x)).reshape(*lead, self.out_dim)


class BoxEmbedder(nn.Module):
    """Float vectors: Linear 256 -> ReLU -> Linear ``out_dim`` -> ReLU."""

    def __init__(self, dim: int, out_dim: int = 64) -> None:
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(dim, 256), nn.ReLU(), nn.Linear(256, out_dim), nn.ReLU())
        self.dim, self.out_dim = dim, out_dim

    def forward(self, x: th.Tensor) -> th.Tensor:
        return self.mlp(x.float())


def is_image_space(space: spaces.Space) -> bool:
    return isinstance(space, spaces.Box) and space.dtype == np.uint8 and len(space.shape) == 3


def make_embedder(space: spaces.Space, out_dim: int = 64) -> nn.Module:
    """The paper's state embedder for ``space`` (images get 128 dims, as in the paper)."""
    if isinstance(space, spaces.MultiDiscrete):
        return MultiDiscreteEmbedder(space.nvec, out_dim=out_dim)
    if isinstance(space, spaces.Discrete):
        return MultiDiscreteEmbedder([space.n], out_dim=out_dim)
    if is_image_space(space):
        return ImageEmbedder(space.shape)
    if isinstance(space, spaces.Box) and len(space.shape) == 1:
        return BoxEmbedder(space.shape[0], out_dim=out_dim)
    raise TypeError(
        f"no embedder for observation space {space}: supported are MultiDiscrete, Discrete, "
        "uint8 HxWxC images and 1-d Box"
    )


class DuelingHead(nn.Module):
    """Two linear heads, value and advantages: Q = V + A - mean_a A (Wang et al., 2016)."""

    def __init__(self, in_dim: int, n_actions: int) -> None:
        super().__init__()
        self.value = nn.Linear(in_dim, 1)
        self.advantage = nn.Linear(in_dim, n_actions)

    def forward(self, x: th.Tensor) -> th.Tensor:
        a = self.advantage(x)
        return self.value(x) + a - a.mean(dim=-1, keepdim=True)
