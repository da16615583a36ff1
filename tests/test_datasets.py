"""The common RGB-D dataset layouts (3DMatch / 7-Scenes, Redwood / Open3D, ScanNet, Replica, Stray Scanner): simulated frames
written in each, read back, and run through `mabdi run --sequence` against the same frames as a TUM folder."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree
from vtkmodules.util.numpy_support import vtk_to_numpy

from mabdi.cli import main
from mabdi.config import load_run_config
from mabdi.io.vtk_files import read_mesh_file
from mabdi.simulate.rig import SimulatedRig
from mabdi.sources.frames import FrameList
from mabdi.sources.image_sequence import colour_lookup
from mabdi.sources import replica
from mabdi.sources.redwood import write_redwood
from mabdi.sources.replica import write_replica
from mabdi.sources.scannet import ScanNetSequence, write_scannet
from mabdi.sources import stray
from mabdi.sources.stray import StraySequence, write_stray
from mabdi.sources.sequences import FORMATS, SequenceError, open_sequence, sequence_format
from mabdi.sources.threedmatch import ThreeDMatchSequence, write_3dmatch
from mabdi.sources.tum import write_tum

#: A small table scene (160x120 sensor, 6 frames): fast, and every layout's quantisation shows.
CONFIG = """
[run]
name = "small_table"
frames = 6
seed = 1

[sensor]
noise = "none"

[sensor.camera]
width = 160
height = 120
fx = 131.25
fy = 131.25
cx = 80.0
cy = 60.0

[path]
center = [0.0, 0.0]
radius_x = 2.2
radius_y = 2.0
z0 = 1.5
z1 = 1.9
look_from = [0.0, 0.0, 0.7]
look_to = [0.0, 0.0, 0.9]

[[scene.objects]]
type = "plane"
size = [6.0, 6.0]

[[scene.objects]]
type = "box"
size = [1.2, 0.8, 0.04]
position = [0.0, 0.0, 0.96]

[[scene.objects]]
type = "box"
size = [0.05, 0.05, 0.96]
position = [0.55, 0.35, 0.0]

