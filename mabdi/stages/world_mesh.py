"""FilterWorldMesh: the map, grown patch by patch (the VTK adaptor of :class:`mabdi.world_map.WorldMap`).

Surface (vtkPolyData) in, the map out as a ``vtkMultiBlockDataSet``: one
block per chunk of space, each with its patches as named blocks and its
bounding box in the block's metadata (:mod:`mabdi.world_map`). Each update
appends the input surface as a new patch keyed ``frame_<i>`` (i from the
input's field data ``frame``), so the cost of a frame grows with its new
surface, not with the map. Every cell gets cell data ``frame``: the frame that
created it.

Why blocks: the expected image E is rendered from the map every frame, and a
VTK mapper re-uploads its whole polydata whenever that changes. Kept as
blocks, the map's existing geometry is never touched again, and
:class:`mabdi.render.depth_image.DepthRenderer` draws each block in view
with its own mapper, so a frame uploads only its new block. Users and exports
get one merged mesh from :meth:`FilterWorldMesh.mesh`.

Keyed patches: a surface filter that re-meshes parts of the map (voxel
planes) marks its cells with an int64 cell array ``patch_key``; the cells of
each key replace the patch of that key (``patch_<key>``) instead of stacking
a new layer, and the int64 field-data array ``removed_patch_keys`` deletes
patches. :meth:`add_patch` / :meth:`remove_patch` do the same from Python.
A re-meshed patch's faces keep the removal evidence of the faces they
replace (matched by centre), so re-meshing does not reset object removal.

Faces are named by the codes of an expected image and its
:class:`~mabdi.face_identity.FaceIdTable` (:meth:`face_lookup`,
:meth:`update_evidence`, :meth:`remove_faces`, ...).
"""

from __future__ import annotations

import numpy as np
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkMultiBlockDataSet, vtkPolyData

from mabdi.algorithm import MabdiAlgorithm
from mabdi.depth import FRAME_ARRAY
from mabdi.face_identity import FaceIdTable
from mabdi.polydata import split_polys
from mabdi.world_map import CHUNK_SIZE, FRAME_CELL_ARRAY, PATCH_KEY_ARRAY, PATCHES_PER_CHUNK, POOL_SIZE, REMOVED_KEYS_ARRAY, WorldMap

__all__ = ["FRAME_CELL_ARRAY", "PATCH_KEY_ARRAY", "REMOVED_KEYS_ARRAY", "FilterWorldMesh"]


def _input_frame(surface: vtkPolyData) -> int | None:
    array = surface.GetFieldData().GetArray(FRAME_ARRAY)
    if array is None or array.GetNumberOfTuples() == 0:
        return None
    return int(array.GetTuple1(0))


