"""Warp kernels of the ICP's per-sample work (:mod:`mabdi.stages.registration_device`): the math of
:mod:`mabdi.stages.registration_kernels` (a camera's) and :mod:`mabdi.stages.scan_registration_kernels` (a
LiDAR's) for a GPU, compiled by Warp for CUDA or for the CPU.

Imported only when a registration runs on a Warp device (importing Warp takes a third of a second).
"""

from __future__ import annotations

import warp as wp

wp.config.log_level = 30  # warnings only: no banner or compile messages in a run's output

#: Samples each GPU thread sums before adding to the totals (fewer atomic additions on the same few addresses).
STRIP = 32
#: Layout of a step's totals: A's 21 upper entries, b, chi2, pairs, candidates, then the two supports' 21 each.
TOTAL_A, TOTAL_B, TOTAL_CHI2, TOTAL_PAIRS, TOTAL_CANDIDATES, TOTAL_SUPPORT = 0, 21, 27, 28, 29, 30
TOTALS = TOTAL_SUPPORT + 42
#: A LiDAR step's totals: A's 21 upper entries and b.
SCAN_TOTALS = TOTAL_B + 6

vec6d = wp.types.vector(length=6, dtype=wp.float64)
mat66d = wp.types.matrix(shape=(6, 6), dtype=wp.float64)

@wp.func
def _e_point_normal(depth: wp.array2d(dtype=wp.float32), row: int, col: int, fx: wp.float64, fy: wp.float64,
                    cx: wp.float64, cy: wp.float64, step: int, max_jump: wp.float64):  # fmt: skip
    """(ok, qx, qy, qz, n): E's camera-frame point at (row, col) and its unit normal facing the camera,
    as :func:`~mabdi.stages.registration_kernels.point_and_normal` computes them."""
    zero = wp.float64(0.0)
    none = wp.vec3d(zero, zero, zero)
    height = depth.shape[0]
    width = depth.shape[1]
    if row < step or col < step or row >= height - step or col >= width - step:
        return False, zero, zero, zero, none
    z = wp.float64(depth[row, col])
    left = wp.float64(depth[row, col - step])
    right = wp.float64(depth[row, col + step])
    up = wp.float64(depth[row - step, col])
    down = wp.float64(depth[row + step, col])
    limit = max_jump * z
    if not (wp.abs(left - z) <= limit and wp.abs(right - z) <= limit and wp.abs(up - z) <= limit and wp.abs(down - z) <= limit):
        return False, zero, zero, zero, none  # also for NaN in the pixel or a neighbour
    half = wp.float64(0.5)
    s = wp.float64(step)
    across = wp.float64(col) + half - cx
    down_from = wp.float64(row) + half - cy
    ax = across / fx
    ay = down_from / fy
    x = ax * z
    y = ay * z
    u = wp.vec3d(((across + s) * right - (across - s) * left) / fx, ay * (right - left), right - left)
    v = wp.vec3d(ax * (down - up), ((down_from + s) * down - (down_from - s) * up) / fy, down - up)
    n = wp.cross(u, v)
    squared = wp.dot(n, n)
    if squared == zero:
        return False, zero, zero, zero, none
    inverse = wp.float64(1.0) / wp.sqrt(squared)
    if wp.dot(n, wp.vec3d(x, y, z)) > zero:
        inverse = -inverse
    return True, x, y, z, n * inverse

@wp.func
def _paired(points: wp.array2d(dtype=wp.float64), i: int, rotation: wp.mat33d, translation: wp.vec3d,
            depth: wp.array2d(dtype=wp.float32), fx: wp.float64, fy: wp.float64, cx: wp.float64, cy: wp.float64,
            step: int, max_jump: wp.float64):  # fmt: skip
    """(ok, p, n, qz, r): sample ``i`` moved into E's camera (m), the normal and depth of E's pixel it projects
    into, and its signed point-to-plane residual (m): :func:`~mabdi.stages.registration_kernels.paired_residual`."""
    zero = wp.float64(0.0)
    p = rotation * wp.vec3d(points[i, 0], points[i, 1], points[i, 2]) + translation
    none = wp.vec3d(zero, zero, zero)
    if p[2] <= zero:
        return False, p, none, zero, zero
    u = fx * p[0] / p[2] + cx
    v = fy * p[1] / p[2] + cy
    if not (u >= zero and v >= zero and u < wp.float64(depth.shape[1]) and v < wp.float64(depth.shape[0])):
        return False, p, none, zero, zero
    ok, qx, qy, qz, n = _e_point_normal(depth, int(v), int(u), fx, fy, cx, cy, step, max_jump)
    if not ok:
        return False, p, none, zero, zero
    return True, p, n, qz, wp.dot(n, p - wp.vec3d(qx, qy, qz))

