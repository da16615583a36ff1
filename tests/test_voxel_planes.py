"""FilterVoxelPlanes and VoxelMap (seed 000): statistics, sliding window, polygons, increments, colours, the loop."""

import itertools

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy

from conftest import check_table_loop
from mabdi.errors import ConfigError
from mabdi.voxels.voxel_map import VoxelMap, moments_to_gaussian
from mabdi.surfaces.voxel_planes import (
    FilterVoxelPlanes,
    VoxelPlanesParameters,
    cube_polygons,
    fan_triangles,
    longest_edges,
    plane_patches,
)
from mabdi.mesh_maps.colours import colours_by_normal, normal_colours_float
from mabdi.polydata import polydata_arrays

S = 0.05


def plane_points(normal, origin, half, count, sigma, seed=0):
    """``count`` points on a square of side 2 * half in the plane, with Gaussian noise along the normal."""
    rng = np.random.default_rng(seed)
    n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    uv = rng.uniform(-half, half, (count, 2))
    offset = sigma * rng.standard_normal(count)
    return uv[:, :1] * u + uv[:, 1:] * v + offset[:, None] * n + np.asarray(origin), n


def all_patches(filter_: FilterVoxelPlanes):
    anchors = filter_.candidate_anchors(filter_.map.block_keys())
    return plane_patches(filter_.map, anchors, filter_.parameters)


