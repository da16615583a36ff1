"""Voxel traversal of ray segments (Amanatides & Woo 1987), compiled with numba: the voxels a ray crosses.

Used to clear free space in the voxel-plane map: where the sensor sees
*through* a surface of the map (measured depth D > expected depth E + tau),
the voxels between the sensor and the measured point are empty now, so their
statistics must go (:meth:`mabdi.voxels.voxel_map.VoxelMap.clear_free_space`).

Grid: voxel (i, j, k) covers [i s, (i + 1) s) x [j s, ...) x [k s, ...) in the
world frame (metres), aligned at 0, index = floor(p / s), negative indices
fine (the grid of :class:`~mabdi.voxels.voxel_map.VoxelMap`).

Segment: ray r runs from ``origins[r]`` towards ``ends[r]``; its end is pulled
back along the ray by ``margins[r]`` metres (Euclidean, along the ray), so
the segment is the half-open

    p(t) = o + t u,  0 <= t < T,   u = (e - o) / |e - o|,   T = |e - o| - margin.

A voxel is *crossed* when the segment runs a positive length through it (a
ray that only grazes an edge or a corner does not cross; up to float64
rounding at such exact ties). Rays with T <= 0 (zero length, or a margin
at least as long as the ray) cross nothing.

``include_end=False`` further drops the voxel holding the pulled-back end
o + T u, keeping only voxels the ray *leaves* before T: every voxel it
returns has its whole chord along the ray at least ``margin`` in front of the
end point. This is what clearing uses, and why: with only the margin, the
voxel holding o + T u is crossed and may be the very voxel holding the
measured surface (a margin tau of 1-3 cm is less than a 5 cm voxel, so the
surface at e and the point tau before it share a voxel more often than not).
Dropping it, a cleared voxel never holds e, nor any point within ``margin``
of e along the ray: the surface's own noisy points (within tau of it) stay.

The traversal visits voxels in order along each ray, recomputing each axis'
next boundary crossing from the voxel index (no accumulated tDelta drift).
Rays run in parallel threads (numba ``prange``). The voxels of all rays are
de-duplicated by a byte mask over their bounding box when it holds at most
:data:`MASK_VOXELS` voxels (a frame's rays from one camera), else by a
count-then-fill pass and a sort. The tests' reference, ``reference_voxels``
and ``reference_pairs`` (numpy, exact slab tests around samples at s/4 steps),
is kept with them (tests/reference_kernels.py).
"""

from __future__ import annotations

import os

import numpy as np

from numba import config, njit, prange

if "NUMBA_THREADING_LAYER" not in os.environ:
    # numba's own thread pool (as mabdi.mesh_maps.neighbourhood): no warning about another package's old TBB
    config.THREADING_LAYER = "workqueue"

#: Largest bounding box (in voxels) de-duplicated by a byte mask; beyond it, a sort.
MASK_VOXELS = 1 << 25

# what the walker does with each voxel it crosses
_COUNT, _FILL, _MASK, _FLAG = 0, 1, 2, 3


