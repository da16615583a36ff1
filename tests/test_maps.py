"""Mesh maps: cost layers, labels and clusters, picking, planning (seed 003)."""

import numpy as np
import pytest

from mabdi.mesh_maps.labels import label_faces, label_floor, planar_clusters
from mabdi.mesh_maps.layers import CostParameters, add_cost_layers, cost_layers, vertex_normals
from mabdi.mesh_maps.mesh_map import MeshMap, MeshMapError, welded_map
from mabdi.mesh_maps.picking import MapPicker, goal_pose, rotation_to_quaternion
from mabdi.mesh_maps.planning import PlanningError, plan


def grid(width, height, spacing, z=None, origin=(0.0, 0.0)):
    """A regular triangulation of a rectangle (diagonals alternating, so no direction is favoured)."""
    nx, ny = int(round(width / spacing)) + 1, int(round(height / spacing)) + 1
    x = origin[0] + np.linspace(-width / 2, width / 2, nx)
    y = origin[1] + np.linspace(-height / 2, height / 2, ny)
    xx, yy = np.meshgrid(x, y, indexing="ij")
    zz = np.zeros_like(xx) if z is None else z(xx, yy)
    vertices = np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="ij")
    a = (i * ny + j).ravel()
    even = ((i + j) % 2 == 0).ravel()
    faces = np.concatenate(
        [
            np.stack([a, a + ny, a + ny + 1], axis=1)[even],
            np.stack([a, a + ny + 1, a + 1], axis=1)[even],
            np.stack([a, a + ny, a + 1], axis=1)[~even],
            np.stack([a + ny, a + ny + 1, a + 1], axis=1)[~even],
        ]
    )
    return MeshMap(vertices, faces)


def test_roughness_is_zero_on_a_plane_and_higher_on_bumps():
    flat = grid(2, 2, 0.02)
    bumpy = grid(2, 2, 0.02, z=lambda x, y: 0.03 * np.sin(x / 0.05) * np.cos(y / 0.05))
    p = CostParameters(radius=0.06)
    flat_layers, bumpy_layers = cost_layers(flat, p), cost_layers(bumpy, p)
    assert flat_layers["roughness"].max() < 1e-6
    assert np.median(bumpy_layers["roughness"]) > 0.02
    np.testing.assert_allclose(np.abs(vertex_normals(flat.vertices, flat.faces)[:, 2]), 1.0)


def test_height_difference_flags_a_20_cm_step():
    step = grid(2, 1, 0.02, z=lambda x, y: np.where(x > 0.0, 0.2, 0.0))
    layers = cost_layers(step, CostParameters(radius=0.1, max_step=0.1))
    x = step.vertices[:, 0]
    near = np.abs(x) < 0.05
    far = np.abs(x) > 0.2
    assert layers["height_difference"][near].min() >= 0.2 - 1e-6
    assert layers["height_difference"][far].max() < 1e-6
    assert (layers["lethal"][near] == 1).all() and (layers["lethal"][far] == 0).all()
    # inflation falls from 1 at the step to 0 at the inflation radius; cost is 1 where lethal
    assert layers["inflation"][np.abs(x - 0.5) < 0.011].max() < 0.01
    assert (layers["cost"][near] == 1).all()


def test_the_compiled_neighbourhood_statistics_give_the_kd_tree_references():
    """radius_statistics (a numba grid hash) against the numpy references over every neighbour a KD-tree finds
    within the radius: the same roughness and height difference on a bumpy, stepped patch."""
    from reference_kernels import height_difference, neighbourhoods, roughness

    from mabdi.mesh_maps.neighbourhood import radius_statistics

    bumpy = grid(1, 1, 0.02, z=lambda x, y: 0.03 * np.sin(x / 0.05) * np.cos(y / 0.05) + np.where(x > 0.2, 0.05, 0.0))
    normals = vertex_normals(bumpy.vertices, bumpy.faces)
    radius = 0.07
    index = neighbourhoods(bumpy.vertices, radius, len(bumpy.vertices))  # all within the radius
    rough, top, bottom = radius_statistics(bumpy.vertices, normals, bumpy.vertices[:, 2], radius)
    np.testing.assert_allclose(rough, roughness(normals, index), atol=1e-6)
    np.testing.assert_allclose(top - bottom, height_difference(bumpy.vertices, index), atol=1e-12)
    assert (top - bottom).max() > 0.05 and rough.max() > 0.05  # the step and the bumps are there to find


