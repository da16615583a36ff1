"""LiDAR scans as range images: pixels by azimuth and elevation or ring, the nearest point per pixel."""

from __future__ import annotations

import numpy as np
import pytest

from mabdi.errors import ConfigError
from mabdi.sources.range_images import (
    KITTI_GEOMETRY,
    geometry_from_table,
    lidar_table,
    range_image,
    range_image_and_returns,
    rows_from_rings,
)
from mabdi.spherical import SphericalGeometry

GEOMETRY = SphericalGeometry(beams=16, columns=64, fov_up=10.0, fov_down=-20.0, range_min=0.5, range_max=50.0)


def _wall_points(geometry, distance, jitter=0.0, seed=0):
    """Points on the plane x = distance along every pixel ray that hits it, moved by up to ``jitter`` of a pixel."""
    rng = np.random.default_rng(seed)
    el, az = geometry.elevations()[:, None], geometry.azimuths()[None, :]
    el = el + jitter * np.radians((geometry.fov_up - geometry.fov_down) / geometry.beams) * rng.uniform(-0.5, 0.5, (geometry.beams, geometry.columns))
    az = az + jitter * 2 * np.pi / geometry.columns * rng.uniform(-0.5, 0.5, (geometry.beams, geometry.columns))
    rays = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)], axis=-1)
    facing = rays[..., 0] > 0.1
    ranges = distance / rays[..., 0]
    return (rays * ranges[..., None])[facing], np.where(facing, ranges, np.nan)


def test_a_wall_reads_its_ranges_at_every_beam():
    points, expected = _wall_points(GEOMETRY, 5.0, jitter=0.9)
    image = range_image(points, GEOMETRY, centred=False)
    assert image.shape == (16, 64) and image.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(image), np.isnan(expected))
    np.testing.assert_allclose(image, expected, rtol=1e-6, equal_nan=True)  # each point's own range, in its pixel


WIDE = SphericalGeometry(beams=32, columns=512, fov_up=45.0, fov_down=-45.0, range_min=0.5, range_max=50.0)


def _room_scan(geometry, elevation_jitter=0.0, seed=0, box=None):
    """Points of a sensor 1.5 m above the floor of a 12 x 8 x 3 m room, one a pixel, each moved off its pixel
    centre's elevation by up to ``elevation_jitter`` of a row (as a deskewed sweep's are); ``box``: (x0, x1) of a
    box in front of the sensor from floor to ceiling, |y| < 1. Returns the points and the range of each centre's ray."""
    rng = np.random.default_rng(seed)
    step = np.radians((geometry.fov_up - geometry.fov_down) / geometry.beams)
    az = np.broadcast_to(geometry.azimuths()[None, :], geometry.shape)

    def ranges(el):
        rays = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)], axis=-1)
        with np.errstate(divide="ignore"):
            t = np.min(np.abs(np.array([6.0, 4.0, 1.5]) / rays), axis=-1)
            if box is not None:
                at = box[0] / rays[..., 0]
                inside = (rays[..., 0] > 0) & (np.abs(rays[..., 1] * at) < 1.0) & (np.abs(rays[..., 2] * at) < 1.5)
                t = np.where(inside, np.minimum(t, at), t)
        return rays, t

    el = geometry.elevations()[:, None] + elevation_jitter * step * rng.uniform(-0.5, 0.5, geometry.shape)
    rays, t = ranges(el)
    return (rays * t[..., None]).reshape(-1, 3), ranges(geometry.elevations()[:, None] + 0 * az)[1]


def test_returns_off_their_rows_are_carried_to_the_pixel_centres():
    # A deskewed sweep's returns lie anywhere in their rows: binned as they are, the floor and ceiling seen at
    # grazing incidence read ranges far from their pixel centres' rays'.
    points, expected = _room_scan(WIDE, elevation_jitter=0.9)
    binned = np.abs(range_image(points, WIDE, centred=False) - expected)
    centred = np.abs(range_image(points, WIDE) - expected)
    assert np.isfinite(centred).all()
    assert np.percentile(binned, 90) > 0.1  # what binning leaves
    assert np.median(centred) < 0.004 and np.percentile(centred, 90) < 0.04
    # Returns exactly on their centres read as they are.
    points, expected = _room_scan(WIDE)
    np.testing.assert_allclose(range_image(points, WIDE), expected, rtol=1e-6)