def _walk(ox, oy, oz, ex, ey, ez, margin, s, include_end, mode, start, out, low, dims, mask, b, slots, stats, flags):
    """Traverse one segment; per crossed voxel: count it (``_COUNT``), write it to ``out[start + k]``
    (``_FILL``), set its byte in ``mask``, a box from voxel ``low`` of ``dims`` voxels (``_MASK``), or
    (``_FLAG``) set ``flags[c, flat]`` when the voxel holds points the ray saw through
    (:func:`seen_through`): ``mask`` is then a dense table over a box of blocks (``low``, ``dims``
    in blocks of ``b`` voxels a side) giving each block's compact index c (-1: no statistics),
    ``stats[slots[c], flat]`` its voxels' statistics (VoxelMap's store: n, sums relative to the corner).
    Returns the number of voxels crossed."""
    dx, dy, dz = ex - ox, ey - oy, ez - oz
    length = np.sqrt(dx * dx + dy * dy + dz * dz)
    limit = length - margin
    if not limit > 0.0:
        return 0
    ix = np.int64(np.floor(ox / s))
    iy = np.int64(np.floor(oy / s))
    iz = np.int64(np.floor(oz / s))
    sx = 1 if dx > 0.0 else (-1 if dx < 0.0 else 0)
    sy = 1 if dy > 0.0 else (-1 if dy < 0.0 else 0)
    sz = 1 if dz > 0.0 else (-1 if dz < 0.0 else 0)
    # t (metres along the ray) of the next boundary on each axis, (i + 1) s going up, i s going down, and
    # the t between two boundaries: Amanatides & Woo's tMax and tDelta (float64: ~1e-16 relative drift
    # per step, thousands of steps stay far below a voxel)
    kx = length / dx if sx != 0 else 0.0
    ky = length / dy if sy != 0 else 0.0
    kz = length / dz if sz != 0 else 0.0
    tx = ((ix + (sx > 0)) * s - ox) * kx if sx != 0 else np.inf
    ty = ((iy + (sy > 0)) * s - oy) * ky if sy != 0 else np.inf
    tz = ((iz + (sz > 0)) * s - oz) * kz if sz != 0 else np.inf
    gx, gy, gz = abs(s * kx), abs(s * ky), abs(s * kz)
    # for _FLAG: block coordinates (box-relative) and the voxel's place in its block, kept by stepping
    bx = by = bz = lx = ly = lz = compact = np.int64(0)
    if mode == _FLAG:
        bx, by, bz = ix // b, iy // b, iz // b
        lx, ly, lz = ix - bx * b, iy - by * b, iz - bz * b
        bx, by, bz = bx - low[0], by - low[1], bz - low[2]
        compact = _compact(mask, dims, bx, by, bz)
    # for _MASK: the voxel's flat index in the box, kept by stepping (the box holds every voxel crossed)
    m = wx = wy = size = np.int64(0)
    if mode == _MASK:
        wy = dims[2]
        wx = dims[1] * wy
        size = dims[0] * wx
        m = (ix - low[0]) * wx + (iy - low[1]) * wy + (iz - low[2])
    count = 0
    while True:
        leave = min(tx, min(ty, tz))
        if include_end or leave <= limit:
            if mode == _FILL:
                row = start + count
                out[row, 0] = ix
                out[row, 1] = iy
                out[row, 2] = iz
            elif mode == _MASK:
                if 0 <= m < size:
                    mask[m] = 1
            elif mode == _FLAG:
                if compact >= 0:
                    flat = (lx * b + ly) * b + lz
                    slot = slots[compact]
                    n = stats[slot, flat, 0]
                    if n > 0.0 and seen_through(
                        stats[slot, flat, 0], stats[slot, flat, 1], stats[slot, flat, 2], stats[slot, flat, 3],
                        stats[slot, flat, 4], stats[slot, flat, 5], stats[slot, flat, 6], stats[slot, flat, 7],
                        stats[slot, flat, 8], stats[slot, flat, 9], ox - ix * s, oy - iy * s, oz - iz * s,
                        dx / length, dy / length, dz / length, limit, s,
                    ):  # fmt: skip
                        flags[compact, flat] = True
            count += 1
        if leave >= limit:
            return count
        # step every axis whose boundary comes now (a tie: the ray passes an edge or corner exactly)
        moved = False
        if tx == leave:
            ix += sx
            tx += gx
            if mode == _MASK:
                m += sx * wx
            elif mode == _FLAG:
                lx += sx
                if lx == b or lx < 0:
                    lx -= sx * b
                    bx += sx
                    moved = True
        if ty == leave:
            iy += sy
            ty += gy
            if mode == _MASK:
                m += sy * wy
            elif mode == _FLAG:
                ly += sy
                if ly == b or ly < 0:
                    ly -= sy * b
                    by += sy
                    moved = True
        if tz == leave:
            iz += sz
            tz += gz
            if mode == _MASK:
                m += sz
            elif mode == _FLAG:
                lz += sz
                if lz == b or lz < 0:
                    lz -= sz * b
                    bz += sz
                    moved = True
        if moved:
            compact = _compact(mask, dims, bx, by, bz)


