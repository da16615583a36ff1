"""Seeing a run: the dashboard, the streamed movie, colours, the viewer without a display."""

import tracemalloc

import numpy as np
import pytest

from mabdi.mesh_maps.colours import colours_by_frame
from mabdi.viz.movie import MovieError, MovieWriter, read_movie_frames


def panel(picture, row, column):
    """The pixels of one of the six panels (2 rows x 3 columns), without the title strip."""
    height, width = picture.shape[0] // 2, picture.shape[1] // 3
    return picture[row * height + 30 : (row + 1) * height, column * width : (column + 1) * width]


def test_run_with_movie_writes_every_frame_and_the_panels_are_in_place(tmp_path, scenes_dir, capsys):
    from PIL import Image

    from mabdi.cli import main

    out = tmp_path / "run"
    assert main(["run", str(scenes_dir / "table.toml"), "--frames", "20", "--movie", "--out", str(out), "--quiet", "--no-eval"]) == 0
    printed = capsys.readouterr().out
    assert "movie:" in printed and "ms per frame" in printed
    frames, size = read_movie_frames(out / "movie.mp4")
    assert frames == 20 and size == (1296, 720)
    snapshots = sorted(p.name for p in out.glob("dashboard_*.png"))
    assert snapshots == ["dashboard_0000.png", "dashboard_0010.png", "dashboard_0019.png"]
    first, middle, last = (np.asarray(Image.open(out / name).convert("RGB")) for name in snapshots)
    assert last.shape == (720, 1296, 3)
    for column in range(3):  # D, E (from frame 1 on), labels: not blank
        assert np.unique(panel(last, 1, column).reshape(-1, 3), axis=0).shape[0] > 3
    # the depth panel shows a range of depths, the label panel its four colours at most plus blending
    assert panel(last, 1, 0).std() > 20
    # the 3-D views change between frames (the frustum moves, the map grows)
    for column in (0, 1):
        assert np.abs(panel(first, 0, column).astype(int) - panel(last, 0, column).astype(int)).sum() > 1000
    # the element plot rises: its curve (blue) reaches higher up the panel at the end than at the start
    def curve_top(picture):
        plot = panel(picture, 0, 2).astype(int)
        blue = (plot[..., 2] > 150) & (plot[..., 0] < 100) & (plot[..., 1] > 80) & (plot[..., 1] < 170)
        rows = np.flatnonzero(blue.any(axis=1))
        return rows.min() if len(rows) else plot.shape[0]

    assert curve_top(last) <= curve_top(middle) <= curve_top(first)
    assert curve_top(middle) < panel(middle, 0, 2).shape[0] - 40


def test_movie_adds_no_memory_per_frame(tmp_path):
    def peak(frames):
        tracemalloc.start()
        with MovieWriter(tmp_path / f"m{frames}.mp4", (320, 240)) as movie:
            for i in range(frames):
                picture = np.full((240, 320, 3), i % 255, dtype=np.uint8)
                movie.write(picture)
        result = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return result

    few, many = peak(30), peak(300)
    assert many - few < 3 * 2**20  # 270 more frames of 230 kB each would be 62 MB
    assert read_movie_frames(tmp_path / "m300.mp4") == (300, (320, 240))


def test_movie_rejects_bad_sizes_and_leaves_nothing_on_failure(tmp_path):
    with pytest.raises(MovieError, match="multiples of 16"):
        MovieWriter(tmp_path / "bad.mp4", (1300, 720))
    with pytest.raises(MovieError, match=r"\(240, 320, 3\) uint8"):
        with MovieWriter(tmp_path / "m.mp4", (320, 240)) as movie:
            movie.write(np.zeros((10, 10, 3), dtype=np.uint8))
    assert list(tmp_path.iterdir()) == []


def test_colours_by_frame_run_dark_to_bright():
    rgb = colours_by_frame(np.arange(10)).astype(float)
    luminance = rgb @ [0.2126, 0.7152, 0.0722]
    assert (np.diff(luminance) > 0).all()
    np.testing.assert_array_equal(colours_by_frame([3, 3, 3])[0], colours_by_frame([0])[0])  # one frame: the first colour


def test_view_without_a_display_writes_a_png(tmp_path, scenes_dir, capsys, monkeypatch):
    from mabdi.cli import main

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    out = tmp_path / "run"
    assert main(["run", str(scenes_dir / "table.toml"), "--frames", "3", "--out", str(out), "--quiet", "--no-eval", "--h5"]) == 0
    capsys.readouterr()
    assert main(["view", str(out)]) == 0
    assert "no display: wrote" in capsys.readouterr().out
    assert (out / "world_mesh_frame.png").stat().st_size > 10_000
    assert main(["view", str(out / "world_mesh.h5"), "--colour", "cost", "--out", str(tmp_path / "cost.png")]) == 0
    assert (tmp_path / "cost.png").is_file()
    assert main(["view", str(out / "world_mesh.vtp"), "--colour", "altitude"]) == 2
    assert "unknown colour 'altitude'" in capsys.readouterr().err
