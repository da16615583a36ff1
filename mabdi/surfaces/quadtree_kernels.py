"""Compiled (numba) versions of FilterQuadTree's per-pixel stages: reduce, normals, pyramid, residual.

Each function computes what its numpy reference computes (same rules, same
float32 pyramid), one pixel or node at a time instead of whole-array passes:
the numpy versions spend most of their time allocating and re-reading 640x480
temporaries. The numpy versions are kept with the tests, not in the package
(tests/reference_kernels.py: ``reduce_points``, ``point_normals``,
``build_leaves``, ``plane_residual``); a test compares the two on Run 1.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _block_median(depth, r, row, col, values, slots):
    """The lower median of block (row, col)'s valid values (r x r) and its slot a * r + b, or slot -1 without a
    valid majority (``values`` and ``slots``: scratch of r * r)."""
    count = 0
    for a in range(r):
        for b in range(r):
            z = depth[row * r + a, col * r + b]
            if np.isfinite(z):
                # insertion sort by depth, then slot (stable)
                k = count
                while k > 0 and values[k - 1] > z:
                    values[k] = values[k - 1]
                    slots[k] = slots[k - 1]
                    k -= 1
                values[k] = z
                slots[k] = a * r + b
                count += 1
    if 2 * count <= r * r:
        return np.nan, -1
    middle = (count - 1) // 2
    return values[middle], slots[middle]


@njit(cache=True)
def reduce_points_kernel(depth, r, fx, fy, cx, cy):
    """(h, w, 3) camera points of r x r blocks: the block's lower median pixel, back-projected (NaN: no majority)."""
    height, width = depth.shape
    h, w = height // r, width // r
    out = np.full((h, w, 3), np.nan)
    values = np.empty(r * r)
    slots = np.empty(r * r, dtype=np.int64)
    for row in range(h):
        for col in range(w):
            z, slot = _block_median(depth, r, row, col, values, slots)
            if slot < 0:
                continue
            u = col * r + slot % r + 0.5
            v = row * r + slot // r + 0.5
            out[row, col, 0] = (u - cx) / fx * z
            out[row, col, 1] = (v - cy) / fy * z
            out[row, col, 2] = z
    return out


@njit(cache=True)
def reduce_ranges_kernel(ranges, r, rays):
    """(h, w, 3) sensor points of a range image's r x r blocks: the block's lower median beam (by range) times
    its unit ray ``rays`` (H, W, 3) (NaN: no majority), the rule :func:`reduce_points_kernel` has for a camera."""
    height, width = ranges.shape
    h, w = height // r, width // r
    out = np.full((h, w, 3), np.nan)
    values = np.empty(r * r)
    slots = np.empty(r * r, dtype=np.int64)
    for row in range(h):
        for col in range(w):
            z, slot = _block_median(ranges, r, row, col, values, slots)
            if slot < 0:
                continue
            i = row * r + slot // r
            j = col * r + slot % r
            for c in range(3):
                out[row, col, c] = z * rays[i, j, c]
    return out


@njit(cache=True)
def point_normals_kernel(points, max_jump):
    """(H, W, 3) unit normals facing the camera, as the numpy reference ``point_normals`` (tests/reference_kernels.py);
    ``max_jump`` one number for every row."""
    height, width = points.shape[0], points.shape[1]
    none = np.zeros((height, width), dtype=np.bool_)
    return point_normals_depth_kernel(points, points[:, :, 2], np.full(height, max_jump), none, none)