#: A ray sees through a voxel's points when it passes within this many standard deviations of them.
HIT_SIGMAS = 3.0
#: Spread added to every voxel's points (a fraction of the voxel size, 1 mm at 5 cm voxels): one point, or
#: a noise-free plane, still has a width.
MIN_SPREAD = 0.02


def seen_through(n, s1x, s1y, s1z, sxx, sxy, sxz, syy, syz, szz, wx, wy, wz, ux, uy, uz, limit, s):
    """Whether a ray saw through a voxel's points: True when it passes through their Gaussian (Mahalanobis
    distance of its closest approach at most :data:`HIT_SIGMAS`, covariance + (MIN_SPREAD s)^2 I) before
    ``limit`` (its pulled-back end, metres along the ray).

    The voxel's statistics (n, S1, S2, relative to its corner), ``w`` = ray origin - corner, ``u`` the
    unit direction. A planar cloud is hit where the ray crosses its plane inside its extent; a ray that
    grazes the surface it measures (a floor at a low angle) passes above the cloud (many normal-noise
    sigmas) or reaches it only after ``limit``, and leaves it. Scalars (numba) or arrays (numpy) alike.
    """
    mx, my, mz = s1x / n, s1y / n, s1z / n
    floor = (MIN_SPREAD * s) ** 2
    a = sxx / n - mx * mx + floor
    b = sxy / n - mx * my
    c = sxz / n - mx * mz
    d = syy / n - my * my + floor
    e = syz / n - my * mz
    f = szz / n - mz * mz + floor
    # inverse of [[a, b, c], [b, d, e], [c, e, f]] by cofactors (times the determinant, which cancels below
    # except in the final distance)
    ia, ib, ic = d * f - e * e, c * e - b * f, b * e - c * d
    id_, ie, if_ = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * ia + b * ib + c * ic
    px, py, pz = wx - mx, wy - my, wz - mz  # origin relative to the centroid
    aux = ia * ux + ib * uy + ic * uz
    auy = ib * ux + id_ * uy + ie * uz
    auz = ic * ux + ie * uy + if_ * uz
    uau = ux * aux + uy * auy + uz * auz
    uap = px * aux + py * auy + pz * auz
    pap = px * (ia * px + ib * py + ic * pz) + py * (ib * px + id_ * py + ie * pz) + pz * (ic * px + ie * py + if_ * pz)
    closest = -uap / uau
    distance = (pap - uap * uap / uau) / det
    return (distance <= HIT_SIGMAS * HIT_SIGMAS) & (closest < limit)


def _compact(table, dims, bx, by, bz):
    """Entry of box cell (bx, by, bz) of a dense table, -1 outside the box."""
    if 0 <= bx < dims[0] and 0 <= by < dims[1] and 0 <= bz < dims[2]:
        return np.int64(table[(bx * dims[1] + by) * dims[2] + bz])
    return np.int64(-1)


def _count_kernel(origins, ends, margins, s, include_end, counts):
    empty = np.zeros((0, 3), dtype=np.int64)
    none = np.zeros(3, dtype=np.int64)
    noflag = np.zeros((0, 0), dtype=np.bool_)
    nostats = np.zeros((0, 0, 1))
    nomask = np.zeros(0, dtype=np.uint8)
    for r in prange(origins.shape[0]):
        counts[r] = _walk(
            origins[r, 0], origins[r, 1], origins[r, 2], ends[r, 0], ends[r, 1], ends[r, 2], margins[r], s,
            include_end, _COUNT, 0, empty, none, none, nomask, 1, none, nostats, noflag,
        )  # fmt: skip


