"""Held-out LiDAR scans (mabdi.evaluate.held_out_scans): recall, precision and what a scan could see, on small
scenes whose answers are known (planes, an occluding square, a ceiling above the field of view)."""

import math

import numpy as np
import pytest
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.evaluate.held_out_scans import (
    HeldOutScans,
    MapScene,
    by_band,
    fscore,
    near_points,
    nearest_sensor_distances,
    precision_samples,
    recall,
    scan_in_world,
    score_map,
    seen_from_scans,
)
from mabdi.polydata import triangles_polydata

pytest.importorskip("open3d")


def rectangles(*boxes) -> vtkPolyData:
    """Horizontal rectangles (x0, x1, y0, y1, z), two triangles each, in one mesh."""
    points, triangles = [], []
    for x0, x1, y0, y1, z in boxes:
        base = len(points)
        points += [(x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)]
        triangles += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    return triangles_polydata(np.array(points, dtype=np.float64), np.array(triangles))


def grid(x0, x1, y0, y1, z, step) -> np.ndarray:
    """Points at the centres of a ``step`` grid over a rectangle, at height z."""
    xs = np.arange(x0 + step / 2, x1, step)
    ys = np.arange(y0 + step / 2, y1, step)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    return np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], axis=1)


def pose(translation=(0.0, 0.0, 0.0), rotation=None) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = translation
    if rotation is not None:
        out[:3, :3] = rotation
    return out


ROLL_180 = np.diag([1.0, -1.0, -1.0])  # the sensor upside down: its z axis points down


def test_scan_in_world_keeps_returns_within_the_range_limits_and_applies_the_pose():
    points = np.array(
        [[0.5, 0, 0, 9], [2.0, 0, 0, 9], [0, 3.0, 0, 9], [0, 0, 10.0, 9], [np.nan, 0, 0, 9], [1.0, 0, 0, 9]], dtype=np.float32
    )
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 degrees about z
    world = scan_in_world(points, pose((10.0, 20.0, 1.0), quarter), range_min=1.0, range_max=10.0)
    # 0.5 m is below range_min, 10 m is not below range_max, NaN is no return, 1.0 m is not above range_min
    np.testing.assert_allclose(world, [[10.0, 22.0, 1.0], [7.0, 20.0, 1.0]], atol=1e-12)


def test_held_out_scans_pool_the_scans_and_remember_which_scan_each_point_came_from():
    scans = [np.array([[2.0, 0, 0], [0.1, 0, 0]]), np.array([[0, 2.0, 0], [0, 0, 3.0], [0, 0, 4.0]])]
    held = HeldOutScans.from_scans(scans, [pose(), pose((1.0, 0, 0))], 0.5, 50.0, (-30.0, 30.0))
    assert len(held) == 4
    np.testing.assert_array_equal(held.scan, [0, 1, 1, 1])
    np.testing.assert_allclose(held.points[1], [1.0, 2.0, 0.0])
    np.testing.assert_allclose(held.sensor_positions, [[0, 0, 0], [1.0, 0, 0]])
    assert held.elevation_limits == (-30.0, 30.0)


def test_distances_are_to_the_nearest_triangle_even_far_from_the_origin():
    far = np.array([1000.0, -2000.0, 50.0])  # float32 alone would keep ~0.1 mm here; the scene's origin keeps more
    plane = rectangles((-5 + far[0], 5 + far[0], -5 + far[1], 5 + far[1], far[2]))
    scene = MapScene(plane)
    points = far + np.array([[0.0, 0.0, 0.02], [1.0, 2.0, -0.07], [0.0, 0.0, 0.2], [6.0, 0.0, 0.0], [8.0, 9.0, 0.0]])
    np.testing.assert_allclose(scene.distances(points), [0.02, 0.07, 0.2, 1.0, 5.0], atol=2e-5)
    shares, distances = recall(scene, points, (0.05, 0.10))
    assert shares == {0.05: pytest.approx(0.2), 0.10: pytest.approx(0.4)}
    assert distances.shape == (5,)


def test_occlusion_is_a_triangle_on_the_segment_before_the_target():
    scene = MapScene(rectangles((-1, 1, -1, 1, 0.5), (-4, 4, -4, 4, 0.0)))
    sensor = np.array([0.0, 0.0, 1.0])
    targets = np.array(
        [
            [0.0, 0.0, 0.0],  # the floor under the square: hidden
            [3.0, 0.0, 0.0],  # the floor beyond the square's shadow (which ends at 2 m): seen
            [0.5, 0.5, 0.5],  # the square itself: its first hit is the target
            [1.9, 0.0, 0.0],  # in the shadow, near its edge
            [0.0, 0.0, 0.52],  # 2 cm above the square: the square lies beyond it
        ]
    )
    np.testing.assert_array_equal(scene.occluded(sensor, targets), [True, False, False, True, False])