@njit(cache=True)
def point_normals_depth_kernel(points, depth, max_jump, right, down, column_step=1):
    """:func:`point_normals_kernel` with the depth tests on ``depth`` (H, W): a camera's z (the points' own), a
    LiDAR's range; and a neighbour that fails the jump rule used all the same where ``right`` (H, W: pixel
    (i, j) with (i, j + 1)) or ``down`` ((i, j) with (i + 1, j)) says the two are on one straight line
    (:func:`mabdi.depth.straight_continuations`; all False: the jump rule alone). ``max_jump`` (H,): each row's
    relative jump; two pixels of rows i and k are compared with the larger of the two rows'.

    ``column_step``: along a row, the neighbours up to this many columns away (the furthest that a run of
    pixels on the surface reaches; 1: the next pixel), so that a LiDAR's columns, much closer than its beams,
    span about a beam's angle as the rows do; each passes the jump rule against the pixel itself."""
    height, width = points.shape[0], points.shape[1]
    normals = np.full((height, width, 3), np.nan)
    du = np.empty(3)
    dv = np.empty(3)
    for i in range(height):
        for j in range(width):
            z = depth[i, j]
            if not np.isfinite(z):
                continue
            for axis in range(2):
                d = du if axis == 0 else dv
                fi, fj = (i, j + 1) if axis == 0 else (i + 1, j)
                bi, bj = (i, j - 1) if axis == 0 else (i - 1, j)
                forward_ok = fi < height and fj < width
                backward_ok = bi >= 0 and bj >= 0
                straight_forward = right[i, j] if axis == 0 else down[i, j]
                straight_backward = backward_ok and (right[bi, bj] if axis == 0 else down[bi, bj])
                jump_forward = max(max_jump[i], max_jump[fi]) if forward_ok else 0.0
                jump_backward = max(max_jump[i], max_jump[bi]) if backward_ok else 0.0
                has_forward = forward_ok and (abs(depth[fi, fj] - z) <= jump_forward * z or straight_forward)
                has_backward = backward_ok and (abs(depth[bi, bj] - z) <= jump_backward * z or straight_backward)
                if axis == 0:  # along the row: as far as the run of surface pixels reaches, up to column_step
                    for step in range(2, column_step + 1):
                        if not has_forward or j + step >= width or not abs(depth[i, j + step] - z) <= max_jump[i] * z:
                            break
                        fj = j + step
                    for step in range(2, column_step + 1):
                        if not has_backward or j - step < 0 or not abs(depth[i, j - step] - z) <= max_jump[i] * z:
                            break
                        bj = j - step
                for c in range(3):
                    forward = points[fi, fj, c] if forward_ok else np.nan
                    backward = points[bi, bj, c] if backward_ok else np.nan
                    if has_forward and has_backward:
                        d[c] = forward - backward
                    elif has_forward:
                        d[c] = forward - points[i, j, c]
                    else:
                        d[c] = points[i, j, c] - backward
            nx = -(du[1] * dv[2] - du[2] * dv[1])
            ny = -(du[2] * dv[0] - du[0] * dv[2])
            nz = -(du[0] * dv[1] - du[1] * dv[0])
            length = np.sqrt(nx * nx + ny * ny + nz * nz)
            if not np.isfinite(length) or length == 0.0:
                continue
            nx, ny, nz = nx / length, ny / length, nz / length
            if nx * points[i, j, 0] + ny * points[i, j, 1] + nz * points[i, j, 2] > 0:
                nx, ny, nz = -nx, -ny, -nz
            normals[i, j, 0] = nx
            normals[i, j, 1] = ny
            normals[i, j, 2] = nz
    return normals


