"""vtkPolyData <-> numpy helpers shared by the sources, filters and runner."""

from __future__ import annotations

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import (
    vtkCellArray,
    vtkCompositeDataSet,
    vtkDataObject,
    vtkDataObjectTreeIterator,
    vtkMultiBlockDataSet,
    vtkPolyData,
)
from vtkmodules.vtkFiltersCore import vtkTriangleFilter

from mabdi.camera import boxes_outside
from mabdi.polydata_kernels import triangle_normals_kernel

#: Cell data the expected-image renderer draws each map face in: its 24-bit code as uint8 RGB (red = low byte), on
#: the renderer's own copy of a block (:mod:`mabdi.face_identity`), never on the map.
FACE_RGB_ARRAY = "face_rgb"


def _cell_array(offsets: np.ndarray, connectivity: np.ndarray) -> vtkCellArray:
    cells = vtkCellArray()
    cells.SetData(
        numpy_to_vtkIdTypeArray(np.ascontiguousarray(offsets, dtype=np.int64), deep=True),
        numpy_to_vtkIdTypeArray(np.ascontiguousarray(connectivity, dtype=np.int64).ravel(), deep=True),
    )
    return cells


def triangles_polydata(points: np.ndarray, triangles: np.ndarray, dtype=np.float64) -> vtkPolyData:
    """A vtkPolyData of triangles from (N, 3) points (stored as ``dtype``) and (M, 3) vertex indices."""
    mesh = vtkPolyData()
    vtk_points = vtkPoints()
    vtk_points.SetData(numpy_to_vtk(np.ascontiguousarray(points, dtype=dtype).reshape(-1, 3), deep=True))
    mesh.SetPoints(vtk_points)
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    mesh.SetPolys(_cell_array(np.arange(0, 3 * len(triangles) + 1, 3), triangles))
    return mesh


def polyline(points: np.ndarray) -> vtkPolyData:
    """A vtkPolyData with one polyline through ``points`` (N, 3)."""
    mesh = vtkPolyData()
    vtk_points = vtkPoints()
    vtk_points.SetData(numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float64), deep=True))
    mesh.SetPoints(vtk_points)
    n = len(points)
    mesh.SetLines(_cell_array(np.array([0, n]), np.arange(n)))
    return mesh


def triangulated(mesh: vtkPolyData) -> vtkPolyData:
    """``mesh`` itself when it holds triangles only, else its polygons as triangles (lines and vertices dropped;
    cell data carried to each triangle of the cell it came from)."""
    if (
        mesh.GetNumberOfStrips()
        or mesh.GetNumberOfLines()
        or mesh.GetNumberOfVerts()
        or mesh.GetPolys().GetMaxCellSize() != 3
    ):
        tri = vtkTriangleFilter()
        tri.SetInputData(mesh)
        tri.PassLinesOff()
        tri.PassVertsOff()
        tri.Update()
        return tri.GetOutput()
    return mesh


def polydata_arrays(mesh: vtkPolyData) -> tuple[np.ndarray, np.ndarray]:
    """(points float64 (N, 3), triangles int64 (M, 3)) of a mesh, triangulated first if needed."""
    mesh = triangulated(mesh)
    points = vtk_to_numpy(mesh.GetPoints().GetData()).astype(np.float64)
    connectivity = vtk_to_numpy(mesh.GetPolys().GetConnectivityArray()).astype(np.int64)
    return points, connectivity.reshape(-1, 3)


