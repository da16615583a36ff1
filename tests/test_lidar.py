"""A spinning LiDAR: range images rendered exactly, E of the map, the loop and the surfaces on range images."""

from __future__ import annotations

import math

import numpy as np

from mabdi.world_map import LIDAR_CHUNK_SIZE
import pytest
from vtkmodules.vtkCommonDataModel import vtkMultiBlockDataSet
from vtkmodules.vtkFiltersCore import vtkAppendPolyData, vtkTriangleFilter
from vtkmodules.vtkFiltersSources import vtkCubeSource, vtkPlaneSource

from mabdi.camera import Intrinsics
from mabdi.config import RunConfig, load_run_config
from mabdi.depth import DepthFrame, depth_array, image_intrinsics, is_range_image
from mabdi.errors import ConfigError
from mabdi.render.depth_image import FilterDepthImage
from mabdi.sensor_noise import SensorNoise
from mabdi.stages.expected_image import FilterExpectedImage, face_id_array
from mabdi.surfaces.pixel_grid import FilterPixelGrid, PixelGridParameters
from mabdi.stages.world_mesh import FilterWorldMesh
from mabdi.polydata import polydata_arrays
from mabdi.spherical import SphericalGeometry

#: A small LiDAR for the tests: 16 beams over 30 degrees, 256 columns.
GEOMETRY = SphericalGeometry(16, 256, 15.0, -15.0, 0.5, 50.0)


def plane(origin, point1, point2):
    source = vtkPlaneSource()
    source.SetOrigin(*origin)
    source.SetPoint1(*point1)
    source.SetPoint2(*point2)
    source.Update()
    return source.GetOutput()


def merged(*meshes):
    append = vtkAppendPolyData()
    for mesh in meshes:
        append.AddInputData(mesh)
    triangulate = vtkTriangleFilter()
    triangulate.SetInputConnection(append.GetOutputPort())
    triangulate.Update()
    return triangulate.GetOutput()


def box(center, size, yaw_deg):
    cube = vtkCubeSource()
    cube.SetXLength(size[0])
    cube.SetYLength(size[1])
    cube.SetZLength(size[2])
    cube.Update()
    points, triangles = polydata_arrays(cube.GetOutput())
    a = math.radians(yaw_deg)
    rotation = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    from mabdi.polydata import triangles_polydata

    return triangles_polydata(points @ rotation.T + np.asarray(center), triangles)


