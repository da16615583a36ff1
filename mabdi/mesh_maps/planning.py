"""Path planning on a mesh map: Dijkstra over the vertex graph and a fast-marching wave front (seed 003).

Both planners read the map's vertex layers ``lethal`` (vertices a robot must
not enter: excluded) and ``cost`` (in [0, 1], from
:mod:`mabdi.mesh_maps.layers`); a map without them is all free and costs nothing.
The local cost of moving is the slowness ``1 + cost_weight * cost`` (per
metre), ``cost_weight`` = 4 by default.

**Dijkstra** (``scipy.sparse.csgraph.dijkstra``): edges of the triangles,
weighted by length times the mean slowness of their two ends; the path runs
along mesh edges, so on a regular triangulation it can be up to about 8%
longer than the true shortest path (edges only go in a few directions).

**Fast marching** (``fmm``): the arrival time T of a wave front from the
start, solving |grad T| = slowness on the triangles. The update is the
first-order triangle update (Kimmel and Sethian): a vertex C gets, from each
triangle (A, B, C) with A and B reached, the time of the planar front that
passes A at T_A and B at T_B, used only when the front comes from inside the
triangle (its direction at C lies between CA and CB, and T_C >= T_A, T_B);
otherwise, as for obtuse triangles where that fails, the triangle gives the
edge updates T_A + |CA| s and T_B + |CB| s. The front advances one vertex
at a time from a heap (Sethian's fast marching, compiled with numba:
:mod:`mabdi.mesh_maps.fast_marching`; a test checks it against the fast iterative
method in numpy, kept with the tests). T is stored as the vertex layer
``arrival_time``. The path follows
-grad T from the goal back to the start, in steps of half the mean edge
length, each step projected back onto the mesh; it cuts across triangles,
so its length approaches the true geodesic's.

:func:`plan` returns a :class:`PlanResult`; an unreachable goal gives
``reachable = False`` and no path.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from mabdi.errors import MabdiError
from mabdi.mesh_maps.fast_marching import fast_marching
from mabdi.mesh_maps.mesh_map import WELD, MeshMap, unique_pairs, welded_map

PLANNERS = ("dijkstra", "fmm")


class PlanningError(MabdiError, ValueError):
    """A planning request that cannot be answered (a start on a lethal vertex, an empty map)."""


@dataclass
class PlanResult:
    """A plan: the path (K, 3) world points, its length (m) and cost (integral of the slowness), reachability."""

    planner: str
    reachable: bool
    path: np.ndarray
    length: float
    cost: float
    start_vertex: int
    goal_vertex: int


def _slowness(mesh_map: MeshMap, cost_weight: float) -> tuple[np.ndarray, np.ndarray]:
    n = mesh_map.number_of_vertices
    cost = mesh_map.vertex_layers.get("cost")
    slowness = np.ones(n) if cost is None else 1.0 + cost_weight * np.asarray(cost, dtype=np.float64).reshape(n)
    lethal = mesh_map.vertex_layers.get("lethal")
    blocked = np.zeros(n, dtype=bool) if lethal is None else np.asarray(lethal).reshape(n) > 0
    return slowness, blocked


def _nearest_free(mesh_map: MeshMap, points, blocked: np.ndarray, max_snap: float) -> list[int]:
    free = np.flatnonzero(~blocked)
    if len(free) == 0:
        raise PlanningError("every vertex of the map is lethal")
    # a tree over the free vertices near the requests only: building one over a million costs 0.3 s
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    candidates = free[np.linalg.norm(mesh_map.vertices[free, None, :] - points[None].astype(np.float32), axis=2).min(axis=1) <= max_snap]
    if len(candidates) == 0:
        candidates = free
    distances, indices = cKDTree(mesh_map.vertices[candidates]).query(points)
    out = []
    for what, point, distance, index in zip(("start", "goal"), points, distances, indices, strict=True):
        out.append(_snapped(what, point, float(distance), int(candidates[index]), max_snap))
    return out


def _snapped(what: str, point: np.ndarray, distance: float, vertex: int, max_snap: float) -> int:
    if distance > max_snap:
        raise PlanningError(
            f"the {what} {tuple(round(float(v), 3) for v in point)} is {distance:.2f} m from the nearest free "
            f"vertex of the map (more than {max_snap} m): not on the map, or on a lethal part of it"
        )
    return vertex


def edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) unique undirected vertex pairs of the triangles."""
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    pairs.sort(axis=1)
    return unique_pairs(pairs)