@wp.kernel
def system_kernel(points: wp.array2d(dtype=wp.float64), tiles: wp.array(dtype=wp.int64),
                   scale: wp.array(dtype=wp.float64), gate: wp.array(dtype=wp.float64), rotation: wp.mat33d,
                   translation: wp.vec3d, depth: wp.array2d(dtype=wp.float32), fx: wp.float64, fy: wp.float64,
                   cx: wp.float64, cy: wp.float64, step: int, max_jump: wp.float64, huber: wp.float64,
                   summaries: int, totals: wp.array(dtype=wp.float64), tile_gradients: wp.array2d(dtype=wp.float64),
                   residuals: wp.array(dtype=wp.float64)):  # fmt: skip
    """One ICP step's sums over a strip of samples (:func:`~mabdi.stages.registration_kernels.point_to_plane_system`);
    ``residuals[i]``: sample i's |r|, or -1 where it is no candidate."""
    strip = wp.tid()
    n = points.shape[0]
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    a = mat66d()
    b = vec6d()
    paired_support = mat66d()
    all_support = mat66d()
    chi2 = zero
    pairs = zero
    candidates = zero
    for i in range(strip * STRIP, wp.min(strip * STRIP + STRIP, n)):
        ok, p, normal, qz, r = _paired(points, i, rotation, translation, depth, fx, fy, cx, cy, step, max_jump)
        if not ok:
            residuals[i] = -one
            continue
        residuals[i] = wp.abs(r)
        candidates += one
        c = wp.cross(p, normal)
        jac = vec6d(c[0], c[1], c[2], normal[0], normal[1], normal[2])
        s = scale[i]
        g = gate[i]
        inside = wp.abs(r) <= g and wp.abs(p[2] - qz) <= wp.float64(2.0) * g
        if summaries != 0:
            information = wp.outer(jac, jac) / (s * s)
            all_support += information
            if inside:
                paired_support += information
        if inside:
            pairs += one
            w = one
            if huber > zero:
                e = wp.abs(r) / s
                if e > huber:
                    w = huber / e
            else:  # Tukey's biweight over the gate
                e = r / g
                w = (one - e * e) * (one - e * e)
            w = w / (s * s)
            a += w * wp.outer(jac, jac)
            b += (w * r) * jac
            chi2 += w * r * r
            if summaries != 0:
                for j in range(6):
                    wp.atomic_add(tile_gradients, int(tiles[i]), j, w * jac[j] * r)
    entry = int(0)
    for j in range(6):
        for k in range(j, 6):
            wp.atomic_add(totals, TOTAL_A + entry, a[j, k])
            wp.atomic_add(totals, TOTAL_SUPPORT + entry, paired_support[j, k])
            wp.atomic_add(totals, TOTAL_SUPPORT + 21 + entry, all_support[j, k])
            entry += 1
        wp.atomic_add(totals, TOTAL_B + j, b[j])
    wp.atomic_add(totals, TOTAL_CHI2, chi2)
    wp.atomic_add(totals, TOTAL_PAIRS, pairs)
    wp.atomic_add(totals, TOTAL_CANDIDATES, candidates)

@wp.kernel
def residuals_kernel(points: wp.array2d(dtype=wp.float64), rotation: wp.mat33d, translation: wp.vec3d,
                      depth: wp.array2d(dtype=wp.float32), fx: wp.float64, fy: wp.float64, cx: wp.float64,
                      cy: wp.float64, step: int, max_jump: wp.float64, residuals: wp.array(dtype=wp.float64)):  # fmt: skip
    """Sample i's |r| at the pose, or -1 where it is no candidate."""
    i = wp.tid()
    ok, p, normal, qz, r = _paired(points, i, rotation, translation, depth, fx, fy, cx, cy, step, max_jump)
    if ok:
        residuals[i] = wp.abs(r)
    else:
        residuals[i] = wp.float64(-1.0)


# -- a LiDAR scan against E's range image (:mod:`mabdi.stages.scan_registration_kernels`) ----------------------


@wp.func
def image_pixel(q: wp.vec3d, row_edges: wp.array(dtype=wp.float64), columns: int):
    """(row, column) of the range-image pixel a sensor-frame point falls in, row -1 outside the image:
    :func:`~mabdi.stages.scan_registration_kernels.image_pixel`."""
    horizontal = wp.sqrt(q[0] * q[0] + q[1] * q[1])
    elevation = wp.atan2(q[2], horizontal)
    rows = row_edges.shape[0] - 1
    if elevation > row_edges[0] or elevation <= row_edges[rows]:
        return -1, 0
    low = int(0)
    high = rows  # row_edges[low] >= elevation > row_edges[high]
    while high - low > 1:
        middle = (low + high) // 2
        if row_edges[middle] >= elevation:
            low = middle
        else:
            high = middle
    azimuth = wp.atan2(q[1], q[0])
    half = wp.float64(0.5)
    column = int(wp.floor(half * (wp.float64(1.0) - azimuth / wp.float64(wp.pi)) * wp.float64(columns))) % columns
    return low, column


