"""Poses that disagree with the depth (camera_from_world poses, a wrong depth scale): the run says so once,
naming the likely causes; a recording whose poses fit stays quiet."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mabdi.stages.registration_check import (
    MAX_CORRECTION_DEG, MAX_CORRECTION_M, MIN_STRETCH, pose_excursion, poses_disagree,
)

REPO = Path(__file__).resolve().parents[1]
WARNING = "the poses disagree with the depth"


def test_the_rule_judges_registered_shares_and_median_corrections():
    """Fewer than a third of the judged frames registered, or a median correction beyond 5 cm / 2 degrees."""
    good = ["no_map", "few_points", "few_points"] + ["registered"] * 7
    assert poses_disagree(good, [0.0] * 3 + [0.002] * 7, [0.0] * 3 + [0.01] * 7) is None
    failing = ["no_map"] + ["few_points"] * 5
    message = poses_disagree(failing, [0.0] * 6, [0.0] * 6)
    assert message and "only 0 of 5 frames registered" in message
    assert "camera_from_world" in message and "--depth-scale" in message and "\n" not in message
    assert poses_disagree(["no_map"] + ["few_points"] * 3, [0.0] * 4, [0.0] * 4) is None, "too few frames to judge"
    # frames that see through the map (a tenth or more of their pixels: inverted poses, a wrong scale) are blamed;
    # frames that fit it but give the registration too few samples (a small image) see through almost none
    through = [0.0] + [0.2] * 5
    assert poses_disagree(failing, [0.0] * 6, [0.0] * 6, through) is not None
    assert poses_disagree(failing, [0.0] * 6, [0.0] * 6, [0.0] + [0.0003] * 5) is None
    # four of nine registered (a map of merged faces lets the first few frames of a wrong scale register near
    # their poses): blamed only where a tenth of the pixels see through the map
    some = ["no_map"] + ["registered"] * 4 + ["few_inliers"] * 5
    small = [0.0] + [0.02] * 9
    assert poses_disagree(some, small, [0.0] * 10, [0.0] + [0.14] * 9) is not None
    assert poses_disagree(some, small, [0.0] * 10, [0.0] + [0.08] * 9) is None
    assert poses_disagree(["no_map"] + ["registered"] * 5 + ["few_inliers"] * 4, small, [0.0] * 10, [0.0] + [0.14] * 9) is None
    assert poses_disagree(["off"] * 10, [0.0] * 10, [0.0] * 10) is None, "registration off: nothing judged"
    moved = ["no_map"] + ["registered"] * 6
    far = [0.0] + [0.152] * 6
    message = poses_disagree(moved, far, [0.0] + [0.3] * 6)
    assert message and "152 mm" in message and "median of 6 registered frames" in message
    assert poses_disagree(moved, [0.0] + [0.9 * MAX_CORRECTION_M] * 6, [0.0] * 7) is None
    assert poses_disagree(moved, [0.0] * 7, [0.0] + [1.1 * MAX_CORRECTION_DEG] * 6) is not None


def _small_table(folder: Path) -> Path:
    """Run 1's table seen by a 160 x 120 camera over a quarter circle in 10 frames (quick, and frames overlap)."""
    text = (REPO / "scenes" / "table.toml").read_text()
    text = text.replace("frames = 30", "frames = 10")
    text = text.replace('noise = "none"', 'noise = "none"\nwidth = 160\nheight = 120\nfx = 130.0\nfy = 130.0\ncx = 80.0\ncy = 60.0')
    text = text.replace("look_to = [0.0, 0.0, 0.9]", "look_to = [0.0, 0.0, 0.9]\nturns = 0.25")
    config = folder / "small_table.toml"
    config.write_text(text)
    return config


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    from mabdi.cli import main

    folder = tmp_path_factory.mktemp("poses")
    assert main(["record", str(_small_table(folder)), "--format", "tum", "--out", str(folder / "tum")]) == 0
    return folder / "tum"


