"""Face identity in the expected image: which map face each pixel of E shows.

The expected-image renderer draws every face of the map blocks in view in a
flat colour that encodes a 24-bit code (red = low byte; 0 = no face). Codes
are a rendering matter, not the faces' names: the renderer gives each block
it draws a range of consecutive codes (:class:`FaceCodes`, first fit), keeps
it while the block stays in view (so the block's colours are not uploaded
again), and frees it when the block leaves the view. A map may therefore hold
any number of faces; only the faces of the blocks drawn in one image share
the 16.7M codes (:data:`MAX_FACE_CODE`), which a 640x480 view never nears.

What a code means travels with E (:class:`FaceIdTable`, field data
``face_id_blocks`` and ``face_id_ranges``): the name of each drawn block (the
world mesh's patch key), its first code, its number of faces and which
polydata was drawn (:func:`block_address`, so that a block replaced since
under the same name is told apart). A face is then (block name, local cell
id), which is how the world mesh keeps its faces' removal evidence and
normals (:mod:`mabdi.world_map`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkStringArray

#: Codes are 1 .. 2^24 - 1 (0 = no face): the faces drawn in one image share them.
MAX_FACE_CODE = 2**24 - 1
#: Field data of E rendered with identity: the names of the blocks drawn, and (first code, faces) of each.
FACE_ID_BLOCKS_ARRAY = "face_id_blocks"
FACE_ID_RANGES_ARRAY = "face_id_ranges"


def face_rgb(base: int, count: int) -> np.ndarray:
    """(count, 3) uint8 RGB of the codes base .. base + count - 1 (red = low byte): the first three bytes of
    each code as a little-endian 32-bit word."""
    words = np.arange(base, base + count, dtype="<u4")
    return np.ascontiguousarray(words.view(np.uint8).reshape(-1, 4)[:, :3])


class FaceCodes:
    """Ranges of consecutive 24-bit codes, one per drawn block (keyed by any hashable), first fit, reused."""

    def __init__(self) -> None:
        self.ranges: dict[object, tuple[int, int]] = {}  # block -> (base, size)
        self._sorted: list[tuple[int, int]] | None = None

    def allocate(self, block, size: int) -> int:
        """A base code for ``size`` faces of ``block`` (its previous range is released); MemoryError when the
        blocks drawn together hold more faces than there are codes."""
        self.release(block)
        if self._sorted is None:
            self._sorted = sorted(self.ranges.values())
        start = 1
        for base, length in self._sorted:
            if base - start >= size:
                break
            start = max(start, base + length)
        if start + size - 1 > MAX_FACE_CODE:
            raise MemoryError(
                f"the map blocks in view hold more than {MAX_FACE_CODE:,} faces: an expected image can tell at most "
                "that many faces apart (a shorter far range or a coarser surface keeps fewer faces in view)"
            )
        self.ranges[block] = (start, size)
        self._sorted = None
        return start

    def release(self, block) -> None:
        if self.ranges.pop(block, None) is not None:
            self._sorted = None

    def clear(self) -> None:
        self.ranges.clear()
        self._sorted = None


def unique_codes(codes) -> tuple[np.ndarray, np.ndarray]:
    """(the distinct codes, sorted; the index of each of ``codes`` among them): ``np.unique(codes,
    return_inverse=True)`` for the face codes of one expected image (0 .. :data:`MAX_FACE_CODE`), by a table over
    the codes' range rather than a sort (a frame votes with some 10^5 pixels on codes in a range of about as many)."""
    codes = np.asarray(codes, dtype=np.int64).reshape(-1)
    if not len(codes):
        return codes.copy(), np.zeros(0, dtype=np.int64)
    low, high = int(codes.min()), int(codes.max())
    if high - low > 8 * len(codes) + 4096:  # few codes spread wide: the sort is cheaper than the table
        return np.unique(codes, return_inverse=True)
    shifted = codes - low
    present = np.zeros(high - low + 1, dtype=bool)
    present[shifted] = True
    distinct = np.flatnonzero(present)
    index = np.empty(high - low + 1, dtype=np.int32)  # fewer than 2^24 codes
    index[distinct] = np.arange(len(distinct), dtype=np.int32)
    return distinct + low, index[shifted].astype(np.int64)


def codes_in(codes, chosen) -> np.ndarray:
    """Boolean array shaped like ``codes``: which of them are among ``chosen`` (``np.isin`` for face codes): by a
    table over the range of ``codes``, or where that range is wide for their number, by a binary search in the
    sorted ``chosen``."""
    codes = np.asarray(codes, dtype=np.int64)
    chosen = np.asarray(chosen, dtype=np.int64).reshape(-1)
    if not codes.size or not len(chosen):
        return np.zeros(codes.shape, dtype=bool)
    low, high = int(codes.min()), int(codes.max())
    if high - low > 8 * codes.size + 4096:
        if np.any(chosen[1:] < chosen[:-1]):
            chosen = np.sort(chosen)
        at = np.minimum(np.searchsorted(chosen, codes), len(chosen) - 1)
        return chosen[at] == codes
    table = np.zeros(high - low + 1, dtype=bool)
    table[chosen[(chosen >= low) & (chosen <= high)] - low] = True
    return table[codes - low]


