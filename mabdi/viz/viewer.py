"""The map viewer: a map file or a run folder, coloured by creation frame, by normal or by a layer.

``view(path)`` opens an interactive pyvista window when a display exists;
without one it renders a PNG off-screen and returns its path. Colour modes:
``frame`` (the frame that created each face,
:func:`mabdi.mesh_maps.colours.colours_by_frame`), ``normal`` (seed 000 eqs. 5-7,
:func:`mabdi.mesh_maps.colours.colours_by_normal`), ``rgb`` (the map's vertex
colours) or any vertex or face layer by name, on the viridis ramp. A run
folder shows ``world_mesh.vtp`` (or ``.h5``) with the scene and the path.

Up: from ``up`` when given, else the mean up of the run's cameras
(:func:`view_up`: -y of an OpenCV camera, +z of a LiDAR), snapped to a world
axis within :data:`SNAP_DEGREES`; +z without poses.

Framing: a parallel projection from above and aside (:data:`VIEW_AZIMUTH`,
:data:`VIEW_ELEVATION`) fitted to the map's bounding box (:data:`FILL`),
with a scale bar (metres) and a title giving the map's name, triangles and
size; ``from_frame=N`` looks from frame N's pose in perspective instead.
Details: docs/architecture.md (``mabdi.viz.viewer``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from mabdi.errors import ConfigError
from mabdi.io.mesh_map_files import load_map, map_file
from mabdi.mesh_maps.colours import colours_by_frame, colours_by_normal
from mabdi.mesh_maps.layers import face_normals
from mabdi.mesh_maps.mesh_map import COLOUR_LAYER


def has_display() -> bool:
    """Whether an interactive window can open (an X or Wayland display, or a desktop OS)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) or sys.platform in ("win32", "darwin")


def _run_files(folder: Path) -> tuple[Path, Path | None, Path | None]:
    """A run folder's map (the VTP first: its faces carry the frame that made them), scene and path."""
    scene, path = folder / "scene.vtp", folder / "path.vtp"
    shown = map_file(folder, ("world_mesh.vtp", "world_mesh.h5", "world_mesh.ply"))
    return shown, scene if scene.is_file() else None, path if path.is_file() else None


def face_colours(mesh_map, colour: str) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """(RGB uint8, or None) and (scalars, or None) for a colour mode, plus where they live ("point" or "cell")."""
    if colour == "frame":
        frames = mesh_map.face_layers.get("frame")
        if frames is None:
            raise ConfigError("colour 'frame': this map has no face layer 'frame' (maps from mabdi run have it)")
        return colours_by_frame(frames), None, "cell"
    if colour == "normal":
        normals, _ = face_normals(mesh_map.vertices, mesh_map.faces)
        return colours_by_normal(normals), None, "cell"
    if colour == "rgb":
        rgb = mesh_map.vertex_layers.get(COLOUR_LAYER)
        if rgb is None:
            raise ConfigError(
                f"colour 'rgb': this map has no vertex colours (layer {COLOUR_LAYER}; maps from a source with colour "
                "images have them)"
            )
        return np.asarray(rgb, dtype=np.uint8), None, "point"
    if colour in mesh_map.vertex_layers:
        values = np.asarray(mesh_map.vertex_layers[colour])
        return None, values if values.ndim == 1 else np.linalg.norm(values, axis=1), "point"
    if colour in mesh_map.face_layers:
        values = np.asarray(mesh_map.face_layers[colour])
        return None, values if values.ndim == 1 else np.linalg.norm(values, axis=1), "cell"
    layers = sorted(set(mesh_map.vertex_layers) | set(mesh_map.face_layers))
    raise ConfigError(f"unknown colour {colour!r}: use frame, normal or a layer of this map ({', '.join(layers) or 'none'})")