def test_seen_area_leaves_out_the_floor_an_occluder_hides():
    """Floor 8 x 8 m, a 2 x 2 m square 0.5 m above its centre, the sensor 1 m above the centre: the square's
    shadow on the floor is 4 x 4 m, so the seen area is 64 - 16 + 4 = 52 m^2 of the 68."""
    mesh = rectangles((-4, 4, -4, 4, 0.0), (-1, 1, -1, 1, 0.5))
    held = HeldOutScans(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), pose((0, 0, 1.0))[None], 0.1, 100.0)
    samples = precision_samples(mesh)
    assert len(samples) == math.ceil(68 / 0.0025)
    seen = seen_from_scans(MapScene(mesh), samples.points, held)
    assert seen.mean() * samples.area == pytest.approx(52.0, abs=0.8)
    on_top = samples.points[:, 2] > 0.25
    assert seen[on_top].all()
    shadow = (np.abs(samples.points[:, :2]) < 1.95).all(axis=1) & ~on_top
    assert not seen[shadow].any()


def test_range_limits_and_the_vertical_field_of_view_bound_what_a_scan_sees():
    """A 6 x 6 m ceiling 1 m above the sensor; a field of view up to 30 degrees sees it only beyond sqrt(3) m
    horizontally, so a disc of 3 pi m^2 is unseen; upside down, the same limits see all of it."""
    ceiling = rectangles((-3, 3, -3, 3, 1.0))
    scene = MapScene(ceiling)
    samples = precision_samples(ceiling)
    upright = HeldOutScans(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), pose()[None], 0.5, 100.0, (-90.0, 30.0))
    seen = seen_from_scans(scene, samples.points, upright)
    assert seen.mean() == pytest.approx((36 - 3 * math.pi) / 36, abs=0.01)
    assert not seen[np.hypot(samples.points[:, 0], samples.points[:, 1]) < 1.7].any()
    flipped = HeldOutScans(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), pose(rotation=ROLL_180)[None], 0.5, 100.0, (-90.0, 30.0))
    assert seen_from_scans(scene, samples.points, flipped).all()
    # range limits: a range_max of 2 m sees the disc of radius sqrt(3) (range sqrt(1 + r^2) < 2) and no farther
    near_only = HeldOutScans(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), pose()[None], 0.5, 2.0)
    assert seen_from_scans(scene, samples.points, near_only).mean() == pytest.approx(3 * math.pi / 36, abs=0.01)


def test_a_map_that_misses_the_occluder_is_scored_against_what_the_scan_saw():
    """The held-out scan saw the floor outside the square's shadow and the square's top (5 cm grids, centred in
    their cells). A map of the floor alone: recall is the floor's share of the points; its seen area is the
    whole floor, and what the scan did not see is imprecise: the 16 m^2 shadow but a band along its edge, 10 cm
    less the 2.5 cm between the edge and the first row of points: (48 + 16 x 0.075) / 64."""
    sensor = np.array([0.0, 0.0, 1.0])
    floor = grid(-4, 4, -4, 4, 0.0, 0.05)
    floor = floor[~(np.abs(floor[:, :2]) < 2).all(axis=1)]
    top = grid(-1, 1, -1, 1, 0.5, 0.05)
    held = HeldOutScans.from_scans([np.concatenate([floor, top]) - sensor], [pose(sensor)], 0.1, 100.0)

    floor_only = score_map(rectangles((-4, 4, -4, 4, 0.0)), held)
    assert floor_only.recall[0.05] == floor_only.recall[0.10] == pytest.approx(len(floor) / (len(floor) + len(top)))
    assert floor_only.area_m2 == pytest.approx(64.0)
    assert floor_only.area_seen_m2 == pytest.approx(64.0)
    assert floor_only.precision == pytest.approx((48 + 16 * 0.075) / 64, abs=0.006)
    assert floor_only.fscore == pytest.approx(fscore(floor_only.precision, floor_only.recall[0.10]))
    assert floor_only.per_scan_recall == [pytest.approx(floor_only.recall[0.10])]

    whole = score_map(rectangles((-4, 4, -4, 4, 0.0), (-1, 1, -1, 1, 0.5)), held)
    assert whole.recall[0.05] == 1.0
    assert whole.area_seen_m2 == pytest.approx(52.0, abs=0.8)
    assert whole.precision > 0.995  # the seen samples all lie by a scanned point; the hidden floor is not counted
    assert whole.fscore > floor_only.fscore


