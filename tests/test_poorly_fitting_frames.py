"""Frames that no rigid pose fits to the map as well as the run's other frames cast no removal votes: a static
table recorded with a few bent frames (their depth waved across the image, as a structured-light camera's is when
a fast turn smears its pattern: no rigid motion undoes it) keeps its faces, and the run says how many frames fit
poorly (:mod:`mabdi.stages.fit_check`)."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from mabdi.stages.fit_check import MIN_FRAMES, POOR_FIT, WINDOW, fits_poorly
from mabdi.sources.tum import read_depth_units

REPO = Path(__file__).resolve().parents[1]
FRAMES = 60
BENT = range(30, 36)  # the frames whose depth is bent
WAVE = 0.03  # the bend's amplitude, a share of the depth


def test_the_rule_against_the_run_so_far():
    earlier = np.full(20, 0.004)
    assert not fits_poorly(POOR_FIT * 0.004 * 0.99, earlier)
    assert fits_poorly(POOR_FIT * 0.004 * 1.01, earlier)
    assert not fits_poorly(1.0, earlier[: MIN_FRAMES - 1])  # too few frames known to judge
    assert not fits_poorly(float("nan"), earlier)
    with_gaps = np.concatenate([earlier, [np.nan] * 5])
    assert fits_poorly(0.02, with_gaps)  # NaN entries skipped
    # the median follows the last WINDOW frames: a run whose residual rose for good takes it as its level
    risen = np.concatenate([np.full(WINDOW, 0.002), np.full(WINDOW // 2 + 1, 0.01)])
    assert not fits_poorly(0.02, risen)
    assert fits_poorly(0.02, risen[: WINDOW])


def _bend(units: np.ndarray, wave: float) -> np.ndarray:
    """The depth (PNG units, 0 = no return) times 1 + ``wave`` sin(4 pi u / W): two waves across the image, a
    bend no rigid pose takes out."""
    width = units.shape[1]
    share = 1.0 + wave * np.sin(4.0 * np.pi * np.arange(width) / width)
    return np.where(units > 0, np.round(units * share[None, :]), 0).astype(np.uint16)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> tuple[Path, Path]:
    """The static table recorded as a TUM folder with a Kinect's noise; and a copy with frames :data:`BENT` bent."""
    from mabdi.cli import main

    folder = tmp_path_factory.mktemp("bent")
    text = (REPO / "scenes" / "table.toml").read_text().replace("frames = 30", f"frames = {FRAMES}")
    text = text.replace('noise = "none"', 'noise = "kinect"')
    (folder / "table.toml").write_text(text)
    straight = folder / "straight"
    assert main(["record", str(folder / "table.toml"), "--format", "tum", "--out", str(straight)]) == 0
    bent = folder / "bent"
    shutil.copytree(straight, bent)
    rows = [line.split() for line in (bent / "depth.txt").read_text().splitlines() if line.strip() and not line.startswith("#")]
    from PIL import Image

    for index in BENT:
        path = bent / rows[index][1]
        units = read_depth_units(path, None)
        Image.fromarray(_bend(units, WAVE)).save(path)
    return straight, bent


def _run(folder: Path, out: Path) -> tuple[dict, str]:
    from mabdi.cli import main

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["run", "--sequence", str(folder), "--out", str(out), "--quiet", "--no-eval", "--time-offset", "0"]) == 0
    return json.loads((out / "summary.json").read_text()), printed.getvalue()


def _metrics(out: Path) -> dict[str, np.ndarray]:
    lines = (out / "metrics.csv").read_text().splitlines()
    names = lines[0].split(",")
    values = [line.split(",") for line in lines[1:]]
    return {name: np.array([row[k] for row in values]) for k, name in enumerate(names)}


