"""Labelled face clusters and cluster sets of a mesh map (seed 003's label manager).

* :func:`label_faces`: a label from a list of face ids (checked).
* :func:`label_floor`: the traversable region: faces that are near-horizontal
  (normal within ``max_slope`` of vertical) and not lethal (when the map has
  a ``lethal`` vertex layer), connected across shared edges; the largest such
  region, or the one holding ``seed_face``.
* :func:`planar_clusters`: a segmentation of the map into connected
  near-planar clusters: faces sharing an edge join when their normals differ
  by less than ``max_angle`` (10 degrees by default); the connected components
  of that graph with at least ``min_faces`` faces are the clusters, numbered
  from 0 by size. A smooth surface stays one cluster (the test is between
  neighbours); creases split.

Face adjacency is built once per call from the sorted edge list (vectorised).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from mabdi.maps.layers import face_normals
from mabdi.maps.mesh_map import MeshMap, MeshMapError


def face_adjacency(faces: np.ndarray) -> np.ndarray:
    """(E, 2) pairs of faces that share an edge (each pair once)."""
    faces = np.asarray(faces, dtype=np.int64)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges.sort(axis=1)
    owner = np.tile(np.arange(len(faces)), 3)
    key = edges[:, 0] * (int(faces.max()) + 1 if len(faces) else 1) + edges[:, 1]
    order = np.argsort(key, kind="stable")
    key, owner = key[order], owner[order]
    same = np.flatnonzero(key[1:] == key[:-1])
    return np.stack([owner[same], owner[same + 1]], axis=1)


def _components(count: int, pairs: np.ndarray) -> np.ndarray:
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(count, count))
    return connected_components(graph, directed=False)[1]


def label_faces(mesh_map: MeshMap, name: str, face_ids) -> np.ndarray:
    """Store the label ``name`` (e.g. ``tree_1``) for ``face_ids``; returns the sorted unique ids."""
    ids = np.unique(np.asarray(face_ids, dtype=np.int64))
    if ids.size and (ids[0] < 0 or ids[-1] >= mesh_map.number_of_faces):
        raise MeshMapError(f"label {name!r}: face ids must lie in [0, {mesh_map.number_of_faces}), got {ids[0]}..{ids[-1]}")
    mesh_map.labels[name] = ids
    return ids


def label_floor(
    mesh_map: MeshMap, name: str = "floor", max_slope: float = float(np.radians(20.0)), seed_face: int | None = None
) -> np.ndarray:
    """Label the connected near-horizontal, non-lethal region (see the module docs); returns its face ids."""
    normals, _ = face_normals(mesh_map.vertices, mesh_map.faces)
    flat = np.abs(normals[:, 2]) >= np.cos(max_slope)
    lethal = mesh_map.vertex_layers.get("lethal")
    if lethal is not None:
        flat &= ~(np.asarray(lethal)[mesh_map.faces] > 0).any(axis=1)
    pairs = face_adjacency(mesh_map.faces)
    pairs = pairs[flat[pairs[:, 0]] & flat[pairs[:, 1]]]
    component = _components(mesh_map.number_of_faces, pairs)
    if seed_face is not None:
        if not flat[seed_face]:
            return label_faces(mesh_map, name, [])
        chosen = component[seed_face]
    else:
        if not flat.any():
            return label_faces(mesh_map, name, [])
        chosen = np.bincount(component[flat]).argmax()
    return label_faces(mesh_map, name, np.flatnonzero((component == chosen) & flat))


def planar_clusters(
    mesh_map: MeshMap, name: str = "planar", max_angle: float = float(np.radians(10.0)), min_faces: int = 1
) -> dict[str, np.ndarray]:
    """Segment the map into connected near-planar clusters and store them as cluster set ``name``."""
    normals, _ = face_normals(mesh_map.vertices, mesh_map.faces)
    pairs = face_adjacency(mesh_map.faces)
    similar = np.abs(np.einsum("ij,ij->i", normals[pairs[:, 0]], normals[pairs[:, 1]])) >= np.cos(max_angle)
    component = _components(mesh_map.number_of_faces, pairs[similar])
    sizes = np.bincount(component)
    ranked = np.argsort(-sizes, kind="stable")
    ranked = ranked[sizes[ranked] >= min_faces]
    order = np.argsort(component, kind="stable")
    starts = np.concatenate([[0], np.cumsum(sizes)])
    clusters = {str(i): np.sort(order[starts[c] : starts[c + 1]]) for i, c in enumerate(ranked)}
    mesh_map.clustersets[name] = clusters
    return clusters