[[scene.objects]]
type = "cylinder"
radius = 0.08
height = 0.2
position = [-0.2, 0.1, 1.0]
"""

WRITERS = {"3dmatch": write_3dmatch, "redwood": write_redwood, "scannet": write_scannet, "replica": write_replica, "stray": write_stray}
#: Each layout's depth step (m): TUM 1/5000, millimetres, Replica 1/6553.5.
STEPS = {"tum": 1 / 5000, "3dmatch": 1e-3, "redwood": 1e-3, "scannet": 1e-3, "replica": 1 / 6553.5, "stray": 1e-3}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """The simulated frames (in memory), the config, and the frames written as TUM and as every layout."""
    root = tmp_path_factory.mktemp("datasets")
    config_file = root / "small_table.toml"
    config_file.write_text(CONFIG)
    rig = SimulatedRig.from_config(load_run_config(config_file))
    try:
        frames = FrameList([rig.read(i) for i in range(len(rig))], "simulated small table")
    finally:
        rig.close()
    folders = {"tum": write_tum(frames, root / "tum")}
    for name, writer in WRITERS.items():
        folders[name] = writer(frames, root / name)
        if name == "replica":  # TUM's 1/5000 m steps cannot hold 1/6553.5 m ones: a TUM folder at Replica's scale
            folders[f"tum_{name}"] = write_tum(frames, root / f"tum_{name}", depth_scale=replica.DEPTH_SCALE)
        else:
            folders[f"tum_{name}"] = write_tum(_quantised(frames, STEPS[name]), root / f"tum_{name}")
    return frames, config_file, folders


def _quantised(frames, step):
    """The frames with depth rounded to ``step`` metres: what a layout of that step holds, made without its reader."""
    out = []
    for i in range(len(frames)):
        frame = frames.read(i)
        frame.depth = (np.rint(frame.depth.astype(np.float64) / step) * step).astype(np.float32)
        out.append(frame)
    return FrameList(out, "quantised")


def _run(config, folder, out, *extra):
    args = ["run", str(config), "--sequence", str(folder), "--no-registration", "--surface", "pixel_grid", "--no-eval"]
    assert main([*args, "--out", str(out), "--quiet", *extra]) == 0
    return read_mesh_file(out / "world_mesh.vtp")


@pytest.mark.parametrize("layout", list(WRITERS))
def test_each_layout_reads_back_the_frames(recorded, layout):
    frames, _, folders = recorded
    assert sequence_format(folders[layout]) == layout
    source = open_sequence(folders[layout])
    assert source.description.startswith(FORMATS[layout][0])
    assert source.intrinsics == frames.intrinsics  # integer pixel centres in the files, +0.5 in mabdi
    assert len(source) == len(frames)
    for i in range(len(frames)):
        got, expected = source.read(i), frames.read(i)
        np.testing.assert_allclose(got.world_from_camera, expected.world_from_camera, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(np.isnan(got.depth), np.isnan(expected.depth))
        np.testing.assert_allclose(got.depth, expected.depth, rtol=0, atol=STEPS[layout] / 2 + 1e-6, equal_nan=True)


@pytest.mark.parametrize("layout", list(WRITERS))
def test_each_layout_gives_the_map_the_tum_folder_gives(recorded, tmp_path, layout):
    """The TUM folder holds the same frames (depth rounded to the layout's step, written without the layout's
    reader or writer; for Replica, a TUM folder at its scale read with --depth-scale). Triangle count within 0.5%; vertices (one per pixel) within one depth step."""
    _, config, folders = recorded
    scale = ["--depth-scale", str(replica.DEPTH_SCALE)] if layout == "replica" else []
    tum = _run(config, folders[f"tum_{layout}"], tmp_path / "tum", *scale)
    other = _run(config, folders[layout], tmp_path / layout)
    cells = tum.GetNumberOfCells(), other.GetNumberOfCells()
    assert cells[0] > 10_000
    assert abs(cells[1] - cells[0]) <= 0.005 * cells[0], cells
    expected = vtk_to_numpy(tum.GetPoints().GetData()).astype(np.float64)
    got = vtk_to_numpy(other.GetPoints().GetData()).astype(np.float64)
    distance, _ = cKDTree(expected).query(got)
    step = max(STEPS["tum"], STEPS[layout])
    assert np.mean(distance <= step + 1e-5) >= 0.995, np.percentile(distance, [50, 99, 99.9])


def test_3dmatch_scene_folder_reads_its_sequences_in_order(recorded, tmp_path):
    frames, _, _ = recorded
    scene = tmp_path / "scene"
    write_3dmatch(FrameList([frames.read(i) for i in range(3)]), scene / "seq-01")
    write_3dmatch(FrameList([frames.read(i) for i in range(3, 6)]), scene / "seq-02")
    (scene / "seq-01" / "camera-intrinsics.txt").rename(scene / "camera-intrinsics.txt")  # in the parent: found there
    (scene / "seq-02" / "camera-intrinsics.txt").unlink()
    source = open_sequence(scene)
    assert isinstance(source, ThreeDMatchSequence) and len(source) == 6
    assert source.intrinsics == frames.intrinsics
    np.testing.assert_allclose(source.poses, frames.poses, atol=1e-12)


def test_scannet_lost_poses_are_skipped_and_counted(recorded, tmp_path):
    frames, _, _ = recorded
    folder = write_scannet(frames, tmp_path / "scannet", lost={1, 4})
    source = ScanNetSequence(folder)
    assert len(source) == 4 and source.skipped == 2
    assert "2 with a NaN or infinite pose skipped" in source.description
    np.testing.assert_allclose(source.poses, frames.poses[[0, 2, 3, 5]], atol=1e-12)


def test_depth_scale_and_camera_options(recorded, tmp_path, capsys):
    frames, config, folders = recorded
    doubled = open_sequence(folders["redwood"], depth_scale=500.0)  # 500 units per metre: every depth twice as far
    first = frames.read(0).depth
    near = first < frames.intrinsics.far / 2 - 0.01
    np.testing.assert_allclose(doubled.read(0).depth[near], 2 * first[near], atol=2e-3)
    camera = "100,90,70.5,50.5,160,120"
    assert open_sequence(folders["replica"], camera=camera).intrinsics.fx == 100.0
    assert open_sequence(folders["3dmatch"], camera="7scenes").intrinsics.fx == 585.0
    with pytest.raises(SequenceError, match="unknown camera 'fr9'"):
        open_sequence(folders["scannet"], camera="fr9")
    # the bag reader takes no depth scale: said at once
    assert main(["run", "--sequence", str(folders["tum"]), "--tolerance", "0.01", "--no-eval", "--quiet",
                 "--frames", "1", "--out", str(tmp_path / "t")]) == 0
    assert main(["run", "--sequence", str(folders["replica"]), "--tolerance", "0.01", "--out", str(tmp_path / "r")]) == 2
    assert "Replica (NICE-SLAM) folder: --tolerance does not apply" in capsys.readouterr().err


def test_a_camera_recording_run_without_a_noise_model_learns_it(recorded, tmp_path, capsys):
    """No config and no --noise: every real camera has noise and its model is unknown, so the run learns it
    (noise = "auto", said on the console and in summary.json); --noise or a config names the model instead."""
    _, config, folders = recorded
    common = ["--tolerance", "0.01", "--no-eval", "--quiet", "--frames", "2"]
    assert main(["run", "--sequence", str(folders["tum"]), *common, "--out", str(tmp_path / "learnt")]) == 0
    assert "noise: auto (learnt from the run" in capsys.readouterr().out
    assert json.loads((tmp_path / "learnt" / "summary.json").read_text())["noise"] == "auto"
    assert main(["run", "--sequence", str(folders["tum"]), *common, "--noise", "kinect", "--out", str(tmp_path / "named")]) == 0
    assert json.loads((tmp_path / "named" / "summary.json").read_text())["noise"] == "kinect"
    assert main(["run", str(config), "--sequence", str(folders["tum"]), *common, "--out", str(tmp_path / "config")]) == 0
    assert json.loads((tmp_path / "config" / "summary.json").read_text())["noise"] == "none"  # as the config says


def test_scannet_colour_of_another_size_is_sampled_along_each_ray():
    from mabdi.camera import Intrinsics

    depth = Intrinsics(fx=100.0, fy=100.0, cx=80.0, cy=60.0, width=160, height=120)
    colour = Intrinsics(fx=300.0, fy=300.0, cx=240.0, cy=180.0, width=480, height=360)  # three times the resolution
    rows, columns = colour_lookup(depth, colour)
    # depth pixel centre u + 0.5 -> colour 3u + 1.5, the centre of colour pixel 3u + 1 (the middle of its three)
    np.testing.assert_array_equal(columns, 3 * np.arange(160) + 1)
    np.testing.assert_array_equal(rows, 3 * np.arange(120) + 1)


def _damage(folder, layout):
    """Break one file of the layout; returns the file's name and the words the error must have."""
    if layout == "3dmatch":
        file = folder / "frame-000002.pose.txt"
        lines = file.read_text().splitlines()
        lines[1] = "0 1 zero 0"
        file.write_text("\n".join(lines) + "\n")
        return f"{file}:2", "expected numbers"
    if layout == "redwood":
        file = folder / "trajectory.log"
        file.write_text("\n".join(file.read_text().splitlines()[:-2]) + "\n")  # the last entry cut short
        return str(file), "ends mid-entry"
    if layout == "scannet":
        file = folder / "intrinsic" / "intrinsic_depth.txt"
        file.write_text("131 0 79.5 0\n0 131\n0 0 1 0\n0 0 0 1\n")
        return f"{file}:2", "expected 3 numbers"
    if layout == "stray":
        file = folder / "odometry.csv"
        lines = file.read_text().splitlines()
        lines[2] = lines[2].replace(",", ", one,", 1)
        file.write_text("\n".join(lines) + "\n")
        return f"{file}:3", "expected numbers"
    file = folder / "traj.txt"
    lines = file.read_text().splitlines()
    lines[3] = " ".join(lines[3].split()[:15])
    file.write_text("\n".join(lines) + "\n")
    return f"{file}:4", "expected 16 numbers"