def test_bent_frames_fit_poorly_and_remove_nothing_of_the_static_table(recordings, tmp_path):
    straight, bent = recordings
    clean, _ = _run(straight, tmp_path / "straight")
    summary, printed = _run(bent, tmp_path / "bent")
    metrics = _metrics(tmp_path / "bent")
    poor = np.flatnonzero(metrics["poor_fit"].astype(int) == 1)
    # the bent frames are found (those whose fit stopped unconverged or beyond its bound too), and (nearly) only they
    assert set(BENT) <= set(poor), poor
    assert len(set(poor) - set(BENT)) <= 1, poor
    assert summary["registration"]["poor_fit"] == len(poor)
    assert f"{len(poor)} fit the map over {POOR_FIT:g} times worse than the run's frames" in printed
    # their residual stands out of the run's
    residual = metrics["residual_mm"].astype(float)
    assert np.nanmin(residual[list(BENT)]) > POOR_FIT * np.nanmedian(residual[: BENT.start])
    # the static table keeps its faces: nothing goes while the bent frames and the frames their votes would have
    # counted with (removal's frames against a face) come (what goes later is what the bent frames meshed in front
    # of the table, seen through by the straight frames after them)
    removed = metrics["cells_removed"].astype(int)
    assert removed[BENT.start : BENT.stop + 2].sum() == 0, removed[BENT.start : BENT.stop + 2]
    assert clean["registration"]["poor_fit"] == 0 and clean["cells_removed"] == 0


def test_frames_that_stood_still_do_not_set_the_runs_level():
    """A sensor standing still fits the map at its noise alone (a handheld LiDAR: 3 mm for nine scans, 9-11 mm once
    it moved): frames within a millimetre and a tenth of a degree of the frame before them are not counted, so the
    first frames that move are judged against frames that moved."""
    from scipy.spatial.transform import Rotation

    from mabdi.stages.fit_check import STILL_DEGREES, STILL_METRES, moved

    poses = np.repeat(np.eye(4)[None], 7, axis=0)
    poses[1, 0, 3] = 0.2 * STILL_METRES  # jitter of a still pose
    poses[2, :3, :3] = Rotation.from_rotvec([0.0, 0.0, np.radians(0.5 * STILL_DEGREES)]).as_matrix()
    poses[3, 0, 3] = 5.0 * STILL_METRES  # moved 5 mm
    poses[4, :3, :3] = Rotation.from_rotvec([0.0, np.radians(2.0 * STILL_DEGREES), 0.0]).as_matrix()  # and turned back
    poses[5] = np.nan  # not run
    assert moved(poses).tolist() == [False, False, False, True, True, False, False]
    assert moved(poses[:1]).tolist() == [False] and moved(np.zeros((0, 4, 4))).tolist() == []

    # the loop's run so far: nine registered frames standing still at 3 mm, then six moving at 10 mm; the level it
    # judges the next frame by holds the moving ones alone
    import mabdi
    from mabdi.camera import Intrinsics, look_at
    from mabdi.depth import DepthFrame
    from mabdi.sources.frames import FrameList
    from mabdi.stages.registration import STATUSES

    camera = Intrinsics(fx=30.0, fy=30.0, cx=8.0, cy=6.0, width=16, height=12)
    frames = [DepthFrame(np.full((12, 16), 2.0, np.float32), camera, np.eye(4), i, i / 30) for i in range(16)]
    loop = mabdi.MabdiLoop(FrameList(frames), surface="quadtree")
    track = [look_at([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])] * 10 + [look_at([0.05 * k, 0.0, 0.0], [1.0, 0.0, 0.0]) for k in range(1, 7)]
    loop._poses[:16] = np.array(track)
    loop._registrations[:16, 0] = STATUSES.index("registered")
    loop._registrations[:16, 5] = [0.003] * 10 + [0.010] * 6
    counted = loop._earlier_residuals(16)
    np.testing.assert_array_equal(counted, np.full(6, 0.010))
    assert fits_poorly(0.010, loop._registrations[:16, 5]) and not fits_poorly(0.010, counted)