def plan(
    mesh_map: MeshMap,
    start,
    goal,
    planner: str = "fmm",
    cost_weight: float = 4.0,
    weld: float = WELD,
    max_snap: float = 0.25,
) -> PlanResult:
    """Plan from the free vertex nearest ``start`` to the one nearest ``goal`` (points in metres).

    A start or goal farther than ``max_snap`` (m) from every free vertex is a :class:`PlanningError`.

    The map is first welded (vertices closer than ``weld`` merged, :func:`welded_map`), so the
    patches of a mabdi map connect; vertex ids in the result refer to the welded map, and with
    ``fmm`` the arrival times are stored on ``mesh_map`` as the vertex layer ``arrival_time``.
    """
    if planner not in PLANNERS:
        raise PlanningError(f"unknown planner {planner!r} (known: {', '.join(PLANNERS)})")
    if mesh_map.number_of_faces == 0:
        raise PlanningError("the map has no faces to plan on")
    original = mesh_map
    if weld > 0:
        mesh_map, groups = welded_map(mesh_map, weld)
    slowness, blocked = _slowness(mesh_map, cost_weight)
    s, g = _nearest_free(mesh_map, [start, goal], blocked, max_snap)
    if planner == "dijkstra":
        return _plan_dijkstra(mesh_map, s, g, slowness, blocked)
    result = _plan_fmm(mesh_map, s, g, slowness, blocked)
    if weld > 0:
        original.vertex_layers["arrival_time"] = mesh_map.vertex_layers["arrival_time"][groups]
    return result


def _result(planner, path, slowness_at, s, g) -> PlanResult:
    steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
    return PlanResult(planner, True, path, float(steps.sum()), float((steps * slowness_at).sum()), s, g)


def _plan_dijkstra(mesh_map: MeshMap, s: int, g: int, slowness: np.ndarray, blocked: np.ndarray) -> PlanResult:
    n = mesh_map.number_of_vertices
    pairs = edges(mesh_map.faces)
    pairs = pairs[~(blocked[pairs[:, 0]] | blocked[pairs[:, 1]])]
    vertices = mesh_map.vertices.astype(np.float64)
    length = np.linalg.norm(vertices[pairs[:, 0]] - vertices[pairs[:, 1]], axis=1)
    weight = length * 0.5 * (slowness[pairs[:, 0]] + slowness[pairs[:, 1]])
    graph = coo_matrix((weight, (pairs[:, 0], pairs[:, 1])), shape=(n, n)).tocsr()
    distance, predecessors = dijkstra(graph, directed=False, indices=s, return_predecessors=True)
    if not np.isfinite(distance[g]):
        return PlanResult("dijkstra", False, np.zeros((0, 3)), float("inf"), float("inf"), s, g)
    route = [g]
    while route[-1] != s:
        route.append(int(predecessors[route[-1]]))
    route = np.array(route[::-1])
    path = vertices[route]
    middle = 0.5 * (slowness[route[1:]] + slowness[route[:-1]])
    return _result("dijkstra", path, middle, s, g)


# -- fast marching --------------------------------------------------------------


