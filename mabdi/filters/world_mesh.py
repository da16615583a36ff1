"""FilterWorldMesh: the map, grown patch by patch.

Surface (vtkPolyData) in, the map out as a ``vtkMultiBlockDataSet`` with one
block per patch. Each update appends the input surface as a new patch keyed
``frame_<i>`` (i from the input's field data ``frame``), so the cost of a
frame grows with its new surface, not with the map. Every cell gets cell data
``frame``: the frame that created it.

Why blocks: the expected image E is rendered from the map every frame, and a
VTK mapper re-uploads its whole polydata whenever that changes. Kept as
blocks, the map's existing geometry is never touched again, and
:class:`mabdi.filters.depth_image.DepthRenderer` draws each block with its own
mapper, so a frame uploads only its new block. Users and exports get one
merged mesh from :meth:`FilterWorldMesh.mesh`.

Keyed patches: a surface filter that re-meshes parts of the map (voxel
planes) marks its cells with an int64 cell array ``patch_key``; the cells of
each key replace the patch of that key (``patch_<key>``) instead of stacking
a new layer, and the int64 field-data array ``removed_patch_keys`` deletes
patches. :meth:`add_patch` / :meth:`remove_patch` do the same from Python.
A re-meshed patch's faces keep the removal evidence of the faces they
replace (matched by centre), so re-meshing does not reset object removal.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkCompositeDataSet, vtkMultiBlockDataSet, vtkPolyData
from vtkmodules.vtkFiltersCore import vtkAppendPolyData

from mabdi.algorithm import MabdiAlgorithm
from mabdi.depth import FRAME_ARRAY
from mabdi.filters.removal import update_log_odds
from mabdi.polydata import FACE_RGB_ARRAY, extract_polys, polydata_from_state, polydata_to_state, triangle_normals

FRAME_CELL_ARRAY = "frame"
PATCH_KEY_ARRAY = "patch_key"
REMOVED_KEYS_ARRAY = "removed_patch_keys"
#: Identities are 1 .. 2^24 - 1 (0 = no face): a map holds at most that many faces at once.
MAX_FACE_ID = 2**24 - 1


class FaceIds:
    """The 24-bit identities of the map's faces: one range of consecutive ids per block, first fit, reused."""

    def __init__(self) -> None:
        self._ranges: dict[str, tuple[int, int]] = {}  # block key -> (base, size)
        self._index: tuple[np.ndarray, np.ndarray, list[str]] | None = None

    def allocate(self, key: str, size: int) -> int:
        """A base id for ``size`` faces of block ``key`` (its previous range is released)."""
        self._ranges.pop(key, None)
        self._index = None
        start = 1
        for base, length in sorted(self._ranges.values()):
            if base - start >= size:
                break
            start = max(start, base + length)
        if start + size - 1 > MAX_FACE_ID:
            raise MemoryError(f"the map holds more than {MAX_FACE_ID:,} faces: face identities are 24-bit")
        self._ranges[key] = (start, size)
        return start

    def release(self, key: str) -> None:
        if self._ranges.pop(key, None) is not None:
            self._index = None

    def clear(self) -> None:
        self._ranges.clear()
        self._index = None

    def lookup(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """(block number into the returned keys, local cell id) of each id; block -1 where no block has it."""
        if self._index is None:
            keys = sorted(self._ranges, key=lambda k: self._ranges[k][0])
            bases = np.array([self._ranges[k][0] for k in keys], dtype=np.int64)
            sizes = np.array([self._ranges[k][1] for k in keys], dtype=np.int64)
            self._index = (bases, sizes, keys)
        bases, sizes, keys = self._index
        ids = np.asarray(ids, dtype=np.int64)
        if not len(bases):
            none = np.full(ids.shape, -1, dtype=np.int64)
            return none, none.copy(), keys
        block = np.searchsorted(bases, ids, side="right") - 1
        inside = block >= 0
        local = np.where(inside, ids - bases[np.maximum(block, 0)], -1)
        inside &= local < sizes[np.maximum(block, 0)]
        return np.where(inside, block, -1), np.where(inside, local, -1), keys


def face_rgb(base: int, count: int) -> np.ndarray:
    """(count, 3) uint8 RGB of the ids base .. base + count - 1 (red = low byte)."""
    ids = np.arange(base, base + count, dtype=np.int64)
    return np.stack([ids & 255, (ids >> 8) & 255, (ids >> 16) & 255], axis=1).astype(np.uint8)


def patch_triangles(patch: vtkPolyData) -> np.ndarray | None:
    """(M, 3) vertex ids of a patch's triangles, or None when it has other polygons."""
    polys = patch.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray())
    if len(offsets) < 2 or np.any(np.diff(offsets) != 3):
        return None
    return vtk_to_numpy(polys.GetConnectivityArray()).reshape(-1, 3)