#: The default view: degrees about up (0 = looking from the horizon's first axis, +x when up is z; -60: from
#: the -y side, a little to +x) and above the horizon.
VIEW_AZIMUTH = -60.0
VIEW_ELEVATION = 35.0
#: The share of the picture's width or height (whichever binds) the map's projected bounding box fills.
FILL = 0.85
#: The cameras' mean up within this many degrees of a world axis (+-x, +-y, +-z) is taken as that axis.
SNAP_DEGREES = 20.0
#: The length of the mean of the cameras' unit up vectors below which they disagree too much to say up (+z then).
MIN_MEAN_UP = 0.3
Z_UP = np.array([0.0, 0.0, 1.0])
_AXES = {"x": 0, "y": 1, "z": 2}


def parse_up(text: str) -> np.ndarray:
    """The unit world vector of ``--up``: an axis (``z``, ``+z``, ``-y``) or three numbers ``x,y,z``."""
    name = str(text).strip().lower()
    sign = -1.0 if name.startswith("-") else 1.0
    if name.lstrip("+-") in _AXES and len(name) <= 2:
        up = np.zeros(3)
        up[_AXES[name.lstrip("+-")]] = sign
        return up
    try:
        up = np.array([float(value) for value in name.split(",")], dtype=np.float64)
    except ValueError:
        up = np.zeros(0)
    if up.shape != (3,) or not np.all(np.isfinite(up)) or np.linalg.norm(up) < 1e-9:
        raise ConfigError(f"view: --up {text!r}: give an axis (x, y, z, -y, ...) or three numbers x,y,z, not all zero")
    return up / np.linalg.norm(up)


def cameras_up(poses, axes: str = "camera") -> np.ndarray | None:
    """The mean of the sensors' up vectors in the world over ``poses`` ((N, 4, 4) world_from_sensor), unnormalised.

    A camera's up is -y of its OpenCV axes (-R[:, 1]); a LiDAR's (``axes="lidar"``: x forward, y left, z up) its
    +z (R[:, 2]). Unit vectors averaged: the length (0 .. 1) says how far they agree. None without poses.
    """
    poses = np.asarray(poses, dtype=np.float64) if poses is not None else np.zeros((0, 4, 4))
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
        return None
    ups = poses[:, :3, 2] if axes == "lidar" else -poses[:, :3, 1]
    ups = ups[np.all(np.isfinite(ups), axis=1)]
    lengths = np.linalg.norm(ups, axis=1)
    ups = ups[lengths > 1e-9] / lengths[lengths > 1e-9, None]
    return ups.mean(axis=0) if len(ups) else None


def _vector(up: np.ndarray) -> str:
    return "(" + ", ".join(f"{round(float(value), 2) + 0.0:.2f}" for value in up) + ")"  # + 0.0: no -0.00


def _axis_name(up: np.ndarray) -> str | None:
    """``+z``, ``-y``, ... when ``up`` is exactly a world axis, else None."""
    index = int(np.argmax(np.abs(up)))
    if abs(up[index]) != 1.0:
        return None
    return ("+" if up[index] > 0 else "-") + "xyz"[index]


def up_from_poses(poses, axes: str = "camera") -> tuple[np.ndarray, str]:
    """(up, why): the unit world vector the sensors' mean up gives (module docs: snapped to a world axis within
    :data:`SNAP_DEGREES`, +z when shorter than :data:`MIN_MEAN_UP` or without poses) and the line that says so."""
    mean = cameras_up(poses, axes)
    sensors = "LiDAR's" if axes == "lidar" else "cameras'"
    if mean is None:
        return Z_UP.copy(), "up: +z (the world's: no poses to take it from; --up sets it)"
    length = float(np.linalg.norm(mean))
    if length < MIN_MEAN_UP:
        return Z_UP.copy(), (
            f"up: +z (the world's: the {sensors} up vectors disagree, their mean {_vector(mean)} is {length:.2f} long; "
            "--up sets it)"
        )
    mean = mean / length
    index = int(np.argmax(np.abs(mean)))
    off = float(np.degrees(np.arccos(min(abs(mean[index]), 1.0))))
    if off <= SNAP_DEGREES:
        axis = np.zeros(3)
        axis[index] = np.sign(mean[index])
        return axis, f"up: {_axis_name(axis)}, the {sensors} mean up {_vector(mean)} snapped ({off:.0f} degrees off)"
    return mean, f"up: {_vector(mean)}, the {sensors} mean up"


