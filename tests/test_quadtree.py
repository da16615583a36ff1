"""FilterQuadTree: merging against known answers, no bridges, no cracks, and in the MABDI loop."""

from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkFiltersCore import vtkFeatureEdges

from conftest import REPO, check_table_loop
from mabdi.camera import Intrinsics, project
from mabdi.depth import depth_image
from mabdi.surfaces.quadtree import FilterQuadTree, QuadTreeParameters

K = Intrinsics(fx=200.0, fy=200.0, cx=128.0, cy=128.0, width=256, height=256, near=0.3, far=6.0)


def mesh_of(depth, **parameters):
    quadtree = FilterQuadTree(QuadTreeParameters(**parameters))
    quadtree.SetInputDataObject(depth_image(depth, K, np.eye(4)))
    quadtree.Update()
    return quadtree.GetOutput()


def oblique_plane():
    normal = np.array([0.0, -np.sin(0.6), -np.cos(0.6)])
    return (normal @ [0.0, 0.0, 2.0]) / (K.rays() @ normal)


def smooth_surface():
    v, u = np.mgrid[0:256, 0:256]
    return 2.0 + 0.3 * np.sin(u / 40.0) * np.cos(v / 50.0)


def test_fronto_parallel_plane_is_one_quad():
    mesh = mesh_of(np.full((256, 256), 2.0), reduction=1)
    assert mesh.GetNumberOfCells() == 1 and mesh.GetCell(0).GetNumberOfPoints() == 4
    np.testing.assert_allclose(vtk_to_numpy(mesh.GetPoints().GetData())[:, 2], 2.0, atol=1e-6)


def test_oblique_plane_is_few_quads_and_n_t_zero_is_one_per_pixel():
    assert mesh_of(oblique_plane(), reduction=1).GetNumberOfCells() <= 4
    assert mesh_of(oblique_plane(), reduction=1, n_t=0.0).GetNumberOfCells() == 256 * 256


def test_face_count_falls_as_n_t_grows():
    counts = [mesh_of(smooth_surface(), reduction=1, n_t=n_t).GetNumberOfCells() for n_t in (0.005, 0.01, 0.02, 0.05, 0.1, 0.2)]
    assert all(a >= b for a, b in zip(counts, counts[1:], strict=False)), counts
    assert counts[0] > 4 * counts[-1]


def test_a_step_is_never_bridged():
    depth = np.full((256, 256), 1.0)
    depth[:, 128:] = 2.0
    mesh = mesh_of(depth, reduction=1)
    z = vtk_to_numpy(mesh.GetPoints().GetData())[:, 2]
    for i in range(mesh.GetNumberOfCells()):
        ids = [mesh.GetCell(i).GetPointId(j) for j in range(mesh.GetCell(i).GetNumberOfPoints())]
        near = z[ids] < 1.5
        assert near.all() or (~near).all()


@pytest.mark.parametrize("reduction", [1, 3])
def test_smooth_surface_with_mixed_quad_sizes_is_closed(reduction):
    mesh = mesh_of(smooth_surface(), reduction=reduction, n_t=0.02)
    levels = vtk_to_numpy(mesh.GetCellData().GetArray("level"))
    assert len(set(levels.tolist())) >= 2  # quads of mixed sizes meet (T-vertices)
    assert any(mesh.GetCell(i).GetNumberOfPoints() > 4 for i in range(mesh.GetNumberOfCells()))
    edges = vtkFeatureEdges()
    edges.SetInputData(mesh)
    edges.BoundaryEdgesOn()
    edges.NonManifoldEdgesOn()
    edges.FeatureEdgesOff()
    edges.ManifoldEdgesOff()
    edges.Update()
    points = vtk_to_numpy(edges.GetOutput().GetPoints().GetData()).astype(np.float64)
    uv, _ = project(points, K, np.eye(4))
    size = 256 // reduction * reduction
    # the image's border is no silhouette (the surface goes on beyond the field of view): the open edges lie on it
    band = 1e-3
    on_border = (uv[:, 0] < band) | (uv[:, 1] < band) | (uv[:, 0] > size - band) | (uv[:, 1] > size - band)
    assert on_border.all(), f"{(~on_border).sum()} open-edge points inside the image"


