"""Mesh maps from and to any file mabdi writes: HDF5 (.h5, .hdf5) and VTK's VTP, PLY, OBJ, STL.

:func:`load_map` gives a :class:`~mabdi.mesh_maps.mesh_map.MeshMap` (layers from
the HDF5 groups or the VTK point and cell data), of a file or of a run's folder
(:func:`map_file`); :func:`save_map` writes one, atomically, the format
following the suffix.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mabdi.errors import ConfigError, DamagedFileError
from mabdi.io.hdf5 import read_map, write_map
from mabdi.io.vtk_files import MESH_FORMATS, read_mesh_file, write_mesh_file
from mabdi.mesh_maps.mesh_map import MeshMap

HDF5_SUFFIXES = (".h5", ".hdf5")
MAP_FORMATS = MESH_FORMATS + HDF5_SUFFIXES


def is_hdf5(path) -> bool:
    return Path(path).suffix.lower() in HDF5_SUFFIXES


#: A run folder's map files, the richest first (the HDF5 file holds the cost layers and labels too).
RUN_MAP_FILES = ("world_mesh.h5", "world_mesh.vtp", "world_mesh.ply")


def map_file(path, names: tuple[str, ...] = RUN_MAP_FILES) -> Path:
    """``path`` itself, or for a run's folder (``mabdi run --out``) its map: the first of ``names`` there (a
    :class:`ConfigError` naming them when it holds none)."""
    path = Path(path)
    if not path.is_dir():
        return path
    for name in names:
        if (path / name).is_file():
            return path / name
    raise ConfigError(f"{path}: a folder, and not a run's: it holds none of {', '.join(names)}")


def load_map(path) -> MeshMap:
    """Read a map file (.h5/.hdf5 in either HDF5 layout, or .vtp/.ply/.obj/.stl), or a run folder's map
    (:func:`map_file`).

    A map with NaN or infinite vertex coordinates is damaged (bounds, picking
    and planning all go wrong on it): :class:`DamagedFileError` says how many.
    """
    path = map_file(path)
    if is_hdf5(path):
        mesh_map = read_map(path)
    elif path.suffix.lower() not in MESH_FORMATS:
        raise ConfigError(f"{path}: unknown map format '{path.suffix}' (known: {', '.join(MAP_FORMATS)})")
    else:
        mesh_map = MeshMap.from_polydata(read_mesh_file(path))
    check_finite(mesh_map, path)
    return mesh_map


def check_finite(mesh_map: MeshMap, path) -> None:
    """Raise :class:`DamagedFileError` (naming ``path`` and the count) if any vertex is NaN or infinite."""
    bad = ~np.isfinite(mesh_map.vertices).all(axis=1)
    count = int(np.count_nonzero(bad))
    if count:
        first = int(np.flatnonzero(bad)[0])
        raise DamagedFileError(
            f"{path}: damaged map: {count:,} of {mesh_map.number_of_vertices:,} vertices are not finite "
            f"(NaN or inf; the first is vertex {first})"
        )


def save_map(mesh_map: MeshMap, path, layout: str = "mesh_tools") -> Path:
    """Write a map file; the format follows the suffix (``layout`` for HDF5: mesh_tools or lvr2)."""
    path = Path(path)
    if is_hdf5(path):
        return write_map(mesh_map, path, layout)
    if path.suffix.lower() not in MESH_FORMATS:
        raise ConfigError(f"{path}: unknown map format '{path.suffix}' (known: {', '.join(MAP_FORMATS)})")
    return write_mesh_file(mesh_map.to_polydata(), path)