@wp.func
def scan_pair(points: wp.array2d(dtype=wp.float64), i: int, rotation: wp.mat33d, translation: wp.vec3d,
              e_points: wp.array3d(dtype=wp.float64), e_normals: wp.array3d(dtype=wp.float64),
              row_edges: wp.array(dtype=wp.float64), columns: int, angle_reach: wp.float64, near_reach: wp.float64):  # fmt: skip
    """(state, q, n, r): return i moved into E's sensor frame and paired with the plane E holds at its pixel
    (:func:`~mabdi.stages.scan_registration_kernels._pair`: state 2 paired, 1 another surface, 0 none)."""
    zero = wp.float64(0.0)
    none = wp.vec3d(zero, zero, zero)
    q = rotation * wp.vec3d(points[i, 0], points[i, 1], points[i, 2]) + translation
    row, column = image_pixel(q, row_edges, columns)
    if row < 0:
        return 0, q, none, zero
    n = wp.vec3d(e_normals[row, column, 0], e_normals[row, column, 1], e_normals[row, column, 2])
    if wp.isnan(n[0]) or wp.isinf(n[0]):
        return 0, q, none, zero
    d = q - wp.vec3d(e_points[row, column, 0], e_points[row, column, 1], e_points[row, column, 2])
    reach = near_reach + angle_reach * wp.length(q)
    if wp.dot(d, d) > reach * reach:
        return 1, q, none, zero
    return 2, q, n, wp.dot(n, d)


@wp.kernel
def scan_system_kernel(points: wp.array2d(dtype=wp.float64), rotation: wp.mat33d, translation: wp.vec3d,
                       e_points: wp.array3d(dtype=wp.float64), e_normals: wp.array3d(dtype=wp.float64),
                       row_edges: wp.array(dtype=wp.float64), columns: int, angle_reach: wp.float64,
                       gate: wp.float64, huber: wp.float64, totals: wp.array(dtype=wp.float64),
                       residuals: wp.array(dtype=wp.float64)):  # fmt: skip
    """One step's sums over a strip of returns (:func:`~mabdi.stages.scan_registration_kernels.scan_to_plane_system`):
    A's 21 upper entries then b in ``totals``; ``residuals[i]``: return i's |r| where it is paired within the
    gate, else -1."""
    strip = wp.tid()
    n = points.shape[0]
    one = wp.float64(1.0)
    a = mat66d()
    b = vec6d()
    for i in range(strip * STRIP, wp.min(strip * STRIP + STRIP, n)):
        state, q, normal, r = scan_pair(points, i, rotation, translation, e_points, e_normals, row_edges, columns, angle_reach, gate)
        if state < 2 or wp.abs(r) > gate:
            residuals[i] = -one
            continue
        weight = one
        if wp.abs(r) > huber:
            weight = huber / wp.abs(r)
        c = wp.cross(q, normal)
        jac = vec6d(c[0], c[1], c[2], normal[0], normal[1], normal[2])
        a += weight * wp.outer(jac, jac)
        b += (weight * r) * jac
        residuals[i] = wp.abs(r)
    entry = int(0)
    for j in range(6):
        for k in range(j, 6):
            wp.atomic_add(totals, TOTAL_A + entry, a[j, k])
            entry += 1
        wp.atomic_add(totals, TOTAL_B + j, b[j])


@wp.kernel
def scan_cost_kernel(points: wp.array2d(dtype=wp.float64), rotation: wp.mat33d, translation: wp.vec3d,
                     e_points: wp.array3d(dtype=wp.float64), e_normals: wp.array3d(dtype=wp.float64),
                     row_edges: wp.array(dtype=wp.float64), columns: int, angle_reach: wp.float64,
                     gate: wp.float64, totals: wp.array(dtype=wp.float64)):  # fmt: skip
    """The sum of min(r, gate)^2 (m^2) and the count of the returns whose pixel shows the map, over a strip
    (:func:`~mabdi.stages.scan_registration_kernels.truncated_cost`): ``totals`` [0] and [1]."""
    strip = wp.tid()
    n = points.shape[0]
    total = wp.float64(0.0)
    seen = wp.float64(0.0)
    for i in range(strip * STRIP, wp.min(strip * STRIP + STRIP, n)):
        state, q, normal, r = scan_pair(points, i, rotation, translation, e_points, e_normals, row_edges, columns, angle_reach, gate)
        if state == 0:
            continue
        if state == 2:
            total += wp.min(r * r, gate * gate)
        else:
            total += gate * gate
        seen += wp.float64(1.0)
    wp.atomic_add(totals, 0, total)
    wp.atomic_add(totals, 1, seen)
