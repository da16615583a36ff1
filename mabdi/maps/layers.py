"""Per-vertex layers of a mesh map: normals, trafficability costs (seed 003), colours.

All vectorised over the vertices (numpy, a scipy KD-tree); z is up (metres).

* ``normals``: area-weighted average of the faces' normals around each vertex.
* **Neighbourhood** of a vertex: the vertices within ``radius`` horizontally
  (the robot's footprint) and ``height_window`` (0.5 m) vertically, an
  ellipsoid, found as a sphere after scaling z by radius / height_window,
  the vertex itself included; all of them, by a grid hash compiled with
  numba (:mod:`mabdi.maps.neighbourhood`), or without numba the
  ``max_neighbours`` nearest (24) by a KD-tree. A sphere of the footprint's radius would never
  see the top of a step taller than the radius; an unbounded column would
  mix levels (the floor under a table with its top).
* ``roughness``: the local normal variation, the mean over the
  neighbourhood of 1 - |n_v . n_u| (0 on a plane, up to 1 for normals at
  right angles).
* ``height_difference``: the largest height difference in the
  neighbourhood, max z - min z (m).
* ``slope``: the angle of the normal from the vertical (radians, unoriented).
* ``lethal``: 1 where a robot must not go: slope above ``max_slope``,
  height difference above ``max_step`` or roughness above ``max_roughness``.
* ``inflation``: 1 at lethal vertices, falling linearly to 0 at
  ``inflation_radius`` from the nearest lethal vertex (a robot's footprint).
* ``cost``: the combined trafficability cost in [0, 1], a weighted sum of
  the normalised layers, ``w_roughness * roughness / max_roughness +
  w_height * height_difference / max_step + w_slope * slope / max_slope +
  w_inflation * inflation`` divided by the sum of the weights, and 1 at
  lethal vertices. Default weights 1, 1, 1, 2: keeping clear of obstacles
  counts twice.

:func:`face_layer` turns a vertex layer into a face layer (mean of its three
vertices; ``max`` for lethal).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mabdi.errors import ConfigError
from mabdi.maps.mesh_map import MeshMap
from mabdi.polydata import triangle_normals, vertex_normals

try:
    from mabdi.maps.neighbourhood import radius_statistics
except ImportError:  # pragma: no cover - numba is a dependency
    radius_statistics = None


def fast_neighbourhoods_available() -> bool:
    return radius_statistics is not None

CHUNK = 1 << 17


@dataclass(frozen=True)
class CostParameters:
    """Thresholds (m, radians) and weights of the cost layers; see the module docs."""

    radius: float = 0.1
    height_window: float = 0.5
    max_neighbours: int = 24  # only without numba (the KD-tree fallback)
    max_slope: float = float(np.radians(30.0))
    max_step: float = 0.1
    max_roughness: float = 0.3
    inflation_radius: float = 0.3
    w_roughness: float = 1.0
    w_height: float = 1.0
    w_slope: float = 1.0
    w_inflation: float = 2.0

    def __post_init__(self) -> None:
        for name in ("radius", "height_window", "max_slope", "max_step", "max_roughness"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"cost layers: {name} must be > 0, got {getattr(self, name)}")
        if self.inflation_radius < 0 or self.max_neighbours < 2:
            raise ConfigError("cost layers: need inflation_radius >= 0 and max_neighbours >= 2")


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (M, 3) of the triangles (right-hand rule) and their areas (M,), in float64
    (:func:`mabdi.polydata.triangle_normals`)."""
    return triangle_normals(np.asarray(vertices, dtype=np.float64), faces)


def neighbourhoods(vertices: np.ndarray, radius: float, max_neighbours: int) -> np.ndarray:
    """(N, K) indices of the vertices within ``radius`` (nearest first, the vertex itself first), N where none.

    """
    points = np.asarray(vertices, dtype=np.float64)
    tree = cKDTree(points)
    k = min(max_neighbours, len(points))
    out = np.empty((len(points), k), dtype=np.int64)
    for start in range(0, len(points), CHUNK):
        _, index = tree.query(points[start : start + CHUNK], k=k, distance_upper_bound=radius, workers=-1)
        out[start : start + CHUNK] = index.reshape(-1, k)
    return out


def _padded(values: np.ndarray, fill: float) -> np.ndarray:
    """``values`` with one more row of ``fill``: the KD-tree's "no neighbour" index N points there."""
    return np.concatenate([values, np.full((1,) + values.shape[1:], fill, dtype=values.dtype)])