def _inverted(recording: Path, out: Path) -> Path:
    """The recording with every pose written as camera_from_world (the inverse of what TUM files hold)."""
    shutil.copytree(recording, out)
    lines = []
    for line in (recording / "groundtruth.txt").read_text().splitlines():
        if line.startswith("#") or not line.strip():
            lines.append(line)
            continue
        stamp, *values = line.split()
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_quat([float(v) for v in values[3:]]).as_matrix()
        pose[:3, 3] = [float(v) for v in values[:3]]
        inverse = np.linalg.inv(pose)
        quaternion = Rotation.from_matrix(inverse[:3, :3]).as_quat()
        lines.append(" ".join([stamp, *(repr(float(v)) for v in (*inverse[:3, 3], *quaternion))]))
    (out / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    return out


def _run(sequence: Path, out: Path, capsys, *options: str) -> str:
    from mabdi.cli import main

    code = main(["run", "--sequence", str(sequence), "--noise", "none", "--out", str(out), "--no-eval", "--quiet", *options])
    captured = capsys.readouterr()
    assert code == 0, captured.err[-2000:]
    return captured.err


def test_a_stretch_of_frames_moved_far_is_named_though_the_median_is_small():
    """Registration that leaves good poses for a stretch of frames (a real recording's 15 frames in a row, up to
    117 mm, out of 648) leaves the median correction at millimetres; the stretch is named with its frames and
    its largest correction. Shorter stretches, or ones broken by a frame within the bounds, are not."""
    frames = np.arange(100, 200)
    metres = np.full(100, 0.002)
    metres[30:45] = np.linspace(0.06, 0.117, 15)
    statuses = ["registered"] * 100
    assert poses_disagree(statuses, metres, np.zeros(100)) is None  # the median hides it
    message = pose_excursion(frames, statuses, metres, np.zeros(100))
    assert message and "frames 130-144" in message and "15 frames in a row" in message and "117 mm" in message
    assert "--no-registration" in message and "\n" not in message
    short = np.full(100, 0.002)
    short[30 : 30 + MIN_STRETCH - 1] = 0.08
    assert pose_excursion(frames, statuses, short, np.zeros(100)) is None
    broken = metres.copy()
    broken[37] = 0.01  # back within the bounds for a frame: two stretches of 7
    assert pose_excursion(frames, statuses, broken, np.zeros(100)) is None
    turned = np.zeros(100)
    turned[50:50 + MIN_STRETCH] = MAX_CORRECTION_DEG + 0.5
    assert "frames 150-159" in pose_excursion(frames, statuses, np.full(100, 0.002), turned)
    unregistered = statuses[:30] + ["not_converged"] * 15 + statuses[45:]
    assert pose_excursion(frames, unregistered, metres, np.zeros(100)) is None  # frames meshed at their given poses


def test_camera_from_world_poses_are_named_and_poses_that_fit_are_quiet(recording, tmp_path, capsys):
    """The recording as written runs quietly; its poses inverted, the run warns once, naming both causes."""
    assert WARNING not in _run(recording, tmp_path / "run", capsys)
    err = _run(_inverted(recording, tmp_path / "inverted"), tmp_path / "inverted_run", capsys)
    assert err.count(WARNING) == 1, err
    line = next(line for line in err.splitlines() if WARNING in line)
    assert line.startswith("mabdi: warning: ") and "camera_from_world" in line and "--depth-scale" in line


def test_a_wrong_depth_scale_is_named_and_a_simulation_stating_its_pose_noise_is_not(recording, tmp_path, capsys):
    """The depth read at 4000 units per metre, written at 5000 (TUM's): every depth 25% long, the run warns once.
    Drifting simulated poses that this small camera cannot register either (1 cm and 0.5 degrees per
    sqrt(metre)) are not blamed: the simulator states its pose noise, and has no pose file or depth scale."""
    from mabdi.cli import main

    err = _run(recording, tmp_path / "run", capsys, "--depth-scale", "4000")
    assert err.count(WARNING) == 1, err
    assert "--depth-scale" in err and "camera_from_world" in err

    drift = ["--set", "sensor.pose_noise.drift_translation=0.01", "--set", "sensor.pose_noise.drift_rotation=0.5"]
    config = _small_table(tmp_path)
    assert main(["run", str(config), "--out", str(tmp_path / "simulated"), "--no-eval", "--quiet", *drift]) == 0
    assert WARNING not in capsys.readouterr().err



def test_a_pose_jump_is_found_beside_steady_steps_and_fast_smooth_motion_is_not():
    """A step over 4 times the larger of the steps beside it (and over 2 cm or 1 degree) is a jump; motion that
    speeds up smoothly is not; the warning names a jump only where the frames after it removed much."""
    from mabdi.stages.registration_check import JUMP_FRAMES, jumps_that_removed, pose_jumps

    poses = np.tile(np.eye(4), (30, 1, 1))
    poses[:, 0, 3] = 0.007 * np.arange(30)  # 7 mm a frame
    poses[12:, 1, 3] += 0.036  # the source jumps 36 mm between frames 11 and 12
    turned = poses.copy()
    turned[20:, :3, :3] = Rotation.from_euler("z", 3.0, degrees=True).as_matrix()  # and turns 3 degrees at 20
    found = pose_jumps(turned)
    assert [f[0] for f in found] == [12, 20]
    frame, metres, degrees, beside_m, _ = found[0]
    assert metres == pytest.approx(np.hypot(0.007, 0.036)) and beside_m == pytest.approx(0.007) and degrees == 0.0
    assert found[1][2] == pytest.approx(3.0)
    faster = np.tile(np.eye(4), (30, 1, 1))
    faster[:, 0, 3] = np.cumsum(0.005 * 1.3 ** np.arange(30) / 1.3**15)  # speeding up by 30% a frame
    assert pose_jumps(faster) == []
    unknown = poses.copy()
    unknown[11] = np.nan  # a frame not run: the steps beside it are not known
    assert 12 not in [f[0] for f in pose_jumps(unknown)]

    removed = np.zeros(30)
    removed[12 : 12 + JUMP_FRAMES] = 400
    removed[25] = 100
    message = jumps_that_removed(poses, removed)
    assert message and "at frame 12 (37 mm" in message and "1,200 faces" in message and "92% of the 1,300" in message
    assert "\n" not in message and "--no-removal" in message
    removed[25] = 10_000  # most of the run's removal elsewhere: the jump is not what took the map
    assert jumps_that_removed(poses, removed) is None
    assert jumps_that_removed(poses, np.zeros(30)) is None
    # removal that asks four frames (a real sensor's) takes the map two frames later: the window follows it
    late = np.zeros(30)
    late[12 + JUMP_FRAMES : 12 + JUMP_FRAMES + 2] = 600
    assert jumps_that_removed(poses, late) is None
    assert "in 5 frames" in jumps_that_removed(poses, late, window=5)


def _jumped(recording: Path, out: Path, frame: int, drop: float) -> Path:
    """The recording with every pose from ``frame`` on moved ``drop`` metres down (a pose source that jumps)."""
    shutil.copytree(recording, out)
    lines, index = [], 0
    for line in (recording / "groundtruth.txt").read_text().splitlines():
        if line.startswith("#") or not line.strip():
            lines.append(line)
            continue
        stamp, *values = line.split()
        if index >= frame:
            values[2] = repr(float(values[2]) - drop)
        lines.append(" ".join([stamp, *values]))
        index += 1
    (out / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    return out


def test_a_pose_jump_that_removal_follows_is_named(tmp_path, capsys):
    """A recording of a camera that barely moves, whose poses drop 30 cm at frame 5 (its steps 5 cm): the frames after see through
    the map and removal takes it; the run says where the poses jumped. The same recording without the jump
    is quiet."""
    from mabdi.cli import main

    text = _small_table(tmp_path).read_text().replace("turns = 0.25", "turns = 0.02")
    config = tmp_path / "still_table.toml"
    config.write_text(text)
    assert main(["record", str(config), "--format", "tum", "--out", str(tmp_path / "tum")]) == 0
    capsys.readouterr()
    jump = "the given poses jump at frame 5"
    assert jump not in _run(tmp_path / "tum", tmp_path / "steady", capsys, "--no-registration")
    err = _run(_jumped(tmp_path / "tum", tmp_path / "jumped", 5, 0.3), tmp_path / "jumped_run", capsys, "--no-registration")
    assert err.count(jump) == 1, err
    line = next(line for line in err.splitlines() if jump in line)
    # a recording's removal asks four frames: the five from the jump on are counted
    assert line.startswith("mabdi: warning: ") and "faces were removed in 5 frames" in line