def test_a_map_a_little_off_the_scan_has_recall_by_threshold():
    """Points 7 cm above a 4 x 4 m plane map, on a 6 x 6 m grid: none within 5 cm; within 10 cm those over the
    map and those less than sqrt(0.1^2 - 0.07^2) m beyond its edge; precision 1 (every seen sample lies within
    sqrt(0.025^2 + 0.025^2 + 0.07^2) = 7.8 cm of a point)."""
    sensor = np.array([0.0, 0.0, 2.0])
    points = grid(-3, 3, -3, 3, 0.07, 0.05)
    held = HeldOutScans.from_scans([points - sensor], [pose(sensor)], 0.1, 100.0)
    score = score_map(rectangles((-2, 2, -2, 2, 0.0)), held)
    beyond = np.linalg.norm(np.maximum(np.abs(points[:, :2]) - 2.0, 0.0), axis=1)  # horizontal distance to the map
    assert score.recall[0.05] == 0.0
    assert score.recall[0.10] == pytest.approx(np.mean(np.hypot(beyond, 0.07) <= 0.10))
    assert score.precision == 1.0
    # by range band: every point lies within 5 m of the sensor (at most sqrt(3^2 + 3^2 + 1.93^2) = 4.7 m)
    first, *rest = score.by_range
    assert (first["from_m"], first["to_m"], first["points"]) == (0.0, 5.0, score.points)
    assert first["recall"] == pytest.approx(score.recall[0.10]) and first["precision"] == 1.0
    assert first["samples_seen"] == score.samples_seen
    assert all(band["points"] == 0 and band["samples_seen"] == 0 and math.isnan(band["recall"]) for band in rest)
    assert score.as_dict()["by_range"][-1]["to_m"] is None


def test_supported_area_is_the_imprecise_area_the_integrated_points_lie_on():
    """A held-out scan whose rings cross a 4 x 4 m floor 0.5 m apart (5 cm along each ring) confirms only the floor
    within 10 cm of a ring; the integrated scans' 5 cm grid lies on all of it, so the rest of the floor is
    supported. A 1 x 4 m shelf 0.5 m up beside the floor has no point of either near it: imprecise and not
    supported. Without integrated points the share is not measured (NaN)."""
    sensor = np.array([0.0, 0.0, 2.0])
    rings = np.concatenate([grid(-2, 2, y - 0.025, y + 0.025, 0.0, 0.05) for y in np.arange(-1.75, 2.0, 0.5)])
    held = HeldOutScans.from_scans([rings - sensor], [pose(sensor)], 0.1, 100.0)
    integrated = grid(-2, 2, -2, 2, 0.0, 0.05)
    floor_and_shelf = rectangles((-2, 2, -2, 2, 0.0), (2.5, 3.5, -2, 2, 0.5))

    score = score_map(floor_and_shelf, held, integrated_points=integrated)
    shelf_share = 4.0 / 20.0
    confirmed_floor = 0.2 / 0.5  # a band 10 cm either side of each ring, in every 0.5 m
    assert score.area_seen_m2 == pytest.approx(20.0, abs=0.2)
    assert score.precision == pytest.approx((1 - shelf_share) * confirmed_floor, abs=0.02)
    assert score.supported == pytest.approx((1 - shelf_share) * (1 - confirmed_floor), abs=0.02)
    assert score.precision + score.supported == pytest.approx(1 - shelf_share, abs=0.005)
    first = score.by_range[0]  # every sample lies within 5 m of the sensor
    assert first["supported"] == pytest.approx(score.supported)
    assert all(math.isnan(band["supported"]) for band in score.by_range[1:])

    unmeasured = score_map(floor_and_shelf, held)
    assert math.isnan(unmeasured.supported) and unmeasured.precision == score.precision


def test_an_empty_map_has_no_recall_and_no_precision():
    held = HeldOutScans.from_scans([np.array([[2.0, 0.0, 0.0]])], [pose()], 0.5, 50.0)
    score = score_map(vtkPolyData(), held)
    assert score.recall[0.05] == 0.0 and score.recall[0.10] == 0.0
    assert math.isnan(score.precision) and math.isnan(score.fscore)
    assert score.samples == 0 and score.triangles == 0


def test_range_bands_and_the_nearest_sensor():
    np.testing.assert_allclose(
        nearest_sensor_distances([[3.0, 4.0, 0.0], [10.0, 0.0, 0.0]], [[0.0, 0.0, 0.0], [10.0, 0.0, 1.0]]), [5.0, 1.0]
    )
    assert np.isinf(nearest_sensor_distances([[1.0, 0.0, 0.0]], np.zeros((0, 3)))).all()
    bands = by_band([1.0, 4.0, 6.0, 30.0, 35.0], [True, False, True, True, True], (0.0, 5.0, 10.0, 20.0, math.inf))
    assert bands[0] == (0.0, 5.0, 2, 0.5) and bands[1] == (5.0, 10.0, 1, 1.0) and bands[3] == (20.0, math.inf, 2, 1.0)
    assert bands[2][2] == 0 and math.isnan(bands[2][3])


def test_near_points_and_fscore():
    samples = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    points = np.array([[0.0, 0.0, 0.09], [1.0, 0.11, 0.0]])
    np.testing.assert_array_equal(near_points(samples, points, 0.10), [True, False, False])
    np.testing.assert_array_equal(near_points(samples, np.zeros((0, 3)), 0.10), [False, False, False])
    assert fscore(0.5, 1.0) == pytest.approx(2 / 3)
    assert fscore(0.0, 0.0) == 0.0
    assert math.isnan(fscore(math.nan, 0.5))