def _vertex_faces(faces: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR (starts, face ids) of the faces around each vertex."""
    owner = np.repeat(np.arange(len(faces)), 3)
    corner = faces.ravel()
    order = np.argsort(corner, kind="stable")
    starts = np.concatenate([[0], np.cumsum(np.bincount(corner, minlength=n))])
    return starts, owner[order]


def arrival_times(mesh_map: MeshMap, source: int, slowness: np.ndarray, blocked: np.ndarray) -> np.ndarray:
    """Arrival time T (N,) of the wave front from vertex ``source`` (inf where it never arrives), by fast
    marching compiled with numba (:mod:`mabdi.mesh_maps.fast_marching`)."""
    vertices = mesh_map.vertices.astype(np.float64)
    faces = mesh_map.faces
    n = len(vertices)
    starts, incident = _vertex_faces(faces, n)
    return fast_marching(vertices, faces, starts, incident, slowness, blocked, source)


def _plan_fmm(mesh_map: MeshMap, s: int, g: int, slowness: np.ndarray, blocked: np.ndarray) -> PlanResult:
    times = arrival_times(mesh_map, s, slowness, blocked)
    mesh_map.vertex_layers["arrival_time"] = times.astype(np.float32)
    if not np.isfinite(times[g]):
        return PlanResult("fmm", False, np.zeros((0, 3)), float("inf"), float("inf"), s, g)
    path, faces = _descend(mesh_map, times, s, g)
    # the slowness of a step: the mean over the corners of the face it ends in
    step_slowness = slowness[mesh_map.faces[faces]].mean(axis=1) if len(faces) else np.zeros(0)
    return _result("fmm", path, step_slowness, s, g)


def _descend(mesh_map: MeshMap, times: np.ndarray, s: int, g: int) -> tuple[np.ndarray, np.ndarray]:
    """Follow -grad T from vertex g to vertex s; the path points (start first) and the face of each step."""
    from vtkmodules.vtkCommonCore import reference
    from vtkmodules.vtkCommonDataModel import vtkGenericCell, vtkStaticCellLocator

    vertices = mesh_map.vertices.astype(np.float64)
    faces = mesh_map.faces
    edge_lengths = np.linalg.norm(vertices[faces[:, 0]] - vertices[faces[:, 1]], axis=1)
    step = 0.5 * float(np.mean(edge_lengths))
    locator = vtkStaticCellLocator()
    mesh = mesh_map.to_polydata()
    locator.SetDataSet(mesh)
    locator.BuildLocator()
    cell = vtkGenericCell()
    target = vertices[s]
    point = vertices[g].copy()
    path = [point.copy()]
    limit = int(4 * times[g] / step) + 1000  # T >= path length, so a descent needs about T / step steps
    closest, cell_id, sub_id, distance = [0.0, 0.0, 0.0], reference(-1), reference(0), reference(0.0)
    face = -1
    step_faces = []
    for _ in range(limit):
        if np.linalg.norm(point - target) <= 1.5 * step:
            break
        locator.FindClosestPoint(point, closest, cell, cell_id, sub_id, distance)
        face = int(cell_id.get())
        gradient = _face_gradients(vertices, faces[face : face + 1], times)[0]
        if not np.all(np.isfinite(gradient)) or np.linalg.norm(gradient) < 1e-12:
            # beside an unreached (lethal) vertex: go to the face's earliest-reached corner
            corner = faces[face][np.argmin(times[faces[face]])]
            direction = vertices[corner] - point
        else:
            direction = -gradient
        length = np.linalg.norm(direction)
        if length < 1e-12:
            break
        point = point + min(step, length) * direction / length
        locator.FindClosestPoint(point, closest, cell, cell_id, sub_id, distance)
        point = np.array(closest)
        path.append(point.copy())
        step_faces.append(face)
    path.append(target.copy())
    step_faces.append(face if face >= 0 else int(np.flatnonzero((faces == s).any(axis=1))[0]))
    return np.array(path[::-1]), np.array(step_faces[::-1], dtype=np.int64)


def _face_gradients(vertices: np.ndarray, faces: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Gradient of T, linear on each triangle (M, 3); NaN where a corner was never reached."""
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    ta, tb, tc = times[faces[:, 0]], times[faces[:, 1]], times[faces[:, 2]]
    e1, e2 = b - a, c - a
    g11 = np.einsum("ij,ij->i", e1, e1)
    g12 = np.einsum("ij,ij->i", e1, e2)
    g22 = np.einsum("ij,ij->i", e2, e2)
    det = g11 * g22 - g12 * g12
    with np.errstate(invalid="ignore", divide="ignore"):
        d1, d2 = tb - ta, tc - ta
        x = (g22 * d1 - g12 * d2) / det
        y = (g11 * d2 - g12 * d1) / det
        gradient = x[:, None] * e1 + y[:, None] * e2
    finite = np.isfinite(ta) & np.isfinite(tb) & np.isfinite(tc) & (det > 0)
    gradient[~finite] = np.nan
    return gradient