@pytest.mark.parametrize("beyond", [np.nan, 4.0])
def test_a_silhouette_ends_at_the_outermost_input_pixel_on_the_surface(beyond):
    """A wall 2 m away over input columns [102, 201) and rows [90, 200), nothing (or a wall 4 m away) around
    it, reduced by 3. Where a block's outermost input pixel is on the wall (columns 102 and 200, row 90) the
    face ends at that pixel's centre, not half a block in (which lost a pixel along every silhouette); where
    the outermost pixel of a block is off it (row 200, in the blocks of rows 198-200) it ends at the block's
    middle pixel, 199.5, the centre of the last pixel on the wall either way."""
    depth = np.full((256, 256), beyond)
    depth[90:200, 102:201] = 2.0
    mesh = mesh_of(depth, reduction=3)
    points = vtk_to_numpy(mesh.GetPoints().GetData()).astype(np.float64)
    uv, _ = project(points[points[:, 2] < 3.0], K, np.eye(4))
    np.testing.assert_allclose(uv.min(axis=0), [102.5, 90.5], atol=1e-6)
    np.testing.assert_allclose(uv.max(axis=0), [200.5, 199.5], atol=1e-6)
    # the outline is the rectangle: every open edge lies on one of its four sides (corners that leaves along
    # a side share move across it only)
    edges = vtkFeatureEdges()
    edges.SetInputData(mesh)
    edges.BoundaryEdgesOn()
    edges.NonManifoldEdgesOff()
    edges.FeatureEdgesOff()
    edges.ManifoldEdgesOff()
    edges.Update()
    outline = vtk_to_numpy(edges.GetOutput().GetPoints().GetData()).astype(np.float64)
    uv, _ = project(outline[outline[:, 2] < 3.0], K, np.eye(4))
    on_side = np.isclose(uv[:, 0], 102.5) | np.isclose(uv[:, 0], 200.5) | np.isclose(uv[:, 1], 90.5) | np.isclose(uv[:, 1], 199.5)
    assert on_side.all(), uv[~on_side]


def test_only_valid_pixels_are_meshed():
    depth = np.full((256, 256), 2.0)
    depth[64:192, 64:192] = np.nan
    mesh = mesh_of(depth, reduction=1)
    uv, _ = project(vtk_to_numpy(mesh.GetPoints().GetData()).astype(np.float64), K, np.eye(4))
    centres = np.array([np.mean(uv[[mesh.GetCell(i).GetPointId(j) for j in range(4)]], axis=0) for i in range(mesh.GetNumberOfCells())])
    inside_hole = (centres > 64.5).all(axis=1) & (centres < 191.5).all(axis=1)
    assert not inside_hole.any()


def test_bad_parameters():
    from mabdi.errors import ConfigError

    with pytest.raises(ConfigError, match="reduction"):
        QuadTreeParameters(reduction=0)


@pytest.mark.slow
def test_quadtree_in_the_loop_on_the_table():
    check_table_loop("quadtree", median_limit=5e-3)


@pytest.mark.slow
def test_faces_lie_on_the_noise_free_table():
    """Every face (its centre) within 1 cm of the scene, over ten poses of Run 1 (noise-free)."""
    from mabdi.config import load_run_config
    from mabdi.evaluate import distances_to_mesh
    from mabdi.render.depth_image import FilterDepthImage
    from mabdi.simulate.path import path_from_config
    from mabdi.sources.scene import SourceScene

    config = load_run_config(REPO / "scenes" / "table.toml")
    scene = SourceScene(config.scene, frames=config.run.frames)
    sensor = FilterDepthImage()
    sensor.SetInputConnection(scene.GetOutputPort())
    quadtree = FilterQuadTree(QuadTreeParameters(triangles=True))
    quadtree.SetInputConnection(sensor.GetOutputPort())
    distances = []
    for pose in path_from_config(config.run.frames, config.path)[::3]:
        sensor.pose = pose
        quadtree.Update()
        mesh = quadtree.GetOutput()
        points = vtk_to_numpy(mesh.GetPoints().GetData()).astype(np.float64)
        triangles = vtk_to_numpy(mesh.GetPolys().GetConnectivityArray()).reshape(-1, 3)
        distances.append(distances_to_mesh(points[triangles].mean(axis=1), scene.mesh_at(0)))
    distances = np.concatenate(distances)
    assert len(distances) > 40_000
    assert distances.max() <= 0.01, f"{(distances > 0.01).sum()} faces beyond 1 cm, worst {distances.max() * 1000:.1f} mm"


