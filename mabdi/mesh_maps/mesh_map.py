"""MeshMap: a triangle mesh with named vertex and face layers, labels and cluster sets (seed 003).

The in-memory form of what :mod:`mabdi.io.hdf5` stores. Vertices are
float32 world coordinates (metres), faces are triangles (int64 indices in
memory, uint32 on disk). A **layer** is a per-vertex or per-face array of
one or more components (``roughness`` (N,), ``normals`` (N, 3), ``frame``
(M,) ...). A **label** names a set of faces: ``tree_1`` is the label ``1`` of
the group ``tree`` (the Mesh Tools convention). A **cluster set** is a
partition (or part of one) of the faces into numbered clusters.

``MeshMap.from_polydata`` accepts any vtkPolyData with polygons: quads and
larger polygons are triangulated (a fan per polygon; face layers are
repeated on each of its triangles), lines and vertices are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.errors import MabdiError

#: The vertex layer (and VTK point array) of a map's vertex colours: uint8 (N, 3) sRGB. The name is Mesh Tools'
#: (``/attributes/rgb_colors`` in its HDF5 maps), so a coloured map is read there as coloured.
COLOUR_LAYER = "rgb_colors"

LABEL_ARRAY_PREFIX = "label:"
#: Vertices closer than this (m) count as one for connectivity (labels, clusters, planning): a mabdi
#: map is a set of patches (frames, voxel-plane polygons) whose borders meet within millimetres
#: but share no vertices.
WELD = 0.005


def colour_point_array(rgb: np.ndarray):
    """A vtkUnsignedCharArray of (N, 3) uint8 RGB (a copy) named as a map's vertex colours
    (:data:`COLOUR_LAYER`, Mesh Tools' ``rgb_colors``)."""
    array = numpy_to_vtk(np.ascontiguousarray(rgb, dtype=np.uint8).reshape(-1, 3), deep=True)
    array.SetName(COLOUR_LAYER)
    return array


class MeshMapError(MabdiError, ValueError):
    """A mesh map whose parts do not fit together (a layer of the wrong length, a face id out of range)."""


def split_label(name: str) -> tuple[str, str]:
    """``"tree_1"`` -> ``("tree", "1")``; a name without ``_`` is its own group with label ``"0"``."""
    if "_" in name:
        group, label = name.rsplit("_", 1)
        if group and label:
            return group, label
    return name, "0"


@dataclass
class MeshMap:
    """A triangle mesh map; see the module docs. Use :meth:`validate` after building one by hand."""

    vertices: np.ndarray
    faces: np.ndarray
    vertex_layers: dict[str, np.ndarray] = field(default_factory=dict)
    face_layers: dict[str, np.ndarray] = field(default_factory=dict)
    labels: dict[str, np.ndarray] = field(default_factory=dict)
    clustersets: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    poses: np.ndarray | None = None
    intrinsics: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(np.asarray(self.vertices, dtype=np.float32).reshape(-1, 3))
        self.faces = np.ascontiguousarray(np.asarray(self.faces, dtype=np.int64).reshape(-1, 3))

    @property
    def number_of_vertices(self) -> int:
        return len(self.vertices)

    @property
    def number_of_faces(self) -> int:
        return len(self.faces)

    def validate(self) -> MeshMap:
        """Raise :class:`MeshMapError` naming the first part that does not fit; returns self."""
        n, m = self.number_of_vertices, self.number_of_faces
        if m and (self.faces.min() < 0 or self.faces.max() >= n):
            raise MeshMapError(f"faces refer to vertex {int(self.faces.max())} but the map has {n} vertices")
        for kind, layers, count in (("vertex", self.vertex_layers, n), ("face", self.face_layers, m)):
            for name, values in layers.items():
                if len(values) != count:
                    raise MeshMapError(f"{kind} layer {name!r} has {len(values)} values, the map has {count} {kind}s")
        for name, ids in self.labels.items():
            self._check_face_ids(f"label {name!r}", ids)
        for set_name, clusters in self.clustersets.items():
            for cluster, ids in clusters.items():
                self._check_face_ids(f"cluster {cluster!r} of cluster set {set_name!r}", ids)
        if self.poses is not None and (self.poses.ndim != 3 or self.poses.shape[1:] != (4, 4)):
            raise MeshMapError(f"poses must have shape (F, 4, 4), got {self.poses.shape}")
        return self

    def _check_face_ids(self, what: str, ids: np.ndarray) -> None:
        ids = np.asarray(ids)
        if ids.size and (ids.min() < 0 or ids.max() >= self.number_of_faces):
            raise MeshMapError(f"{what} refers to face {int(ids.max())} but the map has {self.number_of_faces} faces")

    # -- VTK ---------------------------------------------------------------
    @classmethod
    def from_polydata(cls, mesh: vtkPolyData) -> MeshMap:
        """A map of a vtkPolyData's polygons (triangulated), point data as vertex layers, cell data as face layers.

        Field-data arrays named ``label:<name>`` become labels.
        """
        if mesh.GetNumberOfPoints() == 0:
            return cls(np.zeros((0, 3)), np.zeros((0, 3)))
        vertices = vtk_to_numpy(mesh.GetPoints().GetData())
        polys = mesh.GetPolys()
        offsets = vtk_to_numpy(polys.GetOffsetsArray()).astype(np.int64)
        connectivity = vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64)
        sizes = np.diff(offsets)
        first_poly = mesh.GetNumberOfVerts() + mesh.GetNumberOfLines()  # VTK's cell order: verts, lines, polys, strips
        if (sizes < 3).any():
            raise MeshMapError("the mesh has polygons with fewer than 3 points")
        per = sizes - 2
        owner = np.repeat(np.arange(len(sizes)), per)
        k = np.arange(per.sum()) - np.repeat(np.cumsum(per) - per, per) + 1
        start = offsets[:-1][owner]
        faces = np.stack([connectivity[start], connectivity[start + k], connectivity[start + k + 1]], axis=1)
        vertex_layers = _arrays(mesh.GetPointData())
        cell_layers = _arrays(mesh.GetCellData())
        face_layers = {name: values[first_poly + owner] for name, values in cell_layers.items()}
        labels = {}
        field_data = mesh.GetFieldData()
        for i in range(field_data.GetNumberOfArrays()):
            array = field_data.GetAbstractArray(i)
            if array is not None and array.GetName() and array.GetName().startswith(LABEL_ARRAY_PREFIX):
                labels[array.GetName()[len(LABEL_ARRAY_PREFIX) :]] = vtk_to_numpy(array).astype(np.int64)
        return cls(vertices, faces, vertex_layers, face_layers, labels).validate()

    def to_polydata(self) -> vtkPolyData:
        """vtkPolyData of the triangles, layers as point and cell data, labels as ``label:<name>`` field data."""
        from mabdi.polydata import triangles_polydata

        mesh = triangles_polydata(self.vertices, self.faces, dtype=np.float32)
        for layers, data in ((self.vertex_layers, mesh.GetPointData()), (self.face_layers, mesh.GetCellData())):
            for name, values in layers.items():
                array = numpy_to_vtk(np.ascontiguousarray(values), deep=True)
                array.SetName(name)
                data.AddArray(array)
        for name, ids in self.labels.items():
            array = numpy_to_vtk(np.ascontiguousarray(ids, dtype=np.int64), deep=True)
            array.SetName(LABEL_ARRAY_PREFIX + name)
            mesh.GetFieldData().AddArray(array)
        return mesh

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners of the vertices (metres)."""
        if self.number_of_vertices == 0:
            return np.zeros(3), np.zeros(3)
        return self.vertices.min(axis=0).astype(np.float64), self.vertices.max(axis=0).astype(np.float64)


def unique_pairs(pairs: np.ndarray) -> np.ndarray:
    """Unique rows of (E, 2) non-negative int pairs, sorted; by one int64 key and a sort (numpy's
    unique(axis=0) and its hash-based unique are many times slower on millions of rows)."""
    pairs = np.asarray(pairs, dtype=np.int64)
    if len(pairs) == 0:
        return pairs.reshape(0, 2)
    base = int(pairs.max()) + 1
    keys = np.sort(pairs[:, 0] * base + pairs[:, 1])
    keys = keys[np.concatenate([[True], keys[1:] != keys[:-1]])]
    return np.stack([keys // base, keys % base], axis=1)


def welded_vertices(vertices: np.ndarray, tolerance: float = WELD) -> np.ndarray:
    """(N,) group id of each vertex: vertices closer than ``tolerance`` (m), transitively, share one (0..G-1)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(vertices)
    if tolerance <= 0 or n == 0:
        return np.arange(n)
    pairs = cKDTree(np.asarray(vertices, dtype=np.float64)).query_pairs(tolerance, output_type="ndarray")
    if len(pairs) == 0:
        return np.arange(n)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def welded_map(mesh_map: MeshMap, tolerance: float = WELD) -> tuple[MeshMap, np.ndarray]:
    """The map with vertices closer than ``tolerance`` merged (their mean position), and each old vertex's new id.

    Faces that collapse (two corners merged) are dropped; vertex layers are averaged over each
    group, except ``lethal``, which takes the maximum (a merged vertex is lethal if any was).
    Labels, face layers and cluster sets are not carried over (face ids change).
    """
    groups = welded_vertices(mesh_map.vertices, tolerance)
    count = int(groups.max()) + 1 if len(groups) else 0
    sizes = np.bincount(groups, minlength=count).astype(np.float64)
    vertices = np.stack(
        [np.bincount(groups, weights=mesh_map.vertices[:, k].astype(np.float64), minlength=count) / sizes for k in range(3)],
        axis=1,
    )
    faces = groups[mesh_map.faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])
    layers = {}
    for name, values in mesh_map.vertex_layers.items():
        values = np.asarray(values, dtype=np.float64)
        flat = values.reshape(len(values), -1)
        if name == "lethal":
            merged = np.zeros((count, flat.shape[1]))
            np.maximum.at(merged, groups, flat)
        else:
            merged = np.stack([np.bincount(groups, weights=flat[:, k], minlength=count) / sizes for k in range(flat.shape[1])], axis=1)
        layers[name] = merged.reshape((count,) + values.shape[1:]).astype(np.float32)
    return MeshMap(vertices, faces[keep], layers), groups


def _arrays(data) -> dict[str, np.ndarray]:
    out = {}
    for i in range(data.GetNumberOfArrays()):
        array = data.GetArray(i)
        if array is None or not array.GetName():
            continue
        out[array.GetName()] = vtk_to_numpy(array).copy()
    return out