def test_floor_label_and_planar_clusters_on_a_table():
    floor = grid(3, 3, 0.05)
    top = grid(1, 0.6, 0.05, z=lambda x, y: np.full_like(x, 0.8))
    table = MeshMap(
        np.concatenate([floor.vertices, top.vertices]), np.concatenate([floor.faces, top.faces + floor.number_of_vertices])
    )
    ids = label_floor(table)
    assert set(ids.tolist()) == set(range(floor.number_of_faces))  # the biggest flat region, not the table top
    top_ids = label_floor(table, name="table_top", seed_face=floor.number_of_faces)
    assert len(top_ids) == top.number_of_faces and table.labels["table_top"] is top_ids
    clusters = planar_clusters(table)
    assert sorted(len(c) for c in clusters.values()) == [top.number_of_faces, floor.number_of_faces]
    with pytest.raises(MeshMapError, match="face ids"):
        label_faces(table, "tree_1", [0, 10**6])


def test_patches_that_meet_without_sharing_vertices_are_welded():
    left = grid(1, 1, 0.1, origin=(-0.5, 0))
    right = grid(1, 1, 0.1, origin=(0.5, 0))
    right.vertices[:, 2] += 0.002  # a 2 mm seam, as between two frames' patches
    both = MeshMap(np.concatenate([left.vertices, right.vertices]), np.concatenate([left.faces, right.faces + 121]))
    welded, groups = welded_map(both)
    assert welded.number_of_vertices == 2 * 121 - 11
    assert len(label_floor(both)) == both.number_of_faces
    result = plan(both, [-0.9, 0, 0], [0.9, 0, 0], "dijkstra")
    assert result.reachable and abs(result.length - 1.8) < 0.02


def test_picking_returns_the_first_face_like_brute_force():
    rng = np.random.default_rng(4)
    layers = [grid(2, 2, 0.1, z=lambda x, y, h=h: h + 0.05 * x * y) for h in (0.0, 0.5, 1.0)]
    stacked = MeshMap(
        np.concatenate([m.vertices for m in layers]),
        np.concatenate([m.faces + k * layers[0].number_of_vertices for k, m in enumerate(layers)]),
    )
    picker = MapPicker(stacked)
    v = stacked.vertices.astype(np.float64)
    a, b, c = v[stacked.faces[:, 0]], v[stacked.faces[:, 1]], v[stacked.faces[:, 2]]
    for _ in range(50):
        origin = np.array([*rng.uniform(-0.9, 0.9, 2), rng.choice([-1.0, 2.0])])
        direction = np.array([*rng.normal(0, 0.2, 2), 1.0 if origin[2] < 0 else -1.0])
        hit = picker.pick(origin, direction)
        t = ray_triangles(origin, direction / np.linalg.norm(direction), a, b, c)
        if not np.isfinite(t).any():
            assert hit is None
            continue
        assert hit.face == int(np.nanargmin(t))
        np.testing.assert_allclose(hit.point, origin + np.nanmin(t) * direction / np.linalg.norm(direction), atol=1e-6)
        assert hit.normal @ direction < 0
    assert picker.pick([5, 5, 2], [0, 0, -1]) is None


def ray_triangles(origin, direction, a, b, c):
    """Möller-Trumbore for every triangle: ray parameter t of each hit (inf where none)."""
    e1, e2 = b - a, c - a
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = origin - a
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        w = (q @ direction) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
    ok = (np.abs(det) > 1e-12) & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)
    return np.where(ok, t, np.inf)


def test_goal_pose_lies_in_the_face_plane():
    pose, quaternion = goal_pose([1, 2, 3], [0, 0, 2], [1, 1, 5])
    np.testing.assert_allclose(pose[:3, 0], [np.sqrt(0.5), np.sqrt(0.5), 0], atol=1e-12)
    np.testing.assert_allclose(pose[:3, 2], [0, 0, 1])
    np.testing.assert_allclose(quaternion, [0, 0, np.sin(np.pi / 8), np.cos(np.pi / 8)], atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(pose[:3, :3]), 1.0)
    rotation = np.diag([1.0, -1.0, -1.0])  # 180 degrees about x: w = 0
    np.testing.assert_allclose(np.abs(rotation_to_quaternion(rotation)), [1, 0, 0, 0], atol=1e-12)
    with pytest.raises(ValueError, match="along the face normal"):
        goal_pose([0, 0, 0], [0, 0, 1], [0, 0, 3])