def spread_removal(triangles: np.ndarray, points: int, gone: np.ndarray, followers: np.ndarray, steps: int | None = None) -> np.ndarray:
    """``gone`` grown over the triangles of the mask ``followers`` that share an edge (two vertices) with a
    removed one, ring by ring until nothing more joins (``steps``: at most that many rings)."""
    gone = gone.copy()
    if not followers.any():
        return gone
    marked = np.zeros(points, dtype=bool)
    rings = 0
    while steps is None or rings < steps:
        marked[triangles[gone].ravel()] = True
        new = (marked[triangles].sum(axis=1) >= 2) & followers & ~gone
        if not new.any():
            break
        gone |= new
        rings += 1
    return gone


def enclosed(triangles: np.ndarray, points: int, gone: np.ndarray) -> np.ndarray:
    """Triangles not in ``gone`` whose three vertices all belong to removed triangles too (remnants left
    inside a removed region)."""
    touches = np.zeros(points, dtype=bool)
    touches[triangles[gone].ravel()] = True
    return ~gone & touches[triangles].all(axis=1)


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


def face_centres(patch: vtkPolyData) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3) corner-average centres of a patch's polygons and (M,) their radii (farthest corner), metres."""
    if patch.GetNumberOfCells() == 0:
        return np.zeros((0, 3)), np.zeros(0)
    points = vtk_to_numpy(patch.GetPoints().GetData()).astype(np.float64)
    polys = patch.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray())
    corners = points[vtk_to_numpy(polys.GetConnectivityArray())]
    sizes = np.diff(offsets)
    centres = np.add.reduceat(corners, offsets[:-1], axis=0) / sizes[:, None]
    reach = np.linalg.norm(corners - np.repeat(centres, sizes, axis=0), axis=1)
    return centres, np.maximum.reduceat(reach, offsets[:-1])


def _input_frame(surface: vtkPolyData) -> int | None:
    array = surface.GetFieldData().GetArray(FRAME_ARRAY)
    if array is None or array.GetNumberOfTuples() == 0:
        return None
    return int(array.GetTuple1(0))


