"""Logging a run to Rerun: a .rrd recording that Rerun's own reader loads, with the entities and frames of the run."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import SCENES

rr = pytest.importorskip("rerun")

FRAMES = 5


def read_recording(path) -> tuple[dict[str, set[str]], set[int]]:
    """Entity path -> component columns, and the values of the ``frame`` timeline, by Rerun's own reader."""
    columns: dict[str, set[str]] = {}
    frames: set[int] = set()
    try:
        from rerun.chunk import RrdReader
    except ImportError:  # older SDKs: the dataframe API
        import rerun.dataframe as rd

        recording = rd.load_recording(str(path))
        for column in recording.schema().component_columns():
            columns.setdefault(column.entity_path, set()).add(str(column.component))
        table = recording.view(index="frame", contents="/**").select().read_all()
        frames.update(int(v) for v in table.column("frame").to_pylist() if v is not None)
        return columns, frames
    for chunk in RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        columns.setdefault(chunk.entity_path, set()).update(batch.schema.names)
        if "frame" in chunk.timeline_names:
            frames.update(int(v) for v in batch.column("frame").to_pylist())
    return columns, frames


@pytest.fixture(scope="module")
def recorded_run(tmp_path_factory):
    from mabdi.config import load_run_config
    from mabdi.loop import MappingRun
    from mabdi.viz.rerun_log import rerun_progress

    config = load_run_config(SCENES / "table.toml")
    config.run.frames = FRAMES
    simulation = MappingRun(config)
    path = tmp_path_factory.mktemp("rerun") / "table.rrd"
    progress = rerun_progress(simulation, path)
    result = simulation.run(progress=progress)
    return path, result, progress


def test_a_run_writes_a_recording_that_rerun_reads(recorded_run):
    path, result, progress = recorded_run
    assert progress.logger.logged_frames == FRAMES and progress.logger.stream is None  # closed after the last frame
    columns, frames = read_recording(path)
    paths = {p.lstrip("/") for p in columns}
    assert frames == set(range(FRAMES))
    for entity in ("world/camera", "world/camera/D", "world/camera/E", "world/camera/labels", "world/novel", "world/path"):
        assert entity in paths, entity
    for name in ("novel_fraction", "cells_total", "cells_added", "time_ms"):
        assert f"metrics/{name}" in paths
    # the map: one entity per patch of the world map (pixel grid: one per frame that added triangles and chunk it
    # reached, "frame_<i>" or "frame_<i>@<chunk>"; Rerun escapes the "@")
    added = {r.frame for r in result.records if r.cells_added > 0}
    logged = {p.removeprefix("world/map/").replace("\\", "").split("@")[0] for p in paths if p.startswith("world/map/")}
    assert logged == {f"frame_{i}" for i in added}
    camera = " ".join(columns["/world/camera"] if "/world/camera" in columns else columns["world/camera"])
    assert "Pinhole" in camera and "Transform3D" in camera


def test_only_new_blocks_are_sent_and_removed_ones_cleared(tmp_path):
    from mabdi.stages.world_mesh import FilterWorldMesh
    from mabdi.polydata import triangles_polydata
    from mabdi.viz.rerun_log import RerunLogger

    world = FilterWorldMesh()
    triangle = triangles_polydata(np.eye(3), np.array([[0, 1, 2]]))
    world.add_patch("patch_1", triangle, 0)
    world.add_patch("patch_2", triangle, 0)
    path = tmp_path / "map.rrd"
    with RerunLogger(path, frames=3) as logger:
        for frame in range(3):
            logger.stream.set_time("frame", sequence=frame)
            if frame == 2:
                world.remove_patch("patch_1")
            logger._log_map(world.map, frame)
    RrdReader = pytest.importorskip("rerun.chunk").RrdReader

    sent: dict[str, list[tuple[int, str]]] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        if chunk.entity_path.startswith("/world/map/"):
            batch = chunk.to_record_batch()
            kind = "clear" if "Clear:is_recursive" in batch.schema.names else "mesh"
            sent.setdefault(chunk.entity_path, []).extend((f, kind) for f in batch.column("frame").to_pylist())
    assert sorted(sent["/world/map/patch_1"]) == [(0, "mesh"), (2, "clear")]
    assert sent["/world/map/patch_2"] == [(0, "mesh")]  # unchanged: sent once


def test_polygons_are_triangulated():
    from vtkmodules.vtkFiltersSources import vtkPlaneSource

    from mabdi.viz.rerun_log import triangles_of

    plane = vtkPlaneSource()
    plane.SetResolution(2, 3)
    plane.Update()
    points, triangles = triangles_of(plane.GetOutput())
    assert points.shape == (12, 3) and points.dtype == np.float32
    assert triangles.shape == (12, 3) and triangles.dtype == np.uint32 and triangles.max() < 12


def test_mabdi_run_rerun_writes_the_recording_from_the_command_line(tmp_path):
    from mabdi.cli import main

    path = tmp_path / "cli.rrd"
    out = tmp_path / "run"
    status = main(["run", str(SCENES / "table.toml"), "--frames", str(FRAMES), "--rerun", str(path), "--out", str(out), "--quiet", "--no-eval"])
    assert status == 0 and path.is_file()
    columns, frames = read_recording(path)
    assert frames == set(range(FRAMES)) and any(p.lstrip("/").startswith("world/map/") for p in columns)
