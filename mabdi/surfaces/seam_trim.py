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
with no novel pixel within that pixel's reach (a square window; the frame's
pixels, its pose). The classifier states the reach per novel pixel
(:func:`trim_reach`): two pixels for new surface, so the patch still reaches
over the seam wherever across the rim the map's edge lies; one pixel for a
speck that fills a hole of the map, which the map rings at its depth on every
side, so that one pixel out the patch already lies on the hole's edge. A
reach of one pixel for new surface trimmed several times as many faces, but
left cracks narrower than a pixel along the seams (where the map's patch ends
between two pixel centres), which oblique views see through and which changed
where registration placed later frames; a reach of none for a hole's fill
reopened holes. Only a camera's patches are trimmed, and
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

#: Point data of the classifier's output image (uint8): per pixel the reach of :func:`trim_reach`, 0 on the
#: rim; present only where the patch is trimmed.
TRIM_REACH_ARRAY = "trim_reach"

#: A face stays when a novel pixel lies within this many pixels of the pixel its centroid projects onto ...
TRIM_REACH_PX = 2
#: ... or within this many of a pixel that fills a hole of the map.
FILL_REACH_PX = 1


def trim_reach(novel: np.ndarray, fills: np.ndarray) -> np.ndarray:
    """(H, W) uint8: per pixel, how far (pixels, a square) from it the patch's faces stay: :data:`TRIM_REACH_PX`
    at a pixel of ``novel`` ((H, W) bool, the pixels meshed for their own sake), :data:`FILL_REACH_PX` where it
    fills a hole of the map (``fills``, (H, W) bool), 0 elsewhere (the rim)."""
    reach = np.where(novel, np.uint8(TRIM_REACH_PX), np.uint8(0))
    reach[novel & fills] = FILL_REACH_PX
    return reach


def trims(geometry, rim_pixels: int) -> bool:
    """Whether a patch of a sensor of ``geometry`` meshed with a rim of ``rim_pixels`` is trimmed: a camera's
    (:class:`~mabdi.camera.Intrinsics`), with a rim wider than a pixel (a one-pixel rim is all seam)."""
    return isinstance(geometry, Intrinsics) and rim_pixels > 1


def kept_faces(
    patch: vtkPolyData,
    reach: np.ndarray,
    intrinsics: Intrinsics,
    world_from_camera: np.ndarray,
) -> np.ndarray:
    """(N,) bool per polygon of ``patch``: its centroid projects (``intrinsics``, 4x4 ``world_from_camera``)
    within a pixel's ``reach`` ((H, W) uint8, :func:`trim_reach`; 0: none) of that pixel (a square), or outside
    the image or behind the camera (kept: nothing to say of it)."""
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
    widest = int(reach.max()) if reach.size else 0
    for dv in range(-widest, widest + 1):  # the window read at the faces' pixels only
        for du in range(-widest, widest + 1):
            r, c = rows + dv, cols + du
            valid = (r >= 0) & (r < intrinsics.height) & (c >= 0) & (c < intrinsics.width)
            near[valid] |= reach[r[valid], c[valid]] >= max(abs(dv), abs(du), 1)
    keep[inside] = near
    return keep


def trimmed_patch(
    patch: vtkPolyData,
    reach: np.ndarray,
    intrinsics: Intrinsics,
    world_from_camera: np.ndarray,
) -> vtkPolyData:
    """``patch`` without the faces :func:`kept_faces` drops (``reach``: :func:`trim_reach`; the same object when
    it keeps them all); point and cell arrays and field data carried over."""
    keep = kept_faces(patch, reach, intrinsics, world_from_camera)
    if keep.all():
        return patch
    trimmed = extract_polys(patch, np.flatnonzero(keep))
    trimmed.GetFieldData().ShallowCopy(patch.GetFieldData())
    return trimmed
