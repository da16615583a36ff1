"""Scan-to-map registration of a LiDAR's range images (mabdi.stages.scan_registration).

Real LiDAR poses come from odometry whose heading lags by a degree or more while the sensor turns; the map's
walls then read as seen through, and removal takes them. The scans are fitted to the map along their returns,
and a pose the ICP cannot improve on several times over is kept as given.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mabdi.config import RunConfig, with_overrides
from mabdi.depth import DepthFrame
from mabdi.frame_values import Measured
from mabdi.loop.mapping_run import recorded_simulation
from mabdi.polydata import polydata_arrays
from mabdi.sensor_noise import SensorNoise
from mabdi.sources.frames import FrameList
from mabdi.sources.kitti import write_kitti
from mabdi.spherical import SphericalGeometry
from mabdi.stages.expected_image import FilterExpectedImage
from mabdi.stages.registration import RegistrationParameters
from mabdi.stages.registration_check import PosesDisagreeWarning
from mabdi.stages.scan_registration import ScanRegistration, map_points_and_normals
from mabdi.stages.scan_registration_kernels import image_pixel
from tests.test_lidar import box, merged, plane, render

GEOMETRY = SphericalGeometry(beams=32, columns=512, fov_up=30.0, fov_down=-30.0, range_min=0.5, range_max=40.0)


def room():
    """A 16 x 12 x 4.5 m room (floor at z = -1.5) with two boxes: every direction of a pose is held."""
    x0, x1, y0, y1, z0, z1 = -8.0, 8.0, -6.0, 6.0, -1.5, 3.0
    return merged(
        plane((x0, y0, z0), (x1, y0, z0), (x0, y1, z0)),
        plane((x0, y0, z1), (x0, y1, z1), (x1, y0, z1)),
        plane((x0, y0, z0), (x0, y1, z0), (x0, y0, z1)),
        plane((x1, y0, z0), (x1, y0, z1), (x1, y1, z0)),
        plane((x0, y0, z0), (x0, y0, z1), (x1, y0, z0)),
        plane((x0, y1, z0), (x1, y1, z0), (x0, y1, z1)),
        box((3.0, 2.5, -0.5), (1.5, 1.0, 2.0), 20.0),
        box((-2.5, -3.0, 0.0), (1.0, 2.0, 3.0), -35.0),
    )


def pose(x, y, yaw_deg, z=0.2):
    a = math.radians(yaw_deg)
    p = np.eye(4)
    p[:3, :3] = [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]]
    p[:3, 3] = (x, y, z)
    return p


def scan(mesh, at, noise="none", seed=0) -> np.ndarray:
    from mabdi.depth import depth_array

    return depth_array(render(mesh, GEOMETRY, at, noise=noise, seed=seed))


def heading_error(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))


@pytest.mark.parametrize("table", [(), tuple(np.linspace(29.0, -29.0, 32) ** 3 / 29.0**2)])
def test_a_return_falls_in_the_pixel_the_geometry_puts_it_in(table):
    geometry = GEOMETRY if not table else SphericalGeometry(32, 512, 30.0, -30.0, 0.5, 40.0, table)
    rng = np.random.default_rng(1)
    points = rng.normal(size=(2000, 3)) * [10.0, 10.0, 2.0]
    uv, _ = geometry.pixels(points)
    edges = geometry.row_edges()
    inside = (uv[:, 1] >= 0) & (uv[:, 1] < geometry.beams)
    found = np.array([image_pixel(*p, edges, geometry.columns) for p in points])
    assert (found[~inside, 0] == -1).all()
    # away from the pixels' edges (a float's width), the kernel's pixel is the geometry's
    with np.errstate(invalid="ignore"):  # v is infinite beyond a beam table's outer beams
        clear = inside & (np.abs(uv[:, 1] - np.round(uv[:, 1])) > 1e-6) & (np.abs(uv[:, 0] - np.round(uv[:, 0])) > 1e-6)
    assert clear.sum() > 500
    assert np.array_equal(found[clear, 0], np.floor(uv[clear, 1]).astype(int))
    assert np.array_equal(found[clear, 1], np.floor(uv[clear, 0]).astype(int) % geometry.columns)


def test_the_map_s_normals_from_its_range_image_face_the_sensor():
    wall = plane((6.0, -20.0, -20.0), (6.0, 20.0, -20.0), (6.0, -20.0, 20.0))
    ranges = scan(wall, np.eye(4))
    points, normals = map_points_and_normals(ranges, GEOMETRY)
    known = np.isfinite(normals).all(axis=-1)
    assert known.sum() > 0.9 * np.isfinite(ranges).sum()
    np.testing.assert_allclose(normals[known], np.broadcast_to([-1.0, 0.0, 0.0], normals[known].shape), atol=1e-5)
    np.testing.assert_allclose(points[known][:, 0], 6.0, atol=1e-4)


def _place(given, truth, noise="none"):
    mesh = room()
    expected = FilterExpectedImage(identity=True)
    registration = ScanRegistration(RegistrationParameters(), expected)
    measured = Measured(scan(mesh, truth, noise), GEOMETRY, given, SensorNoise.of("none"), index=1)
    return registration.place(measured, mesh)


def test_a_scan_given_a_lagging_heading_is_fitted_back_to_the_map():
    truth = pose(1.0, -0.5, 25.0)
    given = pose(1.06, -0.53, 27.0)  # 2 degrees and 7 cm off: a turning odometry's lag
    placed, placement, drawn = _place(given, truth)
    assert placement.status == "registered"
    assert heading_error(placed.pose, truth) < 0.02
    assert np.linalg.norm(placed.pose[:3, 3] - truth[:3, 3]) < 0.005
    assert placement.correction_deg == pytest.approx(2.0, abs=0.05)
    assert drawn is None  # E was drawn at the given pose: the loop draws it again at the fitted one


def test_a_good_pose_is_kept_as_given_and_its_drawing_reused():
    truth = pose(-1.0, 0.5, -40.0)
    placed, placement, drawn = _place(truth, truth, noise="range")
    assert placement.status == "registered"
    assert np.array_equal(placed.pose, truth)  # the ICP's pose fits no better than the map's own errors
    assert drawn is not None and np.array_equal(drawn.pose, truth)


def test_registration_follows_a_turning_odometry_and_removal_leaves_the_room(tmp_path):
    """The failure of a real handheld recording: the given heading lags more and more while the sensor turns;
    without registration the scans see through the walls the earlier scans made, and removal takes them."""
    mesh = room()
    truth = [pose(-3.0 + 0.5 * i, -1.0 + 0.2 * i, 6.0 * i) for i in range(12)]
    lag = [min(0.6 * i, 4.0) for i in range(12)]  # degrees
    given = [pose(t[0, 3] + 0.01 * i, t[1, 3], 6.0 * i + lag[i]) for i, t in enumerate(truth)]
    frames = [DepthFrame(scan(mesh, t, "range", seed=i), GEOMETRY, g, i, 0.1 * i) for i, (t, g) in enumerate(zip(truth, given))]
    write_kitti(FrameList(frames, "turning scans"), tmp_path / "seq")

    def run(**settings):
        simulation, _ = recorded_simulation(with_overrides(RunConfig(), settings, where="test"), tmp_path / "seq", noise_stated=False)
        result = simulation.run()
        removed = sum(r.cells_removed for r in result.records)
        return removed / max(result.mesh.GetNumberOfCells(), 1), simulation.meshed_poses()

    removed_off, _ = run(**{"registration.enabled": False})
    with pytest.warns(PosesDisagreeWarning, match="odometry whose heading lags"):
        removed_on, meshed = run()
    assert removed_off > 0.05  # the failure: the walls go
    assert removed_on < 0.01
    # the lag of up to 4 degrees taken off down to what the map's own noise cannot tell apart (the rule)
    errors = [heading_error(m, t) for m, t in zip(meshed, truth)]
    assert max(errors) < 0.5, np.round(errors, 3)
    assert np.median(errors) < 0.1, np.round(errors, 3)


def test_a_source_that_states_its_poses_exact_keeps_them_without_a_fit():
    from mabdi.pose_noise import PoseNoise

    mesh = room()
    expected = FilterExpectedImage(identity=True)
    registration = ScanRegistration(RegistrationParameters(), expected, PoseNoise())
    given = pose(1.06, -0.53, 27.0)
    measured = Measured(scan(mesh, pose(1.0, -0.5, 25.0)), GEOMETRY, given, SensorNoise.of("none"), index=1)
    placed, placement, drawn = registration.place(measured, mesh)
    assert placement.status == "exact" and placement.given_exact
    assert placed.pose is given and drawn is not None


def test_the_carried_correction_goes_through_a_checkpoint():
    mesh = room()
    expected = FilterExpectedImage(identity=True)
    registration = ScanRegistration(RegistrationParameters(), expected)
    fresh = ScanRegistration(RegistrationParameters(), expected)
    fresh.set_state(registration.state())  # none carried: the given pose itself
    assert fresh.state()["last_frame"] == -1 and np.isnan(fresh.state()["correction"]).all()
    truth = pose(1.0, -0.5, 25.0)
    measured = Measured(scan(mesh, truth), GEOMETRY, pose(1.06, -0.53, 27.0), SensorNoise.of("none"), index=3)
    registration.place(measured, mesh)
    state = registration.state()
    assert state["last_frame"] == 3 and np.isfinite(state["correction"]).all()
    fresh.set_state(state)
    np.testing.assert_array_equal(fresh.state()["correction"], state["correction"])
    # the next scan, given with the same lag, starts where the carried correction puts it
    following = Measured(scan(mesh, truth), GEOMETRY, pose(1.06, -0.53, 27.0), SensorNoise.of("none"), index=4)
    placed, placement, _ = fresh.place(following, mesh)
    assert fresh.last_costs[1] * 100 < fresh.last_costs[0]  # the carried pose fits, the given one does not
    assert heading_error(placed.pose, truth) < 0.02