def rows_by_block(block) -> list[tuple[int, np.ndarray]]:
    """(b, the rows of the flat ``block`` that hold b, increasing) for each block index b >= 0 in it (-1: no
    block), b increasing: one stable sort for all blocks rather than a comparison of every row per block."""
    flat = np.asarray(block).reshape(-1)
    valid = np.flatnonzero(flat >= 0)
    if not len(valid):
        return []
    which = flat[valid]
    counts = np.bincount(which)
    small = which.astype(np.uint16) if len(counts) <= 2**16 else which  # 16-bit keys sort by radix
    order = valid[np.argsort(small, kind="stable")]
    ends = np.cumsum(counts)
    return [(int(b), order[ends[b] - counts[b] : ends[b]]) for b in np.flatnonzero(counts)]


def block_address(polydata) -> int:
    """Which polydata object a block is, while it lives (its C++ address): a block replaced under the same name
    is another object. Only meaningful within one process, for one image's codes."""
    return int(polydata.GetAddressAsString("vtkPolyData")[5:], 16)


@dataclass
class FaceIdTable:
    """What the codes of one expected image mean: block ``names[i]`` has codes ``bases[i]`` ..
    ``bases[i] + counts[i] - 1`` for its cells 0 .. counts[i] - 1, and was the polydata ``addresses[i]``
    (:func:`block_address`; 0: not said)."""

    names: list[str]
    bases: np.ndarray
    counts: np.ndarray
    addresses: np.ndarray | None = None

    def __post_init__(self) -> None:
        order = np.argsort(np.asarray(self.bases, dtype=np.int64), kind="stable")
        self.names = [self.names[i] for i in order]
        self.bases = np.asarray(self.bases, dtype=np.int64)[order]
        self.counts = np.asarray(self.counts, dtype=np.int64)[order]
        if self.addresses is None:
            self.addresses = np.zeros(len(self.names), dtype=np.int64)
        self.addresses = np.asarray(self.addresses, dtype=np.int64)[order]

    @classmethod
    def empty(cls) -> FaceIdTable:
        return cls([], np.zeros(0, np.int64), np.zeros(0, np.int64))

    def lookup(self, codes) -> tuple[np.ndarray, np.ndarray]:
        """(index into ``names``, local cell id) of each code; -1, -1 for 0 and codes no block has."""
        codes = np.asarray(codes, dtype=np.int64)
        if not len(self.bases):
            none = np.full(codes.shape, -1, dtype=np.int64)
            return none, none.copy()
        block = np.searchsorted(self.bases, codes, side="right") - 1
        clipped = np.maximum(block, 0)
        local = codes - self.bases[clipped]
        inside = (block >= 0) & (local < self.counts[clipped]) & (codes > 0)
        return np.where(inside, block, -1), np.where(inside, local, -1)

    # -- field data -----------------------------------------------------------
    def write(self, field_data) -> None:
        """Put the table into a vtkFieldData (E's)."""
        names = vtkStringArray()
        names.SetName(FACE_ID_BLOCKS_ARRAY)
        for name in self.names:
            names.InsertNextValue(name)
        ranges = numpy_to_vtk(np.stack([self.bases, self.counts, self.addresses], axis=1).astype(np.int64).reshape(-1, 3), deep=True)
        ranges.SetName(FACE_ID_RANGES_ARRAY)
        field_data.AddArray(names)
        field_data.AddArray(ranges)

    @classmethod
    def read(cls, image) -> FaceIdTable:
        """The table of an expected image rendered with identity (ValueError if it has none)."""
        field = image.GetFieldData()
        names = field.GetAbstractArray(FACE_ID_BLOCKS_ARRAY)
        ranges = field.GetArray(FACE_ID_RANGES_ARRAY)
        if names is None or ranges is None:
            raise ValueError(f"expected image has no field data '{FACE_ID_BLOCKS_ARRAY}' / '{FACE_ID_RANGES_ARRAY}' (rendered without identity?)")
        columns = ranges.GetNumberOfComponents()  # (first code, faces[, address])
        values = vtk_to_numpy(ranges).reshape(-1, columns)
        addresses = values[:, 2].copy() if columns > 2 else None
        return cls([names.GetValue(i) for i in range(names.GetNumberOfValues())], values[:, 0].copy(), values[:, 1].copy(), addresses)
