"""Per-vertex layers of a mesh map: normals, trafficability costs (seed 003), colours.

All vectorised over the vertices (numpy, a scipy KD-tree); z is up (metres).

* ``normals``: area-weighted average of the faces' normals around each vertex.
* **Neighbourhood** of a vertex: the vertices within ``radius`` horizontally
  (the robot's footprint) and ``height_window`` (0.5 m) vertically, an
  ellipsoid, found as a sphere after scaling z by radius / height_window,
  the vertex itself included; all of them, by a grid hash compiled with
  numba (:mod:`mabdi.mesh_maps.neighbourhood`). A sphere of the footprint's radius would never
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
from mabdi.mesh_maps.mesh_map import MeshMap
from mabdi.polydata import triangle_normals, vertex_normals

from mabdi.mesh_maps.neighbourhood import radius_statistics


@dataclass(frozen=True)
class CostParameters:
    """Thresholds (m, radians) and weights of the cost layers; see the module docs."""

    radius: float = 0.1
    height_window: float = 0.5
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
        if self.inflation_radius < 0:
            raise ConfigError(f"cost layers: inflation_radius must be >= 0, got {self.inflation_radius}")


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (M, 3) of the triangles (right-hand rule) and their areas (M,), in float64
    (:func:`mabdi.polydata.triangle_normals`)."""
    return triangle_normals(np.asarray(vertices, dtype=np.float64), faces)


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
    rough, top, bottom = radius_statistics(squashed, normals, vertices[:, 2], p.radius)
    height = top - bottom
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