def _sensor_axes(folder: Path) -> str:
    """``"lidar"`` when the run's ``config.toml`` says ``[sensor] kind = "lidar"`` (its poses are then the LiDAR's
    own axes), else ``"camera"``."""
    import tomllib

    config = folder / "config.toml"
    if not config.is_file():
        return "camera"
    try:
        kind = tomllib.loads(config.read_text()).get("sensor", {}).get("kind")
    except (tomllib.TOMLDecodeError, OSError, AttributeError):
        return "camera"
    return "lidar" if kind == "lidar" else "camera"


def view_up(path, up=None, mesh_map=None) -> tuple[np.ndarray, str]:
    """(up, line): the world's up direction (unit vector) for viewing a run folder or map file, and the line that
    says where it came from (module docs). ``up``: the ``--up`` text or a vector, taken as given; ``mesh_map``:
    the map already loaded from a map file (its own poses, an ``.h5``'s)."""
    if up is not None:
        vector = parse_up(up) if isinstance(up, str) else parse_up(",".join(str(float(v)) for v in np.ravel(up)))
        name = _axis_name(vector)
        return vector, f"up: {name if name else _vector(vector)}, given"
    path = Path(path)
    if path.is_dir():
        poses_file = path / "poses.npy"
        poses = np.load(poses_file, allow_pickle=False) if poses_file.is_file() else None
        return up_from_poses(poses, _sensor_axes(path))
    if mesh_map is None:
        mesh_map = load_map(path)
    return up_from_poses(mesh_map.poses, _sensor_axes(path.parent))


def horizon_axes(up) -> tuple[np.ndarray, np.ndarray]:
    """(first, second): unit vectors across the horizon of ``up`` with (first, second, up) right-handed. The first
    is the world axis most across ``up`` (x before y before z on a tie), made level: x and y when up is +z;
    x and z when up is -y (so the default view comes from -z, behind a y-down world's first camera)."""
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    index = int(np.argmin(np.round(np.abs(up), 12)))
    first = np.eye(3)[index] - up * up[index]
    first /= np.linalg.norm(first)
    return first, np.cross(up, first)


def view_direction(azimuth: float = VIEW_AZIMUTH, elevation: float = VIEW_ELEVATION, up=Z_UP) -> np.ndarray:
    """Unit vector (world frame) from the map's centre towards the camera: ``azimuth`` degrees about ``up`` from
    the first of :func:`horizon_axes`, ``elevation`` degrees above the horizon."""
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    first, second = horizon_axes(up)
    a, e = np.radians(azimuth), np.radians(elevation)
    return np.cos(e) * (np.cos(a) * first + np.sin(a) * second) + np.sin(e) * up


def box_corners(bounds) -> np.ndarray:
    """(8, 3) corners of a VTK bounds tuple (xmin, xmax, ymin, ymax, zmin, zmax)."""
    x, y, z = bounds[0:2], bounds[2:4], bounds[4:6]
    return np.array([[a, b, c] for a in x for b in y for c in z], dtype=np.float64)


