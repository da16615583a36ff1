"""A depth camera's near and far learnt from a recording's frames where nothing states them
(mabdi.sources.depth_range): a close-range camera's depth kept, a far-reaching one's too, a wrong unit not
made into a map of the wrong size, and a stated range obeyed."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from mabdi.camera import Intrinsics
from mabdi.cli import main
from mabdi.depth import DepthFrame
from mabdi.sources.depth_range import DROPPED_SHARE, learn_depth_range
from mabdi.sources.frames import FrameList
from mabdi.sources.tum import write_tum

CAMERA = Intrinsics(fx=65.625, fy=65.625, cx=40.0, cy=30.0, width=80, height=60)  # near 0.5, far 4 (the defaults)


def _frames(low: float, high: float, count: int = 4, camera: Intrinsics = CAMERA) -> FrameList:
    """``count`` frames of a static camera facing a wall whose depth runs from ``low`` (left) to ``high`` (right), m."""
    depth = np.tile(np.linspace(low, high, camera.width, dtype=np.float32), (camera.height, 1))
    return FrameList([DepthFrame(depth.copy(), camera, np.eye(4), i, i / 30.0) for i in range(count)])


def test_a_close_range_cameras_near_is_learnt_below_its_depth():
    learnt = learn_depth_range(_frames(0.25, 0.9), 4)
    assert learnt is not None
    assert 0.2 <= learnt.near < 0.25 and learnt.far == 4.0
    assert (learnt.near_before, learnt.far_before) == (0.5, 4.0)
    assert learnt.dropped_before == pytest.approx(np.mean(np.linspace(0.25, 0.9, 80) <= 0.5))
    assert "depth range 0.23-4 m learnt from 4 of its frames" in learnt.note()


def test_a_far_reaching_cameras_far_is_learnt_beyond_its_depth():
    learnt = learn_depth_range(_frames(2.0, 7.0), 4)
    assert learnt is not None
    assert learnt.near == 0.5 and 7.0 < learnt.far <= 7.5


def test_a_range_that_drops_little_is_kept():
    # a sliver of the wall beyond far: under DROPPED_SHARE of the values
    high = 4.0 + 0.5 * DROPPED_SHARE * (4.0 - 1.0) / (1 - 0.5 * DROPPED_SHARE)
    assert learn_depth_range(_frames(1.0, high), 4) is None


@pytest.mark.parametrize("low, high", [(0.1, 0.45), (4.5, 9.0)])
def test_every_value_on_one_side_is_taken_for_a_wrong_unit_not_a_range(low, high):
    """All of the depth nearer than near (or beyond far): the unit is likelier wrong than the range, and a range
    moved to fit it would make a map of the wrong size."""
    assert learn_depth_range(_frames(low, high), 4) is None


def _close_range_recording(tmp_path):
    """A TUM folder of a close-range camera whose mabdi.toml gives no near or far."""
    folder = write_tum(_frames(0.25, 0.9, camera=Intrinsics(**{**CAMERA.__dict__, "near": 0.05, "far": 10.0})), tmp_path / "tum")
    toml = folder / "mabdi.toml"
    toml.write_text(re.sub(r"(?m)^(near|far) = .*\n", "", toml.read_text()))
    assert not re.search(r"(?m)^(near|far) =", toml.read_text())
    return folder


FAST = ["--quiet", "--no-eval", "--no-registration", "--surface", "pixel_grid", "--frames", "3"]


def test_a_run_keeps_a_close_range_cameras_depth_and_says_so(tmp_path, capsys):
    folder = _close_range_recording(tmp_path)
    out = tmp_path / "run"
    assert main(["run", "--sequence", str(folder), *FAST, "--out", str(out)]) == 0
    captured = capsys.readouterr()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["intrinsics"]["near"] < 0.25 and summary["intrinsics"]["far"] == 4.0
    counts = summary["depth_returns"]
    assert counts["nearer_than_near"] == 0 and counts["beyond_far"] == 0 and counts["returns"] > 0
    assert "depth range 0.23-4 m learnt from 3 of its frames" in captured.out
    assert "dropped as outside near..far" not in captured.err


def test_a_stated_range_is_obeyed(tmp_path, capsys):
    folder = _close_range_recording(tmp_path)
    out = tmp_path / "stated"
    camera = "65.625,65.625,40,30,80,60,0.5,4"
    assert main(["run", "--sequence", str(folder), "--camera", camera, *FAST, "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["intrinsics"]["near"] == 0.5
    assert summary["depth_returns"]["nearer_than_near"] > 0
    assert "dropped as outside near..far" in capsys.readouterr().err
