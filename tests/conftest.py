"""Shared fixtures. Importing mabdi first selects the EGL render window (no X server)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import mabdi  # noqa: F401  (sets VTK_DEFAULT_OPENGL_WINDOW before VTK loads)
from mabdi.polydata import triangles_polydata

REPO = Path(__file__).resolve().parents[1]
SCENES = REPO / "scenes"


def plane_mesh(point, normal, size: float = 40.0, subdivisions: int = 1):
    """A square plane (vtkPolyData) through ``point`` with ``normal``, ``size`` metres on a side."""
    normal = np.asarray(normal, dtype=np.float64)
    normal /= np.linalg.norm(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = np.cross(normal, helper)
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    s = np.linspace(-0.5 * size, 0.5 * size, subdivisions + 1)
    grid_a, grid_b = np.meshgrid(s, s, indexing="ij")
    points = np.asarray(point) + grid_a.reshape(-1, 1) * a + grid_b.reshape(-1, 1) * b
    n = subdivisions + 1
    i, j = np.meshgrid(np.arange(subdivisions), np.arange(subdivisions), indexing="ij")
    v0 = (i * n + j).ravel()
    v1, v2, v3 = v0 + n, v0 + n + 1, v0 + 1
    triangles = np.concatenate([np.stack([v0, v1, v2], 1), np.stack([v0, v2, v3], 1)])
    return triangles_polydata(points, triangles)


def merged(*meshes):
    """One triangle polydata of several (vtkPolyData, or (points, triangles) arrays), points renumbered."""
    from mabdi.polydata import polydata_arrays

    points, triangles, offset = [], [], 0
    for mesh in meshes:
        p, t = mesh if isinstance(mesh, tuple) else polydata_arrays(mesh)
        points.append(p)
        triangles.append(t + offset)
        offset += len(p)
    return triangles_polydata(np.concatenate(points), np.concatenate(triangles))


def pytest_collection_modifyitems(config, items):
    """The files that hold full simulation runs first (those whose every test is marked ``slow``, then those with
    some): ``make test`` hands whole files to its processes in this order, so the longest start first and the
    short ones fill in beside them (no process is left running one long file at the end)."""
    slow_share = {}
    for item in items:
        counts = slow_share.setdefault(item.path, [0, 0])
        counts[0] += item.get_closest_marker("slow") is not None
        counts[1] += 1
    items.sort(key=lambda item: -slow_share[item.path][0] / slow_share[item.path][1])


@pytest.fixture(scope="session")
def scenes_dir() -> Path:
    return SCENES


#: Triangles of the pixel-grid map of Run 1 (docs/benchmarks.md, `mabdi bench --scene table`).
PIXEL_GRID_TABLE_CELLS = 825_799


def check_table_loop(surface: str, median_limit: float):
    """Run 1 with ``surface``; assert the loop's must-shows (10x fewer triangles than the pixel grid,
    median vertex distance to the scene below ``median_limit`` m, second-circle growth <= 15% of
    the first's) and return (simulation, result) for more."""
    from vtkmodules.util.numpy_support import vtk_to_numpy

    from mabdi.config import load_run_config
    from mabdi.evaluate import distances_to_mesh
    from mabdi.loop import MappingRun

    config = load_run_config(REPO / "scenes" / "table.toml")
    config.surface.method = surface
    simulation = MappingRun(config)
    result = simulation.run()
    assert result.mesh.GetNumberOfCells() * 10 <= PIXEL_GRID_TABLE_CELLS
    vertices = vtk_to_numpy(result.mesh.GetPoints().GetData())
    assert np.median(distances_to_mesh(vertices, simulation.scene.mesh_at(29))) < median_limit
    added = np.array([r.cells_added for r in result.records])
    assert added[15:].sum() <= 0.15 * added[:15].sum()
    return simulation, result


def simulation(scene: str, surface: str, **values):
    """The MappingRun of ``scenes/<scene>.toml`` with ``surface``; ``values`` set config keys (``a__b`` = ``a.b``)."""
    from mabdi.config import load_run_config, set_value
    from mabdi.loop import MappingRun

    config = load_run_config(REPO / "scenes" / f"{scene}.toml")
    set_value(config, "surface.method", surface)
    for key, value in values.items():
        set_value(config, key.replace("__", "."), value)
    return MappingRun(config)


@pytest.fixture(scope="session")
def static_runs():
    """Runs 1-2 (nothing leaves) by (scene, surface, removal): (result, metrics), run once for all tests; the
    ``static_runs.removed(scene, surface)`` gives the faces removal took out."""
    from mabdi.evaluate import evaluate_run

    from mabdi.polydata import transformed_polydata

    cache = {}
    removed_faces = {}

    def get(scene: str, surface: str, removal: bool = True):
        key = (scene, surface, removal)
        if key not in cache:
            sim = simulation(scene, surface, removal__enabled=removal)
            removed = []

            def keep_removed(record):
                if record.cells_removed:
                    removed.append(transformed_polydata(sim.loop.removed_surface(), sim.loop.world_from_map()))

            result = sim.run(progress=keep_removed)
            removed_faces[key] = (removed, sim.rig.scene)
            cache[key] = (result, evaluate_run(sim, result))
        return cache[key]

    def removed(scene: str, surface: str) -> tuple[list, object]:
        """(the faces removal took out of run (scene, surface), a vtkPolyData per frame that removed any, in the
        world frame; the scene)."""
        get(scene, surface)
        return removed_faces[(scene, surface, True)]

    get.removed = removed

    return get
