"""mabdi.evaluate.tsdf: the settings' checks, the pixel convention on a tilted plane, runs and tuning."""

from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy

from conftest import plane_mesh
from mabdi.camera import Intrinsics, look_at
from mabdi.depth import DepthFrame
from mabdi.errors import ConfigError
from mabdi.evaluate.tsdf import TsdfSettings, default_grid, tune_tsdf
from mabdi.sources.frames import FrameList

#: A plane through the origin tilted 60 degrees from the floor, seen from 2 m above by the default
#: 640x480 camera (f = 525 px): half a pixel sideways is 1.9 mm at 2 m, which moves the surface
#: 1.9 sin(60) = 1.65 mm along the plane's normal.
TILT = np.radians(60.0)
NORMAL = np.array([np.sin(TILT), 0.0, np.cos(TILT)])


#: Settings whose volume starts small (Open3D grows it; a large initial capacity costs seconds to zero).
CHEAP = TsdfSettings(block_count=256)
SMALL = Intrinsics(width=160, height=120, fx=131.25, fy=131.25, cx=80.0, cy=60.0)


def plane_frames(
    normal=NORMAL, offsets=(0.0, 0.003, 0.007), height=2.0, intrinsics=SMALL, window=(1.0, 3.0)
) -> FrameList:
    """Noise-free depth frames of the plane n.x = 0 from cameras ``height`` above it looking down (numpy, exact).

    Depths outside ``window`` (m) are no return, which keeps the volume small.
    """
    k = intrinsics
    frames = []
    for i, dx in enumerate(offsets):
        pose = look_at((dx, 0.0, height), (dx, 0.0, 0.0), up=(0.0, 1.0, 0.0))
        rays = k.rays() @ pose[:3, :3].T  # world directions of the pixel-centre rays, camera z = 1
        z = -(pose[:3, 3] @ normal) / (rays @ normal)  # z-depth where each ray meets the plane
        depth = np.where((z > window[0]) & (z < window[1]), z, np.nan).astype(np.float32)
        frames.append(DepthFrame(depth, k, pose, i))
    return FrameList(frames, "tilted plane")


def test_settings_defaults_are_the_plain_open3d_settings():
    s = TsdfSettings()
    assert (s.voxel_size, s.trunc_voxels, s.weight_threshold, s.depth_max, s.pixel_centre) == (
        0.01,
        4.0,
        1.0,
        5.0,
        "half",
    )
    assert s.replace(trunc_voxels=6).trunc_voxels == 6.0
    k = Intrinsics()
    assert s.open3d_intrinsic(k)[0, 2] == 320.0 and s.open3d_intrinsic(k)[1, 2] == 240.0
    integer = s.replace(pixel_centre="integer").open3d_intrinsic(k)
    assert integer[0, 2] == 319.5 and integer[1, 2] == 239.5


@pytest.mark.parametrize(
    "changes, words",
    [
        ({"voxel_size": 0.0}, "voxel_size"),
        ({"voxel_size": float("nan")}, "voxel_size"),
        ({"trunc_voxels": 1.5}, "trunc_voxels"),
        ({"trunc_voxels": 13}, "trunc_voxels"),
        ({"weight_threshold": 0.25}, "weight_threshold"),
        ({"weight_threshold": 3.5}, "weight_threshold"),
        ({"depth_max": -1.0}, "depth_max"),
        ({"pixel_centre": "centre"}, "pixel_centre"),
        ({"block_count": 0}, "block_count"),
        ({"trunc_voxels": "4"}, "trunc_voxels"),
    ],
)
def test_settings_checks_name_the_field(changes, words):
    with pytest.raises(ConfigError, match=words):
        TsdfSettings(**changes)


def test_default_grid_covers_the_axes():
    grid = default_grid(Intrinsics())
    assert grid["trunc_voxels"] == (2.0, 3.0, 4.0, 5.0, 6.0)
    assert grid["weight_threshold"] == (0.5, 1.0, 2.0, 3.0)
    assert set(grid["pixel_centre"]) == {"half", "integer"}
    assert grid["depth_max"] == (3.0, 4.0)
    assert grid["smooth_depth"] == (False,)  # no noise model: nothing to smooth
    assert default_grid(Intrinsics(), "kinect")["smooth_depth"] == (False, True)


def signed_offsets(mesh) -> np.ndarray:
    vertices = vtk_to_numpy(mesh.GetPoints().GetData()).astype(np.float64)
    return vertices @ NORMAL