def fit_parallel_camera(camera, bounds, aspect: float, direction=None, fill: float = FILL, up=Z_UP) -> float:
    """Point a parallel-projection ``vtkCamera`` along -``direction`` (default: :func:`view_direction` about
    ``up``) at the box ``bounds`` so its eight corners fill ``fill`` of the picture's width or height (``aspect`` =
    width / height), the world's ``up`` up the picture; returns metres per unit of picture height (2 x the
    parallel scale)."""
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    direction = view_direction(up=up) if direction is None else np.asarray(direction, dtype=np.float64)
    direction = direction / np.linalg.norm(direction)
    right = np.cross(up, direction)
    right /= np.linalg.norm(right)
    screen_up = np.cross(direction, right)
    corners = box_corners(bounds)
    centre = corners.mean(axis=0)
    x, y = (corners - centre) @ right, (corners - centre) @ screen_up
    # the picture's centre: the middle of the projected box (not the box's centre, which projects off it)
    middle = centre + right * (x.max() + x.min()) / 2 + screen_up * (y.max() + y.min()) / 2
    half_width, half_height = (x.max() - x.min()) / 2, (y.max() - y.min()) / 2
    scale = max(half_height, half_width / aspect, 1e-6) / fill
    depth = float(np.linalg.norm(corners - centre, axis=1).max()) + 1.0
    camera.ParallelProjectionOn()
    camera.SetFocalPoint(*middle)
    camera.SetPosition(*(middle + direction * depth * 2))
    camera.SetViewUp(*screen_up)
    camera.SetParallelScale(scale)
    return 2 * scale


def scale_bar_length(metres_across: float) -> float:
    """A round length (1, 2 or 5 x 10^k metres) near a fifth of ``metres_across``."""
    target = metres_across / 5
    power = 10.0 ** np.floor(np.log10(target))
    return float(min((m * power for m in (1, 2, 5, 10)), key=lambda length: abs(np.log(length / target))))


def _add_scale_bar(plotter, metres_per_height: float, window_size) -> None:
    """A black bar of a round length in the picture's lower left corner, labelled in metres."""
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
    from vtkmodules.vtkRenderingCore import vtkActor2D, vtkPolyDataMapper2D

    width, height = window_size
    pixels_per_metre = height / metres_per_height
    length = scale_bar_length(width / pixels_per_metre)
    x0, y0 = 0.04 * width, 0.05 * height
    points = vtkPoints()
    for x, y in ((x0, y0), (x0 + length * pixels_per_metre, y0), (x0, y0 - 6), (x0, y0 + 6)):
        points.InsertNextPoint(x, y, 0.0)
    points.InsertNextPoint(x0 + length * pixels_per_metre, y0 - 6, 0.0)
    points.InsertNextPoint(x0 + length * pixels_per_metre, y0 + 6, 0.0)
    lines = vtkCellArray()
    for a, b in ((0, 1), (2, 3), (4, 5)):
        lines.InsertNextCell(2)
        lines.InsertCellPoint(a)
        lines.InsertCellPoint(b)
    bar = vtkPolyData()
    bar.SetPoints(points)
    bar.SetLines(lines)
    mapper = vtkPolyDataMapper2D()
    mapper.SetInputData(bar)
    actor = vtkActor2D()
    actor.SetMapper(mapper)
    actor.GetProperty().SetColor(0.0, 0.0, 0.0)
    actor.GetProperty().SetLineWidth(3)
    plotter.add_actor(actor, reset_camera=False)
    label = f"{length:g} m" if length >= 1 else f"{length * 100:g} cm"
    plotter.add_text(label, position=(int(x0), int(y0 + 10)), font_size=10, color="black")


def _frame_pose(run_folder: Path | None, frame: int):
    """(pose, intrinsics) of frame ``frame`` of a run folder: ``poses.npy`` and ``summary.json``'s intrinsics."""
    import json

    from mabdi.camera import Intrinsics

    if run_folder is None:
        raise ConfigError("view: --from-frame needs a run folder (its poses.npy), not a map file")
    poses_file = run_folder / "poses.npy"
    if not poses_file.is_file():
        raise ConfigError(f"view: --from-frame: {poses_file} is missing")
    poses = np.load(poses_file, allow_pickle=False)
    if not 0 <= frame < len(poses):
        raise ConfigError(f"view: --from-frame {frame}: {poses_file} holds frames 0 .. {len(poses) - 1}")
    intrinsics = Intrinsics()
    summary = run_folder / "summary.json"
    if summary.is_file():
        stored = json.loads(summary.read_text()).get("intrinsics")
        if stored:
            intrinsics = Intrinsics(**stored)
    return poses[frame], intrinsics


