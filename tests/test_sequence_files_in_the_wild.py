"""Recordings as real tools leave them: depth images of another size than the camera file's, frame numbers
without zero padding, duplicate TUM timestamps, a folder holding two layouts. Small synthetic files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mabdi.cli import main
from mabdi.sources.sequences import SequenceError, open_sequence, sequence_format
from mabdi.sources.tum import write_depth_png

# A camera for 64x48 images, principal point at the centre (integer pixel centres in the files: 31.5, 23.5).
K = "50 0 31.5\n0 50 23.5\n0 0 1\n"


def _depth(path, width=64, height=48, metres=1.0, scale=1000.0):
    path.parent.mkdir(parents=True, exist_ok=True)
    write_depth_png(path, np.full((height, width), metres, dtype=np.float32), scale)


def _pose(x: float) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = x
    return pose


def _pose_text(x: float) -> str:
    return "\n".join(" ".join(f"{v:g}" for v in row) for row in _pose(x)) + "\n"


def _threedmatch(folder, stems, width=64, height=48, k=K):
    """A 3DMatch sequence: frame ``stem`` has its pose translated by x = its number (so the order shows)."""
    folder.mkdir(parents=True, exist_ok=True)
    for stem in stems:
        _depth(folder / f"{stem}.depth.png", width, height)
        (folder / f"{stem}.pose.txt").write_text(_pose_text(float(stem.split("-")[1])))
    if k is not None:
        (folder / "camera-intrinsics.txt").write_text(k)
    return folder


# ---------------------------------------------------------------------------
# A. Depth images of another size than the camera file's


@pytest.mark.parametrize("size", [(128, 96), (32, 24)], ids=["twice", "half"])
def test_3dmatch_depth_of_another_size_than_its_camera_matrix_is_refused(tmp_path, size):
    folder = _threedmatch(tmp_path / "seq", ["frame-000000", "frame-000001"], *size)
    with pytest.raises(SequenceError) as error:
        open_sequence(folder)
    message = str(error.value)
    assert str(folder / "frame-000000.depth.png") in message
    assert f"{size[0]}x{size[1]}" in message and "64x48" in message
    assert "camera-intrinsics.txt" in message
    assert "--camera fx,fy,cx,cy,width,height" in message and "[camera]" in message


def test_3dmatch_depth_of_another_size_reads_with_the_camera_given(tmp_path):
    """The way out the error names works: --camera (camera=) or a mabdi.toml [camera] table for the images' size."""
    folder = _threedmatch(tmp_path / "seq", ["frame-000000", "frame-000001"], 32, 24, k="50 0 32.5\n0 50 23.5\n0 0 1\n")
    source = open_sequence(folder, camera="25,25,16,12,32,24")
    assert (source.intrinsics.width, source.intrinsics.height, source.intrinsics.cx) == (32, 24, 16.0)
    assert source.read(1).depth.shape == (24, 32)
    (folder / "mabdi.toml").write_text("[camera]\nfx = 25.0\nfy = 25.0\ncx = 16.0\ncy = 12.0\nwidth = 32\nheight = 24\n")
    assert open_sequence(folder).intrinsics.fx == 25.0