def test_statistics_match_the_points_far_from_the_origin():
    rng = np.random.default_rng(3)
    points = rng.normal([1000.02, -500.01, 3.0], 0.01, (5000, 3))
    voxels = VoxelMap()
    voxels.add_points(points)
    index = voxels.voxel_indices(points)
    first = np.all(index == index[0], axis=1)
    n, centroid, cov = voxels.gaussians(index[:1])
    assert n[0] == first.sum()
    np.testing.assert_allclose(centroid[0], points[first].mean(axis=0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(cov[0], np.cov(points[first].T, bias=True), rtol=1e-9, atol=1e-15)
    assert voxels.number_of_points == 5000


def test_compiled_and_numpy_statistics_agree(monkeypatch):
    import mabdi.voxels.voxel_map as voxel_map

    rng = np.random.default_rng(8)
    points = rng.normal([-3.0, 0.4, 1.2], 0.8, (50_000, 3))  # negative coordinates, many blocks
    compiled = VoxelMap()
    compiled.add_points(points[:20_000])
    changed = compiled.add_points(points[20_000:])
    # the numpy sums (the path for points whose blocks are too spread for the compiled passes)
    monkeypatch.setattr(voxel_map.VoxelMap, "_add_compiled", lambda self, columns, colours=None: None)
    reference = VoxelMap()
    reference.add_points(points[:20_000])
    expected = reference.add_points(points[20_000:])
    np.testing.assert_array_equal(changed[np.lexsort(changed.T)], expected[np.lexsort(expected.T)])
    voxels = reference.occupied_voxels()
    np.testing.assert_array_equal(compiled.occupied_voxels(), voxels)
    np.testing.assert_allclose(compiled.moments(voxels), reference.moments(voxels), rtol=1e-9, atol=1e-12)


def test_noisy_plane_gives_planar_convex_polygons_on_the_plane():
    # a tilted 1 m square with sigma = 5 mm noise, at Kinect-like density (300k points per m^2)
    origin = np.array([0.3, -2.1, 0.7])
    points, normal = plane_points([0.2, -0.3, 1.0], origin, 0.5, 300_000, 0.005)
    surface = FilterVoxelPlanes()
    surface.add_points(points)
    patches = all_patches(surface)
    vertices, sizes, owner = cube_polygons(patches.normals, patches.centroids, patches.centres, S / 2)
    assert len(sizes) > 300
    assert sizes.min() >= 3 and sizes.max() <= 6
    angles = np.degrees(np.arccos(np.clip(np.abs(patches.normals[owner] @ normal), 0, 1)))
    # windows wholly inside the square: within 2 degrees; at the square's edge the cube faces cut
    # the noisy slab on one side only, which tilts the fit a little more (measured 2.0-3.1 degrees)
    u = np.cross(normal, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    offset = patches.centroids[owner] - origin
    interior = np.maximum(np.abs(offset @ u), np.abs(offset @ v)) < 0.5 - 2 * S
    assert interior.mean() > 0.5
    assert angles[interior].max() < 2.0
    assert angles.max() < 3.5
    assert np.abs((vertices - origin) @ normal).max() < 5e-3
    # each polygon: its vertices on its own plane, and every turn the same way round its normal
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    for k in range(len(sizes)):
        ring = vertices[starts[k] : starts[k] + sizes[k]]
        n = patches.normals[owner[k]]
        assert np.abs((ring - patches.centroids[owner[k]]) @ n).max() < 1e-9
        edges = np.roll(ring, -1, axis=0) - ring
        turns = np.cross(edges, np.roll(edges, -1, axis=0)) @ n
        assert (turns > 0).all(), f"polygon {k} is not convex counter-clockwise"
    # the output mesh carries normals (n_z >= 0), colours and patch keys
    mesh = surface.mesh()
    cells = mesh.GetNumberOfCells()
    assert cells == (sizes - 2).sum()
    assert (vtk_to_numpy(mesh.GetCellData().GetArray("Normals"))[:, 2] >= 0).all()
    assert vtk_to_numpy(mesh.GetCellData().GetArray("rgb")).shape == (cells, 3)
    assert vtk_to_numpy(mesh.GetCellData().GetArray("patch_key")).shape == (cells,)


def test_sliding_window_meshes_a_plane_that_clips_a_voxel_corner():
    """Seed Fig. 3: the plane x + y + z = 2 cm only clips the corner of voxel (0, 0, 0)."""
    from mabdi.evaluate import distances_to_mesh

    points, normal = plane_points([1.0, 1.0, 1.0], [0.02 / 3] * 3, 0.2, 200_000, 0.0)
    clip = np.array([0.02, 0.02, 0.02]) / 3  # centre of the corner triangle inside voxel (0, 0, 0)

    def clip_distance(window):
        surface = FilterVoxelPlanes(VoxelPlanesParameters(window=window))
        surface.add_points(points)
        return surface, distances_to_mesh(clip[None], surface.mesh())[0]

    per_voxel, missed = clip_distance(1)
    sliding, met = clip_distance(2)
    assert per_voxel.map.counts(np.zeros((1, 3), dtype=np.int64))[0] > 0  # the corner has points ...
    assert missed > 3e-3  # ... but on its own it is not planar, so nothing covers it
    assert met < 1e-6


def test_incremental_equals_batch():
    rng = np.random.default_rng(5)
    points, _ = plane_points([0.1, 0.4, 1.0], [-1.3, 0.2, 0.4], 0.6, 120_000, 0.004)
    points = points[rng.permutation(len(points))]
    batch, halves = FilterVoxelPlanes(), FilterVoxelPlanes()
    batch.add_points(points)
    halves.add_points(points[:60_000])
    halves.add_points(points[60_000:])
    voxels = batch.map.occupied_voxels()
    np.testing.assert_array_equal(voxels, halves.map.occupied_voxels())
    np.testing.assert_allclose(halves.map.moments(voxels), batch.map.moments(voxels), rtol=1e-9, atol=1e-12)
    a, b = batch.mesh(), halves.mesh()
    va, ta = polydata_arrays(a)
    vb, tb = polydata_arrays(b)
    np.testing.assert_array_equal(ta, tb)
    np.testing.assert_allclose(va, vb, atol=1e-6)


def points_polydata(points):
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkPolyData

    data = vtkPolyData()
    vtk_points = vtkPoints()
    vtk_points.SetData(numpy_to_vtk(points, deep=True))
    data.SetPoints(vtk_points)
    return data


def test_only_touched_blocks_are_remeshed_and_replaced_in_the_world_mesh():
    from mabdi.stages.world_mesh import FilterWorldMesh

    left, _ = plane_points([0, 0, 1], [0.5, 0.5, 0.2], 0.4, 50_000, 0.0, seed=1)
    right, _ = plane_points([0, 0, 1], [3.5, 0.5, 0.2], 0.4, 50_000, 0.0, seed=2)
    surface = FilterVoxelPlanes()
    world = FilterWorldMesh()
    world.SetInputConnection(surface.GetOutputPort())
    changed = []
    for batch in (left, left, right):  # the same points twice: re-meshed, not stacked
        surface.SetInputDataObject(points_polydata(batch))
        world.Update()
        changed.append(set(surface.changed_blocks.tolist()))
        assert world.number_of_cells == surface.mesh().GetNumberOfCells()
    assert changed[0] == changed[1]
    assert not changed[2] & changed[0]  # new points far away leave the old blocks alone
    patches = set(surface.patch_keys(np.array(sorted(changed[0] | changed[2]), dtype=np.int64)).tolist())
    assert len(patches) == 2 and sorted(world.patch_keys) == sorted(f"patch_{k}" for k in patches)


def test_small_blocks_are_grouped_into_patches_of_forty_voxels_replaced_whole():
    from mabdi.stages.world_mesh import PATCH_KEY_ARRAY, FilterWorldMesh
    from mabdi.voxels.voxel_map import pack_keys, unpack_keys

    assert FilterVoxelPlanes().patch_blocks == 2  # 1 m blocks of 5 cm voxels: 2 x 2 x 2 blocks, 40 voxels a side
    surface = FilterVoxelPlanes(VoxelPlanesParameters(voxel_size=0.2, epsilon=0.05))  # 1 m blocks of 5 voxels
    assert surface.patch_blocks == 8  # 8 x 8 x 8 blocks: 40 voxels on a side
    world = FilterWorldMesh()
    world.SetInputConnection(surface.GetOutputPort())
    floor, _ = plane_points([0, 0, 1], [8.0, 8.0, 0.3], 7.9, 400_000, 0.0, seed=3)  # 16 m: 2 x 2 patches
    surface.SetInputDataObject(points_polydata(floor))
    world.Update()
    full = surface.mesh()
    keys = vtk_to_numpy(full.GetCellData().GetArray(PATCH_KEY_ARRAY))
    assert sorted(set(keys.tolist())) == sorted(pack_keys(np.array([[0, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0]])).tolist())
    assert sorted(world.patch_keys) == sorted(f"patch_{k}" for k in set(keys.tolist()))
    # a few points in one 1 m block re-mesh that block; its whole patch (64 blocks of the floor) is sent again
    corner, _ = plane_points([0, 0, 1], [0.5, 0.5, 0.3], 0.3, 2_000, 0.0, seed=4)
    surface.SetInputDataObject(points_polydata(corner))
    world.Update()
    assert np.unique(np.floor_divide(unpack_keys(surface.changed_blocks), 8), axis=0).tolist() == [[0, 0, 0]]
    sent = surface.GetOutput()
    first = int(pack_keys(np.zeros((1, 3), int))[0])
    assert set(vtk_to_numpy(sent.GetCellData().GetArray(PATCH_KEY_ARRAY)).tolist()) == {first}
    now = vtk_to_numpy(surface.mesh().GetCellData().GetArray(PATCH_KEY_ARRAY))
    assert sent.GetNumberOfCells() == int((now == first).sum()) > 0.9 * int((keys == first).sum())
    assert world.number_of_cells == surface.mesh().GetNumberOfCells()  # replaced, not stacked


def test_sphere_is_accurate_and_patches_meet():
    rng = np.random.default_rng(11)
    directions = rng.standard_normal((400_000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    centre = np.array([0.31, -0.12, 0.9])
    points = centre + directions * (0.5 + 0.005 * rng.standard_normal((len(directions), 1)))
    surface = FilterVoxelPlanes()
    surface.add_points(points)
    patches = all_patches(surface)
    vertices, sizes, owner = cube_polygons(patches.normals, patches.centroids, patches.centres, S / 2)
    radial = np.abs(np.linalg.norm(vertices - centre, axis=1) - 0.5)
    assert radial.mean() < 5e-3
    # patches meet: every polygon edge on a cube face whose neighbour across it has a patch too
    # (not the surface's border) lies within 5 mm of the neighbouring patches
    from trimesh.triangles import closest_point

    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    anchors = patches.anchors[owner]
    index = {tuple(a): k for k, a in enumerate(anchors)}
    triangles, triangle_polygon = fan_triangles(sizes)
    triangles_of = {}
    for t, k in enumerate(triangle_polygon):
        triangles_of.setdefault(k, []).append(t)
    around = [np.array(o) for o in itertools.product((-1, 0, 1), repeat=3) if any(o)]
    samples, candidates = [], []
    for k in range(len(sizes)):
        ring = vertices[starts[k] : starts[k] + sizes[k]]
        centre = patches.centres[owner[k]]
        neighbours = [index.get(tuple(anchors[k] + o)) for o in around]
        near = [t for m in neighbours if m is not None for t in triangles_of[m]]
        for a, b in zip(ring, np.roll(ring, -1, axis=0), strict=True):
            on_face = (np.abs(np.abs(a - centre) - S / 2) < 1e-9) & (np.abs(np.abs(b - centre) - S / 2) < 1e-9)
            on_face &= np.sign(a - centre) == np.sign(b - centre)
            if not on_face.any():
                continue
            axis = int(np.flatnonzero(on_face)[0])
            across = anchors[k].copy()
            across[axis] += int(np.sign(a[axis] - centre[axis]))
            if tuple(across) not in index:
                continue
            for t in np.linspace(0, 1, 5):
                samples.append(a + t * (b - a))
                candidates.append(near)
    counts = np.array([len(c) for c in candidates])
    pairs_point = np.repeat(np.array(samples), counts, axis=0)
    pairs_triangle = vertices[triangles[np.concatenate(candidates)]]
    distance = np.linalg.norm(closest_point(pairs_triangle, pairs_point) - pairs_point, axis=1)
    gaps = np.minimum.reduceat(distance, np.concatenate([[0], np.cumsum(counts)[:-1]]))
    assert len(gaps) > 5000
    assert gaps.max() < 5e-3


def test_memory_grows_with_occupied_blocks_not_the_bounding_box():
    cluster, _ = plane_points([0, 0, 1], [0.5, 0.5, 0.5], 0.3, 20_000, 0.002)
    near, far = VoxelMap(), VoxelMap()
    near.add_points(np.concatenate([cluster, cluster + [1.0, 0, 0]]))
    far.add_points(np.concatenate([cluster, cluster + [100.0, 0, 0]]))
    assert near.number_of_blocks == far.number_of_blocks == 2
    assert far.memory_bytes() <= 1.01 * near.memory_bytes()
    dense = (101 / S) * (1 / S) * (1 / S) * 10 * 8  # a dense fine grid over the far pair's bounding box
    assert far.memory_bytes() < dense / 20
    # negative coordinates are just more blocks
    far.add_points(-cluster)
    assert far.number_of_blocks == 3


def test_colours_by_normal_follow_eqs_5_to_7():
    s = np.sqrt(0.5)
    normals = np.array([[0, 0, 1], [1, 0, 0], [s, 0, s], [0, s, s], [-s, 0, s], [0, -s, s]])
    expected = np.array(
        [[0.5, 0.5, 1.0], [0.5, 0.5, 0.0], [1.0, 0.5, 0.5], [0.5, 1.0, 0.5], [0.0, 0.5, 0.5], [0.5, 0.0, 0.5]]
    )
    np.testing.assert_allclose(normal_colours_float(normals), expected, atol=1e-12)
    rng = np.random.default_rng(0)
    random = rng.standard_normal((1000, 3))
    np.testing.assert_array_equal(colours_by_normal(random), colours_by_normal(-random))
    # continuous where n_x changes sign (phi through +-90 deg and through +-180 deg)
    for base in ([0.0, 0.6, 0.8], [-0.6, 0.0, 0.8], [0.6, 0.0, 0.0]):
        a = np.array(base) + [1e-6, 1e-6, 0]
        b = np.array(base) - [1e-6, 1e-6, 0]
        assert np.abs(normal_colours_float(a[None]) - normal_colours_float(b[None])).max() < 1e-5


def test_bad_parameters_and_inputs():
    with pytest.raises(ConfigError, match="window"):
        VoxelPlanesParameters(window=0)
    with pytest.raises(ConfigError, match="epsilon"):
        VoxelPlanesParameters(epsilon=0)
    with pytest.raises(ConfigError, match="between_beams must be true, false or"):
        VoxelPlanesParameters(between_beams="yes")
    for bad in (0.0, -1.0, "far", True):
        with pytest.raises(ConfigError, match="max_bridge must be a length > 0"):
            VoxelPlanesParameters(max_bridge=bad)
    with pytest.raises(ConfigError, match="whole number of voxels"):
        VoxelMap(0.05, 0.33)
    with pytest.raises(ValueError, match="shape"):
        VoxelMap().add_points(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="NaN"):
        VoxelMap().add_points(np.array([[0.0, np.nan, 1.0]]))


def test_filter_meshes_a_depth_image_and_does_not_add_it_twice():
    from conftest import plane_mesh
    from mabdi.render.depth_image import FilterDepthImage

    sensor = FilterDepthImage()
    sensor.SetInputDataObject(plane_mesh([0, 0, 2.0], [0, 0, 1]))
    sensor.pose = np.eye(4)
    surface = FilterVoxelPlanes(output="full")
    surface.SetInputConnection(sensor.GetOutputPort())
    surface.Update()
    cells = surface.GetOutput().GetNumberOfCells()
    points = surface.map.number_of_points
    assert cells > 0 and points > 100_000
    vertices, _ = polydata_arrays(surface.GetOutput())
    np.testing.assert_allclose(vertices[:, 2], 2.0, atol=1e-4)  # the plane at 2 m
    surface.output = "changed"  # a re-execution with the same image adds nothing
    surface.Update()
    assert surface.map.number_of_points == points
    n, _, _ = moments_to_gaussian(surface.map.moments(surface.map.occupied_voxels()))
    assert n.sum() == points


@pytest.mark.slow
def test_voxel_planes_in_the_loop_on_the_table():
    from mabdi.evaluate.metrics import evaluate_run

    simulation, result = check_table_loop("voxel_planes", median_limit=1e-2)
    assert evaluate_run(simulation, result, samples=30_000).redundancy <= 0.05


def test_triangle_samples_cover_long_triangles_within_the_spacing_and_skip_small_ones():
    from scipy.spatial import cKDTree

    from mabdi.surfaces.voxel_planes import triangle_samples

    # a strip of road between two LiDAR rings 3 m apart, 0.18 m wide; and a triangle smaller than the spacing
    vertices = np.array([[20.0, 0.0, 0.0], [23.0, 0.0, 0.0], [20.0, 0.18, 0.0], [5.0, 5.0, 1.0], [5.05, 5.0, 1.0], [5.0, 5.05, 1.0]])
    triangles = np.array([[0, 1, 2], [3, 4, 5]])
    spacing = 0.1
    points, nearest = triangle_samples(vertices, triangles, spacing)
    assert 30 < len(points) < 150  # a few rows along the strip, not a 30 x 30 grid
    np.testing.assert_allclose(points[:, 2], 0.0)  # all on the first triangle's plane, none from the small one
    assert (points[:, 0] >= 20.0).all() and (points[:, 1] >= 0.0).all()
    assert (points[:, 1] / 0.18 + (points[:, 0] - 20.0) / 3.0 <= 1.0 + 1e-9).all()  # inside
    assert not np.isclose(points[:, None, :], vertices[None, :3]).all(axis=2).any()  # corners left out
    # every point of the triangle lies within the spacing of a sample or a corner
    rng = np.random.default_rng(0)
    a, b = rng.random((2, 5000))
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    inside = vertices[0] + a[:, None] * (vertices[1] - vertices[0]) + b[:, None] * (vertices[2] - vertices[0])
    gaps, _ = cKDTree(np.concatenate([points, vertices[:3]])).query(inside)
    assert gaps.max() <= spacing
    assert set(nearest) <= {0, 1, 2}
    assert triangle_samples(vertices, triangles[1:], spacing)[0].shape == (0, 3)


def test_voxel_planes_mesh_the_road_between_a_lidars_rings():
    """A LiDAR 1.9 m above a road (the street corner of tests/test_lidar.py: a car-sized box at 8 m, a wall at
    30 m): beyond 10 m the rings lie more than a voxel apart, and from the beams alone no window gathers
    ``min_points`` between them. With the pixel grid's surface sampled between beams the road is meshed far
    beyond, and no more polygons lie off the scene."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_lidar import street_corner

    image, off_scene = street_corner()
    far_road, off = {}, {}
    for between in (False, "auto"):
        surface = FilterVoxelPlanes(VoxelPlanesParameters(voxel_size=0.2, between_beams=between), output="full")
        surface.SetInputDataObject(image)
        surface.Update()
        points, triangles = polydata_arrays(surface.GetOutput())
        centroids = points[triangles].mean(axis=1)
        road = (np.abs(centroids[:, 2]) < 0.05) & (np.linalg.norm(centroids[:, :2], axis=1) > 12.0)
        corners = points[triangles[road]]
        far_road[between] = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()
        off[between] = int((off_scene(centroids) > 0.03).sum())
    assert far_road["auto"] > 5.0 * max(far_road[False], 1.0), far_road
    assert off["auto"] <= off[False] + 2, off


def test_max_bridge_leaves_gaps_wider_than_it_unsampled():
    """The street corner of the test above: with ``max_bridge`` 0.3 m the road's rings are bridged only where they
    lie at most 0.3 m apart, so the far road (beyond 12 m, where they lie further apart) keeps no more than the
    beams' own polygons, and the near road (3-6 m) is meshed as with every gap bridged."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_lidar import street_corner

    image, _ = street_corner()
    road_area = {}
    for bridge in ("none", 0.3):
        surface = FilterVoxelPlanes(VoxelPlanesParameters(voxel_size=0.2, max_bridge=bridge), output="full")
        surface.SetInputDataObject(image)
        surface.Update()
        points, triangles = polydata_arrays(surface.GetOutput())
        centroids = points[triangles].mean(axis=1)
        corners = points[triangles]
        area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
        on_road = np.abs(centroids[:, 2]) < 0.05
        distance = np.linalg.norm(centroids[:, :2], axis=1)
        road_area[bridge] = (area[on_road & (distance > 12.0)].sum(), area[on_road & (distance > 3.0) & (distance < 6.0)].sum())
    unlimited, limited = road_area["none"], road_area[0.3]
    assert limited[0] < 0.2 * unlimited[0], road_area
    assert limited[1] == pytest.approx(unlimited[1], rel=0.05), road_area


def test_longest_edges():
    vertices = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 4.0, 0.0], [1.0, 1.0, 1.0]])
    np.testing.assert_allclose(longest_edges(vertices, np.array([[0, 1, 2], [0, 3, 1]])), [5.0, 3.0])
    assert longest_edges(vertices, np.zeros((0, 3), dtype=np.int64)).shape == (0,)


def crease_points(count=60_000, seed=0):
    """A wall's foot: ground z = 0.07 for x > 0.03 and a wall x = 0.03 above it, 3 m long in y, sigma 5 mm.

    The crease lies inside voxels of 0.2 m, not on their faces. Returns the points and a function giving
    each point's distance to the two half-planes."""
    rng = np.random.default_rng(seed)
    ground = np.c_[rng.uniform(0.03, 2.0, count), rng.uniform(0.0, 3.0, count), 0.07 + rng.normal(0, 0.005, count)]
    wall = np.c_[0.03 + rng.normal(0, 0.005, count), rng.uniform(0.0, 3.0, count), rng.uniform(0.07, 2.0, count)]

    def to_crease(p):
        to_ground = np.hypot(np.maximum(0.03 - p[:, 0], 0.0), p[:, 2] - 0.07)
        to_wall = np.hypot(p[:, 0] - 0.03, np.maximum(0.07 - p[:, 2], 0.0))
        return np.minimum(to_ground, to_wall)

    return np.concatenate([ground, wall]), to_crease


def crease_band(count=5000, seed=1):
    """Points on the crease's surface within 0.6 m of the fold, away from the ends in y."""
    rng = np.random.default_rng(seed)
    ground = np.c_[rng.uniform(0.03, 0.6, count), rng.uniform(0.5, 2.5, count), np.full(count, 0.07)]
    wall = np.c_[np.full(count, 0.03), rng.uniform(0.5, 2.5, count), rng.uniform(0.07, 0.6, count)]
    return np.concatenate([ground, wall])


def test_creases_are_filled_from_half_size_voxels():
    """At 0.2 m voxels a 2 x 2 x 2 window that holds a wall's foot is not planar, so the seed's rule leaves a
    band of 0.2-0.4 m open along every crease; the half-size windows fill the cubes of those windows."""
    from mabdi.evaluate.distance import distances_within

    points, to_crease = crease_points()
    band = crease_band()
    plain = FilterVoxelPlanes(VoxelPlanesParameters(voxel_size=0.2, refine=False))
    refined = FilterVoxelPlanes(VoxelPlanesParameters(voxel_size=0.2))  # "auto": on at 0.2 m
    covered = {}
    for name, surface in (("plain", plain), ("refined", refined)):
        surface.add_points(points)
        mesh = surface.mesh()
        covered[name] = (distances_within(band, mesh, cap=0.05) < 0.02).mean()
        vertices, _ = polydata_arrays(mesh)
        assert to_crease(vertices).max() < 0.02  # within epsilon of the surface, the fold included
    assert covered["plain"] < 0.65
    assert covered["refined"] > 0.88
    # the refinement's polygons are their anchor's: the same blocks, and each lies in its anchor's cube
    assert plain.changed_blocks.tolist() == refined.changed_blocks.tolist()


def test_refinement_is_automatic_where_half_size_windows_still_test_planarity():
    assert VoxelPlanesParameters(voxel_size=0.2).refines  # (0.2 m)^2 / 24 >= (0.02 m)^2
    assert not VoxelPlanesParameters().refines  # a camera's 5 cm: half-size windows would pass any crease as planar
    assert VoxelPlanesParameters(refine=True).refines and not VoxelPlanesParameters(voxel_size=0.2, refine=False).refines
    assert FilterVoxelPlanes().halved_map is None
    with pytest.raises(ConfigError, match="refine"):
        VoxelPlanesParameters(refine="sometimes")


def test_refined_creases_incremental_equals_batch_and_state_round_trips():
    rng = np.random.default_rng(6)
    points, _ = crease_points(30_000, seed=3)
    points = points[rng.permutation(len(points))]
    parameters = VoxelPlanesParameters(voxel_size=0.2)
    batch, halves = FilterVoxelPlanes(parameters), FilterVoxelPlanes(parameters)
    batch.add_points(points)
    halves.add_points(points[:30_000])
    restored = FilterVoxelPlanes(parameters)
    restored.set_state(halves.state())
    restored.add_points(points[30_000:])
    va, ta = polydata_arrays(batch.mesh())
    vb, tb = polydata_arrays(restored.mesh())
    np.testing.assert_array_equal(ta, tb)
    np.testing.assert_allclose(va, vb, atol=1e-6)
    # a state written before the refinement existed resumes without it (its statistics hold no half-size voxels)
    old = halves.state()
    del old["halved_map"]
    old["meshed_with"] = {k: v for k, v in old["meshed_with"].items() if k != "refine"}
    before = FilterVoxelPlanes(parameters)
    before.set_state(old)
    assert before.halved_map is None and not before.parameters.refines


def test_removal_empties_the_half_size_statistics_too():
    """Rays that see through the wall, and removal of the wall's faces, empty the half-size voxels they cross as
    they empty the full-size ones, so no refined polygon is later made of points that are gone."""
    points, _ = crease_points(seed=4)
    rng = np.random.default_rng(7)
    for clear in ("faces", "rays"):
        surface = FilterVoxelPlanes(VoxelPlanesParameters(voxel_size=0.2))
        surface.add_points(points)
        halved = surface.halved_map
        shift = 0.05  # a quarter voxel (module docs, "Creases")
        wall = points[(points[:, 0] < 0.1) & (points[:, 2] > 0.5)]
        assert halved.counts(halved.voxel_indices(wall + shift)).min() > 0
        if clear == "faces":
            surface.clear_faces_at(wall)
        else:  # rays from x = -1 through the wall to x = 3 (beyond the ground's end), from 8 cm above the ground
            ends = np.c_[np.full(40_000, 3.0), rng.uniform(0, 3, 40_000), rng.uniform(0.15, 2.0, 40_000)]
            origins = ends * [0, 1, 1] + [-1.0, 0.0, 0.0]
            surface.clear_free_space(origins, ends, 0.05)
        assert surface.map.counts(surface.map.voxel_indices(wall)).max() == 0, clear
        assert halved.counts(halved.voxel_indices(wall + shift)).max() == 0, clear
        surface.add_points(np.zeros((0, 3)))  # re-mesh what was emptied: the wall above 0.3 m is gone
        vertices, _ = polydata_arrays(surface.mesh())
        assert ((np.abs(vertices[:, 0] - 0.03) < 0.03) & (vertices[:, 2] > 0.6)).sum() == 0, clear
        assert (vertices[:, 0] > 0.5).sum() > 100, clear  # the ground away from the wall stays


def test_voxel_planes_reach_the_foot_of_a_car_in_a_lidar_scan():
    """The street corner's car (tests/test_lidar.py) in one scan of a 64 x 1024 LiDAR at 0.2 m voxels: its side
    facing the sensor and the road in front of it are meshed down to the crease they make. A polygon fills its
    cube, so a face's octant reaches a little past the crease (below the road: 11 more triangles off the scene,
    of 18,000). (At 32 x 512 a half-size window on the side holds fewer than ``min_points`` beams.)"""
    import sys
    from pathlib import Path

    from mabdi.evaluate.distance import distances_within

    sys.path.insert(0, str(Path(__file__).parent))
    from test_lidar import street_corner

    image, off_scene = street_corner(64, 1024, range_max=12.0)  # the car and the road around it
    rng = np.random.default_rng(2)
    side = np.c_[np.full(2000, 5.75), rng.uniform(-0.7, 0.7, 2000), rng.uniform(0.0, 0.3, 2000)]  # the face towards the sensor
    road = np.c_[rng.uniform(5.35, 5.75, 2000), rng.uniform(-0.7, 0.7, 2000), np.zeros(2000)]  # the road before it
    covered, off = {}, {}
    for refine in (False, "auto"):
        surface = FilterVoxelPlanes(VoxelPlanesParameters(voxel_size=0.2, refine=refine), output="full")
        surface.SetInputDataObject(image)
        surface.Update()
        mesh = surface.GetOutput()
        points, triangles = polydata_arrays(mesh)
        covered[refine] = [(distances_within(probe, mesh, cap=0.05) < 0.02).mean() for probe in (side, road)]
        off[refine] = int((off_scene(points[triangles].mean(axis=1)) > 0.03).sum())
    assert covered[False][0] < 0.75 and covered[False][1] < 0.55, covered
    assert covered["auto"][0] > 0.95 and covered["auto"][1] > 0.7, covered
    assert off["auto"] <= off[False] + 20, off


def test_a_surface_is_meshed_up_to_where_it_ends_inside_a_window():
    """A panel that ends inside windows (a cabinet door's edge, the border of what was seen): a window whose
    points span half of it along each in-plane axis makes a plane (``MIN_SPAN``), so the panel is meshed to
    within a voxel of its edges. At the old bound (the points spanning 0.71 of the window) the cubes along its
    edges stayed open: a real kitchen lost a fifth of its pixels so."""
    from mabdi.evaluate import distances_to_mesh
    from mabdi.surfaces.voxel_planes import MIN_SPAN, span_variance

    assert MIN_SPAN == 0.5 and VoxelPlanesParameters().lambda_large == pytest.approx(span_variance(0.1))
    # a 0.3 m square panel, tilted and offset against the grid, 2 mm apart, 2 mm noise
    normal = np.array([0.3, -0.5, 0.81])
    normal /= np.linalg.norm(normal)
    u = np.cross(normal, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    a, b = np.meshgrid(np.arange(-0.15, 0.15, 0.002), np.arange(-0.15, 0.15, 0.002))
    points = np.array([0.013, -0.021, 0.037]) + np.outer(a.ravel(), u) + np.outer(b.ravel(), v)
    points += np.random.default_rng(3).normal(0.0, 0.002, size=points.shape)
    surface = FilterVoxelPlanes()
    surface.add_points(points)
    distance = distances_to_mesh(points, surface.mesh())
    covered = distance < 0.01
    assert covered.mean() > 0.99
    # the edges too: the panel's outer 5 cm band
    band = np.maximum(np.abs(a.ravel()), np.abs(b.ravel())) > 0.10
    assert covered[band].mean() > 0.97
