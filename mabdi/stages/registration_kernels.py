"""Compiled (numba) per-pixel work of frame-to-map registration (:mod:`mabdi.stages.registration`).

:func:`point_to_plane_system` is one Gauss-Newton step of projective
point-to-plane ICP: every sampled point of D, moved by the current estimate,
is projected into E's image, paired with the map point and normal E shows at
that pixel, and adds its robustly weighted row to the 6x6 normal equations.
:func:`pose_sigma_image` turns a pose covariance into each pixel's depth
uncertainty. Both read E's points and normals straight from its depth image
(:func:`point_and_normal`), so no image-sized temporaries are made; the
ICP's steps keep the normals they computed (:func:`cached_point_and_normal`):
E does not change while a frame is registered, and after the first steps
the samples land on the same pixels again.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def pixel_ray(row, col, fx, fy, cx, cy):
    """(x / z, y / z) of the ray through pixel (row, col)'s centre (pixel (u, v) covers [u, u + 1) x [v, v + 1)):
    its camera-frame point at depth z is (x / z, y / z, 1) z."""
    return (col + 0.5 - cx) / fx, (row + 0.5 - cy) / fy


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
    ax, ay = pixel_ray(row, col, fx, fy, cx, cy)
    across = col + 0.5 - cx  # the pixel centre's offset from the principal point (pixels)
    down_from = row + 0.5 - cy
    x = ax * z
    y = ay * z
    # u difference: points at columns col +- step (same row); v difference: rows row +- step (same column)
    ux = ((across + step) * right - (across - step) * left) / fx
    uy = ay * (right - left)
    uz = right - left
    vx = ax * (down - up)
    vy = ((down_from + step) * down - (down_from - step) * up) / fy
    vz = down - up
    nx = uy * vz - uz * vy
    ny = uz * vx - ux * vz
    nz = ux * vy - uy * vx
    squared = nx * nx + ny * ny + nz * nz
    if squared == 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    inverse = 1.0 / np.sqrt(squared)
    if nx * x + ny * y + nz * z > 0.0:
        inverse = -inverse
    return True, x, y, z, nx * inverse, ny * inverse, nz * inverse


#: A step whose direction is within this cosine of the opposite of the one before undoes it (a two-cycle).
REVERSAL_COSINE = -0.9
#: A direction of the pose with less than this share of the best constrained direction's information (rotations
#: taken as lengths at the samples' median depth) is held by noise alone and takes no ICP step: a plain wall
#: says nothing of where the camera is along it, and the few normals that noise tilts would slide the pose
#: that way (docs/benchmarks.md, "No ICP step where the scene holds nothing", has the shares measured).
UNCONSTRAINED = 1e-4
#: The solver's "no direction held by noise alone": (6, 0) columns (:func:`solve_normal_equations`).
NO_DIRECTION_HELD = np.zeros((6, 0))
#: States of a pixel in the normal cache of :func:`cached_point_and_normal`.
NORMAL_UNKNOWN = 0
NORMAL_FOUND = 1
NORMAL_NONE = 2


@njit(cache=True, inline="always")
def cached_point_and_normal(depth, normals, known, row, col, fx, fy, cx, cy, step, max_jump):
    """:func:`point_and_normal`, computed once per pixel: ``normals`` (H, W, 3) float64 keeps each
    pixel's unit normal and ``known`` (H, W) int8 whether it was computed (``NORMAL_UNKNOWN`` before, then
    ``NORMAL_FOUND`` or ``NORMAL_NONE``). The same numbers as :func:`point_and_normal`."""
    state = known[row, col]
    if state == NORMAL_UNKNOWN:
        ok, x, y, z, nx, ny, nz = point_and_normal(depth, row, col, fx, fy, cx, cy, step, max_jump)
        if ok:
            normals[row, col, 0] = nx
            normals[row, col, 1] = ny
            normals[row, col, 2] = nz
            known[row, col] = NORMAL_FOUND
        else:
            known[row, col] = NORMAL_NONE
        return ok, x, y, z, nx, ny, nz
    if state == NORMAL_NONE:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    z = np.float64(depth[row, col])
    ax, ay = pixel_ray(row, col, fx, fy, cx, cy)
    return True, ax * z, ay * z, z, normals[row, col, 0], normals[row, col, 1], normals[row, col, 2]


@njit(cache=True, inline="always")
def paired_residual(points, i, rotation, translation, e_depth, e_normals, e_known, fx, fy, cx, cy, step, max_jump):
    """(ok, x, y, z, nx, ny, nz, qz, r): sample ``i`` of ``points`` moved by (``rotation``, ``translation``) into
    E's camera (x, y, z, m), the normal and depth qz of the pixel of E it projects into (the normal cache of
    :func:`cached_point_and_normal`), and its signed point-to-plane residual r (m). ok False where the point
    lies behind the camera, outside the image, or on a pixel of E without a normal."""
    height, width = e_depth.shape
    x = rotation[0, 0] * points[i, 0] + rotation[0, 1] * points[i, 1] + rotation[0, 2] * points[i, 2] + translation[0]
    y = rotation[1, 0] * points[i, 0] + rotation[1, 1] * points[i, 1] + rotation[1, 2] * points[i, 2] + translation[1]
    z = rotation[2, 0] * points[i, 0] + rotation[2, 1] * points[i, 1] + rotation[2, 2] * points[i, 2] + translation[2]
    if z <= 0.0:
        return False, x, y, z, 0.0, 0.0, 0.0, 0.0, 0.0
    u = fx * x / z + cx  # pixel (u, v) covers [u, u + 1) x [v, v + 1)
    v = fy * y / z + cy
    if not (u >= 0.0 and v >= 0.0 and u < width and v < height):
        return False, x, y, z, 0.0, 0.0, 0.0, 0.0, 0.0
    ok, qx, qy, qz, nx, ny, nz = cached_point_and_normal(e_depth, e_normals, e_known, int(v), int(u), fx, fy, cx, cy, step, max_jump)
    if not ok:
        return False, x, y, z, 0.0, 0.0, 0.0, 0.0, 0.0
    return True, x, y, z, nx, ny, nz, qz, nx * (x - qx) + ny * (y - qy) + nz * (z - qz)


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


@njit(cache=True, nogil=True)
def point_to_plane_system(
    points, tiles, n_tiles, scale, gate, rotation, translation, e_depth, e_normals, e_known, fx, fy, cx, cy, step, max_jump, huber,
    summaries=True,
):
    """Normal equations of one ICP step in E's camera frame.

    ``points`` (N, 3): D's sampled points in D's camera frame (m); ``tiles``
    (N,): the image tile (0 .. ``n_tiles`` - 1) each point was sampled in; ``scale``
    (N,): each point's noise (m), the unit of its residual; ``gate`` (N,):
    the largest residual (m) a pair may have; ``rotation``, ``translation``:
    the current estimate of E-camera from D-camera; ``e_depth`` (H, W): E,
    metric depth, NaN where the map has no surface; ``e_normals`` and ``e_known``: the cache of E's normals
    (:func:`cached_point_and_normal`; start it unknown for each E); ``step`` and
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
    n = points.shape[0]
    a00 = a01 = a02 = a03 = a04 = a05 = a11 = a12 = a13 = a14 = a15 = 0.0
    a22 = a23 = a24 = a25 = a33 = a34 = a35 = a44 = a45 = a55 = 0.0
    b0 = b1 = b2 = b3 = b4 = b5 = 0.0
    chi2 = 0.0
    pairs = 0
    candidates = 0
    residuals = np.empty(n)
    support = np.zeros((2, 6, 6))
    tile_gradients = np.zeros((n_tiles, 6))
    jac = np.zeros(6)
    for i in range(n):
        ok, x, y, z, nx, ny, nz, qz, r = paired_residual(
            points, i, rotation, translation, e_depth, e_normals, e_known, fx, fy, cx, cy, step, max_jump
        )
        if not ok:
            continue
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
        # the upper triangle of A, and b, in scalars: LLVM keeps them in registers (arrays are slower)
        j0, j1, j2, j3, j4, j5 = jac[0], jac[1], jac[2], jac[3], jac[4], jac[5]
        w0, w1, w2, w3, w4, w5 = w * j0, w * j1, w * j2, w * j3, w * j4, w * j5
        b0 += w0 * r
        b1 += w1 * r
        b2 += w2 * r
        b3 += w3 * r
        b4 += w4 * r
        b5 += w5 * r
        if summaries:
            t = tiles[i]
            tile_gradients[t, 0] += w0 * r
            tile_gradients[t, 1] += w1 * r
            tile_gradients[t, 2] += w2 * r
            tile_gradients[t, 3] += w3 * r
            tile_gradients[t, 4] += w4 * r
            tile_gradients[t, 5] += w5 * r
        a00 += w0 * j0; a01 += w0 * j1; a02 += w0 * j2; a03 += w0 * j3; a04 += w0 * j4; a05 += w0 * j5  # noqa: E702
        a11 += w1 * j1; a12 += w1 * j2; a13 += w1 * j3; a14 += w1 * j4; a15 += w1 * j5  # noqa: E702
        a22 += w2 * j2; a23 += w2 * j3; a24 += w2 * j4; a25 += w2 * j5  # noqa: E702
        a33 += w3 * j3; a34 += w3 * j4; a35 += w3 * j5  # noqa: E702
        a44 += w4 * j4; a45 += w4 * j5  # noqa: E702
        a55 += w5 * j5
        chi2 += w * r * r
    a = np.array(
        [
            [a00, a01, a02, a03, a04, a05],
            [a01, a11, a12, a13, a14, a15],
            [a02, a12, a22, a23, a24, a25],
            [a03, a13, a23, a33, a34, a35],
            [a04, a14, a24, a34, a44, a45],
            [a05, a15, a25, a35, a45, a55],
        ]
    )
    b = np.array([b0, b1, b2, b3, b4, b5])
    for j in range(6):
        for k in range(j):
            support[0, j, k] = support[0, k, j]
            support[1, j, k] = support[1, k, j]
    return a, b, chi2, pairs, candidates, residuals[:candidates], support, tile_gradients


