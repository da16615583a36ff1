"""Labelled face clusters and cluster sets of a mesh map (seed 003's label manager).

* :func:`label_faces`: a label from a list of face ids (checked).
* :func:`label_floor`: the traversable region: faces that are near-horizontal
  (normal within ``max_slope`` of vertical) and not lethal (when the map has
  a ``lethal`` vertex layer), connected; the largest such
  region, or the one holding ``seed_face``.
* :func:`planar_clusters`: a segmentation of the map into connected
  near-planar clusters: neighbouring faces join when their normals differ
  by less than ``max_angle`` (10 degrees by default); the connected components
  of that graph with at least ``min_faces`` faces are the clusters, numbered
  from 0 by size. A smooth surface stays one cluster (the test is between
  neighbours); creases split.

Connectivity: faces are neighbours when they share a vertex, after welding
vertices closer than ``weld`` (5 mm): mabdi's maps are patches (frames,
voxel-plane polygons) that meet within millimetres without sharing vertices.
All vectorised (a KD-tree for the welding, sorted incidence lists, scipy's
connected components).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from mabdi.mesh_maps.layers import face_normals
from mabdi.mesh_maps.mesh_map import WELD, MeshMap, MeshMapError, unique_pairs, welded_vertices


def face_adjacency(faces: np.ndarray, vertex_ids: np.ndarray | None = None, max_fan: int = 16) -> np.ndarray:
    """(E, 2) pairs of faces that share a vertex (by ``vertex_ids``, e.g. welded; each pair once).

    Every pair around a vertex is listed up to ``max_fan`` faces per vertex; beyond that the
    faces are chained (connectivity is kept, a few similar pairs may be missed).
    """
    faces = np.asarray(faces, dtype=np.int64)
    corner_vertex = (faces if vertex_ids is None else np.asarray(vertex_ids)[faces]).ravel()
    corner_face = np.repeat(np.arange(len(faces)), 3)
    order = np.lexsort((corner_face, corner_vertex))
    vertex, face = corner_vertex[order], corner_face[order]
    pairs = []
    for step in range(1, max_fan):
        same = np.flatnonzero(vertex[step:] == vertex[:-step]) if step < len(vertex) else np.zeros(0, dtype=np.int64)
        if len(same) == 0:
            break
        pairs.append(np.stack([face[same], face[same + step]], axis=1))
    if not pairs:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = np.concatenate(pairs)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    pairs.sort(axis=1)
    return unique_pairs(pairs)


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
    mesh_map: MeshMap,
    name: str = "floor",
    max_slope: float = float(np.radians(20.0)),
    seed_face: int | None = None,
    weld: float = WELD,
) -> np.ndarray:
    """Label the connected near-horizontal, non-lethal region (see the module docs); returns its face ids."""
    normals, _ = face_normals(mesh_map.vertices, mesh_map.faces)
    flat = np.abs(normals[:, 2]) >= np.cos(max_slope)
    lethal = mesh_map.vertex_layers.get("lethal")
    if lethal is not None:
        flat &= ~(np.asarray(lethal)[mesh_map.faces] > 0).any(axis=1)
    pairs = face_adjacency(mesh_map.faces, welded_vertices(mesh_map.vertices, weld))
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
    mesh_map: MeshMap,
    name: str = "planar",
    max_angle: float = float(np.radians(10.0)),
    min_faces: int = 1,
    weld: float = WELD,
) -> dict[str, np.ndarray]:
    """Segment the map into connected near-planar clusters and store them as cluster set ``name``."""
    normals, _ = face_normals(mesh_map.vertices, mesh_map.faces)
    pairs = face_adjacency(mesh_map.faces, welded_vertices(mesh_map.vertices, weld))
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
