"""Typed run configs, loaded from TOML.

A file in ``scenes/`` is a whole run config: ``[run]`` (frames, seed),
``[scene]`` (the objects), ``[sensor]`` (kind, noise model, backend; a
sub-table per thing it describes: ``[sensor.camera]``, ``[sensor.lidar]``,
``[sensor.noise_parameters]``, ``[sensor.pose_noise]``), ``[path]`` (a helix, waypoints or a trajectory), ``[classifier]`` (on/off and thresholds),
``[removal]`` and ``[refinement]`` (their rules, when the classifier turns
them on), ``[registration]`` (frame-to-map registration of each frame's
pose, :mod:`mabdi.stages.registration`), ``[surface]`` (which surface filter, and ``[surface.<name>]`` its
parameters) and ``[output]`` (what is written). Every section and key has a
default, so a config states only what differs. An unknown or misspelt key, a
value of the wrong type, or a value out of range is a :class:`ConfigError`
that names the file and the key.

One home for every parameter: where a section configures a filter, the
section *is* that filter's parameter dataclass (``[classifier]`` is
:class:`~mabdi.stages.classifier.ClassifierParameters`, ``[surface.quadtree]``
is :class:`~mabdi.surfaces.quadtree.QuadTreeParameters`, ...), whose defaults
and checks are written once, in the filter's module; this module only reads
TOML into them and adds the file and key to their error messages. Those
dataclasses are frozen: change values with :func:`with_overrides` (dotted keys such as
``"classifier.enabled"``, ``"surface.quadtree.n_t"``; a new config, checked as a file is) or, in
place, :func:`set_value`.

``load_run_config(path)`` reads a file; ``dump_toml(config)`` writes the
resolved config back. A run saves it as its ``config.toml``
(:func:`run_config_toml`), followed by a ``[resolved]`` table, what the
loop's "auto" settings became for its sensor and source: a record, skipped
when the file is loaded (every "auto" is resolved again). Keys that moved
(:data:`MOVED_KEYS`: older configs' flat ``[sensor] fx``, ``beams``, ...)
load as their new names. Relative mesh paths in a config are resolved
against the config file's folder.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import math
import re
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

from mabdi.camera import Intrinsics
from mabdi.errors import ConfigError, check_switch
from mabdi.io.toml_writer import toml_lines
from mabdi.stages.classifier import ClassifierParameters
from mabdi.stages.refinement import RefinementParameters
from mabdi.stages.registration import RegistrationParameters
from mabdi.stages.removal import RemovalParameters
from mabdi.render.depth_image import BACKENDS
from mabdi.sensor_noise import NOISE_MODELS, RANGE_NOISE_MODELS, SensorNoise
from mabdi.surfaces.registry import surface_filter, surface_filter_names
from mabdi.pose_noise import PoseNoise
from mabdi.spherical import SphericalGeometry

PRIMITIVES = ("box", "cylinder", "sphere", "plane")
#: ``[sensor] kind``: a depth camera (the default) or a spinning LiDAR (range images).
SENSOR_KINDS = ("pinhole", "lidar")
OBJECT_TYPES = (*PRIMITIVES, "mesh")
ANCHORS = ("bottom", "center", "origin")
AXES = ("x", "y", "z", "-x", "-y", "-z", "+x", "+y", "+z")


@dataclass
class ObjectConfig:
    """One object of a scene: a primitive or a mesh asset, its pose, size and schedule.

    Placement: the object is scaled, turned so its ``up`` axis points along
    world z (or rotated by ``rotation``, a 3x3 matrix), turned by ``yaw``
    degrees about world z, then moved so its ``anchor`` lands on
    ``position``: ``bottom`` = centre of the bounding box's bottom face (the
    default: objects stand on the floor at z = position[2]), ``center`` = the
    bounding box centre, ``origin`` = the model's own origin.

    Size: ``box`` takes ``size`` [x, y, z]; ``plane`` ``size`` [x, y] (a
    horizontal rectangle, both faces visible); ``sphere`` ``radius``;
    ``cylinder`` ``radius`` and ``height`` (capped, axis along z); ``mesh``
    (``mesh = "bunny"`` or a PLY/OBJ/STL/VTP path) is scaled by ``scale``
    (a factor) or, if ``height`` is given, uniformly to that height (m).

    Schedule: the object exists at frames ``appear_at <= i < disappear_at``.
    An integer is a frame number; a float in [0, 1] is a fraction of the run
    (0.5 = half way, rounded to the nearest frame).

    Colour: ``colour`` = [r, g, b], integers 0-255 (sRGB): the simulated
    sensor's colour image shows the object flat in that colour (no lighting),
    so a coloured map can be checked pixel for pixel. Objects without it are
    :data:`DEFAULT_COLOUR` grey.
    """

    type: str = "box"
    name: str = ""
    mesh: str = ""
    size: list[float] = field(default_factory=list)
    radius: float = 0.5
    height: float | None = None
    scale: float = 1.0
    resolution: int = 32
    position: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    yaw: float = 0.0
    up: str = "z"
    rotation: list[list[float]] | None = None
    anchor: str = "bottom"
    appear_at: int | float | None = None
    disappear_at: int | float | None = None
    colour: list[int] | None = None


#: The colour (sRGB, 0-255) of a scene object without ``colour``.
DEFAULT_COLOUR = (200, 200, 200)


@dataclass
class SceneConfig:
    """The world: a list of objects (``[[scene.objects]]`` tables)."""

    objects: list[ObjectConfig] = field(default_factory=list)


@dataclass
class CameraConfig:
    """``[sensor.camera]``: a depth camera's pinhole intrinsics (pixels) and depth range (metres).

    The keys, defaults and checks are :class:`mabdi.camera.Intrinsics`' (a
    Kinect-v1-like 640 x 480, f = 525 px); :meth:`intrinsics` builds it. They
    are checked when the whole config is (a principal point inside the image
    width, say), so ``--set`` may change them one at a time.
    """

    width: int = Intrinsics.width
    height: int = Intrinsics.height
    fx: float = Intrinsics.fx
    fy: float = Intrinsics.fy
    cx: float = Intrinsics.cx
    cy: float = Intrinsics.cy
    near: float = Intrinsics.near
    far: float = Intrinsics.far

    def intrinsics(self) -> Intrinsics:
        return Intrinsics(self.fx, self.fy, self.cx, self.cy, self.width, self.height, self.near, self.far)


@dataclass
class LidarConfig:
    """``[sensor.lidar]``: a spinning LiDAR's range image, and its sweep and mount.

    The range image (:class:`mabdi.spherical.SphericalGeometry`, whose defaults
    are a 64-beam Velodyne HDL-64E's): ``beams`` rows by ``columns`` azimuth
    steps over 360 degrees, beams from ``fov_up`` to ``fov_down`` degrees of
    elevation, or at the ``beam_elevations`` given, returns between
    ``range_min`` and ``range_max`` metres. The path gives a LiDAR's poses in
    its own axes (:func:`mabdi.simulate.path.path_from_config`, ``axes="lidar"``).

    The sweep and mount (:mod:`mabdi.simulate.lidar_sweep`): ``sweep`` is
    ``"instant"`` (the default: each range image rendered from the frame's
    pose, every return at its pixel's centre) or ``"deskewed"`` (the sensor
    moves during its sweep: each column fired at its own time from the path's
    pose then, the sweep ending at the frame's pose and timestamp, the returns
    deskewed with the path's true poses into the sensor frame of that pose and
    binned into the range image as a recorded scan is,
    :func:`mabdi.sources.range_images.range_image`; needs Open3D).
    ``sweep_time`` is the seconds one sweep takes (0, the default: the time
    between frames, the path's 1 / ``rate``). ``mount_tilt`` and
    ``mount_roll`` (degrees, 0) turn the sensor on the path's pose,
    ``base_from_sensor = R_y(mount_tilt) R_x(mount_roll)`` (positive tilt tips
    its forward x axis down, positive roll lifts its left side); the frames'
    poses are the path's times the mount, so the range image is in the tilted
    sensor's frame. A camera (``kind = "pinhole"``) with a sweep or mount set
    is an error.
    """

    beams: int = SphericalGeometry.beams
    columns: int = SphericalGeometry.columns
    fov_up: float = SphericalGeometry.fov_up
    fov_down: float = SphericalGeometry.fov_down
    range_min: float = SphericalGeometry.range_min
    range_max: float = SphericalGeometry.range_max
    beam_elevations: list[float] = field(default_factory=list)
    sweep: str = "instant"
    sweep_time: float = 0.0
    mount_tilt: float = 0.0
    mount_roll: float = 0.0

    def geometry(self) -> SphericalGeometry:
        """The LiDAR's range-image geometry."""
        return SphericalGeometry(
            self.beams, self.columns, self.fov_up, self.fov_down, self.range_min, self.range_max, tuple(self.beam_elevations)
        )

    def sweep_settings(self):
        """The sweep and mount (:class:`mabdi.simulate.lidar_sweep.SweepSettings`)."""
        from mabdi.simulate.lidar_sweep import SweepSettings

        return SweepSettings(self.sweep, self.sweep_time, self.mount_tilt, self.mount_roll)


@dataclass
class NoiseParameters:
    """``[sensor.noise_parameters]``: the parameters of the depth noise models (``[sensor] noise`` names the model).

    Defaults and checks are :class:`mabdi.sensor_noise.SensorNoise`'s (its
    module says where each default comes from). ``zbuffer`` (seed 001:
    d + d N(0, zbuffer_sigma) on the normalised z-buffer value d); ``kinect``
    (axial sigma(z) = kinect_coefficient z^2 metres, Khoshelham & Elberink
    2012); ``structured_light`` (a Kinect-v1-like camera by default:
    correlated noise of ``disparity_sigma`` pixels, over
    ``correlation_length`` pixels, on the disparity f b / z with f the
    camera's ``fx`` and b = ``baseline``, quantised to ``disparity_step``
    pixels, so sigma grows with z^2; no returns within ``edge_dropout`` pixels
    of a depth jump larger than ``edge_jump`` or beyond ``max_incidence``
    degrees of incidence); ``range``, a LiDAR's (Gaussian of ``range_sigma``
    metres along the beam, the HDL-64E S2 datasheet's accuracy by default).
    """

    zbuffer_sigma: float = SensorNoise.zbuffer_sigma
    kinect_coefficient: float = SensorNoise.kinect_coefficient
    baseline: float = SensorNoise.baseline
    disparity_sigma: float = SensorNoise.disparity_sigma
    disparity_step: float = SensorNoise.disparity_step
    correlation_length: float = SensorNoise.correlation_length
    edge_dropout: int = SensorNoise.edge_dropout
    edge_jump: float = SensorNoise.edge_jump
    max_incidence: float = SensorNoise.max_incidence
    range_sigma: float = SensorNoise.range_sigma


@dataclass
class SensorConfig:
    """``[sensor]``: what the sensor is (``kind``), its noise model, render backend and hole filling; a
    sub-table for each thing it describes.

    ``kind`` is ``pinhole`` (the default: a depth camera, ``[sensor.camera]``,
    :class:`CameraConfig`) or ``lidar`` (a spinning LiDAR whose images are
    range images, ``[sensor.lidar]``, :class:`LidarConfig`). ``noise`` names
    the depth noise model: ``none``, ``zbuffer``, ``kinect``,
    ``structured_light`` or ``auto`` (the camera's sigma(z) learnt from the
    run, :mod:`mabdi.noise_calibration`) for a camera; ``none`` or ``range``
    for a LiDAR; the models' parameters are ``[sensor.noise_parameters]``
    (:class:`NoiseParameters`). ``backend``: the render backend.
    ``fill_pixel_holes`` (true, false or ``"auto"``, the default): a camera's
    one-pixel holes filled where the pixels on either side agree
    (:mod:`mabdi.depth_holes`); "auto" on fragmented frames only, as depth
    registered to a colour camera gives.

    ``[sensor.pose_noise]`` (:class:`mabdi.pose_noise.PoseNoise`): jitter and
    drift of the poses the frames carry, while the sensor renders from the
    true ones (``jitter_translation`` m, ``jitter_rotation`` degrees per frame;
    ``drift_translation``, ``drift_rotation``: the random walk's spread after
    one metre travelled, growing with sqrt(distance)); zero: exact poses.

    Older configs wrote every key flat under ``[sensor]`` (``fx``, ``beams``,
    ``range_sigma``, ``mount_tilt``, ...): they load as the sub-tables' keys
    (:data:`MOVED_KEYS`). A run's resolved config writes the table of the
    sensor's own kind whole, and the other kind's only where it is set.
    """

    kind: str = "pinhole"
    noise: str = SensorNoise.model
    backend: str = BACKENDS[0]
    fill_pixel_holes: bool | str = "auto"
    camera: CameraConfig = field(default_factory=CameraConfig)
    lidar: LidarConfig = field(default_factory=LidarConfig)
    noise_parameters: NoiseParameters = field(default_factory=NoiseParameters)
    pose_noise: PoseNoise = field(default_factory=PoseNoise)

    def intrinsics(self) -> Intrinsics:
        """The camera's intrinsics (``[sensor.camera]``)."""
        return self.camera.intrinsics()

    def geometry(self) -> Intrinsics | SphericalGeometry:
        """The sensor's geometry: the camera's intrinsics (``kind = "pinhole"``) or the LiDAR's range image (``"lidar"``)."""
        return self.lidar.geometry() if self.kind == "lidar" else self.camera.intrinsics()

    def sensor_noise(self) -> SensorNoise:
        return SensorNoise.from_config(self)

    def sweep_settings(self):
        """The LiDAR's sweep and mount (:meth:`LidarConfig.sweep_settings`)."""
        return self.lidar.sweep_settings()


#: The sub-tables ``[sensor]`` is split into, by what each describes: name -> its dataclass.
SENSOR_TABLES = {"camera": CameraConfig, "lidar": LidarConfig, "noise_parameters": NoiseParameters}


@dataclass
class PathConfig:
    """The sensor's path: a helix (the default), waypoints a robot drives, or a recorded trajectory.

    ``kind = "helix"`` (:func:`mabdi.simulate.helical_path`, which takes its
    defaults from here), metres and degrees: ``center`` (x, y) of the ellipse
    with radii ``radius_x``, ``radius_y``; heights from ``z0`` to ``z1``; the
    sensor looks at a point moving from ``look_from`` to ``look_to``;
    ``turns`` circles starting at ``start_angle`` (-90 = on the -y side of the
    centre). ``run.frames`` frames span the whole helix.

    ``kind = "waypoints"``: ``points`` is a polyline driven at ``speed`` (m/s),
    one frame every 1 / ``rate`` seconds, starting on the first point. Rows
    are ``[x, y, z]`` (the heading follows the direction of travel),
    ``[x, y, z, heading]`` (heading in degrees, counter-clockwise from +x,
    turned through the shorter angle between waypoints) or full poses
    ``[x, y, z, qx, qy, qz, qw]`` (world_from_sensor, rotation slerped).
    ``kind = "trajectory"``: ``file`` is a TUM trajectory (``timestamp tx ty
    tz qx qy qz qw`` per line, world_from_sensor; relative to the config
    file), one frame per pose. Without ``run.frames`` in the config, a run
    takes every frame of such a path (waypoints: floor(length * rate / speed)
    + 1); with it, the first ``run.frames`` of them
    (:mod:`mabdi.simulate.path` has the details).
    """

    kind: str = "helix"
    center: list[float] = field(default_factory=lambda: [0.0, 0.0])
    radius_x: float = 2.5
    radius_y: float = 2.5
    z0: float = 1.2
    z1: float = 1.8
    look_from: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.5])
    look_to: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.8])
    turns: float = 2.0
    start_angle: float = -90.0
    points: list[list[float]] = field(default_factory=list)
    speed: float = 1.0
    rate: float = 10.0
    file: str = ""


