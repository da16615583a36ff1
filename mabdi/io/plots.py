"""Figures written to files (PNG), drawn off-screen with pyvista's VTK charts."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mabdi.io.atomic import atomic_output

#: Line colours for up to eight series (matplotlib's tab10 order).
COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:gray")


def write_elements_plot(series: dict[str, tuple[np.ndarray, np.ndarray]], path, title: str = "") -> Path:
    """Plot the number of mesh elements per frame, one line per series (seed 001 Fig. 7).

    ``series`` maps a label to ``(frames, elements)``. Written atomically as PNG (800x500).
    """
    return write_line_plot(series, path, x_label="frame", y_label="triangles in the map", title=title)


def write_line_plot(series: dict[str, tuple[np.ndarray, np.ndarray]], path, x_label: str, y_label: str, title: str = "") -> Path:
    """Lines ``label -> (x, y)`` on one chart, written atomically as PNG (800x500)."""
    import pyvista as pv

    chart = pv.Chart2D(x_label=x_label, y_label=y_label)
    for (label, (frames, counts)), colour in zip(series.items(), COLOURS * 4, strict=False):
        chart.line(np.asarray(frames, dtype=float), np.asarray(counts, dtype=float), color=colour, width=2.0, label=label)
    chart.title = title
    chart.legend_visible = len(series) > 1
    plotter = pv.Plotter(off_screen=True, window_size=(800, 500))
    try:
        plotter.add_chart(chart)
        picture = plotter.screenshot(return_img=True)
    finally:
        plotter.close()
    write_png(picture, path)
    return Path(path)


def write_png(picture: np.ndarray, path) -> Path:
    """Write an (H, W, 3|4) uint8 picture as PNG, atomically; encoded in memory and written with
    Python, so a full disk raises (:class:`~mabdi.errors.WriteError`) instead of leaving a short file."""
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(picture)).save(buffer, format="PNG")
    with atomic_output(path) as temporary, open(temporary, "wb") as stream:
        stream.write(buffer.getbuffer())
    return Path(path)
