"""The map viewer: a map file or a run folder, coloured by creation frame, by normal or by a layer.

``view(path)`` opens an interactive pyvista window when a display exists;
without one (a robot, a server, CI) it renders a PNG off-screen and returns
its path. Colour modes:

* ``frame``: each face by the frame that created it (viridis, first dark,
  last bright; :func:`mabdi.maps.colours.colours_by_frame`);
* ``normal``: each face by its unoriented normal, seed 000 eqs. 5-7 with
  atan2 (:func:`mabdi.maps.colours.colours_by_normal`);
* any vertex or face layer of the map by name (``cost``, ``roughness``, ...;
  an HDF5 map from ``mabdi run --h5`` has them), on the viridis ramp.

A run folder shows ``world_mesh.vtp`` (or ``.h5``) with the scene
(``scene.vtp``, grey, translucent) and the sensor path (``path.vtp``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from mabdi.errors import ConfigError
from mabdi.io.map_files import load_map
from mabdi.maps.colours import colours_by_frame, colours_by_normal
from mabdi.maps.layers import face_normals


def has_display() -> bool:
    """Whether an interactive window can open (an X or Wayland display, or a desktop OS)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) or sys.platform in ("win32", "darwin")


def _run_files(folder: Path) -> tuple[Path, Path | None, Path | None]:
    for name in ("world_mesh.vtp", "world_mesh.h5", "world_mesh.ply"):
        if (folder / name).is_file():
            scene, path = folder / "scene.vtp", folder / "path.vtp"
            return folder / name, scene if scene.is_file() else None, path if path.is_file() else None
    raise ConfigError(f"{folder}: a run folder needs world_mesh.vtp, .h5 or .ply (none here)")


def face_colours(mesh_map, colour: str) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """(cell RGB uint8, or None) and (point or cell scalars, or None) for a colour mode, plus where scalars live."""
    if colour == "frame":
        frames = mesh_map.face_layers.get("frame")
        if frames is None:
            raise ConfigError("colour 'frame': this map has no face layer 'frame' (maps from mabdi run have it)")
        return colours_by_frame(frames), None, "cell"
    if colour == "normal":
        normals, _ = face_normals(mesh_map.vertices, mesh_map.faces)
        return colours_by_normal(normals), None, "cell"
    if colour in mesh_map.vertex_layers:
        values = np.asarray(mesh_map.vertex_layers[colour])
        return None, values if values.ndim == 1 else np.linalg.norm(values, axis=1), "point"
    if colour in mesh_map.face_layers:
        values = np.asarray(mesh_map.face_layers[colour])
        return None, values if values.ndim == 1 else np.linalg.norm(values, axis=1), "cell"
    layers = sorted(set(mesh_map.vertex_layers) | set(mesh_map.face_layers))
    raise ConfigError(f"unknown colour {colour!r}: use frame, normal or a layer of this map ({', '.join(layers) or 'none'})")


def view(path, colour: str = "frame", screenshot=None, window_size=(1280, 800), interactive: bool | None = None) -> Path | None:
    """Show a map file or run folder; without a display (or with ``screenshot``) write a PNG and return its path."""
    import pyvista as pv

    path = Path(path)
    if not path.exists():
        raise ConfigError(f"view: {path} does not exist")
    scene_file = path_file = None
    map_file = path
    if path.is_dir():
        map_file, scene_file, path_file = _run_files(path)
    mesh_map = load_map(map_file)
    if mesh_map.number_of_faces == 0:
        raise ConfigError(f"view: {map_file} is an empty map (no triangles): nothing to show")
    rgb, scalars, where = face_colours(mesh_map, colour)
    mesh = pv.wrap(mesh_map.to_polydata())
    interactive = has_display() and screenshot is None if interactive is None else interactive
    plotter = pv.Plotter(off_screen=not interactive, window_size=list(window_size))
    plotter.set_background("white")
    if rgb is not None:
        mesh.cell_data["colour"] = rgb
        plotter.add_mesh(mesh, scalars="colour", rgb=True, preference="cell")
    else:
        mesh[colour] = scalars
        plotter.add_mesh(mesh, scalars=colour, preference=where, cmap="viridis", scalar_bar_args={"title": colour})
    if scene_file is not None:
        plotter.add_mesh(pv.read(scene_file), color="lightgrey", opacity=0.2)
    if path_file is not None:
        plotter.add_mesh(pv.read(path_file), color="black", line_width=2)
    plotter.add_text(f"{map_file.name}: {mesh_map.number_of_faces:,} triangles, colour by {colour}", font_size=10, color="black")
    plotter.view_isometric()
    if interactive:
        plotter.show()
        return None
    target = Path(screenshot) if screenshot is not None else map_file.with_name(f"{map_file.stem}_{colour}.png")
    from mabdi.io.atomic import atomic_output

    with atomic_output(target) as temporary:
        plotter.screenshot(str(temporary))
    plotter.close()
    return target
