"""Typed run configs, loaded from TOML.

A file in ``scenes/`` is a whole run config: ``[run]`` (frames, seed),
``[scene]`` (the objects), ``[sensor]`` (intrinsics, noise, backend),
``[path]`` (the helix), ``[classifier]`` (on/off and thresholds),
``[surface]`` (which surface filter) and ``[output]`` (what is written). Every section and key has a default, so a config
states only what differs. An unknown or misspelt key, a value of the wrong
type, or a value out of range is a :class:`ConfigError` that names the file
and the key.

``load_run_config(path)`` reads a file; ``dump_toml(config)`` writes the
resolved config back (saved next to a run's outputs). Relative mesh paths in
a config are resolved against the config file's folder.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

from mabdi.camera import Intrinsics
from mabdi.errors import ConfigError

PRIMITIVES = ("box", "cylinder", "sphere", "plane")
OBJECT_TYPES = (*PRIMITIVES, "mesh")
ANCHORS = ("bottom", "center", "origin")
AXES = ("x", "y", "z", "-x", "-y", "-z", "+x", "+y", "+z")
NOISE_MODELS = ("none", "zbuffer", "kinect")
#: Surface filters by config name; quadtree and voxel_planes join when they exist.
SURFACES = ("pixel_grid", "quadtree", "voxel_planes")
BACKENDS = ("egl", "osmesa")


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


@dataclass
class SceneConfig:
    """The world: a list of objects (``[[scene.objects]]`` tables)."""

    objects: list[ObjectConfig] = field(default_factory=list)


@dataclass
class SensorConfig:
    """The simulated depth sensor: intrinsics (pixels, metres), noise model and render backend.

    Noise models: ``none``; ``zbuffer`` (seed 001: d + d N(0, zbuffer_sigma)
    on the normalised z-buffer value d); ``kinect`` (axial sigma(z) =
    kinect_coefficient z^2 metres, Khoshelham & Elberink 2012).
    """

    width: int = 640
    height: int = 480
    fx: float = 525.0
    fy: float = 525.0
    cx: float = 320.0
    cy: float = 240.0
    near: float = 0.5
    far: float = 4.0
    noise: str = "none"
    zbuffer_sigma: float = 0.001
    kinect_coefficient: float = 1.425e-3
    backend: str = "egl"

    def intrinsics(self) -> Intrinsics:
        return Intrinsics(self.fx, self.fy, self.cx, self.cy, self.width, self.height, self.near, self.far)


@dataclass
class PathConfig:
    """The helical sensor path (see :func:`mabdi.simulate.helical_path`). Metres and degrees."""

    center: list[float] = field(default_factory=lambda: [0.0, 0.0])
    radius_x: float = 2.5
    radius_y: float = 2.5
    z0: float = 1.2
    z1: float = 1.8
    look_from: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.5])
    look_to: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.8])
    turns: float = 2.0
    start_angle: float = -90.0


@dataclass
class ClassifierConfig:
    """FilterClassifier's switch and thresholds (see :mod:`mabdi.filters.classifier`).

    ``enabled = false`` is the "black box": every valid pixel is meshed every frame.
    """

    enabled: bool = True
    tau_min: float = 0.01
    k_sigma: float = 3.0
    min_width: int = 3
    min_region: int = 32
    rim: int = 1


@dataclass
class SurfaceConfig:
    """The surface filter that meshes novel pixels: ``method`` is one of :data:`SURFACES`.

    ``max_jump``: largest depth jump (fraction of the depth) inside a face
    (pixel_grid) or between vertices that are merged (quadtree).
    ``n_t``, ``d_t`` (m), ``reduction``: the quad-tree's merge thresholds and
    block reduction (:mod:`mabdi.filters.quadtree`); in the loop the quad-tree
    outputs triangles, so the map's counts are triangles.
    ``voxel_size`` (m), ``epsilon`` (m, the anticipated point noise),
    ``window`` (voxels a side), ``min_points``: voxel planes
    (:mod:`mabdi.filters.voxel_planes`), which re-meshes the blocks new points
    fall in and replaces them in the map.
    """

    method: str = "pixel_grid"
    max_jump: float = 0.05
    n_t: float = 0.1
    d_t: float = 0.02
    reduction: int = 3
    voxel_size: float = 0.05
    epsilon: float = 0.02
    window: int = 2
    min_points: int = 10


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
    ``snapshots`` (empty: the first, middle and last).
    """

    dir: str = ""
    vtp: bool = True
    ply: bool = True
    h5: bool = False
    depth_images: bool = False
    movie: bool = False
    snapshots: list[int] = field(default_factory=list)


@dataclass
class RunSection:
    """Run-wide settings: a name, the number of frames (iterations) and the noise seed."""

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
    classifier: ClassifierConfig = field(default_factory=ClassifierConfig)
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    #: The file this config was read from (not a TOML key).
    source: Path | None = field(default=None, compare=False, repr=False, metadata={"toml": False})


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
    config = run_config_from_dict(data, where=str(path))
    config.source = path.resolve()
    return config


def run_config_from_dict(data: dict, where: str = "<config>") -> RunConfig:
    """Build and validate a :class:`RunConfig` from parsed TOML (``where`` names the file in errors)."""
    config = _build(RunConfig, data, where, "")
    validate_run_config(config, where)
    return config


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
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.metadata.get("toml", True)}
    section = f"[{prefix}]" if prefix else "top level"
    unknown = [k for k in data if k not in fields]
    if unknown:
        raise ConfigError(
            f"{where}: unknown key '{unknown[0]}' in {section} (known keys: {', '.join(fields)})"
        )
    values = {}
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        values[name] = _convert(hints[name], value, where, key)
    return cls(**values)


