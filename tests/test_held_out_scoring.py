"""Held-out scoring (mabdi.evaluate.held_out): known maps against depth images with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from mabdi.camera import Intrinsics, look_at
from mabdi.depth import DepthFrame
from mabdi.evaluate.held_out import (
    HeldOutTally,
    MapRaycaster,
    corrected_poses,
    held_out_split,
    map_depth,
    pose_differences,
    score_depth,
    score_map,
)
from mabdi.polydata import triangles_polydata
from mabdi.sources.frames import FrameList, FrameSubset

#: A small camera whose principal point is the image's centre (mabdi's pixel centres at u + 0.5).
CAMERA = Intrinsics(fx=60.0, fy=60.0, cx=40.0, cy=30.0, width=80, height=60, near=0.3, far=6.0)


def quad(corners) -> object:
    """Two triangles over the four ``corners`` (in order around the quad)."""
    return triangles_polydata(np.asarray(corners, dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]]))


def plane_depth(normal, offset, intrinsics=CAMERA) -> np.ndarray:
    """The z-depth image of the plane {p: normal . p = offset} (camera frame), analytically."""
    u = (np.arange(intrinsics.width) + 0.5 - intrinsics.cx) / intrinsics.fx
    v = (np.arange(intrinsics.height) + 0.5 - intrinsics.cy) / intrinsics.fy
    uu, vv = np.meshgrid(u, v)
    return offset / (normal[0] * uu + normal[1] * vv + normal[2])


def camera_plane_mesh(pose, normal, offset, half=5.0, x_from=None):
    """A large quad on the camera-frame plane normal . p = offset, put in the world by ``pose``; ``x_from``:
    only the part with camera x >= x_from."""
    normal = np.asarray(normal, dtype=np.float64)
    x0 = -half if x_from is None else x_from
    corners = []
    for x, y in ((x0, -half), (half, -half), (half, half), (x0, half)):
        z = (offset - normal[0] * x - normal[1] * y) / normal[2]
        corners.append((x, y, z))
    corners = np.array(corners)
    world = corners @ pose[:3, :3].T + pose[:3, 3]
    return quad(world)


POSE = look_at((0.4, -1.5, 0.8), (0.1, 0.3, 0.9))


def test_tilted_plane_at_a_pose_scores_perfectly():
    normal = np.array([0.2, -0.3, 1.0])
    truth = plane_depth(normal, 2.0)
    mesh = camera_plane_mesh(POSE, normal, 2.0)
    predicted = map_depth(mesh, CAMERA, POSE)
    np.testing.assert_allclose(predicted, truth, rtol=0, atol=1e-9)
    score = score_depth(truth.astype(np.float32), predicted)
    assert score.valid_pixels == CAMERA.width * CAMERA.height
    assert score.within[0.02] == 1.0 and score.within[0.05] == 1.0
    assert score.coverage == 1.0
    assert score.median_abs_error_mm < 1e-3


def test_plane_shifted_three_centimetres():
    measured = plane_depth(np.array([0.0, 0.0, 1.0]), 2.0)
    mesh = camera_plane_mesh(POSE, [0.0, 0.0, 1.0], 2.03)  # 3 cm behind what was measured
    score = score_depth(measured, map_depth(mesh, CAMERA, POSE))
    assert score.within[0.02] == 0.0
    assert score.within[0.05] == 1.0
    assert score.coverage == 1.0
    assert score.median_abs_error_mm == pytest.approx(30.0, abs=1e-4)
    assert score.as_dict()["within_2cm"] == 0.0 and score.as_dict()["within_5cm"] == 1.0


def test_only_valid_measured_pixels_count():
    measured = plane_depth(np.array([0.0, 0.0, 1.0]), 2.0)
    measured[:, :40] = np.nan  # the left half has no returns
    measured[50:, 60:] = 0.0  # a block of zeros (no return either)
    valid = 80 * 60 - 40 * 60 - 10 * 20
    # the map has nothing over the left half: no pixel with a return is left uncovered
    mesh = camera_plane_mesh(POSE, [0.0, 0.0, 1.0], 2.0, x_from=0.0)
    predicted = map_depth(mesh, CAMERA, POSE)
    assert np.isnan(predicted[:, :40]).all() and np.isfinite(predicted[:, 40:]).all()
    score = score_depth(measured, predicted)
    assert score.valid_pixels == valid
    assert score.coverage == 1.0
    assert score.within[0.02] == 1.0


def test_map_missing_half_the_view():
    measured = plane_depth(np.array([0.0, 0.0, 1.0]), 1.5)
    mesh = camera_plane_mesh(POSE, [0.0, 0.0, 1.0], 1.5, x_from=0.0)
    score = score_depth(measured, map_depth(mesh, CAMERA, POSE))
    assert score.coverage == pytest.approx(0.5)
    assert score.within[0.02] == pytest.approx(0.5)
    assert score.median_abs_error_mm < 1e-3


def test_nearest_surface_wins_and_behind_the_camera_is_not_seen():
    near_plane = camera_plane_mesh(POSE, [0.0, 0.0, 1.0], 1.0)
    far_plane = camera_plane_mesh(POSE, [0.0, 0.0, 1.0], 3.0)
    behind = camera_plane_mesh(POSE, [0.0, 0.0, 1.0], -1.0)
    from vtkmodules.vtkFiltersCore import vtkAppendPolyData

    append = vtkAppendPolyData()
    for mesh in (far_plane, near_plane, behind):
        append.AddInputData(mesh)
    append.Update()
    depth = MapRaycaster(append.GetOutput()).depth(CAMERA, POSE)
    np.testing.assert_allclose(depth, 1.0, atol=1e-9)
    assert np.isnan(map_depth(behind, CAMERA, POSE)).all()


def test_pooled_scores_weigh_pixels_not_frames():
    right = plane_depth(np.array([0.0, 0.0, 1.0]), 2.0)
    shifted = camera_plane_mesh(np.eye(4), [0.0, 0.0, 1.0], 2.03)
    mesh = camera_plane_mesh(np.eye(4), [0.0, 0.0, 1.0], 2.0)
    sparse = right.copy()
    sparse[:, 20:] = np.nan  # a frame with a quarter of the pixels
    tally = HeldOutTally()
    tally.add(right, map_depth(mesh, CAMERA, np.eye(4)))  # 4800 pixels, all within 2 cm
    tally.add(sparse, map_depth(shifted, CAMERA, np.eye(4)))  # 1200 pixels, 3 cm off
    score = tally.score()
    assert score.frames == 2 and score.valid_pixels == 6000
    assert score.within[0.02] == pytest.approx(0.8)
    assert score.within[0.05] == 1.0
    assert score.median_abs_error_mm == pytest.approx(0.05, abs=0.051)  # the middle pixel is an exact one

    frames = [DepthFrame(right.astype(np.float32), CAMERA, np.eye(4), 0), DepthFrame(sparse.astype(np.float32), CAMERA, np.eye(4), 1)]
    pooled, per_frame = score_map(shifted, frames)
    assert pooled.within[0.02] == 0.0 and pooled.within[0.05] == 1.0
    assert pooled.median_abs_error_mm == pytest.approx(30.0, abs=0.06)
    assert [s.valid_pixels for s in per_frame] == [4800, 1200]


def test_empty_map_covers_nothing():
    from vtkmodules.vtkCommonDataModel import vtkPolyData

    measured = plane_depth(np.array([0.0, 0.0, 1.0]), 2.0)
    score = score_depth(measured, map_depth(vtkPolyData(), CAMERA, POSE))
    assert score.coverage == 0.0 and score.within[0.05] == 0.0
    assert np.isnan(score.median_abs_error_mm)


def test_held_out_split():
    integrated, held = held_out_split(25, 10)
    assert held.tolist() == [9, 19]
    assert len(integrated) == 23 and integrated[0] == 0 and 9 not in integrated
    with pytest.raises(ValueError):
        held_out_split(10, 1)


def test_frame_subset_renumbers_frames():
    depth = np.full((CAMERA.height, CAMERA.width), 2.0, dtype=np.float32)
    poses = [np.eye(4) for _ in range(5)]
    for i, pose in enumerate(poses):
        pose[0, 3] = i
    source = FrameList([DepthFrame(depth, CAMERA, pose, i, float(i)) for i, pose in enumerate(poses)])
    subset = FrameSubset(source, [0, 2, 4])
    assert len(subset) == 3
    frame = subset.read(1)
    assert frame.frame == 1 and frame.world_from_camera[0, 3] == 2.0 and frame.timestamp == 2.0
    assert subset.poses[:, 0, 3].tolist() == [0.0, 2.0, 4.0]
    assert subset.timestamps.tolist() == [0.0, 2.0, 4.0]


def test_pose_differences():
    angle = np.radians(10.0)
    turn = np.eye(4)
    turn[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    turn[:3, 3] = [0.03, 0.04, 0.0]
    reference = np.stack([POSE, POSE])
    moved = np.stack([POSE, POSE @ turn])
    d = pose_differences(reference, moved)
    assert d["frames"] == 2
    assert d["translation_mm_max"] == pytest.approx(50.0)
    assert d["rotation_deg_max"] == pytest.approx(10.0)
    assert d["translation_mm_median"] == pytest.approx(25.0)
    assert d["rotation_deg_median"] == pytest.approx(5.0)


def test_corrected_poses_follow_the_frames_around():
    from scipy.spatial.transform import Rotation

    given = np.stack([look_at((0.1 * i, -1.5, 0.8), (0.1 * i, 0.3, 0.9)) for i in range(6)])
    step = np.eye(4)
    step[:3, :3] = Rotation.from_euler("z", 4.0, degrees=True).as_matrix()
    step[:3, 3] = [0.02, 0.0, -0.01]
    meshed_at = np.array([0, 2, 3, 5])
    # the same correction (in the camera's frame) on every meshed frame: the skipped ones get it too
    out = corrected_poses(given, meshed_at, given[meshed_at] @ step, [1, 4])
    np.testing.assert_allclose(out, given[[1, 4]] @ step, atol=1e-12)
    # from no correction at frame 0 to 4 degrees and (2, 0, -1) cm at frame 2: half of it at frame 1
    meshed = given[meshed_at].copy()
    meshed[1] = given[2] @ step
    half = corrected_poses(given, meshed_at, meshed, [1])[0]
    d = pose_differences(given[[1]], half[None])
    assert d["rotation_deg_max"] == pytest.approx(2.0)
    assert d["translation_mm_max"] == pytest.approx(0.5 * np.hypot(20.0, 10.0))
