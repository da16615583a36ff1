"""FilterDepthImage: metric accuracy against analytic depth, noise models, reproducibility, errors."""

from __future__ import annotations

import ctypes.util

import numpy as np
import pytest
from scipy.ndimage import binary_erosion
from vtkmodules.vtkFiltersSources import vtkSphereSource

from conftest import plane_mesh
from mabdi.camera import Intrinsics, backproject, look_at
from mabdi.depth import DepthFrame, depth_array
from mabdi.errors import ConfigError, PoseError
from mabdi.render.depth_image import FilterDepthImage
from mabdi.sensor_noise import SensorNoise
from mabdi.sources.scene import SourceScene


def render(mesh, pose=None, **kwargs) -> DepthFrame:
    sensor = FilterDepthImage(**kwargs)
    sensor.SetInputDataObject(mesh)
    sensor.pose = np.eye(4) if pose is None else pose
    sensor.Update()
    return DepthFrame.from_image(sensor.GetOutput())


def rotation_x(degrees):
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rotation_y(degrees):
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def analytic_plane_depth(intrinsics: Intrinsics, point, normal) -> np.ndarray:
    """z-depth of the plane (point, normal) through every pixel centre (camera frame = world frame)."""
    rays = intrinsics.rays()
    with np.errstate(divide="ignore"):
        return (np.dot(normal, point) / (rays @ normal)) * 1.0


def test_plane_facing_camera_reads_two_metres_everywhere():
    frame = render(plane_mesh([0, 0, 2.0], [0, 0, -1]))
    assert np.isfinite(frame.depth).all()
    np.testing.assert_allclose(frame.depth, 2.0, atol=1e-3)


@pytest.mark.parametrize("axis", ["x", "y"])
def test_tilted_plane_matches_analytic_depth(axis):
    rotate = rotation_x if axis == "x" else rotation_y
    normal = rotate(60.0) @ np.array([0.0, 0.0, -1.0])
    point = np.array([0.0, 0.0, 2.0])
    intrinsics = Intrinsics()
    frame = render(plane_mesh(point, normal), intrinsics=intrinsics)
    expected = analytic_plane_depth(intrinsics, point, normal)
    in_range = (expected > intrinsics.near) & (expected < intrinsics.far)
    # pixels next to the range limits may fall either side of them
    inner = (expected > intrinsics.near * 1.01) & (expected < intrinsics.far * 0.99)
    measured = np.isfinite(frame.depth)
    assert np.array_equal(measured[inner], np.ones(inner.sum(), bool))
    assert not measured[~in_range & ((expected < intrinsics.near * 0.99) | (expected > intrinsics.far * 1.01))].any()
    error = np.abs(frame.depth[inner] - expected[inner])
    assert inner.sum() > 0.3 * inner.size
    assert error.max() < 1e-3, f"max error {error.max() * 1000:.3f} mm"


def test_off_centre_principal_point_and_unequal_focal_lengths():
    intrinsics = Intrinsics(fx=300.0, fy=280.0, cx=150.3, cy=130.7, width=320, height=240, near=0.4, far=5.0)
    normal = rotation_x(35.0) @ rotation_y(-40.0) @ np.array([0.0, 0.0, -1.0])
    point = np.array([0.1, -0.05, 2.0])
    frame = render(plane_mesh(point, normal), intrinsics=intrinsics)
    expected = analytic_plane_depth(intrinsics, point, normal)
    inner = (expected > 0.41) & (expected < 4.95)
    error = np.abs(frame.depth[inner] - expected[inner])
    assert error.max() < 1e-3, f"max error {error.max() * 1000:.3f} mm"


