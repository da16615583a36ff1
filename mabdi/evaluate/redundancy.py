"""Redundancy: how much of a map is stacked layers of the same surface (what MABDI exists to avoid).

For each area-weighted sample of the map, a segment is cast along its
triangle's normal both ways, p - delta n .. p + delta n; the sample is
redundant when the segment crosses a triangle created at a *different* frame
(cell data ``frame``). The redundancy is the share of samples that are.
delta = max(1 cm, 3 sigma(z)) with z the sample's depth from the pose of the
frame that created it and sigma the run's noise model (1 cm when unknown).

Neighbouring patches that only meet at a seam do not count: a segment along
the normal of one patch does not cross a coplanar patch beside it.

Vectorised: the triangles of each frame get a KD-tree of their centroids;
every sample of another frame that lies in or next to a voxel holding one of
that frame's triangles (voxels of max(delta, 5 cm)) takes the
``CANDIDATES`` nearest of them, and the segment-triangle
test (Moller-Trumbore) runs on all pairs at once, in chunks. Samples found
redundant are not tested again.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.evaluate.sampling import SurfaceSamples
from mabdi.polydata import polydata_arrays, segment_crossings

#: Smallest delta (m) of the overlap test.
DELTA_MIN = 0.01
#: Nearest triangle centroids of one frame tested per sample.
CANDIDATES = 8
_CHUNK = 8192


def _voxel_keys(cells: np.ndarray) -> np.ndarray:
    """One int64 key per integer voxel coordinate (21 bits per axis)."""
    cells = cells + (1 << 20)
    return (cells[:, 0] << 42) | (cells[:, 1] << 21) | cells[:, 2]


def redundancy(mesh: vtkPolyData, samples: SurfaceSamples, delta) -> float | None:
    """Share of ``samples`` (taken on ``mesh``) whose normal segment of half-length ``delta`` (m;
    scalar or per sample) crosses a triangle of another frame.

    None for a mesh without cell data ``frame`` (a fused surface such as a
    TSDF's, where the question does not arise); 0 for an empty sample set.
    """
    frames_array = mesh.GetCellData().GetArray("frame")
    if frames_array is None:
        return None
    if len(samples) == 0:
        return 0.0
    points, triangles = polydata_arrays(mesh)
    if len(triangles) != mesh.GetNumberOfCells():
        raise ValueError("redundancy needs a triangle mesh (one cell per triangle, frame per cell)")
    frames = vtk_to_numpy(frames_array).astype(np.int64)
    if np.unique(frames).size < 2:
        return 0.0
    corners = points[triangles]  # (M, 3, 3)
    centroids = corners.mean(axis=1)
    reach = np.broadcast_to(np.asarray(delta, dtype=np.float64), (len(samples),))
    sample_frames = frames[samples.faces]
    redundant = np.zeros(len(samples), dtype=bool)
    order = np.argsort(frames, kind="stable")
    bounds = np.flatnonzero(np.diff(frames[order])) + 1
    voxel = max(float(reach.max()), 0.05) + float(np.linalg.norm(corners - centroids[:, None], axis=2).max())
    sample_voxels = _voxel_keys(np.floor(samples.points / voxel).astype(np.int64))
    face_voxels = np.floor(centroids / voxel).astype(np.int64)
    neighbourhood = np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), -1).reshape(-1, 3)
    for faces in np.split(order, bounds):
        frame = frames[faces[0]]
        occupied = np.unique(face_voxels[faces], axis=0)
        near_voxels = _voxel_keys((occupied[:, None, :] + neighbourhood[None]).reshape(-1, 3))
        near = ~redundant & (sample_frames != frame) & np.isin(sample_voxels, near_voxels)
        todo = np.flatnonzero(near)
        if len(todo) == 0:
            continue
        tree = cKDTree(centroids[faces])
        k = min(CANDIDATES, len(faces))
        for start in range(0, len(todo), _CHUNK):
            chunk = todo[start : start + _CHUNK]
            _, nearest = tree.query(samples.points[chunk], k=k)
            candidates = faces[nearest.reshape(len(chunk), k)]
            a, b, c = (corners[candidates, j] for j in range(3))
            # strict on the edges: a point on the edge abutting triangles share is not a crossing
            origins, directions = samples.points[chunk, None, :], samples.normals[chunk, None, :]
            hits = segment_crossings(origins, directions, reach[chunk, None], a, b, c, inside=1e-9)
            redundant[chunk] |= hits.any(axis=1)
    return float(redundant.mean())