def triangle_frames(mesh: vtkPolyData) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(corner, edge1, edge2, cell) of the triangles of ``mesh``'s polygons, each polygon fanned from its first
    vertex (convex polygons): triangle i is corner[i] + a edge1[i] + b edge2[i] (float64 (T, 3) each, metres)
    and came from polygon cell[i] (int64 (T,)), so a hit names the mesh's own cell."""
    polys = mesh.GetPolys()
    if mesh.GetNumberOfPoints() == 0 or polys.GetNumberOfCells() == 0:
        empty = np.zeros((0, 3))
        return empty, empty, empty, np.zeros(0, dtype=np.int64)
    points = vtk_to_numpy(mesh.GetPoints().GetData()).astype(np.float64)
    offsets = vtk_to_numpy(polys.GetOffsetsArray()).astype(np.int64)
    connectivity = vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64)
    fans = np.maximum(np.diff(offsets) - 2, 0)  # triangles per polygon
    cell = np.repeat(np.arange(len(fans)), fans)
    step = np.arange(len(cell)) - np.repeat(np.cumsum(fans) - fans, fans)  # 0 .. fans - 1 within each polygon
    first = offsets[cell]
    corner = points[connectivity[first]]
    edge1 = points[connectivity[first + step + 1]] - corner
    edge2 = points[connectivity[first + step + 2]] - corner
    return corner, edge1, edge2, cell


def _all_triangles(offsets: np.ndarray) -> bool:
    """Whether polygon ``offsets`` (M + 1,) describe triangles only (every polygon three corners)."""
    return bool(len(offsets) < 2 or (offsets[0] == 0 and np.all(np.diff(offsets) == 3)))


def extract_polys(surface: vtkPolyData, cell_ids: np.ndarray) -> vtkPolyData:
    """A new vtkPolyData with the polygons ``cell_ids`` of ``surface`` (polygons only), its
    points compacted and its point and cell arrays carried over."""
    polys = surface.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray())
    connectivity = vtk_to_numpy(polys.GetConnectivityArray())
    cell_ids = np.asarray(cell_ids, dtype=np.int64)
    if len(connectivity) == 3 * (len(offsets) - 1) and _all_triangles(offsets):
        # triangles only (the map's patches): the corners gathered as rows, no ragged gather
        new_offsets = np.arange(0, 3 * len(cell_ids) + 1, 3, dtype=np.int64)
        old_points = connectivity.reshape(-1, 3)[cell_ids].ravel().astype(np.int64)
    else:
        offsets = offsets.astype(np.int64)
        connectivity = connectivity.astype(np.int64)
        sizes = offsets[cell_ids + 1] - offsets[cell_ids]
        new_offsets = np.concatenate([[0], np.cumsum(sizes)])
        gather = np.repeat(offsets[cell_ids] - new_offsets[:-1], sizes) + np.arange(new_offsets[-1])
        old_points = connectivity[gather]
    used = np.zeros(surface.GetNumberOfPoints(), dtype=bool)
    used[old_points] = True
    point_ids = np.flatnonzero(used)
    renumber = np.cumsum(used) - 1
    # every array below is made here (a gather), so VTK takes it without a second copy (deep=False keeps it alive)
    patch = vtkPolyData()
    points = vtkPoints()
    points.SetData(numpy_to_vtk(vtk_to_numpy(surface.GetPoints().GetData())[point_ids], deep=False))
    patch.SetPoints(points)
    cells = vtkCellArray()
    cells.SetData(numpy_to_vtkIdTypeArray(new_offsets, deep=False), numpy_to_vtkIdTypeArray(renumber[old_points], deep=False))
    patch.SetPolys(cells)
    for source, target, ids in (
        (surface.GetPointData(), patch.GetPointData(), point_ids),
        (surface.GetCellData(), patch.GetCellData(), cell_ids),
    ):
        for i in range(source.GetNumberOfArrays()):
            array = source.GetArray(i)
            if array is None:
                continue
            values = numpy_to_vtk(np.ascontiguousarray(vtk_to_numpy(array)[ids]), deep=False)
            values.SetName(array.GetName())
            target.AddArray(values)
    return patch


