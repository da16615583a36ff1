"""A recording whose pose clock runs apart from its depth clock (motion capture beside a Kinect): the offset is
learnt from the depth, applied where it stands out, and the run then keeps its static map; a recording whose
clocks agree is left as it is."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mabdi.sources.tum import TumSequence, write_tum_trajectory
from mabdi.stages.time_offset import learn_recording_time_offset

REPO = Path(__file__).resolve().parents[1]
RATE = 30.0  # frames a second
FRAMES = 60
OFFSET = 0.02  # s: the depth stamped this much before the pose clock's time of the same instant
START = 1000.0  # s: the clocks' time at the first frame


def _swinging_camera(times: np.ndarray) -> np.ndarray:
    """(N, 4, 4) world_from_camera: a camera 2.4 m from the table, panning +-12 degrees at 0.8 Hz and nodding
    +-5 degrees at 1.3 Hz (its turning rate changes all the time, as a hand-held camera's does)."""
    poses = np.empty((len(times), 4, 4))
    centre = np.array([2.4, 0.3, 1.6])
    target = np.array([0.0, 0.0, 0.9])
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    base = np.stack([right, down, forward], axis=1)  # camera axes (x right, y down, z forward) in the world
    for k, t in enumerate(times):
        pan = np.radians(12.0) * np.sin(2 * np.pi * 0.8 * t)
        nod = np.radians(5.0) * np.sin(2 * np.pi * 1.3 * t + 0.5)
        turn = Rotation.from_rotvec([0.0, 0.0, pan]).as_matrix() @ base @ Rotation.from_rotvec([nod, 0.0, 0.0]).as_matrix()
        poses[k] = np.eye(4)
        poses[k, :3, :3] = turn
        poses[k, :3, 3] = centre
    return poses


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> tuple[Path, Path]:
    """The table seen by a camera swinging in place (``[path] kind = "trajectory"``), recorded as a TUM
    folder with a 100 Hz pose stream; then the same folder with the depth stamped ``OFFSET`` early."""
    from mabdi.cli import main

    folder = tmp_path_factory.mktemp("clocks")
    times = START + np.arange(FRAMES) / RATE
    write_tum_trajectory(folder / "path.txt", times, _swinging_camera(times))
    text = (REPO / "scenes" / "table.toml").read_text()
    text = text.replace("frames = 30", f"frames = {FRAMES}")
    start = text.index("[path]")
    end = text.index("\n[", start)  # the next table
    text = text[:start] + '[path]\nkind = "trajectory"\nfile = "path.txt"\n' + text[end:]
    (folder / "swing.toml").write_text(text)
    agreeing = folder / "agreeing"
    assert main(["record", str(folder / "swing.toml"), "--format", "tum", "--out", str(agreeing)]) == 0
    stream = START + np.arange(-0.2, FRAMES / RATE + 0.2, 0.01)  # a motion-capture system's 100 Hz
    write_tum_trajectory(agreeing / "groundtruth.txt", stream, _swinging_camera(stream))
    apart = folder / "apart"
    apart.mkdir()
    for item in agreeing.iterdir():
        target = apart / item.name
        if item.name == "depth.txt":
            lines = [
                line if line.startswith("#") or not line.strip() else f"{float(line.split()[0]) - OFFSET:.6f} {line.split()[1]}"
                for line in item.read_text().splitlines()
            ]
            target.write_text("\n".join(lines) + "\n")
        else:
            target.symlink_to(item)
    return agreeing, apart


def test_the_offset_is_learnt_from_the_depth(recordings):
    agreeing, apart = recordings
    found = learn_recording_time_offset(TumSequence(apart))
    assert found is not None and found.applied, found
    assert found.seconds == pytest.approx(OFFSET, abs=0.003)
    assert found.error_after < 0.5 * found.error_before
    kept = learn_recording_time_offset(TumSequence(agreeing))
    assert kept is not None and not kept.applied, kept
    assert abs(kept.seconds) <= 0.003
    # read with the offset, the frames get the poses they were taken at
    retimed = TumSequence(apart).with_time_offset(found.seconds)
    truth = TumSequence(agreeing).poses
    turned = Rotation.from_matrix(np.linalg.inv(truth[:, :3, :3]) @ retimed.poses[:, :3, :3]).magnitude()
    assert np.degrees(turned).max() < 0.15


def test_a_still_camera_tells_no_offset():
    """A constant motion gives the same relative poses at any offset: nothing to learn from, nothing applied."""
    from mabdi.stages.time_offset import choose_pairs

    times = np.arange(60) / RATE
    stream = np.arange(-0.2, 2.2, 0.01)
    still = np.repeat(np.eye(4)[None], len(stream), axis=0)
    first, second = choose_pairs(times, stream, still)
    assert len(first) == 0
    spinning = np.repeat(np.eye(4)[None], len(stream), axis=0)
    spinning[:, :3, :3] = Rotation.from_rotvec(np.outer(stream, [0.0, 0.0, np.radians(30.0)])).as_matrix()
    first, second = choose_pairs(times, stream, spinning)
    assert len(first) == 0


def _run(folder: Path, out: Path, *extra: str) -> tuple[dict, str]:
    import contextlib
    import io

    from mabdi.cli import main

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["run", "--sequence", str(folder), "--out", str(out), "--quiet", "--no-eval", *extra]) == 0
    return json.loads((out / "summary.json").read_text()), printed.getvalue()


