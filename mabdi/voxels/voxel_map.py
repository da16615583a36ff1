"""VoxelMap: per-voxel sufficient statistics in a semi-sparse blockwise grid (seed 000, §IV-A, §IV-C).

Space is cut into voxels of ``voxel_size`` metres in the world frame; voxel
(i, j, k) (int64, negative fine) covers [i s, (i + 1) s) x [j s, ...) x
[k s, ...). Voxels are grouped into cubic blocks of ``block_size`` metres,
allocated dense the first time a point falls in one, found by a sorted table
of block keys: memory grows with the occupied blocks, with no bounds.

Per voxel, in float64: n, S1 = sum(q), S2 = sum(q q^T) with q = p - the
voxel's lower corner (so the covariance does not cancel far from the
origin). Adding points only adds to the sums: incremental and order-free.
With colour input (uint8 RGB) the map also keeps per voxel the count and
sums of the coloured points (float32, a parallel array ``_colour``).

Free space (object removal): :meth:`VoxelMap.clear_free_space` walks the rays
that saw through the map (:mod:`mabdi.voxels.traversal`, Amanatides & Woo)
and zeroes the voxels they cross; :meth:`VoxelMap.clear_voxels` zeroes given
voxels; both return the voxels that held points (:class:`ClearedVoxels`).
:meth:`VoxelMap.neighbourhood_moments` combines ``window``^3 voxels (the
seed's eqs. 2-3, exactly the sum of the shifted sums).
Details: docs/architecture.md (``mabdi.voxels.voxel_map``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mabdi.errors import ConfigError
from mabdi.voxels import traversal as voxel_traversal

from numba import njit

#: Statistics per voxel: n, S1 (x, y, z), S2 (xx, xy, xz, yy, yz, zz).
STATS = 10
#: Colour sums per voxel: number of coloured points, sum of red, green, blue.
COLOUR_STATS = 4
_PACK_BITS = 21
_PACK_OFFSET = 1 << (_PACK_BITS - 1)
#: Largest dense table of blocks :meth:`VoxelMap.clear_free_space` builds over its rays' bounding box.
CLEAR_BLOCKS = 1 << 22


def pack_keys(indices: np.ndarray) -> np.ndarray:
    """int64 keys of (M, 3) integer indices in [-2^20, 2^20) (block or voxel coordinates)."""
    shifted = np.asarray(indices, dtype=np.int64) + _PACK_OFFSET
    return (shifted[:, 0] << (2 * _PACK_BITS)) | (shifted[:, 1] << _PACK_BITS) | shifted[:, 2]


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """(M, 3) int64 indices of keys made by :func:`pack_keys`."""
    keys = np.asarray(keys, dtype=np.int64)
    mask = (1 << _PACK_BITS) - 1
    return np.stack([(keys >> (2 * _PACK_BITS)) & mask, (keys >> _PACK_BITS) & mask, keys & mask], axis=1) - _PACK_OFFSET


def _sums(points: np.ndarray) -> np.ndarray:
    """(M, 9) first and second moments (x, y, z, xx, xy, xz, yy, yz, zz) of (M, 3) points."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    return np.stack([x, y, z, x * x, x * y, x * z, y * y, y * z, z * z], axis=1)


