"""FrameSurface: the VTK edge of a surface that meshes one frame at a time.

A subclass implements ``mesh_frame(frame, whole)`` (a
:class:`~mabdi.frame_values.Measured` holding the pixels to mesh, and all of
D or None) and returns the triangles in the world of the frame's pose; the
loop calls it with the frame's values. As a VTK filter it takes a depth
image (the classifier's output, or D itself), reads it into those values,
trims the faces wholly on the classifier's rim where the image marks its
novel pixels (:mod:`mabdi.surfaces.seam_trim`, as the loop does), and passes
the image's field data on to its vtkPolyData output.
"""

from __future__ import annotations

import numpy as np
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkImageData, vtkPolyData

from mabdi.algorithm import MabdiAlgorithm
from mabdi.depth import measured_depth
from mabdi.frame_values import Measured
from mabdi.surfaces.seam_trim import NOVEL_PIXELS_ARRAY, trimmed_patch


class FrameSurface(MabdiAlgorithm):
    """A surface filter of one depth-image input and a vtkPolyData output whose work is :meth:`mesh_frame`."""

    def __init__(self) -> None:
        super().__init__(nInputPorts=1, inputType="vtkImageData", nOutputPorts=1, outputType="vtkPolyData")

    def mesh_frame(self, frame: Measured, whole: np.ndarray | None = None) -> vtkPolyData:
        raise NotImplementedError

    def RequestData(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        image = vtkImageData.GetData(inInfo[0])
        output = vtkPolyData.GetData(outInfo)
        frame = Measured.from_image(image)
        patch = self.mesh_frame(frame, measured_depth(image))
        novel = image.GetPointData().GetArray(NOVEL_PIXELS_ARRAY)
        if novel is not None:
            novel_pixels = vtk_to_numpy(novel).reshape(frame.depth.shape).astype(bool)
            patch = trimmed_patch(patch, novel_pixels, frame.geometry, frame.pose)
        output.ShallowCopy(patch)
        output.GetFieldData().ShallowCopy(image.GetFieldData())
        return 1