def test_half_pixel_centres_land_on_a_tilted_plane_and_integer_centres_do_not():
    pytest.importorskip("open3d")
    from mabdi.evaluate.tsdf import run_tsdf

    frames = plane_frames(intrinsics=Intrinsics())
    offsets = {}
    for centre in ("half", "integer"):
        run = run_tsdf(frames, CHEAP.replace(pixel_centre=centre), mesh_every=None)
        assert run.mesh.GetNumberOfCells() > 10_000
        offsets[centre] = signed_offsets(run.mesh)
    # right convention: no bias, and the surface within 1 mm of the plane
    assert abs(np.mean(offsets["half"])) < 2e-4
    assert np.median(np.abs(offsets["half"])) < 1e-3
    # wrong convention: half a pixel sideways, about 1.65 mm off along the normal, all on one side
    assert np.median(np.abs(offsets["integer"])) > 1.2e-3
    assert abs(np.mean(offsets["integer"])) > 1.2e-3


def test_alignment_error_reads_the_convention():
    pytest.importorskip("open3d")
    from mabdi.evaluate.tsdf import alignment_error

    frame = plane_frames(offsets=(0.0,), intrinsics=Intrinsics()).read(0)
    truth = plane_mesh((0.0, 0.0, 0.0), NORMAL, size=10.0)
    assert alignment_error(frame, truth, 0.01, CHEAP) < 1e-3
    assert alignment_error(frame, truth, 0.01, CHEAP.replace(pixel_centre="integer")) > 1.2e-3


def test_run_tsdf_reports_timings_extractions_and_thresholds():
    pytest.importorskip("open3d")
    from mabdi.evaluate.tsdf import run_tsdf

    frames = plane_frames(offsets=(0.0, 0.002, 0.004, 0.006))
    run = run_tsdf(frames, CHEAP.replace(voxel_size=0.02), mesh_every=2, turns=2.0, weight_thresholds=[2.0, 3.0])
    assert len(run.t_depth_ms) == len(run.t_integrate_ms) == 4
    assert [frame for frame, _, _ in run.extractions] == [1, 3]
    assert run.growth_per_circle(4, 2.0)[0] == run.extractions[0][1]
    assert set(run.meshes) == {1.0, 2.0, 3.0} and run.mesh is run.meshes[1.0]
    counts = [run.meshes[w].GetNumberOfCells() for w in (1.0, 2.0, 3.0)]
    assert counts[0] >= counts[1] >= counts[2] > 0  # a higher threshold keeps fewer voxels
    assert run.volume_bytes > 0 and run.settings.voxel_size == 0.02
    # the old call with a voxel size still works
    assert run_tsdf(frames, 0.02, mesh_every=None).mesh.GetNumberOfCells() == counts[0]
    with pytest.raises(ConfigError, match="weight_threshold"):
        run_tsdf(frames, CHEAP, weight_thresholds=[4.0])


def test_tuning_returns_the_best_grid_point_of_the_score(monkeypatch):
    pytest.importorskip("open3d")
    import mabdi.evaluate.tsdf as tsdf

    # the fake score sees only the mesh: record the settings of each extraction, which tune_tsdf scores at once
    extracted = []
    original = tsdf.TsdfMapper.extract

    def extract(self, weight_threshold=None):
        extracted.append(
            {**{n: getattr(self.settings, n) for n in tsdf.TUNED_AXES}, "weight_threshold": weight_threshold}
        )
        return original(self, weight_threshold)

    monkeypatch.setattr(tsdf.TsdfMapper, "extract", extract)
    target = {"pixel_centre": "integer", "trunc_voxels": 3.0, "weight_threshold": 2.0, "depth_max": 2.5, "smooth_depth": False}

    def fake_score(mesh):
        misses = sum(extracted[-1][name] != target[name] for name in tsdf.TUNED_AXES)
        return {
            "fscore_1cm": 1.0 - 0.1 * misses,
            "precision_1cm": 1.0,
            "recall_1cm": 1.0,
            "triangles": mesh.GetNumberOfCells(),
        }

    frames = plane_frames(offsets=(0.0, 0.004, 0.008))
    grid = {"trunc_voxels": (2.0, 3.0, 4.0), "weight_threshold": (1.0, 2.0), "depth_max": (2.5, 4.0)}
    for search in ("coordinate", "full"):
        tuning = tune_tsdf(frames, 0.02, fake_score, grid=grid, search=search, start=CHEAP)
        assert {name: getattr(tuning.best, name) for name in tsdf.TUNED_AXES} == target, search
        assert tuning.score["fscore_1cm"] == pytest.approx(1.0)
        assert tuning.mesh.GetNumberOfCells() == tuning.score["triangles"]
        assert sum(row["best"] for row in tuning.table) == 1
        assert len({tuple(row[n] for n in tsdf.TUNED_AXES) for row in tuning.table}) == len(
            tuning.table
        )  # no point twice
        if search == "full":
            assert len(tuning.table) == 2 * 3 * 2 * 2 and tuning.integrations == 2 * 3 * 2
        else:
            assert len(tuning.table) < 2 * 3 * 2 * 2