@dataclass(eq=False)
class SurfaceConfig:
    """Which surface filter meshes the novel pixels, and the parameters of each.

    ``method`` names a filter of the surface registry
    (:mod:`mabdi.surfaces.registry`: ``pixel_grid``, ``quadtree``,
    ``voxel_planes`` and any filter registered at run time). Each filter's
    parameters are a sub-table named after it, e.g. ``[surface.quadtree]
    n_t = 0.05``; its keys, defaults and checks are the filter's own
    parameter dataclass (``PixelGridParameters``, ``QuadTreeParameters``,
    ``VoxelPlanesParameters``). Sub-tables of filters other than ``method``
    are checked and kept, so one config can switch surfaces with ``--surface``.
    """

    method: str = "quadtree"
    #: Parameters by surface name, as given in the config (the rest take the defaults).
    parameters: dict = field(default_factory=dict, metadata={"toml": False})

    def parameters_of(self, name: str | None = None):
        """The parameter dataclass of surface ``name`` (default: ``method``), defaults filled in."""
        name = self.method if name is None else name
        given = self.parameters.get(name)
        return given if given is not None else surface_filter(name).parameters()

    def __eq__(self, other) -> bool:
        """Equal when the method and every surface's parameters (defaults filled in) are equal."""
        if not isinstance(other, SurfaceConfig):
            return NotImplemented
        names = (set(self.parameters) | set(other.parameters)) & set(surface_filter_names())
        return self.method == other.method and all(self.parameters_of(n) == other.parameters_of(n) for n in names)


