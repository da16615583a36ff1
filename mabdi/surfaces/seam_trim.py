"""Seam trimming: a new patch keeps only the faces that mesh its novel pixels, not those wholly on its rim.

The classifier meshes the novel pixels together with a rim of known pixels
around them (``rim``: a block of the quad-tree's 3 x 3 where the depth is
noisy), so that the surface places the patch's edge where the novel region
ends rather than up to a block inside it, and no crack opens along the seam
with the map. The rim's own faces are the map's surface meshed a second time,
and on a real camera's frames, where each frame's new surface is a thin
ragged strip, they made up much of the map (docs/benchmarks.md, "The rim's
own faces trimmed").

:func:`trimmed_patch` drops every face whose centroid projects onto a pixel
with no novel pixel within ``reach`` pixels (a square window; the frame's
pixels, its pose): the faces over novel pixels and those up to two pixels
beside them stay, so the patch still reaches over the seam; the others go.
A reach of one pixel trimmed several times as many faces, but left cracks
narrower than a pixel along the seams (where the map's patch ends between
two pixel centres), which oblique views see through and which changed where
registration placed later frames. Only a camera's patches are trimmed, and
only where the rim is wider than a pixel (the quad-tree on noisy depth): a
one-pixel rim is all seam.

Units: pixels; the patch is in the world frame of the frame's pose.
"""

from __future__ import annotations

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.camera import Intrinsics, project
from mabdi.polydata import extract_polys
from mabdi.world_map import face_centres

#: Point data of the classifier's output image (uint8): 1 where a pixel is meshed for its own sake, 0 on the
#: rim; present only where the patch is trimmed.
NOVEL_PIXELS_ARRAY = "novel_pixels"

#: A face stays when a novel pixel lies within this many pixels of the pixel its centroid projects onto.
TRIM_REACH_PX = 2


def trims(geometry, rim_pixels: int) -> bool:
    """Whether a patch of a sensor of ``geometry`` meshed with a rim of ``rim_pixels`` is trimmed: a camera's
    (:class:`~mabdi.camera.Intrinsics`), with a rim wider than a pixel (a one-pixel rim is all seam)."""
    return isinstance(geometry, Intrinsics) and rim_pixels > 1


def kept_faces(
    patch: vtkPolyData,
    novel: np.ndarray,
    intrinsics: Intrinsics,
    world_from_camera: np.ndarray,
    reach: int = TRIM_REACH_PX,
) -> np.ndarray:
    """(N,) bool per polygon of ``patch``: its centroid projects (``intrinsics``, 4x4 ``world_from_camera``)
    within ``reach`` pixels (a square) of a pixel of ``novel`` ((H, W) bool), or outside the image or behind
    the camera (kept: nothing to say of it)."""
    if patch.GetNumberOfCells() == 0:
        return np.zeros(0, dtype=bool)
    uv, z = project(face_centres(patch)[0], intrinsics, world_from_camera)
    with np.errstate(invalid="ignore"):
        u = np.floor(uv[:, 0])
        v = np.floor(uv[:, 1])
        inside = (z > 0) & (u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height)
    keep = ~inside
    rows, cols = v[inside].astype(np.int64), u[inside].astype(np.int64)
    near = np.zeros(len(rows), dtype=bool)
    for dv in range(-int(reach), int(reach) + 1):  # the window read at the faces' pixels only
        for du in range(-int(reach), int(reach) + 1):
            r, c = rows + dv, cols + du
            valid = (r >= 0) & (r < intrinsics.height) & (c >= 0) & (c < intrinsics.width)
            near[valid] |= novel[r[valid], c[valid]]
    keep[inside] = near
    return keep


def trimmed_patch(
    patch: vtkPolyData,
    novel: np.ndarray,
    intrinsics: Intrinsics,
    world_from_camera: np.ndarray,
    reach: int = TRIM_REACH_PX,
) -> vtkPolyData:
    """``patch`` without the faces :func:`kept_faces` drops (the same object when it keeps them all); point and
    cell arrays and field data carried over."""
    keep = kept_faces(patch, novel, intrinsics, world_from_camera, reach)
    if keep.all():
        return patch
    trimmed = extract_polys(patch, np.flatnonzero(keep))
    trimmed.GetFieldData().ShallowCopy(patch.GetFieldData())
    return trimmed