def _check_choice(value: str, choices, where: str, key: str) -> None:
    if value not in choices:
        raise ConfigError(f"{where}: key '{key}' = {value!r} is not one of: {', '.join(choices)}")


def _check_length(values, length: int, where: str, key: str) -> None:
    if len(values) != length:
        raise ConfigError(f"{where}: key '{key}' must have {length} numbers, got {len(values)}")


def validate_object(obj: ObjectConfig, where: str, key: str) -> None:
    """Range and consistency checks of one scene object (the loader checked types)."""
    _check_choice(obj.type, OBJECT_TYPES, where, f"{key}.type")
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
    if obj.type != "mesh" and obj.mesh:
        raise ConfigError(f"{where}: key '{key}.mesh' is only used with type = \"mesh\"")
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
    for name in ("appear_at", "disappear_at"):
        value = getattr(obj, name)
        if isinstance(value, float) and not 0.0 <= value <= 1.0:
            raise ConfigError(
                f"{where}: key '{key}.{name}' = {value} : a float is a fraction of the run in [0, 1]; use an integer for a frame number"
            )
        if isinstance(value, int) and value < 0:
            raise ConfigError(f"{where}: key '{key}.{name}' must be a frame number >= 0, got {value}")


def validate_run_config(config: RunConfig, where: str = "<config>") -> None:
    """Range checks across a whole config."""
    if config.run.frames < 1:
        raise ConfigError(f"{where}: key 'run.frames' must be at least 1, got {config.run.frames}")
    if config.run.seed < 0:
        raise ConfigError(f"{where}: key 'run.seed' must be >= 0, got {config.run.seed}")
    for i, obj in enumerate(config.scene.objects):
        validate_object(obj, where, f"scene.objects[{i}]")
    sensor = config.sensor
    _check_choice(sensor.noise, NOISE_MODELS, where, "sensor.noise")
    _check_choice(sensor.backend, BACKENDS, where, "sensor.backend")
    if sensor.zbuffer_sigma < 0 or sensor.kinect_coefficient < 0:
        raise ConfigError(f"{where}: noise parameters 'sensor.zbuffer_sigma' and 'sensor.kinect_coefficient' must be >= 0")
    try:
        sensor.intrinsics()
    except ConfigError as exc:
        raise ConfigError(f"{where}: [sensor] {exc}") from None
    path = config.path
    _check_length(path.center, 2, where, "path.center")
    _check_length(path.look_from, 3, where, "path.look_from")
    _check_length(path.look_to, 3, where, "path.look_to")
    if path.radius_x <= 0 or path.radius_y <= 0:
        raise ConfigError(f"{where}: keys 'path.radius_x' and 'path.radius_y' must be positive")
    if path.turns <= 0:
        raise ConfigError(f"{where}: key 'path.turns' must be positive, got {path.turns}")
    classifier = config.classifier
    if classifier.tau_min <= 0 or classifier.k_sigma < 0:
        raise ConfigError(f"{where}: need 'classifier.tau_min' > 0 and 'classifier.k_sigma' >= 0")
    if classifier.min_width < 1 or classifier.min_region < 0 or classifier.rim < 0:
        raise ConfigError(f"{where}: need 'classifier.min_width' >= 1, 'classifier.min_region' >= 0, 'classifier.rim' >= 0")
    _check_choice(config.surface.method, SURFACES, where, "surface.method")
    if config.surface.max_jump <= 0:
        raise ConfigError(f"{where}: key 'surface.max_jump' must be > 0, got {config.surface.max_jump}")
    if config.surface.n_t < 0 or config.surface.d_t <= 0 or config.surface.reduction < 1:
        raise ConfigError(f"{where}: need 'surface.n_t' >= 0, 'surface.d_t' > 0 and 'surface.reduction' >= 1")
    if not (config.surface.voxel_size > 0 and config.surface.epsilon > 0):
        raise ConfigError(f"{where}: need 'surface.voxel_size' > 0 and 'surface.epsilon' > 0 (metres)")
    if not 1 <= config.surface.window <= 6 or config.surface.min_points < 3:
        raise ConfigError(f"{where}: need 1 <= 'surface.window' <= 6 and 'surface.min_points' >= 3")


# ---------------------------------------------------------------------------
# Writing (the resolved config saved with a run)


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ("nan" if math.isnan(value) else ("inf" if value > 0 else "-inf"))
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} to TOML")


def _toml_table(obj, prefix: str, lines: list[str]) -> None:
    scalars, tables, arrays = [], [], []
    for f in dataclasses.fields(obj):
        if not f.metadata.get("toml", True):
            continue
        value = getattr(obj, f.name)
        if value is None:
            continue  # absent key = default None
        if dataclasses.is_dataclass(value):
            tables.append((f.name, value))
        elif isinstance(value, list) and value and dataclasses.is_dataclass(value[0]):
            arrays.append((f.name, value))
        else:
            scalars.append(f"{f.name} = {_toml_value(value)}")
    lines.extend(scalars)
    for name, value in tables:
        lines.append("")
        lines.append(f"[{prefix}{name}]")
        _toml_table(value, f"{prefix}{name}.", lines)
    for name, items in arrays:
        for item in items:
            lines.append("")
            lines.append(f"[[{prefix}{name}]]")
            _toml_table(item, f"{prefix}{name}.", lines)


def dump_toml(config) -> str:
    """A config dataclass as TOML text that :func:`run_config_from_dict` reads back to an equal config."""
    lines: list[str] = []
    _toml_table(config, "", lines)
    return "\n".join(lines).lstrip("\n") + "\n"
