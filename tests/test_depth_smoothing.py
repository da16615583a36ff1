"""smooth_depth and the surfaces' ``smooth_depth`` switch: noise falls, planes and steps stay where they are."""

from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy

from mabdi.camera import Intrinsics
from mabdi.config import load_run_config, set_value
from mabdi.depth import depth_image
from mabdi.errors import ConfigError
from mabdi.sensor_noise import SensorNoise
from mabdi.surfaces.depth_smoothing import smooth_depth
from mabdi.surfaces.pixel_grid import FilterPixelGrid, PixelGridParameters
from mabdi.surfaces.quadtree import FilterQuadTree, QuadTreeParameters

K = Intrinsics(fx=525.0, fy=525.0, cx=160.0, cy=120.0, width=320, height=240)
KINECT = SensorNoise("kinect")


def tilted_plane(normal=(0.3, -0.4, -1.0), distance=2.0) -> tuple[np.ndarray, np.ndarray]:
    """z-depth of the plane n . X = -distance (camera frame, n unit) at every pixel, and n."""
    n = np.asarray(normal, dtype=np.float64)
    n /= np.linalg.norm(n)
    rays = K.rays().reshape(K.height, K.width, 3)  # z = 1
    return (-distance / (rays @ n)).astype(np.float32), n


def test_a_plane_keeps_its_depth_and_its_noise_falls_to_a_third():
    exact, _ = tilted_plane()
    sigma = KINECT.sigma(exact, K.near, K.far)
    # noise-free: the inverse-depth mean of symmetric pairs is exact on a plane at any tilt
    np.testing.assert_allclose(smooth_depth(exact, sigma), exact, rtol=2e-6)
    rng = np.random.default_rng(4)
    noisy = exact + sigma * rng.standard_normal(exact.shape).astype(np.float32)
    error = (smooth_depth(noisy, KINECT.sigma(noisy, K.near, K.far)) - exact)[1:-1, 1:-1] / sigma[1:-1, 1:-1]
    assert 0.30 < error.std() < 0.37  # nine pixels: 1/3
    assert abs(error.mean()) < 0.01


def test_steps_holes_and_a_noise_free_sensor_are_left_alone():
    depth = np.full((40, 60), 2.0, np.float32)
    depth[:, 30:] = 2.1  # a 10 cm step
    depth[10:14, 5:9] = np.nan
    sigma = np.full(depth.shape, 0.005)
    out = smooth_depth(depth, sigma)
    np.testing.assert_array_equal(out[:, 29], 2.0)  # beside the step: only pairs along it
    np.testing.assert_array_equal(out[:, 30], np.float32(2.1))
    assert np.isnan(out[10:14, 5:9]).all() and np.isfinite(out[~np.isnan(depth)]).all()
    noisy = depth + np.float32(0.01) * np.random.default_rng(1).standard_normal(depth.shape).astype(np.float32)
    np.testing.assert_array_equal(smooth_depth(noisy, 0.0), noisy)
    with pytest.raises(ValueError, match=r"\(H, W\) depth image, got shape \(5,\)"):
        smooth_depth(np.ones(5), 0.01)


def plane_distances(surface, depth, normal, distance=2.0) -> np.ndarray:
    surface.SetInputDataObject(depth_image(depth, K, np.eye(4), noise=KINECT))
    surface.Update()
    points = vtk_to_numpy(surface.GetOutput().GetPoints().GetData()).astype(np.float64)
    return np.abs(points @ normal + distance)


@pytest.mark.parametrize("make", [FilterPixelGrid, FilterQuadTree])
def test_the_surfaces_mesh_the_smoothed_image_of_a_noisy_plane(make):
    exact, normal = tilted_plane()
    sigma = KINECT.sigma(exact, K.near, K.far)
    noisy = exact + sigma * np.random.default_rng(7).standard_normal(exact.shape).astype(np.float32)
    raw_parameters = PixelGridParameters(max_jump=0.05, smooth_depth=False) if make is FilterPixelGrid else QuadTreeParameters(smooth_depth=False)
    smooth_parameters = PixelGridParameters(max_jump=0.05) if make is FilterPixelGrid else QuadTreeParameters()
    raw = np.median(plane_distances(make(raw_parameters), noisy, normal))
    smoothed = np.median(plane_distances(make(smooth_parameters), noisy, normal))
    assert smoothed < 0.75 * raw
    if make is FilterPixelGrid:  # one pixel each: median |N(0, s)| = 0.674 s, and s = sigma / 3 smoothed
        assert smoothed < 0.3 * 0.674 * np.median(sigma) * 1.5


