"""Distances from points to a triangle mesh.

* :func:`distances_to_mesh`: exact for points anywhere: those within
  :data:`NEAR` of the mesh as below, the others through VTK's
  vtkImplicitPolyDataDistance (one call for all of them).
* :func:`distances_within`: exact below a cap, for maps of millions of
  triangles, where VTK spends most of its time building normals and a
  locator for the whole mesh. The triangles are grouped by size
(their circumradius around the centroid), each group gets a KD-tree of its
centroids, and each point is tested exactly (closest point on a triangle,
Ericson's method) against its ``k`` nearest centroids. The result is exact:
a triangle outside those k has its centroid at least as far as the k-th one,
so it cannot be nearer than (k-th centroid distance - largest radius of the
group); points for which that bound does not settle it are tested against
every triangle of the group within reach (a ball query). Small groups are
tested exhaustively.

``cap`` bounds the work for points far from the mesh: distances beyond it are
reported as some value >= cap (e.g. for recall at 1-2 cm, cap = 5 cm).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkDoubleArray
from vtkmodules.vtkCommonDataModel import vtkPolyData
from vtkmodules.vtkFiltersCore import vtkImplicitPolyDataDistance

from mabdi.polydata import polydata_arrays

#: Upper edges of the triangle-radius groups (m): doubling from 2.5 mm, so each group's bound is tight.
RADIUS_GROUPS = (*(0.0025 * 2.0**i for i in range(10)), np.inf)
#: Groups at most this large are tested exhaustively.
EXHAUSTIVE = 64
#: Nearest centroids tested per point in a KD-tree group.
NEAREST = 16
_PAIRS_PER_CHUNK = 2_000_000
#: Distances (m) :func:`distances_to_mesh` takes from the KD-trees; beyond, from VTK's locator.
NEAR = 0.05


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest point to p on triangle (a, b, c), for broadcastable (..., 3) arrays (Ericson, RTCD 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("...i,...i->...", ab, ap)
    d2 = np.einsum("...i,...i->...", ac, ap)
    bp = p - b
    d3 = np.einsum("...i,...i->...", ab, bp)
    d4 = np.einsum("...i,...i->...", ac, bp)
    cp = p - c
    d5 = np.einsum("...i,...i->...", ab, cp)
    d6 = np.einsum("...i,...i->...", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denominator = va + vb + vc
        v_face = np.where(denominator != 0, vb / denominator, 0.0)
        w_face = np.where(denominator != 0, vc / denominator, 0.0)
        t_ab = np.clip(np.where(d1 - d3 != 0, d1 / (d1 - d3), 0.0), 0.0, 1.0)
        t_ac = np.clip(np.where(d2 - d6 != 0, d2 / (d2 - d6), 0.0), 0.0, 1.0)
        t_bc = np.clip(np.where((d4 - d3) + (d5 - d6) != 0, (d4 - d3) / ((d4 - d3) + (d5 - d6)), 0.0), 0.0, 1.0)
    result = a + ab * v_face[..., None] + ac * w_face[..., None]  # inside the face
    on_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    result = np.where(on_bc[..., None], b + (c - b) * t_bc[..., None], result)
    on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    result = np.where(on_ac[..., None], a + ac * t_ac[..., None], result)
    on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    result = np.where(on_ab[..., None], a + ab * t_ab[..., None], result)
    result = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, result)
    result = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, result)
    result = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, result)
    return result


def _pair_distances(points: np.ndarray, corners: np.ndarray, point_index: np.ndarray, triangle_index: np.ndarray) -> np.ndarray:
    closest = closest_points_on_triangles(
        points[point_index], corners[triangle_index, 0], corners[triangle_index, 1], corners[triangle_index, 2]
    )
    return np.linalg.norm(points[point_index] - closest, axis=-1)


def _exhaustive(points: np.ndarray, corners: np.ndarray, radii: np.ndarray, best: np.ndarray, cap: float) -> None:
    """Test every (point, triangle) pair whose bound |p - centroid| - radius is below min(best, cap)."""
    centroids = corners.mean(axis=1)
    n = len(corners)
    step = max(1, _PAIRS_PER_CHUNK // n)
    for start in range(0, len(points), step):
        rows = np.arange(start, min(start + step, len(points)))
        bound = np.linalg.norm(points[rows, None, :] - centroids[None], axis=2) - radii[None]
        pi, ti = np.nonzero(bound < np.minimum(best[rows], cap)[:, None])
        if len(pi) == 0:
            continue
        d = _pair_distances(points, corners, rows[pi], ti)
        np.minimum.at(best, rows[pi], d)


def _with_tree(points: np.ndarray, corners: np.ndarray, radius: float, best: np.ndarray, cap: float) -> None:
    """k nearest centroids per point (only those within cap + radius), then a ball query where needed."""
    centroids = corners.mean(axis=1)
    tree = cKDTree(centroids)
    k = min(NEAREST, len(corners))
    reach_limit = cap + radius
    step = max(1, _PAIRS_PER_CHUNK // k)
    for start in range(0, len(points), step):
        rows = np.arange(start, min(start + step, len(points)))
        centroid_distance, nearest = tree.query(points[rows], k=k, distance_upper_bound=reach_limit)
        found = np.isfinite(centroid_distance)
        if found.any():
            pi, slot = np.nonzero(found)
            d = _pair_distances(points, corners, rows[pi], nearest[pi, slot])
            np.minimum.at(best, rows[pi], d)
        # a triangle beyond the k nearest centroids is at least (k-th distance - radius) away
        unsure = rows[centroid_distance[:, -1] - radius < np.minimum(best[rows], cap)]
        if len(unsure) == 0:
            continue
        reach = np.minimum(best[unsure], cap) + radius
        lists = tree.query_ball_point(points[unsure], r=reach)
        lengths = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
        if lengths.sum() == 0:
            continue
        candidates = np.concatenate([np.asarray(x, dtype=np.int64) for x in lists if len(x)])
        owners = np.repeat(unsure, lengths)
        d = _pair_distances(points, corners, owners, candidates)
        np.minimum.at(best, owners, d)


def distances_within(points, mesh: vtkPolyData, cap: float) -> np.ndarray:
    """Distance (m) from each of (N, 3) ``points`` to ``mesh``, exact below ``cap``; beyond it some value >= cap.

    Polygons are triangulated first; an empty mesh gives +inf everywhere.
    """
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    best = np.full(len(points), np.inf)
    if len(points) == 0 or mesh.GetNumberOfCells() == 0:
        return best
    if not np.isfinite(cap) or cap <= 0:
        raise ValueError(f"distances_within needs a finite positive cap, got {cap}")
    vertices, triangles = polydata_arrays(mesh)
    corners = vertices[triangles]
    radii = np.linalg.norm(corners - corners.mean(axis=1, keepdims=True), axis=2).max(axis=1)
    group = np.searchsorted(np.asarray(RADIUS_GROUPS), radii)
    for g in np.unique(group):
        members = group == g
        if members.sum() <= EXHAUSTIVE:
            _exhaustive(points, corners[members], radii[members], best, cap)
        else:
            _with_tree(points, corners[members], float(radii[members].max()), best, cap)
    return best


def distances_to_mesh(points, mesh: vtkPolyData) -> np.ndarray:
    """Exact unsigned distance (m) from each of (N, 3) ``points`` to ``mesh``'s surface.

    :func:`distances_within` up to :data:`NEAR` (a map's samples against its ground truth lie mostly within
    millimetres of it, where it is faster than VTK's locator), VTK's vtkImplicitPolyDataDistance for the
    points beyond (exact at any distance, without the ball queries a far point would need). An empty mesh gives
    +inf everywhere.
    """
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    if mesh.GetNumberOfCells() == 0:
        return np.full(len(points), np.inf)
    if len(points) == 0:
        return np.zeros(0)
    distances = distances_within(points, mesh, cap=NEAR)
    far = distances >= NEAR
    if far.any():
        distances[far] = _vtk_distances(points[far], mesh)
    return distances


def _vtk_distances(points: np.ndarray, mesh: vtkPolyData) -> np.ndarray:
    """Exact unsigned distances of (N, 3) float64 ``points`` to a non-empty ``mesh`` (VTK, one call)."""
    distance = vtkImplicitPolyDataDistance()
    distance.SetInput(mesh)
    values = vtkDoubleArray()
    distance.FunctionValue(numpy_to_vtk(points, deep=True), values)
    return np.abs(vtk_to_numpy(values))