def view(
    path, colour: str = "frame", screenshot=None, window_size=(1280, 800), interactive: bool | None = None,
    from_frame: int | None = None, up=None, log=None,
) -> Path | None:
    """Show a map file or run folder; without a display (or with ``screenshot``) write a PNG and return its path.

    The camera frames the map (see the module docs) with ``up`` (``--up`` text, a vector, or None: from the run,
    :func:`view_up`) up the picture, or looks from the pose of frame ``from_frame`` of a run. ``log`` (a callable
    taking a line, e.g. ``print``) is told which up was used.
    """
    import pyvista as pv

    path = Path(path)
    if not path.exists():
        raise ConfigError(f"view: {path} does not exist")
    scene_file = path_file = None
    map_file = path
    if path.is_dir():
        map_file, scene_file, path_file = _run_files(path)
    pose = None
    if from_frame is not None:
        pose, intrinsics = _frame_pose(path if path.is_dir() else None, from_frame)
        window_size = (window_size[0], int(round(window_size[0] * intrinsics.height / intrinsics.width)))
    mesh_map = load_map(map_file)
    if mesh_map.number_of_faces == 0:
        raise ConfigError(f"view: {map_file} is an empty map (no triangles): nothing to show")
    rgb, scalars, where = face_colours(mesh_map, colour)
    if pose is None:
        up_vector, line = view_up(path, up, mesh_map)
        if log is not None:
            log(line)
    elif up is not None:
        view_up(path, up)  # checked, though the frame's pose sets the picture's up
    mesh = pv.wrap(mesh_map.to_polydata())
    interactive = has_display() and screenshot is None if interactive is None else interactive
    plotter = pv.Plotter(off_screen=not interactive, window_size=list(window_size))
    plotter.set_background("white")
    if rgb is not None:
        (mesh.point_data if where == "point" else mesh.cell_data)["colour"] = rgb
        plotter.add_mesh(mesh, scalars="colour", rgb=True, preference=where)
    else:
        mesh[colour] = scalars
        plotter.add_mesh(mesh, scalars=colour, preference=where, cmap="viridis", scalar_bar_args={"title": colour})
    if scene_file is not None:
        plotter.add_mesh(pv.read(scene_file), color="lightgrey", opacity=0.2)
    if path_file is not None:
        plotter.add_mesh(pv.read(path_file), color="black", line_width=2)
    bounds = mesh.bounds
    size = " x ".join(f"{bounds[2 * i + 1] - bounds[2 * i]:.2f}" for i in range(3))
    name = f"{path.name}/{map_file.name}" if path.is_dir() else map_file.name
    title = f"{name}: {mesh_map.number_of_faces:,} triangles, {size} m (x y z), colour by {colour}"
    if pose is not None:
        from mabdi.camera import configure_vtk_camera

        configure_vtk_camera(plotter.camera, intrinsics, pose)
        plotter.renderer.ResetCameraClippingRange()
        title += f", from frame {from_frame}"
    else:
        metres = fit_parallel_camera(plotter.camera, bounds, window_size[0] / window_size[1], up=up_vector)
        plotter.renderer.ResetCameraClippingRange()  # the scene and the path, where they reach past the map, too
        _add_scale_bar(plotter, metres, window_size)
    plotter.add_text(title, font_size=10, color="black")
    if interactive:
        plotter.show()
        return None
    target = Path(screenshot) if screenshot is not None else map_file.with_name(f"{map_file.stem}_{colour}.png")
    from mabdi.io.atomic import atomic_output

    with atomic_output(target) as temporary:
        plotter.screenshot(str(temporary))
    plotter.close()
    return target
