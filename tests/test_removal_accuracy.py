"""Static and dynamic accuracy (the DynamicMap benchmark's SA, DA, AA) on constructed maps with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mabdi.evaluate.removal_accuracy import DYNAMIC, STATIC, UNLABELLED, MapHistory, label_points, removal_accuracy
from mabdi.polydata import triangles_polydata
from mabdi.sources import primitives
from tests.conftest import plane_mesh


def _box(size, centre):
    points, triangles = primitives.box(size)
    return triangles_polydata(points + np.asarray(centre), triangles)


def _grid(x, y, z):
    gx, gy = np.meshgrid(x, y, indexing="ij")
    return np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], axis=1)


def _rectangle(x0, x1, y0, y1, z=0.0):
    points = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])
    return triangles_polydata(points, np.array([[0, 1, 2], [0, 2, 3]]))


# The world: a 4 x 4 m floor (static); a 1 m crate on it that left (its former surface).
FLOOR = plane_mesh((0, 0, 0), (0, 0, 1), size=4.0)
CRATE = _box((1.0, 1.0, 1.0), (0.0, 0.0, 0.5))
FLOOR_POINTS = _grid(np.arange(-1.95, 2.0, 0.1), np.arange(-1.95, 2.0, 0.1), 0.0)  # 40 x 40, none at x = 0
CRATE_TOP = _grid(np.arange(-0.45, 0.5, 0.1), np.arange(-0.45, 0.5, 0.1), 1.0)  # 10 x 10 on the top face
CRATE_SIDE = np.stack([np.full(9, 0.5), np.zeros(9), np.arange(0.1, 1.0, 0.1)], axis=1)  # up the +x face, 0.1 .. 0.9 m
NOISE = np.array([[1.0, 1.0, 0.5], [-1.5, 0.3, 0.2]])  # far from every surface


def test_labels_static_dynamic_and_none():
    points = np.concatenate([FLOOR_POINTS, CRATE_TOP, CRATE_SIDE, NOISE])
    labels = label_points(points, FLOOR, [CRATE])
    assert (labels[:1600] == STATIC).all()
    assert (labels[1600:1700] == DYNAMIC).all()
    side = labels[1700:1709]
    assert side[0] == DYNAMIC  # 10 cm above the floor
    assert (labels[-2:] == UNLABELLED).all()
    wheel = label_points(np.array([[0.5, 0.0, 0.02]]), FLOOR, [CRATE])  # on the crate, 2 cm above the floor
    assert wheel[0] == STATIC  # within 3 cm of the floor: static
    assert (label_points(CRATE_TOP, FLOOR, []) == UNLABELLED).all()


def test_a_map_that_removed_the_crate_and_kept_the_floor():
    raw = np.concatenate([FLOOR_POINTS, CRATE_TOP, CRATE_SIDE, NOISE])
    result = removal_accuracy(raw, FLOOR, FLOOR, [CRATE])
    assert result.static_accuracy == 1.0 and result.dynamic_accuracy == 1.0 and result.associated_accuracy == 1.0
    assert (result.static_points, result.dynamic_points, result.unlabelled) == (1600, 109, 2)


def test_known_shares_lost_and_kept():
    raw = np.concatenate([FLOOR_POINTS, CRATE_TOP, CRATE_SIDE])
    # The final map lost the floor's x > 0 half and kept the crate's top (a ghost), but not its side.
    final = _rectangle(-2.0, 0.0, -2.0, 2.0)
    top = _rectangle(-0.5, 0.5, -0.5, 0.5, z=1.0)
    from mabdi.polydata import polydata_arrays

    p1, t1 = polydata_arrays(final)
    p2, t2 = polydata_arrays(top)
    both = triangles_polydata(np.concatenate([p1, p2]), np.concatenate([t1, t2 + len(p1)]))
    result = removal_accuracy(raw, both, FLOOR, [CRATE])
    assert result.static_accuracy == pytest.approx(0.5)  # 800 of 1600 floor points kept
    # 100 top points kept; of the 9 side points, the one at 0.9 m lies 10 cm below the top face's edge: removed.
    assert result.dynamic_accuracy == pytest.approx(9 / 109)
    assert result.associated_accuracy == pytest.approx(math.sqrt(0.5 * 9 / 109))
    # A map within 1 cm keeps a point; 1.5 cm away does not.
    lifted = _rectangle(-2.0, 2.0, -2.0, 2.0, z=0.009)
    assert removal_accuracy(FLOOR_POINTS, lifted, FLOOR).static_accuracy == 1.0
    assert removal_accuracy(FLOOR_POINTS, _rectangle(-2.0, 2.0, -2.0, 2.0, z=0.015), FLOOR).static_accuracy == 0.0


def test_no_dynamic_points_gives_nan():
    result = removal_accuracy(FLOOR_POINTS, FLOOR, FLOOR, [])
    assert result.static_accuracy == 1.0 and math.isnan(result.dynamic_accuracy) and math.isnan(result.associated_accuracy)
    assert result.as_dict()["dynamic_points"] == 0


def test_map_history_gathers_distinct_vertices_of_every_map():
    history = MapHistory()
    history.add(FLOOR)
    history.add(FLOOR)
    assert len(history) == 4
    history.add(CRATE)
    assert len(history) == 4 + 8
    np.testing.assert_array_equal(np.unique(history.points, axis=0), history.points)
    # The crate's vertices are all dynamic (its bottom corners sit on the floor: static).
    labels = label_points(history.points, FLOOR, [CRATE])
    assert (labels == DYNAMIC).sum() == 4 and (labels == STATIC).sum() == 8


def test_bench_table_shows_the_accuracies():
    from mabdi.evaluate.bench import dynamic_table

    row = {
        "method": "mabdi",
        "triangles_per_frame": [10, 12],
        "dynamic": {
            "ghost_share_end": 0.005,
            "frames_to_clear": {"crate": 2},
            "static_loss": {"area_m2": 0.0},
            "removal": {"static_accuracy": 0.995, "dynamic_accuracy": None, "associated_accuracy": None},
        },
    }
    table = dynamic_table({"methods": [row]})
    assert "| SA | DA | AA |" in table
    assert table.splitlines()[-1] == "| mabdi | 0.50% | crate: 2 | 0.0000 | 0.9950 | - | - |"
