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
        self._cells -= old.GetNumberOfCells()
        self._rebuild_blocks()
        self._merged = None
        return -old.GetNumberOfCells()

    def reset(self) -> None:
        """Empty the map."""
        self._patches.clear()
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
            "next_frame": self._next_frame,
        }

    def set_state(self, state: dict) -> None:
        """Restore a map saved by :meth:`state` (replaces the current map)."""
        self._patches = {key: polydata_from_state(patch) for key, patch in state["patches"]}
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
            self._merged = merged
        return self._merged

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