@njit(cache=True, nogil=True)
def point_to_plane_residuals(points, rotation, translation, e_depth, e_normals, e_known, fx, fy, cx, cy, step, max_jump):
    """The absolute point-to-plane residuals (m) of :func:`point_to_plane_system` alone, in its order (every
    candidate: a point that lands on a pixel of E with a normal), without the normal equations: how well a
    pose fits D to the map (the same arguments; the normal cache is filled as that kernel fills it)."""
    n = points.shape[0]
    residuals = np.empty(n)
    candidates = 0
    for i in range(n):
        ok, _, _, _, _, _, _, _, r = paired_residual(
            points, i, rotation, translation, e_depth, e_normals, e_known, fx, fy, cx, cy, step, max_jump
        )
        if ok:
            residuals[candidates] = abs(r)
            candidates += 1
    return residuals[:candidates]


@njit(cache=True, nogil=True)
def structure_information(
    points, scale, gate, rotation, translation, e_depth, e_normals, e_known, fx, fy, cx, cy, step, max_jump, directions, min_sine,
):
    """The information the pairs of :func:`point_to_plane_system` give along each of ``directions`` ((6, K)
    columns: rotation vector, translation), counting of each pair's normal only what lies beyond ``min_sine``
    of the plane the direction moves its point in: the part of J^T J that no tilt of the normals by up to
    asin(``min_sine``) can make. A wall's normals, tilted a degree or two by the map's own faces, hold a
    slide along it or a turn about its normal at a few thousandths of what they hold across it; this counts
    none of that, and the whole of what an edge, a leg or a step holds (their normals lie across the motion)."""
    n = points.shape[0]
    count = directions.shape[1]
    information = np.zeros(count)
    for i in range(n):
        ok, x, y, z, nx, ny, nz, qz, r = paired_residual(
            points, i, rotation, translation, e_depth, e_normals, e_known, fx, fy, cx, cy, step, max_jump
        )
        g = gate[i]
        if not ok or abs(r) > g or abs(z - qz) > 2.0 * g:
            continue
        inverse_variance = 1.0 / (scale[i] * scale[i])
        for j in range(count):
            wx, wy, wz = directions[0, j], directions[1, j], directions[2, j]
            # the point's displacement under the motion: omega x p + t
            dx = wy * z - wz * y + directions[3, j]
            dy = wz * x - wx * z + directions[4, j]
            dz = wx * y - wy * x + directions[5, j]
            squared = dx * dx + dy * dy + dz * dz
            if squared <= 0.0:
                continue
            along = abs(nx * dx + ny * dy + nz * dz) / np.sqrt(squared)  # the normal's share along the motion
            if along > min_sine:
                beyond = (along - min_sine) / (1.0 - min_sine)
                information[j] += inverse_variance * squared * beyond * beyond
    return information


