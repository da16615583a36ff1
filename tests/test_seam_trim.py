"""A new patch keeps the faces within two pixels of its novel pixels; the other faces of the classifier's rim, the
map's surface meshed again, are dropped, and so are the faces the map already holds within 1 cm
(:mod:`mabdi.surfaces.seam_trim`)."""

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
from mabdi.frame_values import Expected
from mabdi.surfaces.seam_trim import NOVEL_PIXELS_ARRAY, faces_on_map, kept_faces, trimmed_patch, trims

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


def test_a_face_stays_when_a_novel_pixel_lies_within_two_pixels_of_its_centroid():
    novel = np.zeros(CAMERA.shape, bool)
    novel[30, 40] = True
    places = [(40, 30), (41, 31), (38, 28), (42, 32), (43, 30), (40, 27), (37, 33)]
    faces = [triangle_at(u, v) for u, v in places]
    faces.append(triangle([[36.0, 30.0], [44.0, 30.0], [36.0, 33.0]]))  # centroid at (38.7, 31): beside it
    faces.append(triangle([[40.2, 30.2], [49.0, 30.2], [40.2, 39.0]]))  # a corner on it, centroid 3 pixels off
    patch = patch_of(faces)
    keep = kept_faces(patch, novel, CAMERA, np.eye(4))
    np.testing.assert_array_equal(keep, [True, True, True, True, False, False, False, True, False])
    assert kept_faces(patch, novel, CAMERA, np.eye(4), reach=1).tolist() == [True, True] + [False] * 7
    trimmed = trimmed_patch(patch, novel, CAMERA, np.eye(4))
    assert trimmed.GetNumberOfCells() == 5 and trimmed.GetNumberOfPoints() == 15


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


def map_of_panned_wall(step_px: int):
    frames = panned_wall(8, step_px)
    loop = mabdi.MabdiLoop(
        frames, surface="quadtree", noise="kinect", registration=RegistrationParameters(enabled=False)
    )
    assert loop.classifier_parameters.rim == 3
    for i in range(len(frames)):
        loop.step(i)
        assert loop.last_frame.classified.novel_pixels is not None
    return loop


def interior_holes(loop, yaw_deg: float) -> int:
    """Pixels the map, drawn from a camera turned ``yaw_deg`` about the wall's middle, leaves uncovered inside
    its own outline (cracks along the seams)."""
    from scipy import ndimage

    from mabdi.camera import look_at
    from mabdi.frame_values import Measured

    camera = Intrinsics(fx=320.0, fy=320.0, cx=160.0, cy=120.0, width=320, height=240)
    middle = np.array([0.8, 0.0, 2.0])
    eye = middle + 2.0 * np.array([np.sin(np.radians(yaw_deg)), 0.0, -np.cos(np.radians(yaw_deg))])
    pose = look_at(eye, middle, up=(0, -1, 0))
    view = Measured(np.zeros(camera.shape, np.float32), camera, pose, mabdi.SensorNoise(), 0)
    covered = np.isfinite(loop.expected.render(loop.world.map, view).depth)
    return int(np.count_nonzero(ndimage.binary_fill_holes(covered) & ~covered))


def test_a_panned_wall_keeps_fewer_rim_faces_and_no_cracks(monkeypatch):
    """The quad-tree on noisy depth meshes each new strip with a rim of a 3 x 3 block over the map (so that its
    edge reaches the seam); faces more than two pixels from the strip are trimmed: fewer faces and less area for
    the same wall, and seen from oblique views the map has no crack along its seams. (The faces on the map are
    kept here: they are the next test's.)"""
    monkeypatch.setattr("mabdi.loop.loop.without_faces_on_map", lambda patch, *args, **kwargs: patch)
    trimmed = map_of_panned_wall(11)
    monkeypatch.setattr("mabdi.loop.loop.trimmed_patch", lambda patch, *args, **kwargs: patch)
    whole = map_of_panned_wall(11)
    cells = trimmed.mesh().GetNumberOfCells(), whole.mesh().GetNumberOfCells()
    assert cells[0] < 0.95 * cells[1], cells
    assert polydata_area(trimmed.mesh()) < polydata_area(whole.mesh()) - 0.05  # m^2 of wall meshed twice
    for yaw in (-40.0, -20.0, 0.0, 20.0, 40.0):
        assert interior_holes(trimmed, yaw) == 0, yaw


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


def test_a_surface_that_keeps_state_hands_out_its_patches_whole(monkeypatch):
    """Voxel planes replace their own patches by key: with a rim wider than a pixel set by hand, the loop does not
    trim what they hand out."""

    def refuse(*args, **kwargs):
        raise AssertionError("a stateful surface's patch was trimmed")

    monkeypatch.setattr("mabdi.loop.loop.trimmed_patch", refuse)
    frames = panned_wall(3, 11)
    loop = mabdi.MabdiLoop(
        frames, surface="voxel_planes", noise="kinect", classifier=ClassifierParameters(rim=3),
        registration=RegistrationParameters(enabled=False),
    )  # fmt: skip
    for i in range(len(frames)):
        loop.step(i)
    assert loop.last_frame.classified.novel_pixels is not None and loop.mesh().GetNumberOfCells() > 0