def split_polys(surface: vtkPolyData, labels) -> list[tuple[int, vtkPolyData]]:
    """The polygons of ``surface`` grouped by ``labels`` (one integer per cell): ``(label, patch)`` for each label,
    ascending, where ``patch`` is :func:`extract_polys` of the cells of that label in their order. One pass over
    the surface however many groups there are (:func:`extract_polys` per group walks the whole surface each time)."""
    labels = np.asarray(labels)
    if labels.shape != (surface.GetNumberOfCells(),):
        raise ValueError(f"split_polys: {labels.shape} labels for {surface.GetNumberOfCells()} cells")
    if not len(labels):
        return []
    polys = surface.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray()).astype(np.int64)
    connectivity = vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64)
    order = np.argsort(labels, kind="stable")
    sorted_labels = labels[order]
    cell_starts = np.flatnonzero(np.r_[True, sorted_labels[1:] != sorted_labels[:-1]])
    cell_bounds = np.r_[cell_starts, len(order)]
    group_of_cell = np.repeat(np.arange(len(cell_starts)), np.diff(cell_bounds))
    sizes = offsets[order + 1] - offsets[order]
    new_offsets = np.concatenate([[0], np.cumsum(sizes)])
    gather = np.repeat(offsets[order] - new_offsets[:-1], sizes) + np.arange(new_offsets[-1])
    corner_group = np.repeat(group_of_cell, sizes)
    n_points = surface.GetNumberOfPoints()
    # each group's points, ascending within the group (as extract_polys keeps them), and each corner's place there
    pairs, corner_pair = np.unique(corner_group * n_points + connectivity[gather], return_inverse=True)
    pair_group, point_ids = np.divmod(pairs, n_points)
    point_bounds = np.searchsorted(pair_group, np.arange(len(cell_starts) + 1))
    local = corner_pair.ravel() - point_bounds[corner_group]
    points = vtk_to_numpy(surface.GetPoints().GetData())[point_ids]
    arrays = []  # (target: 0 point data / 1 cell data, name, values in group order)
    for target, (source, ids) in enumerate(((surface.GetPointData(), point_ids), (surface.GetCellData(), order))):
        for i in range(source.GetNumberOfArrays()):
            array = source.GetArray(i)
            if array is not None:
                arrays.append((target, array.GetName(), vtk_to_numpy(array)[ids]))
    out = []
    for g in range(len(cell_starts)):
        c0, c1 = cell_bounds[g], cell_bounds[g + 1]
        p0, p1 = point_bounds[g], point_bounds[g + 1]
        k0, k1 = new_offsets[c0], new_offsets[c1]
        patch = vtkPolyData()
        vtk_points = vtkPoints()
        vtk_points.SetData(numpy_to_vtk(np.ascontiguousarray(points[p0:p1]), deep=True))
        patch.SetPoints(vtk_points)
        patch.SetPolys(_cell_array(new_offsets[c0 : c1 + 1] - k0, local[k0:k1]))
        data = (patch.GetPointData(), patch.GetCellData())
        for target, name, values in arrays:
            lo, hi = (p0, p1) if target == 0 else (c0, c1)
            vtk_values = numpy_to_vtk(np.ascontiguousarray(values[lo:hi]), deep=True)
            vtk_values.SetName(name)
            data[target].AddArray(vtk_values)
        out.append((sorted_labels[c0].item(), patch))
    return out


def polydata_to_state(mesh: vtkPolyData) -> dict:
    """A polygonal vtkPolyData as plain numpy arrays (points, polygon offsets and connectivity, point and
    cell arrays by name), for checkpoints; :func:`polydata_from_state` rebuilds it exactly."""
    points = mesh.GetPoints()
    polys = mesh.GetPolys()
    state = {
        "points": vtk_to_numpy(points.GetData()).copy() if points is not None else np.zeros((0, 3), np.float32),
        "offsets": vtk_to_numpy(polys.GetOffsetsArray()).copy(),
        "connectivity": vtk_to_numpy(polys.GetConnectivityArray()).copy(),
        "point_data": {},
        "cell_data": {},
        "attributes": {"point_data": {}, "cell_data": {}},  # name -> attribute type (Normals, Scalars, ...)
    }
    for key, data in (("point_data", mesh.GetPointData()), ("cell_data", mesh.GetCellData())):
        for i in range(data.GetNumberOfArrays()):
            array = data.GetArray(i)
            if array is not None and array.GetName():
                state[key][array.GetName()] = vtk_to_numpy(array).copy()
                role = data.IsArrayAnAttribute(i)
                if role >= 0:
                    state["attributes"][key][array.GetName()] = role
    return state