@njit(cache=True)
def pyramid_kernel(points, normals, n_t, d_t, normal_noise, distance_noise, noise_aware, min_distance):
    """Leaves of the merge pyramid, as the numpy reference ``build_leaves`` (tests/reference_kernels.py).

    ``noise_aware`` False: the seed's test, children's normals within ``n_t`` per component of their
    average and centroids within ``d_t`` of the averaged plane. True: ``normal_noise`` and
    ``distance_noise`` (H, W, float32) say what the noise lets one pixel's normal (per component) and
    point (along the normal, m) stray; a node's children each average 4**(level - 1) pixels, so the test
    allows the mean of its pixels' values over 2**(level - 1): normals within that where it is more than
    ``n_t``, centroids within it but no further than ``d_t`` and at least ``min_distance``.

    Returns (level, row, col, normal (float64, unit), point, root region count).
    """
    height, width = points.shape[0], points.shape[1]
    n_t32 = np.float32(n_t)
    d_t32 = np.float32(d_t)
    min_distance32 = np.float32(min_distance)
    quarter = np.float32(0.25)
    # level 0
    single = np.zeros((height, width), dtype=np.bool_)
    count = np.zeros((height, width), dtype=np.int64)
    ns = np.zeros((height, width, 3), dtype=np.float32)
    ps = np.zeros((height, width, 3), dtype=np.float32)
    ss = np.zeros((height, width, 2), dtype=np.float32)  # the noise allowances (normal, distance)
    for i in range(height):
        for j in range(width):
            if np.isfinite(normals[i, j, 0]) and np.isfinite(points[i, j, 2]):
                single[i, j] = True
                count[i, j] = 1
                for c in range(3):
                    ns[i, j, c] = np.float32(normals[i, j, c])
                    ps[i, j, c] = np.float32(points[i, j, c])
                ss[i, j, 0] = np.float32(normal_noise[i, j])
                ss[i, j, 1] = np.float32(distance_noise[i, j])
    singles = [single]
    normal_levels = [ns]
    point_levels = [ps]
    noise_levels = [ss]
    regions = 0
    shrink = np.float32(1.0)  # 1 / 2**(level - 1) of the level being formed
    while singles[-1].size > 1:
        below = singles[-1]
        nb = normal_levels[-1]
        pb = point_levels[-1]
        sb = noise_levels[-1]
        h, w = below.shape
        ph, pw = (h + 1) // 2, (w + 1) // 2
        above = np.zeros((ph, pw), dtype=np.bool_)
        count_above = np.zeros((ph, pw), dtype=np.int64)
        n_above = np.zeros((ph, pw, 3), dtype=np.float32)
        p_above = np.zeros((ph, pw, 3), dtype=np.float32)
        s_above = np.zeros((ph, pw, 2), dtype=np.float32)
        any_merged = False
        n_avg = np.zeros(3, dtype=np.float32)
        p_avg = np.zeros(3, dtype=np.float32)
        s_avg = np.zeros(2, dtype=np.float32)
        for i in range(ph):
            for j in range(pw):
                all_single = True
                total = 0
                for c in range(3):
                    n_avg[c] = np.float32(0.0)
                    p_avg[c] = np.float32(0.0)
                s_avg[0] = np.float32(0.0)
                s_avg[1] = np.float32(0.0)
                for a in range(2):
                    for b in range(2):
                        ci, cj = 2 * i + a, 2 * j + b
                        if ci < h and cj < w:
                            all_single = all_single and below[ci, cj]
                            total += count[ci, cj]
                            for c in range(3):
                                n_avg[c] += nb[ci, cj, c]
                                p_avg[c] += pb[ci, cj, c]
                            s_avg[0] += sb[ci, cj, 0]
                            s_avg[1] += sb[ci, cj, 1]
                        else:
                            all_single = False
                for c in range(3):
                    n_avg[c] *= quarter
                    p_avg[c] *= quarter
                s_avg[0] *= quarter
                s_avg[1] *= quarter
                merged = all_single
                if merged:
                    normal_limit = n_t32
                    distance_limit = d_t32
                    if noise_aware:
                        normal_limit = max(n_t32, s_avg[0] * shrink)
                        distance_limit = min(d_t32, max(min_distance32, s_avg[1] * shrink))
                    length = np.sqrt(n_avg[0] * n_avg[0] + n_avg[1] * n_avg[1] + n_avg[2] * n_avg[2])
                    for a in range(2):
                        for b in range(2):
                            ci, cj = 2 * i + a, 2 * j + b
                            deviation = np.float32(0.0)
                            distance = np.float32(0.0)
                            for c in range(3):
                                deviation = max(deviation, abs(n_avg[c] - nb[ci, cj, c]))
                                if length > 0:
                                    distance += (n_avg[c] / length) * (pb[ci, cj, c] - p_avg[c])
                            if not (deviation < normal_limit and abs(distance) < distance_limit):
                                merged = False
                if merged:
                    any_merged = True
                    above[i, j] = True
                    count_above[i, j] = 1
                    for c in range(3):
                        n_above[i, j, c] = n_avg[c]
                        p_above[i, j, c] = p_avg[c]
                    s_above[i, j, 0] = s_avg[0]
                    s_above[i, j, 1] = s_avg[1]
                else:
                    count_above[i, j] = total
        singles.append(above)
        normal_levels.append(n_above)
        point_levels.append(p_above)
        noise_levels.append(s_above)
        shrink *= np.float32(0.5)
        count = count_above
        if not any_merged:
            break
    regions = 0
    for i in range(count.shape[0]):
        for j in range(count.shape[1]):
            regions += count[i, j]
    # leaves: single nodes whose parent is not single (at most one per level-0 node)
    capacity = height * width
    levels = np.empty(capacity, dtype=np.int64)
    rows = np.empty(capacity, dtype=np.int64)
    cols = np.empty(capacity, dtype=np.int64)
    leaf_normals = np.empty((capacity, 3))
    leaf_points = np.empty((capacity, 3))
    k = 0
    for level in range(len(singles)):
        s = singles[level]
        for i in range(s.shape[0]):
            for j in range(s.shape[1]):
                if s[i, j] and (level + 1 == len(singles) or not singles[level + 1][i // 2, j // 2]):
                    levels[k] = level
                    rows[k] = i
                    cols[k] = j
                    nv = normal_levels[level][i, j]
                    length = np.sqrt(np.float64(nv[0]) ** 2 + np.float64(nv[1]) ** 2 + np.float64(nv[2]) ** 2)
                    for c in range(3):
                        leaf_normals[k, c] = np.float64(nv[c]) / length
                        leaf_points[k, c] = np.float64(point_levels[level][i, j, c])
                    k += 1
    return levels[:k], rows[:k], cols[:k], leaf_normals[:k], leaf_points[:k], regions


@njit(cache=True)
def plane_residual_kernel(points, level, row, col, normal, point, max_jump, largest):
    """As the numpy reference ``plane_residual`` (tests/reference_kernels.py): for leaves up to ``largest`` pixels a side, the
    largest distance of a same-surface pixel of the leaf or its ring from the leaf's plane."""
    jumps = np.full(points.shape[0], max_jump)
    depth = points[:, :, 2]
    return plane_residual_depth_kernel(points, depth, level, row, col, normal, point, point[:, 2], jumps, largest)


@njit(cache=True)
def plane_residual_depth_kernel(points, depth, level, row, col, normal, point, point_depth, max_jump, largest):
    """:func:`plane_residual_kernel` with the same-surface test on ``depth`` (H, W) and the leaves' ``point_depth``
    (a camera's z, a LiDAR's range), each pixel's by its row's ``max_jump`` (H,)."""
    height, width = points.shape[0], points.shape[1]
    residual = np.zeros(level.shape[0])
    for k in range(level.shape[0]):
        side = 1 << level[k]
        if side > largest:
            continue
        top, left = row[k] * side, col[k] * side
        z0 = point_depth[k]
        worst = 0.0
        for dr in range(-1, side + 1):
            for dc in range(-1, side + 1):
                r, c = top + dr, left + dc
                if r < 0 or r >= height or c < 0 or c >= width:
                    continue
                z = depth[r, c]
                if not (abs(z - z0) <= max_jump[r] * z0):
                    continue
                distance = abs(
                    (points[r, c, 0] - point[k, 0]) * normal[k, 0]
                    + (points[r, c, 1] - point[k, 1]) * normal[k, 1]
                    + (points[r, c, 2] - point[k, 2]) * normal[k, 2]
                )
                if distance > worst:
                    worst = distance
        residual[k] = worst
    return residual
