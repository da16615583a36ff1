"""Pose files as real tools write them: rotations to 6 significant digits, or a float32 tracker's drift from
orthonormal, are read as the nearest rotation and counted once; a matrix that is no rigid motion is still named."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mabdi.camera import RIGID_TOLERANCE, Intrinsics, PoseRepairs, pose_from_file
from mabdi.depth import DepthFrame
from mabdi.errors import PoseError, PoseFileWarning
from mabdi.simulate.path import CAMERA_FROM_LIDAR
from mabdi.sources.frames import FrameList
from mabdi.sources.kitti import write_kitti
from mabdi.sources.redwood import write_redwood
from mabdi.sources.replica import write_replica
from mabdi.sources.scannet import write_scannet
from mabdi.sources.sequences import SequenceError, open_sequence
from mabdi.sources.threedmatch import write_3dmatch
from mabdi.spherical import SphericalGeometry

#: Each image layout's writer and the glob of its pose files.
LAYOUTS = {
    "3dmatch": (write_3dmatch, "frame-*.pose.txt"),
    "redwood": (write_redwood, "trajectory.log"),
    "scannet": (write_scannet, "pose/*.txt"),
    "replica": (write_replica, "traj.txt"),
}
NUMBER = re.compile(r"-?\d+\.\d+(?:[eE][-+]?\d+)?")


def _poses(frames: int) -> list[np.ndarray]:
    """Camera poses with rotations about every axis (no entry 0 or 1), so rounding reaches every entry."""
    poses = []
    for i in range(frames):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_euler("xyz", [0.31 + 0.05 * i, -0.27 + 0.03 * i, 0.93 - 0.07 * i]).as_matrix()
        pose[:3, 3] = [0.4 + 0.1 * i, -0.2, 1.3]
        poses.append(pose)
    return poses


def _camera_frames(frames: int = 4) -> FrameList:
    intrinsics = Intrinsics(fx=40.0, fy=40.0, cx=16.0, cy=12.0, width=32, height=24)
    depth = np.full((24, 32), 1.5, dtype=np.float32)
    return FrameList([DepthFrame(depth, intrinsics, pose, i) for i, pose in enumerate(_poses(frames))], "planes")


def _rewrite_numbers(files, digits: int) -> None:
    """Every decimal number in ``files`` written again with ``digits`` significant digits, as many tools do."""
    for path in files:
        text = path.read_text()
        path.write_text(NUMBER.sub(lambda m: f"{float(m.group()):.{digits}g}", text))


def _orthonormality(rotation) -> float:
    return float(np.abs(rotation.T @ rotation - np.eye(3)).max())


def test_a_rotation_to_six_digits_is_read_as_the_nearest_rotation():
    pose = _poses(1)[0]
    written = np.array([[float(f"{v:.6g}") for v in row] for row in pose])
    assert _orthonormality(written[:3, :3]) > RIGID_TOLERANCE  # what a strict check refuses
    rigid, error = pose_from_file(written, "poses.txt:3")
    assert error == pytest.approx(_orthonormality(written[:3, :3]))
    assert _orthonormality(rigid[:3, :3]) < 1e-12 and np.linalg.det(rigid[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_allclose(rigid, pose, atol=2e-6)  # back to the rotation that was written, to its digits
    np.testing.assert_array_equal(rigid[:3, 3], written[:3, 3])


@pytest.mark.parametrize(
    ("matrix", "message"),
    [
        (np.diag([1.05, 1.0, 1.0, 1.0]), r"poses.txt:7 is not rigid: rotation block is not orthonormal \(max \|R\^T R - I\| = 0.10"),
        (np.diag([1.0, -1.0, 1.0, 1.0]), r"poses.txt:7 is not rigid: rotation block is a reflection"),
        (np.vstack([np.eye(4)[:3], [0.0, 0.0, 0.5, 1.0]]), r"poses.txt:7 last row must be \(0, 0, 0, 1\)"),
    ],
)
def test_a_matrix_that_is_no_rigid_motion_is_still_refused(matrix, message):
    with pytest.raises(PoseError, match=message):
        pose_from_file(matrix, "poses.txt:7")


def test_repairs_count_what_they_changed():
    repairs = PoseRepairs()
    exact = _poses(1)[0]
    drifted = exact.copy()
    drifted[:3, :3] += 1e-4 * np.array([[1, -2, 0.5], [0.3, 1, -1], [2, 0, -0.7]])  # a float32 tracker's drift
    repairs.read(exact)
    repairs.read(drifted)
    assert (repairs.poses, repairs.repaired) == (2, 1)
    assert repairs.worst_error == pytest.approx(_orthonormality(drifted[:3, :3]))
    assert 0 < repairs.worst_shift < 5e-4  # metres, for a point 1 m away
    assert "1 of 2 poses" in repairs.note("seq") and PoseRepairs().note("seq") is None


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_every_image_layout_reads_poses_written_to_six_digits(tmp_path, layout):
    writer, pattern = LAYOUTS[layout]
    frames = _camera_frames()
    folder = writer(frames, tmp_path / layout)
    _rewrite_numbers(sorted(folder.glob(pattern)), 6)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        source = open_sequence(folder)
    notes = [w for w in caught if issubclass(w.category, PoseFileWarning)]
    assert len(notes) == 1 and re.search(r"\d of 4 poses have rotation blocks up to", str(notes[0].message))
    for i in range(len(frames)):
        got = source.read(i).world_from_camera
        assert _orthonormality(got[:3, :3]) < 1e-12
        np.testing.assert_allclose(got, frames.read(i).world_from_camera, atol=2e-5)


def test_exact_poses_say_nothing(tmp_path):
    folder = write_3dmatch(_camera_frames(), tmp_path / "exact")
    with warnings.catch_warnings():
        warnings.simplefilter("error", PoseFileWarning)
        assert len(open_sequence(folder)) == 4


def test_a_scaled_pose_in_a_file_is_named_with_its_file(tmp_path):
    folder = write_3dmatch(_camera_frames(), tmp_path / "scaled")
    (folder / "frame-000002.pose.txt").write_text("1.01 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(SequenceError, match=r"frame-000002\.pose\.txt.*not orthonormal"):
        open_sequence(folder)


def test_kitti_poses_at_a_millionth_from_orthonormal_are_read(tmp_path):
    geometry = SphericalGeometry(beams=8, columns=32, fov_up=10.0, fov_down=-20.0, range_min=0.5, range_max=50.0)
    depth = np.full(geometry.shape, 4.0, dtype=np.float32)
    frames = FrameList(
        [DepthFrame(depth, geometry, pose @ CAMERA_FROM_LIDAR, i, 0.1 * i) for i, pose in enumerate(_poses(3))], "scans"
    )
    folder = write_kitti(frames, tmp_path / "kitti")
    _rewrite_numbers([folder / "poses.txt"], 6)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        source = open_sequence(folder)
    assert sum(issubclass(w.category, PoseFileWarning) for w in caught) == 1
    for i in range(3):
        assert _orthonormality(source.read(i).world_from_camera[:3, :3]) < 1e-12
        np.testing.assert_allclose(source.poses[i], frames.poses[i], atol=2e-5)
