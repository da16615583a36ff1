"""The MABDI loop end to end: growth levels off, accuracy against the ground truth, object addition,
the hand-built pipeline, errors and outputs."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy

from conftest import REPO
from mabdi.cli import main
from mabdi.config import load_run_config, set_value
from mabdi.depth import depth_array
from mabdi.errors import ConfigError
from mabdi.evaluate import distances_to_mesh
from mabdi.render.depth_image import FilterDepthImage
from mabdi.loop import MappingRun
from mabdi.io.run_folder import OutputError
from mabdi.loop.run_outputs import METRICS_COLUMNS
from mabdi.polydata import triangles_polydata


def run(name, **changes):
    config = load_run_config(REPO / "scenes" / f"{name}.toml")
    for dotted, value in changes.items():
        set_value(config, dotted.replace("__", "."), value)
    simulation = MappingRun(config)
    return simulation, simulation.run()


@pytest.fixture(scope="session")
def table_run():
    return run("table")


@pytest.fixture(scope="session")
def table_black_box():
    return run("table", classifier__enabled=False)


def circles(result):
    added = np.array([r.cells_added for r in result.records])
    half = len(added) // 2
    return added[:half].sum(), added[half:].sum()


def test_map_stops_growing_on_the_second_circle(table_run):
    first, second = circles(table_run[1])
    assert second <= 0.15 * first, (first, second)


def test_black_box_keeps_growing(table_black_box):
    first, second = circles(table_black_box[1])
    assert second >= 0.8 * first, (first, second)


def test_records_add_up(table_run):
    result = table_run[1]
    totals = np.cumsum([r.cells_added - r.cells_removed for r in result.records])
    np.testing.assert_array_equal(totals, result.cells)
    assert result.cells[-1] == result.mesh.GetNumberOfCells()
    assert result.records[0].novel_fraction == 1.0  # the empty map explains nothing
    assert all(0.0 <= r.novel_fraction <= 1.0 for r in result.records)
    assert all(r.t_total_ms >= r.t_depth_ms for r in result.records)


def test_noise_free_table_map_lies_on_the_scene(table_run):
    simulation, result = table_run
    vertices = vtk_to_numpy(result.mesh.GetPoints().GetData())
    distance = distances_to_mesh(vertices[::7], simulation.scene.mesh_at(29))
    assert np.median(distance) < 2e-3, np.median(distance)


@pytest.mark.slow
def test_kinect_noise_table_map_within_a_centimetre():
    simulation, result = run("table", sensor__noise="kinect")
    vertices = vtk_to_numpy(result.mesh.GetPoints().GetData())
    distance = distances_to_mesh(vertices[::7], simulation.scene.mesh_at(29))
    assert np.median(distance) < 1e-2, np.median(distance)


@pytest.fixture(scope="session")
def dynamic_run():
    return run("bunnies_dynamic")


@pytest.mark.slow
def test_new_bunny_makes_the_map_jump(dynamic_run):
    simulation, result = dynamic_run
    middle = [o.name for o in simulation.scene.objects].index("bunny_middle")
    appear = simulation.scene.objects[middle].appear
    added = np.array([r.cells_added for r in result.records])
    before = added[appear - 8 : appear]
    assert added[appear] > 5 * max(np.median(before), 1), (added[appear], before)


@pytest.mark.slow
def test_final_map_covers_the_new_bunny(dynamic_run):
    simulation, result = dynamic_run
    names = [o.name for o in simulation.scene.objects]
    middle = simulation.scene.objects[names.index("bunny_middle")]
    bunny_only = triangles_polydata(middle.points, middle.triangles)
    intrinsics = simulation.config.sensor.intrinsics()
    full, alone = FilterDepthImage(intrinsics=intrinsics), FilterDepthImage(intrinsics=intrinsics)
    alone.SetInputDataObject(bunny_only)
    samples = []
    for frame in range(middle.appear, simulation.config.run.frames, 3):
        pose = simulation.poses[frame]
        full.SetInputDataObject(simulation.scene.mesh_at(frame))
        for renderer in (full, alone):
            renderer.pose = pose
            renderer.Update()
        d_full, d_alone = depth_array(full.GetOutput()), depth_array(alone.GetOutput())
        visible = np.isfinite(d_alone) & (np.abs(d_full - d_alone) < 1e-3)
        from mabdi.camera import backproject

        points = backproject(np.where(visible, d_alone, np.nan), intrinsics, pose)
        samples.append(points[:: max(1, len(points) // 3000)])
    samples = np.concatenate(samples)
    assert len(samples) > 10000
    covered = distances_to_mesh(samples, result.mesh) < 0.02
    assert covered.mean() >= 0.8, covered.mean()


def test_hand_built_pipeline_from_the_readme_equals_simulation(monkeypatch):
    """The README's pipeline of filters is the loop without object removal (a stage of MabdiLoop, not a filter)
    and without registration (the example takes the poses as given), with the seed's pixel grid."""
    table_run = run("table", surface__method="pixel_grid", removal__enabled=False, registration__enabled=False)
    text = (REPO / "README.md").read_text()
    code = text.split("<!-- example: hand-built loop -->")[1].split("```python")[1].split("```")[0]
    monkeypatch.chdir(REPO)
    namespace: dict = {}
    exec(compile(code, "README.md example", "exec"), namespace)
    by_hand = namespace["mesh"]
    simulated = table_run[1].mesh
    assert by_hand.GetNumberOfCells() == simulated.GetNumberOfCells()
    np.testing.assert_array_equal(vtk_to_numpy(by_hand.GetPoints().GetData()), vtk_to_numpy(simulated.GetPoints().GetData()))
    np.testing.assert_array_equal(
        vtk_to_numpy(by_hand.GetPolys().GetConnectivityArray()), vtk_to_numpy(simulated.GetPolys().GetConnectivityArray())
    )