@njit(cache=True, parallel=True)
def pose_sigma_image(e_depth, fx, fy, cx, cy, step, max_jump, covariance, min_cosine):
    """(H, W) float32 depth standard deviation (m) that the pose covariance causes at each pixel of E.

    See :func:`mabdi.stages.registration.pose_depth_sigma`. NaN where E has no surface. Rows run in parallel
    threads (each pixel is its own: the image is the same on any number of cores).
    """
    height, width = e_depth.shape
    sigma = np.full((height, width), np.nan, dtype=np.float32)
    # the quadratic form J C J^T over the 21 distinct entries of the symmetric C (off-diagonals twice)
    c = covariance
    c00, c11, c22, c33, c44, c55 = c[0, 0], c[1, 1], c[2, 2], c[3, 3], c[4, 4], c[5, 5]
    c01, c02, c03, c04, c05 = 2 * c[0, 1], 2 * c[0, 2], 2 * c[0, 3], 2 * c[0, 4], 2 * c[0, 5]
    c12, c13, c14, c15 = 2 * c[1, 2], 2 * c[1, 3], 2 * c[1, 4], 2 * c[1, 5]
    c23, c24, c25 = 2 * c[2, 3], 2 * c[2, 4], 2 * c[2, 5]
    c34, c35 = 2 * c[3, 4], 2 * c[3, 5]
    c45 = 2 * c[4, 5]
    for row in prange(height):
        for col in range(width):
            depth = np.float64(e_depth[row, col])
            if not np.isfinite(depth):
                continue
            ok, x, y, z, nx, ny, nz = point_and_normal(e_depth, row, col, fx, fy, cx, cy, step, max_jump)
            distance = 0.0
            if not ok:  # a silhouette or the border: head-on
                z = depth
                ax, ay = pixel_ray(row, col, fx, fy, cx, cy)
                x = ax * z
                y = ay * z
                distance = np.sqrt(x * x + y * y + z * z)
                nx, ny, nz = -x / distance, -y / distance, -z / distance
            else:
                distance = np.sqrt(x * x + y * y + z * z)
            # J = (p x n, n): :func:`point_plane_jacobian`
            j0 = y * nz - z * ny
            j1 = z * nx - x * nz
            j2 = x * ny - y * nx
            variance = (
                j0 * (c00 * j0 + c01 * j1 + c02 * j2 + c03 * nx + c04 * ny + c05 * nz)
                + j1 * (c11 * j1 + c12 * j2 + c13 * nx + c14 * ny + c15 * nz)
                + j2 * (c22 * j2 + c23 * nx + c24 * ny + c25 * nz)
                + nx * (c33 * nx + c34 * ny + c35 * nz)
                + ny * (c44 * ny + c45 * nz)
                + nz * c55 * nz
            )
            cosine = abs(nx * x + ny * y + nz * z) / distance
            if cosine < min_cosine:
                cosine = min_cosine
            sigma[row, col] = np.sqrt(max(variance, 0.0)) / cosine * z / distance
    return sigma


