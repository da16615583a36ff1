"""WorldMap: the map as a spatial store of fixed-size world-space chunks.

The map is a set of **patches** (vtkPolyData of triangles, each under a key:
``frame_<i>`` for the novel surface of frame i, ``frame_<i>@<chunk>`` for its
part in one chunk when it spans several, ``patch_<k>`` for a surface
filter's keyed patch that later replaces it, ``merged_<i>`` for frame
patches merged). A **chunk** is a cube of ``chunk_size`` metres, chunk (i, j, k)
centred on (i, j, k) * chunk_size (:meth:`WorldMap.chunk_indices`): a frame's faces go to the chunk of their
centre, a keyed patch whole to the chunk of its bounding box's centre. Per face, a patch keeps its normal (world), its
removal evidence (log-odds), the number of frames that contradicted it and its evidence pool (one frame's faces in
a cube of ``pool_size``, fixed as they enter, so removal does not depend on the chunking); cell data ``frame``.

Why chunks:

* **E draws what is in view.** :attr:`multiblock` is the map as VTK sees it:
  one block per chunk, each holding its patches as named blocks (the patch
  keys), with the chunk's bounding box (the union of its patches' boxes) in
  the block metadata (``BOUNDING_BOX``). The expected-image renderer skips
  chunks outside the view frustum, so its cost follows the view, not the
  map (:func:`mabdi.render.depth_image.named_leaves`).
* **Bounded draw calls.** Once a chunk holds more than ``patches_per_chunk``
  frame patches, they are merged into one (:meth:`WorldMap.compact`): a concatenation (no shared vertex: removal's
  edge-connected spread sees the same faces as before). Keyed patches are replaced whole, never merged; a frame
  patch of :data:`FULL_PATCH_FACES` faces or more stays apart, so what a removal rebuilds stays bounded.
* **Bounded bookkeeping.** Adding or replacing a patch touches its chunk's
  block only; nothing is proportional to the number of frames.

A face is named by (patch key, cell id in the patch). The expected image
says which face each pixel shows with codes that mean something for that
image alone (:mod:`mabdi.face_identity`); the methods that take face codes
take the image's :class:`~mabdi.face_identity.FaceIdTable` beside them. A
block named in a table whose patch has since been replaced (the table says
which polydata was drawn) counts as not in the map; removal casts the pixels
that showed it against the patch now there. There is no cap on the number of faces.

:class:`mabdi.stages.world_mesh.FilterWorldMesh` is the VTK adaptor that
appends each frame's surface; checkpoints keep :meth:`state`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkCompositeDataSet, vtkDataObject, vtkMultiBlockDataSet, vtkPolyData
from vtkmodules.vtkFiltersCore import vtkAppendPolyData

from mabdi.face_identity import FaceIdTable, block_address, rows_by_block
from mabdi.polydata_kernels import corners_marked, triangle_centres, triangles_touching
from mabdi.polydata import extract_polys, polydata_from_state, split_polys, polydata_to_state, triangle_normals

FRAME_CELL_ARRAY = "frame"
#: Cell data of a surface whose faces are keyed patches (voxel planes): the patch each face belongs to.
PATCH_KEY_ARRAY = "patch_key"
#: Field data of such a surface: the keys of patches it no longer holds (removed from the map on append).
REMOVED_KEYS_ARRAY = "removed_patch_keys"
#: Edge of a chunk for a depth camera (metres): small beside what a depth camera sees at once, so culling draws
#: little beyond the view. Chunks a view wide (8 m) were a few percent faster, but changed real recordings' maps
#: (docs/benchmarks.md, "A camera's map in 8 m chunks").
CHUNK_SIZE = 2.0
#: Edge of a chunk for a spinning LiDAR (metres, :func:`mabdi.loop.loop.chunk_size_for`): it sees tens of metres
#: all around at once (the street's per-stage costs with 2 and 6 m chunks, and BALM's with 6 and 16 m, are in
#: docs/benchmarks.md).
LIDAR_CHUNK_SIZE = 6.0
#: Frame patches a chunk holds before they are merged into one (keyed patches do not count).
PATCHES_PER_CHUNK = 8
#: A frame patch of at least this many faces is full: no longer merged, nor counted against ``patches_per_chunk``,
#: so what a removal or refinement rebuilds (and re-uploads) stays this size however large the chunk.
FULL_PATCH_FACES = 32_768
#: Edge of an evidence pool for a camera (metres): the faces one frame made within one cube of this edge pool
#: their removal evidence (:meth:`WorldMap.update_evidence`), however the map is chunked or merged.
POOL_SIZE = 2.0
#: Edge of an evidence pool for a spinning LiDAR (metres).
LIDAR_POOL_SIZE = 6.0

#: A re-meshed patch's face whose centre lies within this (metres) of an old face's is that face, unchanged.
UNCHANGED_FACE = 1e-5

ChunkIndex = tuple[int, int, int]


@dataclass
class Patch:
    """One patch of the map: its polydata and, per face, normal (world), removal log-odds, contradicting frames
    and whether it shared an edge with a face removed from the patch."""

    key: str
    polydata: vtkPolyData
    chunk: ChunkIndex
    normals: np.ndarray  # (M, 3) float32
    evidence: np.ndarray  # (M,) float32
    contradicted: np.ndarray  # (M,) uint16
    keyed: bool = False
    #: (M,) bool, a keyed patch's faces that were not in the patch it replaced (new, or fitted again to new
    #: points); None: all its faces came with it
    refitted: np.ndarray | None = None
    #: (M,) bool, faces that shared an edge with a face removed from the patch (they follow it once
    #: contradicted: :meth:`WorldMap.update_evidence`); None: none did
    beside_removed: np.ndarray | None = None
    #: (M,) int64, the evidence pool of each face (:meth:`WorldMap.update_evidence`): one frame's faces within one
    #: pool cube, or a keyed patch whole; None until the map sets it
    pools: np.ndarray | None = None
    #: pool -> frames in which any face of it was contradicted (pools never contradicted are not listed)
    pool_frames: dict[int, int] = field(default_factory=dict)

    def beside_removed_faces(self) -> np.ndarray:
        """(M,) bool :attr:`beside_removed`, all False where None."""
        return self.beside_removed if self.beside_removed is not None else np.zeros(self.cells, dtype=bool)

    @property
    def cells(self) -> int:
        return self.polydata.GetNumberOfCells()

    @property
    def mergeable(self) -> bool:
        """A frame patch (not keyed) with fewer than :data:`FULL_PATCH_FACES` faces: :meth:`WorldMap.compact` merges it."""
        return not self.keyed and self.cells < FULL_PATCH_FACES


class Chunk:
    """The patches of one chunk, in the order they came, and their VTK block (one named block per patch)."""

    def __init__(self, index: ChunkIndex) -> None:
        self.index = index
        self.patches: dict[str, Patch] = {}
        self.block = vtkMultiBlockDataSet()
        self.frame_patches = 0  # unkeyed patches not yet full (merged beyond PATCHES_PER_CHUNK)
        self._numbers: dict[str, int] = {}  # patch key -> block number

    def set(self, patch: Patch) -> None:
        """Add ``patch``, or replace the patch of its key in place."""
        previous = self.patches.get(patch.key)
        if previous is not None:
            self.frame_patches -= previous.mergeable
        self.frame_patches += patch.mergeable
        self.patches[patch.key] = patch
        number = self._numbers.get(patch.key)
        if number is None:
            number = self._numbers[patch.key] = self.block.GetNumberOfBlocks()
            self.block.SetBlock(number, patch.polydata)
            self.block.GetMetaData(number).Set(vtkCompositeDataSet.NAME(), patch.key)
        else:
            self.block.SetBlock(number, patch.polydata)
        self.block.Modified()

    def remove(self, keys) -> None:
        """Drop the patches ``keys`` (the block is rebuilt from those left)."""
        for key in keys:
            patch = self.patches.pop(key)
            self.frame_patches -= patch.mergeable
        self.block.SetNumberOfBlocks(0)
        self._numbers = {}
        for number, (key, patch) in enumerate(self.patches.items()):
            self._numbers[key] = number
            self.block.SetBlock(number, patch.polydata)
            self.block.GetMetaData(number).Set(vtkCompositeDataSet.NAME(), key)
        self.block.Modified()

    def bounds(self) -> tuple[float, ...]:
        """(xmin, xmax, ymin, ymax, zmin, zmax) of its patches (metres)."""
        boxes = np.array([p.polydata.GetBounds() for p in self.patches.values()])
        return (boxes[:, 0].min(), boxes[:, 1].max(), boxes[:, 2].min(), boxes[:, 3].max(), boxes[:, 4].min(), boxes[:, 5].max())


def update_log_odds(
    evidence: np.ndarray, frames: np.ndarray, contradicted: np.ndarray, confirmed: np.ndarray, parameters
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame of removal's evidence rule (:mod:`mabdi.stages.removal`, "The rule"; ``parameters``: its
    :class:`~mabdi.stages.removal.RemovalParameters`): (new log-odds, new counts of the frames that contradicted
    each face since a frame last confirmed it, removed mask)."""
    against = contradicted > confirmed
    evidence = evidence + np.where(against, parameters.hit, np.where(confirmed > 0, -parameters.miss, 0.0))
    evidence = np.clip(evidence, parameters.floor, parameters.ceiling).astype(np.float32)
    # frames that saw through the face since a frame last confirmed it (one confirming frame starts it again)
    frames = np.where(against, frames + 1, np.where(confirmed > 0, 0, frames)).astype(np.uint16)
    gone = (evidence >= parameters.threshold) & (frames >= parameters.frames_required)
    return evidence, frames, gone


