"""The viewer frames the map: its projected bounds fill the picture, a run folder adds the path, --from-frame
looks from a frame's pose; the picture's title and scale bar."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from mabdi.cli import main
from mabdi.viz.viewer import FILL, scale_bar_length


def map_pixels(png) -> np.ndarray:
    """Mask of the pixels that show the map coloured by frame (viridis: saturated), not the white background,
    the grey scene, the black path, title and scale bar."""
    picture = np.asarray(Image.open(png).convert("RGB")).astype(np.int16)
    return (picture.max(axis=2) - picture.min(axis=2)) > 40


def dark_pixels(png) -> int:
    picture = np.asarray(Image.open(png).convert("RGB"))
    return int((picture.max(axis=2) < 60).sum())


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory, scenes_dir):
    out = tmp_path_factory.mktemp("view") / "table"
    assert main(["run", str(scenes_dir / "table.toml"), "--frames", "4", "--out", str(out), "--quiet", "--no-eval"]) == 0
    return out


def test_the_map_fills_the_picture(run_folder, tmp_path, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    png = tmp_path / "x.png"
    assert main(["view", str(run_folder), "--out", str(png)]) == 0
    mask = map_pixels(png)
    height, width = mask.shape
    rows, columns = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    fill = max((columns[-1] - columns[0] + 1) / width, (rows[-1] - rows[0] + 1) / height)
    # the box's corners fill FILL of the binding side; the map inside its box reaches at least half of it
    assert fill >= 0.5, fill
    centre = np.array([(columns[0] + columns[-1]) / 2 / width, (rows[0] + rows[-1]) / 2 / height])
    np.testing.assert_allclose(centre, [0.5, 0.5], atol=0.15)  # centred, not off to a side


def test_a_run_folder_shows_the_path_and_the_map_file_alone_does_not(run_folder, tmp_path):
    folder_png, map_png = tmp_path / "folder.png", tmp_path / "map.png"
    assert main(["view", str(run_folder), "--out", str(folder_png)]) == 0
    assert main(["view", str(run_folder / "world_mesh.vtp"), "--out", str(map_png)]) == 0
    # the same framing (the map's bounds) for both: only the path (black) and the scene (grey) differ
    assert np.mean(map_pixels(folder_png) == map_pixels(map_png)) > 0.9
    assert dark_pixels(folder_png) > dark_pixels(map_png) + 300


def test_from_frame_looks_from_the_sensor_and_checks_the_frame(run_folder, tmp_path, capsys):
    png = tmp_path / "frame.png"
    assert main(["view", str(run_folder), "--from-frame", "2", "--out", str(png)]) == 0
    picture = Image.open(png)
    assert picture.size == (1280, 960)  # the sensor's 4:3
    assert map_pixels(png).mean() > 0.3  # the sensor looked at the table: the map fills much of its view
    assert main(["view", str(run_folder), "--from-frame", "4", "--out", str(png)]) == 2
    assert "poses.npy holds frames 0 .. 3" in capsys.readouterr().err
    assert main(["view", str(run_folder / "world_mesh.vtp"), "--from-frame", "0", "--out", str(png)]) == 2
    assert "needs a run folder" in capsys.readouterr().err


def test_scale_bar_lengths_are_round():
    assert scale_bar_length(10.0) == 2.0
    assert scale_bar_length(25.0) == 5.0
    assert scale_bar_length(0.4) == pytest.approx(0.1)
    assert 0.5 < FILL < 1.0
