"""One sensor geometry object: a camera's Intrinsics and a LiDAR's SphericalGeometry answer the same questions
(projection, the image's value, angular resolution), so the stages ask it instead of branching on its type."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mabdi.camera import Intrinsics, look_at
from mabdi.depth import depth_image, image_intrinsics, is_range_image
from mabdi.spherical import SphericalGeometry

CAMERA = Intrinsics(fx=300.0, fy=280.0, cx=80.0, cy=60.0, width=160, height=120, near=0.3, far=8.0)
LIDAR = SphericalGeometry(beams=16, columns=360, fov_up=15.0, fov_down=-15.0, range_min=0.5, range_max=50.0)
TABLE = SphericalGeometry(beams=4, columns=720, fov_up=10.0, fov_down=-30.0, beam_elevations=(8.0, 2.0, -10.0, -28.0))
GEOMETRIES = {"camera": CAMERA, "lidar": LIDAR, "lidar with a beam table": TABLE}


def _ray_angle(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    return float(np.arccos(np.clip(np.dot(a, b), -1.0, 1.0)))


@pytest.mark.parametrize("name", GEOMETRIES)
def test_points_on_pixel_rays_project_back_to_those_pixels_with_the_images_value(name):
    """A point at value * ray of a pixel centre, seen from a pose, projects to that centre with that value."""
    geometry = GEOMETRIES[name]
    rng = np.random.default_rng(7)
    rows = rng.integers(0, geometry.height, 50)
    cols = rng.integers(0, geometry.width, 50)
    values = rng.uniform(1.0, 5.0, 50)
    sensor_points = geometry.rays()[rows, cols] * values[:, None]
    pose = look_at([0.4, -1.0, 1.2], [2.0, 1.0, 0.5])
    world = sensor_points @ pose[:3, :3].T + pose[:3, 3]
    uv, value = geometry.project_points(world, pose)
    np.testing.assert_allclose(uv, np.stack([cols + 0.5, rows + 0.5], axis=1), atol=1e-6)
    np.testing.assert_allclose(value, values, rtol=1e-9)
    np.testing.assert_allclose(geometry.sensor_values(sensor_points), values, rtol=1e-9)


@pytest.mark.parametrize("name", GEOMETRIES)
def test_pixel_angle_is_the_widest_step_between_neighbouring_rays_at_the_centre(name):
    """``pixel_angle``: the larger of the angles to the next column and the next row at the image centre (a
    LiDAR's widest beam spacing); ``pixels_per_radian`` turns an angle across columns into pixels."""
    geometry = GEOMETRIES[name]
    rays = geometry.rays()
    v, u = geometry.height // 2, geometry.width // 2
    if geometry.range_image:  # the row nearest the horizon: columns' rays lie an azimuth step apart there
        v = int(np.argmin(np.abs(geometry.elevations())))
    across = _ray_angle(rays[v, u], rays[v, u + 1])
    steps = [across, _ray_angle(rays[v, u], rays[min(v + 1, geometry.height - 1), u])]
    if geometry.range_image:  # every beam spacing counts, not only the centre's
        steps += [_ray_angle(rays[i, u], rays[i + 1, u]) for i in range(geometry.height - 1)]
    assert geometry.pixel_angle() == pytest.approx(max(steps), rel=2e-3)
    assert geometry.pixels_per_radian() * across == pytest.approx(1.0, rel=2e-3)


def test_the_kind_of_image_and_what_a_depth_jump_scales_by():
    """A camera's image holds z-depth and ends at its edges; a LiDAR's holds range and wraps round; a jump
    between a LiDAR's neighbouring beams scales by its pixel angle over the default camera's."""
    assert not CAMERA.range_image and not CAMERA.wraps_around and CAMERA.jump_scale() == 1.0
    assert LIDAR.range_image and LIDAR.wraps_around
    assert LIDAR.jump_scale() == pytest.approx(LIDAR.pixel_angle() * Intrinsics().fx)
    assert LIDAR.pixel_angle() == pytest.approx(math.radians(30.0 / 16))  # beams 1.875 deg apart, columns 1 deg
    points = np.array([[0.0, 0.0, 2.0], [1.0, 2.0, 2.0]])
    np.testing.assert_allclose(CAMERA.sensor_values(points), [2.0, 2.0])
    np.testing.assert_allclose(LIDAR.sensor_values(points), [2.0, 3.0])
    for geometry in (CAMERA, LIDAR, TABLE):
        image = depth_image(np.ones(geometry.shape, np.float32), geometry, np.eye(4), 0)
        assert image_intrinsics(image) == geometry
        assert is_range_image(image) is geometry.range_image