def patch_triangles(patch: vtkPolyData) -> np.ndarray | None:
    """(M, 3) vertex ids of a patch's triangles, or None when it has other polygons."""
    polys = patch.GetPolys()
    if polys.GetNumberOfCells() == 0 or polys.IsHomogeneous() != 3:  # (IsHomogeneous: every cell's size, or -1)
        return None
    return vtk_to_numpy(polys.GetConnectivityArray()).reshape(-1, 3)


def spread_removal(triangles: np.ndarray, points: int, gone: np.ndarray, followers: np.ndarray, steps: int | None = None) -> np.ndarray:
    """``gone`` grown over the triangles of the mask ``followers`` that share an edge (two vertices) with a
    removed one, ring by ring until nothing more joins (``steps``: at most that many rings)."""
    gone = gone.copy()
    if not followers.any():
        return gone
    rings = 0
    while steps is None or rings < steps:
        new = beside(triangles, points, gone) & followers
        if not new.any():
            break
        gone |= new
        rings += 1
    return gone


def beside(triangles: np.ndarray, points: int, gone: np.ndarray) -> np.ndarray:
    """Triangles not in ``gone`` that share an edge (two vertices) with one in it."""
    return ~gone & (corners_marked(triangles, points, gone) >= 2)


def enclosed(triangles: np.ndarray, points: int, gone: np.ndarray) -> np.ndarray:
    """Triangles not in ``gone`` whose three vertices all belong to removed triangles too (remnants left
    inside a removed region)."""
    return ~gone & (corners_marked(triangles, points, gone) == 3)