def _fill_kernel(origins, ends, margins, s, include_end, starts, out):
    none = np.zeros(3, dtype=np.int64)
    noflag = np.zeros((0, 0), dtype=np.bool_)
    nostats = np.zeros((0, 0, 1))
    nomask = np.zeros(0, dtype=np.uint8)
    for r in prange(origins.shape[0]):
        _walk(
            origins[r, 0], origins[r, 1], origins[r, 2], ends[r, 0], ends[r, 1], ends[r, 2], margins[r], s,
            include_end, _FILL, starts[r], out, none, none, nomask, 1, none, nostats, noflag,
        )  # fmt: skip


def _mask_kernel(origins, ends, margins, s, include_end, low, dims, mask):
    empty = np.zeros((0, 3), dtype=np.int64)
    noflag = np.zeros((0, 0), dtype=np.bool_)
    nostats = np.zeros((0, 0, 1))
    for r in prange(origins.shape[0]):
        _walk(
            origins[r, 0], origins[r, 1], origins[r, 2], ends[r, 0], ends[r, 1], ends[r, 2], margins[r], s,
            include_end, _MASK, 0, empty, low, dims, mask, 1, low, nostats, noflag,
        )  # fmt: skip


def _flag_kernel(origins, ends, margins, s, include_end, b, block_low, block_dims, compact_of_box, slots, stats, flags):
    empty = np.zeros((0, 3), dtype=np.int64)
    for r in prange(origins.shape[0]):
        _walk(
            origins[r, 0], origins[r, 1], origins[r, 2], ends[r, 0], ends[r, 1], ends[r, 2], margins[r], s,
            include_end, _FLAG, 0, empty, block_low, block_dims, compact_of_box, b, slots, stats, flags,
        )  # fmt: skip


def flag_occupied(origins, ends, margins, voxel_size, include_end, block_voxels, block_low, block_dims, compact_of_box, slots, stats, flags):
    """Compiled: set ``flags[c, flat]`` for every voxel the segments cross that holds points they saw
    through (:func:`seen_through`, see ``_walk``); for
    :meth:`mabdi.voxels.voxel_map.VoxelMap.clear_free_space`. Rays as :func:`prepare_rays` gives them."""
    _flag_kernel(origins, ends, margins, float(voxel_size), include_end, np.int64(block_voxels), block_low, block_dims, compact_of_box, slots, stats, flags)


seen_through = njit(cache=True, inline="always")(seen_through)
_compact = njit(cache=True, inline="always")(_compact)
_walk = njit(cache=True, inline="always")(_walk)
_count_kernel = njit(cache=True, parallel=True)(_count_kernel)
_fill_kernel = njit(cache=True, parallel=True)(_fill_kernel)
_mask_kernel = njit(cache=True, parallel=True)(_mask_kernel)
_flag_kernel = njit(cache=True, parallel=True)(_flag_kernel)


