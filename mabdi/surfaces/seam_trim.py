"""Seam trimming: a new patch keeps the faces that mesh its novel pixels, not those on its rim or on the map.

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

:func:`faces_on_map` then drops the faces that the map already holds: a face
whose centroid and three corners all lie within ``ON_MAP_M`` along its normal
of a map face that E shows at or beside the pixel the point projects onto,
and whose pixels (the box of its corners) hold no pixel where E shows no face.
Those are a second layer of the same surface (the rim's faces over the map, a
hole fill's edge). The second test keeps the faces that cover the map's
cracks, a pixel wide between its patches, which the tested points can miss:
dropped too, the cracks reopened and real frames were predicted worse
(docs/benchmarks.md, "New faces the map already holds").

Units: pixels and metres; the patch is in the world frame of the frame's pose.
"""

from __future__ import annotations

import numpy as np
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.camera import Intrinsics, project
from mabdi.polydata import extract_polys, segment_crossings, triangle_normals
from mabdi.surfaces.seam_trim_kernels import boxes_hold_kernel
from mabdi.world_map import face_centres, patch_triangles

#: Point data of the classifier's output image (uint8): 1 where a pixel is meshed for its own sake, 0 on the
#: rim; present only where the patch is trimmed.
NOVEL_PIXELS_ARRAY = "novel_pixels"

#: A face stays when a novel pixel lies within this many pixels of the pixel its centroid projects onto.
TRIM_REACH_PX = 2
#: A new face is the map's when its centroid and corners lie within this (m) of map faces along its normal.
ON_MAP_M = 0.01
#: The map faces a point is tested against: those E shows within this many pixels of the pixel it projects onto.
ON_MAP_WINDOW_PX = 1


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
    return _with_faces(patch, kept_faces(patch, novel, intrinsics, world_from_camera, reach))


def _with_faces(patch: vtkPolyData, keep: np.ndarray) -> vtkPolyData:
    """``patch`` with only the faces ``keep`` ((M,) bool; the same object when it keeps them all), point and cell
    arrays and field data carried over."""
    if keep.all():
        return patch
    kept = extract_polys(patch, np.flatnonzero(keep))
    kept.GetFieldData().ShallowCopy(patch.GetFieldData())
    return kept


def faces_on_map(patch: vtkPolyData, expected, face_corners_of, reach: float = ON_MAP_M) -> np.ndarray:
    """(M,) bool per triangle of ``patch``: the map already holds it (module docs). ``expected``: the frame's E
    (:class:`~mabdi.frame_values.Expected`, with its face codes); ``face_corners_of(codes, table)``: the map's
    triangles (N, 3, 3) for E's codes (:meth:`mabdi.world_map.WorldMap.face_corners_of`). All False for a
    patch of other polygons, or an E drawn without face identity."""
    triangles = patch_triangles(patch) if patch.GetNumberOfCells() else None
    if triangles is None or expected.face_ids is None or not isinstance(expected.geometry, Intrinsics):
        return np.zeros(patch.GetNumberOfCells(), dtype=bool)
    points = vtk_to_numpy(patch.GetPoints().GetData()).astype(np.float64)
    corners = points[triangles]  # (M, 3, 3)
    centroids = corners.mean(axis=1)
    tested = np.concatenate([centroids[:, None], corners], axis=1)  # (M, 4, 3): the centroid, then the corners
    intrinsics = expected.geometry
    uv, z = project(tested.reshape(-1, 3), intrinsics, expected.pose)
    uv, z = uv.reshape(-1, 4, 2), z.reshape(-1, 4)
    on_map = np.zeros(len(triangles), dtype=bool)
    # the cheap test first: the faces whose pixels hold no pixel where E shows no face
    candidates = np.flatnonzero((z > 0).all(axis=1) & ~over_a_hole(uv[:, 1:], expected.face_ids == 0))
    if len(candidates) == 0:
        return on_map
    uv = uv[candidates].reshape(-1, 2)
    rows, cols = np.floor(uv[:, 1]).astype(np.int64), np.floor(uv[:, 0]).astype(np.int64)
    window = range(-ON_MAP_WINDOW_PX, ON_MAP_WINDOW_PX + 1)
    codes = np.zeros((len(uv), len(window) ** 2), dtype=np.int64)
    for k, (dv, du) in enumerate((dv, du) for dv in window for du in window):
        r, c = rows + dv, cols + du
        ok = (r >= 0) & (r < intrinsics.height) & (c >= 0) & (c < intrinsics.width)
        codes[ok, k] = expected.face_ids[r[ok], c[ok]]
    unique, index = np.unique(codes, return_inverse=True)
    unique_corners = np.full((len(unique), 3, 3), np.nan)
    shown = unique != 0
    if shown.any():
        unique_corners[shown] = face_corners_of(unique[shown], expected.table)
    normals = np.repeat(triangle_normals(points, triangles[candidates])[0], 4, axis=0)
    flat = tested[candidates].reshape(-1, 3)
    corners_near = unique_corners[index.reshape(codes.shape)]  # (N, K, 3, 3): the map faces beside each point
    crossing = segment_crossings(
        flat[:, None], normals[:, None], reach, corners_near[:, :, 0], corners_near[:, :, 1], corners_near[:, :, 2]
    )
    on_map[candidates] = crossing.any(axis=1).reshape(-1, 4).all(axis=1)
    return on_map


def over_a_hole(corners_uv: np.ndarray, hole: np.ndarray) -> np.ndarray:
    """(M,) bool: whether the pixel box of each triangle's ``corners_uv`` (M, 3, 2) holds a pixel of ``hole``
    ((H, W) bool: E shows no face there) or leaves the image."""
    height, width = hole.shape
    with np.errstate(invalid="ignore"):
        low = np.floor(np.nanmin(corners_uv, axis=1))
        high = np.floor(np.nanmax(corners_uv, axis=1))
    finite = np.isfinite(low).all(axis=1) & np.isfinite(high).all(axis=1)
    low, high = np.where(finite[:, None], low, -1), np.where(finite[:, None], high, -1)
    inside = finite & (low >= 0).all(axis=1) & (high[:, 0] < width) & (high[:, 1] < height)
    boxes = np.zeros((len(corners_uv), 4), dtype=np.int64)
    boxes[:, 0], boxes[:, 1], boxes[:, 2], boxes[:, 3] = low[:, 0], high[:, 0], low[:, 1], high[:, 1]
    boxes[~inside] = (1, 0, 1, 0)  # empty: such a face is over a hole already
    return ~inside | boxes_hold_kernel(hole, boxes)


def without_faces_on_map(patch: vtkPolyData, expected, face_corners_of, reach: float = ON_MAP_M) -> vtkPolyData:
    """``patch`` without the faces :func:`faces_on_map` finds (the same object when there are none)."""
    return _with_faces(patch, ~faces_on_map(patch, expected, face_corners_of, reach))