def test_the_readmes_stages_called_with_values_make_the_hand_built_pipelines_map(monkeypatch):
    """The README's loop of stage methods (values in and out, no VTK pipeline) and its pipeline of the same
    filters make the same map: the filters' RequestData are adaptors over the methods."""
    text = (REPO / "README.md").read_text()
    monkeypatch.chdir(REPO)
    meshes = []
    for example in ("hand-built loop", "stages called with values"):
        code = text.split(f"<!-- example: {example} -->")[1].split("```python")[1].split("```")[0]
        namespace: dict = {"print": lambda *args: None}
        exec(compile(code, f"README.md example ({example})", "exec"), namespace)
        meshes.append(namespace["mesh"])
    by_pipeline, by_values = meshes
    assert by_values.GetNumberOfCells() == by_pipeline.GetNumberOfCells() > 100_000
    np.testing.assert_array_equal(vtk_to_numpy(by_values.GetPoints().GetData()), vtk_to_numpy(by_pipeline.GetPoints().GetData()))
    np.testing.assert_array_equal(
        vtk_to_numpy(by_values.GetPolys().GetConnectivityArray()), vtk_to_numpy(by_pipeline.GetPolys().GetConnectivityArray())
    )


def test_the_mabdi_loop_example_from_the_readme_equals_simulation(monkeypatch):
    """The README's MabdiLoop example (the loop in one object, on the simulated rig) makes the map a run of the
    same config with the quad-tree makes."""
    _, result = run("table", surface__method="quadtree")
    text = (REPO / "README.md").read_text()
    code = text.split("<!-- example: MabdiLoop -->")[1].split("```python")[1].split("```")[0]
    monkeypatch.chdir(REPO)
    namespace: dict = {}
    exec(compile(code, "README.md example", "exec"), namespace)
    mesh = namespace["loop"].mesh()
    assert mesh.GetNumberOfCells() == result.mesh.GetNumberOfCells() > 10_000
    np.testing.assert_array_equal(vtk_to_numpy(mesh.GetPoints().GetData()), vtk_to_numpy(result.mesh.GetPoints().GetData()))


#: Each stage of a simulated run, and the method of it that runs a frame: the simulator's are VTK filters
#: (RequestData); the loop calls its stages' own methods with the frame's values.
STAGES = {
    "scene": (lambda s: s.rig.scene, "RequestData"),
    "sensor": (lambda s: s.rig.sensor, "RequestData"),
    "measured": (lambda s: s.loop.depth_frames, "measured"),
    "expected": (lambda s: s.loop.expected, "render"),
    "classifier": (lambda s: s.loop.classifier, "classify"),
    "surface": (lambda s: s.loop.surface, "mesh_frame"),
    "world": (lambda s: s.loop.world, "append"),
}


@pytest.mark.parametrize("stage", list(STAGES))
def test_an_exception_in_any_stage_reaches_the_caller(stage):
    config = load_run_config(REPO / "scenes" / "table.toml")
    config.run.frames = 3
    simulation = MappingRun(config)

    def broken(*args):
        raise RuntimeError(f"{stage} broke")

    owner, method = STAGES[stage]
    setattr(owner(simulation), method, broken)
    with pytest.raises(RuntimeError, match=f"{stage} broke"):
        simulation.run()


