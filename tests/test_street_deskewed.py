"""The street scanned as a real spinning LiDAR scans it (``scenes/street_deskewed.toml``: a 128-beam, +-45 degree
sensor tipped 12 degrees forward whose sweeps are made while it moves and deskewed, :mod:`mabdi.simulate.lidar_sweep`),
through the whole loop: issue 26's targets for the street (F@2cm, the way back against the way out, ghosts, static
and dynamic accuracy of removal), and removal takes at most 0.5% of the static map. A full run (76 scans): slow."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import SCENES, merged
from test_evaluate import open3d_or_skip

pytestmark = pytest.mark.slow

#: A removed face is the departed car's when its centre lies within this (m) of the car's box.
CAR_REACH = 0.1


@pytest.mark.xfail(
    strict=False,
    reason=(
        "the mapping of deskewed, tilted wide-FoV scans is short of F@2cm 0.95, the way back's 15%, dynamic accuracy "
        "0.95 and a ghost share of 1%: docs/benchmarks.md, \"Removal's votes along each return's own ray\", has the "
        "measured figures"
    ),
)
def test_the_deskewed_street_is_mapped_and_removal_keeps_the_static_map():
    open3d_or_skip()
    from mabdi.config import load_run_config
    from mabdi.evaluate import distances_to_mesh, evaluate_run
    from mabdi.evaluate.dynamic import GhostObserver
    from mabdi.loop import MappingRun
    from mabdi.loop.run_pipeline import FrameCallback, RunPipeline
    from mabdi.polydata import polydata_arrays, polydata_area, transformed_polydata, triangle_normals, triangles_polydata

    sim = MappingRun(load_run_config(SCENES / "street_deskewed.toml"))
    removed = []

    def keep_removed(record):
        if record.cells_removed:
            removed.append(transformed_polydata(sim.loop.removed_surface(), sim.loop.world_from_map()))

    ghosts = GhostObserver(every=19)  # SA and DA count the vertices of every map measured, as tests/test_street.py
    RunPipeline(sim, observers=[ghosts, FrameCallback(keep_removed)]).run()
    run = ghosts.ghosts
    scores = evaluate_run(sim, run.result)
    added = np.array([r.cells_added for r in run.result.records])
    half = len(added) // 2
    removal = run.removal

    # removal's faces: the departed car's (within CAR_REACH of its box), else the static map's
    faces = run.result.mesh.GetNumberOfCells()
    area = polydata_area(run.result.mesh)
    static_faces = static_area = 0.0
    if removed:
        points, triangles = polydata_arrays(merged(*removed))
        face_area = triangle_normals(points, triangles)[1]
        car = next(o for o in sim.rig.scene.objects if o.name == "car_leaving")
        near_car = distances_to_mesh(points[triangles].mean(axis=1), triangles_polydata(car.points, car.triangles)) <= CAR_REACH
        static_faces, static_area = float((~near_car).sum()), float(face_area[~near_car].sum())
    summary = {
        "F@2cm": scores.fscore_2cm,
        "out": int(added[:half].sum()),
        "back": int(added[half:].sum()),
        "back/out": added[half:].sum() / max(added[:half].sum(), 1),
        "ghost share": run.final_share,
        "SA": removal.static_accuracy,
        "DA": removal.dynamic_accuracy,
        "static faces removed / map faces": static_faces / faces,
        "static area removed / map area": static_area / area,
        "map faces": faces,
    }
    print(summary)
    assert scores.fscore_2cm >= 0.95, summary
    assert added[half:].sum() <= 0.15 * added[:half].sum(), summary
    assert run.final_share <= 0.01, summary
    assert removal.static_accuracy >= 0.99, summary
    assert removal.dynamic_accuracy >= 0.95, summary
    assert static_faces <= 0.005 * faces, summary