class FilterWorldMesh(MabdiAlgorithm):
    """The map: appends each frame's surface as a patch (vtkPolyData -> vtkMultiBlockDataSet)."""

    def __init__(self) -> None:
        super().__init__(nInputPorts=1, inputType="vtkPolyData", nOutputPorts=1, outputType="vtkMultiBlockDataSet")
        self._map = vtkMultiBlockDataSet()
        self._patches: dict[str, vtkPolyData] = {}
        self._cells = 0
        self._merged: vtkPolyData | None = None
        self._last_input: tuple[str, int] | None = None
        self._next_frame = 0
        #: Net change in the number of cells made by the last update (replacements count net).
        self.cells_added = 0
        self._ids = FaceIds()
        #: By face identity: normal (world), removal evidence (log-odds), frames that contradicted it.
        self._face_normals = np.zeros((0, 3), dtype=np.float32)
        self._face_evidence = np.zeros(0, dtype=np.float32)
        self._face_contradicted = np.zeros(0, dtype=np.uint16)

    # -- the map -----------------------------------------------------------
    @property
    def map(self) -> vtkMultiBlockDataSet:
        """The live map (one block per patch). Feed it to the expected-image renderer."""
        return self._map

    @property
    def number_of_cells(self) -> int:
        return self._cells

    @property
    def number_of_points(self) -> int:
        return sum(p.GetNumberOfPoints() for p in self._patches.values())

    @property
    def patch_keys(self) -> list[str]:
        return list(self._patches)

    def memory_bytes(self) -> int:
        """Memory held by the map's patches (VTK's actual memory size)."""
        return 1024 * sum(p.GetActualMemorySize() for p in self._patches.values())

    def _rebuild_blocks(self) -> None:
        self._map.SetNumberOfBlocks(0)
        for index, (key, patch) in enumerate(self._patches.items()):
            self._map.SetBlock(index, patch)
            self._map.GetMetaData(index).Set(vtkCompositeDataSet.NAME(), key)
        self._map.Modified()

    def add_patch(self, key: str, patch: vtkPolyData, frame: int) -> int:
        """Add ``patch`` under ``key`` (replacing a patch of that key); returns the net change in cells."""
        patch = self._stamp(patch, frame)
        old = self._patches.get(key)
        previous = self._block_evidence(key, old) if old is not None else None
        base = self._identify(key, patch)
        count = patch.GetNumberOfCells()
        self._face_evidence[base : base + count] = 0.0
        self._face_contradicted[base : base + count] = 0
        if previous is not None:
            self._inherit_evidence(patch, base, *previous)
        before = self._cells
        if old is not None:
            self._cells -= old.GetNumberOfCells()
            self._patches[key] = patch
            index = list(self._patches).index(key)
            self._map.SetBlock(index, patch)
        else:
            self._patches[key] = patch
            index = len(self._patches) - 1
            self._map.SetBlock(index, patch)
            self._map.GetMetaData(index).Set(vtkCompositeDataSet.NAME(), key)
        self._cells += patch.GetNumberOfCells()
        self._map.Modified()
        self._merged = None
        return self._cells - before

    def remove_patch(self, key: str) -> int:
        """Remove the patch ``key`` if present; returns the net change in cells (<= 0)."""
        old = self._patches.pop(key, None)
        if old is None:
            return 0
        self._ids.release(key)
        self._cells -= old.GetNumberOfCells()
        self._rebuild_blocks()
        self._merged = None
        return -old.GetNumberOfCells()

    def reset(self) -> None:
        """Empty the map."""
        self._patches.clear()
        self._ids.clear()
        self._face_normals = np.zeros((0, 3), dtype=np.float32)
        self._face_evidence = np.zeros(0, dtype=np.float32)
        self._face_contradicted = np.zeros(0, dtype=np.uint16)
        self._cells = 0
        self._merged = None
        self._last_input = None
        self._next_frame = 0
        self.cells_added = 0
        self._rebuild_blocks()
        self.Modified()

    def state(self) -> dict:
        """The map as plain data (patches in order as [key, arrays] pairs, face id ranges, evidence), for checkpoints."""
        return {
            "patches": [[key, polydata_to_state(patch)] for key, patch in self._patches.items()],
            "ranges": {key: [int(base), int(count)] for key, (base, count) in self._ids._ranges.items()},
            "evidence": self._face_evidence.copy(),
            "contradicted": self._face_contradicted.copy(),
            "next_frame": self._next_frame,
        }

    def set_state(self, state: dict) -> None:
        """Restore a map saved by :meth:`state` (replaces the current map)."""
        self._patches = {key: polydata_from_state(patch) for key, patch in state["patches"]}
        self._ids.clear()
        self._ids._ranges.update({key: (int(base), int(count)) for key, (base, count) in state["ranges"].items()})
        self._face_evidence = state["evidence"].copy()
        self._face_contradicted = state["contradicted"].copy()
        self._face_normals = np.zeros((len(self._face_evidence), 3), dtype=np.float32)
        for key, patch in self._patches.items():
            base, count = self._ids._ranges[key]
            self._face_normals[base : base + count] = face_normals(patch)
        self._cells = sum(p.GetNumberOfCells() for p in self._patches.values())
        self._next_frame = int(state["next_frame"])
        self._merged = None
        self._last_input = None
        self.cells_added = 0
        self._rebuild_blocks()
        self.Modified()

    def mesh(self) -> vtkPolyData:
        """The whole map as one vtkPolyData (cell data ``frame``); cached until the map changes."""
        if self._merged is None:
            merged = vtkPolyData()
            if self._patches:
                append = vtkAppendPolyData()
                for patch in self._patches.values():
                    append.AddInputData(patch)
                append.Update()
                merged.ShallowCopy(append.GetOutput())
                merged.GetCellData().RemoveArray(FACE_RGB_ARRAY)
            self._merged = merged
        return self._merged

    # -- faces: identity in E, evidence, removal ------------------------------
    def _identify(self, key: str, patch: vtkPolyData, normals: np.ndarray | None = None) -> int:
        """Give the faces of block ``key`` their identities (cell data ``face_rgb``) and normals (computed
        unless given); returns the base id."""
        count = patch.GetNumberOfCells()
        base = self._ids.allocate(key, count)
        self._grow(base + count)
        rgb = numpy_to_vtk(face_rgb(base, count), deep=True)
        rgb.SetName(FACE_RGB_ARRAY)
        patch.GetCellData().AddArray(rgb)
        self._face_normals[base : base + count] = face_normals(patch) if normals is None else normals
        return base

    def _grow(self, size: int) -> None:
        """Room in the per-identity arrays for ids below ``size`` (doubling)."""
        if size <= len(self._face_evidence):
            return
        capacity = max(size, 2 * len(self._face_evidence), 1024)
        grown = len(self._face_evidence)
        self._face_normals = np.concatenate([self._face_normals, np.zeros((capacity - grown, 3), np.float32)])
        self._face_evidence = np.concatenate([self._face_evidence, np.zeros(capacity - grown, np.float32)])
        self._face_contradicted = np.concatenate([self._face_contradicted, np.zeros(capacity - grown, np.uint16)])

    def _block_evidence(self, key: str, patch: vtkPolyData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(face centres, removal evidence, contradicting frames) of the faces of block ``key``."""
        base, count = self._ids._ranges[key]
        centres, _ = face_centres(patch)
        return centres, self._face_evidence[base : base + count].copy(), self._face_contradicted[base : base + count].copy()

    def _inherit_evidence(self, patch: vtkPolyData, base: int, centres: np.ndarray, evidence: np.ndarray, frames: np.ndarray) -> None:
        """A re-meshed block's faces keep the removal evidence of the face they replace.

        Voxel planes re-mesh a block whenever a point lands in it: with fresh evidence, the ghost of a
        departed object whose block keeps receiving points (the floor seen where it stood) would never
        gather the frames removal asks for. A new face takes the evidence of the old face whose centre is
        nearest to its own, if that centre lies within the new face (its radius); otherwise it starts at 0.
        """
        if not len(centres):
            return
        new_centres, radii = face_centres(patch)
        distance, nearest = cKDTree(centres).query(new_centres, distance_upper_bound=float(radii.max()) if len(radii) else 0.0)
        same = np.isfinite(distance) & (distance <= radii)
        ids = base + np.flatnonzero(same)
        self._face_evidence[ids] = evidence[nearest[same]]
        self._face_contradicted[ids] = frames[nearest[same]]

    def face_lookup(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Where faces ``ids`` (24-bit identities from E) live: (block number into ``keys``, cell id in the
        block, keys); block -1 for ids not in the map."""
        return self._ids.lookup(np.asarray(ids, dtype=np.int64))

    def block(self, key: str) -> vtkPolyData:
        """The polydata of block ``key`` (read it; change its points only through :meth:`move_points`)."""
        return self._patches[key]

    def move_points(self, key: str, vertex_ids: np.ndarray, positions: np.ndarray) -> None:
        """Move vertices ``vertex_ids`` of block ``key`` to ``positions`` (K, 3) world metres; faces unchanged.

        The block's points are changed in place and marked modified, so the expected-image renderer
        re-uploads that block only; the normals of the faces around the moved vertices are recomputed.
        """
        patch = self._patches[key]
        current = vtk_to_numpy(patch.GetPoints().GetData())
        vertex_ids = np.asarray(vertex_ids, dtype=np.int64)
        positions = np.asarray(positions)
        if positions.shape != (len(vertex_ids), 3):
            raise ValueError(f"move_points: {len(vertex_ids)} vertex ids of block {key} need ({len(vertex_ids)}, 3) positions, got {positions.shape}")
        if len(vertex_ids) and (vertex_ids.min() < 0 or vertex_ids.max() >= len(current)):
            raise ValueError(f"move_points: block {key} has {len(current)} points, got vertex ids outside 0..{len(current) - 1}")
        current[vertex_ids] = positions.astype(current.dtype)
        patch.GetPoints().Modified()
        patch.Modified()
        base, count = self._ids._ranges[key]
        triangles = patch_triangles(patch)
        if triangles is None:  # not all triangles: the block's normals anew
            self._face_normals[base : base + count] = face_normals(patch)
        else:
            moved = np.zeros(len(current), dtype=bool)
            moved[vertex_ids] = True
            faces = np.flatnonzero(moved[triangles].any(axis=1))
            self._face_normals[base + faces] = triangle_normals(current.astype(np.float32, copy=False), triangles[faces])[0]
        self._map.Modified()
        self._merged = None

    def face_normals_of(self, ids: np.ndarray) -> np.ndarray:
        """(N, 3) world normals of the faces ``ids`` (24-bit identities from E); NaN for ids not in the map."""
        ids = np.asarray(ids, dtype=np.int64)
        block, _, _ = self._ids.lookup(ids)
        normals = np.full((len(ids), 3), np.nan, dtype=np.float32)
        live = block >= 0
        normals[live] = self._face_normals[ids[live]]
        return normals

    def face_evidence_of(self, ids: np.ndarray) -> np.ndarray:
        """The removal log-odds of faces ``ids`` (meaningless for ids not in the map)."""
        ids = np.asarray(ids, dtype=np.int64)
        return self._face_evidence[np.minimum(ids, len(self._face_evidence) - 1)] if len(self._face_evidence) else np.zeros(len(ids), np.float32)

    def update_evidence(self, ids: np.ndarray, contradicted: np.ndarray, confirmed: np.ndarray, parameters) -> np.ndarray:
        """Add one frame's votes and return the identities of the faces whose removal the evidence now calls for.

        ``ids``: faces voted on this frame; ``contradicted`` / ``confirmed``: their pixel votes. The rule is
        :func:`mabdi.filters.removal.update_log_odds` (``parameters``: :class:`~mabdi.filters.removal.RemovalParameters`).
        """
        ids = np.asarray(ids, dtype=np.int64)
        block, _, _ = self._ids.lookup(ids)
        live = block >= 0
        ids = ids[live]
        evidence, frames, gone = update_log_odds(
            self._face_evidence[ids], self._face_contradicted[ids], contradicted[live], confirmed[live], parameters
        )
        self._face_evidence[ids] = evidence
        self._face_contradicted[ids] = frames
        return ids[gone]

    def remove_faces(self, ids: np.ndarray) -> vtkPolyData:
        """Remove the faces ``ids`` from their blocks (each changed block is rebuilt, so only it is re-uploaded).

        Returns the removed faces as one vtkPolyData (for the dashboard); the net change is in ``cells_removed``.
        """
        block, local, keys = self._ids.lookup(np.asarray(ids, dtype=np.int64))
        removed_parts = []
        for b in np.unique(block[block >= 0]):
            key = keys[b]
            patch = self._patches[key]
            base, count = self._ids._ranges[key]
            gone = np.zeros(count, dtype=bool)
            gone[local[block == b]] = True
            triangles = patch_triangles(patch)
            if triangles is not None:
                # A departed object's faces are contiguous: faces already contradicted (evidence above 0)
                # go with a removed face they are edge-connected to, and so do the direct neighbours of the
                # removed faces that were never voted on at all (smaller than a pixel: no pixel centre
                # showed them), and kept faces left as islands inside the removed region.
                evidence = self._face_evidence[base : base + count]
                points = patch.GetNumberOfPoints()
                gone = spread_removal(triangles, points, gone, evidence > 0)
                never_voted = (evidence == 0) & (self._face_contradicted[base : base + count] == 0)
                gone = spread_removal(triangles, points, gone, never_voted, steps=1)
                gone |= enclosed(triangles, points, gone)
            removed_parts.append(extract_polys(patch, np.flatnonzero(gone)))
            keep = np.flatnonzero(~gone)
            if keep.size == 0:
                self.remove_patch(key)
                continue
            kept_evidence = self._face_evidence[base + keep]
            kept_frames = self._face_contradicted[base + keep]
            kept_normals = self._face_normals[base + keep]
            kept = extract_polys(patch, keep)
            kept.GetCellData().RemoveArray(FACE_RGB_ARRAY)
            new_base = self._identify(key, kept, kept_normals)
            self._face_evidence[new_base : new_base + keep.size] = kept_evidence
            self._face_contradicted[new_base : new_base + keep.size] = kept_frames
            self._cells -= patch.GetNumberOfCells() - kept.GetNumberOfCells()
            self._patches[key] = kept
            self._map.SetBlock(list(self._patches).index(key), kept)
            self._map.Modified()
            self._merged = None
        removed = vtkPolyData()
        if removed_parts:
            append = vtkAppendPolyData()
            for part in removed_parts:
                append.AddInputData(part)
            append.Update()
            removed.ShallowCopy(append.GetOutput())
        return removed

    @staticmethod
    def _stamp(patch: vtkPolyData, frame: int) -> vtkPolyData:
        """A shallow copy of ``patch`` with cell data ``frame`` (kept if the patch has it already)."""
        stamped = vtkPolyData()
        stamped.ShallowCopy(patch)
        stamped.GetFieldData().Initialize()
        if stamped.GetCellData().GetArray(FRAME_CELL_ARRAY) is None:
            frames = numpy_to_vtk(np.full(stamped.GetNumberOfCells(), frame, dtype=np.int32), deep=True)
            frames.SetName(FRAME_CELL_ARRAY)
            stamped.GetCellData().AddArray(frames)
        stamped.GetCellData().RemoveArray(PATCH_KEY_ARRAY)
        return stamped

    # -- pipeline ----------------------------------------------------------
    def RequestData(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        surface = vtkPolyData.GetData(inInfo[0])
        stamp = (surface.GetAddressAsString("vtkObject"), surface.GetMTime())
        if stamp != self._last_input:  # a re-execution with the same input appends nothing
            self._last_input = stamp
            frame = _input_frame(surface)
            if frame is None:
                frame = self._next_frame
            self._next_frame = frame + 1
            self.cells_added = self._append(surface, frame)
        output = vtkMultiBlockDataSet.GetData(outInfo)
        output.ShallowCopy(self._map)
        return 1

    def _append(self, surface: vtkPolyData, frame: int) -> int:
        added = 0
        removed = surface.GetFieldData().GetArray(REMOVED_KEYS_ARRAY)
        if removed is not None:
            for key in vtk_to_numpy(removed).tolist():
                added += self.remove_patch(f"patch_{key}")
        if surface.GetNumberOfCells() == 0:
            return added
        keys = surface.GetCellData().GetArray(PATCH_KEY_ARRAY)
        if keys is None:
            return added + self.add_patch(f"frame_{frame}", surface, frame)
        keys = vtk_to_numpy(keys)
        order = np.argsort(keys, kind="stable")
        boundaries = np.flatnonzero(np.diff(keys[order])) + 1
        for group in np.split(order, boundaries):
            added += self.add_patch(f"patch_{int(keys[group[0]])}", extract_polys(surface, group), frame)
        return added