def moments_to_gaussian(moments: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Counts (M,), means (M, 3) and covariances (M, 3, 3) of (M, 10) moments (relative frame).

    Rows with n = 0 give NaN means and covariances.
    """
    n = moments[:, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = moments[:, 1:4] / n[:, None]
        second = moments[:, 4:] / n[:, None]
    xx, xy, xz, yy, yz, zz = second.T
    cov = np.empty((len(n), 3, 3))
    cov[:, 0, 0] = xx - mean[:, 0] * mean[:, 0]
    cov[:, 0, 1] = cov[:, 1, 0] = xy - mean[:, 0] * mean[:, 1]
    cov[:, 0, 2] = cov[:, 2, 0] = xz - mean[:, 0] * mean[:, 2]
    cov[:, 1, 1] = yy - mean[:, 1] * mean[:, 1]
    cov[:, 1, 2] = cov[:, 2, 1] = yz - mean[:, 1] * mean[:, 2]
    cov[:, 2, 2] = zz - mean[:, 2] * mean[:, 2]
    return n, mean, cov


def shift_moments(moments: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Moments of the same points seen from a frame whose origin is ``-offset`` away: q -> q + offset.

    ``offset`` is one 3-vector or one per row.
    """
    n = moments[:, 0:1]
    s1 = moments[:, 1:4]
    d = np.broadcast_to(np.asarray(offset, dtype=np.float64), s1.shape)
    out = moments.copy()
    out[:, 1:4] = s1 + n * d
    # S2' = S2 + d S1^T + S1 d^T + n d d^T, unique entries in the order xx, xy, xz, yy, yz, zz
    for column, (a, b) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
        out[:, 4 + column] += d[:, a] * s1[:, b] + s1[:, a] * d[:, b] + n[:, 0] * d[:, a] * d[:, b]
    return out


def _block_range(px, py, pz, s, b):
    """Lowest and highest block coordinates of the points (one pass)."""
    low = np.full(3, np.iinfo(np.int64).max, dtype=np.int64)
    high = np.full(3, np.iinfo(np.int64).min, dtype=np.int64)
    for i in range(px.shape[0]):
        for axis, value in enumerate((px[i], py[i], pz[i])):
            block = np.int64(np.floor(value / s)) // b
            low[axis] = min(low[axis], block)
            high[axis] = max(high[axis], block)
    return low, high


def _mark_blocks(px, py, pz, s, b, low, box, present):
    for i in range(px.shape[0]):
        bx = np.int64(np.floor(px[i] / s)) // b - low[0]
        by = np.int64(np.floor(py[i] / s)) // b - low[1]
        bz = np.int64(np.floor(pz[i] / s)) // b - low[2]
        present[(bx * box[1] + by) * box[2] + bz] = True


def _accumulate(px, py, pz, s, b, low, box, compact_of_box, slot_of_compact, stats, touched, rgb=None, colour=None):
    """Add each point's moments to its voxel (relative to the voxel's corner); mark the voxel touched. With
    ``rgb`` ((M, 3) uint8) add one and the point's colour to the voxel's ``colour`` sums too (numba compiles
    the two cases apart: without colour the branch is pruned)."""
    for i in range(px.shape[0]):
        vx = np.int64(np.floor(px[i] / s))
        vy = np.int64(np.floor(py[i] / s))
        vz = np.int64(np.floor(pz[i] / s))
        bx, by, bz = vx // b, vy // b, vz // b
        compact = compact_of_box[((bx - low[0]) * box[1] + (by - low[1])) * box[2] + (bz - low[2])]
        flat = ((vx - bx * b) * b + (vy - by * b)) * b + (vz - bz * b)
        x, y, z = px[i] - vx * s, py[i] - vy * s, pz[i] - vz * s
        row = stats[slot_of_compact[compact], flat]
        row[0] += 1.0
        row[1] += x
        row[2] += y
        row[3] += z
        row[4] += x * x
        row[5] += x * y
        row[6] += x * z
        row[7] += y * y
        row[8] += y * z
        row[9] += z * z
        touched[compact, flat] = True
        if rgb is not None:
            sums = colour[slot_of_compact[compact], flat]
            sums[0] += 1.0
            sums[1] += rgb[i, 0]
            sums[2] += rgb[i, 1]
            sums[3] += rgb[i, 2]


_block_range = njit(cache=True)(_block_range)
_mark_blocks = njit(cache=True)(_mark_blocks)
_accumulate = njit(cache=True)(_accumulate)


@dataclass(frozen=True)
class ClearedVoxels:
    """What :meth:`VoxelMap.clear_voxels` / :meth:`VoxelMap.clear_free_space` removed.

    ``voxels`` (K, 3) int64: the voxels that held points and are empty now, sorted by (i, j, k);
    ``blocks`` (sorted int64 keys, :func:`pack_keys` of block coordinates): their blocks;
    ``points``: how many points their statistics counted.
    """

    voxels: np.ndarray
    blocks: np.ndarray
    points: int

    def __len__(self) -> int:
        return len(self.voxels)


class VoxelMap:
    """Sufficient statistics of points per voxel, stored blockwise (see the module docs).

    ``voxel_size`` and ``block_size`` in metres; ``block_size`` must be a whole
    number of voxels. Attributes after :meth:`add_points`, :meth:`clear_voxels` or
    :meth:`clear_free_space`: ``last_changed``, the (M, 3) voxel indices whose statistics changed.
    """

    def __init__(self, voxel_size: float = 0.05, block_size: float = 1.0) -> None:
        if not voxel_size > 0:
            raise ConfigError(f"VoxelMap: voxel_size must be > 0 m, got {voxel_size}")
        ratio = block_size / voxel_size
        if not block_size > 0 or abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
            raise ConfigError(
                f"VoxelMap: block_size ({block_size} m) must be a whole number of voxels of {voxel_size} m"
            )
        self.voxel_size = float(voxel_size)
        self.block_voxels = int(round(ratio))
        self.block_size = self.block_voxels * self.voxel_size
        self.reset()

    # -- storage -----------------------------------------------------------
    def reset(self) -> None:
        """Forget every point."""
        b3 = self.block_voxels**3
        self._keys = np.zeros(0, dtype=np.int64)  # sorted block keys
        self._slots = np.zeros(0, dtype=np.int64)  # slot of each key in _stats
        self._stats = np.zeros((0, b3, STATS), dtype=np.float64)
        self._colour: np.ndarray | None = None  # (capacity, b3, COLOUR_STATS) float32 once coloured points arrive
        self._used = 0
        self.last_changed = np.zeros((0, 3), dtype=np.int64)

    def state(self) -> dict:
        """The statistics as plain data (sizes in metres, the used blocks' arrays, the store's capacity), for
        checkpoints; ``colour``, the colour sums, only when the map has colour."""
        state = {
            "voxel_size": self.voxel_size,
            "block_size": self.block_size,
            "keys": self._keys.copy(),
            "slots": self._slots.copy(),
            "stats": self._stats[: self._used].copy(),
            "capacity": int(len(self._stats)),
            "last_changed": np.asarray(self.last_changed, dtype=np.int64).copy(),
        }
        if self._colour is not None:
            state["colour"] = self._colour[: self._used].copy()
        return state

    @classmethod
    def from_state(cls, state: dict) -> VoxelMap:
        """The map of :meth:`state` (the same statistics, and the same capacity, so it grows as the original would)."""
        voxels = cls(float(state["voxel_size"]), float(state["block_size"]))
        stats = np.asarray(state["stats"], dtype=np.float64)
        voxels._stats = np.zeros((max(int(state["capacity"]), len(stats)),) + voxels._stats.shape[1:], dtype=np.float64)
        voxels._stats[: len(stats)] = stats
        voxels._used = len(stats)
        if state.get("colour") is not None:  # states written before colour have none
            colour = np.asarray(state["colour"], dtype=np.float32)
            if colour.shape != stats.shape[:2] + (COLOUR_STATS,):
                raise ValueError(f"VoxelMap state: colour sums of shape {colour.shape} do not match statistics of shape {stats.shape}")
            voxels._colour = np.zeros(voxels._stats.shape[:2] + (COLOUR_STATS,), dtype=np.float32)
            voxels._colour[: len(colour)] = colour
        voxels._keys = np.asarray(state["keys"], dtype=np.int64).copy()
        voxels._slots = np.asarray(state["slots"], dtype=np.int64).copy()
        voxels.last_changed = np.asarray(state["last_changed"], dtype=np.int64).reshape(-1, 3).copy()
        return voxels

    @property
    def number_of_blocks(self) -> int:
        return int(len(self._keys))

    @property
    def has_colour(self) -> bool:
        """Whether coloured points have been added (the map keeps colour sums)."""
        return self._colour is not None

    @property
    def number_of_points(self) -> int:
        return int(round(self._stats[: self._used, :, 0].sum()))

    def memory_bytes(self) -> int:
        """Bytes held by the allocated blocks (statistics and the block table)."""
        per_block = self._stats[0].nbytes if len(self._stats) else self.block_voxels**3 * STATS * 8
        if self._colour is not None:
            per_block += self._colour[0].nbytes if len(self._colour) else self.block_voxels**3 * COLOUR_STATS * 4
        return int(self._used * per_block + self._keys.nbytes + self._slots.nbytes)

    def block_slots(self, block_keys: np.ndarray) -> np.ndarray:
        """Slot of each block key in the statistics store, -1 for blocks never allocated."""
        block_keys = np.asarray(block_keys, dtype=np.int64)
        if len(self._keys) == 0:
            return np.full(block_keys.shape, -1, dtype=np.int64)
        where = np.searchsorted(self._keys, block_keys)
        where = np.minimum(where, len(self._keys) - 1)
        return np.where(self._keys[where] == block_keys, self._slots[where], -1)

    def _allocate(self, block_keys: np.ndarray) -> None:
        """Allocate zeroed blocks for the (unique) keys that have none yet."""
        new = block_keys[self.block_slots(block_keys) < 0]
        if len(new) == 0:
            return
        needed = self._used + len(new)
        if needed > len(self._stats):
            capacity = max(needed, 2 * len(self._stats), 8)
            grown = np.zeros((capacity,) + self._stats.shape[1:], dtype=np.float64)
            grown[: self._used] = self._stats[: self._used]
            self._stats = grown
            if self._colour is not None:
                colour = np.zeros(grown.shape[:2] + (COLOUR_STATS,), dtype=np.float32)
                colour[: self._used] = self._colour[: self._used]
                self._colour = colour
        slots = np.arange(self._used, needed, dtype=np.int64)
        self._used = needed
        keys = np.concatenate([self._keys, new])
        order = np.argsort(keys, kind="stable")
        self._keys = keys[order]
        self._slots = np.concatenate([self._slots, slots])[order]

    # -- indexing ----------------------------------------------------------
    def voxel_indices(self, points: np.ndarray) -> np.ndarray:
        """(M, 3) int64 index of the voxel holding each world point."""
        return np.floor(np.asarray(points, dtype=np.float64) / self.voxel_size).astype(np.int64)

    def _locate(self, voxels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Block key and local flat index (within its block) of (M, 3) voxel indices."""
        b = self.block_voxels
        blocks = np.floor_divide(voxels, b)
        local = voxels - blocks * b
        return pack_keys(blocks), (local[:, 0] * b + local[:, 1]) * b + local[:, 2]

    # -- updates -----------------------------------------------------------
    def add_points(self, points: np.ndarray, colours: np.ndarray | None = None) -> np.ndarray:
        """Add (M, 3) world points (metres), and their (M, 3) uint8 RGB ``colours`` when given; returns the
        (K, 3) indices of the voxels that changed.

        Non-finite points are an error (drop invalid pixels before).
        """
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"VoxelMap.add_points: points must have shape (M, 3), got {points.shape}")
        if colours is not None:
            colours = np.asarray(colours)
            if colours.shape != points.shape or colours.dtype != np.uint8:
                raise ValueError(
                    f"VoxelMap.add_points: colours must be uint8 of shape {points.shape} (one RGB per point), got {colours.dtype} {colours.shape}"
                )
            colours = np.ascontiguousarray(colours)
        if len(points) == 0:
            self.last_changed = np.zeros((0, 3), dtype=np.int64)
            return self.last_changed
        if not np.isfinite(points).all():
            raise ValueError("VoxelMap.add_points: points contain NaN or infinite coordinates")
        b = self.block_voxels
        s = self.voxel_size
        if colours is not None and self._colour is None:
            self._colour = np.zeros(self._stats.shape[:2] + (COLOUR_STATS,), dtype=np.float32)
        # per axis, contiguous: column arithmetic on (M, 3) arrays is strided and several times slower
        columns = [np.ascontiguousarray(points[:, axis]) for axis in range(3)]
        changed = self._add_compiled(columns, colours)
        if changed is not None:
            self.last_changed = changed
            return changed
        # the points' blocks are too spread for the compiled passes' dense box: numpy sums over the touched blocks
        voxel = [np.floor(c / s).astype(np.int64) for c in columns]
        block = [v // b for v in voxel]
        local_flat = ((voxel[0] - block[0] * b) * b + (voxel[1] - block[1] * b)) * b + (voxel[2] - block[2] * b)
        touched, compact = np.unique(pack_keys(np.stack(block, axis=1)), return_inverse=True)
        compact = compact.ravel()
        self._allocate(np.sort(touched))
        slots = self.block_slots(touched)
        b3 = b**3
        flat = compact * b3 + local_flat
        size = len(touched) * b3
        x, y, z = (c - v * s for c, v in zip(columns, voxel, strict=True))
        weights = (x, y, z, x * x, x * y, x * z, y * y, y * z, z * z)
        if 8 * len(points) >= size:
            # many points: dense sums over the touched blocks, no sorting
            sums = np.empty((STATS, size))
            sums[0] = np.bincount(flat, minlength=size)
            for column, values in enumerate(weights, start=1):
                sums[column] = np.bincount(flat, weights=values, minlength=size)
            if colours is not None:
                colour_sums = np.empty((COLOUR_STATS, size))
                colour_sums[0] = sums[0]
                for channel in range(3):
                    colour_sums[1 + channel] = np.bincount(flat, weights=colours[:, channel], minlength=size)
                self._colour[slots] += colour_sums.reshape(COLOUR_STATS, len(touched), b3).transpose(1, 2, 0)
            sums = sums.reshape(STATS, len(touched), b3).transpose(1, 2, 0)
            self._stats[slots] += sums
            changed = np.flatnonzero(sums[:, :, 0].ravel() > 0)
        else:
            # few points in big blocks (the novel pixels of a frame): sums over the touched voxels only
            changed, inverse = np.unique(flat, return_inverse=True)
            sums = np.empty((len(changed), STATS))
            sums[:, 0] = np.bincount(inverse, minlength=len(changed))
            for column, values in enumerate(weights, start=1):
                sums[:, column] = np.bincount(inverse, weights=values, minlength=len(changed))
            self._stats[slots[changed // b3], changed % b3] += sums
            if colours is not None:
                colour_sums = np.empty((len(changed), COLOUR_STATS))
                colour_sums[:, 0] = sums[:, 0]
                for channel in range(3):
                    colour_sums[:, 1 + channel] = np.bincount(inverse, weights=colours[:, channel], minlength=len(changed))
                self._colour[slots[changed // b3], changed % b3] += colour_sums
        self.last_changed = self._voxels_of(touched[changed // b3], changed % b3)
        return self.last_changed

    def _add_compiled(self, columns, colours: np.ndarray | None = None) -> np.ndarray | None:
        """:meth:`add_points` in three compiled passes over the points (range, blocks, sums and colours); None
        when the points' blocks are too spread for a dense box (the numpy path handles those)."""
        b, s = self.block_voxels, self.voxel_size
        low, high = _block_range(*columns, s, b)
        if max(np.abs(low).max(), np.abs(high).max()) >= _PACK_OFFSET:
            raise ValueError("VoxelMap.add_points: points lie outside the +-1000 km the block keys can address")
        box = high - low + 1
        volume = int(np.prod(box))
        if volume > 1 << 20:
            return None
        present = np.zeros(volume, dtype=np.bool_)
        _mark_blocks(*columns, s, b, low, box, present)
        boxes = np.flatnonzero(present)
        coords = np.stack([boxes // (box[1] * box[2]), (boxes // box[2]) % box[1], boxes % box[2]], axis=1)
        touched = pack_keys(coords + low)
        self._allocate(np.sort(touched))
        compact_of_box = np.full(volume, -1, dtype=np.int64)
        compact_of_box[boxes] = np.arange(len(boxes))
        marks = np.zeros((len(boxes), b**3), dtype=np.bool_)
        slots = self.block_slots(touched)
        _accumulate(*columns, s, b, low, box, compact_of_box, slots, self._stats, marks, colours, self._colour)
        compact, flat = np.nonzero(marks)
        return self._voxels_of(touched[compact], flat)

    # -- removal -----------------------------------------------------------
    def clear_voxels(self, voxels: np.ndarray) -> ClearedVoxels:
        """Zero the statistics of (M, 3) voxel indices (duplicates fine); returns those that held points.

        Voxels without points (or in blocks never allocated) change nothing.
        """
        voxels = np.asarray(voxels, dtype=np.int64).reshape(-1, 3)
        b = self.block_voxels
        blocks = np.floor_divide(voxels, b)
        addressable = ((blocks >= -_PACK_OFFSET) & (blocks < _PACK_OFFSET)).all(axis=1)  # no key aliasing
        voxels, blocks = voxels[addressable], blocks[addressable]
        local = voxels - blocks * b
        slots = self.block_slots(pack_keys(blocks))
        flat = (local[:, 0] * b + local[:, 1]) * b + local[:, 2]
        held = np.flatnonzero(slots >= 0)
        held = held[self._stats[slots[held], flat[held], 0] > 0]
        _, first = np.unique(slots[held] * b**3 + flat[held], return_index=True)
        held = held[first]
        return self._clear(voxels[held], slots[held], flat[held])

    def clear_free_space(self, origins: np.ndarray, ends: np.ndarray, margins=0.0) -> ClearedVoxels:
        """Empty the voxels that rays from ``origins`` to ``ends`` cross in free space; returns those that held points.

        ``origins`` (N, 3) or one (3,) (a camera centre) and ``ends`` (N, 3) in world metres: the
        measured points of rays that saw through the map. Each ray is walked up to ``margins``
        metres (along the ray; one number or (N,), e.g. the classifier's threshold tau(z) of each
        pixel, scaled by |ray| / z) before its end, and the voxel holding that pulled-back end is
        kept too (:func:`mabdi.voxels.traversal.traverse_voxels` with ``include_end=False``):
        a ray never clears its own end point's voxel. A crossed voxel is emptied when the ray saw
        through its points (:func:`mabdi.voxels.traversal.seen_through`: it passes within
        3 sigma of their Gaussian before the pulled-back end), so a ray that grazes the surface it
        measures, or passes beside points in a voxel it crosses, leaves them. One compiled pass walks the rays and flags the crossed voxels that hold points (when the
        rays' blocks fit a dense table of :data:`CLEAR_BLOCKS` blocks); otherwise :meth:`clear_voxels`
        of the traversal.
        """
        origins, ends, margins = voxel_traversal.prepare_rays(origins, ends, margins)
        s, b = self.voxel_size, self.block_voxels
        if len(ends) == 0 or self._used == 0:
            return self._clear(np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
        low, dims = voxel_traversal.voxel_box(origins, ends, margins, s)
        block_low = np.floor_divide(low, b)
        block_dims = np.floor_divide(low + dims - 1, b) - block_low + 1
        if float(np.prod(block_dims.astype(np.float64))) > CLEAR_BLOCKS:
            return self.clear_voxels(self._seen_through(origins, ends, margins))
        coords = unpack_keys(self._keys) - block_low
        inside = np.flatnonzero(((coords >= 0) & (coords < block_dims)).all(axis=1))
        table = np.full(int(np.prod(block_dims)), -1, dtype=np.int64)
        box = (coords[inside, 0] * block_dims[1] + coords[inside, 1]) * block_dims[2] + coords[inside, 2]
        table[box] = np.arange(len(inside))
        flags = np.zeros((len(inside), b**3), dtype=np.bool_)
        slots = self._slots[inside]
        voxel_traversal.flag_occupied(origins, ends, margins, s, False, b, block_low, block_dims, table, slots, self._stats, flags)
        compact, flat = np.nonzero(flags)
        return self._clear(self._voxels_of(self._keys[inside][compact], flat), slots[compact], flat)

    def _seen_through(self, origins: np.ndarray, ends: np.ndarray, margins: np.ndarray) -> np.ndarray:
        """The voxels :meth:`clear_free_space` empties, from every (ray, voxel) crossing: for rays whose blocks
        do not fit the compiled pass's table (a test checks that both give the same map)."""
        rays, voxels = voxel_traversal.ray_voxels(origins, ends, self.voxel_size, margins, include_end=False)
        moments = self.moments(voxels)
        occupied = moments[:, 0] > 0
        rays, voxels, moments = rays[occupied], voxels[occupied], moments[occupied]
        delta = ends[rays] - origins[rays]
        length = np.linalg.norm(delta, axis=1)
        w = origins[rays] - voxels * self.voxel_size
        u = delta / length[:, None]
        hit = voxel_traversal.seen_through(*moments.T, *w.T, *u.T, length - margins[rays], self.voxel_size)
        return voxels[hit]

    def _clear(self, voxels: np.ndarray, slots: np.ndarray, flat: np.ndarray) -> ClearedVoxels:
        """Zero the statistics of distinct voxels (their slots and flat indices); the result, sorted."""
        points = int(round(self._stats[slots, flat, 0].sum()))
        self._stats[slots, flat] = 0.0
        if self._colour is not None:
            self._colour[slots, flat] = 0.0
        order = np.lexsort(voxels.T[::-1])
        voxels = voxels[order]
        self.last_changed = voxels
        return ClearedVoxels(voxels, np.unique(self.block_of(voxels)), points)

    def _voxels_of(self, block_keys: np.ndarray, local_flat: np.ndarray) -> np.ndarray:
        b = self.block_voxels
        local = np.stack([local_flat // (b * b), (local_flat // b) % b, local_flat % b], axis=1)
        return unpack_keys(block_keys) * b + local

    # -- queries -----------------------------------------------------------
    def moments(self, voxels: np.ndarray) -> np.ndarray:
        """(M, 10) statistics of (M, 3) voxel indices (zeros for empty voxels), relative to each voxel's corner."""
        voxels = np.asarray(voxels, dtype=np.int64).reshape(-1, 3)
        block_keys, local = self._locate(voxels)
        slots = self.block_slots(block_keys)
        out = np.zeros((len(voxels), STATS))
        found = slots >= 0
        out[found] = self._stats[slots[found], local[found]]
        return out

    def colour_sums(self, voxels: np.ndarray) -> np.ndarray:
        """(M, 4) float64 colour sums of (M, 3) voxel indices: coloured points, sum of red, green, blue (zeros for
        voxels without coloured points, and everywhere in a map without colour)."""
        voxels = np.asarray(voxels, dtype=np.int64).reshape(-1, 3)
        out = np.zeros((len(voxels), COLOUR_STATS))
        if self._colour is None:
            return out
        block_keys, local = self._locate(voxels)
        slots = self.block_slots(block_keys)
        found = slots >= 0
        out[found] = self._colour[slots[found], local[found]]
        return out

    def colours(self, voxels: np.ndarray) -> np.ndarray:
        """(M, 3) float64 mean RGB (0-255) of the coloured points of (M, 3) voxels; NaN where there are none."""
        sums = self.colour_sums(voxels)
        with np.errstate(invalid="ignore", divide="ignore"):
            return sums[:, 1:] / sums[:, :1]

    def counts(self, voxels: np.ndarray) -> np.ndarray:
        """Number of points in each of the (M, 3) voxels."""
        return self.moments(voxels)[:, 0].astype(np.int64)

    def gaussians(self, voxels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Counts, world centroids (M, 3) and covariances (M, 3, 3) of voxels (NaN where empty)."""
        voxels = np.asarray(voxels, dtype=np.int64).reshape(-1, 3)
        n, mean, cov = moments_to_gaussian(self.moments(voxels))
        return n, mean + voxels * self.voxel_size, cov

    def occupied_voxels(self, block_keys: np.ndarray | None = None) -> np.ndarray:
        """(M, 3) indices of the voxels holding points (of the given blocks, or all)."""
        keys = self._keys if block_keys is None else np.asarray(block_keys, dtype=np.int64)
        slots = self.block_slots(keys)
        keys, slots = keys[slots >= 0], slots[slots >= 0]
        if len(keys) == 0:
            return np.zeros((0, 3), dtype=np.int64)
        block, local = np.nonzero(self._stats[slots, :, 0] > 0)
        return self._voxels_of(keys[block], local)

    def block_keys(self) -> np.ndarray:
        """Sorted keys of the allocated blocks."""
        return self._keys.copy()

    def block_of(self, voxels: np.ndarray) -> np.ndarray:
        """Block key of each of the (M, 3) voxel (or vertex) indices."""
        return pack_keys(np.floor_divide(np.asarray(voxels, dtype=np.int64), self.block_voxels))

    def neighbourhood_moments(self, corners: np.ndarray, window: int) -> np.ndarray:
        """(M, 10) combined statistics of the ``window``^3 voxels from each (M, 3) lowest voxel index.

        Moments are relative to the lowest voxel's corner (corners * voxel_size), eqs. (2)-(3) in
        raw-moment form.
        """
        corners = np.asarray(corners, dtype=np.int64).reshape(-1, 3)
        total = np.zeros((len(corners), STATS))
        for offset in np.ndindex(window, window, window):
            step = np.array(offset, dtype=np.int64)
            moments = self.moments(corners + step)
            total += shift_moments(moments, step * self.voxel_size)
        return total