def test_sphere_matches_analytic_depth_inside_the_limb():
    radius, centre = 0.5, np.array([0.1, -0.05, 2.0])
    source = vtkSphereSource()
    source.SetRadius(radius)
    source.SetCenter(*centre)
    source.SetThetaResolution(256)
    source.SetPhiResolution(256)
    source.Update()  # chord error about 0.05 mm
    intrinsics = Intrinsics()
    frame = render(source.GetOutput(), intrinsics=intrinsics)
    rays = intrinsics.rays()
    b = rays @ centre
    a = (rays * rays).sum(-1)
    disc = b * b - a * (centre @ centre - radius * radius)
    hit = disc > 0
    expected = np.where(hit, (b - np.sqrt(np.where(hit, disc, 0))) / a, np.nan)
    inside = binary_erosion(hit, iterations=3)  # more than 2 px inside the limb
    assert inside.sum() > 10000
    assert np.isfinite(frame.depth[inside]).all()
    error = np.abs(frame.depth[inside] - expected[inside])
    assert error.max() < 1e-3, f"max error {error.max() * 1000:.3f} mm"
    outside = binary_erosion(~hit, iterations=3)  # more than 2 px outside the limb
    assert np.isnan(frame.depth[outside]).all()


def test_table_backprojects_onto_the_scene_surface(scenes_dir):
    from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
    from vtkmodules.vtkCommonCore import vtkDoubleArray
    from vtkmodules.vtkFiltersCore import vtkImplicitPolyDataDistance

    scene = SourceScene.from_file(scenes_dir / "table.toml")
    sensor = FilterDepthImage()
    sensor.SetInputConnection(scene.GetOutputPort())
    sensor.pose = look_at([1.6, -1.4, 1.7], [0.0, 0.0, 0.8])
    sensor.Update()
    frame = DepthFrame.from_image(sensor.GetOutput())
    points = backproject(frame.depth, frame.intrinsics, frame.world_from_camera)
    assert len(points) > 100000
    distance = vtkImplicitPolyDataDistance()
    distance.SetInput(scene.GetOutput())
    values = vtkDoubleArray()
    distance.FunctionValue(numpy_to_vtk(points[::10].copy(), deep=True), values)
    d = np.abs(vtk_to_numpy(values))
    assert np.median(d) < 1e-3, f"median {np.median(d) * 1000:.3f} mm"
    assert np.percentile(d, 95) < 5e-3


@pytest.mark.parametrize("model", ["zbuffer", "kinect"])
@pytest.mark.parametrize("z", [1.0, 2.0, 3.0])
def test_noise_standard_deviation_matches_the_model(model, z):
    noise = SensorNoise(model)
    frame = render(plane_mesh([0, 0, z], [0, 0, -1]), noise=noise, seed=11)
    valid = np.isfinite(frame.depth)
    assert valid.mean() > 0.99
    measured = frame.depth[valid].astype(np.float64).std()
    expected = float(noise.sigma(z, 0.5, 4.0))
    assert measured == pytest.approx(expected, rel=0.10)
    assert frame.depth[valid].mean() == pytest.approx(z, abs=3 * expected / np.sqrt(valid.sum()) + 1e-4)


def test_zbuffer_noise_sigma_is_about_1_6_15_mm():
    sigma = SensorNoise("zbuffer").sigma(np.array([1.0, 2.0, 3.0]), 0.5, 4.0)
    np.testing.assert_allclose(sigma, [1.0e-3, 6.0e-3, 15.0e-3], rtol=0.05)


def test_zbuffer_noise_pushed_past_far_plane_is_no_return():
    frame = render(plane_mesh([0, 0, 3.98], [0, 0, -1]), noise=SensorNoise("zbuffer", zbuffer_sigma=0.01), seed=1)
    lost = np.isnan(frame.depth).mean()
    assert 0.2 < lost < 0.8  # a real share of the noisy values cross d = 1
    assert np.nanmax(frame.depth) <= 4.0 + 1e-6


def test_noise_is_reproducible_per_frame_and_differs_between_frames():
    sensor = FilterDepthImage(noise="kinect", seed=5)
    sensor.SetInputDataObject(plane_mesh([0, 0, 2.0], [0, 0, -1]))
    sensor.pose = np.eye(4)
    images = {}
    for frame in (0, 1, 0):
        sensor.frame = frame
        sensor.Update()
        images.setdefault(frame, []).append(depth_array(sensor.GetOutput()).copy())
    first, again = images[0]
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, images[1][0])
    other_seed = render(plane_mesh([0, 0, 2.0], [0, 0, -1]), noise="kinect", seed=6)
    assert not np.array_equal(first, other_seed.depth)


