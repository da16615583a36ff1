"""KITTI-style LiDAR folders: read as range images with the poses through calib's Tr, written by write_kitti."""

from __future__ import annotations

import numpy as np
import pytest

from mabdi.camera import look_at
from mabdi.depth import DepthFrame
from mabdi.simulate.path import CAMERA_FROM_LIDAR
from mabdi.sources.frames import FrameList
from mabdi.sources.kitti import KittiSequence, read_scan, write_kitti
from mabdi.sources.range_images import KITTI_GEOMETRY
from mabdi.sources.sequences import SequenceError, open_sequence, sequence_format
from mabdi.spherical import SphericalGeometry

GEOMETRY = SphericalGeometry(beams=16, columns=64, fov_up=10.0, fov_down=-20.0, range_min=0.5, range_max=50.0)


def _room(geometry, half=(6.0, 4.0, 1.5)):
    """Range image inside an axis-aligned box room centred on the sensor (every ray hits a wall)."""
    rays = geometry.rays()
    with np.errstate(divide="ignore"):
        t = np.min(np.abs(np.asarray(half) / rays), axis=-1)
    return np.where(t < geometry.range_max, t, np.nan).astype(np.float32)


def _source(geometry=GEOMETRY, frames=3):
    poses = [look_at([0.3 * i, 0.1 * i, 1.0], [5.0, 1.0 + i, 0.8]) @ CAMERA_FROM_LIDAR for i in range(frames)]
    depth = _room(geometry)
    depth[2, 5] = np.nan  # a pixel without a return
    return FrameList([DepthFrame(depth, geometry, pose, i, 0.1 * i) for i, pose in enumerate(poses)], "lidar frames")


def test_written_folder_reads_back_the_frames(tmp_path):
    source = _source()
    write_kitti(source, tmp_path / "seq")
    assert sequence_format(tmp_path / "seq") == "kitti"
    recording = open_sequence(tmp_path / "seq")
    assert isinstance(recording, KittiSequence) and len(recording) == 3
    assert recording.intrinsics == GEOMETRY  # from the [lidar] table
    np.testing.assert_allclose(recording.poses, source.poses, atol=1e-12)
    np.testing.assert_allclose(recording.timestamps, [0.0, 0.1, 0.2])
    for i in range(3):
        got, want = recording.read(i), source.read(i)
        np.testing.assert_array_equal(np.isnan(got.depth), np.isnan(want.depth))
        np.testing.assert_allclose(got.depth, want.depth, rtol=2e-7, equal_nan=True)
        assert got.frame == i
    points = read_scan(tmp_path / "seq" / "velodyne" / "000001.bin")
    assert points.dtype == np.float32 and len(points) == 16 * 64 - 1


def test_a_frame_s_own_returns_are_written_as_measured(tmp_path):
    # A scan read from points keeps each pixel's own return: written out, the points are those returns, and
    # read back they give the same returns and range image, not their pixel centres' estimates.
    rng = np.random.default_rng(2)
    rays = GEOMETRY.rays()
    nudged = rays + rng.uniform(-0.002, 0.002, rays.shape)  # returns a little off their pixel centres
    nudged /= np.linalg.norm(nudged, axis=-1, keepdims=True)
    scan = (nudged * _room(GEOMETRY)[..., None]).reshape(-1, 3)
    scan = scan[np.isfinite(scan).all(axis=1)]
    from mabdi.sources.range_images import range_image_and_returns

    depth, returns = range_image_and_returns(scan, GEOMETRY)
    source = FrameList([DepthFrame(depth, GEOMETRY, np.eye(4), 0, 0.0, None, returns)], "lidar scans")
    folder = write_kitti(source, tmp_path / "seq")
    written = read_scan(folder / "velodyne" / "000000.bin")[:, :3]
    held = np.isfinite(returns).all(axis=2)
    np.testing.assert_array_equal(np.sort(written, axis=0), np.sort(returns[held], axis=0))
    back = KittiSequence(folder).read(0)
    np.testing.assert_array_equal(back.return_points, returns)
    np.testing.assert_allclose(back.depth, depth, rtol=1e-6, equal_nan=True)


def test_poses_are_read_through_the_calibration(tmp_path):
    source = _source(frames=2)
    folder = write_kitti(source, tmp_path / "seq")
    text = (folder / "poses.txt").read_text().splitlines()
    camera0 = np.vstack([np.array(text[1].split(), dtype=float).reshape(3, 4), [0, 0, 0, 1]])
    tr = np.vstack([np.array((folder / "calib.txt").read_text().split()[1:], dtype=float).reshape(3, 4), [0, 0, 0, 1]])
    np.testing.assert_allclose(np.linalg.inv(tr) @ camera0 @ tr, source.poses[1], atol=1e-12)  # Tr^-1 P Tr
    # Without calib.txt the poses are the LiDAR's own.
    (folder / "calib.txt").unlink()
    np.testing.assert_allclose(KittiSequence(folder).poses[1], camera0, atol=1e-12)