def ray_cast(mesh, geometry, pose):
    """(H, W) ranges by brute force: every beam against every triangle (numpy, float64), NaN: none in range."""
    points, triangles = polydata_arrays(mesh)
    a = points[triangles[:, 0]]
    e1 = points[triangles[:, 1]] - a
    e2 = points[triangles[:, 2]] - a
    d = geometry.rays().reshape(-1, 3) @ pose[:3, :3].T
    o = pose[:3, 3]
    p = np.cross(d[:, None, :], e2[None])
    det = np.einsum("tk,ntk->nt", e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o - a
        u = np.einsum("tk,ntk->nt", s, p) * inv
        q = np.cross(s, e1)
        v = np.einsum("nk,tk->nt", d, q) * inv
        t = np.einsum("tk,tk->t", e2, q)[None] * inv
        hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        t = np.where(hit, t, np.inf).min(axis=1)
    t[~((t > geometry.range_min) & (t < geometry.range_max))] = np.nan
    return t.reshape(geometry.shape)


def render(mesh, geometry, pose, noise="none", seed=0):
    sensor = FilterDepthImage(geometry, noise=noise, seed=seed)
    sensor.SetInputDataObject(mesh)
    sensor.pose = pose
    sensor.Update()
    return sensor.GetOutput()


def test_range_image_of_a_plane_reads_the_exact_range_at_every_beam():
    wall = plane((3.0, -5.0, -5.0), (3.0, 5.0, -5.0), (3.0, -5.0, 5.0))  # x = 3 m, 10 m square
    image = render(wall, GEOMETRY, np.eye(4))
    assert is_range_image(image) and image_intrinsics(image) == GEOMETRY
    ranges = depth_array(image)
    rays = GEOMETRY.rays()
    with np.errstate(divide="ignore"):
        expected = 3.0 / rays[..., 0]
    hits = (rays[..., 0] > 0) & (np.abs(rays[..., 1] * expected) < 5) & (np.abs(rays[..., 2] * expected) < 5)
    assert hits.sum() > 1000
    np.testing.assert_array_equal(np.isfinite(ranges), hits)
    assert np.abs(ranges[hits] - expected[hits]).max() < 1e-3  # within 1 mm at every beam (float32 metres)
    # the points lie on the plane: range times unit ray, x = 3
    points = ranges[hits][:, None] * rays[hits]
    assert np.abs(points[:, 0] - 3.0).max() < 1e-3


def test_range_image_of_a_box_reads_the_exact_range_at_every_beam():
    # a box before a wall and a floor, the sensor moved and turned: every beam against a brute-force ray cast
    scene = merged(
        box((4.0, 0.7, 0.2), (1.2, 0.8, 1.4), 30.0),
        plane((8.0, -20.0, -1.5), (8.0, 20.0, -1.5), (8.0, -20.0, 6.0)),
        plane((-20.0, -20.0, -1.5), (20.0, -20.0, -1.5), (-20.0, 20.0, -1.5)),
    )
    pose = np.eye(4)
    a = math.radians(10.0)
    pose[:3, :3] = [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
    pose[:3, 3] = (0.3, -0.2, 0.1)
    geometry = SphericalGeometry(32, 512, 10.0, -30.0, 0.5, 40.0)
    ranges = depth_array(render(scene, geometry, pose))
    reference = ray_cast(scene, geometry, pose)
    np.testing.assert_array_equal(np.isfinite(ranges), np.isfinite(reference))
    both = np.isfinite(reference)
    assert both.sum() > 0.5 * both.size
    assert np.abs(ranges[both] - reference[both]).max() < 1e-3
    # the box is seen, and its near faces read nearer than the wall
    assert np.nanmin(ranges) < 3.8


def test_range_noise_is_seeded_and_of_its_sigma():
    wall = plane((3.0, -5.0, -5.0), (3.0, 5.0, -5.0), (3.0, -5.0, 5.0))
    exact = depth_array(render(wall, GEOMETRY, np.eye(4)))
    noisy = depth_array(render(wall, GEOMETRY, np.eye(4), SensorNoise("range", range_sigma=0.02), seed=3))
    again = depth_array(render(wall, GEOMETRY, np.eye(4), SensorNoise("range", range_sigma=0.02), seed=3))
    np.testing.assert_array_equal(noisy, again)
    error = (noisy - exact)[np.isfinite(exact)]
    assert abs(error.std() - 0.02) < 0.003 and abs(error.mean()) < 0.003
    with pytest.raises(ConfigError, match="camera's"):
        SensorNoise("kinect").ranges_with_noise(exact, np.random.default_rng(0))


def test_expected_image_of_a_mapped_plane_matches_the_measured_one_within_a_millimetre():
    wall = plane((3.0, -5.0, -2.0), (3.0, 5.0, -2.0), (3.0, -5.0, 5.0))
    pose = np.eye(4)
    measured = render(wall, GEOMETRY, pose)
    surface = FilterPixelGrid()
    surface.SetInputDataObject(measured)
    world = FilterWorldMesh()
    world.SetInputConnection(surface.GetOutputPort())
    world.Update()
    assert world.number_of_cells > 0
    # E from a pose moved a little: the beams fall between the mapped ones
    moved = np.eye(4)
    moved[:3, 3] = (0.2, 0.05, 0.03)
    measured_moved = render(wall, GEOMETRY, moved)
    expected = FilterExpectedImage(identity=True)
    expected.SetInputDataObject(0, world.map)
    expected.SetInputDataObject(1, measured_moved)
    expected.Update()
    e = depth_array(expected.GetOutput())
    d = depth_array(measured_moved)
    both = np.isfinite(e) & np.isfinite(d)
    assert both.sum() > 0.9 * np.isfinite(e).sum() and both.sum() > 300
    assert np.abs(e[both] - d[both]).max() < 1e-3
    ids = face_id_array(expected.GetOutput())
    assert (ids[np.isfinite(e)] > 0).all() and (ids[~np.isfinite(e)] == 0).all()


def test_lidar_sensor_config(tmp_path):
    path = tmp_path / "lidar.toml"
    path.write_text(
        '[sensor]\nkind = "lidar"\nnoise = "range"\n[sensor.lidar]\nbeams = 32\ncolumns = 512\nfov_up = 10.0\nfov_down = -30.0\n'
        '[sensor.noise_parameters]\nrange_sigma = 0.01\n'
    )
    config = load_run_config(path)
    assert config.sensor.geometry() == SphericalGeometry(32, 512, 10.0, -30.0, 0.5, 80.0)
    assert config.sensor.sensor_noise().sigma(np.array([5.0]), 0.5, 80.0)[0] == pytest.approx(0.01)
    assert RunConfig().sensor.kind == "pinhole"
    path.write_text('[sensor]\nkind = "lidar"\nnoise = "kinect"\n')
    with pytest.raises(ConfigError, match="sensor.noise"):
        load_run_config(path)
    path.write_text('[sensor]\nkind = "sonar"\n')
    with pytest.raises(ConfigError, match="sensor.kind"):
        load_run_config(path)
    path.write_text('[sensor]\nkind = "lidar"\n[sensor.lidar]\nfov_up = -30.0\nfov_down = 10.0\n')
    with pytest.raises(ConfigError, match=r"\[sensor.lidar\] .*fov_down"):
        load_run_config(path)


def test_simulated_lidar_poses_look_where_the_path_looks(tmp_path):
    from mabdi.simulate.path import path_from_config
    from mabdi.simulate.rig import SimulatedRig

    path = tmp_path / "lidar.toml"
    path.write_text('[run]\nframes = 4\n[sensor]\nkind = "lidar"\n[sensor.lidar]\nbeams = 8\ncolumns = 64\n')
    config = load_run_config(path)
    rig = SimulatedRig.from_config(config)
    camera = path_from_config(4, config.path)
    np.testing.assert_allclose(rig.true_poses[:, :3, 0], camera[:, :3, 2], atol=1e-12)  # x forward = optical axis
    np.testing.assert_allclose(rig.true_poses[:, :3, 2], -camera[:, :3, 1], atol=1e-12)  # z up = image up
    frame = rig.read(0)
    assert frame.intrinsics == config.sensor.geometry() and frame.colour is None
    rig.close()


def test_depth_frame_round_trip_keeps_the_spherical_geometry():
    ranges = np.full(GEOMETRY.shape, 4.0, dtype=np.float32)
    frame = DepthFrame(ranges, GEOMETRY, np.eye(4), 3)
    back = DepthFrame.from_image(frame.to_image())
    assert back.intrinsics == GEOMETRY and back.frame == 3
    np.testing.assert_array_equal(back.depth, ranges)


def test_composite_map_renders_as_one():
    wall = plane((3.0, -5.0, -5.0), (3.0, 5.0, -5.0), (3.0, -5.0, 5.0))
    floor = plane((-20.0, -20.0, -1.5), (20.0, -20.0, -1.5), (-20.0, 20.0, -1.5))
    blocks = vtkMultiBlockDataSet()
    blocks.SetBlock(0, wall)
    blocks.SetBlock(1, floor)
    np.testing.assert_array_equal(depth_array(render(blocks, GEOMETRY, np.eye(4))), depth_array(render(merged(wall, floor), GEOMETRY, np.eye(4))))


def street_corner(beams=32, columns=512, range_max=60.0):
    """A LiDAR 1.9 m above a flat ground, a car-sized box at 8 m and a wall at 30 m, 5 mm range noise: (its range
    image, the distance of world points from the scene)."""
    geometry = SphericalGeometry(beams, columns, 2.0, -24.8, 1.0, range_max)
    centre, half = np.array([8.0, 0.0, 0.75]), np.array([2.25, 0.9, 0.75])
    scene = merged(
        plane((-60.0, -60.0, 0.0), (60.0, -60.0, 0.0), (-60.0, 60.0, 0.0)),
        box(centre, 2 * half, 0.0),
        plane((30.0, -60.0, 0.0), (30.0, 60.0, 0.0), (30.0, -60.0, 12.0)),
    )
    pose = np.eye(4)
    pose[2, 3] = 1.9
    image = render(scene, geometry, pose, noise=SensorNoise("range", range_sigma=0.005), seed=1)

    def off_scene(points):
        outside = np.abs(points - centre) - half
        to_box = np.abs(np.linalg.norm(np.maximum(outside, 0), axis=1) + np.minimum(outside.max(axis=1), 0))
        return np.minimum(np.minimum(np.abs(points[:, 2]), np.abs(points[:, 0] - 30.0)), to_box)

    return image, off_scene


def beam_column(surface_of, elevations_deg):
    """Sensor-frame points (H, 1, 3) of beams in the x-z plane at ``elevations_deg`` (top row first), each at the
    point ``surface_of(elevation)`` gives (NaN: no return), and their sigma (5 mm)."""
    points = np.array([surface_of(math.radians(e)) for e in elevations_deg], dtype=np.float64)[:, None, :]
    return points, np.full(points.shape[:2], 0.005)


#: Beams 0.4 degrees apart from 2 to 14 degrees below the horizon, top row first; the sensor 1.9 m up.
ELEVATIONS = -2.0 - 0.4 * np.arange(31)
HEIGHT = 1.9


def test_straight_lines_reach_the_last_ring_before_the_road_ends_or_meets_a_wall():
    """Ground seen at grazing incidence: every edge between two of its rings is straight, the last two rings'
    too, though no ring lies beyond them on the road's line (the road ends: no return; a wall stands there:
    the next sample is on the wall). The edge from the ground to the wall is not straight; the wall's are."""
    from mabdi.depth import straight_continuations

    def ground_until(end):
        def hit(elevation):
            x = HEIGHT / math.tan(-elevation)
            return (x, 0.0, -HEIGHT) if x <= end else (np.nan, np.nan, np.nan)

        return hit

    def ground_and_wall(wall):
        def hit(elevation):
            x = HEIGHT / math.tan(-elevation)
            return (x, 0.0, -HEIGHT) if x <= wall else (wall, 0.0, wall * math.tan(elevation))

        return hit

    points, sigma = beam_column(ground_until(25.0), ELEVATIONS)
    rings = np.isfinite(points[:, 0, 0])
    vertical, _, _ = straight_continuations(points, sigma)
    assert 10 < rings.sum() < len(rings)
    edges = rings[:-1] & rings[1:]
    np.testing.assert_array_equal(vertical[:, 0], edges)  # the farthest pair included

    points, sigma = beam_column(ground_and_wall(25.0), ELEVATIONS)
    on_wall = np.isclose(points[:, 0, 0], 25.0)
    vertical, _, _ = straight_continuations(points, sigma)
    assert 3 < on_wall.sum() < len(on_wall) - 10
    foot = np.flatnonzero(on_wall)[-1]  # the edge (foot, foot + 1) joins the wall's lowest sample to the ground
    assert not vertical[foot, 0]
    assert vertical[:foot, 0].all() and vertical[foot + 1 :, 0].all()  # the wall's, and the ground's to the last ring


def test_a_sample_beyond_a_silhouette_on_the_foreground_line_does_not_join_it():
    """A car's roof (1.5 m, seen from 1.9 m) ends 0.45 m before a facade, and the facade's sample at the roof's
    height lies exactly on the roof's extrapolated line. That sample continues the facade's own line too, so the
    roof is not joined to it (no false roof over the gap). Being on both lines, it is joined to neither by this
    rule (the facade, seen head-on, is joined by the jump rule); every other edge of the roof and the facade is
    straight."""
    from mabdi.depth import straight_continuations

    facade, roof_end, roof = 5.45, 5.0, -0.4

    def hit(elevation):
        x_roof = roof / math.tan(elevation)
        if x_roof <= roof_end:
            return (x_roof, 0.0, roof)
        return (facade, 0.0, facade * math.tan(elevation))

    # beams 0.4 degrees apart, one of them through the facade at the roof's height
    elevations = math.degrees(math.atan2(roof, facade)) - 0.4 * np.arange(-5, 6)
    points, sigma = beam_column(hit, elevations)
    on_facade = np.isclose(points[:, 0, 0], facade)
    gap = np.flatnonzero(on_facade)[-1]  # the facade's sample at the roof's height, then the roof's far edge
    assert abs(points[gap, 0, 2] - roof) < 1e-9 and on_facade[:gap].all() and not on_facade[gap + 1 :].any()
    vertical, _, _ = straight_continuations(points, sigma)
    assert not vertical[gap, 0] and not vertical[gap - 1, 0]
    assert vertical[: gap - 1, 0].all() and vertical[gap + 1 :, 0].all()


def test_the_pixel_grid_meshes_ground_seen_at_grazing_incidence_and_nothing_off_the_scene():
    """The jump rule alone meshes the ground to about 10 m (beyond, more than 79 degrees from its normal); the
    straight-line rule (``grazing``, on for range images) meshes it to the wall, to the last ring before the
    wall's foot (the rings lie 7 m apart there), and adds no triangle more than 3 cm off the scene (no bridge
    from the box to the ground behind it, or from the wall's top to the sky)."""
    image, off_scene = street_corner()
    reach, front, off = {}, {}, {}
    for grazing in (False, "auto"):
        surface = FilterPixelGrid(PixelGridParameters(grazing=grazing))
        surface.SetInputDataObject(image)
        surface.Update()
        points, triangles = polydata_arrays(surface.GetOutput())
        centroids = points[triangles].mean(axis=1)
        ground = np.abs(centroids[:, 2]) < 0.05
        reach[grazing] = np.linalg.norm(centroids[ground, :2], axis=1).max()
        front[grazing] = centroids[ground, 0].max()  # towards the wall at x = 30 m
        off[grazing] = set(map(tuple, np.round(centroids[off_scene(centroids) > 0.03], 4)))
    assert reach[False] < 12.0 < 28.0 < reach["auto"], reach
    assert front["auto"] > 26.0, front
    assert off["auto"] <= off[False], len(off["auto"] - off[False])  # the corners' chords of the box, as before


def test_the_quadtree_meshes_ground_seen_at_grazing_incidence_and_nothing_off_the_scene():
    """The same corner of a street meshed by the quad-tree (no reduction, as the street scene runs it): with
    ``grazing`` the ground's normals take their neighbours along the beams' straight lines, and leaves of
    two or more pixels keep their far corners on their fitted plane, so the meshed area grows more than
    fourfold; a single pixel's normal is no fitted plane, and no vertex lands off the scene that did not
    without the rule. No triangle is without area (single pixels on two silhouettes, their corners moved
    onto one line, made a third of the triangles here before they were left out)."""
    from mabdi.surfaces.quadtree import FilterQuadTree, QuadTreeParameters
    from mabdi.polydata import polydata_area

    image, off_scene = street_corner()
    area, off = {}, {}
    for grazing in (False, "auto"):
        quadtree = FilterQuadTree(QuadTreeParameters(reduction=1, grazing=grazing, triangles=True))
        quadtree.SetInputDataObject(image)
        quadtree.Update()
        points, triangles = polydata_arrays(quadtree.GetOutput())
        area[grazing] = polydata_area(quadtree.GetOutput())
        off[grazing] = int((off_scene(points) > 0.03).sum())
        corners = points[triangles]
        doubled = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
        assert doubled.min() > 1e-9, "a triangle with no area (a single pixel collapsed onto a line)"
    assert area["auto"] > 4.0 * area[False], area
    assert off["auto"] <= off[False], off


#: The Velodyne VLP-32C's beam elevations (degrees, top first): 0.33 degrees apart about the horizon, 3-10 beyond.
VLP_32C = (
    15.0, 10.333, 7.0, 4.667, 3.333, 2.333, 1.667, 1.333, 1.0, 0.667, 0.333, 0.0, -0.333, -0.667, -1.0, -1.333,
    -1.667, -2.0, -2.333, -2.667, -3.0, -3.333, -3.667, -4.0, -4.667, -5.333, -6.148, -7.254, -8.843, -11.31, -15.639, -25.0,
)  # fmt: skip


@pytest.mark.parametrize("surface", ["pixel_grid", "quadtree"])
def test_an_uneven_sensor_s_dense_beams_are_not_meshed_across_a_silhouette_by_its_widest_gap(surface):
    """A sensor of uneven beams (its beam table, as a bag's rings give it): a box 20 m away before a wall at 30 m,
    seen by the beams 0.33 degrees apart. The jump between neighbouring beams is judged by their own spacing,
    not the widest (9.4 degrees, which allowed 86% of the range and joined the box to the wall: 153 faces of the
    pixel grid and 220 of the quad-tree lay more than 25 cm off the scene): no more such faces than the same
    sensor's beams spread evenly make."""
    from mabdi.surfaces.quadtree import FilterQuadTree, QuadTreeParameters

    centre, half = np.array([20.0, 0.0, 1.0]), np.array([1.0, 3.0, 1.0])
    scene = merged(
        plane((-60.0, -60.0, 0.0), (60.0, -60.0, 0.0), (-60.0, 60.0, 0.0)),
        box(centre, 2 * half, 0.0),
        plane((30.0, -60.0, 0.0), (30.0, 60.0, 0.0), (30.0, -60.0, 12.0)),
    )

    def off_scene(points):
        outside = np.abs(points - centre) - half
        to_box = np.abs(np.linalg.norm(np.maximum(outside, 0), axis=1) + np.minimum(outside.max(axis=1), 0))
        return np.minimum(np.minimum(np.abs(points[:, 2]), np.abs(points[:, 0] - 30.0)), to_box)

    pose = np.eye(4)
    pose[2, 3] = 1.9
    off = {}
    for name, geometry in {
        "table": SphericalGeometry(32, 1024, 17.5, -27.5, 1.0, 60.0, VLP_32C),
        "even": SphericalGeometry(32, 1024, 17.5, -27.5, 1.0, 60.0),
    }.items():
        image = render(scene, geometry, pose)
        mesher = FilterPixelGrid(PixelGridParameters()) if surface == "pixel_grid" else FilterQuadTree(QuadTreeParameters(reduction=1))
        mesher.SetInputDataObject(image)
        mesher.Update()
        points, triangles = polydata_arrays(mesher.GetOutput())
        assert len(triangles) > 1000
        centroids = points[triangles].mean(axis=1)
        box_side = (np.abs(centroids[:, 0] - 19.0) < 0.03) & (np.abs(centroids[:, 1]) < 3.0)
        assert box_side.sum() > 50  # the box's face towards the sensor is meshed
        off[name] = int((off_scene(centroids) > 0.25).sum())  # faces bridging the box and the wall
    assert off["table"] <= off["even"], off


@pytest.mark.parametrize("reduction", [1, 3])
def test_quadtree_meshes_a_straight_wall_from_the_range_image_flat(reduction):
    # seed 002 §3.2's case: a wall in front of the sensor is curved in the range image; the quad-tree's
    # spherical transform makes it flat again, merges it into big faces, with the wall's normal
    from vtkmodules.util.numpy_support import vtk_to_numpy

    from mabdi.surfaces.quadtree import FilterQuadTree, QuadTreeParameters

    geometry = SphericalGeometry(32, 512, 10.0, -20.0, 0.5, 50.0)
    wall = plane((4.0, -8.0, -3.0), (4.0, 8.0, -3.0), (4.0, -8.0, 3.0))
    image = render(wall, geometry, np.eye(4))
    ranges = depth_array(image)
    assert np.nanmax(ranges) - np.nanmin(ranges) > 1.0  # curved in the range image: 4 m ahead, more aside
    quadtree = FilterQuadTree(QuadTreeParameters(reduction=reduction))
    quadtree.SetInputDataObject(image)
    quadtree.Update()
    mesh = quadtree.GetOutput()
    points = vtk_to_numpy(mesh.GetPoints().GetData()).astype(np.float64)
    assert np.abs(points[:, 0] - 4.0).max() < 0.002  # every vertex on the wall
    normals = vtk_to_numpy(mesh.GetCellData().GetNormals()).astype(np.float64)
    angle = np.degrees(np.arccos(np.clip(normals @ np.array([-1.0, 0.0, 0.0]), -1.0, 1.0)))
    assert angle.max() < 1.0  # facing the sensor, within a degree of the wall's normal
    level = vtk_to_numpy(mesh.GetCellData().GetArray("level"))
    beams_on_wall = int(np.isfinite(ranges).sum())
    assert level.max() >= 8 and mesh.GetNumberOfCells() < beams_on_wall / 8  # large merged faces
    # the faces cover the wall's seen part about as the pixel grid's triangles between the beams do
    from mabdi.polydata import polydata_area

    grid = FilterPixelGrid()
    grid.SetInputDataObject(image)
    grid.Update()
    assert polydata_area(mesh) > 0.8 * polydata_area(grid.GetOutput()) > 30.0


#: The circle both LiDAR scenes are scanned from, and their floor (TOML).
CIRCLE_PATH = """
[path]
radius_x = 2.5
radius_y = 2.2
z0 = 1.4
z1 = 1.6
look_from = [0.0, 0.0, 0.5]
look_to = [0.0, 0.0, 0.6]
"""
FLOOR = """
[[scene.objects]]
name = "floor"
type = "plane"
size = [8.0, 8.0]
"""

LIDAR_SCENE = """
[run]
name = "lidar_boxes"
frames = {frames}
seed = 2

[sensor]
kind = "lidar"
noise = "{noise}"

[sensor.lidar]
beams = 32
columns = 512
fov_up = 15.0
fov_down = -45.0
range_min = 0.3
range_max = 20.0

{path}
[surface]
method = "{surface}"

[surface.quadtree]
reduction = 1  # a LiDAR's beams are already further apart than a camera's 3 x 3 pixel blocks

{floor}
[[scene.objects]]
name = "stays"
type = "box"
size = [0.6, 0.6, 0.8]
position = [-0.8, 0.0, 0.0]

[[scene.objects]]
name = "leaves"
type = "box"
size = [0.6, 0.6, 0.8]
position = [0.8, 0.0, 0.0]
disappear_at = {leave}
"""


def run_scene(tmp_path, name: str, text: str, **values):
    """Write a scene's TOML (``text`` with the circle, the floor and ``values`` filled in) and run it:
    (the MappingRun, its result)."""
    from mabdi.loop import MappingRun

    path = tmp_path / f"{name}.toml"
    path.write_text(text.format(path=CIRCLE_PATH, floor=FLOOR, **values))
    simulation = MappingRun(load_run_config(path))
    return simulation, simulation.run()


def lidar_run(tmp_path, surface="pixel_grid", noise="none", frames=16, leave=1.0):
    return run_scene(
        tmp_path, f"lidar_{surface}_{noise}", LIDAR_SCENE,
        frames=frames, noise=noise, surface=surface, leave=leave if leave < 1.0 else frames + 1,
    )  # fmt: skip


@pytest.mark.parametrize("surface", ["pixel_grid", "quadtree"])
def test_lidar_loop_maps_the_scene_and_stops_growing(tmp_path, surface):
    from mabdi.evaluate import distances_to_mesh
    from mabdi.evaluate.metrics import evaluate_run

    simulation, result = lidar_run(tmp_path, surface)
    assert isinstance(simulation.source.intrinsics, SphericalGeometry)
    assert simulation.loop.world.store.chunk_size == LIDAR_CHUNK_SIZE  # a LiDAR's map in larger chunks than a camera's
    added = np.array([r.cells_added for r in result.records])
    assert added[8:].sum() <= 0.15 * added[:8].sum()  # the second circle adds little
    vertices, _ = polydata_arrays(result.mesh)
    assert np.median(distances_to_mesh(vertices[::5], simulation.scene.mesh_at(0))) < 1e-3
    scores = evaluate_run(simulation, result)
    assert scores.fscore_2cm > 0.9, scores


def test_lidar_loop_removes_a_box_that_leaves(tmp_path):
    simulation, result = lidar_run(tmp_path, frames=24, leave=0.5)
    points, triangles = polydata_arrays(result.mesh)
    centres = points[triangles].mean(axis=1)
    inside = np.all(np.abs(centres - (0.8, 0.0, 0.4)) < (0.32, 0.32, 0.42), axis=1) & (centres[:, 2] > 0.02)
    kept = np.all(np.abs(centres - (-0.8, 0.0, 0.4)) < (0.32, 0.32, 0.42), axis=1) & (centres[:, 2] > 0.02)
    assert sum(r.cells_removed for r in result.records) > 0
    assert inside.sum() <= 0.05 * kept.sum()  # the box that left is gone from the map, the other stays
    assert kept.sum() > 100


WIDE_STATIC_SCENE = """
[run]
name = "lidar_wide_static"
frames = 24
seed = 2

[sensor]
kind = "lidar"
noise = "range"

[sensor.lidar]
beams = 64
columns = 1024
fov_up = 45.0
fov_down = -45.0
range_min = 0.3
range_max = 30.0
sweep = "deskewed"

[sensor.noise_parameters]
range_sigma = 0.01

{path}
[surface]
method = "{surface}"

{floor}
[[scene.objects]]
name = "a"
type = "box"
size = [0.6, 0.6, 0.8]
position = [-0.8, 0.0, 0.0]

[[scene.objects]]
name = "b"
type = "box"
size = [0.4, 0.4, 1.2]
position = [0.8, 0.3, 0.0]

[[scene.objects]]
name = "c"
type = "box"
size = [0.3, 1.0, 0.5]
position = [0.2, -1.0, 0.0]
"""


@pytest.mark.parametrize("surface", ["pixel_grid", "quadtree"])
def test_a_static_scene_scanned_by_a_wide_lidar_keeps_its_faces_at_the_silhouettes(tmp_path, surface):
    """A wide-FoV LiDAR (64 beams over 90 degrees: 1.4 degrees between beams, 0.35 between columns) whose
    deskewed returns are carried to pixel centres: the map's silhouettes are off by up to a beam spacing in any
    direction, and a later scan sees past them. A misplaced edge explains that within a beam's angle down and
    across (rows and columns); a removal rule that reaches one pixel each way took 3-4% of this static map."""
    _, result = run_scene(tmp_path, "wide", WIDE_STATIC_SCENE, surface=surface)
    removed = sum(r.cells_removed for r in result.records)
    total = result.records[-1].cells_total
    assert total > 30_000
    assert removed <= 0.02 * total, (removed, total)


def test_one_projection_for_either_geometry_round_trips_pixel_centres():
    from mabdi.camera import Intrinsics, pixel_rays

    pose = np.eye(4)
    pose[:3, 3] = (1.0, -2.0, 0.5)
    a = math.radians(35.0)
    pose[:3, :3] = [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
    for geometry in (GEOMETRY, SphericalGeometry(8, 64, 10.0, -20.0, 0.5, 50.0, (8.0, 5.0, 1.0, -2.0, -6.0, -10.0, -15.0, -19.0)), Intrinsics(width=64, height=48, cx=32, cy=24)):
        values = np.random.default_rng(1).uniform(1.0, 9.0, geometry.shape)
        sensor = pixel_rays(geometry) * values[..., None]
        world = sensor.reshape(-1, 3) @ pose[:3, :3].T + pose[:3, 3]
        uv, value = geometry.project_points(world, pose)
        rows, cols = np.indices(geometry.shape)
        np.testing.assert_allclose(uv[:, 0], cols.ravel() + 0.5, atol=1e-6)
        np.testing.assert_allclose(uv[:, 1], rows.ravel() + 0.5, atol=1e-6)
        np.testing.assert_allclose(value, values.ravel(), rtol=1e-9)
        np.testing.assert_allclose(geometry.sensor_values(sensor), values, rtol=1e-9)
        if isinstance(geometry, SphericalGeometry):  # rays at continuous coordinates meet the pixel-centre rays
            np.testing.assert_allclose(geometry.rays_at(cols + 0.5, rows + 0.5), geometry.rays(), atol=1e-12)


@pytest.mark.parametrize("layout", ["kitti", "velodyne", "ouster"])
def test_recorded_lidar_scans_give_the_simulators_map(tmp_path, layout):
    # the simulated LiDAR's scans written as a KITTI-style folder or as PointCloud2 in a ROS 2 bag and read
    # back: the loop on the recording makes the map the simulator's frames make (triangle count within 1%)
    from mabdi.loop.loop import MabdiLoop
    from mabdi.simulate.rig import SimulatedRig
    from mabdi.sources.kitti import write_kitti
    from mabdi.sources.rosbag2 import write_lidar_rosbag2
    from mabdi.sources.sequences import open_sequence

    path = tmp_path / "lidar.toml"
    path.write_text(LIDAR_SCENE.format(path=CIRCLE_PATH, floor=FLOOR, frames=8, noise="none", surface="pixel_grid", leave=9))
    config = load_run_config(path)
    rig = SimulatedRig.from_config(config)
    folder = tmp_path / "recording"
    if layout == "kitti":
        write_kitti(rig, folder)
    else:
        write_lidar_rosbag2(rig, folder, layout=layout)
    recording = open_sequence(folder)
    assert recording.intrinsics == rig.intrinsics and len(recording) == len(rig)

    def triangles(source):
        loop = MabdiLoop.from_config(config, source)
        for i in range(len(source)):
            loop.step(i)
        return loop.mesh().GetNumberOfCells()

    simulated, recorded = triangles(rig), triangles(recording)
    assert simulated > 1000
    assert abs(recorded - simulated) <= 0.01 * simulated
    rig.close()


def test_the_pixel_grid_joins_the_azimuth_seam():
    """A range image's columns go round 360 degrees: a wall behind the sensor, where the last column meets the
    first, is meshed across the seam (the point straight behind is covered) with every vertex on the wall."""
    geometry = SphericalGeometry(16, 256, 10.0, -10.0, 0.5, 30.0)
    wall = plane((-5.0, -8.0, -3.0), (-5.0, 8.0, -3.0), (-5.0, -8.0, 3.0))  # azimuth +-180 degrees: the seam
    surface = FilterPixelGrid()
    surface.SetInputDataObject(render(wall, geometry, np.eye(4)))
    surface.Update()
    points, triangles = polydata_arrays(surface.GetOutput())
    assert np.abs(points[:, 0] + 5.0).max() < 1e-4
    corners = points[triangles][:, :, 1:]  # (y, z) on the wall
    across = (corners[:, :, 0].max(axis=1) > 0) & (corners[:, :, 0].min(axis=1) < 0)
    assert across.sum() == 2 * (geometry.beams - 1)  # one pair of triangles per pair of beams across the seam
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]

    def side(start, end, point):  # the z of the 2-D cross product: which side of start -> end the point lies
        return (end[:, 0] - start[:, 0]) * (point[1] - start[:, 1]) - (end[:, 1] - start[:, 1]) * (point[0] - start[:, 0])

    for target in ([0.0, 0.0], [0.0, 0.5]):
        p = np.asarray(target)
        u, v, w = side(a, b, p), side(b, c, p), side(c, a, p)
        assert (((u >= 0) & (v >= 0) & (w >= 0)) | ((u <= 0) & (v <= 0) & (w <= 0))).any(), target


def test_expected_range_image_says_where_the_map_reaches_into_a_beams_footprint():
    """A floor patch 4 to 8 m ahead of a LiDAR 1.9 m up: E's ``map_in_footprint`` is set at the beams that hit
    it, and at a beam that misses it exactly where the patch's far edge lies within half a beam step of it."""
    from mabdi.stages.expected_image import map_in_footprint

    lidar = SphericalGeometry(32, 256, 2.0, -30.0, 0.5, 50.0)  # beams 1 degree apart
    height = 1.9
    patch = plane((4.0, -1.0, 0.0), (8.0, -1.0, 0.0), (4.0, 1.0, 0.0))
    pose = np.eye(4)
    pose[2, 3] = height
    expected = FilterExpectedImage()
    expected.SetInputDataObject(0, patch)
    expected.SetInputDataObject(1, render(plane((-50, -50, 0), (50, -50, 0), (-50, 50, 0)), lidar, pose))
    expected.Update()
    covered = map_in_footprint(expected.GetOutput())
    e = depth_array(expected.GetOutput())
    assert covered[np.isfinite(e)].all()
    column = lidar.columns // 2  # looks forward (azimuth -0.7 degrees)
    elevation = np.degrees(lidar.elevations())
    step = (lidar.fov_up - lidar.fov_down) / lidar.beams
    near_edge, far_edge = -np.degrees(np.arctan(height / 4.0)), -np.degrees(np.arctan(height / 8.0))
    # the patch spans elevations [near_edge, far_edge] ahead; a footprint is the beam's elevation +- step / 2
    clearly_in = (elevation - 0.4 * step <= far_edge) & (elevation + 0.4 * step >= near_edge)
    clearly_out = (elevation - 0.6 * step > far_edge) | (elevation + 0.6 * step < near_edge)
    assert clearly_in.sum() >= 4 and clearly_out.sum() >= 8
    assert covered[clearly_in, column].all() and not covered[clearly_out, column].any()
    assert np.isnan(e[clearly_out, column]).all()
    # a camera's E does not say
    camera = FilterExpectedImage()
    camera.SetInputDataObject(0, patch)
    camera.SetInputDataObject(1, DepthFrame(np.full((48, 64), 2.0, dtype=np.float32), Intrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=32.0, cy=24.0), pose, 0).to_image())
    camera.Update()
    assert map_in_footprint(camera.GetOutput()) is None


def test_thin_novel_strips_go_only_where_the_map_reaches_into_their_footprint():
    from mabdi.stages.classifier import remove_specks

    novel = np.zeros((16, 64), dtype=bool)
    novel[5, 2:62] = True  # a strip one pixel tall, 60 long
    novel[10, 20:30] = True  # one pixel tall, 10 long: under min_region
    novel[12:15, 40:52] = True  # wide enough for the opening
    covered = np.zeros_like(novel)
    covered[5, 2:28] = True  # the map reaches into the strip's left part
    kept = remove_specks(novel, 3, 32, covered)
    assert kept[5, 28:62].all() and not kept[5, 2:28].any()
    assert not kept[10].any() and kept[12:15, 40:52].all()
    without = remove_specks(novel, 3, 32)  # no word on the map's reach (a camera): every thin region goes
    assert not without[5].any() and without[12:15, 40:52].all()


def test_the_quadtree_s_reduction_is_a_camera_s_3_and_a_range_image_s_1():
    # A LiDAR's beams are further apart than a camera's 3 x 3 pixels: "auto" reduces a range image by 1.
    from vtkmodules.util.numpy_support import vtk_to_numpy

    from mabdi.camera import Intrinsics
    from mabdi.surfaces.quadtree import FilterQuadTree, QuadTreeParameters, resolved

    geometry = SphericalGeometry(32, 512, 10.0, -20.0, 0.5, 50.0)
    assert resolved(QuadTreeParameters(), geometry).reduction == 1
    assert resolved(QuadTreeParameters(), Intrinsics()).reduction == 3
    assert resolved(QuadTreeParameters(reduction=2), geometry).reduction == 2  # a number stays
    wall = plane((4.0, -8.0, -3.0), (4.0, 8.0, -3.0), (4.0, -8.0, 3.0))
    image = render(wall, geometry, np.eye(4))
    meshes = []
    for parameters in (QuadTreeParameters(), QuadTreeParameters(reduction=1)):
        quadtree = FilterQuadTree(parameters)
        quadtree.SetInputDataObject(image)
        quadtree.Update()
        meshes.append(vtk_to_numpy(quadtree.GetOutput().GetPoints().GetData()))
    np.testing.assert_array_equal(meshes[0], meshes[1])


def _corridor_scan(geometry, seed=0, origin=(0.0, 0.0, 0.0)):
    """A deskewed-like scan of a 40 x 6 x 3 m corridor centred on the world's origin, from ``origin``: one return a
    pixel, each anywhere in its pixel (continuous elevations and azimuths), exact. Returns the points (sensor
    frame, axes as the world's) and the corridor's half sizes (m)."""
    rng = np.random.default_rng(seed)
    step = np.radians((geometry.fov_up - geometry.fov_down) / geometry.beams)
    az = geometry.azimuths()[None, :] + 0.9 * 2 * np.pi / geometry.columns * rng.uniform(-0.5, 0.5, geometry.shape)
    el = geometry.elevations()[:, None] + 0.9 * step * rng.uniform(-0.5, 0.5, geometry.shape)
    rays = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)], axis=-1)
    half = np.array([20.0, 3.0, 1.5])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.nanmin(np.where(rays != 0, (np.sign(rays) * half - np.asarray(origin)) / rays, np.inf), axis=-1)
    return (rays * t[..., None]).reshape(-1, 3), half


