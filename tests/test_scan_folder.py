"""Folders of LiDAR scans beside their poses, in the layouts tools ship: read as the KITTI folder of the same
scans and poses reads."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from mabdi.errors import PoseFileWarning
from mabdi.sources.kitti import read_scan, write_kitti
from mabdi.sources.pose_files import in_seconds, name_times
from mabdi.sources.scan_folder import ScanFolderSequence, is_scan_folder
from mabdi.sources.sequences import SequenceError, open_sequence, sequence_format
from tests.test_kitti import _source


def _write_pcd(path, points):
    """A binary PCD of float32 x y z, as PCL writes one."""
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\nDATA binary\n"
    )
    path.write_bytes(header.encode() + np.ascontiguousarray(points, dtype="<f4").tobytes())


@pytest.fixture()
def kitti(tmp_path):
    """(the KITTI folder of three LiDAR frames, as read) to build the PCD layouts from."""
    folder = write_kitti(_source(frames=3), tmp_path / "kitti")
    return open_sequence(folder)


def _six_digits(pose):
    return [float(f"{v:.6f}") for v in np.asarray(pose).ravel()]


def _assert_same_recording(read, kitti, times=None):
    assert len(read) == len(kitti)
    assert read.intrinsics.beams == kitti.intrinsics.beams and read.intrinsics.columns == kitti.intrinsics.columns
    np.testing.assert_allclose(read.poses, kitti.poses, atol=2e-6)
    if times is not None:
        np.testing.assert_allclose(read.timestamps, times)
    for i in range(len(kitti)):
        got, want = read.read(i), kitti.read(i)
        np.testing.assert_array_equal(np.isnan(got.depth), np.isnan(want.depth))
        np.testing.assert_allclose(got.depth, want.depth, rtol=1e-6, equal_nan=True)


def _balm_folder(path, kitti, scan_names=lambda i: f"full{i}.pcd"):
    """BALM's layout: unpadded ``fullN.pcd`` beside ``alidarPose.csv``, four comma-ended lines a scan, the time in
    the 4x4's last element, rotations written to 6 digits."""
    path.mkdir()
    lines = []
    for i, pose in enumerate(kitti.poses):
        _write_pcd(path / scan_names(i), read_scan(kitti.scan_paths[i]))
        values = _six_digits(pose)
        values[15] = 1630577758.569490 + 0.5 * i
        lines += ["".join(f"{v:.6f}," for v in values[r * 4 : r * 4 + 4]) for r in range(4)]
    (path / "alidarPose.csv").write_text("\n".join(lines) + "\n")
    (path / "mabdi.toml").write_text((kitti.path / "mabdi.toml").read_text())
    return path


def test_balm_s_folder_reads_as_the_kitti_folder_of_its_scans(tmp_path, kitti):
    # Ten scans and more order by number, not by name: full10 after full9.
    folder = _balm_folder(tmp_path / "balm", kitti, lambda i: f"full{[9, 10, 11][i]}.pcd")
    assert sequence_format(folder) == "scans"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read = open_sequence(folder)
    assert isinstance(read, ScanFolderSequence)
    assert [p.name for p in read.scan_paths] == ["full9.pcd", "full10.pcd", "full11.pcd"]
    _assert_same_recording(read, kitti, 1630577758.569490 + 0.5 * np.arange(3))
    repaired = [str(w.message) for w in caught if issubclass(w.category, PoseFileWarning)]
    assert len(repaired) == 1 and "alidarPose.csv" in repaired[0]  # 6-digit rotations, made rigid and said once


def test_a_clouds_and_poses_folder_reads_as_the_kitti_folder_of_its_scans(tmp_path, kitti):
    # A cloud a file and a 4x4 a file, one row a line (as prime-slam/sova's evaluation data), times beside them.
    folder = tmp_path / "sova"
    (folder / "clouds").mkdir(parents=True)
    (folder / "poses").mkdir()
    for i, pose in enumerate(kitti.poses):
        _write_pcd(folder / "clouds" / f"{i}.pcd", read_scan(kitti.scan_paths[i]))
        np.savetxt(folder / "poses" / f"{i}.txt", pose)
    (folder / "times.txt").write_text("0.0\n0.1\n0.2\n")
    (folder / "mabdi.toml").write_text((kitti.path / "mabdi.toml").read_text())
    _assert_same_recording(open_sequence(folder), kitti, [0.0, 0.1, 0.2])
    (folder / "poses" / "2.txt").unlink()
    with pytest.raises(SequenceError, match=r"no pose for scan 2.pcd"):
        open_sequence(folder)