def test_a_run_learns_the_offset_and_keeps_its_static_map(recordings, tmp_path):
    """The clocks 20 ms apart while the camera swings: with the recording's pairing the frames are placed up to
    a degree off. Registration against exact synthetic depth corrects that (a real camera's map is too noisy for
    it to: the recording's poses are kept); meshed at the given poses, removal takes part of the static table.
    With the offset learnt, registration has nothing to correct and removal takes almost nothing."""
    _, apart = recordings
    learnt, printed = _run(apart, tmp_path / "auto")
    assert "poses taken +20" in printed and "the pose clock's offset learnt from the depth" in printed
    assert "poses taken +20" in learnt["source"]
    paired, printed = _run(apart, tmp_path / "paired", "--time-offset", "0")
    assert "pose clock" not in printed
    assert learnt["registration"]["median_correction_deg"] < 0.15
    assert paired["registration"]["median_correction_deg"] > 0.5
    learnt, learnt_printed = _run(apart, tmp_path / "auto_given", "--no-registration")
    paired, paired_printed = _run(apart, tmp_path / "paired_given", "--no-registration", "--time-offset", "0")
    made = learnt["cells"] + learnt["cells_removed"]
    assert paired["cells_removed"] > 4 * max(learnt["cells_removed"], 25), (paired["cells_removed"], learnt["cells_removed"])
    assert learnt["cells_removed"] <= 0.01 * made
    # the run says what removal took, and on a recording that took much, what may have taken it
    made = paired["cells"] + paired["cells_removed"]
    assert f"removal: {paired['cells_removed']:,} faces removed ({100 * paired['cells_removed'] / made:.1f}% of the {made:,} made)" in paired_printed
    assert "if nothing in the scene moved" in paired_printed and "clock" in paired_printed
    assert "removal: " in learnt_printed and "if nothing in the scene moved" not in learnt_printed


def test_the_option_is_checked_and_named(recordings, tmp_path, capsys):
    from mabdi.cli import main

    _, apart = recordings
    with pytest.raises(SystemExit):
        main(["run", "--sequence", str(apart), "--time-offset", "soon"])
    assert "expected auto or a number of seconds, got 'soon'" in capsys.readouterr().err
    assert main(["run", "scenes/table.toml", "--time-offset", "0.01"]) == 2
    assert "--time-offset is for recorded sequences" in capsys.readouterr().err