def test_frames_with_no_return_add_nothing(tmp_path):
    path = tmp_path / "empty.toml"
    path.write_text("[run]\nframes = 3\n")  # no objects: every D is all NaN
    simulation = MappingRun(load_run_config(path))
    result = simulation.run()
    assert [r.cells_total for r in result.records] == [0, 0, 0]
    assert result.mesh.GetNumberOfCells() == 0


def test_unknown_surface_name_is_a_config_error(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text('[surface]\nmethod = "marching_cubes"\n')
    with pytest.raises(ConfigError, match="surface.method' = 'marching_cubes' is not one of: pixel_grid, quadtree"):
        load_run_config(path)


def test_output_under_a_regular_file_is_a_clear_error(tmp_path):
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("x")
    config = load_run_config(REPO / "scenes" / "table.toml")
    config.run.frames = 2
    with pytest.raises(OutputError, match="is a file, not a folder"):
        MappingRun(config).run(blocker / "run")
    assert blocker.read_text() == "x"


def test_failed_run_leaves_earlier_outputs_whole(tmp_path):
    config = load_run_config(REPO / "scenes" / "table.toml")
    config.run.frames = 2
    out = tmp_path / "run"
    MappingRun(config).run(out)
    before = (out / "world_mesh.vtp").read_bytes()
    simulation = MappingRun(config)

    def broken(*args):
        raise RuntimeError("surface broke")

    simulation.loop.surface.mesh_frame = broken
    with pytest.raises(RuntimeError):
        simulation.run(out)
    assert (out / "world_mesh.vtp").read_bytes() == before
    assert not [p for p in out.iterdir() if ".tmp" in p.name]


def test_cli_run_writes_every_output(tmp_path, capsys):
    out = tmp_path / "bb"
    status = main(["run", str(REPO / "scenes" / "table.toml"), "--frames", "4", "--no-classifier", "--out", str(out), "--quiet"])
    assert status == 0
    printed = capsys.readouterr().out
    assert "black box" in printed and str(out) in printed and "frames/s" in printed
    for name in ("config.toml", "world_mesh.vtp", "world_mesh.ply", "metrics.csv", "summary.json", "elements.png", "scene.vtp"):
        assert (out / name).is_file(), name
    with open(out / "metrics.csv") as handle:
        rows = list(csv.reader(handle))
    assert tuple(rows[0][: len(METRICS_COLUMNS)]) == METRICS_COLUMNS
    assert [int(r[0]) for r in rows[1:]] == [0, 1, 2, 3]
    assert all(float(r[1]) == 1.0 for r in rows[1:])  # black box: every valid pixel is meshed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 4 and summary["classifier"] is False
    assert summary["cells"] == int(rows[-1][list(METRICS_COLUMNS).index("cells_total")])
    from PIL import Image

    assert Image.open(out / "elements.png").size == (800, 500)
    resolved = load_run_config(out / "config.toml")
    assert resolved.classifier.enabled is False and resolved.run.frames == 4


def test_ply_is_readable_by_trimesh_and_meshio(tmp_path):
    import meshio
    import trimesh

    config = load_run_config(REPO / "scenes" / "table.toml")
    config.run.frames = 2
    result = MappingRun(config).run(tmp_path / "r")
    ply = tmp_path / "r" / "world_mesh.ply"
    loaded = trimesh.load(ply, process=False)
    assert loaded.faces.shape == (result.mesh.GetNumberOfCells(), 3)
    read = meshio.read(ply)
    assert read.cells[0].type == "triangle" and len(read.cells[0].data) == result.mesh.GetNumberOfCells()


def test_export_round_trip(tmp_path, capsys):
    config = load_run_config(REPO / "scenes" / "table.toml")
    config.run.frames = 2
    result = MappingRun(config).run(tmp_path / "r")
    cells = result.mesh.GetNumberOfCells()
    source = tmp_path / "r" / "world_mesh.vtp"
    for target in ("map.ply", "map.obj", "map.stl", "back.vtp"):
        assert main(["export", str(source), str(tmp_path / target)]) == 0
        source = tmp_path / target
        assert f"{cells:,} cells" in capsys.readouterr().out
    assert main(["export", str(source), str(tmp_path / "map.dae")]) == 2
    assert "unknown format '.dae' (known: .vtp, .ply, .obj, .stl, .h5" in capsys.readouterr().err


def test_cli_unknown_surface_is_named(tmp_path, capsys):
    status = main(["run", str(REPO / "scenes" / "table.toml"), "--surface", "marching_cubes", "--out", str(tmp_path / "o")])
    assert status == 2
    assert "surface.method" in capsys.readouterr().err