def test_a_scan_is_meshed_where_its_returns_lie_not_at_its_pixel_centres():
    # Walls, floor and ceiling seen at grazing incidence down a corridor: a pixel centre's range, carried from
    # the returns around it, is off the surface by centimetres there; the pixel's own return is on it.
    from mabdi.depth import NO_NOISE
    from mabdi.frame_values import Measured
    from mabdi.sources.range_images import range_image_and_returns
    from mabdi.surfaces.quadtree import QuadTreeParameters, leaves_of_image

    geometry = SphericalGeometry(64, 1024, 45.0, -45.0, 0.5, 50.0)
    points, half = _corridor_scan(geometry)
    depth, returns = range_image_and_returns(points, geometry)

    def off(vertices):  # m from the nearest wall, floor or ceiling
        return np.min(np.abs(np.abs(vertices) - half), axis=1)

    at_centres, at_returns = (Measured(depth, geometry, np.eye(4), NO_NOISE, 0, return_points=r) for r in (None, returns))
    grid = FilterPixelGrid()
    vertices, triangles = polydata_arrays(grid.mesh_frame(at_returns))
    assert len(triangles) > 100_000
    assert off(vertices[np.unique(triangles)]).max() < 1e-3
    vertices, triangles = polydata_arrays(grid.mesh_frame(at_centres))
    assert np.percentile(off(vertices[np.unique(triangles)]), 99) > 0.01  # what the pixel centres gave

    # the quad-tree's leaves: each plane through its own pixels' returns
    def leaf_residuals(measured):
        _, _, leaves, _ = leaves_of_image(depth, geometry, QuadTreeParameters(), NO_NOISE, None, measured.return_points)
        worst = []
        for level, row, col, normal, point in zip(leaves.level, leaves.row, leaves.col, leaves.normal, leaves.point):
            side = 1 << int(level)
            block = returns[row * side : (row + 1) * side, col * side : (col + 1) * side].reshape(-1, 3)
            block = block[np.isfinite(block).all(axis=1)]
            worst.append(np.abs((block - point) @ normal).max() if len(block) else 0.0)
        return np.array(worst)

    assert np.percentile(leaf_residuals(at_returns), 99) < 1e-4
    assert np.percentile(leaf_residuals(at_centres), 99) > 0.01