@pytest.mark.parametrize("form", ["kitti_lines", "4x4_lines", "timed_3x4_lines", "tum", "sec_nsec", "3x4_blocks"])
def test_a_pose_file_in_each_form_reads_the_same_poses(tmp_path, kitti, form):
    folder = tmp_path / "scans"
    (folder / "pcd").mkdir(parents=True)
    lines = ["# written by a LiDAR SLAM tool"]
    for i, pose in enumerate(kitti.poses):
        _write_pcd(folder / "pcd" / f"cloud_{i:04d}.pcd", read_scan(kitti.scan_paths[i]))
        values = [f"{v:.9f}" for v in pose.ravel()]
        if form == "kitti_lines":
            lines.append(" ".join(values[:12]))
        elif form == "4x4_lines":
            lines.append(",".join(values))
        elif form == "timed_3x4_lines":  # a time in ns since the epoch, then the matrix
            lines.append(",".join([str(1566535940795328163 + 100_000_000 * i), *values[:12]]))
        elif form == "3x4_blocks":
            lines += [" ".join(values[r * 4 : r * 4 + 4]) for r in range(3)]
        else:
            from mabdi.sources.sequences import quaternions_from_rotations

            q = quaternions_from_rotations(pose[None, :3, :3])[0]
            stamp = [0.1 * i] if form == "tum" else [1583836591, 100_000_000 * i]
            lines.append(" ".join(f"{v:.9f}" for v in [*stamp, *pose[:3, 3], *q]))
    if form in ("tum", "sec_nsec"):
        lines.insert(1, "timestamp tx ty tz qx qy qz qw")
    (folder / "trajectory.txt").write_text("\n".join(lines) + "\n")
    (folder / "mabdi.toml").write_text((kitti.path / "mabdi.toml").read_text())
    times = {"tum": [0.0, 0.1, 0.2], "sec_nsec": 1583836591 + np.array([0.0, 0.1, 0.2]),
             "timed_3x4_lines": 1566535940.795328163 + np.array([0.0, 0.1, 0.2])}.get(form, [np.nan] * 3)
    _assert_same_recording(open_sequence(folder), kitti, times)


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda text: text.replace("1.0 0.0 0.0 0.0", "1.0 0.0 0.0", 1), r"trajectory.txt:2: pose: 11 numbers"),
        (lambda text: text + "1 0 0 0 0 1 0 0 0 0 1 0\n", r"trajectory.txt: 4 poses for 3 scans, and the poses hold no times to pair them by"),
        (lambda text: text.replace("1.0 0.0 0.0 0.0", "2.0 0.0 0.0 0.0", 1), r"trajectory.txt:2: not a rigid transform"),
        (lambda text: text.replace("1.0 0.0 0.0 0.0", "1.0 zero 0.0 0.0", 1), r"trajectory.txt:2: pose: a field is not a number"),
    ],
)
def test_a_damaged_pose_file_is_named_with_its_line(tmp_path, damage, message):
    folder = tmp_path / "scans"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        _write_pcd(folder / f"{i}.pcd", rng.uniform(-5, 5, (200, 3)))
    text = "# poses\n" + "".join(f"1.0 0.0 0.0 0.0 0.0 1.0 0.0 {i}.0 0.0 0.0 1.0 0.0\n" for i in range(3))
    (folder / "trajectory.txt").write_text(damage(text))
    with pytest.raises(SequenceError, match=message):
        open_sequence(folder)


def test_scans_of_one_number_or_of_none_are_named(tmp_path):
    folder = tmp_path / "scans"
    folder.mkdir()
    points = np.random.default_rng(0).uniform(-5, 5, (200, 3))
    for name in ("scan_1.pcd", "full1.pcd"):
        _write_pcd(folder / name, points)
    (folder / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2)
    with pytest.raises(SequenceError, match=r"two files have the same number \(full1.pcd, scan_1.pcd\)"):
        open_sequence(folder)
    (folder / "full1.pcd").rename(folder / "last.pcd")
    with pytest.raises(SequenceError, match=r"last.pcd: a frame file's name must hold its number"):
        open_sequence(folder)


def test_a_folder_of_scans_without_poses_is_not_read_as_a_recording(tmp_path):
    folder = tmp_path / "scans"
    folder.mkdir()
    _write_pcd(folder / "0.pcd", np.random.default_rng(0).uniform(-5, 5, (200, 3)))
    with pytest.raises(SequenceError, match=r"not a recorded sequence: .*a folder of LiDAR scans"):
        open_sequence(folder)


