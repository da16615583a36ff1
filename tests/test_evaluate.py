"""mabdi.evaluate: metrics on analytic cases, exact distances, visibility, the TSDF baseline and mabdi bench."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from vtkmodules.util.numpy_support import numpy_to_vtk

from conftest import REPO
from mabdi.camera import Intrinsics, look_at
from mabdi.evaluate.distance import distances_to_mesh, distances_within
from mabdi.evaluate.metrics import evaluate_map, growth_per_circle, observed_ground_truth, ply_size
from mabdi.evaluate.redundancy import redundancy
from mabdi.evaluate.sampling import sample_surface
from mabdi.io.vtk_files import write_mesh_file
from mabdi.polydata import triangles_polydata


def square(x0, x1, y0, y1, z=0.0, frame=None, n=40):
    """A rectangle [x0, x1] x [y0, y1] at height z, n x n squares, optional cell data frame."""
    xs, ys = np.linspace(x0, x1, n + 1), np.linspace(y0, y1, n + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    points = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], axis=1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    v0 = (i * (n + 1) + j).ravel()
    triangles = np.concatenate([np.stack([v0, v0 + n + 1, v0 + n + 2], 1), np.stack([v0, v0 + n + 2, v0 + 1], 1)])
    mesh = triangles_polydata(points, triangles)
    if frame is not None:
        array = numpy_to_vtk(np.full(mesh.GetNumberOfCells(), frame, dtype=np.int32), deep=True)
        array.SetName("frame")
        mesh.GetCellData().AddArray(array)
    return mesh


def merged(*meshes):
    from vtkmodules.vtkFiltersCore import vtkAppendPolyData

    append = vtkAppendPolyData()
    for mesh in meshes:
        append.AddInputData(mesh)
    append.Update()
    return append.GetOutput()


TRUTH = square(-1, 1, -1, 1)


def all_observed(mesh, count=100_000):
    return sample_surface(mesh, count)


def test_shifted_plane_reads_five_millimetres():
    metrics = evaluate_map(square(-1, 1, -1, 1, z=0.005), TRUTH, all_observed(TRUTH))
    assert metrics.accuracy_mean_mm == pytest.approx(5.0, abs=0.1)
    assert metrics.accuracy_median_mm == pytest.approx(5.0, abs=0.1)
    assert metrics.precision_1cm == 1.0 and metrics.recall_1cm == 1.0 and metrics.fscore_1cm == 1.0


def test_half_a_plane_is_half_complete():
    metrics = evaluate_map(square(-1, 0, -1, 1), TRUTH, all_observed(TRUTH))
    assert metrics.recall_1cm == pytest.approx(0.50, abs=0.02)
    assert metrics.precision_1cm == 1.0
    assert metrics.fscore_1cm == pytest.approx(2 * 0.5 / 1.5, abs=0.02)


def test_redundancy_of_layers_copies_and_seams():
    def share(mesh):
        return redundancy(mesh, sample_surface(mesh, 20_000), 0.01)

    assert share(merged(square(-1, 1, -1, 1, frame=0), square(-1, 1, -1, 1, frame=1))) >= 0.95  # the same surface twice
    assert share(merged(square(-1, 1, -1, 1, frame=0), square(-1, 1, -1, 1, z=0.004, frame=1, n=37))) >= 0.95  # a noisy second layer
    assert share(square(-1, 1, -1, 1, frame=0)) <= 0.02  # a single copy
    assert share(merged(square(-1, 0, -1, 1, frame=0), square(0, 1, -1, 1, frame=1))) <= 0.05  # a seam
    assert share(merged(square(-1, 1, -1, 1, frame=0), square(-1, 1, -1, 1, z=0.05, frame=1))) <= 0.02  # 5 cm apart
    assert redundancy(square(-1, 1, -1, 1), sample_surface(TRUTH, 100), 0.01) is None  # no frames: not defined


def test_hidden_surfaces_are_not_counted_as_missed():
    front = square(-1, 1, -1, 1, z=1.0)
    back = square(-0.5, 0.5, -0.5, 0.5, z=0.5)  # hidden behind the front plane from above
    truth = merged(front, back)
    poses = np.stack([look_at([0.0, 0.0, 2.5], [0.0, 0.0, 0.0], up=(0, 1, 0)), look_at([0.3, 0.0, 2.5], [0.0, 0.0, 0.0], up=(0, 1, 0))])
    intrinsics = Intrinsics(width=320, height=240, fx=130.0, fy=130.0, cx=160.0, cy=120.0, near=0.5, far=4.0)
    observed = observed_ground_truth(truth, truth, poses, intrinsics, count=50_000)
    on_back = np.abs(observed.points[:, 2] - 0.5) < 1e-6
    assert len(observed) > 30_000 and not on_back.any()
    metrics = evaluate_map(front, truth, observed)
    assert metrics.recall_1cm > 0.99
    everything = evaluate_map(front, truth, all_observed(truth))
    assert everything.recall_1cm < 0.9  # counting the hidden plane would call it missed


def test_a_surface_is_observed_only_by_poses_that_saw_it_there():
    """In a world that changes, a sample of the final scene counts as observed only from a pose whose scene
    held its surface: from a pose before the door closed the line of sight to the door's back face was
    clear (free space then), yet no pose ever saw that face."""
    from mabdi.evaluate.visibility import observed_mask

    wall = square(-1, 1, -1, 1, z=0.0)
    door_front = square(-0.3, 0.3, -0.3, 0.3, z=1.0)
    door_back = square(-0.25, 0.25, -0.25, 0.25, z=0.96)  # facing away from the cameras (inset: a silhouette
    # lets a sample one pixel behind pass, the 2x2 rule's slack)
    final = merged(wall, door_front, door_back)
    poses = np.stack([look_at([0.0, 0.0, 2.5], [0.0, 0.0, 0.0], up=(0, 1, 0)), look_at([0.2, 0.0, 2.5], [0.0, 0.0, 0.0], up=(0, 1, 0))])
    intrinsics = Intrinsics(width=320, height=240, fx=130.0, fy=130.0, cx=160.0, cy=120.0, near=0.5, far=4.0)
    samples = sample_surface(final, 20_000).points
    on_front = np.abs(samples[:, 2] - 1.0) < 1e-6
    on_back = np.abs(samples[:, 2] - 0.96) < 1e-6
    behind_door = (np.abs(samples[:, 2]) < 1e-6) & (np.abs(samples[:, 0]) < 0.25) & (np.abs(samples[:, 1]) < 0.25)
    assert on_front.sum() > 100 and on_back.sum() > 100 and behind_door.sum() > 100

    open_both = observed_mask(samples, [wall, wall], poses, intrinsics)  # the door closes after both poses
    assert not open_both[on_front | on_back].any()
    assert open_both[behind_door].all()
    closed_later = observed_mask(samples, [wall, final], poses, intrinsics)
    assert closed_later[on_front].mean() > 0.99 and not closed_later[on_back].any()
    assert closed_later[behind_door].all()  # seen by the first pose, while the door was open


def test_distances_are_exact_near_and_far_and_capped_ones_below_the_cap():
    from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
    from vtkmodules.vtkCommonCore import vtkDoubleArray
    from vtkmodules.vtkFiltersCore import vtkImplicitPolyDataDistance
    from vtkmodules.vtkFiltersSources import vtkSphereSource

    sphere = vtkSphereSource()
    sphere.SetThetaResolution(120)
    sphere.SetPhiResolution(60)
    sphere.Update()
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(6000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    # on the sphere (radius 0.5) within millimetres, within centimetres, and up to 20 m off
    radii = 0.5 + np.concatenate([rng.normal(0, 0.002, 3000), rng.normal(0, 0.03, 2000), rng.uniform(-0.45, 20, 1000)])
    points = directions * radii[:, None]
    reference = vtkImplicitPolyDataDistance()  # VTK's locator, exact at any distance
    reference.SetInput(sphere.GetOutput())
    values = vtkDoubleArray()
    reference.FunctionValue(numpy_to_vtk(points, deep=True), values)
    exact = np.abs(vtk_to_numpy(values))
    np.testing.assert_allclose(distances_to_mesh(points, sphere.GetOutput()), exact, atol=1e-12)
    capped = distances_within(points, sphere.GetOutput(), cap=0.05)
    near = exact < 0.05
    assert 3000 < near.sum() < 6000
    np.testing.assert_allclose(capped[near], exact[near], atol=1e-12)
    assert (capped[~near] >= 0.05 - 1e-12).all()


def test_growth_per_circle_and_ply_size(tmp_path):
    assert growth_per_circle([10, 5, 5, 1, 1, 0], turns=2.0) == [20, 2]
    mesh = square(0, 1, 0, 1)
    path = write_mesh_file(mesh, tmp_path / "m.ply")
    assert ply_size(mesh) == path.stat().st_size


def test_sampling_is_uniform_by_area_and_reproducible():
    big, small = square(0, 2, 0, 1, n=4), square(5, 6, 0, 1, n=30)
    samples = sample_surface(merged(big, small), 30_000)
    share_big = (samples.points[:, 0] < 3).mean()
    assert share_big == pytest.approx(2 / 3, abs=0.01)
    np.testing.assert_array_equal(samples.points, sample_surface(merged(big, small), 30_000).points)


def open3d_or_skip():
    try:
        import open3d  # noqa: F401
    except (ImportError, OSError):
        if os.environ.get("CI"):
            raise  # CI installs the comparison extra: a missing Open3D there is a failure
        pytest.skip('Open3D not installed (pip install "mabdi[compare]")')


def test_tsdf_baseline_is_aligned_and_not_crippled():
    open3d_or_skip()
    from mabdi.config import load_run_config
    from mabdi.evaluate.metrics import scenes_per_pose
    from mabdi.evaluate.tsdf import alignment_error, run_tsdf
    from mabdi.simulate import SimulatedRig

    config = load_run_config(REPO / "scenes" / "table.toml")
    rig = SimulatedRig.from_config(config)
    assert alignment_error(rig.noise_free(0), rig.scene.mesh_at(0)) < 1e-3
    run = run_tsdf(rig, 0.01)
    frames = config.run.frames
    observed = observed_ground_truth(
        rig.scene.mesh_at(frames - 1), scenes_per_pose(rig.scene, frames), rig.poses, config.sensor.intrinsics()
    )
    metrics = evaluate_map(run.mesh, rig.scene.mesh_at(frames - 1), observed)
    assert metrics.fscore_2cm > 0.9, metrics


@pytest.mark.slow
def test_bench_without_open3d_reports_mabdi_and_black_box(tmp_path, monkeypatch, capsys):
    import mabdi.evaluate.bench as bench_module
    from mabdi.cli import main

    monkeypatch.setattr(bench_module, "open3d_status", lambda: (False, "Open3D is not available (test)"))
    out = tmp_path / "bench"
    status = main(["bench", "--scene", str(REPO / "scenes" / "table.toml"), "--frames", "20", "--out", str(out)])
    assert status == 0
    printed = capsys.readouterr().out
    assert "| mabdi |" in printed and "| black_box |" in printed and "tsdf_1cm skipped" in printed
    bench = json.loads((out / "bench.json").read_text())
    rows = {row["method"]: row for row in bench["methods"]}
    assert set(rows) == {"mabdi", "black_box"}
    mabdi_metrics, box = rows["mabdi"]["metrics"], rows["black_box"]["metrics"]
    assert mabdi_metrics["fscore_1cm"] > 0.95 and box["fscore_1cm"] > 0.95
    assert mabdi_metrics["redundancy"] < 0.1 < 0.9 < box["redundancy"]
    assert box["triangles"] > 3 * mabdi_metrics["triangles"]  # quad-tree: 91k against 24k over 20 frames
    assert bench["machine"]["cpu"] and bench["machine"]["render"]["backend"] == "egl"
    assert (out / "bench.md").read_text().count("|") > 20 and (out / "elements.png").is_file()


def test_run_reports_ground_truth_metrics(tmp_path, capsys):
    from mabdi.cli import main

    out = tmp_path / "run"
    assert main(["run", str(REPO / "scenes" / "table.toml"), "--frames", "6", "--out", str(out), "--quiet"]) == 0
    assert "vs ground truth: F@1cm" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["metrics"]["fscore_2cm"] > 0.9
    assert summary["metrics"]["triangles"] == summary["cells"]


def test_bench_frames_state_what_the_simulator_states():
    """The bench keeps the simulation's frames in memory and states what the simulator states: the noise
    model and the given poses' accuracy (exact poses are stated exact, so the registration weighs them as
    ``mabdi run`` does, not as a recording of unknown accuracy)."""
    from mabdi.config import load_run_config, with_overrides
    from mabdi.evaluate.bench import bench_frames
    from mabdi.stages.registration import RegistrationParameters
    from mabdi.pose_noise import PoseNoise

    config = with_overrides(load_run_config(REPO / "scenes" / "table.toml"), {"run.frames": 2}, where="test")
    rig, frames = bench_frames(config)
    assert frames.pose_accuracy == PoseNoise() and frames.noise == rig.noise
    assert RegistrationParameters().given_variance(frames.pose_accuracy) == ((0.0, 0.0), (0.0, 0.0))
    jittered = with_overrides(config, {"sensor.pose_noise.jitter_translation": 0.003}, where="test")
    rig, frames = bench_frames(jittered)
    assert frames.pose_accuracy == PoseNoise(jitter_translation=0.003) == rig.pose_accuracy
    np.testing.assert_array_equal(frames.true_poses, rig.true_poses)
    assert not np.array_equal(frames.poses, frames.true_poses)
    from mabdi.sources.frames import FrameList

    with pytest.raises(TypeError, match="FrameList: pose_accuracy must be a PoseNoise or None, got 0.003"):
        FrameList([frames.read(0)], pose_accuracy=0.003)
    with pytest.raises(TypeError, match="FrameList: noise must be a SensorNoise or None, got 'kinect'"):
        FrameList([frames.read(0)], noise="kinect")


def test_samples_of_a_surface_do_not_depend_on_its_triangles_order_or_starting_corners():
    """A map stored in other blocks (its triangles in another order, each starting at another corner) is the same
    surface and gets the same samples; the faces named are the mesh's own."""
    mesh = merged(square(-1, 1, -1, 1), square(0, 2, 0, 2, z=0.3, n=7))
    from mabdi.polydata import polydata_arrays

    points, triangles = polydata_arrays(mesh)
    rng = np.random.default_rng(3)
    order = rng.permutation(len(triangles))
    shift = rng.integers(0, 3, len(triangles))
    shuffled = triangles[order][np.arange(len(triangles))[:, None], (shift[:, None] + np.arange(3)) % 3]
    other = triangles_polydata(points, shuffled)
    a, b = sample_surface(mesh, 5_000), sample_surface(other, 5_000)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.normals, b.normals)
    np.testing.assert_array_equal(triangles[a.faces], triangles[order][b.faces])  # each sample's own face, by index
    assert a.area == pytest.approx(b.area)
    # each sample lies on the face it names
    corners = points[triangles[a.faces]]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert np.abs(np.einsum("ij,ij->i", a.points - corners[:, 0], normal)).max() < 1e-9