def _one_pixel_normal_errors(points, half, geometry, noise):
    """Degrees between each one-pixel leaf's normal (no merging: every pixel its own leaf) and the corridor
    surface it lies on, away from the corridor's edges; and each leaf's range (m)."""
    from mabdi.sources.range_images import range_image_and_returns
    from mabdi.surfaces.quadtree import QuadTreeParameters, leaves_of_image

    depth, returns = range_image_and_returns(points, geometry)
    unmerged = QuadTreeParameters(n_t=0.0, d_t=1e-9, smooth_depth=False)
    _, _, leaves, _ = leaves_of_image(depth, geometry, unmerged, noise, None, returns)
    point, normal = leaves.point[leaves.level == 0], leaves.normal[leaves.level == 0]
    truth = np.eye(3)[np.argmin(np.abs(np.abs(point) - half), axis=1)]
    inner = np.sort(np.abs(np.abs(point) - half), axis=1)[:, 1] > 0.3  # 30 cm from another surface
    error = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", normal, truth)), 0.0, 1.0)))
    return error[inner], np.linalg.norm(point[inner], axis=1)


def test_a_lidar_pixel_s_normal_comes_from_its_neighbours_returns_a_beam_s_angle_along_its_row():
    # A deskewed scan's returns lie anywhere in their pixels. Points on the centre rays (the range carried to
    # each centre) tilt a pixel's normal by degrees, which a leaf's corner, half a beam away at grazing
    # incidence, turns into centimetres off the surface; the returns themselves are on it. Along a row the
    # next column's return lies a quarter of a beam's angle away here, so the range noise tilts a normal
    # from it four times as much as across the rows: the normal reaches a beam's angle along the row.
    from mabdi.depth import NO_NOISE
    from mabdi.surfaces.quadtree import normal_column_step

    geometry = SphericalGeometry(64, 1024, 45.0, -45.0, 0.5, 50.0)
    assert normal_column_step(geometry) == 4  # 1.43 degrees between beams, 0.35 between columns
    assert normal_column_step(SphericalGeometry(64, 1024, 2.0, -24.8)) == 1  # 0.43 against 0.35
    assert normal_column_step(SphericalGeometry(16, 4096, 15.0, -15.0)) == 8  # 2 against 0.088: at most 8
    points, half = _corridor_scan(geometry)
    error, distance = _one_pixel_normal_errors(points, half, geometry, NO_NOISE)
    assert len(error) > 50_000
    assert np.percentile(error[distance < 8.0], 99) < 0.01  # on the pixel centres' rays: 24 degrees

    rng = np.random.default_rng(1)
    ranges = np.linalg.norm(points, axis=1)
    noisy = points * ((ranges + rng.normal(0.0, 0.02, len(ranges))) / ranges)[:, None]
    error, distance = _one_pixel_normal_errors(noisy, half, geometry, SensorNoise("range", range_sigma=0.02))
    # 4-8 m: the next column's return alone gives 6.2 degrees, the pixel centres' 4.5
    assert np.median(error[(distance > 4.0) & (distance < 8.0)]) < 3.0


