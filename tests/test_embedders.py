"""sb3_dream.common.embedders: the batched shortcuts and layouts compute the same function and gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from sb3_dream.common.embedders import ImageEmbedder, MultiDiscreteEmbedder


def test_multidiscrete_embedder_runs_distinct_values_once_with_the_same_result():
    th.manual_seed(0)
    emb = MultiDiscreteEmbedder(np.array([9, 9, 5, 25]))
    few = th.stack([th.randint(0, n, (40,)) for n in (9, 9, 5, 25)], dim=1)
    x = few[th.randint(0, 40, (600,))].reshape(200, 3, 4)  # many rows, few distinct values
    assert x.reshape(-1, 4).shape[0] >= emb.dedup_min_rows

    calls = []
    handle = emb.mlp.register_forward_hook(lambda module, inputs, output: calls.append(inputs[0].shape[0]))
    out = emb(x)
    (out**2).sum().backward()
    grads = [p.grad.clone() for p in emb.parameters()]
    handle.remove()
    assert out.shape == (200, 3, emb.embed_dim)
    assert calls == [len(th.unique(few, dim=0))]  # the MLP saw each distinct value once

    emb.zero_grad()
    emb.dedup_min_rows = 10**9  # row by row, as in a small batch
    ref = emb(x)
    (ref**2).sum().backward()
    th.testing.assert_close(out, ref)
    for g, g_ref in zip(grads, (p.grad for p in emb.parameters())):
        # equal up to float summation order (sums over 600 rows vs over their distinct values)
        assert (g - g_ref).abs().max() <= 1e-5 * g_ref.abs().max()


def test_multidiscrete_embedder_takes_an_empty_batch():
    emb = MultiDiscreteEmbedder(np.array([9, 9, 5]))
    for batch in [(0,), (0, 4), (4, 0)]:
        out = emb(th.zeros(*batch, 3, dtype=th.long))
        assert out.shape == (*batch, emb.embed_dim)


def _reference_cnn(emb: ImageEmbedder, frames: th.Tensor) -> th.Tensor:
    """The paper's CNN written out layer by layer on channel-first float frames."""
    x = frames.float() / 255.0
    for layer in emb.cnn:
        x = layer(x)
    return emb.linear(x)


def test_image_embedder_runs_channels_last_with_the_channel_first_result():
    th.manual_seed(0)
    space = spaces.Box(0, 255, shape=(3, 60, 80), dtype=np.uint8)
    emb = ImageEmbedder(space)
    frames = th.randint(0, 256, (2, 5, 3, 60, 80), dtype=th.uint8)
    layouts = []
    handle = emb.cnn[0].register_forward_hook(
        lambda m, i, o: layouts.append(i[0].is_contiguous(memory_format=th.channels_last))
    )
    out = emb(frames)
    handle.remove()
    assert layouts == [True] and out.shape == (2, 5, 128)
    ref = _reference_cnn(emb, frames.reshape(10, 3, 60, 80)).reshape(2, 5, 128)
    th.testing.assert_close(out, ref, rtol=1e-5, atol=1e-6)
    # channel-last spaces (the env's own HxWxC frames) give the same embedding
    emb_hwc = ImageEmbedder(spaces.Box(0, 255, shape=(60, 80, 3), dtype=np.uint8))
    emb_hwc.load_state_dict(emb.state_dict())
    th.testing.assert_close(emb_hwc(frames.permute(0, 1, 3, 4, 2)), out, rtol=1e-5, atol=1e-6)


def test_image_downsample_averages_each_2x2_block_before_the_cnn():
    th.manual_seed(0)
    space = spaces.Box(0, 255, shape=(3, 60, 80), dtype=np.uint8)
    emb = ImageEmbedder(space, downsample=2)
    frames = th.randint(0, 256, (6, 3, 60, 80), dtype=th.uint8)
    blocks = frames.float().reshape(6, 3, 30, 2, 40, 2).mean(dim=(3, 5))  # 40 x 30 frames
    ref = _reference_cnn(emb, blocks)
    th.testing.assert_close(emb(frames), ref, rtol=1e-5, atol=1e-6)
    assert emb.cnn(th.zeros(1, 3, 30, 40)).shape[1] == emb.linear[0].in_features == 64
    # no parameters of its own: a downsampling embedder's state dict has the paper's keys and shapes
    full = ImageEmbedder(space)
    assert {k: v.shape for k, v in emb.state_dict().items() if not k.startswith("linear")} == {
        k: v.shape for k, v in full.state_dict().items() if not k.startswith("linear")
    }


@pytest.mark.parametrize(
    "factor, message",
    [(0, "image_downsample must be an integer >= 1"), (2.0, "image_downsample must be an integer"),
     (3, "image_downsample=3 leaves 26 x 20 pixels")],
)  # fmt: skip
def test_image_downsample_rejects_bad_factors(factor, message):
    with pytest.raises(ValueError, match=message):
        ImageEmbedder(spaces.Box(0, 255, shape=(3, 60, 80), dtype=np.uint8), downsample=factor)