def test_run_on_depth_of_another_size_exits_with_the_error(tmp_path, capsys):
    folder = _threedmatch(tmp_path / "seq", ["frame-000000", "frame-000001"], 128, 96)
    assert main(["run", "--sequence", str(folder), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mabdi: error: ") and "128x96" in err and "64x48" in err
    assert not (tmp_path / "out" / "world_mesh.vtp").exists()


def test_scannet_depth_of_another_size_than_its_camera_matrix_is_refused(tmp_path):
    folder = tmp_path / "scene"
    for n in range(2):
        _depth(folder / "depth" / f"{n}.png", 128, 96)
        (folder / "pose").mkdir(exist_ok=True)
        (folder / "pose" / f"{n}.txt").write_text(_pose_text(n))
    (folder / "intrinsic").mkdir()
    (folder / "intrinsic" / "intrinsic_depth.txt").write_text("50 0 31.5 0\n0 50 23.5 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(SequenceError) as error:
        open_sequence(folder)
    message = str(error.value)
    assert str(folder / "depth" / "0.png") in message and "128x96" in message and "64x48" in message
    assert "intrinsic_depth.txt" in message and "--camera" in message


def test_redwood_depth_of_another_size_than_its_camera_json_is_refused_at_open(tmp_path):
    folder = tmp_path / "redwood"
    entries = []
    for n in range(2):
        _depth(folder / "depth" / f"{n:06d}.png", 128, 96)
        entries.append(f"{n} {n} {n + 1}\n" + _pose_text(n))
    (folder / "trajectory.log").write_text("".join(entries))
    camera = {"width": 64, "height": 48, "intrinsic_matrix": [50, 0, 0, 0, 50, 0, 31.5, 23.5, 1]}
    (folder / "camera_intrinsic.json").write_text(json.dumps(camera))
    with pytest.raises(SequenceError) as error:
        open_sequence(folder)
    message = str(error.value)
    assert str(folder / "depth" / "000000.png") in message and "128x96" in message and "64x48" in message
    assert "camera_intrinsic.json" in message and "--camera" in message


def test_tum_depth_of_another_size_than_its_camera_is_refused_at_open(tmp_path):
    folder = tmp_path / "tum"
    _depth(folder / "depth" / "1.000000.png", 128, 96, scale=5000.0)
    (folder / "depth.txt").write_text("1.000000 depth/1.000000.png\n")
    (folder / "groundtruth.txt").write_text("1.0 0 0 0 0 0 0 1\n")
    (folder / "mabdi.toml").write_text("[camera]\nfx = 50.0\nfy = 50.0\ncx = 32.0\ncy = 24.0\nwidth = 64\nheight = 48\n")
    with pytest.raises(SequenceError) as error:
        open_sequence(folder)
    message = str(error.value)
    assert "1.000000.png" in message and "128x96" in message and "64x48" in message
    assert "mabdi.toml" in message and "--camera" in message
    with pytest.raises(SequenceError, match=r"1\.000000\.png: image is 128x96, intrinsics say 640x480.*--camera fx,fy,cx,cy,width,height"):
        open_sequence(folder, camera="fr1").read(0)  # a camera given: the first frame read says so
    source = open_sequence(folder, camera="100,100,64,48,128,96")  # what the error says to give
    assert source.read(0).depth.shape == (96, 128)


def test_replica_depth_of_another_size_than_its_camera_is_refused_at_open(tmp_path):
    folder = tmp_path / "room0"
    for n in range(2):
        _depth(folder / "results" / f"depth{n:06d}.png", 128, 96, scale=6553.5)
    (folder / "traj.txt").write_text("".join(" ".join(f"{v:g}" for v in _pose(n).ravel()) + "\n" for n in range(2)))
    (folder / "mabdi.toml").write_text('[camera]\npreset = "replica"\n')
    with pytest.raises(SequenceError) as error:
        open_sequence(folder)
    message = str(error.value)
    assert "depth000000.png" in message and "128x96" in message and "1200x680" in message and "--camera" in message
    assert "camera.preset replica" in message


# ---------------------------------------------------------------------------
# B. Frame numbers without zero padding


def test_natural_order_compares_numbers_as_numbers():
    from mabdi.sources.sequence_files import natural_sorted

    names = ["frame-10.depth.png", "frame-2.depth.png", "frame-1.depth.png", "frame-11.depth.png", "frame-0.depth.png"]
    assert natural_sorted(names) == ["frame-0.depth.png", "frame-1.depth.png", "frame-2.depth.png", "frame-10.depth.png", "frame-11.depth.png"]
    assert natural_sorted(["b2", "a10", "a9", "b10"]) == ["a9", "a10", "b2", "b10"]


def test_3dmatch_frames_without_zero_padding_are_read_in_number_order(tmp_path):
    folder = _threedmatch(tmp_path / "seq", [f"frame-{n}" for n in range(12)])
    source = open_sequence(folder)
    np.testing.assert_array_equal(source.poses[:, 0, 3], np.arange(12))
    assert [f.name for f in source.files[:3]] == ["frame-0.depth.png", "frame-1.depth.png", "frame-2.depth.png"]


def test_3dmatch_scene_sequences_without_zero_padding_are_read_in_number_order(tmp_path):
    scene = tmp_path / "scene"
    for s in (1, 2, 10):
        _threedmatch(scene / f"seq-{s}", [f"frame-{s * 100 + n}" for n in range(2)], k=None)
    (scene / "camera-intrinsics.txt").write_text(K)
    source = open_sequence(scene)
    assert [p.name for p in source.sequences] == ["seq-1", "seq-2", "seq-10"]
    np.testing.assert_array_equal(source.poses[:, 0, 3], [100, 101, 200, 201, 1000, 1001])


def test_redwood_frames_without_zero_padding_are_read_in_number_order(tmp_path):
    folder = tmp_path / "redwood"
    entries = []
    for n in range(12):
        _depth(folder / "depth" / f"{n}.png", metres=1.0 + n / 100)
        entries.append(f"{n} {n} {n + 1}\n" + _pose_text(n))
    (folder / "trajectory.log").write_text("".join(entries))
    source = open_sequence(folder, camera="50,50,32,24,64,48")
    assert [f.name for f in source.files] == [f"{n}.png" for n in range(12)]
    assert source.read(10).depth[0, 0] == pytest.approx(1.10)


def test_replica_frames_without_zero_padding_are_read_in_number_order(tmp_path):
    folder = tmp_path / "room0"
    for n in range(12):
        _depth(folder / "results" / f"depth{n}.png", 1200, 680, metres=1.0 + n / 100, scale=6553.5)
    (folder / "traj.txt").write_text("".join(" ".join(f"{v:g}" for v in _pose(n).ravel()) + "\n" for n in range(12)))
    source = open_sequence(folder, camera="replica")
    assert [f.name for f in source.files] == [f"depth{n}.png" for n in range(12)]
    assert source.read(2).depth[0, 0] == pytest.approx(1.02, abs=1e-3)


# ---------------------------------------------------------------------------
# C. Duplicate TUM timestamps; a folder holding two layouts


def _tum(folder, depth_lines, groundtruth_lines):
    folder.mkdir(parents=True, exist_ok=True)
    for line in depth_lines:
        name = line.split()[1]
        if not (folder / name).exists():
            _depth(folder / name, scale=5000.0)
    (folder / "depth.txt").write_text("# timestamp filename\n" + "".join(line + "\n" for line in depth_lines))
    (folder / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "".join(line + "\n" for line in groundtruth_lines))
    (folder / "mabdi.toml").write_text("[camera]\nfx = 50.0\nfy = 50.0\ncx = 32.0\ncy = 24.0\nwidth = 64\nheight = 48\n")
    return folder


def test_tum_groundtruth_samples_that_disagree_at_one_time_are_refused(tmp_path):
    depth = ["1.0 depth/1.png", "1.1 depth/2.png"]
    same = _tum(tmp_path / "same", depth, ["1.0 0 0 0 0 0 0 1", "1.0 0 0 0 0 0 0 1", "1.1 0.1 0 0 0 0 0 1"])
    np.testing.assert_allclose(open_sequence(same).poses[:, 0, 3], [0.0, 0.1])
    conflict = _tum(tmp_path / "conflict", depth, ["1.0 0 0 0 0 0 0 1", "1.05 0.05 0 0 0 0 0 1", "1.05 0.55 0 0 0 0 0 1", "1.1 0.1 0 0 0 0 0 1"])
    with pytest.raises(SequenceError) as error:
        open_sequence(conflict)
    message = str(error.value)
    assert str(conflict / "groundtruth.txt") in message
    assert "lines 3 and 4" in message and "0.5 m" in message


def test_tum_depth_timestamps_listed_twice(tmp_path):
    """The same image listed twice is one frame; two images at one time are an error naming both lines."""
    groundtruth = ["1.0 0 0 0 0 0 0 1", "1.1 0.1 0 0 0 0 0 1"]
    repeated = _tum(tmp_path / "repeated", ["1.0 depth/1.png", "1.1 depth/2.png", "1.1 depth/2.png"], groundtruth)
    assert len(open_sequence(repeated)) == 2
    clash = _tum(tmp_path / "clash", ["1.0 depth/1.png", "1.1 depth/2.png", "1.1 depth/3.png"], groundtruth)
    with pytest.raises(SequenceError) as error:
        open_sequence(clash)
    message = str(error.value)
    assert str(clash / "depth.txt") in message and "lines 3 and 4" in message
    assert "depth/2.png" in message and "depth/3.png" in message


def test_a_folder_holding_tum_and_3dmatch_files_says_which_it_reads(tmp_path):
    folder = _tum(tmp_path / "both", ["1.0 depth/1.png"], ["1.0 0 0 0 0 0 0 1"])
    _threedmatch(folder, ["frame-000000", "frame-000001", "frame-000002"])
    with pytest.warns(UserWarning) as caught:
        source = open_sequence(folder)
    assert len(source) == 1  # TUM, as before
    message = str(caught[0].message)
    assert "TUM" in message and "3DMatch" in message and "frame-*.depth.png" in message
    assert "[sequence]" in message and 'format = "3dmatch"' in message
    with open(folder / "mabdi.toml", "a") as stream:
        stream.write('[sequence]\nformat = "3dmatch"\n')
    assert sequence_format(folder) == "3dmatch"
    assert len(open_sequence(folder)) == 3
    (folder / "mabdi.toml").write_text('[sequence]\nformat = "7scenes"\n')
    with pytest.raises(SequenceError, match=r"mabdi\.toml.*sequence\.format.*'7scenes'.*3dmatch"):
        sequence_format(folder)