@dataclass
class OutputConfig:
    """What a run writes. ``dir`` defaults to ``runs/<run.name>`` (relative to the working folder).

    ``depth_images``: also write D, E and the labels of every frame as VTI
    (about 1 MB per frame each). ``h5``: also write ``world_mesh.h5`` (Mesh
    Tools layout, :mod:`mabdi.io.hdf5`) with its cost layers, colours by
    normal, the creation frame of each face, a ``floor`` label, planar
    clusters, and the run's poses and intrinsics. ``movie``: ``mabdi run``
    also writes ``movie.mp4``, the six-panel dashboard of every frame
    (:mod:`mabdi.viz`), and ``dashboard_<frame>.png`` for the frames in
    ``snapshots`` (empty: the first, middle and last). ``checkpoint_every``:
    save the loop's state every N frames (0: never), so ``mabdi run --resume``
    can finish an interrupted run; the checkpoint goes when the run completes.
    "auto": every 10 frames, spaced further apart once writing them would take
    more than a twentieth of the loop's time (a large map's state takes seconds
    to write; :class:`mabdi.loop.run_pipeline.Checkpoints`).
    """

    dir: str = ""
    vtp: bool = True
    ply: bool = True
    h5: bool = False
    depth_images: bool = False
    movie: bool = False
    snapshots: list[int] = field(default_factory=list)
    checkpoint_every: int | str = "auto"


