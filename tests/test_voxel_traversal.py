"""Voxel traversal (Amanatides & Woo) and free-space clearing of the voxel map (object removal)."""

import numpy as np
import pytest
from reference_kernels import reference_pairs, reference_voxels

import mabdi.voxels.voxel_map as voxel_map
import mabdi.voxels.traversal as voxel_traversal
from mabdi.voxels.voxel_map import VoxelMap
from mabdi.surfaces.voxel_planes import FilterVoxelPlanes
from mabdi.voxels.traversal import ray_voxels, traverse_voxels


def _along_x(xs):
    return np.column_stack([xs, np.zeros_like(xs), np.zeros_like(xs)])


def test_a_ray_along_x_crosses_the_voxels_it_runs_through():
    origin, end = [0.01, 0.05, 0.05], [[0.49, 0.05, 0.05]]
    np.testing.assert_array_equal(traverse_voxels(origin, end, 0.1), _along_x(np.arange(5)))
    # backwards, and mirrored into negative coordinates
    np.testing.assert_array_equal(traverse_voxels([0.49, 0.05, 0.05], [[0.01, 0.05, 0.05]], 0.1), _along_x(np.arange(5)))
    mirrored = traverse_voxels([-0.01, -0.05, -0.05], [[-0.49, -0.05, -0.05]], 0.1)
    np.testing.assert_array_equal(mirrored, _along_x(np.arange(-5, 0)) - [0, 1, 1])
    # without the end's voxel: only the voxels the ray leaves
    np.testing.assert_array_equal(traverse_voxels(origin, end, 0.1, include_end=False), _along_x(np.arange(4)))
    # an end exactly on a boundary: the segment is half-open, voxel 5 is not entered, voxel 4 is left
    for include_end in (True, False):
        found = traverse_voxels(origin, [[0.5, 0.05, 0.05]], 0.1, include_end=include_end)
        np.testing.assert_array_equal(found, _along_x(np.arange(5)))


def test_the_margin_stops_the_segment_short():
    origin, end = np.array([0.01, 0.05, 0.05]), np.array([[0.49, 0.05, 0.05]])
    # 0.49 - 0.15 = 0.34: voxels 0..3, and 0..2 when the end's voxel is dropped
    np.testing.assert_array_equal(traverse_voxels(origin, end, 0.1, 0.15), _along_x(np.arange(4)))
    np.testing.assert_array_equal(traverse_voxels(origin, end, 0.1, 0.15, include_end=False), _along_x(np.arange(3)))
    # a margin as long as the ray, or a ray of length 0: nothing
    assert len(traverse_voxels(origin, end, 0.1, 0.48)) == 0
    assert len(traverse_voxels(origin, origin[None], 0.1)) == 0
    # one margin per ray
    ends = np.array([[0.49, 0.05, 0.05], [0.49, 0.15, 0.05]])
    origins = np.array([[0.01, 0.05, 0.05], [0.01, 0.15, 0.05]])
    found = traverse_voxels(origins, ends, 0.1, np.array([0.0, 0.3]))
    expected = np.concatenate([_along_x(np.arange(5)), _along_x(np.arange(2)) + [0, 1, 0]])
    np.testing.assert_array_equal(found, np.unique(expected, axis=0))  # rows sorted by (i, j, k)


def _random_rays(rng, n=400):
    origins = rng.uniform(-3.0, 3.0, (n, 3))
    ends = origins + rng.normal(0.0, 1.5, (n, 3))
    ends[:40, 1:] = origins[:40, 1:]  # along x
    ends[40:80, [0, 2]] = origins[40:80, [0, 2]]  # along y
    ends[80:120, 2] = origins[80:120, 2]  # in a plane z = const
    ends[120:130] = origins[120:130]  # length 0
    ends[130:140] = origins[130:140] + rng.normal(0.0, 30.0, (10, 3))  # very long
    margins = rng.uniform(0.0, 0.3, n)
    margins[140:150] = 0.0
    margins[150:155] = 100.0  # longer than the ray
    return origins, ends, margins


@pytest.mark.parametrize("include_end", [True, False])
def test_traversal_matches_the_exact_reference_on_random_rays(include_end, monkeypatch):
    rng = np.random.default_rng(11)
    origins, ends, margins = _random_rays(rng)
    for s in (0.1, 0.05):
        expected = reference_voxels(origins, ends, s, margins, include_end=include_end)
        assert len(expected) > 1000
        assert (expected < 0).any()  # negative coordinates
        np.testing.assert_array_equal(traverse_voxels(origins, ends, s, margins, include_end=include_end), expected)
        rays, voxels = ray_voxels(origins, ends, s, margins, include_end=include_end)
        ref_rays, ref_voxels = reference_pairs(origins, ends, s, margins, include_end=include_end)
        np.testing.assert_array_equal(rays, ref_rays)  # the same crossings, in the same order along each ray
        np.testing.assert_array_equal(voxels, ref_voxels)
        steps = np.abs(np.diff(voxels, axis=0)).sum(axis=1)[np.diff(rays) == 0]
        assert steps.max() == 1  # consecutive voxels of a ray share a face
    # the sort path (a bounding box too big for the mask) agrees with the mask and the numpy reference
    compiled = traverse_voxels(origins, ends, 0.1, margins, include_end=include_end)
    monkeypatch.setattr(voxel_traversal, "MASK_VOXELS", 0)
    np.testing.assert_array_equal(traverse_voxels(origins, ends, 0.1, margins, include_end=include_end), compiled)
    np.testing.assert_array_equal(reference_voxels(origins, ends, 0.1, margins, include_end=include_end), compiled)