def test_e_is_compared_with_a_return_along_the_return_s_own_ray():
    # The same corridor, mapped exactly: a pixel's range carried to its centre's ray is centimetres off at grazing
    # incidence, so D - E along the centre rays would read the map as seen through or in front of the scan. Cast
    # along each return's own ray and carried as its return was, E agrees with D to float precision.
    from mabdi.depth import NO_NOISE
    from mabdi.frame_values import Measured
    from dataclasses import replace

    from mabdi.render.range_rendering import sector_views
    from mabdi.stages.classifier import CONTRADICTED, ClassifierParameters, FilterClassifier
    from mabdi.sources.range_images import range_image_and_returns

    geometry = SphericalGeometry(64, 1024, 45.0, -45.0, 0.5, 50.0)
    points, half = _corridor_scan(geometry, seed=1)
    depth, returns = range_image_and_returns(points, geometry)
    corridor = box((0.0, 0.0, 0.0), 2 * half, 0.0)
    measured = Measured(depth, geometry, np.eye(4), NO_NOISE, 0, return_points=returns)
    stage = FilterExpectedImage(identity=True)
    at_centres = stage.render(corridor, measured)
    along = stage.along_returns(measured, at_centres)
    gaps = {}
    for name, expected in (("centres", at_centres), ("returns", along)):
        both = np.isfinite(depth) & np.isfinite(expected.depth)
        assert both.sum() >= 0.999 * np.isfinite(depth).sum()
        gaps[name] = np.abs(depth - expected.depth)[both]
        assert (expected.face_ids[both] > 0).all()
    assert np.percentile(gaps["centres"], 99) > 0.01  # what the centre rays read
    assert gaps["returns"].max() < 1e-3
    # each return's own ray meets the wall, floor or ceiling it lies on
    x, y, z = (np.abs(returns[..., k]) for k in range(3))
    on = np.stack([np.abs(x - half[0]), np.abs(y - half[1]), np.abs(z - half[2])]).argmin(axis=0)
    normals = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    corners, triangles = polydata_arrays(corridor)
    face_normals = np.abs(np.cross(*(corners[triangles[:, k]] - corners[triangles[:, 0]] for k in (1, 2))))
    face_axis = face_normals.argmax(axis=1)
    cells = along.table.lookup(along.face_ids)[1]
    assert (face_axis[cells[both]] == on[both]).all()
    # classified as D is: along the centre rays the carried ranges see through the exact map, along the returns none
    classifier = FilterClassifier(ClassifierParameters())
    noisy = replace(measured, noise=SensorNoise("range"))
    assert (classifier.classify(noisy, at_centres).labels == CONTRADICTED).sum() > 100
    assert (classifier.classify(noisy, along).labels == CONTRADICTED).sum() == 0
    # a scan without returns of its own (an instant sweep) is compared along its centre rays
    plain = replace(measured, return_points=None)
    assert stage.along_returns(plain, at_centres) is at_centres
    with pytest.raises(ValueError, match="render E of this frame first"):
        stage.along_returns(replace(measured, index=1), at_centres)
    moved = np.eye(4)
    moved[:3, 3] = (1.0, 0.0, 0.0)
    stage.render(corridor, replace(measured, pose=moved))  # the drawing is another pose's now
    with pytest.raises(ValueError, match="render E of this frame first"):
        stage.along_returns(measured, at_centres)

    # a direction's render pixel: a centre ray's is the cached one; NaN, or a window leaving the renders, none
    views = sector_views(geometry)
    rays = geometry.rays().reshape(-1, 3)
    np.testing.assert_array_equal(views.render_pixels(rays), views.centres)
    up = np.array([[0.0, 0.0, 1.0], [np.nan, np.nan, np.nan]])
    np.testing.assert_array_equal(views.render_pixels(up), [-1, -1])