def face_normals(patch: vtkPolyData) -> np.ndarray:
    """(M, 3) float32 unit normals of a patch's polygons (from their first three corners; triangles in the map)."""
    if patch.GetNumberOfCells() == 0:
        return np.zeros((0, 3), dtype=np.float32)
    points = vtk_to_numpy(patch.GetPoints().GetData()).astype(np.float32, copy=False)
    polys = patch.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray())[:-1]
    connectivity = vtk_to_numpy(polys.GetConnectivityArray())
    corners = np.stack([connectivity[offsets], connectivity[offsets + 1], connectivity[offsets + 2]], axis=1)
    return triangle_normals(points, corners)[0]


def face_centres(patch: vtkPolyData, cells=None) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3) corner-average centres of a patch's polygons and (M,) their radii (farthest corner), metres;
    ``cells``: only those polygons (ids, in that order)."""
    polys = patch.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray())
    connectivity = vtk_to_numpy(polys.GetConnectivityArray())
    if cells is None:
        starts, sizes = offsets[:-1], np.diff(offsets)
    else:
        cells = np.asarray(cells, dtype=np.int64)
        starts, sizes = offsets[cells], offsets[cells + 1] - offsets[cells]
    if not len(sizes):
        return np.zeros((0, 3)), np.zeros(0)
    if sizes.min() == 3 and sizes.max() == 3:  # triangles (the map's faces): compiled, no ragged gather
        points = vtk_to_numpy(patch.GetPoints().GetData())
        return triangle_centres(points, connectivity, np.ascontiguousarray(starts, dtype=np.int64))
    firsts = np.cumsum(sizes) - sizes  # where each polygon's corners start in the gathered list
    corner_ids = connectivity[np.repeat(starts - firsts, sizes) + np.arange(int(sizes.sum()))]
    corners = vtk_to_numpy(patch.GetPoints().GetData())[corner_ids].astype(np.float64)
    centres = np.add.reduceat(corners, firsts, axis=0) / sizes[:, None]
    reach = np.linalg.norm(corners - np.repeat(centres, sizes, axis=0), axis=1)
    return centres, np.maximum.reduceat(reach, firsts)


def stamped(patch: vtkPolyData, frame: int, drop=()) -> vtkPolyData:
    """A shallow copy of ``patch`` with cell data ``frame`` (kept if the patch has it already), no field data,
    and without the cell arrays named in ``drop``."""
    copy = vtkPolyData()
    copy.ShallowCopy(patch)
    copy.GetFieldData().Initialize()
    if copy.GetCellData().GetArray(FRAME_CELL_ARRAY) is None:
        frames = numpy_to_vtk(np.full(copy.GetNumberOfCells(), frame, dtype=np.int32), deep=True)
        frames.SetName(FRAME_CELL_ARRAY)
        copy.GetCellData().AddArray(frames)
    for name in drop:
        copy.GetCellData().RemoveArray(name)
    return copy


def _append(polydatas: list[vtkPolyData]) -> vtkPolyData:
    merged = vtkPolyData()
    if polydatas:
        append = vtkAppendPolyData()
        for polydata in polydatas:
            append.AddInputData(polydata)
        append.Update()
        merged.ShallowCopy(append.GetOutput())
    return merged


class WorldMap:
    """The map in chunks of ``chunk_size`` metres (see the module docs); removal evidence pooled in cubes of
    ``pool_size`` metres (None: ``chunk_size``)."""

    def __init__(
        self, chunk_size: float = CHUNK_SIZE, patches_per_chunk: int = PATCHES_PER_CHUNK, pool_size: float | None = POOL_SIZE
    ) -> None:
        if not (math.isfinite(chunk_size) and chunk_size > 0):
            raise ValueError(f"WorldMap: chunk_size must be a positive number of metres, got {chunk_size!r}")
        pool_size = chunk_size if pool_size is None else pool_size
        if not (math.isfinite(pool_size) and pool_size > 0):
            raise ValueError(f"WorldMap: pool_size must be a positive number of metres, got {pool_size!r}")
        if isinstance(patches_per_chunk, bool) or not isinstance(patches_per_chunk, int) or patches_per_chunk < 1:
            raise ValueError(f"WorldMap: patches_per_chunk must be a positive integer, got {patches_per_chunk!r}")
        self.chunk_size = float(chunk_size)
        self.pool_size = float(pool_size)
        self.patches_per_chunk = patches_per_chunk
        self.multiblock = vtkMultiBlockDataSet()
        self.reset()

    # -- the map -----------------------------------------------------------
    def reset(self) -> None:
        """Empty the map."""
        self.chunks: dict[ChunkIndex, Chunk] = {}
        self._numbers: dict[ChunkIndex, int] = {}  # chunk -> its block number in multiblock
        self._patches: dict[str, Patch] = {}
        self._cells = 0
        self._merges = 0
        self._pools = 0  # evidence pools handed out
        #: merged patch key -> [(part key, its number of points)], in the order their points were concatenated
        self._merged_from: dict[str, list[tuple[str, int]]] = {}
        self._merged: vtkPolyData | None = None
        self._rebuild_top()

    @property
    def number_of_cells(self) -> int:
        return self._cells

    @property
    def number_of_points(self) -> int:
        return sum(p.polydata.GetNumberOfPoints() for p in self._patches.values())

    @property
    def patch_keys(self) -> list[str]:
        return list(self._patches)

    def patch(self, key: str) -> Patch:
        return self._patches[key]

    def block(self, key: str) -> vtkPolyData:
        """The polydata of patch ``key`` (read it; change its points only through :meth:`move_points`)."""
        return self._patches[key].polydata

    def memory_bytes(self) -> int:
        """Memory held by the map: its patches (VTK's actual memory size) and their per-face arrays."""
        total = 0
        for p in self._patches.values():
            total += 1024 * p.polydata.GetActualMemorySize() + p.normals.nbytes + p.evidence.nbytes + p.contradicted.nbytes + p.pools.nbytes
        return total

    def chunk_of(self, polydata: vtkPolyData) -> ChunkIndex:
        """The chunk holding the centre of ``polydata``'s bounding box."""
        b = polydata.GetBounds()
        centre = np.array([b[0] + b[1], b[2] + b[3], b[4] + b[5]]) / 2.0
        return tuple(int(i) for i in self.chunk_indices(centre))

    def chunk_indices(self, points) -> np.ndarray:
        """(..., 3) int64 chunk index of world points: chunk (i, j, k) is the cube of ``chunk_size`` centred on
        (i, j, k) * chunk_size (the world origin is the centre of chunk (0, 0, 0))."""
        return np.floor(np.asarray(points, dtype=np.float64) / self.chunk_size + 0.5).astype(np.int64)

    def chunk_bounds(self) -> dict[ChunkIndex, tuple[float, ...]]:
        """The bounding box of each chunk's patches (what the renderer culls with)."""
        return {index: chunk.bounds() for index, chunk in self.chunks.items()}

    def add_patch(self, key: str, polydata: vtkPolyData, frame: int, keyed: bool = False) -> int:
        """Add ``polydata`` under ``key``; returns the net change in cells.

        A keyed patch (a surface filter's block) goes whole into the chunk of its centre and replaces the patch
        of its key, its faces keeping the removal evidence of the faces they replace. A frame's patch is split
        by chunk (each face into the chunk of its centre: ``<key>@i_j_k`` where it spans several), so that a
        chunk's bounding box stays about its own size and E draws only what is near the view.
        """
        polydata = stamped(polydata, frame)
        if keyed:
            return self._add(key, polydata, self.chunk_of(polydata), keyed=True)
        parts = self._split_by_chunk(polydata)
        if len(parts) == 1:
            return self._add(key, polydata, parts[0][0], keyed=False)
        return sum(self._add("{}@{}_{}_{}".format(key, *chunk), part, chunk, keyed=False) for chunk, part in parts)

    def _next_pool(self) -> int:
        self._pools += 1
        return self._pools - 1

    def _new_pools(self, polydata: vtkPolyData) -> np.ndarray:
        """(M,) int64 new evidence pools for one frame's faces in one chunk: one per pool cube their centres
        reach (one for them all where pools are as large as chunks)."""
        cells = polydata.GetNumberOfCells()
        if self.pool_size == self.chunk_size or cells == 0:
            inverse = np.zeros(cells, dtype=np.int64)
        else:
            cubes = np.floor(face_centres(polydata)[0] / self.pool_size + 0.5).astype(np.int64)
            cubes -= cubes.min(axis=0)
            span = cubes.max(axis=0) + 1
            flat = (cubes[:, 0] * span[1] + cubes[:, 1]) * span[2] + cubes[:, 2]
            inverse = np.unique(flat, return_inverse=True)[1].reshape(-1).astype(np.int64)
        pools = self._pools + inverse
        self._pools += int(inverse.max()) + 1 if cells else 0
        return pools

    def _split_by_chunk(self, polydata: vtkPolyData) -> list[tuple[ChunkIndex, vtkPolyData]]:
        """(chunk, the faces of ``polydata`` whose centre lies in it) for each chunk it reaches (one: itself)."""
        b = polydata.GetBounds()
        low, high = self.chunk_indices([b[0], b[2], b[4]]), self.chunk_indices([b[1], b[3], b[5]])
        if polydata.GetNumberOfCells() == 0 or (low == high).all():  # within one chunk: no face to look at
            return [(tuple(int(i) for i in low), polydata)]
        cells = self.chunk_indices(face_centres(polydata)[0]) - low  # 0 .. span per axis
        span = high - low + 1
        flat = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
        if (flat == flat[0]).all():
            return [(tuple(int(i) for i in low + cells[0]), polydata)]
        return [(tuple(int(i) for i in low + np.unravel_index(n, tuple(span))), part) for n, part in split_polys(polydata, flat)]

    def _add(self, key: str, polydata: vtkPolyData, chunk: ChunkIndex, keyed: bool) -> int:
        old = self._patches.get(key)
        patch = Patch(
            key, polydata, chunk, face_normals(polydata),
            np.zeros(polydata.GetNumberOfCells(), np.float32), np.zeros(polydata.GetNumberOfCells(), np.uint16), keyed,
        )
        if old is not None:
            self._inherit_evidence(patch, old)
        elif keyed:  # a keyed patch is one pool, kept as it is replaced (_inherit_evidence)
            patch.pools = np.full(patch.cells, self._next_pool(), dtype=np.int64)
        else:
            patch.pools = self._new_pools(polydata)
        before = self._cells
        self._put(patch, replacing=old)
        self._changed()
        return self._cells - before

    def remove_patch(self, key: str) -> int:
        """Remove the patch ``key`` if present; returns the net change in cells (<= 0)."""
        old = self._patches.get(key)
        if old is None:
            return 0
        self._take(old)
        self._changed()
        return -old.cells

    def _put(self, patch: Patch, replacing: Patch | None = None) -> None:
        if replacing is not None and replacing.chunk != patch.chunk:
            self._take(replacing)
            replacing = None
        chunk = self.chunks.get(patch.chunk)
        if chunk is None:
            chunk = self.chunks[patch.chunk] = Chunk(patch.chunk)
            self._place_chunk(chunk)
        if replacing is not None:
            self._cells -= replacing.cells
        chunk.set(patch)
        self._patches[patch.key] = patch
        self._cells += patch.cells
        self._set_bounds(chunk)

    def _take(self, patch: Patch) -> None:
        chunk = self.chunks[patch.chunk]
        chunk.remove([patch.key])
        del self._patches[patch.key]
        self._cells -= patch.cells
        if not chunk.patches:
            del self.chunks[patch.chunk]
            self._rebuild_top()
        else:
            self._set_bounds(chunk)

    def compact(self) -> None:
        """Merge the frame patches of each chunk that holds more than ``patches_per_chunk`` into one.

        Not done while a patch is added: merged patches get new names, so face codes of an expected image
        rendered before would name patches no longer there. The loop compacts at the end of each frame, once
        its E's codes have been used (removal votes come after the append).
        """
        self._merged_from = {key: parts for key, parts in self._merged_from.items() if key in self._patches}
        for chunk in self.chunks.values():
            if chunk.frame_patches > self.patches_per_chunk:
                self._merge_frame_patches(chunk)

    def merged_parts(self, key: str) -> list[tuple[str, int]]:
        """The patches merged into patch ``key`` at the last :meth:`compact` that made it, as (key, number of
        points) in the order of its points; empty for a patch that was not made by merging (or merged earlier).
        What was kept per vertex of the parts (refinement's state) can follow them so."""
        return list(self._merged_from.get(key, ()))

    def _merge_frame_patches(self, chunk: Chunk) -> None:
        """Merge a chunk's frame patches into one, size-tiered: the largest stays apart while it holds more
        faces than all the others together, so a known place that keeps receiving small patches does not copy
        (and re-upload) its whole chunk every few frames; each face is copied O(log n) times over a run."""
        parts = [p for p in chunk.patches.values() if p.mergeable]
        largest = max(parts, key=lambda p: p.cells)
        if 2 * largest.cells > sum(p.cells for p in parts):
            parts = [p for p in parts if p is not largest]
        if len(parts) < 2:
            return
        merged = Patch(
            f"merged_{self._merges}",
            _append([p.polydata for p in parts]),
            chunk.index,
            np.concatenate([p.normals for p in parts]),
            np.concatenate([p.evidence for p in parts]),
            np.concatenate([p.contradicted for p in parts]),
            pools=np.concatenate([p.pools for p in parts]),
            pool_frames={pool: frames for p in parts for pool, frames in p.pool_frames.items()},
        )
        if any(p.beside_removed is not None for p in parts):
            merged.beside_removed = np.concatenate([p.beside_removed_faces() for p in parts])
        self._merges += 1
        self._merged_from[merged.key] = [(p.key, p.polydata.GetNumberOfPoints()) for p in parts]
        chunk.remove([part.key for part in parts])
        for part in parts:
            del self._patches[part.key]
        chunk.set(merged)
        self._patches[merged.key] = merged

    def _place_chunk(self, chunk: Chunk) -> None:
        number = self.multiblock.GetNumberOfBlocks()
        self._numbers[chunk.index] = number
        self.multiblock.SetBlock(number, chunk.block)
        self.multiblock.GetMetaData(number).Set(vtkCompositeDataSet.NAME(), "chunk_{}_{}_{}".format(*chunk.index))

    def _rebuild_top(self) -> None:
        self.multiblock.SetNumberOfBlocks(0)
        self._numbers = {}
        for chunk in self.chunks.values():
            self._place_chunk(chunk)
            self._set_bounds(chunk)
        self.multiblock.Modified()

    def _set_bounds(self, chunk: Chunk) -> None:
        self.multiblock.GetMetaData(self._numbers[chunk.index]).Set(vtkDataObject.BOUNDING_BOX(), chunk.bounds(), 6)

    def _changed(self) -> None:
        self.multiblock.Modified()
        self._merged = None

    def mesh(self) -> vtkPolyData:
        """The whole map as one vtkPolyData (cell data ``frame``), chunk by chunk; cached until the map changes."""
        if self._merged is None:
            self._merged = _append([p.polydata for chunk in self.chunks.values() for p in chunk.patches.values()])
        return self._merged

    # -- faces: evidence, normals, removal ------------------------------------
    def _inherit_evidence(self, patch: Patch, old: Patch) -> None:
        """A re-meshed patch's faces keep the removal evidence of the face they replace.

        Voxel planes re-mesh a block whenever a point lands in it: with fresh evidence, the ghost of a
        departed object whose block keeps receiving points (the floor seen where it stood) would never
        gather the frames removal asks for. A new face takes the evidence of the old face whose centre is
        nearest to its own, if that centre lies within the new face (its radius); otherwise it starts at 0.
        """
        centres, _ = face_centres(old.polydata)
        patch.refitted = np.ones(patch.cells, dtype=bool)
        pool = int(old.pools[0]) if len(old.pools) else self._next_pool()
        patch.pools = np.full(patch.cells, pool, dtype=np.int64)  # a replaced patch stays one pool
        patch.pool_frames = {pool: old.pool_frames[pool]} if pool in old.pool_frames else {}
        if not len(centres) or not patch.cells:
            return
        new_centres, radii = face_centres(patch.polydata)
        distance, nearest = cKDTree(centres).query(new_centres, distance_upper_bound=float(radii.max()))
        same = np.isfinite(distance) & (distance <= radii)
        patch.evidence[same] = old.evidence[nearest[same]]
        patch.contradicted[same] = old.contradicted[nearest[same]]
        if old.beside_removed is not None:
            patch.beside_removed = np.zeros(patch.cells, dtype=bool)
            patch.beside_removed[same] = old.beside_removed[nearest[same]]
        patch.refitted = ~(np.isfinite(distance) & (distance <= UNCHANGED_FACE))

    def face_lookup(self, codes, table: FaceIdTable) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Where the faces of an expected image's ``codes`` live: (index into the returned patch keys, cell id in
        the patch, keys); index -1 for codes of no face in the map.

        A block of the table is the patch of its name when that is the polydata E drew (and holds as many
        faces); else (re-meshed, or faces removed since E was drawn) its codes find nothing here: the removal
        stage casts the pixels that showed a re-meshed block against its new faces (:meth:`stale_blocks`).
        """
        groups, local = self._current_groups(codes, table)
        block = np.full(local.shape, -1, dtype=np.int64)
        for b, rows in groups:
            block.reshape(-1)[rows] = b
        return block, np.where(block >= 0, local, -1), list(table.names)

    def _current_groups(self, codes, table: FaceIdTable) -> tuple[list[tuple[int, np.ndarray]], np.ndarray]:
        """(``(b, rows)`` for each block ``b`` of ``table`` that ``codes`` name and that is current, with the flat
        rows of ``codes`` in it (:func:`~mabdi.face_identity.rows_by_block`); each code's cell id in its block)."""
        block, local = table.lookup(codes)
        return [(b, rows) for b, rows in rows_by_block(block) if self._drawn_is_current(table, b)], local

    def _drawn_is_current(self, table: FaceIdTable, b: int) -> bool:
        """Whether block ``b`` of ``table`` is the patch of its name as it is now (the same polydata, as many faces)."""
        patch = self._patches.get(table.names[b])
        if patch is None or patch.cells != int(table.counts[b]):
            return False
        address = int(table.addresses[b])
        return address == 0 or address == block_address(patch.polydata)

    def current_blocks(self, table: FaceIdTable) -> list[int]:
        """Indices of the blocks of ``table`` that are the patch of their name as it is now (their codes find
        their faces: :meth:`face_lookup`)."""
        return [b for b in range(len(table.names)) if self._drawn_is_current(table, b)]

    def stale_blocks(self, table: FaceIdTable) -> list[int]:
        """Indices of the blocks of ``table`` whose name is a patch of the map that is not the one drawn (a keyed
        patch re-meshed since): their codes find nothing, and the pixels that showed them can be cast against
        the patch now there (:mod:`mabdi.stages.object_removal`)."""
        return [b for b, name in enumerate(table.names) if name in self._patches and not self._drawn_is_current(table, b)]

    def refitted_faces(self, key: str) -> np.ndarray:
        """(M,) bool: the faces of patch ``key`` made or fitted again when it last replaced a patch (all False for a
        patch that replaced none)."""
        patch = self._patches[key]
        return patch.refitted if patch.refitted is not None else np.zeros(patch.cells, dtype=bool)

    def _per_face(self, codes, table: FaceIdTable, attribute: str, fill) -> np.ndarray:
        codes = np.asarray(codes, dtype=np.int64)
        groups, local = self._current_groups(codes, table)
        sample = getattr(next(iter(self._patches.values())), attribute) if self._patches else np.zeros(0, np.float32)
        out = np.full((len(codes), *sample.shape[1:]), fill, dtype=sample.dtype)
        for b, rows in groups:
            out[rows] = getattr(self._patches[table.names[b]], attribute)[local[rows]]
        return out

    def face_corners_of(self, codes, table: FaceIdTable) -> np.ndarray:
        """(N, 3, 3) float64 world corners of the triangles ``codes``; NaN for codes of no face in the map, or of a
        face of a patch with other polygons than triangles."""
        codes = np.asarray(codes, dtype=np.int64).reshape(-1)
        out = np.full((len(codes), 3, 3), np.nan)
        groups, local = self._current_groups(codes, table)
        for b, rows in groups:
            patch = self._patches[table.names[b]]
            triangles = patch_triangles(patch.polydata)
            if triangles is None:
                continue
            points = vtk_to_numpy(patch.polydata.GetPoints().GetData())
            out[rows] = points[triangles[local[rows]]]
        return out

    def face_normals_of(self, codes, table: FaceIdTable) -> np.ndarray:
        """(N, 3) world normals of the faces ``codes``; NaN for codes of no face in the map."""
        return self._per_face(codes, table, "normals", np.nan).reshape(-1, 3) if self._patches else np.full((len(codes), 3), np.nan, np.float32)

    def face_evidence_of(self, codes, table: FaceIdTable) -> np.ndarray:
        """The removal log-odds of faces ``codes`` (0 for codes of no face in the map)."""
        return self._per_face(codes, table, "evidence", 0.0) if self._patches else np.zeros(len(codes), np.float32)

    def update_evidence(self, codes, contradicted: np.ndarray, confirmed: np.ndarray, parameters, table: FaceIdTable) -> np.ndarray:
        """Add one frame's votes and return the codes of the faces whose removal the evidence now calls for.

        ``codes``: faces voted on this frame (of the expected image whose ``table`` is given);
        ``contradicted`` / ``confirmed``: their pixel votes. The rule is
        :func:`update_log_odds` (``parameters``: :class:`~mabdi.stages.removal.RemovalParameters`);
        besides, a face that shared an edge with a face removed before (:attr:`Patch.beside_removed`) goes
        as soon as its evidence is above 0. That is the rule by which contradicted faces follow a removed
        neighbour (:meth:`_removed_with`), kept when the neighbour went first: a departed object's small
        faces seen by one beam in one frame after the faces around them went would otherwise stay.

        A pool (:attr:`Patch.pools`: the faces one frame made within one cube of ``pool_size``, or a keyed patch)
        pools its faces' evidence when nothing in it stands: once ``frames_required`` frames have contradicted
        some face of it (:attr:`Patch.pool_frames`) and every face of it that was ever voted on has evidence
        above 0 (contradicted and not confirmed since), its contradicted faces go, those this frame did not
        show too. A roof seen from across a street by one beam in each of several scans has each small face
        contradicted once, by different scans, and would otherwise stay. A static pool has faces that pixels
        confirm, and then the rule does not apply. Pools are fixed when a frame's faces enter the map, so the
        rule does not depend on how the map is chunked or its patches merged.
        """
        codes = np.asarray(codes, dtype=np.int64)
        groups, local = self._current_groups(codes, table)
        condemned = []
        for b, rows in groups:
            patch = self._patches[table.names[b]]
            cells = local[rows]
            evidence, frames, gone = update_log_odds(
                patch.evidence[cells], patch.contradicted[cells], contradicted[rows], confirmed[rows], parameters
            )
            patch.evidence[cells] = evidence
            patch.contradicted[cells] = frames
            gone |= patch.beside_removed_faces()[cells] & (evidence > 0)
            condemned.append(codes[rows[gone]])
            against = contradicted[rows] > confirmed[rows]
            if against.any():  # a frame that contradicts nothing in a pool cannot make its case
                condemned.append(table.bases[b] + self._pooled_removal(patch, np.unique(patch.pools[cells[against]]), parameters))
        return np.unique(np.concatenate(condemned)) if condemned else np.zeros(0, dtype=np.int64)

    @staticmethod
    def _pooled_removal(patch: Patch, against: np.ndarray, parameters) -> np.ndarray:
        """Count one more contradicting frame for each pool of ``against`` in ``patch``; the cell ids of the
        contradicted faces of those pools that have now been contradicted in ``parameters.frames_required``
        frames and have no voted face standing (:meth:`update_evidence`)."""
        ready = []
        for pool in against.tolist():
            frames = patch.pool_frames[pool] = patch.pool_frames.get(pool, 0) + 1
            if frames >= parameters.frames_required:
                ready.append(pool)
        if not ready:
            return np.zeros(0, dtype=np.int64)
        faces = np.flatnonzero(np.isin(patch.pools, ready))
        pool_of = np.searchsorted(np.sort(ready), patch.pools[faces])
        evidence = patch.evidence[faces]
        standing = ((evidence != 0) | (patch.contradicted[faces] > 0)) & (evidence <= 0)  # voted, and not against
        fallen = np.bincount(pool_of, weights=standing, minlength=len(ready)) == 0
        return faces[fallen[pool_of] & (evidence > 0)]

    def remove_faces(self, codes, table: FaceIdTable, follow_frames: int = 1) -> vtkPolyData:
        """Remove the faces ``codes`` from their patches (each changed patch is rebuilt, so only it is re-uploaded).

        Faces go with their edge-connected neighbours as :meth:`_removed_with` says (``follow_frames``: removal's
        :attr:`~mabdi.stages.removal.RemovalParameters.follow_frames`). Returns the removed faces as one
        vtkPolyData (for the dashboard).
        """
        groups, local = self._current_groups(np.asarray(codes, dtype=np.int64), table)
        removed_parts = []
        for b, rows in groups:
            patch = self._patches[table.names[b]]
            triangles = patch_triangles(patch.polydata)
            gone = np.zeros(patch.cells, dtype=bool)
            gone[local[rows]] = True
            if triangles is not None:  # polygons other than triangles: no edges to follow
                gone = self._removed_with(patch, triangles, gone, follow_frames)
            removed_parts.append(extract_polys(patch.polydata, np.flatnonzero(gone)))
            keep = np.flatnonzero(~gone)
            if keep.size == 0:
                self._take(patch)
                continue
            near = patch.beside_removed_faces()
            if triangles is not None:
                near = near | beside(triangles, patch.polydata.GetNumberOfPoints(), gone)
            kept = Patch(
                patch.key, extract_polys(patch.polydata, keep), patch.chunk,
                patch.normals[keep], patch.evidence[keep], patch.contradicted[keep], patch.keyed,
                beside_removed=near[keep] if near[keep].any() else None,
                pools=patch.pools[keep], pool_frames=patch.pool_frames,
            )
            self._put(kept, replacing=patch)
        self._changed()
        return _append(removed_parts)

    @staticmethod
    def _removed_with(patch: Patch, triangles: np.ndarray, gone: np.ndarray, follow_frames: int = 1) -> np.ndarray:
        """The faces that go with the condemned ``gone`` of a patch of ``triangles`` (its (M, 3) vertex ids).

        A departed object's faces are contiguous: faces already contradicted (evidence above 0, and at least
        ``follow_frames`` frames against them since a frame last confirmed them) go with a
        removed face they are edge-connected to, and so do the direct neighbours of the removed faces that
        were never voted on at all (smaller than a pixel: no pixel centre showed them), and kept faces left
        as islands inside the removed region. Contradicted faces beside those that joined (a never-voted
        neighbour, an island) follow them too, and so on while contradicted faces join: a chain of
        never-voted faces alone does not spread the removal beyond one ring.
        """
        points = patch.polydata.GetNumberOfPoints()
        contradicted = (patch.evidence > 0) & (patch.contradicted >= follow_frames)
        never_voted = (patch.evidence == 0) & (patch.contradicted == 0)
        gone = spread_removal(triangles, points, gone, contradicted)
        while True:
            ring = spread_removal(triangles, points, gone, never_voted, steps=1)
            ring |= enclosed(triangles, points, ring)
            grown = spread_removal(triangles, points, ring, contradicted)
            if (grown == ring).all():
                return ring
            gone = grown

    def move_points(self, key: str, vertex_ids: np.ndarray, positions: np.ndarray) -> None:
        """Move vertices ``vertex_ids`` of patch ``key`` to ``positions`` (K, 3) world metres; faces unchanged.

        The patch's points are changed in place and marked modified, so the expected-image renderer
        re-uploads that patch only; the normals of the faces around the moved vertices are recomputed.
        """
        self.move_points_of([(key, vertex_ids, positions)])

    def move_points_of(self, moves) -> None:
        """:meth:`move_points` for each ``(key, vertex_ids, positions)`` of ``moves`` in turn (a frame's
        refinement), with each touched chunk's bounds set once, after its last move."""
        touched = {}
        try:
            for key, vertex_ids, positions in moves:
                chunk = self._move(key, vertex_ids, positions)
                touched[chunk.index] = chunk
        finally:  # a move refused (ValueError) leaves the moves before it applied, with their bounds
            for chunk in touched.values():
                self._set_bounds(chunk)
            if touched:
                self._changed()

    def _move(self, key: str, vertex_ids: np.ndarray, positions: np.ndarray) -> Chunk:
        """Move one patch's vertices and recompute the normals of the faces around them; returns its chunk
        (whose bounds the caller sets)."""
        patch = self._patches[key]
        current = vtk_to_numpy(patch.polydata.GetPoints().GetData())
        vertex_ids = np.asarray(vertex_ids, dtype=np.int64)
        positions = np.asarray(positions)
        if positions.shape != (len(vertex_ids), 3):
            raise ValueError(f"move_points: {len(vertex_ids)} vertex ids of block {key} need ({len(vertex_ids)}, 3) positions, got {positions.shape}")
        if len(vertex_ids) and (vertex_ids.min() < 0 or vertex_ids.max() >= len(current)):
            raise ValueError(f"move_points: block {key} has {len(current)} points, got vertex ids outside 0..{len(current) - 1}")
        current[vertex_ids] = positions.astype(current.dtype)
        patch.polydata.GetPoints().Modified()
        patch.polydata.Modified()
        triangles = patch_triangles(patch.polydata)
        if triangles is None:  # not all triangles: the patch's normals anew
            patch.normals = face_normals(patch.polydata)
        else:
            faces = triangles_touching(triangles, len(current), vertex_ids)
            patch.normals[faces] = triangle_normals(current.astype(np.float32, copy=False), triangles[faces])[0]
        return self.chunks[patch.chunk]

    # -- checkpoints --------------------------------------------------------
    def state(self) -> dict:
        """The map as plain data (patches chunk by chunk, in order, with their chunk and per-face evidence), for
        checkpoints: :meth:`set_state` rebuilds the same chunks in the same order, so a resumed run's map is
        byte-identical."""
        return {
            "chunk_size": self.chunk_size,
            "pool_size": self.pool_size,
            "merges": self._merges,
            "pools": self._pools,
            "merged_from": {key: [[part, int(points)] for part, points in parts] for key, parts in self._merged_from.items()},
            "patches": [
                [key, polydata_to_state(p.polydata), list(p.chunk), p.evidence.copy(), p.contradicted.copy(), p.keyed,
                 p.beside_removed_faces().copy(), None, p.pools.copy(),
                 np.array(sorted(p.pool_frames.items()), dtype=np.int64).reshape(-1, 2)]
                for chunk in self.chunks.values()
                for key, p in chunk.patches.items()
            ],
        }

    def set_state(self, state: dict) -> None:
        """Restore a map saved by :meth:`state` (replaces the current map); also reads the checkpoints of the
        map kept as one block per patch (face evidence by 24-bit identity ranges)."""
        if "ranges" in state:
            state = _chunked_state(state, self.chunk_size)
        self.reset()
        self.chunk_size = float(state["chunk_size"])
        self.pool_size = float(state.get("pool_size", self.chunk_size))
        self._merges = int(state["merges"])
        self._merged_from = {key: [(str(part), int(points)) for part, points in parts] for key, parts in state.get("merged_from", {}).items()}
        for key, polydata, chunk, evidence, contradicted, keyed, *later in state["patches"]:
            polydata = polydata_from_state(polydata)
            patch = Patch(key, polydata, tuple(int(i) for i in chunk), face_normals(polydata), evidence.copy(), contradicted.copy(), bool(keyed))
            if later and np.asarray(later[0]).any():  # checkpoints before the flag have none
                patch.beside_removed = np.asarray(later[0], dtype=bool).copy()
            if len(later) > 2:  # the faces' pools and the pools' frame counts
                patch.pools = np.asarray(later[2], dtype=np.int64).copy()
                patch.pool_frames = {int(pool): int(frames) for pool, frames in np.asarray(later[3]).reshape(-1, 2)}
            else:  # checkpoints before pools: the patch is one pool (with its frame count where kept)
                patch.pools = np.full(patch.cells, self._next_pool(), dtype=np.int64)
                if len(later) > 1 and int(later[1]):
                    patch.pool_frames = {int(patch.pools[0]) if patch.cells else -1: int(later[1])}
            self._put(patch)
        self._pools = max(self._pools, int(state.get("pools", 0)))
        self._changed()


def _chunked_state(state: dict, chunk_size: float) -> dict:
    """A checkpoint of the map kept as patches with evidence by identity range, as :meth:`WorldMap.state`."""
    patches = []
    for key, polydata in state["patches"]:
        base, count = state["ranges"][key]
        chunk = WorldMap(chunk_size).chunk_of(polydata_from_state(polydata))
        patches.append([
            key, polydata, list(chunk), state["evidence"][base : base + count].copy(),
            state["contradicted"][base : base + count].copy(), key.startswith("patch_"),
        ])
    return {"chunk_size": chunk_size, "merges": 0, "patches": patches}