@dataclass
class RunSection:
    """Run-wide settings: a name (a plain folder name: the default output is ``runs/<name>``),
    the number of frames (iterations) and the noise seed."""

    name: str = ""
    frames: int = 30
    seed: int = 0


@dataclass
class RunConfig:
    """A whole run: what a file in ``scenes/`` holds."""

    run: RunSection = field(default_factory=RunSection)
    scene: SceneConfig = field(default_factory=SceneConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    path: PathConfig = field(default_factory=PathConfig)
    classifier: ClassifierParameters = field(default_factory=ClassifierParameters)
    removal: RemovalParameters = field(default_factory=RemovalParameters)
    refinement: RefinementParameters = field(default_factory=RefinementParameters)
    registration: RegistrationParameters = field(default_factory=RegistrationParameters)
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    #: The file this config was read from (not a TOML key).
    source: Path | None = field(default=None, compare=False, repr=False, metadata={"toml": False})
    #: Whether ``run.frames`` was taken from a waypoint or trajectory path (the config left it out): changing a
    #: ``path`` key with :func:`set_value` then takes it again (not a TOML key).
    frames_from_path: bool = field(default=False, compare=False, repr=False, metadata={"toml": False})
    #: The dotted keys the config file or an override set (``"sensor.noise"``, ``"run.frames"``, ...), to tell a
    #: key left unset from one set to its default value (not a TOML key). A config read back from a run's
    #: resolved ``config.toml`` states every key it writes.
    stated: frozenset = field(default=frozenset(), compare=False, repr=False, metadata={"toml": False})


# ---------------------------------------------------------------------------
# Loading


def load_run_config(path) -> RunConfig:
    """Read and validate a run config file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: run config not found")
    try:
        with path.open("rb") as handle:
            data = tomllib.load(handle)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    config = run_config_from_dict(data, where=str(path), base_dir=path.resolve().parent)
    config.source = path.resolve()
    return config


def run_config_from_dict(data: dict, where: str = "<config>", base_dir=None, validate: bool = True) -> RunConfig:
    """Build and validate a :class:`RunConfig` from parsed TOML (``where`` names the file in errors).

    A waypoint or trajectory ``[path]`` without ``run.frames`` sets it to the path's own number of frames
    (:func:`mabdi.simulate.routes.path_frame_count`; a trajectory ``file`` is relative to ``base_dir``).
    ``validate=False`` leaves out the checks across sections (:func:`validate_run_config`).
    """
    from mabdi.simulate.routes import check_path_keys

    data = moved_keys({k: v for k, v in data.items() if k != RESOLVED_TABLE}, where)  # [resolved]: a run's record
    config = _build(RunConfig, data, where, "")
    path_table = data.get("path", {})
    check_path_keys(config.path, list(path_table) if isinstance(path_table, dict) else [], where)
    run_table = data.get("run", {})
    if config.path.kind != "helix" and not (isinstance(run_table, dict) and "frames" in run_table):
        config.frames_from_path = True
        _frames_from_path(config, where, base_dir)
    config.stated = stated_keys(data)
    if validate:
        validate_run_config(config, where)
    return config


#: Keys that moved: old dotted name -> new one. Old configs (and the resolved config.toml of older run folders)
#: keep loading, from files and ``--set``: their keys are read as the new ones. The stages' switches moved to
#: their own sections; the flat ``[sensor]`` keys to the sub-table of what they describe (:data:`SENSOR_TABLES`).
MOVED_KEYS = {
    "classifier.removal": "removal.enabled",
    "classifier.refinement": "refinement.enabled",
    **{
        f"sensor.{f.name}": f"sensor.{table}.{f.name}"
        for table, cls in SENSOR_TABLES.items()
        for f in dataclasses.fields(cls)
    },
}


def moved_keys(data: dict, where: str) -> dict:
    """Parsed TOML ``data`` with the keys of :data:`MOVED_KEYS` under their new names (a copy where one moved;
    a new key may lie in a sub-table, ``sensor.camera.fx``); an old key and its new one both given, with
    different values, is an error naming both."""
    moved = None
    for old, new in MOVED_KEYS.items():
        *old_tables, old_key = old.split(".")
        table = _table_at(data if moved is None else moved, old_tables)
        if table is None or old_key not in table:
            continue
        if moved is None:
            moved = copy.deepcopy(data)
            table = _table_at(moved, old_tables)
        value = table.pop(old_key)
        *new_tables, new_key = new.split(".")
        target = moved
        for depth, name in enumerate(new_tables):
            target = target.setdefault(name, {})
            if not isinstance(target, dict):
                raise ConfigError(f"{where}: '{'.'.join(new_tables[: depth + 1])}' must be a table")
        if new_key in target and target[new_key] != value:
            raise ConfigError(
                f"{where}: {old} = {value!r} and {new} = {target[new_key]!r} disagree; {old} is the old name of {new}: keep that one"
            )
        target[new_key] = value
    return data if moved is None else moved


def _table_at(data: dict, names) -> dict | None:
    """The table of parsed TOML ``data`` at the path ``names`` (None where there is none)."""
    for name in names:
        data = data.get(name) if isinstance(data, dict) else None
    return data if isinstance(data, dict) else None


def stated_keys(data: dict, prefix: str = "") -> frozenset:
    """The dotted keys of parsed TOML ``data`` that hold values (tables opened, arrays of tables by their own key)."""
    keys = set()
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        if isinstance(value, dict):
            keys |= stated_keys(value, key)
        else:
            keys.add(key)
    return frozenset(keys)


def _frames_from_path(config: RunConfig, where: str, base_dir=None) -> None:
    """Set ``run.frames`` to the number of frames of the config's waypoint or trajectory path."""
    from mabdi.simulate.routes import path_frame_count

    try:
        config.run.frames = path_frame_count(config.path, base_dir)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _type_name(tp) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _convert(tp, value, where: str, key: str):
    """Check ``value`` against annotation ``tp`` and convert it (int -> float where a float is expected)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(tp)
        if value is None and type(None) in options:
            return None
        for option in options:
            if option is type(None):
                continue
            try:
                return _convert(option, value, where, key)
            except ConfigError:
                continue
        names = " or ".join(_type_name(o) for o in options if o is not type(None))
        raise ConfigError(f"{where}: key '{key}' must be {names}, got {value!r}")
    if origin is list:
        (item_type,) = typing.get_args(tp)
        if not isinstance(value, list):
            raise ConfigError(f"{where}: key '{key}' must be a list, got {value!r}")
        return [_convert(item_type, v, where, f"{key}[{i}]") for i, v in enumerate(value)]
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: '{key}' must be a table, got {value!r}")
        return _build(tp, value, where, key)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: key '{key}' must be a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{where}: key '{key}' must be finite, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: key '{key}' must be an integer, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: key '{key}' must be a string, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: key '{key}' must be true or false, got {value!r}")
        return value
    raise TypeError(f"config field type {tp!r} is not supported")  # a bug in mabdi, not user input


def _build(cls, data: dict, where: str, prefix: str):
    if cls is SurfaceConfig:
        return _build_surface(data, where, prefix)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.metadata.get("toml", True)}
    section = f"[{prefix}]" if prefix else "top level"
    unknown = [k for k in data if k not in fields]
    if unknown:
        raise ConfigError(
            f"{where}: unknown key '{unknown[0]}' in {section} (known keys: {', '.join(fields)}){_sensor_hint(cls, unknown[0])}"
        )
    values = {}
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        values[name] = _convert(hints[name], value, where, key)
    try:
        return cls(**values)
    except ConfigError as exc:  # the dataclass's own checks (one home): add the file and section
        raise ConfigError(f"{where}: {section} {exc}") from None


def _sensor_hint(cls, key: str) -> str:
    """Where an unknown key of a ``[sensor]`` sub-table belongs, when another sub-table has it ("" otherwise)."""
    tables = {**SENSOR_TABLES, "pose_noise": PoseNoise}
    if cls not in tables.values():
        return ""
    owners = [name for name, table in tables.items() if table is not cls and key in {f.name for f in dataclasses.fields(table)}]
    return f"; {key} is a key of [sensor.{owners[0]}]" if owners else ""


def _build_surface(data: dict, where: str, prefix: str) -> SurfaceConfig:
    """``[surface]``: ``method`` and one sub-table per surface filter, each built as that filter's parameters."""
    names = surface_filter_names()
    config = SurfaceConfig()
    for key, value in data.items():
        if key == "method":
            config.method = _convert(str, value, where, f"{prefix}.method")
        elif key in names:
            if not isinstance(value, dict):
                raise ConfigError(f"{where}: '{prefix}.{key}' must be a table of {key}'s parameters, got {value!r}")
            config.parameters[key] = _build(surface_filter(key).parameters, value, where, f"{prefix}.{key}")
        else:
            owners = [n for n in names if key in {f.name for f in dataclasses.fields(surface_filter(n).parameters)}]
            hint = f"; {key} is a parameter of {' and '.join(owners)}: put it in [{prefix}.{owners[0]}]" if owners else ""
            raise ConfigError(
                f"{where}: unknown key '{key}' in [{prefix}] (known keys: method, {', '.join(names)}){hint}"
            )
    return config


def _set_dotted(data: dict, key: str, value, where: str) -> None:
    """Set dotted ``key`` in parsed TOML ``data`` (tables by name, arrays of tables by index)."""
    parts = key.split(".")
    if not all(parts):
        raise ConfigError(f"{where}: key '{key}' is not a dotted key (section.key, or surface.<filter>.key)")
    node = data
    for depth, part in enumerate(parts):
        here = ".".join(parts[:depth]) or "the top level"
        last = depth == len(parts) - 1
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise ConfigError(f"{where}: key '{key}': '{here}' is a list of {len(node)} items, '{part}' is not an index in it")
            if last:
                node[int(part)] = value
            else:
                node = node[int(part)]
        elif isinstance(node, dict):
            if last:
                node[part] = value
            else:
                node = node.setdefault(part, {})
        else:
            raise ConfigError(f"{where}: unknown key '{key}': '{here}' is a value, not a table")


def _overridden(config: RunConfig, overrides: dict, where: str, whole: bool) -> RunConfig:
    data = tomllib.loads(dump_toml(config))
    if config.frames_from_path:  # the frames follow a waypoint or trajectory path unless an override sets them
        data.get("run", {}).pop("frames", None)
    for key, value in overrides.items():
        if key.split(".")[0] == RESOLVED_TABLE:
            raise ConfigError(
                f"{where}: key '{key}': [{RESOLVED_TABLE}] is what a run's \"auto\" settings became, written by the run "
                "and not read; set the section's own key"
            )
        _set_dotted(data, MOVED_KEYS.get(key, key), value, where)  # an old name sets the new key
    base_dir = config.source.parent if config.source is not None else None
    resolved = run_config_from_dict(data, where=where, base_dir=base_dir, validate=whole)
    resolved.source = config.source
    resolved.stated = config.stated | frozenset(MOVED_KEYS.get(key, key) for key in overrides)  # the file's keys and the overrides, not every key dumped
    return resolved


def settings_overrides(settings, where: str = "command line") -> dict:
    """{dotted key: value} of ``--set KEY=VALUE`` settings (TOML value syntax; a bare word is a string:
    ``surface.method=quadtree``), for :func:`with_overrides`; a setting without ``=`` is a ConfigError."""
    overrides = {}
    for setting in settings:
        key, equals, text = setting.partition("=")
        if not equals or not key.strip():
            raise ConfigError(f"{where}: --set wants KEY=VALUE, got {setting!r}")
        try:
            value = tomllib.loads(f"value = {text}")["value"]
        except tomllib.TOMLDecodeError:
            value = text
        overrides[key.strip()] = value
    return overrides


def with_overrides(config: RunConfig, overrides: dict, where: str = "<overrides>", whole: bool = True) -> RunConfig:
    """A new RunConfig: ``config`` with the values of ``overrides`` (dotted key -> value) set, the whole checked.

    The one way a config is changed after it is read (``mabdi run``'s options
    and ``--set``, a sweep's grid and ``[set]``, the bench's methods,
    :func:`set_value`). Keys are dotted paths into the TOML of the config:
    ``"run.frames"``, ``"classifier.enabled"``, a surface filter's parameter
    ``"surface.quadtree.n_t"``, a sub-table's ``"sensor.pose_noise.jitter_rotation"``,
    list items by index ``"scene.objects.0.position"``. The resolved config
    is written as TOML (:func:`dump_toml`), the values are set at their paths,
    and the result is read back by :func:`run_config_from_dict`: every check
    a config file gets (unknown keys, types, ranges, the filters' own
    parameter checks, the checks across sections) runs, and nothing else
    needs to know the config's layout. An error is a :class:`ConfigError`
    naming ``where`` and the key that caused it. ``config`` is not changed;
    the new one keeps its ``source`` (relative mesh paths stay resolved
    against the same folder). ``whole=False`` leaves out the checks across
    sections (:func:`validate_run_config`: a principal point inside the image
    width, say), for a config changed one value at a time.
    """
    try:
        return _overridden(config, overrides, where, whole)
    except ConfigError as exc:
        error, culprit = exc, None
    for key, value in overrides.items():  # the key that fails on its own, when one does
        try:
            _overridden(config, {key: value}, where, whole)
        except ConfigError as alone:
            error, culprit = alone, key
            break
    detail = str(error).removeprefix(f"{where}: ")
    if culprit is None or f"'{culprit}'" in detail:
        raise ConfigError(f"{where}: {detail}") from None
    detail = re.sub(r"^\[[^\]]*\] ", "", detail)  # the section: the key names it
    raise ConfigError(f"{where}: key '{culprit}': {detail}") from None


def set_value(config: RunConfig, key: str, value, where: str = "command line") -> None:
    """Set one value of ``config`` in place by its dotted key: :func:`with_overrides` applied to ``config`` itself.

    The value's type and its section's own checks run; the checks across
    sections wait for :func:`validate_run_config` (a config may pass through
    such a state while its values are set one by one: the width, then cx).
    Raises :class:`ConfigError` naming the key; ``config`` is unchanged then.
    """
    resolved = with_overrides(config, {key: value}, where, whole=False)
    for f in dataclasses.fields(RunConfig):
        setattr(config, f.name, getattr(resolved, f.name))


def _check_choice(value: str, choices, where: str, key: str) -> None:
    if value not in choices:
        raise ConfigError(f"{where}: key '{key}' = {value!r} is not one of: {', '.join(choices)}")


def _check_length(values, length: int, where: str, key: str) -> None:
    if len(values) != length:
        raise ConfigError(f"{where}: key '{key}' must have {length} numbers, got {len(values)}")


def validate_object(obj: ObjectConfig, where: str, key: str) -> None:
    """Range and consistency checks of one scene object (the loader checked types)."""
    _check_choice(obj.type, OBJECT_TYPES, where, f"{key}.type")
    if obj.type != "mesh" and obj.mesh:  # before the size checks: a mesh without type = "mesh" is a box
        raise ConfigError(
            f"{where}: key '{key}.mesh' is only used with type = \"mesh\" (this object's type is {obj.type!r}; "
            "add type = \"mesh\")"
        )
    _check_choice(obj.anchor, ANCHORS, where, f"{key}.anchor")
    _check_choice(obj.up, AXES, where, f"{key}.up")
    _check_length(obj.position, 3, where, f"{key}.position")
    if obj.type == "box":
        _check_length(obj.size, 3, where, f"{key}.size")
    if obj.type == "plane":
        _check_length(obj.size, 2, where, f"{key}.size")
    if obj.type in ("box", "plane") and min(obj.size) <= 0:
        raise ConfigError(f"{where}: key '{key}.size' must be positive, got {obj.size}")
    if obj.type in ("sphere", "cylinder") and obj.radius <= 0:
        raise ConfigError(f"{where}: key '{key}.radius' must be positive, got {obj.radius}")
    if obj.type == "cylinder" and obj.height is None:
        raise ConfigError(f"{where}: key '{key}.height' is required for a cylinder")
    if obj.type in ("box", "sphere", "plane") and obj.height is not None:
        raise ConfigError(f"{where}: key '{key}.height' is not used by a {obj.type} (use size or radius)")
    if obj.height is not None and obj.height <= 0:
        raise ConfigError(f"{where}: key '{key}.height' must be positive, got {obj.height}")
    if obj.type == "mesh" and not obj.mesh:
        raise ConfigError(f"{where}: key '{key}.mesh' is required for type 'mesh' (\"bunny\" or a file path)")
    if obj.scale <= 0:
        raise ConfigError(f"{where}: key '{key}.scale' must be positive, got {obj.scale}")
    if obj.resolution < 3:
        raise ConfigError(f"{where}: key '{key}.resolution' must be at least 3, got {obj.resolution}")
    if obj.rotation is not None:
        if obj.up != "z":
            raise ConfigError(f"{where}: give either '{key}.up' or '{key}.rotation', not both")
        if len(obj.rotation) != 3 or any(len(row) != 3 for row in obj.rotation):
            raise ConfigError(f"{where}: key '{key}.rotation' must be a 3x3 matrix (3 rows of 3 numbers)")
        import numpy as np

        r = np.array(obj.rotation)
        if np.abs(r.T @ r - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0:
            raise ConfigError(f"{where}: key '{key}.rotation' is not a rotation matrix (orthonormal, det +1)")
    if obj.colour is not None:
        _check_length(obj.colour, 3, where, f"{key}.colour")
        if any(not 0 <= c <= 255 for c in obj.colour):
            raise ConfigError(f"{where}: key '{key}.colour' must be [r, g, b] with integers 0-255, got {obj.colour}")
    for name in ("appear_at", "disappear_at"):
        value = getattr(obj, name)
        if isinstance(value, float) and not 0.0 <= value <= 1.0:
            raise ConfigError(
                f"{where}: key '{key}.{name}' = {value} : a float is a fraction of the run in [0, 1]; use an integer for a frame number"
            )
        if isinstance(value, int) and value < 0:
            raise ConfigError(f"{where}: key '{key}.{name}' must be a frame number >= 0, got {value}")


def schedule_frame(value, frames: int) -> int | None:
    """An object's ``appear_at`` / ``disappear_at`` as a frame number (the one rule, used by the scene and the checks):
    ints are frames, floats fractions of ``frames`` (nearest frame).
    """
    if value is None:
        return None
    if isinstance(value, float):
        return int(math.floor(value * frames + 0.5))
    return int(value)


def _check_schedule(obj: ObjectConfig, frames: int, where: str, key: str) -> None:
    """An object must exist at some frame of the run: ``appear_at < disappear_at`` once resolved."""
    appear = schedule_frame(obj.appear_at, frames) or 0
    disappear = schedule_frame(obj.disappear_at, frames)
    if appear >= frames:
        raise ConfigError(
            f"{where}: '{key}' appears at frame {appear} (appear_at = {obj.appear_at!r}), after the run's last "
            f"frame {frames - 1}: it would never be seen"
        )
    if disappear is not None and disappear <= appear:
        raise ConfigError(
            f"{where}: '{key}' disappears (disappear_at = {obj.disappear_at!r}, frame {disappear}) before or when "
            f"it appears (appear_at = {obj.appear_at!r}, frame {appear}): it would never be seen"
        )


def validate_run_config(config: RunConfig, where: str = "<config>") -> None:
    """Range checks across a whole config."""
    if config.run.frames < 1:
        raise ConfigError(f"{where}: key 'run.frames' must be at least 1, got {config.run.frames}")
    if config.run.seed < 0:
        raise ConfigError(f"{where}: key 'run.seed' must be >= 0, got {config.run.seed}")
    name = config.run.name
    if name and (name in (".", "..") or "/" in name or "\\" in name or name != name.strip() or "\0" in name):
        raise ConfigError(
            f"{where}: key 'run.name' = {name!r} must be a plain folder name (no '/', not '..'): "
            "runs are written to runs/<name>; use --out for another place"
        )
    for i, obj in enumerate(config.scene.objects):
        validate_object(obj, where, f"scene.objects[{i}]")
        _check_schedule(obj, config.run.frames, where, f"scene.objects[{i}]")
    sensor = config.sensor
    _check_choice(sensor.kind, SENSOR_KINDS, where, "sensor.kind")
    _check_choice(sensor.noise, RANGE_NOISE_MODELS if sensor.kind == "lidar" else tuple(m for m in NOISE_MODELS if m != "range"), where, "sensor.noise")
    _check_choice(sensor.backend, BACKENDS, where, "sensor.backend")
    try:
        check_switch("sensor.fill_pixel_holes", sensor.fill_pixel_holes)
    except ConfigError as exc:
        raise ConfigError(f"{where}: key {exc}") from None
    for table, check in (  # both geometries, whichever the kind: a value set out of range is an error
        ("camera", sensor.camera.intrinsics),
        ("lidar", sensor.lidar.geometry),
        ("noise_parameters", sensor.sensor_noise),
    ):
        try:
            check()
        except ConfigError as exc:
            raise ConfigError(f"{where}: [sensor.{table}] {exc}") from None
    from mabdi.simulate.lidar_sweep import SWEEP_KEYS, SWEEP_MODES

    lidar = sensor.lidar
    _check_choice(lidar.sweep, SWEEP_MODES, where, "sensor.lidar.sweep")
    try:
        sweep = lidar.sweep_settings()
    except ConfigError as exc:
        raise ConfigError(f"{where}: [sensor.lidar] {exc}") from None
    if sensor.kind != "lidar" and (sweep.deskewed or sweep.mounted or sweep.duration):
        given = [k for k in SWEEP_KEYS if getattr(lidar, k) != getattr(LidarConfig, k)]
        raise ConfigError(
            f"{where}: key 'sensor.lidar.{given[0]}' is a LiDAR's (its sweep and mount); this sensor is kind = {sensor.kind!r}"
        )
    path = config.path
    from mabdi.simulate.routes import PATH_KINDS, waypoint_distances

    _check_choice(path.kind, PATH_KINDS, where, "path.kind")
    if path.kind == "waypoints":
        try:
            waypoint_distances(path)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None
    if path.kind == "trajectory" and not path.file:
        raise ConfigError(f"{where}: key 'path.file' is required for kind = \"trajectory\" (a TUM trajectory file)")
    _check_length(path.center, 2, where, "path.center")
    _check_length(path.look_from, 3, where, "path.look_from")
    _check_length(path.look_to, 3, where, "path.look_to")
    if path.radius_x <= 0 or path.radius_y <= 0:
        raise ConfigError(f"{where}: keys 'path.radius_x' and 'path.radius_y' must be positive")
    if path.turns <= 0:
        raise ConfigError(f"{where}: key 'path.turns' must be positive, got {path.turns}")
    names = surface_filter_names()
    _check_choice(config.surface.method, names, where, "surface.method")
    every = config.output.checkpoint_every
    if (isinstance(every, str) and every != "auto") or (isinstance(every, int) and every < 0):
        raise ConfigError(f"{where}: key 'output.checkpoint_every' must be \"auto\" or >= 0 frames (0: no checkpoints), got {every!r}")


# ---------------------------------------------------------------------------
# Writing (the resolved config saved with a run)


def _toml_table(obj) -> dict:
    """A config dataclass as the dict :func:`mabdi.io.toml_writer.toml_lines` writes: fields in order, ``None``
    (the default of an absent key) and fields marked ``toml=False`` left out; a surface section holds its method and
    the parameters of every surface filter it names; ``[sensor]`` the other kind's table (a camera's
    ``[sensor.lidar]``) only with the keys set away from their defaults."""
    if isinstance(obj, SurfaceConfig):
        table = {"method": obj.method}
        for name in sorted(set(obj.parameters) | {obj.method}):
            if name in surface_filter_names():
                table[name] = _toml_table(obj.parameters_of(name))
        return table
    table = {}
    for f in dataclasses.fields(obj):
        if not f.metadata.get("toml", True):
            continue
        if isinstance(obj, PathConfig) and not _path_key_written(obj, f.name):
            continue
        value = getattr(obj, f.name)
        if value is None:
            continue  # absent key = default None
        if dataclasses.is_dataclass(value):
            table[f.name] = _toml_table(value)
            if isinstance(obj, SensorConfig) and f.name == _OTHER_KIND_TABLE.get(obj.kind):
                default = _toml_table(type(value)())  # the other kind's table: only the keys set
                table[f.name] = {k: v for k, v in table[f.name].items() if v != default[k]}
                if not table[f.name]:
                    del table[f.name]
        elif isinstance(value, list) and value and dataclasses.is_dataclass(value[0]):
            table[f.name] = [_toml_table(item) for item in value]
        else:
            table[f.name] = value
    return table


#: ``[sensor]``'s sub-table of the other kind of sensor, written only where set (a camera's runs write no LiDAR).
_OTHER_KIND_TABLE = {"pinhole": "lidar", "lidar": "camera"}


def _path_key_written(path: PathConfig, name: str) -> bool:
    """Whether a ``[path]`` key is written: those of its kind (``kind`` itself unless it is the default helix)."""
    from mabdi.simulate.routes import KIND_KEYS

    if name == "kind":
        return path.kind != "helix"
    return name in KIND_KEYS.get(path.kind, ())


def scene_digest(scene: SceneConfig, frames: int) -> str:
    """SHA-256 of a scene's resolved TOML and the run length its schedules are resolved against (a recording names
    the scene it came from by it)."""
    text = dump_toml(scene) + f"frames = {int(frames)}\n"
    return hashlib.sha256(text.encode()).hexdigest()


def dump_toml(config) -> str:
    """A config dataclass as TOML text that :func:`run_config_from_dict` reads back to an equal config."""
    return "\n".join(toml_lines(_toml_table(config))).lstrip("\n") + "\n"


#: The table a run's ``config.toml`` ends with: what the loop's "auto" settings became (:func:`run_config_toml`).
RESOLVED_TABLE = "resolved"

_RESOLVED_NOTE = """\
# [resolved] is written by the run and not read: loading this file skips it and resolves every "auto" again
# (to the same values for the same sensor and source). It says what the loop ran with
# (mabdi.loop.loop.resolve_settings): whether object removal and refinement ran, and each setting whose
# value differs from the sections above ("auto" made a value, a rule the sensor or the source turned off)."""


def run_config_toml(config: RunConfig, settings=None) -> str:
    """A run's ``config.toml``: :func:`dump_toml` of ``config`` (loads back to an equal config), then, given the
    loop's resolved ``settings`` (:class:`mabdi.loop.loop.LoopSettings`), a commented ``[resolved]`` table of
    them: its plain fields as they are, and of each stage's parameters the keys that differ from ``config``'s
    section of the same name. The loader skips ``[resolved]``; ``--set resolved.*`` is an error."""
    text = dump_toml(config)
    if settings is None:
        return text
    table = {}
    for f in dataclasses.fields(settings):
        value = getattr(settings, f.name)
        if not dataclasses.is_dataclass(value):
            table[f.name] = value
            continue
        given = _toml_table(getattr(config, f.name)) if hasattr(config, f.name) else {}
        changed = {k: v for k, v in _toml_table(value).items() if k not in given or given[k] != v}
        if changed:
            table[f.name] = changed
    return text + "\n" + _RESOLVED_NOTE + "\n" + "\n".join(toml_lines({RESOLVED_TABLE: table})).lstrip("\n") + "\n"