def test_poses_at_their_own_clock_are_interpolated_at_the_scans_times(tmp_path, kitti):
    # Five scans named by their times (seconds and nanoseconds), poses at 10 Hz on another clock covering the
    # middle three: those three are read at the poses interpolated to their times, the other two skipped and said.
    folder = tmp_path / "sensor"
    (folder / "lidar" / "ouster").mkdir(parents=True)
    start = 1583836591
    scan_times = start + np.array([0.0, 0.25, 0.45, 0.65, 0.9])
    points = [read_scan(kitti.scan_paths[i % 3]) for i in range(5)]
    for t, p in zip(scan_times, points, strict=True):
        seconds = int(t)
        _write_pcd(folder / "lidar" / "ouster" / f"cloud_{seconds}_{round((t - seconds) * 1e9):09d}.pcd", p)
    pose_times = start + np.arange(0.2, 0.75, 0.1)  # 0.2 .. 0.7 s
    lines = ["#sec,nsec,x,y,z,qx,qy,qz,qw"]
    for t in pose_times:
        seconds = int(round(t, 6))
        lines.append(f"{seconds},{round((t - seconds) * 1e9)},{t - start},{2 * (t - start)},1.5,0,0,0,1")
    (folder / "registered_poses.csv").write_text("\n".join(lines) + "\n")
    (folder / "mabdi.toml").write_text((kitti.path / "mabdi.toml").read_text())
    read = open_sequence(folder)
    assert len(read) == 3 and "2 scans without a pose skipped" in read.description
    np.testing.assert_allclose(read.timestamps, scan_times[1:4], atol=1e-6)
    np.testing.assert_allclose(read.poses[:, 0, 3], scan_times[1:4] - start, atol=1e-6)  # x moves 1 m/s
    np.testing.assert_allclose(read.poses[:, 1, 3], 2 * (scan_times[1:4] - start), atol=1e-6)
    np.testing.assert_array_equal(read.read(0).depth, kitti.read(1).depth)


def test_times_are_read_as_seconds_whatever_their_unit():
    np.testing.assert_allclose(in_seconds(np.array([1.566e18, 1.566e15, 1.566e12, 1.566e9, 12.5]))[:1], [1.566e9])
    for stamp in (1.566e18, 1.566e15, 1.566e12, 1.566e9):
        np.testing.assert_allclose(in_seconds(np.array([stamp])), [1.566e9])
    np.testing.assert_allclose(in_seconds(np.array([0.0, 12.5])), [0.0, 12.5])
    from pathlib import Path

    names = [Path("1566535940795328163.bin"), Path("cloud_1583836591_182590976.pcd"), Path("1630577758.569490.pcd")]
    np.testing.assert_allclose(name_times(names[:1]), [1566535940.795328163])
    np.testing.assert_allclose(name_times(names[1:2]), [1583836591.182590976])
    np.testing.assert_allclose(name_times(names[2:]), [1630577758.569490])


def test_a_scan_folder_of_bin_scans_in_a_folder_below(tmp_path, kitti):
    # KITTI's .bin scans one folder down (a dataset's sensor_data/<sensor>/), a pose file with a time a line.
    folder = tmp_path / "seq"
    (folder / "sensor_data" / "lidar").mkdir(parents=True)
    lines = []
    for i, pose in enumerate(kitti.poses):
        (folder / "sensor_data" / "lidar" / f"{1000 + i}.bin").write_bytes(kitti.scan_paths[i].read_bytes())
        lines.append(",".join(str(v) for v in [1000 + i, *pose[:3].ravel()]))
    (folder / "global_pose.csv").write_text("\n".join(lines) + "\n")
    (folder / "mabdi.toml").write_text((kitti.path / "mabdi.toml").read_text())
    _assert_same_recording(open_sequence(folder), kitti, [1000.0, 1001.0, 1002.0])
    (folder / "other").mkdir()
    for name in ("0.bin", "1.bin"):
        (folder / "other" / name).write_bytes(kitti.scan_paths[0].read_bytes())
    with pytest.raises(SequenceError, match=r"scans in 2 folders \(other, sensor_data/lidar\)"):
        open_sequence(folder)


def test_a_kitti_folder_is_read_as_kitti_alone(kitti):
    # velodyne/ holds .bin scans beside poses.txt: a KITTI folder, not also a scan folder to warn of
    assert sequence_format(kitti.path) == "kitti"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not isinstance(open_sequence(kitti.path), ScanFolderSequence)