@njit(cache=True)
def sample_depth_points(measured, stride, fx, fy, cx, cy, tile, tiles_across, tolerance):
    """D's samples, one per ``stride`` x ``stride`` cell whose centre pixel has a return: the mean of the
    camera-frame points (m) of the 2 x 2 pixels that end at the centre pixel (rows and columns centre - 1 and
    centre) whose depths lie within ``tolerance`` times the centre pixel's depth of it (the centre pixel alone
    where ``tolerance`` is 0). Returns (points (N, 3) in D's camera frame, their mean depths (N,), the index of
    the ``tile`` x ``tile`` image tile the centre pixel lies in (N,), row by row with ``tiles_across`` tiles a
    row, the pixels averaged (N,)). See :func:`mabdi.stages.registration.sample_points`."""
    height, width = measured.shape
    offset = stride // 2
    rows = (height - offset + stride - 1) // stride
    cols = (width - offset + stride - 1) // stride
    points = np.empty((rows * cols, 3))
    depths = np.empty(rows * cols)
    tiles = np.empty(rows * cols, dtype=np.int64)
    counts = np.empty(rows * cols, dtype=np.int64)
    n = 0
    for i in range(rows):
        row = i * stride + offset
        for j in range(cols):
            col = j * stride + offset
            centre = np.float64(measured[row, col])
            if not np.isfinite(centre):
                continue
            sx = sy = sz = 0.0
            count = 0
            for dr in range(-1, 1):
                r = row + dr
                for dc in range(-1, 1):
                    c = col + dc
                    if r < 0 or c < 0:
                        continue
                    if dr != 0 or dc != 0:
                        if tolerance <= 0.0:
                            continue
                        z = np.float64(measured[r, c])
                        if not (abs(z - centre) <= tolerance * centre):  # NaN: no return
                            continue
                    else:
                        z = centre
                    ax, ay = pixel_ray(r, c, fx, fy, cx, cy)
                    sx += ax * z
                    sy += ay * z
                    sz += z
                    count += 1
            points[n, 0] = sx / count
            points[n, 1] = sy / count
            points[n, 2] = sz / count
            depths[n] = sz / count
            tiles[n] = (row // tile) * tiles_across + col // tile
            counts[n] = count
            n += 1
    return points[:n], depths[:n], tiles[:n], counts[:n]


@njit(cache=True)
def rigid_from_vector(rotation_vector, translation):
    """The 4x4 transform of a rotation vector (radians; Rodrigues' formula) and a translation (m)."""
    transform = np.eye(4)
    angle = np.sqrt(rotation_vector[0] ** 2 + rotation_vector[1] ** 2 + rotation_vector[2] ** 2)
    x = y = z = 0.0
    if angle > 0.0:
        x, y, z = rotation_vector[0] / angle, rotation_vector[1] / angle, rotation_vector[2] / angle
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    k2 = k @ k
    sine, versine = np.sin(angle), 1.0 - np.cos(angle)
    for i in range(3):
        for j in range(3):
            transform[i, j] += sine * k[i, j] + versine * k2[i, j]
        transform[i, 3] = translation[i]
    return transform


@njit(cache=True)
def rigid_size(transform):
    """(translation in m, rotation angle in degrees) of a 4x4 rigid transform (the angle from both its sine and
    its cosine, exact for small angles too)."""
    r = transform
    sine = 0.5 * np.sqrt((r[2, 1] - r[1, 2]) ** 2 + (r[0, 2] - r[2, 0]) ** 2 + (r[1, 0] - r[0, 1]) ** 2)
    angle = np.degrees(np.arctan2(sine, 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0)))
    translation = np.sqrt(r[0, 3] ** 2 + r[1, 3] ** 2 + r[2, 3] ** 2)
    return translation, angle


