"""LiDAR recordings as they come: a KITTI folder whose sensor is not the default one, scan files of odd sizes."""

from __future__ import annotations

import dataclasses
import re
import warnings

import numpy as np
import pytest

import mabdi.sources.range_images as range_images
from mabdi.sources.kitti import KittiSequence, read_scan
from mabdi.sources.range_images import KITTI_GEOMETRY
from mabdi.sources.sequences import SequenceError, open_sequence


def _scan(elevations, columns=360, half=(20.0, 15.0, 3.0), jitter=0.0, seed=0):
    """(N, 4) float32 points of a spinning LiDAR at the centre of a box room: one ring per elevation (degrees)."""
    rng = np.random.default_rng(seed)
    el = np.radians(np.asarray(elevations, dtype=np.float64))[:, None] + np.radians(jitter) * rng.standard_normal((len(elevations), columns))
    az = np.linspace(-np.pi, np.pi, columns, endpoint=False)[None, :]
    rays = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) + 0 * az], axis=-1).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        t = np.min(np.abs(np.asarray(half) / rays), axis=-1)
    points = np.zeros((len(rays), 4), dtype="<f4")
    points[:, :3] = rays * t[:, None]
    points[:, 3] = 0.3
    return points


def _folder(path, elevations, scans=3, jitter=0.0, lidar=None):
    """A KITTI folder of ``scans`` scans of the sensor with beams at ``elevations``; ``lidar``: a [lidar] table's text."""
    (path / "velodyne").mkdir(parents=True)
    for i in range(scans):
        _scan(elevations, jitter=jitter, seed=i).tofile(path / "velodyne" / f"{i:06d}.bin")
    (path / "poses.txt").write_text("".join(f"1 0 0 {0.1 * i} 0 1 0 0 0 0 1 0\n" for i in range(scans)))
    if lidar is not None:
        (path / "mabdi.toml").write_text("[lidar]\n" + lidar)
    return path


EMPTY_ROWS = "rows between its top and bottom beams hold no returns"