def test_smooth_depth_is_a_surface_config_key_and_is_checked(tmp_path):
    config = load_run_config("scenes/table.toml")
    assert config.surface.parameters_of("pixel_grid").smooth_depth is True
    set_value(config, "surface.quadtree.smooth_depth", False)
    assert config.surface.parameters_of("quadtree").smooth_depth is False
    with pytest.raises(ConfigError, match="smooth_depth must be true or false, got 'yes'"):
        PixelGridParameters(smooth_depth="yes")


def test_the_compiled_pass_equals_the_array_formulation_bit_for_bit():
    """smooth_depth (one compiled pass) against the module docs' rule in array slices, with holes, steps, a
    per-pixel sigma and the image border."""

    def by_slices(depth, sigma, gate_k=3.0):
        z = depth.astype(np.float64)
        gate = gate_k * np.sqrt(2.0) * np.broadcast_to(sigma, z.shape)
        height, width = z.shape
        padded = np.pad(z, 1, constant_values=np.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse_sum, count = 1.0 / z, np.ones_like(z)
            for du, dv in ((1, 0), (0, 1), (1, 1), (1, -1)):
                ahead = padded[1 + dv : 1 + dv + height, 1 + du : 1 + du + width]
                behind = padded[1 - dv : 1 - dv + height, 1 - du : 1 - du + width]
                pair = (np.abs(ahead - z) <= gate) & (np.abs(behind - z) <= gate)
                inverse_sum[pair] += 1.0 / ahead[pair] + 1.0 / behind[pair]
                count[pair] += 2.0
            return (count / inverse_sum).astype(np.float32)

    rng = np.random.default_rng(5)
    depth = (2.0 + rng.normal(0, 0.003, (37, 53))).astype(np.float32)
    depth[:, 30:] += 0.4  # a step
    depth[rng.random(depth.shape) < 0.05] = np.nan
    sigma = (0.001 + 0.002 * rng.random(depth.shape)).astype(np.float32)
    smoothed = smooth_depth(depth, sigma)
    assert np.array_equal(smoothed, by_slices(depth, sigma), equal_nan=True)
    assert not np.array_equal(smoothed, depth, equal_nan=True)


def test_the_window_follows_the_noise_correlation():
    """3 x 3 where pixels err on their own; 1.5 correlation lengths each way where they err together (capped);
    every opposite pair of the window once."""
    from mabdi.surfaces.depth_smoothing import MAX_SMOOTHING_RADIUS, smoothing_radius
    from mabdi.surfaces.depth_smoothing_kernels import PAIR_DIRECTIONS, pair_directions

    assert smoothing_radius(KINECT) == smoothing_radius(SensorNoise("zbuffer")) == 1
    assert smoothing_radius(SensorNoise("structured_light", correlation_length=2.5)) == 4
    assert smoothing_radius(SensorNoise("structured_light", correlation_length=20.0)) == MAX_SMOOTHING_RADIUS
    assert smoothing_radius(SensorNoise("structured_light", disparity_sigma=0.0)) == 1  # quantisation alone
    np.testing.assert_array_equal(pair_directions(1), PAIR_DIRECTIONS)
    pairs = pair_directions(4)
    assert len(pairs) == (9 * 9 - 1) // 2 and np.abs(pairs).max() == 4
    both_sides = {tuple(p) for p in pairs} | {tuple(-p) for p in pairs}
    assert len(both_sides) == 80 and (0, 0) not in both_sides


def test_a_wide_window_takes_out_correlated_noise_and_keeps_planes_and_steps():
    """Noise correlated over 2.5 pixels on a tilted plane: the 3 x 3 window leaves nearly all of it, the 9 x 9
    window about 70%; the noise-free plane comes out as it went in, and a step stays a step."""
    from mabdi.sensor_noise import correlated_field

    exact, _ = tilted_plane()
    sigma = np.full(exact.shape, 0.01)
    np.testing.assert_allclose(smooth_depth(exact, sigma, radius=4), exact, rtol=2e-6)
    noisy = exact + np.float32(0.01) * correlated_field(exact.shape, 2.5, np.random.default_rng(2))
    spread = {r: ((smooth_depth(noisy, sigma, radius=r) - exact)[8:-8, 8:-8] / 0.01).std() for r in (1, 4)}
    assert spread[1] > 0.9 and spread[4] < 0.8, spread
    step = np.full((40, 60), 2.0, np.float32)
    step[:, 30:] = 2.1
    out = smooth_depth(step, np.full(step.shape, 0.005), radius=4)
    np.testing.assert_array_equal(out[:, :30], 2.0)
    np.testing.assert_array_equal(out[:, 30:], np.float32(2.1))


def test_a_window_radius_that_is_not_a_whole_pixel_count_is_refused():
    for radius in (0, 2.5, True):
        with pytest.raises(ValueError, match=r"radius must be an integer >= 1 \(pixels\), got"):
            smooth_depth(np.ones((4, 4), np.float32), 0.01, radius=radius)