def test_tuning_breaks_ties_with_fewer_triangles_and_checks_the_score():
    pytest.importorskip("open3d")

    frames = plane_frames(offsets=(0.0, 0.004, 0.008))
    grid = {"pixel_centre": ("half",), "trunc_voxels": (2.0, 6.0), "weight_threshold": (1.0,), "depth_max": (4.0,)}

    def flat(mesh):
        return {"fscore_1cm": 0.5, "precision_1cm": 0.5, "recall_1cm": 0.5, "triangles": mesh.GetNumberOfCells()}

    tuning = tune_tsdf(frames, 0.02, flat, grid=grid, search="full", start=CHEAP)
    assert tuning.score["triangles"] == min(row["triangles"] for row in tuning.table)
    with pytest.raises(ValueError, match="triangles"):
        tune_tsdf(frames, 0.02, lambda mesh: {"fscore_1cm": 1.0}, grid=grid, start=CHEAP)
    with pytest.raises(ConfigError, match="trunc_voxels"):
        tune_tsdf(frames, 0.02, flat, grid={"trunc_voxels": (1.0,)})


def test_smoothed_depth_brings_the_surface_of_a_noisy_plane_nearer():
    """``smooth_depth`` integrates the depth smoothed by the noise model (as the pixel grid and quad-tree mesh
    it): with one noisy frame the TSDF surface lies nearer the plane; without a noise model nothing changes."""
    pytest.importorskip("open3d")
    from mabdi.evaluate.tsdf import run_tsdf
    from mabdi.sensor_noise import SensorNoise

    exact = plane_frames(offsets=(0.0,), intrinsics=Intrinsics()).read(0)
    sigma = SensorNoise("kinect").sigma(exact.depth, exact.intrinsics.near, exact.intrinsics.far)
    noisy_depth = exact.depth + sigma * np.random.default_rng(2).standard_normal(exact.depth.shape).astype(np.float32)
    frames = FrameList([DepthFrame(noisy_depth, exact.intrinsics, exact.world_from_camera, 0)], "noisy plane")
    settings = CHEAP.replace(weight_threshold=0.5)
    raw = np.median(np.abs(signed_offsets(run_tsdf(frames, settings, mesh_every=None, noise="kinect").mesh)))
    smoothed_run = run_tsdf(frames, settings.replace(smooth_depth=True), mesh_every=None, noise="kinect")
    assert np.median(np.abs(signed_offsets(smoothed_run.mesh))) < 0.6 * raw
    unsmoothed = run_tsdf(frames, settings.replace(smooth_depth=True), mesh_every=None)  # no noise model
    assert unsmoothed.mesh.GetNumberOfCells() == run_tsdf(frames, settings, mesh_every=None).mesh.GetNumberOfCells()
    with pytest.raises(ConfigError, match="smooth_depth must be true or false"):
        TsdfSettings(smooth_depth="yes")


def test_range_images_fuse_along_each_beam_onto_the_wall_they_saw():
    """A LiDAR's range images of a wall 4 m ahead (two poses 0.3 m apart), fused beam by beam: the mesh lies on
    the wall (median 2 mm, 90% within 1 cm at 5 cm voxels) and spans what the beams reached, and a
    far wall the depth range leaves out is not fused."""
    pytest.importorskip("open3d")
    from mabdi.evaluate.tsdf import TsdfMapper
    from mabdi.polydata import polydata_arrays
    from mabdi.spherical import SphericalGeometry

    lidar = SphericalGeometry(beams=64, columns=1024, fov_up=10.0, fov_down=-10.0, range_min=0.5, range_max=30.0)
    rays = lidar.rays()
    settings = TsdfSettings(voxel_size=0.05, trunc_voxels=3, weight_threshold=0.5, depth_max=20.0, block_resolution=8)
    mapper = TsdfMapper(settings, lidar)
    for y in (0.0, 0.3):
        pose = np.eye(4)
        pose[:3, 3] = (1.0, y, 0.5)
        with np.errstate(divide="ignore", invalid="ignore"):
            ranges = np.where(rays[..., 0] > 0.5, 4.0 / rays[..., 0], np.nan)  # the wall x = 5 in the world
            ranges = np.where(rays[..., 0] < -0.5, -25.0 / rays[..., 0], ranges)  # a wall behind, beyond depth_max
        mapper.integrate(ranges, pose)
    points, triangles = polydata_arrays(mapper.extract())
    assert len(triangles) > 10_000
    off = np.abs(points[:, 0] - 5.0)
    assert np.median(off) < 2e-3 and np.percentile(off, 90) < 1e-2
    # rays with x > 0.5 reach 60 degrees either side: y from -6.9 to 7.2 m, z within 10 degrees of 0.5 m
    assert points[:, 1].min() < -6.5 and points[:, 1].max() > 6.8
    assert points[:, 2].min() < -0.5 and points[:, 2].max() > 1.5 and np.all(np.abs(points[:, 2] - 0.5) < 1.5)