def _read_all(source, rows: bool = False):
    """Every frame of ``source`` and the LidarGeometryWarnings raised while opening and reading it: those of points
    outside the image, or with ``rows`` those of rows without returns."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        source = source()
        frames = [source.read(i) for i in range(len(source))]
    ours = [w for w in caught if issubclass(w.category, range_images.LidarGeometryWarning)]
    return source, frames, [w for w in ours if (EMPTY_ROWS in str(w.message)) == rows]


WIDE_32 = np.linspace(45.0, -45.0, 32)  # a +-45 degree sensor of 32 evenly spread beams
HDL_64 = np.linspace(2.0, -24.8, 64)  # the Velodyne HDL-64E's span
#: The Velodyne VLP-32C's beam elevations (degrees, top first; its manual's table).
VLP_32C = np.array([
    15.0, 10.333, 7.0, 4.667, 3.333, 2.333, 1.667, 1.333, 1.0, 0.667, 0.333, 0.0, -0.333, -0.667, -1.0, -1.333,
    -1.667, -2.0, -2.333, -2.667, -3.0, -3.333, -3.667, -4.0, -4.667, -5.333, -6.148, -7.254, -8.843, -11.31, -15.639, -25.0,
])  # fmt: skip


def test_wide_sensor_without_lidar_table_is_learnt_and_said_once(tmp_path):
    folder = _folder(tmp_path / "seq", WIDE_32, jitter=0.02)
    source, frames, said = _read_all(lambda: open_sequence(folder))
    assert len(said) == 1  # once a run, not once a scan
    message = str(said[0].message)
    # The share of the first scan outside the default geometry, their elevations against the image's.
    inside = np.isfinite(range_images.range_image(_scan(WIDE_32, jitter=0.02)[:, :3], KITTI_GEOMETRY, centred=False)).sum()
    share = 1 - inside / (32 * 360)
    assert f"{100 * share:.0f}% of" in message
    assert re.search(r"\+45\.\d to -45\.\d degrees", message) and "+3.0 to -25.0" in message
    assert str(folder / "mabdi.toml") in message and "[lidar]" in message
    for key in ("fov_up", "fov_down", "beams"):
        assert key in message
    # The geometry learnt from the first scan: the sensor's span (half a beam spacing beyond the outer beams) and
    # its 32 beams, one a row, so nearly every point of every scan lands in the image.
    geometry = source.intrinsics
    spacing = 90.0 / 31
    # Its 360 firings a turn, fewer than the default's 1,024 columns: 0.9 of them as columns (324), so that no
    # column is left between firings (before, 1,024 columns held a return in about one of three).
    assert geometry.beams == 32 and geometry.columns == int(0.9 * 360)
    assert geometry.fov_up == pytest.approx(45 + spacing / 2, abs=0.05) and geometry.fov_down == pytest.approx(-45 - spacing / 2, abs=0.05)
    assert f"fov_up = {geometry.fov_up:g}" in message and "beams = 32" in message
    assert "learnt" in source.description
    # An HDL-64E's scans without a table fit the default geometry: no warning, nothing learnt.
    hdl = _folder(tmp_path / "hdl", HDL_64, jitter=0.02)
    source, _, said = _read_all(lambda: open_sequence(hdl))
    assert said == [] and source.intrinsics == KITTI_GEOMETRY and source.description == f"KITTI folder {hdl}"
    for frame in frames:
        assert frame.intrinsics == geometry
        rows_hit = np.isfinite(frame.depth).any(axis=1)
        assert rows_hit.all()  # every row holds its beam
        assert np.isfinite(frame.depth).mean() > 0.95  # nearly every pixel holds a return
    wide = dataclasses.replace(geometry, columns=KITTI_GEOMETRY.columns)
    assert np.isfinite(range_images.range_image(_scan(WIDE_32, jitter=0.02)[:, :3], wide, centred=False)).mean() < 0.4


def test_wide_sensor_of_unclear_rings_keeps_the_beam_count(tmp_path):
    # Elevations spread evenly (no rings to count): the span is learnt, the default beam count kept.
    folder = tmp_path / "seq"
    (folder / "velodyne").mkdir(parents=True)
    rng = np.random.default_rng(3)
    el, az = np.radians(rng.uniform(-40.0, 40.0, 20000)), rng.uniform(-np.pi, np.pi, 20000)
    points = np.zeros((20000, 4), dtype="<f4")
    points[:, :3] = 10.0 * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    points.tofile(folder / "velodyne" / "000000.bin")
    (folder / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    source, _, said = _read_all(lambda: KittiSequence(folder))
    assert len(said) == 1 and "beams = 64" in str(said[0].message)
    assert source.intrinsics.beams == 64
    assert source.intrinsics.fov_up == pytest.approx(40.0, abs=1.0) and source.intrinsics.fov_down == pytest.approx(-40.0, abs=1.0)


def test_uneven_smeared_beams_with_stray_returns_are_counted(tmp_path):
    # A wide sensor's 32 beams spaced 2.2 and 3.6 degrees in turn, each ring smeared 0.3 degrees (a deskewed
    # sweep), with a few stray returns between some rings: 32 beams learnt, and no row of the image left empty.
    steps = np.where(np.arange(31) % 2 == 0, 2.2, 3.6)
    elevations = 45.0 - np.concatenate([[0.0], np.cumsum(steps)])
    rng = np.random.default_rng(5)
    rings = [_scan(elevations, columns=1024, jitter=0.08, seed=1)]
    strays = elevations[::3][:8] - 1.1  # between a ring and the next, a tenth as many returns
    rings.append(_scan(strays, columns=1024, seed=2)[rng.random(8 * 1024) < 0.1])
    folder = tmp_path / "seq"
    (folder / "velodyne").mkdir(parents=True)
    np.concatenate(rings).tofile(folder / "velodyne" / "000000.bin")
    (folder / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    source, frames, said = _read_all(lambda: KittiSequence(folder))
    assert len(said) == 1 and "beams = 32" in str(said[0].message)
    geometry = source.intrinsics
    assert geometry.beams == 32
    assert geometry.fov_up > elevations[0] and geometry.fov_down < elevations[-1]
    rows_filled = np.isfinite(frames[0].depth).mean(axis=1)
    assert rows_filled.min() > 0.9  # every row holds returns carried to its centre


def test_a_sensor_a_little_wider_than_the_default_has_its_span_learnt(tmp_path):
    """A Velodyne VLP-32C (+15 to -25 degrees, its beams dense about the horizon): 5 of its 32 beams lie above the
    default image's top edge. Its span is learnt, so the map does not miss them; before, the default geometry was
    kept while under a quarter of a scan missed it, and a sixth of every scan was lost."""
    folder = _folder(tmp_path / "seq", VLP_32C, jitter=0.02)
    source, frames, said = _read_all(lambda: open_sequence(folder))
    assert len(said) == 1
    message = str(said[0].message)
    share = int(re.search(r"(\d+)% of its", message).group(1))
    assert 100 * 5 / 32 <= share <= 100 * 5.5 / 32 + 1 and "learnt" in message and "fov_up" in message
    geometry = source.intrinsics
    assert geometry.fov_up > 15.0 and geometry.fov_down < -25.0 and geometry.columns == int(0.9 * 360)
    # The beams are uneven: not counted as evenly spread, so the default's 64 rows over the learnt span.
    assert geometry.beams == KITTI_GEOMETRY.beams
    points = _scan(VLP_32C, jitter=0.02)[:, :3]
    assert range_images.scan_fit(points, geometry).share < 0.01
    # Every beam reaches the image: the top five too, which the default image missed.
    rows = np.flatnonzero(np.isfinite(frames[0].depth).any(axis=1))
    top_rows = geometry.pixels(points[np.degrees(np.arcsin(points[:, 2] / np.linalg.norm(points, axis=1))) > 3.0])[0][:, 1]
    assert np.isin(np.unique(np.floor(top_rows).astype(int)), rows).all() and len(np.unique(np.floor(top_rows))) >= 5


def test_returns_of_the_carrier_are_no_part_of_the_learnt_geometry(tmp_path):
    """Returns nearer than the image's near range (the car or the person carrying the sensor, often a quarter of a
    scan) neither count as missing the image nor stretch the learnt span: a 32-beam sensor of +10.67 to -30.67
    degrees (a Velodyne HDL-32E) on a roof whose returns within 1 m reach down to -55 degrees learns its own 32
    beams; before, the roof's returns were taken for the sensor's lowest beams (a span down to -53 degrees)."""
    hdl_32 = np.linspace(10.67, -30.67, 32)
    folder = tmp_path / "seq"
    (folder / "velodyne").mkdir(parents=True)
    rng = np.random.default_rng(7)
    roof = np.zeros((12000, 4), dtype="<f4")
    el, az = np.radians(rng.uniform(-55.0, -35.0, 12000)), rng.uniform(-np.pi, np.pi, 12000)
    distance = rng.uniform(0.4, 0.95, 12000)
    roof[:, :3] = distance[:, None] * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    scan = np.concatenate([_scan(hdl_32, columns=1024, jitter=0.02), roof])
    scan.tofile(folder / "velodyne" / "000000.bin")
    (folder / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    source, frames, said = _read_all(lambda: KittiSequence(folder))
    assert len(said) == 1 and "beams = 32" in str(said[0].message)
    geometry = source.intrinsics
    spacing = 41.34 / 31
    assert geometry.beams == 32
    assert geometry.fov_up == pytest.approx(10.67 + spacing / 2, abs=0.05)
    assert geometry.fov_down == pytest.approx(-30.67 - spacing / 2, abs=0.05)
    # The roof is no part of the fit: nothing of the scene lies outside the learnt image.
    fit = range_images.scan_fit(scan[:, :3], geometry)
    assert fit.returns == 32 * 1024 and fit.share == 0.0
    assert np.isfinite(frames[0].depth).mean() > 0.9  # one ring a row (1,024 returns a ring, 1,024 columns)


def test_far_rings_give_the_spacing_where_near_rings_are_smeared(tmp_path):
    """A moving 32-beam sensor's near returns smeared across the rings (deskewing, the lasers' offsets): the
    rings are counted on the far half of the returns, where they stand apart, and their spacing spread over the
    whole scan's span: 32 beams, not the default's 64."""
    elevations = np.linspace(10.0, -30.0, 32)
    far = _scan(elevations, columns=1024, half=(40.0, 30.0, 30.0), jitter=0.02, seed=1)
    rng = np.random.default_rng(2)
    near = np.zeros((40000, 4), dtype="<f4")
    el, az = np.radians(rng.uniform(-30.0, 10.0, 40000)), rng.uniform(-np.pi, np.pi, 40000)
    near[:, :3] = rng.uniform(2.0, 5.0, 40000)[:, None] * np.stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    points = np.concatenate([far, near])[:, :3].astype(np.float64)
    assert range_images.beam_elevations_of(range_images._returns(points, 1.0)[1]) is None  # smeared: not counted
    learnt, _ = range_images.learn_geometry(points, KITTI_GEOMETRY)
    assert learnt.beams == 32
    assert learnt.fov_up == pytest.approx(10.0 + 40.0 / 62, abs=0.3) and learnt.fov_down == pytest.approx(-30.0 - 40.0 / 62, abs=0.3)


def test_rings_smeared_in_the_first_scan_are_counted_in_a_later_one(tmp_path):
    """The first scan's rings smeared (the sensor moving as it starts), the next scans' sharp: the beams are
    counted in those, so the image has the sensor's 32 rows, not the default's 64."""
    folder = tmp_path / "seq"
    (folder / "velodyne").mkdir(parents=True)
    _scan(WIDE_32, columns=1024, jitter=1.0, seed=0).tofile(folder / "velodyne" / "000000.bin")
    for i in (1, 2):
        _scan(WIDE_32, columns=1024, jitter=0.02, seed=i).tofile(folder / "velodyne" / f"{i:06d}.bin")
    (folder / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 3)
    assert range_images.learn_geometry(read_scan(folder / "velodyne" / "000000.bin")[:, :3], KITTI_GEOMETRY)[0].beams == 64
    source, _, said = _read_all(lambda: KittiSequence(folder))
    assert source.intrinsics.beams == 32 and "learnt from 000000.bin..000002.bin" in source.description


def test_wrong_lidar_table_is_said_once_and_kept(tmp_path):
    table = "beams = 64\ncolumns = 1024\nfov_up = 3.0\nfov_down = -25.0\nrange_min = 1.0\nrange_max = 120.0\n"
    folder = _folder(tmp_path / "seq", WIDE_32, lidar=table)
    source, _, said = _read_all(lambda: KittiSequence(folder))
    assert len(said) == 1
    message = str(said[0].message)
    assert source.intrinsics == KITTI_GEOMETRY  # the table is the user's word: kept, but questioned
    assert "000000.bin" in message and re.search(r"\d+% of", message) and "+45.0 to -45.0" in message
    assert str(folder / "mabdi.toml") in message and "fov_up" in message and "fov_down" in message
    # The sensor's own table: quiet.
    right = _folder(tmp_path / "right", WIDE_32, lidar="beams = 32\nfov_up = 46.5\nfov_down = -46.5\n")
    source, _, said = _read_all(lambda: open_sequence(right))
    assert said == [] and source.intrinsics.beams == 32


def test_scans_beyond_range_are_said(tmp_path):
    table = "fov_up = 50.0\nfov_down = -50.0\nrange_max = 5.0\n"
    folder = _folder(tmp_path / "seq", WIDE_32, lidar=table)
    _, _, said = _read_all(lambda: KittiSequence(folder))
    assert len(said) == 1 and "range_max" in str(said[0].message)


@pytest.mark.parametrize("extra", [1, 2, 3])
def test_scan_with_trailing_bytes_is_refused_with_its_size(tmp_path, extra):
    path = tmp_path / "000000.bin"
    path.write_bytes(_scan(HDL_64[:4], columns=16).tobytes() + b"\0" * extra)
    size = 4 * 16 * 16 + extra
    with pytest.raises(SequenceError) as caught:
        read_scan(path)
    message = str(caught.value)
    assert str(path) in message and f"{size} bytes" in message and "16" in message
    assert f"{size - extra} bytes" not in message


def test_scan_with_trailing_bytes_stops_the_folder(tmp_path):
    folder = _folder(tmp_path / "seq", HDL_64, scans=2)
    with open(folder / "velodyne" / "000001.bin", "ab") as stream:
        stream.write(b"\1\2")
    source = KittiSequence(folder)
    with pytest.raises(SequenceError, match=re.escape(f"{folder / 'velodyne' / '000001.bin'}: {64 * 360 * 16 + 2} bytes")):
        source.read(1)


def test_a_lidar_recordings_run_names_its_default_noise_not_a_learnt_one(tmp_path, capsys):
    from mabdi.cli import main

    folder = _folder(tmp_path / "seq", HDL_64, scans=2)
    assert main(["run", "--sequence", str(folder), "--quiet", "--no-eval", "--out", str(tmp_path / "run")]) == 0
    printed = capsys.readouterr().out
    assert "noise: range, 0.02 m (a LiDAR's default: no config and no --noise name the sensor's model)" in printed
    assert "learnt from the run" not in printed


def test_an_image_of_more_rows_than_the_sensor_has_beams_is_said(tmp_path):
    """A 32-beam sensor read with a table of 64 rows over its span: every other row holds no return, and nothing
    is meshed across such a row (a real HDL-32E so read made a map of 4,104 triangles instead of 443,860); the
    run says so once, with the numbers and the keys to set. Its own 32 beams: quiet."""
    table = "beams = 64\nfov_up = 46.5\nfov_down = -46.5\n"
    folder = _folder(tmp_path / "seq", WIDE_32, lidar=table)
    source, frames, said = _read_all(lambda: KittiSequence(folder), rows=True)
    assert len(said) == 1
    message = str(said[0].message)
    empty, spanned = range_images.rows_without_returns(frames[0].return_points)
    assert spanned >= 60 and 28 <= empty <= 32
    assert f"{empty} of the range image's {spanned} rows" in message and "beams = 64" in message
    assert "000000.bin" in message and str(folder / "mabdi.toml") in message and "beam_elevations" in message
    right = _folder(tmp_path / "right", WIDE_32, lidar="beams = 32\nfov_up = 46.5\nfov_down = -46.5\n")
    _, frames, said = _read_all(lambda: KittiSequence(right), rows=True)
    assert said == [] and range_images.rows_without_returns(frames[0].return_points) == (0, 32)