def test_output_layout_and_field_data():
    frame_filter = FilterDepthImage(intrinsics=Intrinsics(width=64, height=48, fx=52.5, fy=52.5, cx=32, cy=24))
    frame_filter.SetInputDataObject(plane_mesh([0, 0, 2.0], [0, 0, -1]))
    pose = look_at([0, 0, 0], [0, 0, 2.0], up=(0, -1, 0))
    frame_filter.pose = pose
    frame_filter.frame = 7
    frame_filter.Update()
    image = frame_filter.GetOutput()
    assert image.GetExtent() == (0, 63, 0, 47, 0, 0)
    assert image.GetPointData().GetArray("depth").GetDataTypeAsString() == "float"
    frame = DepthFrame.from_image(image)
    assert frame.frame == 7
    np.testing.assert_allclose(frame.world_from_camera, pose)


def test_top_row_of_the_array_is_the_top_of_the_image():
    # A plane above the optical axis (camera y < 0 is up) closer than the one below.
    from vtkmodules.vtkFiltersCore import vtkAppendPolyData

    append = vtkAppendPolyData()
    append.AddInputData(plane_mesh([0, -5.0, 1.5], [0, 0, -1], size=10.0))  # y in [-10, 0]: upper half
    append.AddInputData(plane_mesh([0, 5.0, 3.0], [0, 0, -1], size=10.0))  # y in [0, 10]: lower half
    append.Update()
    frame = render(append.GetOutput())
    np.testing.assert_allclose(frame.depth[:200], 1.5, atol=1e-3)
    np.testing.assert_allclose(frame.depth[280:], 3.0, atol=1e-3)


def test_pose_errors():
    sensor = FilterDepthImage()
    with pytest.raises(PoseError, match="4x4"):
        sensor.pose = np.eye(3)
    skewed = np.eye(4)
    skewed[0, 1] = 0.3
    with pytest.raises(PoseError, match="not rigid"):
        sensor.pose = skewed


def test_missing_pose_is_a_clear_error():
    sensor = FilterDepthImage()
    sensor.SetInputDataObject(plane_mesh([0, 0, 2.0], [0, 0, -1]))
    with pytest.raises(ValueError, match="pose is not set"):
        sensor.Update()


def test_unknown_noise_model_is_an_error():
    with pytest.raises(ConfigError, match="unknown noise model 'gaussian'"):
        FilterDepthImage(noise="gaussian")


def test_unknown_backend_is_an_error():
    with pytest.raises(ConfigError, match="backend"):
        FilterDepthImage(backend="x11")


def test_wrong_input_type_is_a_clear_error():
    from vtkmodules.vtkCommonDataModel import vtkImageData

    sensor = FilterDepthImage()
    sensor.SetInputDataObject(vtkImageData())
    sensor.pose = np.eye(4)
    with pytest.raises(TypeError, match="vtkImageData"):
        sensor.Update()


def test_setting_the_same_pose_does_not_modify_the_filter():
    sensor = FilterDepthImage()
    sensor.pose = np.eye(4)
    before = sensor.GetMTime()
    sensor.pose = np.eye(4)
    sensor.frame = 0
    assert sensor.GetMTime() == before
    sensor.frame = 1
    assert sensor.GetMTime() > before


@pytest.mark.skipif(ctypes.util.find_library("OSMesa") is None, reason="libOSMesa not installed (apt-get install libosmesa6)")
def test_osmesa_backend_matches_egl():
    mesh = plane_mesh([0, 0, 2.0], rotation_x(40.0) @ np.array([0, 0, -1.0]))
    egl = render(mesh, backend="egl")
    osmesa = render(mesh, backend="osmesa")
    np.testing.assert_allclose(osmesa.depth, egl.depth, atol=1e-4, equal_nan=True)


