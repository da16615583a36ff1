"""Depth registered to a colour camera: a regular pattern of one-pixel holes is filled where the pixels on either
side agree, never across a depth edge, and only on frames that are fragmented by it."""

from __future__ import annotations

import numpy as np
import pytest

import mabdi
from mabdi.camera import Intrinsics, look_at
from mabdi.depth import DepthFrame
from mabdi.depth_holes import fill_pixel_holes, is_fragmented
from mabdi.errors import ConfigError
from mabdi.polydata import polydata_area
from mabdi.sources.frames import FrameList, SourceDepthFrames

INTRINSICS = Intrinsics(fx=60.0, fy=60.0, cx=40.0, cy=30.0, width=80, height=60)


def _wall(distance: float = 2.0) -> np.ndarray:
    """Depth of a wall facing the camera, tilted 30 degrees about the vertical (depth varies across columns)."""
    u = (np.arange(INTRINSICS.width) + 0.5 - INTRINSICS.cx) / INTRINSICS.fx
    slope = np.tan(np.radians(30.0))
    z = distance / (1.0 - slope * u)  # the plane z = distance + slope * x, with x = u z
    return np.broadcast_to(z, (INTRINSICS.height, INTRINSICS.width)).astype(np.float32).copy()


def _pattern(shape) -> np.ndarray:
    """A third of the pixels, each a hole of one pixel with returns left, right, above and below it (as a depth
    image reprojected to a colour camera leaves them); no return keeps all four neighbours."""
    rows, cols = np.indices(shape)
    return (rows + 2 * cols) % 3 == 0


def test_a_patterned_frame_is_fragmented_and_filled_on_the_surface():
    truth = _wall()
    holed = truth.copy()
    holed[_pattern(holed.shape)] = np.nan
    assert is_fragmented(holed) and not is_fragmented(truth)
    filled, count = fill_pixel_holes(holed)
    assert np.isfinite(filled[1:-1, 1:-1]).all()  # inside the border every hole has a pair above and below
    assert count == int(np.isfinite(filled).sum() - np.isfinite(holed).sum())
    assert np.nanmax(np.abs(filled - truth)) < 2e-3  # the mean of the two sides, on a slanted wall at 1.5-3.2 m


def test_no_hole_is_bridged_across_a_depth_edge():
    depth = np.full((7, 7), 2.0, dtype=np.float32)
    depth[:, 4:] = 2.3  # a step of 30 cm between columns 3 and 4
    depth[[0, 2, 4], 3] = np.nan  # holes along the step: 2.0 on their left, 2.3 on their right
    filled, count = fill_pixel_holes(depth)
    # the up-down pairs along the step agree (2.0 above and below), the left-right pairs across it do not
    assert count == 2 and filled[2, 3] == pytest.approx(2.0) and filled[4, 3] == pytest.approx(2.0)
    assert np.isnan(filled[0, 3])  # on the border: only the pair across the step is whole
    lone = np.full((3, 3), 2.0, dtype=np.float32)
    lone[1, :] = [2.0, np.nan, 2.5]
    lone[0, 1] = lone[2, 1] = np.nan
    lone[0, 0] = lone[0, 2] = 1.0  # both diagonals pair 1.0 with 2.0
    assert np.isnan(fill_pixel_holes(lone)[0][1, 1])  # every pair around the centre crosses a jump


def test_the_noise_widens_what_agrees():
    depth = np.full((3, 3), np.nan, dtype=np.float32)
    depth[1, 0], depth[1, 2] = 3.00, 3.06  # 2% apart: beyond 1% of the depth alone
    assert fill_pixel_holes(depth)[1] == 0
    sigma = lambda z: 0.0015 * z * z  # noqa: E731 - a Kinect's 13.5 mm at 3 m
    assert fill_pixel_holes(depth, sigma)[0][1, 1] == pytest.approx(3.03)


def _frames(depth, count=3):
    poses = [look_at([0.02 * i, -0.01 * i, 0.0], [0.02 * i, -0.01 * i, 1.0], up=(0.0, -1.0, 0.0)) for i in range(count)]
    return FrameList([DepthFrame(depth, INTRINSICS, pose, i) for i, pose in enumerate(poses)], "wall")


@pytest.mark.parametrize("surface", ["pixel_grid", "quadtree"])
def test_the_surfaces_mesh_a_patterned_wall_as_the_whole_wall(surface):
    truth = _wall()
    holed = truth.copy()
    holed[_pattern(holed.shape)] = np.nan
    areas = {}
    for name, depth, holes in (("whole", truth, "auto"), ("filled", holed, "auto"), ("left", holed, False)):
        loop = mabdi.MabdiLoop(_frames(depth), surface=surface, noise="kinect", pixel_holes=holes)
        records = [loop.step(i) for i in range(3)]
        areas[name] = polydata_area(loop.mesh())
        if name == "filled":
            assert records[0].filled_pixels > 0.99 * int(_pattern(holed.shape).sum())
        else:
            assert all(r.filled_pixels == 0 for r in records)
    assert areas["filled"] > 0.97 * areas["whole"]
    assert areas["left"] < 0.5 * areas["whole"]  # what the surfaces make of the holes left as they are


def test_frames_with_real_no_returns_are_left_as_they_are():
    depth = _wall()
    depth[10:14, 20:30] = np.nan  # a black patch: no returns over a region
    depth[40, 50] = np.nan  # and a lone pixel
    source = SourceDepthFrames(_frames(depth, 1))
    source.Update()
    assert source.filled_pixels == 0
    forced = SourceDepthFrames(_frames(depth, 1), pixel_holes=True)
    forced.Update()
    assert forced.filled_pixels >= 1  # the lone pixel; the patch's inner pixels have no returning pair
    with pytest.raises(ConfigError, match="pixel_holes"):
        SourceDepthFrames(_frames(depth, 1), pixel_holes="sometimes")
