"""Compiled (numba) per-pixel work of frame-to-map registration (:mod:`mabdi.filters.registration`).

:func:`point_to_plane_system` is one Gauss-Newton step of projective
point-to-plane ICP: every sampled point of D, moved by the current estimate,
is projected into E's image, paired with the map point and normal E shows at
that pixel, and adds its robustly weighted row to the 6x6 normal equations.
:func:`pose_sigma_image` turns a pose covariance into each pixel's depth
uncertainty. Both read E's points and normals straight from its depth image
(:func:`point_and_normal`), so no image-sized temporaries are made.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def point_and_normal(depth, row, col, fx, fy, cx, cy, step, max_jump):
    """(ok, x, y, z, nx, ny, nz): pixel (row, col)'s camera-frame point (m) and unit normal, facing the camera.

    The normal is the cross product of the central differences over ``step``
    pixels in u and in v. There is none (ok False) at the image border, where
    the pixel or a neighbour has no depth, or where a neighbour differs from
    it by more than ``max_jump`` times its depth (a silhouette: the two sides
    are different surfaces).
    """
    height, width = depth.shape
    if row < step or col < step or row >= height - step or col >= width - step:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    z = np.float64(depth[row, col])
    left = np.float64(depth[row, col - step])
    right = np.float64(depth[row, col + step])
    up = np.float64(depth[row - step, col])
    down = np.float64(depth[row + step, col])
    limit = max_jump * z
    if not (abs(left - z) <= limit and abs(right - z) <= limit and abs(up - z) <= limit and abs(down - z) <= limit):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0  # also for NaN in the pixel or a neighbour
    ax = (col + 0.5 - cx) / fx
    ay = (row + 0.5 - cy) / fy
    x = ax * z
    y = ay * z
    # u difference: points at columns col +- step (same row); v difference: rows row +- step (same column)
    ux = (col + step + 0.5 - cx) / fx * right - (col - step + 0.5 - cx) / fx * left
    uy = ay * (right - left)
    uz = right - left
    vx = ax * (down - up)
    vy = (row + step + 0.5 - cy) / fy * down - (row - step + 0.5 - cy) / fy * up
    vz = down - up
    nx = uy * vz - uz * vy
    ny = uz * vx - ux * vz
    nz = ux * vy - uy * vx
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    if norm == 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    if nx * x + ny * y + nz * z > 0.0:
        norm = -norm
    return True, x, y, z, nx / norm, ny / norm, nz / norm


@njit(cache=True, inline="always")
def point_plane_jacobian(jac, x, y, z, nx, ny, nz):
    """``jac`` = d(n . p) / d(omega, t) = (p x n, n): how a point p's distance along the normal n moves under a
    small pose change (rotation vector omega, translation t)."""
    jac[0] = y * nz - z * ny
    jac[1] = z * nx - x * nz
    jac[2] = x * ny - y * nx
    jac[3] = nx
    jac[4] = ny
    jac[5] = nz


@njit(cache=True)
def point_to_plane_system(
    points, tiles, n_tiles, scale, gate, rotation, translation, e_depth, fx, fy, cx, cy, step, max_jump, huber, summaries=True
):
    """Normal equations of one ICP step in E's camera frame.

    ``points`` (N, 3): D's sampled points in D's camera frame (m); ``tiles``
    (N,): the image tile (0 .. ``n_tiles`` - 1) each point was sampled in; ``scale``
    (N,): each point's noise (m), the unit of its residual; ``gate`` (N,):
    the largest residual (m) a pair may have; ``rotation``, ``translation``:
    the current estimate of E-camera from D-camera; ``e_depth`` (H, W): E,
    metric depth, NaN where the map has no surface; ``step`` and
    ``max_jump``: E's normals (:func:`point_and_normal`); ``huber``: the
    Huber threshold in units of ``scale`` (0: Tukey's biweight over the
    gate). Parameters are (rotation vector, translation), a left
    perturbation of the estimate.

    Returns (A (6, 6), b (6,), chi2, pairs, candidates, residuals, support,
    tile_gradients): A x = -b is the step; tile_gradients (n_tiles, 6) is b
    summed per tile (its spread says how correlated the residuals are); chi2 is the weighted sum of squared normalised
    residuals; pairs the points within their gate; candidates the points that
    landed on a pixel of E with a normal; residuals (candidates,) their
    absolute residuals (m); support (2, 6, 6) the information J^T J / s^2 of
    the pairs and of all candidates, without the robust weights (which
    directions the pairs constrain, against what the map could constrain).
    ``summaries`` False leaves support and tile_gradients at zero (the steps
    before the last need only A and b).
    """
    height, width = e_depth.shape
    n = points.shape[0]
    a = np.zeros((6, 6))
    b = np.zeros(6)
    chi2 = 0.0
    pairs = 0
    candidates = 0
    residuals = np.empty(n)
    support = np.zeros((2, 6, 6))
    tile_gradients = np.zeros((n_tiles, 6))
    jac = np.zeros(6)
    for i in range(n):
        x = rotation[0, 0] * points[i, 0] + rotation[0, 1] * points[i, 1] + rotation[0, 2] * points[i, 2] + translation[0]
        y = rotation[1, 0] * points[i, 0] + rotation[1, 1] * points[i, 1] + rotation[1, 2] * points[i, 2] + translation[1]
        z = rotation[2, 0] * points[i, 0] + rotation[2, 1] * points[i, 1] + rotation[2, 2] * points[i, 2] + translation[2]
        if z <= 0.0:
            continue
        u = fx * x / z + cx  # pixel (u, v) covers [u, u + 1) x [v, v + 1)
        v = fy * y / z + cy
        if not (u >= 0.0 and v >= 0.0 and u < width and v < height):
            continue
        ok, qx, qy, qz, nx, ny, nz = point_and_normal(e_depth, int(v), int(u), fx, fy, cx, cy, step, max_jump)
        if not ok:
            continue
        r = nx * (x - qx) + ny * (y - qy) + nz * (z - qz)
        residuals[candidates] = abs(r)
        candidates += 1
        point_plane_jacobian(jac, x, y, z, nx, ny, nz)
        s = scale[i]
        g = gate[i]
        inside = abs(r) <= g and abs(z - qz) <= 2.0 * g
        if summaries:
            inverse_variance = 1.0 / (s * s)
            for j in range(6):
                for k in range(j, 6):
                    information = jac[j] * jac[k] * inverse_variance
                    support[1, j, k] += information
                    if inside:
                        support[0, j, k] += information
        if not inside:
            continue
        pairs += 1
        if huber > 0.0:
            e = abs(r) / s
            w = 1.0 if e <= huber else huber / e
        else:  # Tukey's biweight over the gate: full weight at 0, none at the gate
            e = r / g
            w = (1.0 - e * e) ** 2
        w /= s * s
        for j in range(6):
            wj = w * jac[j]
            b[j] += wj * r
            if summaries:
                tile_gradients[tiles[i], j] += wj * r
            for k in range(j, 6):
                a[j, k] += wj * jac[k]
        chi2 += w * r * r
    for j in range(6):
        for k in range(j):
            a[j, k] = a[k, j]
            support[0, j, k] = support[0, k, j]
            support[1, j, k] = support[1, k, j]
    return a, b, chi2, pairs, candidates, residuals[:candidates], support, tile_gradients


@njit(cache=True)
def pose_sigma_image(e_depth, fx, fy, cx, cy, step, max_jump, covariance, min_cosine):
    """(H, W) float32 depth standard deviation (m) that the pose covariance causes at each pixel of E.

    See :func:`mabdi.filters.registration.pose_depth_sigma`. NaN where E has no surface.
    """
    height, width = e_depth.shape
    sigma = np.full((height, width), np.nan, dtype=np.float32)
    jac = np.zeros(6)
    for row in range(height):
        for col in range(width):
            depth = np.float64(e_depth[row, col])
            if not np.isfinite(depth):
                continue
            ok, x, y, z, nx, ny, nz = point_and_normal(e_depth, row, col, fx, fy, cx, cy, step, max_jump)
            distance = 0.0
            if not ok:  # a silhouette or the border: head-on
                z = depth
                x = (col + 0.5 - cx) / fx * z
                y = (row + 0.5 - cy) / fy * z
                distance = np.sqrt(x * x + y * y + z * z)
                nx, ny, nz = -x / distance, -y / distance, -z / distance
            else:
                distance = np.sqrt(x * x + y * y + z * z)
            point_plane_jacobian(jac, x, y, z, nx, ny, nz)
            variance = 0.0
            for j in range(6):
                for k in range(6):
                    variance += jac[j] * covariance[j, k] * jac[k]
            cosine = abs(nx * x + ny * y + nz * z) / distance
            if cosine < min_cosine:
                cosine = min_cosine
            sigma[row, col] = np.sqrt(max(variance, 0.0)) / cosine * z / distance
    return sigma