class FilterWorldMesh(MabdiAlgorithm):
    """The map: appends each frame's surface as a patch (vtkPolyData -> vtkMultiBlockDataSet of chunks)."""

    def __init__(
        self, chunk_size: float = CHUNK_SIZE, patches_per_chunk: int = PATCHES_PER_CHUNK, compact_on_append: bool = True,
        pool_size: float | None = POOL_SIZE,
    ) -> None:
        super().__init__(nInputPorts=1, inputType="vtkPolyData", nOutputPorts=1, outputType="vtkMultiBlockDataSet")
        #: The store itself (chunks, patches, per-face evidence).
        self.store = WorldMap(chunk_size, patches_per_chunk, pool_size)
        #: Merge each chunk's frame patches (:meth:`WorldMap.compact`) before appending a surface. A loop that
        #: uses an expected image's face codes after appending (removal votes) turns it off and calls
        #: :meth:`compact` itself once the codes are used (merged patches get new names).
        self.compact_on_append = compact_on_append
        self._last_input: tuple[str, int] | None = None
        self._next_frame = 0
        #: Net change in the number of cells made by the last update (replacements count net).
        self.cells_added = 0

    # -- the map -----------------------------------------------------------
    @property
    def map(self) -> vtkMultiBlockDataSet:
        """The live map (one block per chunk, its patches under it). Feed it to the expected-image renderer."""
        return self.store.multiblock

    @property
    def number_of_cells(self) -> int:
        return self.store.number_of_cells

    @property
    def number_of_points(self) -> int:
        return self.store.number_of_points

    @property
    def patch_keys(self) -> list[str]:
        return self.store.patch_keys

    def memory_bytes(self) -> int:
        return self.store.memory_bytes()

    def add_patch(self, key: str, patch: vtkPolyData, frame: int) -> int:
        """Add ``patch`` under ``key`` (replacing a patch of that key); returns the net change in cells."""
        return self.store.add_patch(key, patch, frame, keyed=key.startswith("patch_"))

    def remove_patch(self, key: str) -> int:
        """Remove the patch ``key`` if present; returns the net change in cells (<= 0)."""
        return self.store.remove_patch(key)

    def reset(self) -> None:
        """Empty the map."""
        self.store.reset()
        self._last_input = None
        self._next_frame = 0
        self.cells_added = 0
        self.Modified()

    def state(self) -> dict:
        """The map as plain data, for checkpoints."""
        return {**self.store.state(), "next_frame": self._next_frame}

    def set_state(self, state: dict) -> None:
        """Restore a map saved by :meth:`state` (replaces the current map)."""
        self.store.set_state(state)
        self._next_frame = int(state["next_frame"])
        self._last_input = None
        self.cells_added = 0
        self.Modified()

    def mesh(self) -> vtkPolyData:
        """The whole map as one vtkPolyData (cell data ``frame``); cached until the map changes."""
        return self.store.mesh()

    def block(self, key: str) -> vtkPolyData:
        """The polydata of patch ``key`` (read it; change its points only through :meth:`move_points`)."""
        return self.store.block(key)

    def compact(self) -> None:
        """Merge each chunk's frame patches beyond the limit (:meth:`mabdi.world_map.WorldMap.compact`)."""
        self.store.compact()

    def move_points(self, key: str, vertex_ids: np.ndarray, positions: np.ndarray) -> None:
        """Move vertices of patch ``key`` (see :meth:`mabdi.world_map.WorldMap.move_points`)."""
        self.store.move_points(key, vertex_ids, positions)

    def move_points_of(self, moves) -> None:
        """Apply a frame's vertex ``moves`` ``(key, vertex_ids, positions)`` (see :meth:`mabdi.world_map.WorldMap.move_points_of`)."""
        self.store.move_points_of(moves)

    # -- faces, by the codes of an expected image -------------------------------
    def face_lookup(self, codes, table: FaceIdTable):
        """(index into keys, cell id in the patch, keys) of an expected image's face ``codes``; -1 where none."""
        return self.store.face_lookup(codes, table)

    def refitted_faces(self, key: str) -> np.ndarray:
        """Faces of patch ``key`` made or fitted again at its last replacement (:meth:`WorldMap.refitted_faces`)."""
        return self.store.refitted_faces(key)

    def current_blocks(self, table: FaceIdTable) -> list[int]:
        """Blocks of ``table`` that are their patch as it is now (:meth:`WorldMap.current_blocks`)."""
        return self.store.current_blocks(table)

    def stale_blocks(self, table: FaceIdTable) -> list[int]:
        """Blocks of ``table`` re-meshed since it was drawn (:meth:`WorldMap.stale_blocks`)."""
        return self.store.stale_blocks(table)

    def face_corners_of(self, codes, table: FaceIdTable) -> np.ndarray:
        return self.store.face_corners_of(codes, table)

    def face_normals_of(self, codes, table: FaceIdTable) -> np.ndarray:
        return self.store.face_normals_of(codes, table)

    def face_evidence_of(self, codes, table: FaceIdTable) -> np.ndarray:
        return self.store.face_evidence_of(codes, table)

    def update_evidence(self, codes, contradicted, confirmed, parameters, table: FaceIdTable) -> np.ndarray:
        """One frame's removal votes; the codes of the faces now condemned (:meth:`WorldMap.update_evidence`)."""
        return self.store.update_evidence(codes, contradicted, confirmed, parameters, table)

    def remove_faces(self, codes, table: FaceIdTable, follow_frames: int = 1) -> vtkPolyData:
        """Remove faces (and those that go with them); returns the removed faces (:meth:`WorldMap.remove_faces`)."""
        return self.store.remove_faces(codes, table, follow_frames)

    def append(self, surface: vtkPolyData, frame: int) -> int:
        """Append frame ``frame``'s surface (world coordinates; cell data ``patch_key`` for keyed patches, field
        data ``removed_keys`` for patches it replaces) to the map; returns the net change in cells (also
        :attr:`cells_added`)."""
        self._next_frame = frame + 1
        if self.compact_on_append:
            self.store.compact()
        self.cells_added = self._append(surface, frame)
        return self.cells_added

    # -- pipeline ----------------------------------------------------------
    def RequestData(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        surface = vtkPolyData.GetData(inInfo[0])
        stamp = (surface.GetAddressAsString("vtkObject"), surface.GetMTime())
        if stamp != self._last_input:  # a re-execution with the same input appends nothing
            self._last_input = stamp
            frame = _input_frame(surface)
            self.append(surface, self._next_frame if frame is None else frame)
        output = vtkMultiBlockDataSet.GetData(outInfo)
        output.ShallowCopy(self.store.multiblock)
        return 1

    def _append(self, surface: vtkPolyData, frame: int) -> int:
        added = 0
        removed = surface.GetFieldData().GetArray(REMOVED_KEYS_ARRAY)
        if removed is not None:
            for key in vtk_to_numpy(removed).tolist():
                added += self.store.remove_patch(f"patch_{key}")
        if surface.GetNumberOfCells() == 0:
            return added
        keys = surface.GetCellData().GetArray(PATCH_KEY_ARRAY)
        if keys is None:
            return added + self.store.add_patch(f"frame_{frame}", surface, frame)
        for key, patch in split_polys(surface, vtk_to_numpy(keys)):
            patch.GetCellData().RemoveArray(PATCH_KEY_ARRAY)
            added += self.store.add_patch(f"patch_{key}", patch, frame, keyed=True)
        return added
