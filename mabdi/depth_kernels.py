"""Numba kernels of :mod:`mabdi.depth`: the straight-line test on a point image's neighbouring samples."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def continues_kernel(points, sigma, start_v, start_u, step_v, step_u, sigmas, floor, spacing, out):
    """``out[v, u]`` = whether sample c lies on the straight line through samples a and b (:func:`mabdi.depth._continues`),
    where a = ``points[start_v + v, start_u + u]``, b = a's position plus (``step_v``, ``step_u``) and c = b's plus
    the same; ``sigma`` (H, W) is the samples' standard deviation (m). ``sigmas``, ``floor`` and ``spacing`` are
    LINE_SIGMAS, LINE_FLOOR and LINE_SPACING. NaN samples give False."""
    rows, cols = out.shape
    for v in range(rows):
        for u in range(cols):
            va, ua = start_v + v, start_u + u
            vb, ub = va + step_v, ua + step_u
            vc, uc = vb + step_v, ub + step_u
            sx = points[vb, ub, 0] - points[va, ua, 0]
            sy = points[vb, ub, 1] - points[va, ua, 1]
            sz = points[vb, ub, 2] - points[va, ua, 2]
            ax = points[vc, uc, 0] - points[vb, ub, 0]
            ay = points[vc, uc, 1] - points[vb, ub, 1]
            az = points[vc, uc, 2] - points[vb, ub, 2]
            length = np.sqrt(sx * sx + sy * sy + sz * sz)
            ratio = np.sqrt(ax * ax + ay * ay + az * az) / length
            along = (ax * sx + ay * sy + az * sz) / length
            cx = ay * sz - az * sy
            cy = az * sx - ax * sz
            cz = ax * sy - ay * sx
            off_line = np.sqrt(cx * cx + cy * cy + cz * cz) / length
            spread = sigma[vc, uc] * np.sqrt(1.0 + (1.0 + ratio) ** 2 + ratio**2)
            px, py, pz = points[vc, uc, 0], points[vc, uc, 1], points[vc, uc, 2]
            tolerance = sigmas * spread + floor * np.sqrt(px * px + py * py + pz * pz)
            out[v, u] = along > 0 and ratio <= spacing and ratio >= 1.0 / spacing and off_line <= tolerance