def test_traversal_inputs():
    assert traverse_voxels(np.zeros(3), np.zeros((0, 3)), 0.05).shape == (0, 3)
    with pytest.raises(ValueError, match="finite"):
        traverse_voxels(np.zeros(3), np.array([[np.nan, 0.0, 1.0]]), 0.05)
    with pytest.raises(ValueError, match="margins"):
        traverse_voxels(np.zeros(3), np.ones((2, 3)), 0.05, -0.01)
    with pytest.raises(ValueError, match="margins"):
        traverse_voxels(np.zeros(3), np.ones((2, 3)), 0.05, np.zeros(3))
    with pytest.raises(ValueError, match="origins"):
        traverse_voxels(np.zeros((3, 3)), np.ones((2, 3)), 0.05)
    with pytest.raises(ValueError, match="voxel_size"):
        traverse_voxels(np.zeros(3), np.ones((2, 3)), 0.0)


def _box_and_wall(rng):
    """A box's face (y = 1 m, 0.6 m square) in front of a wall (y = 3 m), 3 mm noise; a camera at y = -0.5."""
    face = np.column_stack([rng.uniform(-0.3, 0.3, 30_000), rng.normal(1.0, 0.003, 30_000), rng.uniform(0.0, 0.6, 30_000)])
    wall = np.column_stack([rng.uniform(-1.5, 1.5, 60_000), rng.normal(3.0, 0.003, 60_000), rng.uniform(-0.7, 1.3, 60_000)])
    camera = np.array([0.0, -0.5, 0.3])
    return face, wall, camera


def _rays_through(camera, face_points, depth):
    """End points on the plane y = ``depth`` of the rays from ``camera`` through ``face_points``."""
    scale = (depth - camera[1]) / (face_points[:, 1] - camera[1])
    return camera + (face_points - camera) * scale[:, None]


def test_rays_through_a_departed_box_clear_it_and_leave_the_wall_behind():
    rng = np.random.default_rng(5)
    face, wall, camera = _box_and_wall(rng)
    voxels = VoxelMap()
    voxels.add_points(face)
    voxels.add_points(wall)
    face_voxels = np.unique(voxels.voxel_indices(face), axis=0)
    wall_voxels = np.unique(voxels.voxel_indices(wall), axis=0)
    wall_before = voxels.moments(wall_voxels)
    # the box left: the camera sees the wall through where the face was (a 5 mm grid of rays, past its edges)
    u, w = np.meshgrid(np.arange(-0.36, 0.36, 0.005), np.arange(-0.06, 0.66, 0.005))
    through = np.column_stack([u.ravel(), np.ones(u.size), w.ravel()])
    ends = _rays_through(camera, through, 3.0) + [0.0, 1.0, 0.0] * rng.normal(0.0, 0.003, (u.size, 1))
    margins = 0.02 * np.linalg.norm(ends - camera, axis=1) / (ends[:, 1] - camera[1])  # tau = 2 cm in depth

    cleared = voxels.clear_free_space(camera, ends, margins)

    np.testing.assert_array_equal(voxels.counts(face_voxels), 0)  # the whole face is gone
    np.testing.assert_array_equal(voxels.moments(wall_voxels), wall_before)  # the wall is untouched
    np.testing.assert_array_equal(cleared.voxels, face_voxels)  # exactly the face's voxels, sorted
    np.testing.assert_array_equal(voxels.last_changed, face_voxels)
    assert cleared.points == len(face)
    assert voxels.number_of_points == len(wall)
    np.testing.assert_array_equal(cleared.blocks, np.unique(voxels.block_of(face_voxels)))
    # again: nothing left to clear
    again = voxels.clear_free_space(camera, ends, margins)
    assert len(again) == 0 and again.points == 0 and len(again.blocks) == 0