def test_a_render_from_the_same_pose_of_the_same_unchanged_map_is_not_drawn_again():
    from vtkmodules.util.numpy_support import vtk_to_numpy

    from mabdi.render.depth_image import DepthRenderer
    from mabdi.stages.expected_image import render_expected

    k = Intrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=32.0, cy=24.0)
    mesh = plane_mesh([0, 0, 2.0], [0, 0, -1], size=4.0, subdivisions=4)
    renderer = DepthRenderer(face_identity=True)
    pose = np.eye(4)
    first = render_expected(renderer, mesh, k, pose).copy()
    codes = renderer.render_identity().copy()
    draws = []
    window_render = renderer.window.Render
    renderer.window.Render = lambda: (draws.append(1), window_render())
    again = render_expected(renderer, mesh, k, pose.copy())  # E at a registered pose that is the given one
    assert not draws
    np.testing.assert_array_equal(again, first)
    np.testing.assert_array_equal(renderer.render_identity(), codes)
    into = np.full(codes.shape, 7, dtype=np.uint32)  # the range renderer's buffer: the same identities, no copy made
    assert renderer.render_identity(out=into) is into
    np.testing.assert_array_equal(into, codes)
    assert len(np.unique(codes)) > 2
    # the map changed (its points moved 0.5 m nearer): drawn again, and it reads so
    points = vtk_to_numpy(mesh.GetPoints().GetData())
    points[:, 2] -= 0.5
    mesh.GetPoints().Modified()
    moved = render_expected(renderer, mesh, k, pose)
    assert len(draws) == 1
    np.testing.assert_allclose(moved, 1.5, atol=1e-3)
    # another pose: drawn again
    shifted = pose.copy()
    shifted[2, 3] = -0.5
    np.testing.assert_allclose(render_expected(renderer, mesh, k, shifted), 2.0, atol=1e-3)
    assert len(draws) == 2


def test_a_render_from_a_pose_within_the_reuse_distance_is_the_last_drawing():
    """``reuse_within_px``: a pose that moves no point of the image by more than that many pixels (a registered
    pose a hair from the given one) is served the last drawing; one beyond it, or any other pose with 0, is drawn."""
    from scipy.spatial.transform import Rotation

    from mabdi.render.depth_image import DepthRenderer, pose_shift_px
    from mabdi.stages.expected_image import render_expected

    k = Intrinsics(width=64, height=48, fx=50.0, fy=50.0, cx=32.0, cy=24.0, near=0.5)
    mesh = plane_mesh([0, 0, 2.0], rotation_x(30.0) @ np.array([0, 0, -1.0]), size=4.0, subdivisions=4)
    renderer = DepthRenderer(face_identity=True)
    pose = np.eye(4)
    first = render_expected(renderer, mesh, k, pose).copy()
    draws = []
    window_render = renderer.window.Render
    renderer.window.Render = lambda: (draws.append(1), window_render())

    def turned(pixels: float) -> np.ndarray:
        moved = np.eye(4)
        moved[:3, :3] = Rotation.from_rotvec([0.0, pixels / k.fx, 0.0]).as_matrix()
        return moved

    assert pose_shift_px(pose, turned(0.05), k) == pytest.approx(0.05)
    nudged = np.eye(4)
    nudged[0, 3] = 0.001  # 1 mm seen at the near limit (0.5 m): 0.1 px
    assert pose_shift_px(pose, nudged, k) == pytest.approx(0.1)
    render_expected(renderer, mesh, k, turned(0.05))
    assert len(draws) == 1, "reuse is off by default"
    renderer.reuse_within_px = 0.1
    np.testing.assert_array_equal(render_expected(renderer, mesh, k, turned(0.08)), render_expected(renderer, mesh, k, turned(0.05)))
    assert len(draws) == 1
    render_expected(renderer, mesh, k, turned(0.3))
    assert len(draws) == 2
    assert not np.array_equal(render_expected(renderer, mesh, k, turned(3.0)), first)
