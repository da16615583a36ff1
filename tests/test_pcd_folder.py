"""Folders of PCD scans with their poses, in the layouts LiDAR tools ship: read as the KITTI folder of the same
scans and poses reads."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from mabdi.errors import PoseFileWarning
from mabdi.sources.kitti import read_scan, write_kitti
from mabdi.sources.pcd_folder import PcdFolderSequence
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
    assert sequence_format(folder) == "pcd"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read = open_sequence(folder)
    assert isinstance(read, PcdFolderSequence)
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


@pytest.mark.parametrize("form", ["kitti_lines", "4x4_lines", "tum", "3x4_blocks"])
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
        elif form == "3x4_blocks":
            lines += [" ".join(values[r * 4 : r * 4 + 4]) for r in range(3)]
        else:
            from mabdi.sources.sequences import quaternions_from_rotations

            q = quaternions_from_rotations(pose[None, :3, :3])[0]
            lines.append(" ".join(f"{v:.9f}" for v in [0.1 * i, *pose[:3, 3], *q]))
    if form == "tum":
        lines.insert(1, "timestamp tx ty tz qx qy qz qw")
    (folder / "trajectory.txt").write_text("\n".join(lines) + "\n")
    (folder / "mabdi.toml").write_text((kitti.path / "mabdi.toml").read_text())
    _assert_same_recording(open_sequence(folder), kitti, [0.0, 0.1, 0.2] if form == "tum" else [np.nan] * 3)


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda text: text.replace("1.0 0.0 0.0 0.0", "1.0 0.0 0.0", 1), r"trajectory.txt:2: pose: 11 numbers"),
        (lambda text: text + "1 0 0 0 0 1 0 0 0 0 1 0\n", r"trajectory.txt: 4 poses, but .* holds 3 .pcd scans"),
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
    with pytest.raises(SequenceError, match=r"two scans are number 1 \(full1.pcd, scan_1.pcd\)"):
        open_sequence(folder)
    (folder / "full1.pcd").rename(folder / "last.pcd")
    with pytest.raises(SequenceError, match=r"last.pcd: a scan's name must hold its number"):
        open_sequence(folder)


def test_a_folder_of_scans_without_poses_is_not_read_as_a_recording(tmp_path):
    folder = tmp_path / "scans"
    folder.mkdir()
    _write_pcd(folder / "0.pcd", np.random.default_rng(0).uniform(-5, 5, (200, 3)))
    with pytest.raises(SequenceError, match=r"not a recorded sequence: .*a folder of PCD scans"):
        open_sequence(folder)
