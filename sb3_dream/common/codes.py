"""Statistics of learned codes (DREAM's f(T) and g, IMPORT's e(T) and e(tau)) that the diagnostics report."""

from __future__ import annotations

import numpy as np


def mean_pair_sq_distance(codes: np.ndarray) -> float:
    """The mean of ||c_j - c_k||^2 over ordered pairs j != k of the rows of ``codes`` [n, z], the
    scale a code's error is read against; without the [n, n, z] tensor of differences."""
    codes = np.asarray(codes, dtype=np.float64)
    n = len(codes)
    pair_sum = 2 * n * (codes**2).sum() - 2 * (codes.sum(axis=0) ** 2).sum()
    return float(pair_sum / max(1, n * (n - 1)))
