"""sb3_dream.common.embedders: the batched shortcut computes the same function and gradients."""

from __future__ import annotations

import numpy as np
import torch as th

from sb3_dream.common.embedders import MultiDiscreteEmbedder


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