def plane_map_expected(hole=None) -> tuple[Expected, object]:
    """E of a map that is the plane z = 2 m (two triangles wider than the view, codes 1 and 2, split along the
    image's diagonal) seen by CAMERA at the origin, with no face drawn in ``hole`` (a (rows, cols) slice pair);
    and the map's face_corners_of."""
    far = 400.0  # pixels from the image's centre
    low_u, high_u, low_v, high_v = CAMERA.cx - far, CAMERA.cx + far, CAMERA.cy - far, CAMERA.cy + far
    corners = {
        1: triangle([[low_u, low_v], [high_u, low_v], [low_u, high_v]]),
        2: triangle([[high_u, low_v], [high_u, high_v], [low_u, high_v]]),
    }
    v, u = np.mgrid[0 : CAMERA.height, 0 : CAMERA.width]
    codes = np.where((u + 0.5 - CAMERA.cx) + (v + 0.5 - CAMERA.cy) < 0, 1, 2).astype(np.int32)
    if hole is not None:
        codes[hole] = 0
    depth = np.where(codes > 0, 2.0, np.nan).astype(np.float32)

    def face_corners_of(asked, table):
        assert table == "table"
        return np.stack([corners[int(c)] for c in np.asarray(asked)])

    return Expected(depth, CAMERA, np.eye(4), 0, face_ids=codes, table="table"), face_corners_of


def test_a_new_face_on_the_map_within_a_centimetre_is_dropped_and_others_stay():
    """Faces whose centroid and corners lie within 1 cm of the map along their normal go, whichever of the map's
    faces is under them (the two straddle the diagonal); a face 3 cm in front stays, and so does a face with a
    corner over a hole of the map (E shows no face there) or outside the image."""
    expected, corners_of = plane_map_expected(hole=(slice(40, 50), slice(60, 70)))
    big = [[10, 10], [22, 10], [10, 22]]  # a dozen pixels across
    patch = patch_of(
        [
            triangle(big, 2.005),  # on the map, 5 mm behind it
            triangle([[36, 26], [44, 26], [40, 34]], 1.995),  # on the map, across the faces' shared diagonal
            triangle(big, 2.03),  # 3 cm in front: a new surface
            triangle([[50, 36], [65, 45], [50, 45]], 2.0),  # a corner over the hole, 3 pixels inside it
            triangle([[75, 5], [85, 5], [75, 12]], 2.0),  # a corner outside the image
        ]
    )
    assert faces_on_map(patch, expected, corners_of).tolist() == [True, True, False, False, False]
    assert faces_on_map(patch, expected, corners_of, reach=0.004).tolist() == [False, False, False, False, False]


def test_a_face_over_a_crack_of_the_map_stays_though_its_corners_lie_on_the_map():
    """A crack one pixel wide through a face's pixels (E shows no face there) keeps the face, which covers it,
    though its centroid and corners all lie on the map's faces; the same face with no crack under it goes."""
    face = [[10, 10], [22, 10], [10, 22]]  # the centroid at (14, 14); no tested point in column 12
    cracked, corners_of = plane_map_expected(hole=(slice(0, CAMERA.height), slice(12, 13)))
    whole, _ = plane_map_expected()
    patch = patch_of([triangle(face, 2.005)])
    assert faces_on_map(patch, cracked, corners_of).tolist() == [False]
    assert faces_on_map(patch, whole, corners_of).tolist() == [True]


def test_no_face_is_dropped_where_e_has_no_face_identity():
    expected, corners_of = plane_map_expected()
    patch = patch_of([triangle([[10, 10], [22, 10], [10, 22]], 2.0)])
    plain = Expected(expected.depth, CAMERA, np.eye(4), 0)
    assert faces_on_map(patch, plain, corners_of).tolist() == [False]
    assert faces_on_map(patch, expected, corners_of).tolist() == [True]


def test_a_panned_wall_drops_the_faces_the_map_holds_and_keeps_no_cracks(monkeypatch):
    """A new strip's faces that lie on the map's wall (the rim within two pixels of the strip) are dropped: fewer
    faces than with the trim alone, and from oblique views the map still has no crack along its seams."""
    dropped = map_of_panned_wall(11)
    monkeypatch.setattr("mabdi.loop.loop.without_faces_on_map", lambda patch, *args, **kwargs: patch)
    kept = map_of_panned_wall(11)
    cells = dropped.mesh().GetNumberOfCells(), kept.mesh().GetNumberOfCells()
    assert cells[0] < 0.95 * cells[1], cells
    for yaw in (-40.0, -20.0, 0.0, 20.0, 40.0):
        assert interior_holes(dropped, yaw) == 0, yaw


def test_the_box_kernel_agrees_with_array_slices():
    from mabdi.surfaces.seam_trim_kernels import boxes_hold_kernel

    rng = np.random.default_rng(5)
    mask = rng.random((30, 40)) < 0.02
    u0, v0 = rng.integers(0, 40, 500), rng.integers(0, 30, 500)
    u1, v1 = np.minimum(u0 + rng.integers(-1, 6, 500), 39), np.minimum(v0 + rng.integers(-1, 6, 500), 29)
    boxes = np.stack([u0, u1, v0, v1], axis=1)
    expected = [bool(mask[b[2] : b[3] + 1, b[0] : b[1] + 1].any()) for b in boxes]
    assert boxes_hold_kernel(mask, boxes).tolist() == expected
    assert any(expected) and not all(expected)