@pytest.mark.parametrize("noise", ["none", "kinect", "structured_light"])
def test_compiled_stages_give_the_numpy_leaves(noise):
    """The numba kernels (reduce, normals, pyramid, plane test) against the numpy reference, on Run 1
    (structured light: with the noise-aware merge test)."""
    from reference_kernels import quadtree_leaves_of_image

    from mabdi.config import load_run_config
    from mabdi.depth import depth_array
    from mabdi.render.depth_image import FilterDepthImage
    from mabdi.sensor_noise import SensorNoise
    from mabdi.surfaces.quadtree import leaves_of_image
    from mabdi.simulate.path import path_from_config
    from mabdi.sources.scene import SourceScene

    config = load_run_config(REPO / "scenes" / "table.toml")
    scene = SourceScene(config.scene, frames=config.run.frames)
    sensor = FilterDepthImage(noise=noise, seed=3)
    sensor.SetInputConnection(scene.GetOutputPort())
    parameters = QuadTreeParameters(triangles=True)
    for pose in path_from_config(config.run.frames, config.path)[::10]:
        sensor.pose = pose
        sensor.Update()
        depth = depth_array(sensor.GetOutput())
        fast = leaves_of_image(depth, sensor.intrinsics, parameters, SensorNoise(noise))
        slow = quadtree_leaves_of_image(depth, sensor.intrinsics, parameters, SensorNoise(noise))
        # block medians: the same depth (a tie may pick another pixel of that depth)
        np.testing.assert_array_equal(np.isfinite(fast[0][..., 2]), np.isfinite(slow[0][..., 2]))
        np.testing.assert_array_equal(fast[0][..., 2], slow[0][..., 2])
        a, b = fast[2], slow[2]
        assert a.regions == b.regions > 0
        np.testing.assert_array_equal(np.lexsort((a.col, a.row, a.level)), np.lexsort((b.col, b.row, b.level)))
        for name in ("level", "row", "col"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        np.testing.assert_allclose(a.point, b.point, atol=2e-2)
        np.testing.assert_allclose(a.normal, b.normal, atol=1e-6)


def test_noise_aware_merging_makes_fewer_faces_where_the_noise_hides_the_difference():
    """Under noise correlated across pixels (the structured-light model), the merge test allows what the noise
    makes children's normals and centroids stray: a plane at about 3.5 m gets under half the faces and its
    vertices lie nearer the truth; a wavy surface at 2 m keeps its shape (vertex errors no larger). "auto"
    turns it on for that noise and off for the Kinect model (independent noise)."""
    from mabdi.sensor_noise import SensorNoise, correlated_field

    noise = SensorNoise("structured_light")

    def run(truth, merge, model=noise):
        field = correlated_field(truth.shape, noise.correlation_length, np.random.default_rng(1))
        depth = (truth + noise.sigma(truth, K.near, K.far) * field).astype(np.float32)
        quadtree = FilterQuadTree(QuadTreeParameters(noise_merge=merge, triangles=True))
        quadtree.SetInputDataObject(depth_image(depth, K, np.eye(4), noise=model))
        quadtree.Update()
        mesh = quadtree.GetOutput()
        points = vtk_to_numpy(mesh.GetPoints().GetData())
        uv, z = project(points, K, np.eye(4))
        u, v = np.floor(uv).astype(int).T
        inside = (u >= 0) & (v >= 0) & (u < K.width) & (v < K.height)
        error = np.abs(z[inside] - truth[v[inside], u[inside]])
        return mesh.GetNumberOfCells(), error.mean(), np.percentile(error, 95)

    plane = 1.75 * oblique_plane()
    (faces_off, mean_off, _), (faces_on, mean_on, _) = run(plane, False), run(plane, True)
    assert faces_on < 0.5 * faces_off and mean_on <= mean_off, (faces_on, faces_off, mean_on, mean_off)
    wavy = smooth_surface()
    (_, mean_off, p95_off), (_, mean_on, p95_on) = run(wavy, False), run(wavy, True)
    assert mean_on <= 1.05 * mean_off and p95_on <= 1.05 * p95_off, (mean_on, mean_off, p95_on, p95_off)
    assert run(plane, "auto")[0] == faces_on
    assert run(plane, "auto", SensorNoise("kinect"))[0] == run(plane, False, SensorNoise("kinect"))[0]
    from mabdi.errors import ConfigError

    with pytest.raises(ConfigError, match="noise_merge"):
        QuadTreeParameters(noise_merge="yes")