def test_a_resumed_run_reads_the_recording_with_the_offset_its_start_learnt(recordings, tmp_path, monkeypatch, capsys):
    from mabdi.cli import main
    from mabdi.loop import run_pipeline
    from mabdi.stages import time_offset

    _, apart = recordings
    out = tmp_path / "resumed"
    stop = run_pipeline.InterruptCheck.on_frame

    def interrupt_after_frame_two(self, pipeline, record):
        if record.frame == 2:  # the offset learnt over the 40 frames run
            raise KeyboardInterrupt
        stop(self, pipeline, record)

    monkeypatch.setattr(run_pipeline.InterruptCheck, "on_frame", interrupt_after_frame_two)
    args = ["run", "--sequence", str(apart), "--frames", "40", "--set", "output.checkpoint_every=1", "--no-eval", "--quiet"]
    assert main([*args, "--out", str(out)]) == 130
    monkeypatch.setattr(run_pipeline.InterruptCheck, "on_frame", stop)

    def not_again(*args, **kwargs):
        raise AssertionError("the resume learnt the offset again")

    monkeypatch.setattr(time_offset, "learn_time_offset", not_again)
    capsys.readouterr()
    assert main(["run", "--resume", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 40 and "poses taken +20" in summary["source"]


@pytest.mark.parametrize("pose_topic", ["/tf", "/camera/pose"])
def test_a_bag_learns_the_offset_of_its_pose_stream(recordings, tmp_path, pose_topic):
    """The same frames as a ROS 2 bag, each image stamped with the pose its stamp gives (the clocks 20 ms apart):
    the offset is learnt from /tf chained (sampled every 10 ms) or from the PoseStamped topic, and the bag read
    with it gives the images the poses they were taken at."""
    from mabdi.sources.frames import FrameList
    from mabdi.sources.rosbag2 import Rosbag2Sequence, write_rosbag2

    agreeing, apart = recordings
    recorded = TumSequence(apart)
    frames = [recorded.read(i) for i in range(len(recorded))]
    bag = write_rosbag2(FrameList(frames, "clocks apart"), tmp_path / "bag")
    sequence = Rosbag2Sequence(bag, pose_topic=pose_topic, tolerance=0.025)
    found = learn_recording_time_offset(sequence)
    assert found is not None and found.applied and found.seconds == pytest.approx(OFFSET, abs=0.004), found
    retimed = sequence.with_time_offset(found.seconds)
    assert retimed.pose_source == pose_topic and "poses taken +" in retimed.description
    truth = TumSequence(agreeing).poses
    turned = Rotation.from_matrix(np.linalg.inv(truth[1:-1, :3, :3]) @ retimed.poses[1:-1, :3, :3]).magnitude()
    before = Rotation.from_matrix(np.linalg.inv(truth[1:-1, :3, :3]) @ sequence.poses[1:-1, :3, :3]).magnitude()
    assert np.degrees(turned).max() < 0.3 < np.degrees(before).max()


def test_key_frames_with_a_pose_each_are_run_as_paired(recordings, tmp_path):
    """A folder of key frames a few hundred milliseconds apart, each with the pose of its own timestamp (as
    trajectories of key frames are published): no pose between the frames to move the pairing to, so no offset
    is learnt or applied, the run says why, and every frame keeps its pose."""
    agreeing, _ = recordings
    folder = tmp_path / "key_frames"
    folder.mkdir()
    lines = [line for line in (agreeing / "depth.txt").read_text().splitlines() if line.strip() and not line.startswith("#")]
    kept = lines[::4]
    (folder / "depth.txt").write_text("# depth maps\n" + "\n".join(kept) + "\n")
    times = np.array([float(line.split()[0]) for line in kept])
    write_tum_trajectory(folder / "groundtruth.txt", times, _swinging_camera(times))
    for item in agreeing.iterdir():
        if item.name not in ("depth.txt", "groundtruth.txt", "rgb.txt"):
            (folder / item.name).symlink_to(item)
    found = learn_recording_time_offset(TumSequence(folder))
    assert found is not None and not found.applied
    assert found.note().startswith("poses taken at the depth timestamps (a pose every 133 ms (median)")
    summary, printed = _run(folder, tmp_path / "run")
    assert summary["frames"] == len(kept)
    assert "a pose every 133 ms" in printed