def test_another_tool_s_bin_files_below_a_folder_are_no_scans(tmp_path):
    # A photogrammetry folder (cameras.bin, images.bin, points3D.bin below it) beside a poses file: no recording
    folder = tmp_path / "photos"
    (folder / "sparse" / "0").mkdir(parents=True)
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        (folder / "sparse" / "0" / name).write_bytes(b"\0" * 64)
    (folder / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    assert not is_scan_folder(folder)
    with pytest.raises(SequenceError, match="not a recorded sequence"):
        open_sequence(folder)


def _room_scans(poses, half=(6.0, 4.0, 1.5), centre=(0.0, 0.0, 1.5)):
    """Scans of one box room (metres, z up) from each LiDAR pose (world from sensor): every ray of a 64-beam,
    720-column sensor to the first wall it meets, in the sensor's axes."""
    from mabdi.spherical import SphericalGeometry

    geometry = SphericalGeometry(beams=64, columns=720, fov_up=15.0, fov_down=-25.0, range_min=0.5, range_max=50.0)
    rays = geometry.rays().reshape(-1, 3)
    return [(rays * first_wall(rays, pose, half, centre)[:, None]).astype(np.float32) for pose in poses]


def first_wall(rays, pose, half, centre):
    """For each sensor-frame ray (N, 3), its parameter at the first wall of a box room (``half`` sizes about
    ``centre``, metres, world frame) it meets from inside, the sensor at ``pose`` (world from sensor)."""
    direction = rays @ pose[:3, :3].T
    origin = pose[:3, 3] - np.asarray(centre)
    with np.errstate(divide="ignore"):
        return np.min(np.where(direction != 0, (np.sign(direction) * np.asarray(half) - origin) / direction, np.inf), axis=1)


def _lidar_poses(count=4):
    """A LiDAR moving 0.4 m and turning 8 degrees a scan (world from sensor, z up)."""
    poses = []
    for i in range(count):
        a = np.radians(8.0 * i)
        pose = np.eye(4)
        pose[:3, :3] = [[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]
        pose[:3, 3] = (-2.0 + 0.4 * i, 0.3 * i, 1.2)
        poses.append(pose)
    return np.array(poses)


@pytest.mark.parametrize("layout", ["scan_folder", "kitti_without_calib"])
def test_poses_in_a_camera_s_axes_are_told_by_the_scans_and_turned(tmp_path, layout):
    # KITTI's ground truth is a camera's pose (x right, y down, z forward); without the calibration that relates
    # it to the LiDAR, the scans show it: read as the LiDAR's, the scans do not lie on each other.
    from mabdi.sources.pose_axes import CAMERA_FROM_LIDAR_AXES

    lidar = _lidar_poses()
    turn = np.eye(4)
    turn[:3, :3] = CAMERA_FROM_LIDAR_AXES
    camera = turn @ lidar @ np.linalg.inv(turn)  # the same motion written in a camera's axes
    folder = tmp_path / "seq"
    scans = folder / ("scans" if layout == "scan_folder" else "velodyne")
    scans.mkdir(parents=True)
    for i, points in enumerate(_room_scans(lidar)):
        np.column_stack([points, np.zeros(len(points), np.float32)]).astype("<f4").tofile(scans / f"{i:06d}.bin")
    (folder / "poses.txt").write_text("".join(" ".join(f"{v:.9f}" for v in p[:3].ravel()) + "\n" for p in camera))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read = open_sequence(folder)
    said = [str(w.message) for w in caught if issubclass(w.category, PoseFileWarning)]
    assert len(said) == 1 and "read as a camera's axes" in said[0] and "turns them into the LiDAR's" in said[0]
    assert "poses read as a camera's axes" in read.description
    np.testing.assert_allclose(read.poses, lidar, atol=1e-8)
    # written inverted (sensor from world), the same
    (folder / "poses.txt").write_text("".join(" ".join(f"{v:.9f}" for v in p[:3].ravel()) + "\n" for p in np.linalg.inv(lidar)))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read = open_sequence(folder)
    assert "poses read as sensor from world (inverted)" in read.description
    np.testing.assert_allclose(read.poses, lidar, atol=1e-8)
    # the same scans beside the LiDAR's own poses are read as written
    (folder / "poses.txt").write_text("".join(" ".join(f"{v:.9f}" for v in p[:3].ravel()) + "\n" for p in lidar))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read = open_sequence(folder)
    assert not [w for w in caught if "camera's" in str(w.message)]
    np.testing.assert_allclose(read.poses, lidar, atol=1e-8)


def test_a_scan_folder_s_calibration_relates_camera_poses_to_the_lidar(tmp_path, kitti):
    # A KITTI sequence's files without the velodyne/ folder: calib.txt's Tr is read as a KITTI folder reads it
    folder = tmp_path / "flat"
    folder.mkdir()
    for i, scan in enumerate(kitti.scan_paths):
        (folder / f"{i:06d}.bin").write_bytes(scan.read_bytes())
    for name in ("poses.txt", "calib.txt", "times.txt", "mabdi.toml"):
        (folder / name).write_text((kitti.path / name).read_text())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read = open_sequence(folder)
    assert isinstance(read, ScanFolderSequence) and not [w for w in caught if "camera's" in str(w.message)]
    _assert_same_recording(read, kitti, [0.0, 0.1, 0.2])