def test_rays_passing_above_a_floor_leave_it():
    # rays to a wall pass 3 cm or more above a floor: they cross its voxels but not its points
    rng = np.random.default_rng(2)
    floor = np.column_stack([rng.uniform(-1.0, 1.0, 80_000), rng.uniform(0.0, 2.9, 80_000), rng.normal(0.0, 0.003, 80_000)])
    wall = np.column_stack([rng.uniform(-1.0, 1.0, 40_000), rng.normal(3.0, 0.003, 40_000), rng.uniform(0.0, 1.0, 40_000)])
    voxels = VoxelMap()
    voxels.add_points(np.concatenate([floor, wall]))
    before = voxels.moments(voxels.occupied_voxels())
    camera = np.array([0.0, -0.5, 0.4])
    ends = np.column_stack([rng.uniform(-0.8, 0.8, 20_000), rng.normal(3.0, 0.003, 20_000), rng.uniform(0.03, 0.9, 20_000)])
    crossed = traverse_voxels(camera, ends, voxels.voxel_size, 0.02, include_end=False)
    assert np.isin(voxel_map.pack_keys(crossed), voxel_map.pack_keys(voxels.voxel_indices(floor))).sum() > 30
    assert len(voxels.clear_free_space(camera, ends, 0.02)) == 0
    np.testing.assert_array_equal(voxels.moments(voxels.occupied_voxels()), before)


def test_compiled_and_numpy_clearing_agree(monkeypatch):
    rng = np.random.default_rng(9)
    points = rng.normal([0.5, 1.0, 0.2], 0.7, (60_000, 3))
    origins = rng.normal([0.5, 1.0, 0.2], 1.0, (800, 3))
    ends = rng.normal([0.5, 1.0, 0.2], 1.0, (800, 3))
    margins = rng.uniform(0.0, 0.05, 800)
    results = []
    # the compiled pass; the numpy path around the compiled traversal (CLEAR_BLOCKS 0); that path with the
    # numpy reference traversal
    for patch in (None, ("CLEAR_BLOCKS", voxel_map, 0), ("ray_voxels", voxel_traversal, reference_pairs)):
        if patch is not None:
            monkeypatch.setattr(patch[1], patch[0], patch[2])
        voxels = VoxelMap()
        voxels.add_points(points)
        cleared = voxels.clear_free_space(origins, ends, margins)
        results.append((cleared, voxels.moments(voxels.occupied_voxels()), voxels.occupied_voxels()))
    assert len(results[0][0]) > 50
    for cleared, moments, occupied in results[1:]:
        np.testing.assert_array_equal(cleared.voxels, results[0][0].voxels)
        assert cleared.points == results[0][0].points
        np.testing.assert_array_equal(occupied, results[0][2])
        np.testing.assert_array_equal(moments, results[0][1])


def test_clearing_voxels_without_points_changes_nothing():
    rng = np.random.default_rng(4)
    points = rng.normal([0.0, 0.0, 0.0], 0.05, (2000, 3))
    voxels = VoxelMap()
    assert len(voxels.clear_free_space(np.zeros(3), np.ones((3, 3)))) == 0  # an empty map
    voxels.add_points(points)
    occupied = voxels.occupied_voxels()
    before = voxels.moments(occupied)
    empty_in_block = np.array([[19, 19, 19], [10, -10, 5]])
    far_away = np.array([[500, 500, 500], [-(1 << 40), 0, 0]])
    cleared = voxels.clear_voxels(np.concatenate([empty_in_block, far_away]))
    assert len(cleared) == 0 and cleared.points == 0
    assert len(voxels.clear_free_space([2.0, 2.0, 2.0], [[3.0, 2.5, 2.0], [2.0, 2.0, 4.0]])) == 0
    np.testing.assert_array_equal(voxels.moments(occupied), before)
    # clearing some voxels (duplicates fine) removes exactly their points
    chosen = np.concatenate([occupied[:5], occupied[:2], empty_in_block])
    cleared = voxels.clear_voxels(chosen)
    order = np.lexsort(occupied[:5].T[::-1])
    np.testing.assert_array_equal(cleared.voxels, occupied[:5][order])
    assert cleared.points == int(before[:5, 0].sum())
    assert voxels.number_of_points == len(points) - cleared.points
    np.testing.assert_array_equal(voxels.moments(occupied[5:]), before[5:])


def test_re_meshing_after_clearing_drops_the_box_and_keeps_the_wall():
    rng = np.random.default_rng(6)
    face, wall, camera = _box_and_wall(rng)
    planes = FilterVoxelPlanes(output="full")
    planes.add_points(np.concatenate([face, wall]))
    u, w = np.meshgrid(np.arange(-0.36, 0.36, 0.005), np.arange(-0.06, 0.66, 0.005))
    ends = _rays_through(camera, np.column_stack([u.ravel(), np.ones(u.size), w.ravel()]), 3.0)
    wall_only = FilterVoxelPlanes(output="full")
    wall_only.add_points(wall)
    assert planes.number_of_triangles > wall_only.number_of_triangles
    planes.map.clear_free_space(camera, ends, 0.02)
    planes.remesh_all()
    assert planes.number_of_triangles == wall_only.number_of_triangles
