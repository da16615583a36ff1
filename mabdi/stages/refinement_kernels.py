"""Compiled (numba) version of the refinement's per-pixel work on one block.

:func:`observe_block_kernel` applies the rules of
:mod:`mabdi.stages.refinement` one pixel at a time and straight into the
block's sums, instead of whole-array passes with (pixels, 3 corners, 3)
temporaries and a sort of the vertices in view. The numpy version it was
written from, ``observe_block``, is kept with the tests
(tests/reference_kernels.py), and a test checks that both agree on every
block call of a run.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def observe_block_kernel(
    triangles, points, original, normal, prior, weight, total,
    cells, rays, measured, expected, length, sd, centre,
    focal, cos_grazing, gate_k, replace, replace_ratio, replace_share, radius_px,
):  # fmt: skip
    """One block's pixels (``cells``: the face each shows; ``rays`` unit world rays, ``measured`` and
    ``expected`` z-depths D and E, ``length`` ray metres per metre of z-depth, ``sd`` sigma(D), ``centre`` the
    camera's position, ``focal`` in pixels): adds the observations to the block's ``weight`` and ``total`` in
    place (see :mod:`mabdi.stages.refinement`); returns (per pixel: its face is replaced, pixels that
    observed, vertices whose weight grew)."""
    n = len(cells)
    facing = np.zeros(n, dtype=np.bool_)
    same = np.zeros(n, dtype=np.bool_)
    better = np.zeros(n, dtype=np.bool_)
    cosine = np.zeros(n)
    any_better = False
    for i in range(n):
        f = cells[i]
        i0, i1, i2 = triangles[f, 0], triangles[f, 1], triangles[f, 2]
        e1x = np.float64(points[i1, 0]) - points[i0, 0]
        e1y = np.float64(points[i1, 1]) - points[i0, 1]
        e1z = np.float64(points[i1, 2]) - points[i0, 2]
        e2x = np.float64(points[i2, 0]) - points[i0, 0]
        e2y = np.float64(points[i2, 1]) - points[i0, 1]
        e2z = np.float64(points[i2, 2]) - points[i0, 2]
        nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
        norm = np.sqrt(nx * nx + ny * ny + nz * nz)
        if norm <= 0:
            continue
        c = abs(rays[i, 0] * nx + rays[i, 1] * ny + rays[i, 2] * nz) / norm
        if c < cos_grazing:
            continue
        facing[i] = True
        cosine[i] = c
        face_var = (1.0 / (prior[i0] + weight[i0]) + 1.0 / (prior[i1] + weight[i1]) + 1.0 / (prior[i2] + weight[i2])) / 3.0
        if abs(measured[i] - expected[i]) <= gate_k * np.sqrt(sd[i] * sd[i] + face_var):
            same[i] = True
            if face_var >= (replace_ratio * sd[i]) ** 2:
                better[i] = True
                any_better = True

    gone = np.zeros(n, dtype=np.bool_)
    if replace and any_better:
        votes = np.zeros(len(triangles))
        counts = np.zeros(len(triangles))
        for i in range(n):
            if facing[i]:
                counts[cells[i]] += 1.0
            if better[i]:
                votes[cells[i]] += 1.0
        for i in range(n):
            f = cells[i]
            gone[i] = votes[f] > 0 and votes[f] >= replace_share * counts[f]

    touched = np.zeros(len(points), dtype=np.bool_)
    observed = 0
    beta = np.empty(3)
    for i in range(n):
        if not same[i] or gone[i]:
            continue
        observed += 1
        f = cells[i]
        a = triangles[f, 0]
        e_ray = expected[i] * length[i]
        d_ray = measured[i] * length[i]
        hx, hy, hz = centre[0] + rays[i, 0] * e_ray, centre[1] + rays[i, 1] * e_ray, centre[2] + rays[i, 2] * e_ray
        # barycentric weights of the hit on the face (current positions), clipped to the face and normalised
        ax, ay, az = np.float64(points[a, 0]), np.float64(points[a, 1]), np.float64(points[a, 2])
        b, c3 = triangles[f, 1], triangles[f, 2]
        e1x, e1y, e1z = points[b, 0] - ax, points[b, 1] - ay, points[b, 2] - az
        e2x, e2y, e2z = points[c3, 0] - ax, points[c3, 1] - ay, points[c3, 2] - az
        vx, vy, vz = hx - ax, hy - ay, hz - az
        d00 = e1x * e1x + e1y * e1y + e1z * e1z
        d01 = e1x * e2x + e1y * e2y + e1z * e2z
        d11 = e2x * e2x + e2y * e2y + e2z * e2z
        d20 = vx * e1x + vy * e1y + vz * e1z
        d21 = vx * e2x + vy * e2y + vz * e2z
        denominator = d00 * d11 - d01 * d01
        if not denominator > 0:
            denominator = 1.0
        b1 = (d11 * d20 - d01 * d21) / denominator
        b2 = (d00 * d21 - d01 * d20) / denominator
        beta[0] = min(max(1.0 - b1 - b2, 0.0), 1.0)
        beta[1] = min(max(b1, 0.0), 1.0)
        beta[2] = min(max(b2, 0.0), 1.0)
        scale = max(beta[0] + beta[1] + beta[2], 1e-12)
        # the measured point on the pixel's ray at D
        residual = d_ray - e_ray
        mx, my, mz = hx + rays[i, 0] * residual, hy + rays[i, 1] * residual, hz + rays[i, 2] * residual
        radius = radius_px * measured[i] / focal
        information = cosine[i] / (sd[i] * sd[i])
        for k in range(3):
            v = triangles[f, k]
            tx, ty, tz = mx - original[v, 0], my - original[v, 1], mz - original[v, 2]
            s = normal[v, 0] * tx + normal[v, 1] * ty + normal[v, 2] * tz
            ux, uy, uz = tx - s * normal[v, 0], ty - s * normal[v, 1], tz - s * normal[v, 2]
            if np.sqrt(ux * ux + uy * uy + uz * uz) > radius:
                continue
            w = beta[k] / scale * information
            if w > 0:
                weight[v] += w
                total[v] += w * s
                touched[v] = True
    return gone, observed, np.flatnonzero(touched)


@njit(cache=True)
def match_kept_points_kernel(old, new):
    """For each row of ``new``, the index of the identical row of ``old``, where ``new`` is ``old`` with some
    rows taken out and the rest in their order (a block rebuilt with faces removed); None when it is not."""
    where = np.empty(len(new), dtype=np.int64)
    i = 0
    for j in range(len(new)):
        while i < len(old) and not (old[i, 0] == new[j, 0] and old[i, 1] == new[j, 1] and old[i, 2] == new[j, 2]):
            i += 1
        if i == len(old):
            return None
        where[j] = i
        i += 1
    return where
