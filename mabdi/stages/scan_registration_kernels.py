"""Compiled (numba) per-return work of scan-to-map registration (:mod:`mabdi.stages.scan_registration`).

:func:`scan_to_plane_system` is one Gauss-Newton step of projective point-to-plane ICP on a range image:
every return of the scan, moved by the current estimate, is projected into E's range image (the map drawn
from the scan's start pose), paired with the map point and normal E holds at that pixel, and adds its
robustly weighted row to the 6x6 normal equations. :func:`truncated_cost` scores a pose the same way.
Frames: points and E in the sensor frame of the start pose; ranges and lengths in metres.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mabdi.stages.registration_kernels import point_plane_jacobian


@njit(cache=True, inline="always")
def image_pixel(x, y, z, row_edges, columns):
    """(row, column) of the range-image pixel a sensor-frame point falls in, row -1 outside the image.
    ``row_edges``: :meth:`~mabdi.spherical.SphericalGeometry.row_edges` (radians, decreasing from the top edge);
    columns as :mod:`mabdi.spherical` lays them out (column 0 looks backwards over the left)."""
    horizontal = np.sqrt(x * x + y * y)
    elevation = np.arctan2(z, horizontal)
    rows = row_edges.shape[0] - 1
    if elevation > row_edges[0] or elevation <= row_edges[rows]:
        return -1, 0
    low, high = 0, rows  # row_edges[low] >= elevation > row_edges[high]
    while high - low > 1:
        middle = (low + high) // 2
        if row_edges[middle] >= elevation:
            low = middle
        else:
            high = middle
    azimuth = np.arctan2(y, x)
    column = int(np.floor(0.5 * (1.0 - azimuth / np.pi) * columns)) % columns
    return low, column


@njit(cache=True, inline="always")
def _pair(points, i, rotation, translation, e_points, e_normals, row_edges, columns, angle_reach, near_reach):
    """(state, q (moved point), n, residual along n): return i moved by (rotation, translation), paired with the
    map point and normal E holds at its pixel. State 2: paired; 1: E has a surface there, but its point lies
    farther from the return than ``near_reach`` (m) plus ``angle_reach`` (radians) of the return's range
    (another surface seen in the same pixel); 0: E has none there."""
    px, py, pz = points[i, 0], points[i, 1], points[i, 2]
    qx = rotation[0, 0] * px + rotation[0, 1] * py + rotation[0, 2] * pz + translation[0]
    qy = rotation[1, 0] * px + rotation[1, 1] * py + rotation[1, 2] * pz + translation[1]
    qz = rotation[2, 0] * px + rotation[2, 1] * py + rotation[2, 2] * pz + translation[2]
    row, column = image_pixel(qx, qy, qz, row_edges, columns)
    if row < 0:
        return 0, qx, qy, qz, 0.0, 0.0, 0.0, 0.0
    nx, ny, nz = e_normals[row, column, 0], e_normals[row, column, 1], e_normals[row, column, 2]
    if not np.isfinite(nx):
        return 0, qx, qy, qz, 0.0, 0.0, 0.0, 0.0
    dx = qx - e_points[row, column, 0]
    dy = qy - e_points[row, column, 1]
    dz = qz - e_points[row, column, 2]
    reach = near_reach + angle_reach * np.sqrt(qx * qx + qy * qy + qz * qz)
    if dx * dx + dy * dy + dz * dz > reach * reach:
        return 1, qx, qy, qz, 0.0, 0.0, 0.0, 0.0
    return 2, qx, qy, qz, nx, ny, nz, nx * dx + ny * dy + nz * dz


@njit(cache=True, nogil=True)
def scan_to_plane_system(points, rotation, translation, e_points, e_normals, row_edges, columns, angle_reach, gate, huber):
    """One step's normal equations: (A (6x6), b (6,), |residuals| (pairs,)) of the returns ``points`` (N, 3)
    paired within ``gate`` (m) of E's planes, Huber-weighted beyond ``huber`` (m). The step (rotation vector,
    translation) is left of the estimate, in the sensor frame of the start pose."""
    a = np.zeros((6, 6))
    b = np.zeros(6)
    jac = np.zeros(6)
    residuals = np.empty(points.shape[0])
    count = 0
    for i in range(points.shape[0]):
        state, qx, qy, qz, nx, ny, nz, r = _pair(points, i, rotation, translation, e_points, e_normals, row_edges, columns, angle_reach, gate)
        if state < 2 or abs(r) > gate:
            continue
        weight = 1.0 if abs(r) <= huber else huber / abs(r)
        point_plane_jacobian(jac, qx, qy, qz, nx, ny, nz)
        for j in range(6):
            b[j] += weight * jac[j] * r
            for k in range(j, 6):
                a[j, k] += weight * jac[j] * jac[k]
        residuals[count] = abs(r)
        count += 1
    for j in range(6):
        for k in range(j):
            a[j, k] = a[k, j]
    return a, b, residuals[:count]


@njit(cache=True, nogil=True)
def truncated_cost(points, rotation, translation, e_points, e_normals, row_edges, columns, angle_reach, gate):
    """(cost, seen): how well a pose fits the returns to the map: the mean of min(r, gate)^2 (m^2) over the
    returns whose pixel shows the map (one paired beyond the gate, or not paired, costs the gate's square),
    and how many did."""
    total = 0.0
    seen = 0
    for i in range(points.shape[0]):
        state, qx, qy, qz, nx, ny, nz, r = _pair(points, i, rotation, translation, e_points, e_normals, row_edges, columns, angle_reach, gate)
        if state == 0:
            continue
        total += min(r * r, gate * gate) if state == 2 else gate * gate
        seen += 1
    return (total / seen if seen else np.nan), seen


@njit(cache=True, inline="always")
def _nearer(ranges, row, column, other_row, other_column, best_jump):
    """The jump (m) to neighbour (other_row, other_column) when it has a range and is nearer in range than
    ``best_jump``, else ``best_jump``."""
    value = ranges[other_row, other_column]
    if not np.isfinite(value):
        return best_jump
    jump = abs(value - ranges[row, column])
    return jump if jump < best_jump else best_jump


@njit(cache=True, nogil=True)
def points_and_normals(ranges, rays, max_jump):
    """E's points and unit normals (H, W, 3) float64 in the sensor frame from its ``ranges`` (H, W; NaN: no map)
    and unit ``rays`` (H, W, 3); see :func:`mabdi.stages.scan_registration.map_points_and_normals`."""
    h, w = ranges.shape
    points = np.full((h, w, 3), np.nan)
    normals = np.full((h, w, 3), np.nan)
    for row in range(h):
        for column in range(w):
            value = ranges[row, column]
            if np.isfinite(value):
                for k in range(3):
                    points[row, column, k] = value * rays[row, column, k]
    for row in range(h):
        for column in range(w):
            value = ranges[row, column]
            if not np.isfinite(value):
                continue
            reach = max_jump * value
            # across the beams (columns wrap around): the neighbour nearer in range, as a difference
            left, right = (column - 1) % w, (column + 1) % w
            jump_left = _nearer(ranges, row, column, row, left, np.inf)
            jump_right = _nearer(ranges, row, column, row, right, np.inf)
            if min(jump_left, jump_right) > reach:
                continue
            other = right if jump_right < jump_left else left
            sign = 1.0 if other == right else -1.0
            ax = sign * (points[row, other, 0] - points[row, column, 0])
            ay = sign * (points[row, other, 1] - points[row, column, 1])
            az = sign * (points[row, other, 2] - points[row, column, 2])
            # along the beams (rows do not wrap)
            jump_up = _nearer(ranges, row, column, row - 1, column, np.inf) if row > 0 else np.inf
            jump_down = _nearer(ranges, row, column, row + 1, column, np.inf) if row < h - 1 else np.inf
            if min(jump_up, jump_down) > reach:
                continue
            other_row = row + 1 if jump_down < jump_up else row - 1
            sign = 1.0 if other_row == row + 1 else -1.0
            bx = sign * (points[other_row, column, 0] - points[row, column, 0])
            by = sign * (points[other_row, column, 1] - points[row, column, 1])
            bz = sign * (points[other_row, column, 2] - points[row, column, 2])
            nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
            length = np.sqrt(nx * nx + ny * ny + nz * nz)
            if not length > 0.0:
                continue
            if nx * points[row, column, 0] + ny * points[row, column, 1] + nz * points[row, column, 2] > 0.0:
                length = -length  # facing the sensor
            normals[row, column, 0] = nx / length
            normals[row, column, 1] = ny / length
            normals[row, column, 2] = nz / length
    return points, normals
