"""The depth image: a vtkImageData every mabdi filter reads and writes.

Layout (design.md):

* extent (0, W-1, 0, H-1, 0, 0), origin 0, spacing 1;
* point array ``depth`` (float32): metric z-depth along the optical axis,
  NaN where there is no return, row-major with index v*W + u and v = 0 the
  **top** row of the image;
* field data ``intrinsics`` (float64[8]: fx, fy, cx, cy, width, height, near,
  far), ``world_from_camera`` (float64[16], row-major) and ``frame``
  (int64[1], the frame index, -1 when unknown).

:class:`DepthFrame` is the numpy side of the same thing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkImageData

from mabdi.camera import Intrinsics, check_pose

DEPTH_ARRAY = "depth"
INTRINSICS_ARRAY = "intrinsics"
POSE_ARRAY = "world_from_camera"
FRAME_ARRAY = "frame"


@dataclass
class DepthFrame:
    """A depth image as numpy: (H, W) float32 metres, its intrinsics, pose and frame index."""

    depth: np.ndarray
    intrinsics: Intrinsics
    world_from_camera: np.ndarray
    frame: int = -1

    def __post_init__(self) -> None:
        self.depth = np.asarray(self.depth, dtype=np.float32)
        if self.depth.shape != self.intrinsics.shape:
            raise ValueError(
                f"depth image has shape {self.depth.shape}, but intrinsics say (height, width) = {self.intrinsics.shape}"
            )
        self.world_from_camera = check_pose(self.world_from_camera, "world_from_camera")

    def to_image(self) -> vtkImageData:
        """This frame as a depth-image vtkImageData."""
        return depth_image(self.depth, self.intrinsics, self.world_from_camera, self.frame)

    @classmethod
    def from_image(cls, image) -> DepthFrame:
        """Read a depth-image vtkImageData (copies the depth array)."""
        intrinsics = image_intrinsics(image)
        return cls(depth_array(image).copy(), intrinsics, image_pose(image), image_frame(image))


def depth_image(depth, intrinsics: Intrinsics, world_from_camera, frame: int = -1) -> vtkImageData:
    """Build a depth-image vtkImageData from a (H, W) array of metres (v = 0 the top row); copies ``depth``."""
    depth = np.array(depth, dtype=np.float32, order="C", copy=True)
    if depth.shape != intrinsics.shape:
        raise ValueError(
            f"depth image has shape {depth.shape}, but intrinsics say (height, width) = {intrinsics.shape}"
        )
    image = vtkImageData()
    fill_depth_image(image, depth, intrinsics, check_pose(world_from_camera, "world_from_camera"), frame)
    return image


def fill_depth_image(image: vtkImageData, depth: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray, frame: int) -> None:
    """Fill an existing vtkImageData (a filter's output) with a depth image. Inputs are trusted.

    The image shares ``depth``'s memory: hand over an array nobody else writes to.
    """
    height, width = depth.shape
    image.SetExtent(0, width - 1, 0, height - 1, 0, 0)
    image.SetOrigin(0.0, 0.0, 0.0)
    image.SetSpacing(1.0, 1.0, 1.0)
    # Shallow: the VTK array keeps a reference to the numpy buffer (callers hand over a fresh array).
    array = numpy_to_vtk(np.ascontiguousarray(depth, dtype=np.float32).ravel(), deep=False)
    array.SetName(DEPTH_ARRAY)
    point_data = image.GetPointData()
    point_data.Initialize()
    point_data.SetScalars(array)
    field = image.GetFieldData()
    field.Initialize()
    for name, values in (
        (INTRINSICS_ARRAY, intrinsics.to_array()),
        (POSE_ARRAY, np.asarray(pose, dtype=np.float64).ravel()),
        (FRAME_ARRAY, np.array([frame], dtype=np.int64)),
    ):
        vtk_array = numpy_to_vtk(values, deep=True)
        vtk_array.SetName(name)
        field.AddArray(vtk_array)


def _field_array(image, name: str) -> np.ndarray:
    if image is None or not hasattr(image, "GetFieldData"):
        raise TypeError(f"expected a depth-image vtkImageData, got {type(image).__name__}")
    array = image.GetFieldData().GetArray(name)
    if array is None:
        raise ValueError(f"depth image has no field-data array '{name}' (is it a mabdi depth image?)")
    return vtk_to_numpy(array)


def image_intrinsics(image) -> Intrinsics:
    """Intrinsics stored in a depth image's field data."""
    return Intrinsics.from_array(_field_array(image, INTRINSICS_ARRAY))


def image_pose(image) -> np.ndarray:
    """``world_from_camera`` (4x4) stored in a depth image's field data."""
    values = _field_array(image, POSE_ARRAY)
    if values.size != 16:
        raise ValueError(f"depth image field '{POSE_ARRAY}' must hold 16 values, got {values.size}")
    return check_pose(values.reshape(4, 4), "depth image world_from_camera")


def image_frame(image) -> int:
    """Frame index stored in a depth image's field data (-1 when absent)."""
    array = image.GetFieldData().GetArray(FRAME_ARRAY)
    return int(vtk_to_numpy(array)[0]) if array is not None and array.GetNumberOfTuples() else -1


def depth_array(image) -> np.ndarray:
    """(H, W) float32 view of a depth image's ``depth`` array (no copy; row 0 is the top)."""
    intrinsics = image_intrinsics(image)
    array = image.GetPointData().GetArray(DEPTH_ARRAY)
    if array is None:
        raise ValueError(f"depth image has no point array '{DEPTH_ARRAY}'")
    values = vtk_to_numpy(array)
    if values.size != intrinsics.width * intrinsics.height:
        raise ValueError(
            f"depth array has {values.size} values, intrinsics say {intrinsics.width}x{intrinsics.height}"
        )
    return values.reshape(intrinsics.shape)