@pytest.mark.parametrize("layout", list(WRITERS))
def test_a_malformed_file_of_each_layout_is_named(recorded, tmp_path, layout, capsys):
    frames, _, _ = recorded
    folder = WRITERS[layout](frames, tmp_path / layout)
    where, words = _damage(folder, layout)
    with pytest.raises(SequenceError, match=words) as error:
        open_sequence(folder)
    assert where in str(error.value)
    assert main(["run", "--sequence", str(folder), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mabdi: error: ") and where in err and err.count("\n") == 1


def test_a_non_rigid_pose_and_a_missing_image_are_named(recorded, tmp_path):
    frames, _, _ = recorded
    folder = write_3dmatch(frames, tmp_path / "seq")
    (folder / "frame-000001.pose.txt").write_text("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(SequenceError, match=r"frame-000001\.pose\.txt: .*rigid|orthonormal"):
        open_sequence(folder)
    folder = write_redwood(frames, tmp_path / "redwood")
    (folder / "depth" / "000003.png").unlink()
    with pytest.raises(SequenceError, match="trajectory.log: 6 poses, but depth/ holds 5 images"):
        open_sequence(folder)
    (folder / "depth" / "000003.png").write_bytes(b"not a png")
    with pytest.raises(SequenceError, match="000003.png: cannot read"):
        open_sequence(folder).read(3)


def test_the_summary_names_the_layout(recorded, tmp_path):
    _, config, folders = recorded
    _run(config, folders["scannet"], tmp_path / "out")
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["frames"] == 6


def test_scannet_colour_of_another_size_is_registered_to_the_depth(recorded, tmp_path):
    """A colour camera three times the depth camera's resolution (same centre and axes): each depth pixel takes
    the middle one of its 3x3 colour pixels, so a colour image made by repeating each pixel 3x3 reads back as
    the original. A JPEG six times larger is decoded reduced (JPEG's DCT scaling, never below the depth
    image's size) and sampled with its intrinsics scaled alike: it matches within JPEG's error."""
    from PIL import Image

    from mabdi.camera import Intrinsics

    frames, _, _ = recorded
    folder = write_scannet(FrameList([frames.read(i) for i in range(2)]), tmp_path / "scannet")
    depth = frames.intrinsics
    colour_camera = Intrinsics(fx=3 * depth.fx, fy=3 * depth.fy, cx=3 * depth.cx, cy=3 * depth.cy, width=3 * depth.width, height=3 * depth.height)
    (folder / "intrinsic" / "intrinsic_color.txt").write_text(
        f"{colour_camera.fx} 0 {colour_camera.cx - 0.5} 0\n0 {colour_camera.fy} {colour_camera.cy - 0.5} 0\n0 0 1 0\n0 0 0 1\n"
    )
    rng = np.random.default_rng(3)
    v, u = np.mgrid[0 : depth.height, 0 : depth.width]
    originals = []
    (folder / "color").mkdir()
    for i in range(2):
        original = rng.integers(0, 256, (depth.height, depth.width, 3), dtype=np.uint8)
        originals.append(original)
        Image.fromarray(original.repeat(3, axis=0).repeat(3, axis=1)).save(folder / "color" / f"{i}.png")
    source = ScanNetSequence(folder)
    for i in range(2):
        np.testing.assert_array_equal(source.read(i).colour, originals[i])
    smooth = np.stack([u * 255 // depth.width, v * 255 // depth.height, (u + v) % 256], axis=-1).astype(np.uint8)
    for i in range(2):
        (folder / "color" / f"{i}.png").unlink()
        Image.fromarray(smooth.repeat(6, axis=0).repeat(6, axis=1)).save(folder / "color" / f"{i}.jpg", quality=95)
    big = Intrinsics(fx=6 * depth.fx, fy=6 * depth.fy, cx=6 * depth.cx, cy=6 * depth.cy, width=6 * depth.width, height=6 * depth.height)
    (folder / "intrinsic" / "intrinsic_color.txt").write_text(
        f"{big.fx} 0 {big.cx - 0.5} 0\n0 {big.fy} {big.cy - 0.5} 0\n0 0 1 0\n0 0 0 1\n"
    )
    colour = ScanNetSequence(folder).read(1).colour  # a 960x720 JPEG, decoded at a quarter (240x180 >= 160x120)
    error = np.abs(colour.astype(int) - smooth.astype(int))
    assert np.median(error) <= 3 and np.percentile(error, 99) <= 40, (np.median(error), np.percentile(error, 99))


def _mp4_with_a_video_track(path, width, height):
    """The boxes an MP4's header holds, down to a track header (``tkhd``) of ``width`` x ``height`` (16.16 fixed point)."""
    import struct

    def box(kind, body):
        return struct.pack(">I4s", 8 + len(body), kind) + body

    tkhd = box(b"tkhd", bytes(76) + struct.pack(">II", width << 16, height << 16))
    # the video's data first and the header box last, as a recorder that writes it at the end leaves them
    path.write_bytes(box(b"ftyp", b"isom" + bytes(4)) + box(b"mdat", bytes(5000)) + box(b"moov", box(b"trak", tkhd)))


def test_stray_camera_is_the_colour_cameras_scaled_to_the_depth(recorded, tmp_path):
    """camera_matrix.csv is the colour camera's (ARKit's 1920 x 1440 capture: 12 times the 160 x 120 depth
    here); the depth camera is it scaled by the widths' ratio, the colour width read from rgb.mp4's header, or
    without one the capture width whose centre K's principal point is."""
    frames, _, _ = recorded
    folder = write_stray(frames, tmp_path / "stray")
    camera = frames.intrinsics
    k = np.array([[camera.fx * 12, 0, camera.cx * 12 - 0.5], [0, camera.fy * 12, camera.cy * 12 - 0.5], [0, 0, 1]])
    (folder / "camera_matrix.csv").write_text("\n".join(", ".join(f"{v:.10g}" for v in row) for row in k) + "\n")
    got = open_sequence(folder).intrinsics
    assert (got.width, got.height) == (160, 120)
    np.testing.assert_allclose([got.fx, got.fy, got.cx, got.cy], [camera.fx, camera.fy, camera.cx, camera.cy], atol=1e-9)
    _mp4_with_a_video_track(folder / "rgb.mp4", 1440, 1080)  # the video says 1440 wide: K is for that size
    got = open_sequence(folder).intrinsics
    np.testing.assert_allclose([got.fx, got.cx], [camera.fx * 12 * 160 / 1440, camera.cx * 12 * 160 / 1440], atol=1e-9)
    (folder / "rgb.mp4").unlink()
    k[0, 2] = 800.0  # twice cx is near no capture width: refused, naming the file
    (folder / "camera_matrix.csv").write_text("\n".join(", ".join(f"{v:.10g}" for v in row) for row in k) + "\n")
    with pytest.raises(SequenceError, match=r"camera_matrix\.csv: no rgb\.mp4 .* --camera"):
        open_sequence(folder)
    assert open_sequence(folder, camera="100,100,80,60,160,120").intrinsics.fx == 100.0


def test_stray_depth_below_the_confidence_asked_is_no_return(recorded, tmp_path, capsys):
    frames, _, _ = recorded
    levels = np.indices(frames.intrinsics.shape).sum(axis=0) % 3  # 0, 1, 2 in diagonal stripes
    folder = write_stray(frames, tmp_path / "stray", confidence=lambda index: levels)
    valid = np.isfinite(frames.read(2).depth)
    for least in (0, 1, 2):
        source = StraySequence(folder, min_confidence=least)
        got = np.isfinite(source.read(2).depth)
        np.testing.assert_array_equal(got, valid & (levels >= least))
    assert open_sequence(folder).min_confidence == stray.MIN_CONFIDENCE == 1
    with pytest.raises(SequenceError, match="min_confidence must be 0, 1 or 2"):
        StraySequence(folder, min_confidence=3)
    # the run's option: the image's right half of low confidence is meshed only with 0 asked; a layout without
    # confidence refuses it
    halves = np.where(np.arange(frames.intrinsics.width) < frames.intrinsics.width // 2, 2, 0)
    folder = write_stray(frames, tmp_path / "halves", confidence=lambda index: np.broadcast_to(halves, frames.intrinsics.shape))
    common = ["--no-registration", "--no-eval", "--quiet", "--frames", "2"]
    sizes = {}
    for least in (0, 2):
        out = tmp_path / f"run{least}"
        assert main(["run", "--sequence", str(folder), "--min-confidence", str(least), *common, "--out", str(out)]) == 0
        sizes[least] = read_mesh_file(out / "world_mesh.vtp").GetNumberOfCells()
    assert 0 < sizes[2] < sizes[0]
    other = write_scannet(FrameList([frames.read(0)]), tmp_path / "scannet")
    assert main(["run", "--sequence", str(other), "--min-confidence", "2", "--out", str(tmp_path / "s")]) == 2
    assert "ScanNet folder: --min-confidence does not apply" in capsys.readouterr().err


def test_stray_odometry_as_newer_apps_write_it_and_a_frame_without_a_pose(recorded, tmp_path):
    """Newer exports add the colour camera's fx, fy, cx, cy and two empty distortion columns to each row; a
    depth image whose frame number no row has is named."""
    frames, _, _ = recorded
    folder = write_stray(frames, tmp_path / "stray")
    lines = (folder / "odometry.csv").read_text().splitlines()
    wide = [lines[0] + ", fx, fy, cx, cy, distortion_center_x, distortion_center_y"]
    wide += [line + ", 1597.9, 1597.9, 955.4, 717.7, , " for line in lines[1:]]
    (folder / "odometry.csv").write_text("\n".join(wide) + "\n")
    source = open_sequence(folder)
    np.testing.assert_allclose(source.poses, frames.poses, atol=1e-12)
    assert np.all(np.diff(source.timestamps) > 0)
    (folder / "odometry.csv").write_text("\n".join(wide[:4] + wide[5:]) + "\n")  # frame 3's row gone
    with pytest.raises(SequenceError, match=r"depth/000003\.png: no row of .*odometry\.csv has its frame number 3"):
        open_sequence(folder)