def prepare_rays(origins, ends, margins=0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Checked, broadcast, contiguous float64 ``(origins (N, 3), ends (N, 3), margins (N,))``.

    ``origins`` may be one point (3,) for all rays (a camera centre); ``margins`` one number or one
    per ray, finite and >= 0 (metres).
    """
    ends = np.asarray(ends, dtype=np.float64)
    if ends.ndim != 2 or ends.shape[1] != 3:
        raise ValueError(f"voxel traversal: ends must have shape (N, 3), got {ends.shape}")
    origins = np.asarray(origins, dtype=np.float64)
    if origins.shape not in ((3,), (1, 3), ends.shape):
        raise ValueError(f"voxel traversal: origins must have shape (3,) or {ends.shape}, got {origins.shape}")
    origins = np.ascontiguousarray(np.broadcast_to(origins.reshape(-1, 3), ends.shape))
    margins = np.asarray(margins, dtype=np.float64)
    if margins.ndim > 1 or (margins.ndim == 1 and len(margins) != len(ends)):
        raise ValueError(f"voxel traversal: margins must be one number or one per ray ({len(ends)}), got {margins.shape}")
    margins = np.ascontiguousarray(np.broadcast_to(margins, (len(ends),)))
    if not (np.isfinite(origins).all() and np.isfinite(ends).all()):
        raise ValueError("voxel traversal: origins and ends must be finite (drop invalid pixels before)")
    if not (np.isfinite(margins).all() and (margins >= 0).all()):
        raise ValueError("voxel traversal: margins must be finite and >= 0 m")
    return origins, np.ascontiguousarray(ends), margins


def segment_ends(origins: np.ndarray, ends: np.ndarray, margins: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) pulled-back ends o + T u and (N,) T (metres; <= 0: the ray crosses nothing)."""
    delta = ends - origins
    length = np.linalg.norm(delta, axis=1)
    limit = length - margins
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(length > 0, np.maximum(limit, 0.0) / np.where(length > 0, length, 1.0), 0.0)
    return origins + delta * scale[:, None], limit


def voxel_box(origins: np.ndarray, ends: np.ndarray, margins: np.ndarray, voxel_size: float):
    """Lowest voxel index (3,) and size (3,) of a box holding every voxel the segments can cross (one voxel
    of padding for rounding)."""
    pulled, _ = segment_ends(origins, ends, margins)
    low = np.floor(np.minimum(origins.min(axis=0), pulled.min(axis=0)) / voxel_size).astype(np.int64) - 1
    high = np.floor(np.maximum(origins.max(axis=0), pulled.max(axis=0)) / voxel_size).astype(np.int64) + 1
    return low, high - low + 1


def traverse_voxels(origins, ends, voxel_size: float, margins=0.0, *, include_end: bool = True) -> np.ndarray:
    """Unique (M, 3) int64 indices of the voxels of ``voxel_size`` metres crossed by the ray segments.

    ``origins`` (N, 3) or (3,) and ``ends`` (N, 3) in world metres; each segment stops ``margins``
    (metres, one number or (N,)) before its end point; ``include_end=False`` also drops the voxel
    holding that pulled-back end (see the module docs). Rows are sorted by (i, j, k).
    """
    if not voxel_size > 0:
        raise ValueError(f"voxel traversal: voxel_size must be > 0 m, got {voxel_size}")
    origins, ends, margins = prepare_rays(origins, ends, margins)
    s = float(voxel_size)
    if len(ends) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    low, dims = voxel_box(origins, ends, margins, s)
    volume = float(np.prod(dims.astype(np.float64)))
    if volume <= MASK_VOXELS:
        mask = np.zeros(int(volume), dtype=np.uint8)
        _mask_kernel(origins, ends, margins, s, include_end, low, dims, mask)
        flat = np.flatnonzero(mask)
        return np.stack([flat // (dims[1] * dims[2]), (flat // dims[2]) % dims[1], flat % dims[2]], axis=1) + low
    rays, out = _pairs(origins, ends, margins, s, include_end)
    if volume < 2.0**62:
        key = ((out[:, 0] - low[0]) * dims[1] + (out[:, 1] - low[1])) * dims[2] + (out[:, 2] - low[2])
        flat = np.unique(key)
        return np.stack([flat // (dims[1] * dims[2]), (flat // dims[2]) % dims[1], flat % dims[2]], axis=1) + low
    return np.unique(out, axis=0)


def _pairs(origins, ends, margins, s, include_end):
    counts = np.empty(len(ends), dtype=np.int64)
    _count_kernel(origins, ends, margins, s, include_end, counts)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    out = np.empty((int(counts.sum()), 3), dtype=np.int64)
    _fill_kernel(origins, ends, margins, s, include_end, starts, out)
    return np.repeat(np.arange(len(ends)), counts), out


def ray_voxels(origins, ends, voxel_size: float, margins=0.0, *, include_end: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Every (ray, voxel) crossing: ray indices (K,) and voxel indices (K, 3) int64, by ray, each ray's
    voxels in order along it; arguments as :func:`traverse_voxels`. Compiled count-then-fill passes."""
    if not voxel_size > 0:
        raise ValueError(f"voxel traversal: voxel_size must be > 0 m, got {voxel_size}")
    origins, ends, margins = prepare_rays(origins, ends, margins)
    return _pairs(origins, ends, margins, float(voxel_size), include_end)