def polydata_from_state(state: dict) -> vtkPolyData:
    """The vtkPolyData of :func:`polydata_to_state` (same dtypes, same order)."""
    mesh = vtkPolyData()
    points = vtkPoints()
    points.SetData(numpy_to_vtk(np.ascontiguousarray(state["points"]), deep=True))
    mesh.SetPoints(points)
    mesh.SetPolys(_cell_array(state["offsets"], state["connectivity"]))
    for key, data in (("point_data", mesh.GetPointData()), ("cell_data", mesh.GetCellData())):
        for name, values in state[key].items():
            array = numpy_to_vtk(np.ascontiguousarray(values), deep=True)
            array.SetName(name)
            data.AddArray(array)
        for name, role in state["attributes"][key].items():
            data.SetActiveAttribute(name, role)
    return mesh


def triangle_normals(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unit normals (M, 3), areas (M,)) of triangles ``triangles`` (M, 3) into ``points`` (N, 3), right-hand rule.

    The one face-normal rule of the package (the map's faces, cost layers, labels, picking, surface sampling).
    Computed in the points' dtype (float32 points give float32 normals); a degenerate triangle has normal 0 and
    area 0.
    """
    points = np.asarray(points)
    if points.dtype in (np.float32, np.float64) and points.ndim == 2 and len(triangles):
        return triangle_normals_kernel(points, np.asarray(triangles))
    a = points[triangles[:, 0]]
    cross = np.cross(points[triangles[:, 1]] - a, points[triangles[:, 2]] - a)
    length = np.linalg.norm(cross, axis=1)
    return cross / np.where(length > 0, length, length.dtype.type(1.0))[:, None], 0.5 * length


def vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(N, 3) float64 unit vertex normals, the area-weighted mean of the normals of the triangles around each vertex
    (0 where a vertex has none)."""
    normals, areas = triangle_normals(np.asarray(points, dtype=np.float64), triangles)
    weighted = normals * areas[:, None]
    out = np.zeros((len(points), 3))
    for corner in range(3):
        for axis in range(3):
            out[:, axis] += np.bincount(triangles[:, corner], weights=weighted[:, axis], minlength=len(points))
    length = np.linalg.norm(out, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(length > 0, out / length, 0.0)


def polydata_area(mesh: vtkPolyData) -> float:
    """Total area (m^2) of a mesh's polygons (triangulated)."""
    if mesh.GetNumberOfCells() == 0:
        return 0.0
    points, triangles = polydata_arrays(mesh)
    corners = points[triangles]
    return float(0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum())


def transformed_polydata(mesh: vtkPolyData, matrix: np.ndarray) -> vtkPolyData:
    """A copy of ``mesh`` moved by the rigid 4x4 ``matrix``: its points, and its 3-component point and cell
    arrays whose names say they are normals, turned by the rotation (the rest shared with ``mesh``)."""
    matrix = np.asarray(matrix, dtype=np.float64)
    out = vtkPolyData()
    out.ShallowCopy(mesh)
    if mesh.GetNumberOfPoints() == 0:
        return out
    points = vtk_to_numpy(mesh.GetPoints().GetData())
    moved = (points.astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]).astype(points.dtype)
    vtk_points = vtkPoints()
    vtk_points.SetData(numpy_to_vtk(moved, deep=True))
    out.SetPoints(vtk_points)
    for data, source in ((out.GetPointData(), mesh.GetPointData()), (out.GetCellData(), mesh.GetCellData())):
        for index in range(source.GetNumberOfArrays()):
            array = source.GetArray(index)
            if array is None or array.GetNumberOfComponents() != 3 or "normal" not in (array.GetName() or "").lower():
                continue
            values = vtk_to_numpy(array)
            turned = numpy_to_vtk((values.astype(np.float64) @ matrix[:3, :3].T).astype(values.dtype), deep=True)
            turned.SetName(array.GetName())
            data.AddArray(turned)
    return out


def polydata_leaves(data) -> list[vtkPolyData]:
    """The vtkPolyData of ``data``: itself, or the non-empty leaves of a composite dataset."""
    return [leaf for _, leaf in named_leaves(data)]


def named_leaves(data, planes: np.ndarray | None = None) -> list[tuple[str, vtkPolyData]]:
    """(name, polydata) of the non-empty leaves of ``data`` (a vtkPolyData is one leaf named ``""``).

    A leaf's name is its block's metadata NAME (the world map's patch key), else its path of block numbers.
    With ``planes`` (:func:`mabdi.camera.frustum_planes`), a block whose metadata holds a BOUNDING_BOX wholly
    outside them is skipped with everything under it (the world map's chunks carry theirs).
    """
    if isinstance(data, vtkPolyData):
        return [("", data)] if data.GetNumberOfCells() else []
    if not isinstance(data, vtkCompositeDataSet):
        raise TypeError(
            "expected a vtkPolyData or a composite dataset of polydata, "
            f"got {data.GetClassName() if data is not None else None}"
        )
    leaves: list[tuple[str, vtkPolyData]] = []
    _collect_leaves(data, "", planes, leaves)
    return leaves


def _collect_leaves(tree, prefix: str, planes, leaves: list) -> None:
    if not isinstance(tree, vtkMultiBlockDataSet):  # other composites: every leaf, by iterator
        iterator = vtkDataObjectTreeIterator()
        iterator.SetDataSet(tree)
        iterator.SkipEmptyNodesOn()
        iterator.VisitOnlyLeavesOn()
        iterator.InitTraversal()
        while not iterator.IsDoneWithTraversal():
            leaf = iterator.GetCurrentDataObject()
            if not isinstance(leaf, vtkPolyData):
                raise TypeError(f"composite dataset has a {leaf.GetClassName()} block; only vtkPolyData can be rendered")
            if leaf.GetNumberOfCells():
                leaves.append((f"{prefix}{iterator.GetCurrentFlatIndex()}", leaf))
            iterator.GoToNextItem()
        return
    for index in range(tree.GetNumberOfBlocks()):
        block = tree.GetBlock(index)
        if block is None:
            continue
        meta = tree.GetMetaData(index) if tree.HasMetaData(index) else None
        name = meta.Get(vtkCompositeDataSet.NAME()) if meta is not None and meta.Has(vtkCompositeDataSet.NAME()) else None
        if planes is not None and meta is not None and meta.Has(vtkDataObject.BOUNDING_BOX()):
            if boxes_outside(meta.Get(vtkDataObject.BOUNDING_BOX()), planes)[0]:
                continue
        if isinstance(block, vtkPolyData):
            if block.GetNumberOfCells():
                leaves.append((name if name is not None else f"{prefix}{index}", block))
        elif isinstance(block, vtkCompositeDataSet):
            _collect_leaves(block, f"{prefix}{index}/", planes, leaves)
        else:
            raise TypeError(f"composite dataset has a {block.GetClassName()} block; only vtkPolyData can be rendered")


def segment_crossings(origins, directions, reach, a, b, c, inside: float = 0.0) -> np.ndarray:
    """Whether the segments ``origins`` + t ``directions`` (unit), |t| <= ``reach`` (m), cross the triangles
    (``a``, ``b``, ``c``) (Moller-Trumbore); all arrays broadcast together, (..., 3) points and (...) reaches.
    A crossing lies ``inside`` or more into the triangle in barycentric terms (0: its edges count; a small
    positive value: a point on the edge two abutting triangles share crosses neither). NaN corners cross nothing."""
    e1, e2 = b - a, c - a
    directions = np.broadcast_to(directions, np.broadcast_shapes(np.shape(directions), e2.shape))
    p = np.cross(directions, e2)
    det = np.einsum("...i,...i->...", e1, p)
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = 1.0 / det
        s = origins - a
        u = np.einsum("...i,...i->...", s, p) * inv
        q = np.cross(s, e1)
        v = np.einsum("...i,...i->...", directions, q) * inv
        t = np.einsum("...i,...i->...", e2, q) * inv
        return (np.abs(det) > 1e-12) & (u >= inside) & (v >= inside) & (u + v <= 1.0 - inside) & (np.abs(t) <= reach)
