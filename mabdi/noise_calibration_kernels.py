"""Compiled (numba) binning of one frame's residuals for :mod:`mabdi.noise_calibration`.

:func:`add_residuals_kernel` does in two passes over the sampled pixels what
the array formulation did with a stable sort by depth bin: each bin's ring
takes the frame's last ``samples_per_bin`` counted residuals, in row-major
order, after those it holds.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def add_residuals_kernel(
    measured, expected, skip, use_skip, stride, floor2, coefficient, gate_k, min_gate, edges, residuals, added
):  # fmt: skip
    """Add |D - E| (metres) of every ``stride``-th pixel of ``measured`` and ``expected`` (NaN: none; ``skip``:
    pixels left out where ``use_skip``) that lies within max(``gate_k`` sigma(E), ``min_gate``), sigma(z) =
    sqrt(``floor2`` + (``coefficient`` z^2)^2), to the ring of its depth bin (``edges``): ``residuals`` (bins,
    samples per bin) and ``added`` (residuals ever added per bin) change in place. Returns how many were counted."""
    height, width = measured.shape
    bins = added.shape[0]
    capacity = residuals.shape[1]
    rows = (height + stride - 1) // stride
    columns = (width + stride - 1) // stride
    which = np.empty(rows * columns, dtype=np.int64)
    values = np.empty(rows * columns, dtype=np.float64)
    counts = np.zeros(bins, dtype=np.int64)
    n = 0
    for r in range(0, height, stride):
        for c in range(0, width, stride):
            d = np.float64(measured[r, c])
            e = np.float64(expected[r, c])
            if not (np.isfinite(d) and np.isfinite(e)) or (use_skip and skip[r, c]):
                continue
            residual = abs(d - e)
            term = coefficient * e * e
            gate = gate_k * np.sqrt(floor2 + term * term)
            if gate < min_gate:
                gate = min_gate
            if not residual <= gate:
                continue
            b = np.searchsorted(edges, e, side="right") - 1
            if b < 0 or b >= bins:
                continue
            which[n] = b
            values[n] = residual
            counts[b] += 1
            n += 1
    seen = np.zeros(bins, dtype=np.int64)
    for i in range(n):
        b = which[i]
        j = seen[b]
        seen[b] += 1
        first = max(counts[b] - capacity, 0)  # only a bin's last `capacity` of this frame are kept
        if j >= first:
            residuals[b, (added[b] + j - first) % capacity] = values[i]
    for b in range(bins):
        added[b] += min(counts[b], capacity)
    return n
