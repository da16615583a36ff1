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
"""

from __future__ import annotations

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkCompositeDataSet, vtkMultiBlockDataSet, vtkPolyData
from vtkmodules.vtkFiltersCore import vtkAppendPolyData

from mabdi.algorithm import MabdiAlgorithm
from mabdi.depth import FRAME_ARRAY
from mabdi.polydata import extract_polys, polydata_from_state, polydata_to_state

FRAME_CELL_ARRAY = "frame"
PATCH_KEY_ARRAY = "patch_key"
REMOVED_KEYS_ARRAY = "removed_patch_keys"
#: Cell data of every block: the face's 24-bit identity as uint8 RGB (red = low byte), drawn by the
#: expected-image renderer so that E says which face each pixel shows. Not part of :meth:`FilterWorldMesh.mesh`.
FACE_RGB_ARRAY = "face_rgb"
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


def edge_pairs(patch: vtkPolyData) -> tuple[np.ndarray, np.ndarray]:
    """(a, b): the pairs of triangles of a patch that share an edge (empty for non-triangle patches)."""
    polys = patch.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray()).astype(np.int64)
    if len(offsets) < 2 or np.any(np.diff(offsets) != 3):
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    triangles = vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64).reshape(-1, 3)
    edges = np.sort(np.stack([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]], axis=1), axis=2)
    keys = (edges[..., 0] * (int(triangles.max()) + 1) + edges[..., 1]).ravel()
    owner = np.repeat(np.arange(len(triangles)), 3)
    order = np.argsort(keys, kind="stable")
    keys, owner = keys[order], owner[order]
    same = keys[1:] == keys[:-1]
    return owner[:-1][same], owner[1:][same]


def spread_removal(patch: vtkPolyData, gone: np.ndarray, followers: np.ndarray, steps: int | None = None) -> np.ndarray:
    """``gone`` grown over edge-connected triangles of the mask ``followers``: whole connected groups of
    followers that touch a removed face (``steps=1``: only the followers next to a removed face)."""
    a, b = edge_pairs(patch)
    if not len(a) or not followers.any() or not gone.any():
        return gone
    if steps == 1:
        reach = np.zeros_like(gone)
        reach[b[gone[a]]] = True
        reach[a[gone[b]]] = True
        return gone | (reach & followers)
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    member = gone | followers
    keep = member[a] & member[b]
    size = len(gone)
    graph = coo_matrix((np.ones(int(keep.sum()), dtype=np.int8), (a[keep], b[keep])), shape=(size, size))
    _, component = connected_components(graph, directed=False)
    touched = np.zeros(component.max() + 1, dtype=bool)
    touched[component[gone]] = True
    return gone | (member & touched[component])


def enclosed(patch: vtkPolyData, gone: np.ndarray) -> np.ndarray:
    """Triangles not in ``gone`` whose edge neighbours (at least two) are all in ``gone``."""
    a, b = edge_pairs(patch)
    if not len(a) or not gone.any():
        return np.zeros_like(gone)
    count = np.bincount(a, minlength=len(gone)) + np.bincount(b, minlength=len(gone))
    gone_count = np.bincount(a, weights=gone[b], minlength=len(gone)) + np.bincount(b, weights=gone[a], minlength=len(gone))
    return ~gone & (count >= 2) & (gone_count == count)


def face_normals(patch: vtkPolyData) -> np.ndarray:
    """(M, 3) float32 unit normals of a patch's polygons (from their first three corners; triangles in the map)."""
    if patch.GetNumberOfCells() == 0:
        return np.zeros((0, 3), dtype=np.float32)
    points = vtk_to_numpy(patch.GetPoints().GetData()).astype(np.float64)
    polys = patch.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray())[:-1].astype(np.int64)
    connectivity = vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64)
    a, b, c = (points[connectivity[offsets + k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return (normals / np.where(length > 0, length, 1.0)).astype(np.float32)


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
        #: Per block: face normals (world), removal evidence (log-odds) and frames that contradicted each face.
        self._normals: dict[str, np.ndarray] = {}
        self._evidence: dict[str, np.ndarray] = {}
        self._contradicted_frames: dict[str, np.ndarray] = {}

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
        self._identify(key, patch)
        count = patch.GetNumberOfCells()
        self._evidence[key] = np.zeros(count, dtype=np.float32)
        self._contradicted_frames[key] = np.zeros(count, dtype=np.uint16)
        before = self._cells
        old = self._patches.get(key)
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
        for table in (self._normals, self._evidence, self._contradicted_frames):
            table.pop(key, None)
        self._cells -= old.GetNumberOfCells()
        self._rebuild_blocks()
        self._merged = None
        return -old.GetNumberOfCells()

    def reset(self) -> None:
        """Empty the map."""
        self._patches.clear()
        self._ids.clear()
        for table in (self._normals, self._evidence, self._contradicted_frames):
            table.clear()
        self._cells = 0
        self._merged = None
        self._last_input = None
        self._next_frame = 0
        self.cells_added = 0
        self._rebuild_blocks()
        self.Modified()

    def state(self) -> dict:
        """The map as plain arrays (patches in order, with their keys), for checkpoints."""
        return {
            "patches": [(key, polydata_to_state(patch)) for key, patch in self._patches.items()],
            "ranges": dict(self._ids._ranges),
            "evidence": {k: v.copy() for k, v in self._evidence.items()},
            "contradicted_frames": {k: v.copy() for k, v in self._contradicted_frames.items()},
            "next_frame": self._next_frame,
        }

    def set_state(self, state: dict) -> None:
        """Restore a map saved by :meth:`state` (replaces the current map)."""
        self._patches = {key: polydata_from_state(patch) for key, patch in state["patches"]}
        self._ids.clear()
        self._ids._ranges.update(state["ranges"])
        self._normals = {key: face_normals(patch) for key, patch in self._patches.items()}
        self._evidence = {k: v.copy() for k, v in state["evidence"].items()}
        self._contradicted_frames = {k: v.copy() for k, v in state["contradicted_frames"].items()}
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
    def _identify(self, key: str, patch: vtkPolyData) -> None:
        """Give the faces of block ``key`` their identities (cell data ``face_rgb``) and normals."""
        count = patch.GetNumberOfCells()
        base = self._ids.allocate(key, count)
        rgb = numpy_to_vtk(face_rgb(base, count), deep=True)
        rgb.SetName(FACE_RGB_ARRAY)
        patch.GetCellData().AddArray(rgb)
        self._normals[key] = face_normals(patch)

    def face_lookup(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Where faces ``ids`` (24-bit identities from E) live: (block number into ``keys``, cell id in the
        block, keys); block -1 for ids not in the map."""
        return self._ids.lookup(np.asarray(ids, dtype=np.int64))

    def block(self, key: str) -> vtkPolyData:
        """The polydata of block ``key`` (read it; change its points only through :meth:`move_points`)."""
        return self._patches[key]

    def move_points(self, key: str, points: np.ndarray) -> None:
        """Give block ``key`` new vertex positions (N, 3) (same count and order; faces unchanged).

        The block's points are replaced in place and marked modified, so the expected-image renderer
        re-uploads that block only.
        """
        patch = self._patches[key]
        current = vtk_to_numpy(patch.GetPoints().GetData())
        if points.shape != current.shape:
            raise ValueError(f"move_points: block {key} has {current.shape} points, got {points.shape}")
        current[:] = points.astype(current.dtype)
        patch.GetPoints().Modified()
        patch.Modified()
        self._normals[key] = face_normals(patch)
        self._map.Modified()
        self._merged = None

    def face_normals_of(self, ids: np.ndarray) -> np.ndarray:
        """(N, 3) world normals of the faces ``ids`` (24-bit identities from E); NaN for ids not in the map."""
        block, local, keys = self._ids.lookup(ids)
        normals = np.full((len(block), 3), np.nan, dtype=np.float32)
        for b in np.unique(block[block >= 0]):
            chosen = block == b
            normals[chosen] = self._normals[keys[b]][local[chosen]]
        return normals

    def update_evidence(self, ids: np.ndarray, contradicted: np.ndarray, confirmed: np.ndarray, parameters) -> np.ndarray:
        """Add one frame's votes and return the identities of the faces whose removal the evidence now calls for.

        ``ids``: faces voted on this frame; ``contradicted`` / ``confirmed``: their pixel votes. The rule is
        :func:`mabdi.filters.removal.update_log_odds` (``parameters``: :class:`~mabdi.filters.removal.RemovalParameters`).
        """
        from mabdi.filters.removal import update_log_odds

        block, local, keys = self._ids.lookup(ids)
        remove = []
        for b in np.unique(block[block >= 0]):
            chosen = block == b
            key = keys[b]
            cells = local[chosen]
            evidence, frames, gone = update_log_odds(
                self._evidence[key][cells], self._contradicted_frames[key][cells], contradicted[chosen], confirmed[chosen], parameters
            )
            self._evidence[key][cells] = evidence
            self._contradicted_frames[key][cells] = frames
            remove.append(ids[chosen][gone])
        return np.concatenate(remove) if remove else np.zeros(0, dtype=np.int64)

    def remove_faces(self, ids: np.ndarray) -> vtkPolyData:
        """Remove the faces ``ids`` from their blocks (each changed block is rebuilt, so only it is re-uploaded).

        Returns the removed faces as one vtkPolyData (for the dashboard); the net change is in ``cells_removed``.
        """
        block, local, keys = self._ids.lookup(np.asarray(ids, dtype=np.int64))
        removed_parts = []
        for b in np.unique(block[block >= 0]):
            key = keys[b]
            patch = self._patches[key]
            gone = np.zeros(patch.GetNumberOfCells(), dtype=bool)
            gone[local[block == b]] = True
            # A departed object's faces are contiguous: faces already contradicted (evidence above 0) go
            # with a removed face they are edge-connected to, and so do the direct neighbours of the removed
            # faces that were never voted on at all (smaller than a pixel: no pixel centre showed them).
            evidence = self._evidence[key]
            gone = spread_removal(patch, gone, evidence > 0)
            never_voted = (evidence == 0) & (self._contradicted_frames[key] == 0)
            gone |= spread_removal(patch, gone, never_voted, steps=1)
            gone |= enclosed(patch, gone)  # a face whose every neighbour went is a remnant of the same surface
            removed_parts.append(extract_polys(patch, np.flatnonzero(gone)))
            keep = np.flatnonzero(~gone)
            if keep.size == 0:
                self.remove_patch(key)
                continue
            kept = extract_polys(patch, keep)
            kept.GetCellData().RemoveArray(FACE_RGB_ARRAY)
            self._identify(key, kept)
            self._evidence[key] = self._evidence[key][keep]
            self._contradicted_frames[key] = self._contradicted_frames[key][keep]
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
