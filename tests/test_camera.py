"""mabdi.camera: intrinsics, poses, z-buffer conversion, projection, VTK camera."""

from __future__ import annotations

import math

import numpy as np
import pytest
from vtkmodules.vtkRenderingCore import vtkCamera

from mabdi.camera import (
    Intrinsics,
    backproject,
    check_pose,
    configure_vtk_camera,
    depth_to_zbuffer,
    intrinsics_from_vtk_camera,
    look_at,
    pose_from_vtk_camera,
    project,
    zbuffer_depth_derivative,
    zbuffer_to_depth,
)
from mabdi.errors import ConfigError, PoseError


def test_default_intrinsics_are_kinect_like():
    k = Intrinsics()
    assert (k.width, k.height, k.fx, k.fy, k.cx, k.cy, k.near, k.far) == (640, 480, 525, 525, 320.0, 240.0, 0.5, 4.0)
    assert k.shape == (480, 640)
    assert k.vertical_view_angle == pytest.approx(math.degrees(2 * math.atan(240 / 525)))


def test_ray_through_pixel_centre():
    k = Intrinsics()
    rays = k.rays()
    assert rays.shape == (480, 640, 3)
    np.testing.assert_allclose(rays[0, 0], [(0.5 - 320) / 525, (0.5 - 240) / 525, 1.0])
    np.testing.assert_allclose(rays[479, 639], [(639.5 - 320) / 525, (479.5 - 240) / 525, 1.0])


def test_intrinsics_array_round_trip():
    k = Intrinsics(500.0, 510.0, 300.5, 220.25, 600, 400, 0.3, 5.0)
    assert Intrinsics.from_array(k.to_array()) == k


@pytest.mark.parametrize("field,value", [("fx", 0.0), ("fy", -525.0), ("fx", float("nan"))])
def test_non_positive_focal_length_is_an_error(field, value):
    with pytest.raises(ConfigError, match=field):
        Intrinsics(**{field: value})


@pytest.mark.parametrize("kwargs", [{"near": 0.0}, {"near": 5.0, "far": 4.0}, {"width": 0}, {"height": 2.5}])
def test_bad_range_or_size_is_an_error(kwargs):
    with pytest.raises(ConfigError):
        Intrinsics(**kwargs)


def test_zbuffer_depth_round_trip_and_endpoints():
    z = np.linspace(0.5, 4.0, 101)
    d = depth_to_zbuffer(z, 0.5, 4.0)
    assert d[0] == pytest.approx(0.0) and d[-1] == pytest.approx(1.0)
    np.testing.assert_allclose(zbuffer_to_depth(d[:-1], 0.5, 4.0), z[:-1], rtol=1e-12)
    assert np.isnan(zbuffer_to_depth(np.array([1.0]), 0.5, 4.0)[0])  # background = no return


def test_zbuffer_derivative_matches_finite_difference():
    z = np.array([1.0, 2.0, 3.0])
    d = depth_to_zbuffer(z, 0.5, 4.0)
    h = 1e-7
    numeric = (zbuffer_to_depth(d + h, 0.5, 4.0) - zbuffer_to_depth(d - h, 0.5, 4.0)) / (2 * h)
    np.testing.assert_allclose(zbuffer_depth_derivative(z, 0.5, 4.0), numeric, rtol=1e-5)


def test_project_backproject_round_trip():
    k = Intrinsics()
    pose = look_at([1.0, -2.0, 1.5], [0.0, 0.0, 0.5])
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.6, 3.9, size=k.shape)
    depth[::7, ::5] = np.nan
    points = backproject(depth, k, pose, keep_invalid=True)
    valid = np.isfinite(depth)
    uv, z = project(points[valid], k, pose)
    np.testing.assert_allclose(z, depth[valid], rtol=1e-12)
    v, u = np.nonzero(valid)
    np.testing.assert_allclose(uv[:, 0], u + 0.5, atol=1e-9)
    np.testing.assert_allclose(uv[:, 1], v + 0.5, atol=1e-9)
    assert backproject(depth, k, pose).shape == (valid.sum(), 3)


def test_backproject_rejects_wrong_shape():
    with pytest.raises(ValueError, match="shape"):
        backproject(np.ones((10, 10)), Intrinsics(), np.eye(4))


def test_check_pose_errors_name_the_problem():
    with pytest.raises(PoseError, match="4x4"):
        check_pose(np.eye(3))
    not_rigid = np.eye(4)
    not_rigid[0, 0] = 2.0
    with pytest.raises(PoseError, match="not rigid"):
        check_pose(not_rigid)
    mirrored = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(PoseError, match="reflection"):
        check_pose(mirrored)
    bad_row = np.eye(4)
    bad_row[3, 0] = 1.0
    with pytest.raises(PoseError, match="last row"):
        check_pose(bad_row)


def test_look_at_frame_is_opencv_and_points_at_target():
    pose = look_at([0.0, -3.0, 1.0], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(pose[:3, 2], [0, 1, 0], atol=1e-12)  # forward
    np.testing.assert_allclose(pose[:3, 0], [1, 0, 0], atol=1e-12)  # right
    np.testing.assert_allclose(pose[:3, 1], [0, 0, -1], atol=1e-12)  # down
    with pytest.raises(PoseError, match="parallel"):
        look_at([0, 0, 2], [0, 0, 0])
    with pytest.raises(PoseError, match="coincide"):
        look_at([1, 1, 1], [1, 1, 1])


def test_vtk_camera_round_trip_with_off_centre_principal_point():
    k = Intrinsics(fx=410.0, fy=395.0, cx=170.3, cy=101.7, width=320, height=240, near=0.3, far=6.0)
    pose = look_at([1.0, 2.0, 1.2], [0.2, -0.1, 0.4])
    camera = vtkCamera()
    configure_vtk_camera(camera, k, pose)
    back = intrinsics_from_vtk_camera(camera, 320, 240)
    for name in ("fx", "fy", "cx", "cy", "near", "far"):
        assert getattr(back, name) == pytest.approx(getattr(k, name), rel=1e-9), name
    np.testing.assert_allclose(pose_from_vtk_camera(camera), pose, atol=1e-9)