def test_each_pixel_keeps_its_own_return_beside_the_range_at_its_centre():
    # The range image says where each pixel centre's ray meets the surface; the return the pixel took it from
    # is kept as it was measured, for the surfaces to mesh (a deskewed return lies up to half a pixel off).
    points, _ = _room_scan(WIDE, elevation_jitter=0.9, seed=3)
    depth, returns = range_image_and_returns(points, WIDE)
    np.testing.assert_array_equal(depth, range_image(points, WIDE))
    assert returns.shape == (*WIDE.shape, 3) and returns.dtype == np.float32
    held = np.isfinite(returns).all(axis=2)
    assert np.isnan(returns[~held]).all() and held.mean() > 0.5
    # each held return is one of the scan's points, and it falls in its own pixel
    uv, _ = WIDE.pixels(returns[held].astype(np.float64))
    rows, cols = np.nonzero(held)
    np.testing.assert_array_equal(np.floor(uv[:, 1]).astype(int), rows)
    np.testing.assert_array_equal(np.minimum(np.floor(uv[:, 0]).astype(int), WIDE.columns - 1), cols)
    distance = np.linalg.norm(points[:, None, :] - returns[held][None, ::97, :], axis=2).min(axis=0)
    assert distance.max() < 1e-5  # float32 copies of the points themselves
    # pixels carried to their centres read other ranges than their own returns, and empty pixels hold none
    assert np.nanmax(np.abs(np.linalg.norm(returns, axis=2) - depth)) > 0.01


def test_a_depth_edge_is_not_bridged():
    # A box 3 m ahead against the wall at 6 m: no pixel takes a range between the two.
    points, expected = _room_scan(WIDE, elevation_jitter=0.9, box=(3.0, 3.5))
    image = range_image(points, WIDE)
    ahead = np.abs(WIDE.azimuths()) < np.radians(10)
    between = (image[:, ahead] > 3.6) & (image[:, ahead] < 5.5) & (np.abs(WIDE.elevations()) < np.radians(20))[:, None]
    assert not between.any()
    assert np.median(np.abs(image - expected)) < 0.004


def test_the_nearest_point_of_a_pixel_wins_and_non_returns_are_left_out():
    direction = GEOMETRY.rays()[3, 10]
    points = np.array([4.0 * direction, 3.0 * direction, 9.0 * direction, [0, 0, 0], [np.nan, 0, 0], 0.2 * direction, 60.0 * GEOMETRY.rays()[5, 5]])
    image = range_image(points, GEOMETRY)
    assert image[3, 10] == pytest.approx(3.0)
    assert np.isfinite(image).sum() == 1  # too near, too far, NaN and the origin are no returns
    above = np.array([[10.0, 0.0, 5.0]])  # 26.6 degrees up: above the top beam's edge
    assert np.isnan(range_image(above, GEOMETRY)).all()


def test_rows_from_rings_either_numbering():
    points, _ = _wall_points(GEOMETRY, 5.0)
    _, v = GEOMETRY.pixels(points)[0].T
    top_first = np.floor(v).astype(int)  # Ouster: ring 0 is the top beam
    np.testing.assert_array_equal(rows_from_rings(top_first, points, 16), top_first)
    bottom_first = 15 - top_first  # Velodyne: ring 0 is the lowest beam
    np.testing.assert_array_equal(rows_from_rings(bottom_first, points, 16), top_first)
    np.testing.assert_array_equal(range_image(points, GEOMETRY, rows=rows_from_rings(bottom_first, points, 16)), range_image(points, GEOMETRY))
    with pytest.raises(ValueError, match="ring 16 is outside 0 .. 15"):
        rows_from_rings(top_first + 1, points, 16)


def test_rows_by_ring_ignore_the_elevation():
    direction = GEOMETRY.rays()[3, 10]
    image = range_image(np.array([7.0 * direction]), GEOMETRY, rows=[12])
    assert image[12, 10] == pytest.approx(7.0) and np.isfinite(image).sum() == 1


def test_lidar_table_round_trip_and_errors():
    table = lidar_table(GEOMETRY)
    assert "beam_elevations" not in table
    assert geometry_from_table(table, "m.toml") == GEOMETRY
    uneven = SphericalGeometry(beams=3, columns=8, beam_elevations=(2.0, -1.0, -10.0))
    assert geometry_from_table(lidar_table(uneven), "m.toml") == uneven
    assert geometry_from_table({"columns": 2048}, "m.toml", KITTI_GEOMETRY).columns == 2048
    with pytest.raises(ConfigError, match="m.toml: unknown key 'lidar.rings'"):
        geometry_from_table({"rings": 3}, "m.toml")
    with pytest.raises(ConfigError, match="m.toml: 'lidar.beams' must be a number"):
        geometry_from_table({"beams": "64"}, "m.toml")
    with pytest.raises(ConfigError, match=r"m.toml: \[lidar\]: lidar: need -90 <= fov_down < fov_up"):
        geometry_from_table({"fov_up": -30.0}, "m.toml")