def test_kitti_points_default_geometry(tmp_path):
    folder = tmp_path / "seq"
    (folder / "velodyne").mkdir(parents=True)
    # Three points of the HDL-64E: straight ahead at 10 m, 20 degrees left and 10 degrees down at 30 m, behind.
    el, az = np.radians([0.0, -10.0, -20.0]), np.radians([0.0, 20.0, 180.0])
    points = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el), np.zeros(3)], axis=1) * [[10], [30], [5]]
    points[:, 3] = 0.5
    points.astype("<f4").tofile(folder / "velodyne" / "000000.bin")
    (folder / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    frame = open_sequence(folder).read(0)
    assert frame.intrinsics == KITTI_GEOMETRY and frame.depth.shape == (64, 1024)
    rows, columns = np.nonzero(np.isfinite(frame.depth))
    uv, _ = KITTI_GEOMETRY.pixels(points[:, :3])
    assert sorted(zip(rows.tolist(), columns.tolist(), strict=True)) == sorted(
        zip(np.floor(uv[:, 1]).astype(int).tolist(), np.floor(uv[:, 0]).astype(int).tolist(), strict=True)
    )
    assert frame.depth[np.floor(uv[1, 1]).astype(int), np.floor(uv[1, 0]).astype(int)] == pytest.approx(30.0)
    assert np.floor(uv[0, 0]) == 512 and np.floor(uv[0, 1]) == 6  # ahead: on the edge of the centre columns; 3 of 28 degrees down
    assert np.isnan(frame.timestamp)


def test_poses_written_as_4x4_matrices_read_as_3x4_ones(tmp_path):
    """A poses.txt of 16 numbers a line (4x4 row-major, last row 0 0 0 1, as some odometry tools write it) reads
    the same poses as the KITTI 3x4 lines."""
    folder = write_kitti(_source(frames=2), tmp_path / "seq")
    expected = KittiSequence(folder).poses
    rows = [line.split() for line in (folder / "poses.txt").read_text().splitlines() if line.strip()]
    (folder / "poses.txt").write_text("".join(" ".join(row + ["0", "0", "0", "1"]) + "\n" for row in rows))
    np.testing.assert_array_equal(KittiSequence(folder).poses, expected)


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda f: (f / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n"), r"poses.txt: 1 poses, but velodyne/ holds 2 scans"),
        (lambda f: (f / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1\n" * 2), r"poses.txt:1: pose: expected 12 finite numbers"),
        (lambda f: (f / "poses.txt").write_text("2 0 0 0 0 1 0 0 0 0 1 0\n" * 2), r"poses.txt:1: not a rigid transform"),
        (lambda f: (f / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0 0 0 1 1\n" * 2), r"poses.txt:1: pose: a 4x4 matrix's last row must be 0 0 0 1"),
        (lambda f: (f / "calib.txt").write_text("P0: 1 2 3\n"), r"calib.txt: no 'Tr:' line"),
        (lambda f: (f / "times.txt").write_text("0.0\n"), r"times.txt: 1 timestamps, but velodyne/ holds 2 scans"),
        (lambda f: (f / "velodyne" / "000001.bin").write_bytes(b"\0" * 20), r"000001.bin: 20 bytes is not a whole number of points"),
        (lambda f: (f / "velodyne" / "scan.bin").write_bytes(b""), r"scan.bin: a scan's name must be its number"),
        (lambda f: (f / "mabdi.toml").write_text("[lidar]\nbeams = 0\n"), r"mabdi.toml: \[lidar\]: lidar: beams must be a positive integer"),
    ],
)
def test_damaged_folders_name_the_file(tmp_path, damage, message):
    folder = write_kitti(_source(frames=2), tmp_path / "seq")
    damage(folder)
    with pytest.raises(SequenceError, match=message):
        recording = KittiSequence(folder)
        recording.read(1)


def test_a_camera_source_is_refused(tmp_path):
    from mabdi.camera import Intrinsics

    camera = Intrinsics(fx=10.0, fy=10.0, cx=4.0, cy=3.0, width=8, height=6)
    source = FrameList([DepthFrame(np.ones((6, 8), np.float32), camera, np.eye(4))])
    with pytest.raises(SequenceError, match="a KITTI folder holds a LiDAR's scans, but these frames are a camera's"):
        write_kitti(source, tmp_path / "seq")
    assert not (tmp_path / "seq").exists()


def test_recording_a_camera_as_kitti_names_the_problem(tmp_path, capsys):
    from pathlib import Path

    from mabdi.cli import main

    scene = Path(__file__).resolve().parents[1] / "scenes" / "table.toml"
    assert main(["record", str(scene), "--format", "kitti", "--frames", "2", "--out", str(tmp_path / "seq")]) != 0
    assert "a KITTI folder holds a LiDAR's scans, but these frames are a camera's" in capsys.readouterr().err
    assert not (tmp_path / "seq").exists()
