"""Folders of depth images beside one pose file, as capture apps and SLAM tools export them: read back the frames
they were written from."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from mabdi.camera import quaternions_from_rotations
from mabdi.errors import PoseFileWarning
from mabdi.sources.depth_folder import DepthFolderSequence
from mabdi.sources.sequence_files import write_colour_png
from mabdi.sources.sequences import SequenceError, open_sequence, sequence_format
from mabdi.sources.tum import write_depth_png
from tests.test_sequences import INTRINSICS, _frames


def _camera_matrix(path):
    """The test camera as a 3x3 K with integer pixel centres (OpenCV's), as the exports write it."""
    k = np.array([[INTRINSICS.fx, 0, INTRINSICS.cx - 0.5], [0, INTRINSICS.fy, INTRINSICS.cy - 0.5], [0, 0, 1]])
    path.write_text("\n".join(" ".join(f"{v:.6f}" for v in row) for row in k) + "\n")


def _folder(path, frames, names, pose_lines, colour=False):
    (path / "depth").mkdir(parents=True)
    for frame, name in zip(frames, names, strict=True):
        write_depth_png(path / "depth" / f"{name}.png", frame.depth, 1000.0)
        if colour:
            (path / "rgb").mkdir(exist_ok=True)
            write_colour_png(path / "rgb" / f"{name}.png", np.full((48, 64, 3), frame.frame * 40, dtype=np.uint8))
    (path / "poses.txt").write_text("\n".join(pose_lines) + "\n")
    _camera_matrix(path / "intrinsics.txt")
    return path


def _check(read, frames):
    assert read.intrinsics.fx == pytest.approx(INTRINSICS.fx) and read.intrinsics.cy == pytest.approx(INTRINSICS.cy)
    assert (read.intrinsics.width, read.intrinsics.height) == (64, 48)
    for index, frame in enumerate(frames):
        got = read.read(index)
        np.testing.assert_allclose(got.world_from_camera, frame.world_from_camera, atol=2e-6)
        both = np.isfinite(got.depth) & np.isfinite(frame.depth)
        assert both.sum() > 0.95 * np.isfinite(frame.depth).sum()
        assert np.isnan(got.depth[5:9, 10:20]).all()  # no return stays no return
        np.testing.assert_allclose(got.depth[both], frame.depth[both], atol=0.0005 + 1e-6)  # millimetres


def test_depth_images_beside_a_kitti_style_pose_file(tmp_path):
    frames = _frames()
    lines = [" ".join(f"{v:.6f}" for v in f.world_from_camera[:3].ravel()) for f in frames]  # 6 digits
    folder = _folder(tmp_path / "export", frames, [f"frame_{i}" for i in (8, 9, 10, 11, 12)], lines, colour=True)
    assert sequence_format(folder) == "depth_folder"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read = open_sequence(folder)
    assert isinstance(read, DepthFolderSequence) and len(read) == 5
    assert [f.name for f in read.files] == [f"frame_{i}.png" for i in (8, 9, 10, 11, 12)]  # 10 after 9
    _check(read, frames)
    assert any(issubclass(w.category, PoseFileWarning) for w in caught)  # 6-digit rotations made rigid, said
    assert read.read(2).colour[0, 0, 0] == 80  # frame_10's colour, matched by its number


def test_a_trajectory_on_its_own_clock_is_interpolated_at_the_images_times(tmp_path):
    # The images are named by their times; the poses, 100 Hz TUM lines, cover all but the first image.
    frames = _frames()
    times = np.array([0.0, 0.05, 0.1, 0.15, 0.2]) + 1_700_000_000.0
    start = times[1] - 0.004
    pose_times = np.arange(start, times[-1] + 0.01, 0.01)
    positions = [f.world_from_camera[:3, 3] for f in frames]
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    rotation = quaternions_from_rotations(frames[0].world_from_camera[None, :3, :3])[0]
    velocity = (positions[1] - positions[0]) / 0.05  # the frames' positions lie on a line, 0.05 s apart
    for t in pose_times:  # the position moves at that velocity; one rotation
        x = positions[0] + velocity * (t - times[0])
        lines.append(" ".join(f"{v:.9f}" for v in [t, *x, *rotation]))
    folder = _folder(tmp_path / "export", frames, [f"{t:.3f}" for t in times], lines)
    read = open_sequence(folder)
    assert len(read) == 4 and "1 outside the poses' times skipped" in read.description
    np.testing.assert_allclose(read.timestamps, times[1:])
    for index in range(4):
        np.testing.assert_allclose(read.poses[index, :3, 3], positions[index + 1], atol=1e-6)


def test_a_folder_without_a_camera_says_how_to_give_one(tmp_path):
    frames = _frames()
    lines = [" ".join(f"{v:.9f}" for v in f.world_from_camera[:3].ravel()) for f in frames]
    folder = _folder(tmp_path / "export", frames, [str(i) for i in range(5)], lines)
    (folder / "intrinsics.txt").unlink()
    with pytest.raises(SequenceError, match=r"no intrinsics: pass camera= \(--camera"):
        open_sequence(folder)
    read = open_sequence(folder, camera="60.5,58.25,31.75,24.5,64,48")
    _check(read, frames)


def test_a_missing_colour_image_is_named(tmp_path):
    frames = _frames()
    lines = [" ".join(f"{v:.9f}" for v in f.world_from_camera[:3].ravel()) for f in frames]
    folder = _folder(tmp_path / "export", frames, [str(i) for i in range(5)], lines, colour=True)
    (folder / "rgb" / "3.png").unlink()
    with pytest.raises(SequenceError, match=r"rgb: no colour image for depth image 3.png"):
        open_sequence(folder)


@pytest.mark.parametrize("kind", ["metres", "millimetres"])
def test_depth_arrays_read_as_metres_or_units(tmp_path, kind):
    # NumPy arrays a frame: float metres (0, NaN, inf no return), or integer millimetres as a PNG's
    frames = _frames()
    folder = tmp_path / "export"
    (folder / "depth").mkdir(parents=True)
    for frame in frames:
        depth = frame.depth.astype(np.float64)
        if kind == "metres":
            depth[0, 2], depth[0, 3] = 0.0, np.inf
            np.save(folder / "depth" / f"{frame.frame:04d}.npy", depth)
        else:
            np.save(folder / "depth" / f"{frame.frame:04d}.npy", np.nan_to_num(np.rint(depth * 1000)).astype(np.uint16))
    (folder / "traj.txt").write_text("\n".join(" ".join(f"{v:.9f}" for v in f.world_from_camera.ravel()) for f in frames) + "\n")
    _camera_matrix(folder / "K.txt")
    read = open_sequence(folder)
    assert sequence_format(folder) == "depth_folder" and len(read) == 5
    _check(read, frames)
    if kind == "metres":
        got = read.read(1).depth
        assert np.isnan(got[0, 2]) and np.isnan(got[0, 3])
        np.testing.assert_array_equal(got[10:, 20:], frames[1].depth[10:, 20:])  # float metres as written
    with pytest.raises(SequenceError, match=r"0000.npy: depth array is 64x48, the camera 32x48"):
        open_sequence(folder, camera="60.5,58.25,31.75,24.5,32,48").read(0)


def _room_depths(poses, intrinsics=INTRINSICS, half=(3.0, 2.5, 1.5), centre=(0.0, 0.0, 1.5)):
    """z-depth images (m) of one box room seen from each camera pose (world from camera, OpenCV axes)."""
    from mabdi.camera import pixel_rays
    from tests.test_scan_folder import first_wall

    rays = pixel_rays(intrinsics).reshape(-1, 3)  # z = 1: a ray's parameter is the z-depth
    return [first_wall(rays, pose, half, centre).reshape(intrinsics.height, intrinsics.width).astype(np.float32) for pose in poses]


@pytest.mark.parametrize("written", ["opencv", "opengl", "inverted", "inverted opengl"])
def test_poses_written_another_way_are_told_by_the_frames_and_turned(tmp_path, written):
    # Capture apps write a camera's pose in OpenGL's axes (x right, y up, z backward), graphics tools a view
    # matrix (world to camera); the frames of a room lie on each other only with the poses read so, and mabdi
    # turns them into its camera's (OpenCV's) world-from-camera poses.
    from mabdi.camera import look_at

    poses = np.array([look_at([0.4 * i - 1.0, -1.0 + 0.2 * i, 1.4], [1.5, 1.0 - 0.3 * i, 1.0]) for i in range(4)])
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    written_poses = {
        "opencv": poses, "opengl": poses @ flip, "inverted": np.linalg.inv(poses), "inverted opengl": np.linalg.inv(poses @ flip),
    }[written]
    folder = tmp_path / "export"
    (folder / "depth").mkdir(parents=True)
    for i, depth in enumerate(_room_depths(poses)):
        write_depth_png(folder / "depth" / f"{i}.png", depth, 1000.0)
    _camera_matrix(folder / "intrinsics.txt")
    (folder / "poses.txt").write_text("".join(" ".join(f"{v:.9f}" for v in p.ravel()) + "\n" for p in written_poses))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read = open_sequence(folder)
    said = [str(w.message) for w in caught if "turns them into the camera's" in str(w.message)]
    assert len(said) == int(written != "opencv") and ("poses read as" in read.description) == (written != "opencv")
    np.testing.assert_allclose(read.poses, poses, atol=1e-8)
