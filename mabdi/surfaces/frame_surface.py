"""FrameSurface: the VTK edge of a surface that meshes one frame at a time.

A subclass implements ``mesh_frame(frame, whole)`` (a
:class:`~mabdi.frame_values.Measured` holding the pixels to mesh, and all of
D or None) and returns the triangles in the world of the frame's pose; the
loop calls it with the frame's values. As a VTK filter it takes a depth
image (the classifier's output, or D itself), reads it into those values,
and passes the image's field data on to its vtkPolyData output.
"""

from __future__ import annotations

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkImageData, vtkPolyData

from mabdi.algorithm import MabdiAlgorithm
from mabdi.depth import measured_depth
from mabdi.frame_values import Measured


class FrameSurface(MabdiAlgorithm):
    """A surface filter of one depth-image input and a vtkPolyData output whose work is :meth:`mesh_frame`."""

    def __init__(self) -> None:
        super().__init__(nInputPorts=1, inputType="vtkImageData", nOutputPorts=1, outputType="vtkPolyData")

    def mesh_frame(self, frame: Measured, whole: np.ndarray | None = None) -> vtkPolyData:
        raise NotImplementedError

    def RequestData(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        image = vtkImageData.GetData(inInfo[0])
        output = vtkPolyData.GetData(outInfo)
        output.ShallowCopy(self.mesh_frame(Measured.from_image(image), measured_depth(image)))
        output.GetFieldData().ShallowCopy(image.GetFieldData())
        return 1