def test_the_loop_s_removal_votes_along_each_return_s_own_ray():
    # Scans of the mapped corridor that keep their own returns: the classifier (novelty, along the centre rays)
    # reads some carried ranges as seeing through the map; removal's votes, along the returns' own rays, none.
    from mabdi.depth import DepthFrame
    from mabdi.loop import MabdiLoop
    from mabdi.sources.frames import FrameList
    from mabdi.sources.range_images import range_image_and_returns
    from mabdi.stages.classifier import CONTRADICTED

    geometry = SphericalGeometry(64, 1024, 45.0, -45.0, 0.5, 50.0)
    frames = []
    for i in range(3):
        origin = (-2.0 + 2.0 * i, 0.3 * (i % 2), 0.1 * i - 0.1)
        points, half = _corridor_scan(geometry, seed=i, origin=origin)
        depth, returns = range_image_and_returns(points, geometry)
        pose = np.eye(4)
        pose[:3, 3] = origin
        frames.append(DepthFrame(depth, geometry, pose, i, float(i), None, returns))
    loop = MabdiLoop(FrameList(frames, "corridor"), surface="pixel_grid", noise=SensorNoise("range"))
    loop.world.append(_box_inside(half, cell=0.25), 0)  # the corridor mapped exactly, in faces a quarter metre wide
    seen = []
    find = loop.object_removal.find

    def spy(measured, expected, classified, *rest):
        seen.append(classified)
        return find(measured, expected, classified, *rest)

    loop.object_removal.find = spy
    records = [loop.step(i) for i in range(len(frames))]
    assert len(seen) == len(frames)
    assert all(record.contradicted_pixels > 100 for record in records)
    assert all((classified.labels == CONTRADICTED).sum() == 0 for classified in seen)
    assert sum(record.cells_removed for record in records) == 0


