"""A new patch keeps the faces over its novel pixels and the pixel beside them; faces wholly on the classifier's
rim, the map's surface meshed again, are dropped (:mod:`mabdi.surfaces.seam_trim`)."""

from __future__ import annotations

import numpy as np

import mabdi
from mabdi.camera import Intrinsics
from mabdi.depth import DepthFrame
from mabdi.polydata import polydata_area, triangles_polydata
from mabdi.sources.frames import FrameList
from mabdi.spherical import SphericalGeometry
from mabdi.stages.classifier import ClassifierParameters, FilterClassifier
from mabdi.stages.registration import RegistrationParameters
from mabdi.surfaces.seam_trim import NOVEL_PIXELS_ARRAY, kept_faces, trimmed_patch, trims

CAMERA = Intrinsics(fx=80.0, fy=80.0, cx=40.0, cy=30.0, width=80, height=60)


def triangle(corners_uv, z: float = 2.0) -> np.ndarray:
    """(3, 3) the triangle whose corners project onto the continuous pixel coordinates ``corners_uv`` (u, v; pixel
    (i, j) spans [i, i + 1) x [j, j + 1)), z metres ahead of the camera at the origin."""
    corners = np.asarray(corners_uv, dtype=np.float64)
    x = (corners[:, 0] - CAMERA.cx) / CAMERA.fx * z
    y = (corners[:, 1] - CAMERA.cy) / CAMERA.fy * z
    return np.column_stack([x, y, np.full(3, z)])


def triangle_at(u: int, v: int, z: float = 2.0) -> np.ndarray:
    """A small triangle inside pixel (u, v)."""
    return triangle([[u + 0.3, v + 0.4], [u + 0.7, v + 0.4], [u + 0.5, v + 0.7]], z)


def patch_of(triangles: list[np.ndarray]):
    points = np.concatenate(triangles)
    return triangles_polydata(points, np.arange(len(points)).reshape(-1, 3))


def test_a_face_stays_when_a_novel_pixel_lies_within_a_pixel_of_its_centroid():
    novel = np.zeros(CAMERA.shape, bool)
    novel[30, 40] = True
    places = [(40, 30), (41, 31), (39, 29), (42, 30), (40, 32), (37, 27)]
    faces = [triangle_at(u, v) for u, v in places]
    faces.append(triangle([[37.0, 30.0], [44.0, 30.0], [37.0, 33.0]]))  # centroid at (39.3, 31): beside it
    faces.append(triangle([[40.2, 30.2], [46.0, 30.2], [40.2, 36.0]]))  # a corner on it, centroid 2 pixels off
    patch = patch_of(faces)
    keep = kept_faces(patch, novel, CAMERA, np.eye(4))
    np.testing.assert_array_equal(keep, [True, True, True, False, False, False, True, False])
    assert kept_faces(patch, novel, CAMERA, np.eye(4), reach=2).tolist() == [True] * 5 + [False, True, True]
    trimmed = trimmed_patch(patch, novel, CAMERA, np.eye(4))
    assert trimmed.GetNumberOfCells() == 4 and trimmed.GetNumberOfPoints() == 12


def test_faces_outside_the_image_or_behind_the_camera_are_kept():
    novel = np.zeros(CAMERA.shape, bool)
    behind = triangle_at(40, 30, z=2.0) * np.array([1.0, 1.0, -1.0])
    straddling = triangle([[-3.0, 10.0], [2.0, 10.0], [-3.0, 14.0]])  # its centroid left of the image
    patch = patch_of([triangle_at(-6, 30), triangle_at(40, 70), behind, triangle_at(10, 10), straddling])
    assert kept_faces(patch, novel, CAMERA, np.eye(4)).tolist() == [True, True, True, False, True]
    whole = patch_of([triangle_at(40, 30)])
    novel[30, 40] = True
    assert trimmed_patch(whole, novel, CAMERA, np.eye(4)) is whole  # nothing to drop: the same patch


def test_only_a_cameras_rim_wider_than_the_reach_is_trimmed():
    assert trims(CAMERA, 3) and trims(CAMERA, 2)
    assert not trims(CAMERA, 1) and not trims(CAMERA, 0)
    lidar = SphericalGeometry(beams=16, columns=64, fov_up=15.0, fov_down=-15.0)
    assert not trims(lidar, 3)


def panned_wall(frames: int, step_px: int = 6) -> FrameList:
    """A wall 2 m ahead, the camera moving sideways ``step_px`` pixels' worth of wall a frame, with Kinect
    noise: each frame after the first sees a strip of new wall beside the map's."""
    rng = np.random.default_rng(3)
    sigma = float(mabdi.SensorNoise("kinect").sigma(np.array([2.0]), CAMERA.near, CAMERA.far)[0])
    shift = step_px * 2.0 / CAMERA.fx
    out = []
    for i in range(frames):
        pose = np.eye(4)
        pose[0, 3] = i * shift
        depth = (2.0 + rng.normal(0.0, sigma, CAMERA.shape)).astype(np.float32)
        out.append(DepthFrame(depth, CAMERA, pose, i, i / 30))
    return FrameList(out)


def test_a_panned_wall_is_mapped_as_one_layer_without_cracks():
    """The quad-tree on noisy depth meshes each new strip with a rim of a 3 x 3 block over the map (so that its
    edge reaches the seam); the faces wholly on the rim are trimmed, so the map is about one layer of wall, and
    drawn from the last pose it has no crack along the seams."""
    frames = panned_wall(8)
    loop = mabdi.MabdiLoop(frames, surface="quadtree", noise="kinect", registration=RegistrationParameters(enabled=False))
    assert loop.classifier_parameters.rim == 3
    added = []
    for i in range(len(frames)):
        record = loop.step(i)
        added.append(record.cells_added)
        if i:
            assert loop.last_frame.classified.novel_pixels is not None
    mesh = loop.mesh()
    # the wall is flat at 2 m: one layer's area is the map's extent across the image plane
    bounds = mesh.GetBounds()
    extent = (bounds[1] - bounds[0]) * (bounds[3] - bounds[2])
    area = polydata_area(mesh)
    # each strip is 6 pixels wide; its faces on or beside a novel pixel reach about a pixel over the map (the
    # rim's faces all kept: 3 pixels, 1.13 times the extent)
    assert 0.95 * extent < area < 1.08 * extent, (area, extent, added)
    # no crack along the seams: the map drawn from the last pose covers its view but for the border's block
    expected = loop.expected.render(loop.world.map, loop.last_frame.measured).depth
    assert np.isfinite(expected[3:-3, 3:-3]).mean() > 0.995


def test_the_classifier_image_marks_its_novel_pixels_only_where_the_patch_is_trimmed():
    from mabdi.depth import depth_image
    from mabdi.sensor_noise import SensorNoise

    measured = np.full(CAMERA.shape, 2.0, np.float32)
    expected = measured.copy()
    expected[:, 40:] = np.nan  # the right half is new
    for rim, marked in ((3, True), (1, False)):
        classifier = FilterClassifier(ClassifierParameters(rim=rim))
        classifier.SetInputDataObject(0, depth_image(measured, CAMERA, np.eye(4), frame=1, noise=SensorNoise("kinect")))
        classifier.SetInputDataObject(1, depth_image(expected, CAMERA, np.eye(4), frame=1))
        classifier.Update()
        array = classifier.GetOutput().GetPointData().GetArray(NOVEL_PIXELS_ARRAY)
        assert (array is not None) == marked
        if marked:
            novel = np.asarray(array).reshape(CAMERA.shape).astype(bool)
            assert novel[:, 40:].all() and not novel[:, :40].any()