@njit(cache=True)
def solve_normal_equations(a, b, length, held_by_noise):
    """The step x of A x = -b and A's inverse, with rotations (the first three) taken as lengths at
    ``length`` metres. Along directions the scene does not constrain (information under
    :data:`UNCONSTRAINED` of the best constrained one's), and along ``held_by_noise`` ((6, m) unit
    columns in those scaled units, :data:`NO_DIRECTION_HELD` for none:
    :func:`mabdi.stages.registration.noise_held_directions`), there is no step, and
    the inverse holds the variance that share of information would give, the least that direction may
    have: the pose stays where it started there, and says that direction is known far less than the held ones."""
    scaling = np.ones(6)
    scaling[:3] = 1.0 / length
    scaled = a * np.outer(scaling, scaling)
    if held_by_noise.shape[1]:
        keep = np.eye(6) - held_by_noise @ held_by_noise.T
        scaled = keep @ scaled @ keep
    values, vectors = np.linalg.eigh(scaled)
    largest = max(values[-1], 0.0)
    inverse_values = np.zeros_like(values)
    step_values = np.zeros_like(values)
    floor = largest * UNCONSTRAINED
    for i in range(len(values)):
        if values[i] > floor:
            inverse_values[i] = 1.0 / values[i]
            step_values[i] = inverse_values[i]
        elif floor > 0.0:
            inverse_values[i] = 1.0 / floor
    inverse = ((vectors * inverse_values) @ vectors.T) * np.outer(scaling, scaling)
    step_inverse = ((vectors * step_values) @ vectors.T) * np.outer(scaling, scaling)
    return -(step_inverse @ b), inverse


@njit(cache=True)
def gauss_newton_update(a, b, transform, previous, length, held_by_noise):
    """One Gauss-Newton step of the ICP: the new estimate (the step's rigid motion, left of ``transform``),
    the step's size (m, degrees) and the step (rotation vector, translation).

    ``previous``: the step before (6,), zeros for none. A step that undoes it (their directions, rotations
    taken as lengths at ``length`` metres, within ``REVERSAL_COSINE``, and about as long) is a two-cycle:
    pairs at the edge of the gate flip in and out, and the two poses swap for ever. Half of it is taken,
    which lands between them. ``held_by_noise``: directions that take no step (:func:`solve_normal_equations`)."""
    step, _ = solve_normal_equations(a, b, length, held_by_noise)
    dot = 0.0
    norm_step = 0.0
    norm_previous = 0.0
    for i in range(6):
        scale = length if i < 3 else 1.0
        dot += step[i] * previous[i] * scale * scale
        norm_step += (step[i] * scale) ** 2
        norm_previous += (previous[i] * scale) ** 2
    if norm_step > 0.0 and norm_previous > 0.0:
        cosine = dot / np.sqrt(norm_step * norm_previous)
        ratio = np.sqrt(norm_step / norm_previous)
        if cosine < REVERSAL_COSINE and 0.5 < ratio < 2.0:
            step = 0.5 * step
    update = rigid_from_vector(step[:3], step[3:])
    translation, angle = rigid_size(update)
    return update @ transform, translation, angle, step


@njit(cache=True)
def median_every(values, stride):
    """The median of every ``stride``-th of ``values`` (the first included); NaN when there are none."""
    if len(values) == 0:
        return np.nan
    return np.median(values[::stride])