def _box_inside(half, cell):
    """The six walls of a box of half sizes ``half`` (m) centred on the origin, in squares of about ``cell`` m."""
    hx, hy, hz = half
    walls = []
    for origin, point1, point2 in (
        ((-hx, -hy, -hz), (hx, -hy, -hz), (-hx, hy, -hz)), ((-hx, -hy, hz), (hx, -hy, hz), (-hx, hy, hz)),
        ((-hx, -hy, -hz), (hx, -hy, -hz), (-hx, -hy, hz)), ((-hx, hy, -hz), (hx, hy, -hz), (-hx, hy, hz)),
        ((-hx, -hy, -hz), (-hx, hy, -hz), (-hx, -hy, hz)), ((hx, -hy, -hz), (hx, hy, -hz), (hx, -hy, hz)),
    ):  # fmt: skip
        source = vtkPlaneSource()
        source.SetOrigin(*origin)
        source.SetPoint1(*point1)
        source.SetPoint2(*point2)
        sides = np.linalg.norm(np.subtract(point1, origin)), np.linalg.norm(np.subtract(point2, origin))
        source.SetResolution(*(max(1, int(side / cell)) for side in sides))
        source.Update()
        walls.append(source.GetOutput())
    return merged(*walls)


def test_the_compiled_straight_line_test_is_the_numpy_definition():
    # mabdi.depth._continues says what the test is; the kernel computes it over an image in each direction.
    from mabdi.depth import LINE_FLOOR, LINE_SIGMAS, LINE_SPACING, _continues
    from mabdi.depth_kernels import continues_kernel

    rng = np.random.default_rng(4)
    base = np.cumsum(rng.normal(0.0, 0.3, (40, 50, 3)), axis=0)  # lines, some straight enough and some not
    points = base + rng.normal(0.0, 0.005, base.shape) * (rng.random((40, 50, 1)) < 0.5)
    points[rng.random((40, 50)) < 0.05] = np.nan
    points[3, 4] = points[4, 4]  # a zero step
    sigma = rng.uniform(0.001, 0.05, (40, 50))
    for start, step in (((0, 0), (1, 0)), ((2, 0), (-1, 0)), ((0, 0), (0, 1)), ((0, 2), (0, -1)), ((0, 2), (1, -1)), ((2, 0), (-1, 1))):
        rows, cols = 40 - 2 * abs(step[0]), 50 - 2 * abs(step[1])
        out = np.zeros((rows, cols), dtype=bool)
        continues_kernel(points, sigma, start[0], start[1], step[0], step[1], LINE_SIGMAS, LINE_FLOOR, LINE_SPACING, out)

        def at(k):  # the k-th sample of each triple
            v0, u0 = start[0] + k * step[0], start[1] + k * step[1]
            return v0, u0

        (va, ua), (vb, ub), (vc, uc) = at(0), at(1), at(2)
        expected = _continues(
            points[va : va + rows, ua : ua + cols], points[vb : vb + rows, ub : ub + cols], points[vc : vc + rows, uc : uc + cols],
            sigma[vc : vc + rows, uc : uc + cols],
        )  # fmt: skip
        np.testing.assert_array_equal(out, expected)
        assert 0 < out.sum() < out.size