def roughness(normals: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Mean of 1 - |n_v . n_u| over each vertex's neighbourhood (``index`` from :func:`neighbourhoods`)."""
    normals = np.asarray(normals, dtype=np.float32)
    padded = _padded(normals, 0.0)
    out = np.empty(len(normals))
    for start in range(0, len(normals), CHUNK):
        block = slice(start, start + CHUNK)
        valid = index[block] < len(normals)
        dots = np.abs(np.einsum("nkc,nc->nk", padded[index[block]], normals[block]))
        out[block] = np.where(valid, 1.0 - dots, 0.0).sum(axis=1) / valid.sum(axis=1)
    return out


def height_difference(vertices: np.ndarray, index: np.ndarray) -> np.ndarray:
    """max z - min z over each vertex's neighbourhood (m)."""
    z = np.asarray(vertices, dtype=np.float64)[:, 2]
    return _padded(z, -np.inf)[index].max(axis=1) - _padded(z, np.inf)[index].min(axis=1)


def inflation(vertices: np.ndarray, lethal: np.ndarray, radius: float) -> np.ndarray:
    """1 at lethal vertices, falling linearly to 0 at ``radius`` from the nearest one."""
    out = lethal.astype(np.float64)
    if radius <= 0 or not lethal.any() or lethal.all():
        return out
    points = np.asarray(vertices, dtype=np.float64)
    tree = cKDTree(points[lethal])
    free = np.flatnonzero(~lethal)
    distance, _ = tree.query(points[free], k=1, distance_upper_bound=radius, workers=-1)
    out[free] = np.clip(1.0 - distance / radius, 0.0, 1.0)
    return out


def cost_layers(mesh_map: MeshMap, parameters: CostParameters | None = None) -> dict[str, np.ndarray]:
    """The vertex layers normals, roughness, height_difference, slope, lethal, inflation and cost (float32)."""
    p = parameters or CostParameters()
    vertices, faces = mesh_map.vertices, mesh_map.faces
    normals = vertex_normals(vertices, faces)
    squashed = np.asarray(vertices, dtype=np.float64) * [1.0, 1.0, p.radius / p.height_window]
    if fast_neighbourhoods_available():
        rough, top, bottom = radius_statistics(squashed, normals, vertices[:, 2], p.radius)
        height = top - bottom
    else:  # without numba: the nearest max_neighbours within the radius, by a KD-tree
        index = neighbourhoods(squashed, p.radius, p.max_neighbours)
        rough = roughness(normals, index)
        height = height_difference(vertices, index)
    slope = np.arccos(np.clip(np.abs(normals[:, 2]), 0.0, 1.0))
    lethal = (slope > p.max_slope) | (height > p.max_step) | (rough > p.max_roughness)
    inflated = inflation(vertices, lethal, p.inflation_radius)
    weights = p.w_roughness + p.w_height + p.w_slope + p.w_inflation
    cost = (
        p.w_roughness * np.minimum(rough / p.max_roughness, 1.0)
        + p.w_height * np.minimum(height / p.max_step, 1.0)
        + p.w_slope * np.minimum(slope / p.max_slope, 1.0)
        + p.w_inflation * inflated
    ) / weights
    cost[lethal] = 1.0
    layers = {
        "normals": normals,
        "roughness": rough,
        "height_difference": height,
        "slope": slope,
        "lethal": lethal.astype(np.float64),
        "inflation": inflated,
        "cost": cost,
    }
    return {name: values.astype(np.float32) for name, values in layers.items()}


def add_cost_layers(mesh_map: MeshMap, parameters: CostParameters | None = None, faces: bool = True) -> MeshMap:
    """Compute :func:`cost_layers` into ``mesh_map.vertex_layers`` (and their face versions); returns the map."""
    layers = cost_layers(mesh_map, parameters)
    mesh_map.vertex_layers.update(layers)
    if faces:
        for name in ("roughness", "height_difference", "lethal", "cost"):
            mesh_map.face_layers[f"face_{name}"] = face_layer(mesh_map, layers[name], "max" if name == "lethal" else "mean")
    return mesh_map


def face_layer(mesh_map: MeshMap, values: np.ndarray, reduce: str = "mean") -> np.ndarray:
    """A face layer from a vertex layer: the ``mean`` or ``max`` of each triangle's three vertices."""
    corners = np.asarray(values)[mesh_map.faces]
    if reduce == "mean":
        return corners.mean(axis=1).astype(np.float32)
    if reduce == "max":
        return corners.max(axis=1).astype(np.float32)
    raise ValueError(f"face_layer: reduce must be 'mean' or 'max', got {reduce!r}")