@pytest.fixture(scope="module")
def floor_with_box():
    floor = grid(4, 3, 0.02)
    box = (np.abs(floor.vertices[:, 0]) <= 0.25) & (np.abs(floor.vertices[:, 1]) <= 0.5)
    floor.vertex_layers["lethal"] = box.astype(np.float32)
    return floor, box


@pytest.mark.parametrize("planner, tolerance", [("fmm", 0.03), ("dijkstra", 0.10)])
def test_planners_go_around_a_lethal_box(floor_with_box, planner, tolerance):
    floor, box = floor_with_box
    result = plan(floor, [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], planner)
    assert result.reachable
    # the path never enters the box (the corner points of the free vertices around it are fine)
    inside = (np.abs(result.path[:, 0]) < 0.25 - 1e-6) & (np.abs(result.path[:, 1]) < 0.5 - 1e-6)
    assert not inside.any()
    detour = 2 * np.hypot(0.75, 0.5) + 0.5  # around a corner of the box, along its side, to the goal
    assert abs(result.length - detour) <= tolerance * detour, result.length
    np.testing.assert_allclose(result.path[0], [-1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(result.path[-1], [1, 0, 0], atol=1e-9)


def test_the_compiled_heap_gives_the_numpy_iterative_arrival_times(floor_with_box):
    """Fast marching (numba heap) against the fast iterative method in numpy, around a blocked box with a
    slowness that varies: the same first-order update, so the same times."""
    from reference_kernels import iterative_arrival_times

    from mabdi.mesh_maps.planning import arrival_times

    floor, box = floor_with_box
    x, y = floor.vertices[:, 0], floor.vertices[:, 1]
    slowness = 1.0 + 0.5 * (x > 0.5) + 0.25 * np.sin(3 * y) ** 2
    source = int(np.argmin(np.hypot(x + 1.0, y)))
    heap = arrival_times(floor, source, slowness, box)
    iterative = iterative_arrival_times(floor, source, slowness, box)
    np.testing.assert_array_equal(np.isfinite(heap), np.isfinite(iterative))
    assert np.isfinite(heap).sum() > 0.8 * len(heap) and np.isinf(heap[box]).all()
    # the iterative method stops once no time improves by more than 1e-9 of the domain size (measured: 1.4e-8)
    np.testing.assert_allclose(heap[np.isfinite(heap)], iterative[np.isfinite(iterative)], rtol=0, atol=1e-6)


@pytest.mark.parametrize("planner", ["fmm", "dijkstra"])
def test_an_unreachable_goal_is_reported(planner):
    floor = grid(2, 1, 0.05)
    wall = np.abs(floor.vertices[:, 0]) < 0.06  # a lethal band across the whole floor
    floor.vertex_layers["lethal"] = wall.astype(np.float32)
    result = plan(floor, [-0.8, 0, 0], [0.8, 0, 0], planner)
    assert not result.reachable and len(result.path) == 0 and result.length == float("inf")


def test_costly_regions_are_avoided_when_cheaper_to_go_around():
    floor = grid(3, 2, 0.04)
    mud = (np.abs(floor.vertices[:, 0]) < 0.3) & (floor.vertices[:, 1] < 0.6)
    floor.vertex_layers["cost"] = np.where(mud, 1.0, 0.0).astype(np.float32)
    straight = plan(floor, [-1, 0, 0], [1, 0, 0], "fmm", cost_weight=0.0)
    around = plan(floor, [-1, 0, 0], [1, 0, 0], "fmm", cost_weight=4.0)
    assert abs(straight.length - 2.0) < 0.03
    assert around.path[:, 1].max() > 0.55 and around.cost < 2.0 + 0.6 * 4.0


def test_add_cost_layers_gives_face_layers_and_bad_requests_are_named():
    floor = grid(1, 1, 0.05)
    add_cost_layers(floor)
    assert floor.face_layers["face_cost"].shape == (floor.number_of_faces,)
    with pytest.raises(PlanningError, match="unknown planner"):
        plan(floor, [0, 0, 0], [0.1, 0, 0], "astar")
    with pytest.raises(PlanningError, match="no faces"):
        plan(MeshMap(np.zeros((0, 3)), np.zeros((0, 3))), [0, 0, 0], [1, 0, 0])
