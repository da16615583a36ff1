"""`mabdi run --sequence` on small recordings: --frames and [run] frames, the hints of an empty map and of
depth dropped by near and far, noise = "auto" under a config that leaves it unset, and --camera's checks."""

from __future__ import annotations

import csv
import json
import re
import shutil

import numpy as np
import pytest

from mabdi.cli import main
from mabdi.loop.run_pipeline import InterruptCheck

SMALL = """
[run]
name = "small"
frames = 4
seed = 1

[sensor]
noise = "none"

[sensor.camera]
width = 80
height = 60
fx = 65.625
fy = 65.625
cx = 40.0
cy = 30.0

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
"""

#: A config for runs on the recording that names no noise model and no frames (the user's own settings file).
NO_NOISE = """
[classifier]
enabled = true

[surface]
method = "pixel_grid"
"""

FAST = ["--quiet", "--no-eval", "--no-registration", "--surface", "pixel_grid"]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A 4-frame TUM folder of a small table scene (80 x 60 pixels; depths 1.6 .. 4 m)."""
    root = tmp_path_factory.mktemp("recordings")
    config = root / "small.toml"
    config.write_text(SMALL)
    assert main(["record", str(config), "--format", "tum", "--out", str(root / "tum")]) == 0
    return root / "tum"


def _copy_with_camera(recording, tmp_path, **camera) -> object:
    """The recording with its mabdi.toml [camera] keys replaced (near, far)."""
    folder = tmp_path / "copy"
    shutil.copytree(recording, folder)
    text = (folder / "mabdi.toml").read_text()
    for key, value in camera.items():
        text = re.sub(rf"(?m)^{key} = .*$", f"{key} = {value}", text)
    (folder / "mabdi.toml").write_text(text)
    return folder


def _summary(out) -> dict:
    return json.loads((out / "summary.json").read_text())


def _rows(out) -> list[dict]:
    with open(out / "metrics.csv") as stream:
        return list(csv.DictReader(stream))


# ---------------------------------------------------------------------------
# 1. --frames and [run] frames with --sequence


def test_frames_runs_the_first_frames_of_a_recording(recording, tmp_path, capsys):
    out = tmp_path / "two"
    assert main(["run", "--sequence", str(recording), "--frames", "2", *FAST, "--out", str(out)]) == 0
    assert _summary(out)["frames"] == 2
    assert [int(row["frame"]) for row in _rows(out)] == [0, 1]
    assert np.load(out / "poses.npy").shape == (2, 4, 4)
    assert "its first 2 frames run" in capsys.readouterr().out


def test_run_frames_of_a_config_applies_to_a_recording(recording, tmp_path, capsys):
    config = tmp_path / "three.toml"
    config.write_text("[run]\nframes = 3\n" + NO_NOISE)
    out = tmp_path / "three"
    assert main(["run", str(config), "--sequence", str(recording), *FAST, "--out", str(out)]) == 0
    assert _summary(out)["frames"] == 3
    assert f"note: run.frames = 3 ({config}) runs the first 3 of the recording's 4 frames" in capsys.readouterr().out


def test_frames_beyond_the_recording_runs_them_all_with_a_note(recording, tmp_path, capsys):
    out = tmp_path / "all"
    assert main(["run", "--sequence", str(recording), "--frames", "9", *FAST, "--out", str(out)]) == 0
    assert _summary(out)["frames"] == 4
    assert "note: --frames 9, but the recording has 4 frames: all 4 are run" in capsys.readouterr().out


def test_a_resumed_recording_run_keeps_its_frames(recording, tmp_path, monkeypatch):
    out = tmp_path / "resumed"
    stop = InterruptCheck.on_frame

    def interrupt_after_frame_one(self, pipeline, record):
        if record.frame == 1:
            raise KeyboardInterrupt
        stop(self, pipeline, record)

    monkeypatch.setattr(InterruptCheck, "on_frame", interrupt_after_frame_one)
    args = ["run", "--sequence", str(recording), "--frames", "3", "--set", "output.checkpoint_every=1", *FAST]
    assert main([*args, "--out", str(out)]) == 130
    monkeypatch.setattr(InterruptCheck, "on_frame", stop)
    assert main(["run", "--resume", str(out), "--quiet"]) == 0
    summary = _summary(out)
    assert summary["frames"] == 3
    assert summary["depth_returns"]["frames"] == 3  # the frames before the checkpoint are counted too


# ---------------------------------------------------------------------------
# 2. An empty map says what near, far and the depth's unit dropped


def test_depth_in_the_wrong_unit_names_near_and_the_depth_scale(recording, tmp_path, capsys):
    out = tmp_path / "unit"
    # 50000 units per metre for TUM's 5000: every depth ten times too near (0.16 .. 0.4 m, all nearer than 0.5 m)
    assert main(["run", "--sequence", str(recording), "--depth-scale", "50000", *FAST, "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "the map is empty" in err
    assert "nearer than near (0.5 m)" in err
    assert re.search(r"the depth values run 0\.1\d* \.\. 0\.[34]\d* m", err)
    assert "--depth-scale" in err and "50000 units per metre here" in err
    assert "objects' positions" not in err and "too few points per voxel" not in err
    counts = _summary(out)["depth_returns"]
    assert counts["returns"] == 0 and counts["nearer_than_near"] > 0 and counts["near"] == 0.5


def test_close_range_depth_under_the_near_plane_is_named_not_the_surface_filter(recording, tmp_path, capsys):
    """The tour's case: most of the depth nearer than near, a few returns left, no triangles: the warning
    spoke of too few points per voxel; it names near, the share it dropped and where near is set."""
    folder = _copy_with_camera(recording, tmp_path, near="3.6")
    out = tmp_path / "near"
    assert main(["run", "--sequence", str(folder), *FAST, "--out", str(out)]) == 1
    err = capsys.readouterr().err
    counts = _summary(out)["depth_returns"]
    assert counts["returns"] > 0  # some depth was left: not the "no return at all" case
    share = counts["nearer_than_near"] / (counts["pixels"] - counts["no_return"])
    assert f"{100 * share:.1f}% were nearer than near (3.6 m)" in err
    assert "a lower near" in err and f"[camera] table of {folder / 'mabdi.toml'}" in err
    assert "too few points per voxel" not in err


def test_a_far_below_the_depth_names_far_and_where_to_set_it(recording, tmp_path, capsys):
    folder = _copy_with_camera(recording, tmp_path, far="1.0")
    assert main(["run", "--sequence", str(folder), *FAST, "--out", str(tmp_path / "far")]) == 1
    err = capsys.readouterr().err
    assert "the map is empty" in err
    assert "beyond far (1 m)" in err and "0.0% were nearer than near" in err
    assert f"[camera] table of {folder / 'mabdi.toml'}" in err and "a higher far" in err
    assert "too few points per voxel" not in err


# ---------------------------------------------------------------------------
# 3. noise = "auto" under a config that leaves it unset; --camera's checks; depth beyond far counted


def test_a_config_that_leaves_noise_unset_keeps_the_recordings_auto(recording, tmp_path, capsys):
    config = tmp_path / "settings.toml"
    config.write_text(NO_NOISE)
    out = tmp_path / "auto"
    assert main(["run", str(config), "--sequence", str(recording), "--frames", "2", *FAST, "--out", str(out)]) == 0
    assert _summary(out)["noise"] == "auto"
    assert "noise: auto (learnt from the run: the config does not set [sensor] noise" in capsys.readouterr().out
    config.write_text(NO_NOISE + '\n[sensor]\nnoise = "none"\n')  # stated, even as the default value: obeyed
    out = tmp_path / "stated"
    assert main(["run", str(config), "--sequence", str(recording), "--frames", "2", *FAST, "--out", str(out)]) == 0
    assert _summary(out)["noise"] == "none"


@pytest.mark.parametrize(
    "camera, words",
    [
        ("65.625,65.625,40,30,80.5,60", "width must be a positive whole number of pixels, got 80.5"),
        ("65.625,65.625,40,30,80,0", "height must be a positive whole number of pixels, got 0"),
        ("-65.625,65.625,40,30,80,60", "fx must be positive, got -65.625"),
        ("65.625,0,40,30,80,60", "fy must be positive, got 0"),
        ("65.625,65.625,40,30,80", "expected 6 numbers fx,fy,cx,cy,width,height"),
    ],
)
def test_camera_numbers_are_checked_field_by_field(recording, tmp_path, capsys, camera, words):
    assert main(["run", "--sequence", str(recording), f"--camera={camera}", *FAST, "--out", str(tmp_path / "c")]) == 2
    assert f"--camera {camera}: {words}" in capsys.readouterr().err


def test_a_fractional_width_is_refused_for_a_layout_that_read_it_as_a_whole_one(recording, tmp_path, capsys):
    from mabdi.sources.frames import FrameList
    from mabdi.sources.sequences import open_sequence
    from mabdi.sources.threedmatch import write_3dmatch

    tum = open_sequence(recording)
    folder = write_3dmatch(FrameList([tum.read(i) for i in range(2)]), tmp_path / "3dmatch")
    camera = "65.625,65.625,40,30,80.5,60"  # was read as 80 pixels, and the run went on
    assert main(["run", "--sequence", str(folder), "--camera", camera, *FAST, "--out", str(tmp_path / "c")]) == 2
    assert f"--camera {camera}: width must be a positive whole number of pixels, got 80.5" in capsys.readouterr().err


def test_camera_numbers_with_near_and_far_run_a_tum_recording(recording, tmp_path):
    out = tmp_path / "camera"
    camera = "65.625,65.625,40,30,80,60,0.2,6"
    assert main(["run", "--sequence", str(recording), "--camera", camera, "--frames", "2", *FAST, "--out", str(out)]) == 0
    intrinsics = _summary(out)["intrinsics"]
    assert (intrinsics["width"], intrinsics["near"], intrinsics["far"]) == (80, 0.2, 6.0)


def test_depth_beyond_far_is_counted_and_said_once(recording, tmp_path, capsys):
    folder = _copy_with_camera(recording, tmp_path, far="3.0")
    out = tmp_path / "beyond"
    assert main(["run", "--sequence", str(folder), *FAST, "--out", str(out)]) == 0
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "dropped as outside near..far" in line]
    assert len(lines) == 1, err
    counts = _summary(out)["depth_returns"]
    share = counts["beyond_far"] / (counts["pixels"] - counts["no_return"])
    assert 0.02 < share < 0.5 and counts["far"] == 3.0 and counts["frames"] == 4
    assert f"{100 * share:.1f}% of the depth values were dropped" in lines[0]
    assert "beyond far (3 m)" in lines[0] and "a higher far" in lines[0] and "--camera fx,fy,cx,cy,width,height,near,far" in lines[0]


def test_a_recorded_simulation_of_the_first_frames_resumes_to_them_without_being_told(recording, tmp_path):
    """The API: a run of recorded_simulation(..., frames=2) whose recording dict does not repeat the frames
    still resumes to 2 frames (the pipeline keeps the source's own count in the checkpoint)."""
    from mabdi.config import load_run_config, with_overrides
    from mabdi.loop.mapping_run import recorded_simulation, resume_run

    config = with_overrides(
        load_run_config(recording.parent / "small.toml"),
        {"output.checkpoint_every": 1, "registration.enabled": False, "surface.method": "pixel_grid"},
    )
    simulation, _ = recorded_simulation(config, recording, frames=2)

    def interrupt(record):
        if record.frame == 0:
            raise KeyboardInterrupt

    out = tmp_path / "api"
    with pytest.raises(KeyboardInterrupt):
        simulation.run(out, progress=interrupt, recording={"path": str(recording), "options": {}})
    result = resume_run(out).run()
    assert len(result.records) == 2
