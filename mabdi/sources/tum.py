"""TUM RGB-D benchmark folders: read them as a frame source, write any frame source in their layout.

The layout (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats):

* ``depth/<timestamp>.png``: 16-bit PNG, 5000 units per metre, 0 = no
  return; ``depth.txt``: lines ``timestamp filename``;
* ``rgb/<timestamp>.png`` and ``rgb.txt`` (optional): colour images
  registered to the depth images;
* ``groundtruth.txt``: lines ``timestamp tx ty tz qx qy qz qw``: the camera's
  optical frame in the world (metres, unit quaternion scalar last).

Poses: a ground-truth line maps camera points (x right, y down, z forward)
to world points, exactly mabdi's ``world_from_camera``, used as it is. Each
depth frame's pose is interpolated between the ground-truth samples around
its timestamp (plus ``time_offset``, 0 unless given: the pose clock's offset
from the depth clock) within ``tolerance`` seconds (default 0.02 s), else the
nearest within it; frames with neither are skipped and counted. Each frame
carries the colour image nearest in time.

Intrinsics: the ``camera=`` argument (an :class:`Intrinsics`, a preset name
or ``"fx,fy,cx,cy,width,height"``), else the ``[camera]`` table of a
``mabdi.toml`` in the folder, else the folder's ``calibration.txt`` (one
line ``fx fy cx cy``, integer pixel centres, the depth images' size: the
variant of the layout ETH3D's SLAM benchmark ships and its tools write;
:func:`read_calibration`), else the preset of the Kinect a benchmark
folder's name gives (:func:`benchmark_camera`); values in mabdi's pixel convention (pixel
(u, v) centred on (u + 0.5, v + 0.5)); lens distortion is ignored.

Pillow is imported inside the functions that use it. Details:
docs/architecture.md (``mabdi.sources.tum``).
"""

from __future__ import annotations

import dataclasses
import re
import struct
from pathlib import Path

import numpy as np

from mabdi.camera import Intrinsics, quaternions_from_rotations
from mabdi.depth import DepthFrame
from mabdi.io.atomic import atomic_output, write_text
from mabdi.sources.frames import FrameSource
from mabdi.sources.png import decode_gray16_png
from mabdi.sources.sequence_files import (
    METADATA_FILE,
    GIVE_THE_CAMERA,
    SequenceError,
    camera_from_text,
    camera_origin,
    camera_table,
    check_depth_size,
    depth_png_size,
    intrinsics_from_matrix,
    frame_timestamps,
    intrinsics_with,
    metadata_path,
    interpolate_poses,
    nearest_within,
    poses_from_translations_quaternions,
    prepare_folder,
    read_colour_image,
    read_sequence_metadata,
    write_colour_png,
    write_metadata,
)

#: Depth units per metre in TUM PNGs.
DEPTH_SCALE = 5000.0
#: The camera file of the layout's ETH3D variant: one line ``fx fy cx cy`` (:func:`read_calibration`).
CALIBRATION_FILE = "calibration.txt"

_DEFAULTS = Intrinsics()


def _tum_camera(fx: float, fy: float, cx: float, cy: float) -> Intrinsics:
    """Intrinsics from TUM's published values (integer pixel centres) with mabdi's +0.5 shift; 640x480, default range."""
    return dataclasses.replace(_DEFAULTS, fx=fx, fy=fy, cx=cx + 0.5, cy=cy + 0.5, width=640, height=480)


#: The TUM cameras, from the benchmark's calibration page (colour-camera intrinsics, which the
#: registered depth images share), shifted to mabdi's pixel centres (cx + 0.5, cy + 0.5).
#: ``ros`` is the uncalibrated default (525, 525, 319.5, 239.5) the benchmark recommends for
#: the pre-registered depth images.
PRESETS: dict[str, Intrinsics] = {
    "fr1": _tum_camera(517.3, 516.5, 318.6, 255.3),
    "fr2": _tum_camera(520.9, 521.0, 325.1, 249.7),
    "fr3": _tum_camera(535.4, 539.2, 320.1, 247.6),
    "ros": _tum_camera(525.0, 525.0, 319.5, 239.5),
}


def benchmark_camera(folder: Path) -> tuple[str, str] | None:
    """(preset, where it was read) of a folder the TUM benchmark published: its sequence name, as the header of
    ``depth.txt`` gives it (``# file: 'rgbd_dataset_freiburg1_xyz.bag'``) or the folder's own name, names the
    Kinect that recorded it (``freiburg1`` -> ``fr1``); None when neither does."""
    try:
        with open(folder / "depth.txt", encoding="utf-8", errors="replace") as lines:
            header = [line for _, line in zip(range(5), lines) if line.startswith("#")]
    except OSError:
        header = []
    for text, where in ((" ".join(header), "named by depth.txt's header"), (folder.name, "named by the folder")):
        found = re.search(r"freiburg([123])", text)
        if found:
            return f"fr{found.group(1)}", where
    return None


def read_calibration(file: Path, depth_file: Path) -> Intrinsics:
    """The camera of a ``calibration.txt``: its one line ``fx fy cx cy`` (pixels; pixel centres at integers, as
    TUM's documentation, OpenCV and ETH3D's SLAM benchmark put them: mabdi's cx, cy are 0.5 more), for images of
    ``depth_file``'s size; near and far the defaults. A :class:`SequenceError` names the file and line otherwise."""
    try:
        text = file.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise SequenceError(f"{file}: cannot read the camera: {exc}") from None
    lines = [(number, line.split()) for number, line in enumerate(text.splitlines(), 1) if line.strip() and not line.lstrip().startswith("#")]
    if len(lines) != 1 or len(lines[0][1]) != 4:
        where = f"{file}:{lines[0][0]}" if lines else str(file)
        raise SequenceError(
            f"{where}: expected one line 'fx fy cx cy' (pixels, pixel centres at integers), got "
            f"{'nothing' if not lines else repr(' / '.join(' '.join(fields) for _, fields in lines))}: a camera with "
            f"lens distortion is not read; give the camera of undistorted images with --camera fx,fy,cx,cy,width,height"
        )
    number, fields = lines[0]
    try:
        fx, fy, cx, cy = (float(field) for field in fields)
    except ValueError:
        raise SequenceError(f"{file}:{number}: 'fx fy cx cy' must be numbers, got {' '.join(fields)!r}") from None
    matrix = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return intrinsics_from_matrix(matrix, *depth_png_size(depth_file), f"{file}:{number}")


def tum_preset(name: str, where: str = "camera") -> Intrinsics:
    """The :data:`PRESETS` entry ``name`` (``fr1``, ``fr2``, ``fr3``, ``ros``), or an error listing them."""
    try:
        return PRESETS[name]
    except (KeyError, TypeError):
        raise SequenceError(f"{where}: unknown TUM camera preset {name!r} (known: {', '.join(PRESETS)})") from None


def read_tum_list(path: Path, columns: int) -> tuple[np.ndarray, list[list[str]]]:
    """Timestamps (s) and the remaining fields of a TUM list file (``#`` comments, blank lines skipped).

    Every line must have exactly ``columns`` fields (timestamp included) and a
    numeric timestamp; otherwise a :class:`SequenceError` names the file and line.
    """
    times, rows, _ = read_tum_lines(path, columns)
    return times, rows


def read_tum_lines(path: Path, columns: int) -> tuple[np.ndarray, list[list[str]], list[int]]:
    """:func:`read_tum_list`'s timestamps and fields, and the line number of each."""
    if not path.is_file():
        raise SequenceError(f"TUM folder {path.parent}: missing {path.name}")
    times: list[float] = []
    rows: list[list[str]] = []
    numbers: list[int] = []
    with open(path, encoding="utf-8", errors="replace") as stream:
        for number, line in enumerate(stream, start=1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            fields = line.split()
            if len(fields) != columns:
                raise SequenceError(f"{path}:{number}: expected {columns} fields, got {len(fields)}: {line!r}")
            try:
                time = float(fields[0])
            except ValueError:
                raise SequenceError(f"{path}:{number}: timestamp {fields[0]!r} is not a number") from None
            if not np.isfinite(time):
                raise SequenceError(f"{path}:{number}: timestamp {fields[0]!r} is not finite")
            times.append(time)
            rows.append(fields[1:])
            numbers.append(number)
    return np.array(times, dtype=np.float64), rows, numbers


def repeated_times(times) -> list[tuple[int, int]]:
    """(first, later) index pairs of the entries of ``times`` whose timestamp an earlier entry has."""
    first: dict[float, int] = {}
    pairs = []
    for index, time in enumerate(np.asarray(times, dtype=np.float64).tolist()):
        if time in first:
            pairs.append((first[time], index))
        else:
            first[time] = index
    return pairs


#: Two ground-truth samples at one timestamp that agree within these are one sample written twice.
SAME_SAMPLE_METRES = 1e-3
SAME_SAMPLE_DEGREES = 0.1


def read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (s) and (N, 4, 4) world_from_camera poses of a TUM ``groundtruth.txt``.

    A sample repeated at its timestamp (within :data:`SAME_SAMPLE_METRES` and
    :data:`SAME_SAMPLE_DEGREES`) is read once; two that disagree at one timestamp
    are a :class:`SequenceError` naming their lines (which is the camera's is unknown).
    """
    times, rows, numbers = read_tum_lines(path, 8)
    values = np.empty((len(rows), 7), dtype=np.float64)
    for index, fields in enumerate(rows):
        try:
            values[index] = [float(f) for f in fields]
        except ValueError:
            raise SequenceError(
                f"{path}: pose at timestamp {float(times[index])!r} has a field that is not a number: {fields}"
            ) from None
    bad = ~np.isfinite(values).all(axis=1) | (np.linalg.norm(values[:, 3:], axis=1) < 1e-9)
    if bad.any():
        raise SequenceError(f"{path}: pose at timestamp {float(times[np.argmax(bad)])!r} is not finite or has a zero quaternion")
    poses = poses_from_translations_quaternions(values[:, :3], values[:, 3:])
    repeated = repeated_times(times)
    for first, later in repeated:
        metres = float(np.linalg.norm(poses[first, :3, 3] - poses[later, :3, 3]))
        cosine = (np.trace(poses[first, :3, :3].T @ poses[later, :3, :3]) - 1.0) / 2.0
        degrees = float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))
        if metres > SAME_SAMPLE_METRES or degrees > SAME_SAMPLE_DEGREES:
            raise SequenceError(
                f"{path}: lines {numbers[first]} and {numbers[later]} give two poses at timestamp {float(times[first])!r}, "
                f"{metres:.3g} m and {degrees:.3g} degrees apart: which is the camera's is unknown; remove one"
            )
    keep = np.setdiff1d(np.arange(len(times)), [later for _, later in repeated])
    return times[keep], poses[keep]


def read_depth_list(path: Path) -> tuple[np.ndarray, list[list[str]]]:
    """Timestamps and fields of a ``depth.txt``. An image listed twice is read once; two images at one
    timestamp are a :class:`SequenceError` naming their lines: the benchmark's tools (``associate.py``)
    key frames by timestamp and would keep one silently, and which was taken then is unknown."""
    times, rows, numbers = read_tum_lines(path, 2)
    repeated = repeated_times(times)
    for first, later in repeated:
        if rows[first] != rows[later]:
            raise SequenceError(
                f"{path}: lines {numbers[first]} and {numbers[later]} list two depth images at timestamp "
                f"{float(times[first])!r} ({rows[first][0]}, {rows[later][0]}): which was taken then is unknown; remove one"
            )
    keep = np.setdiff1d(np.arange(len(times)), [later for _, later in repeated])
    return times[keep], [rows[i] for i in keep]


def read_depth_units(path: Path, shape: tuple[int, int] | None) -> np.ndarray:
    """(H, W) uint16 values of a 16-bit single-channel depth PNG, as stored; ``shape`` (H, W) checked when given.

    A missing, damaged or differently shaped image is a :class:`SequenceError` naming it.
    """
    try:
        with open(path, "rb") as stream:
            raw = decode_gray16_png(stream.read())
    except FileNotFoundError:
        raise SequenceError(f"{path}: depth image missing") from None
    except (ValueError, struct.error) as exc:
        raise SequenceError(f"{path}: cannot read depth PNG: {exc}") from None
    if raw is None:
        from PIL import Image, UnidentifiedImageError  # only where mabdi's own PNG reader cannot: start-up memory (module docs)

        try:
            with Image.open(path) as image:
                if image.format != "PNG" or image.mode not in ("I;16", "I;16B", "I;16L", "I"):
                    raise SequenceError(
                        f"{path}: not a 16-bit single-channel PNG (format {image.format}, mode {image.mode})"
                    )
                raw = np.asarray(image)
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
            if isinstance(exc, SequenceError):
                raise
            raise SequenceError(f"{path}: cannot read depth PNG: {exc}") from None
    if shape is not None and raw.shape != tuple(shape):
        raise SequenceError(
            f"{path}: image is {raw.shape[1]}x{raw.shape[0]}, intrinsics say {shape[1]}x{shape[0]}: every depth image "
            f"must be its camera's size; if the camera is wrong, {GIVE_THE_CAMERA} the sequence's {METADATA_FILE}"
        )
    return raw


def read_depth_png(path: Path, intrinsics: Intrinsics, scale: float = DEPTH_SCALE, no_return=(0,)) -> np.ndarray:
    """(H, W) float32 depth in metres of a 16-bit depth PNG (``scale`` units per metre; the ``no_return`` values become NaN)."""
    return depth_from_units(read_depth_units(path, intrinsics.shape), scale, no_return)


def depth_from_units(raw: np.ndarray, scale: float, no_return=(0,)) -> np.ndarray:
    """float32 metres of uint16 depth ``raw`` at ``scale`` units per metre; the ``no_return`` values become NaN."""
    depth = raw.astype(np.float32)
    depth *= np.float32(1.0 / scale)
    for value in no_return:
        depth[raw == value] = np.nan
    return depth


def depth_png_values(depth: np.ndarray, scale: float = DEPTH_SCALE) -> np.ndarray:
    """uint16 PNG values of (H, W) depth in metres: round(depth * scale); NaN, <= 0 and > 65535 units become 0."""
    units = np.rint(np.asarray(depth, dtype=np.float64) * scale)
    with np.errstate(invalid="ignore"):
        keep = (units > 0) & (units <= 65535)
    return np.where(keep, units, 0).astype(np.uint16)


def write_depth_png(path, depth: np.ndarray, scale: float = DEPTH_SCALE, compress_level: int = 1) -> None:
    """Write (H, W) depth in metres as a 16-bit PNG (:func:`depth_png_values`), atomically."""
    from PIL import Image  # on first use: a start-up memory choice (module docs)

    values = depth_png_values(depth, scale)
    with atomic_output(path) as temporary:
        Image.fromarray(values).save(temporary, format="PNG", compress_level=compress_level)


class TumSequence(FrameSource):
    """A TUM RGB-D benchmark folder as a :class:`FrameSource` (see the module docs).

    Parameters: ``folder`` (the sequence folder), ``camera`` (an
    :class:`Intrinsics`, a preset name in :data:`PRESETS` or
    ``"fx,fy,cx,cy,width,height"``; wins over the folder's ``mabdi.toml``),
    ``tolerance`` (seconds between a depth frame and its ground-truth pose,
    default 0.02), ``depth_scale`` (PNG units per metre, default
    :data:`DEPTH_SCALE`), ``time_offset`` (seconds from a depth frame's
    timestamp to the time its pose is taken at, default 0: where the depth
    and the ground truth were stamped by clocks apart; learnt by
    :mod:`mabdi.stages.time_offset`). Frames are the depth images that
    have a pose, in ``depth.txt``'s order; ``skipped`` counts the others.
    ``read(i)`` decodes one PNG; timestamps and poses are known at open;
    ``pose_samples`` holds the ground truth as read (times (s), (N, 4, 4) poses).
    """

    def __init__(
        self,
        folder,
        camera: Intrinsics | str | None = None,
        tolerance: float = 0.02,
        depth_scale: float | None = None,
        time_offset: float = 0.0,
    ) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise SequenceError(f"TUM folder {self.folder} does not exist or is not a folder")
        if not (np.isfinite(tolerance) and tolerance >= 0):
            raise SequenceError(f"TUM folder {self.folder}: tolerance must be >= 0 seconds, got {tolerance!r}")
        if not np.isfinite(time_offset):
            raise SequenceError(f"TUM folder {self.folder}: time offset must be a number of seconds, got {time_offset!r}")
        self.metadata = read_sequence_metadata(self.folder)
        self._camera = camera
        self.camera_note: str | None = None  # where the camera came from, when the folder's name gave it
        self._intrinsics = self._resolve_camera(camera)
        self.tolerance = float(tolerance)
        self.time_offset = float(time_offset)
        self.depth_scale = DEPTH_SCALE if depth_scale is None else depth_scale
        if not (isinstance(self.depth_scale, (int, float)) and np.isfinite(self.depth_scale) and self.depth_scale > 0):
            raise SequenceError(f"TUM folder {self.folder}: depth scale must be a positive number of units per metre, got {depth_scale!r}")

        depth_times, depth_rows = read_depth_list(self.folder / "depth.txt")
        pose_times, poses = read_groundtruth(self.folder / "groundtruth.txt")
        self.pose_samples = (pose_times, poses)
        matched = interpolate_poses(depth_times + self.time_offset, pose_times, poses, self.tolerance)
        keep = np.isfinite(matched[:, 0, 0])
        self.skipped = int((~keep).sum())
        self._timestamps = depth_times[keep]
        self._poses = matched[keep]
        self._files = [self.folder / depth_rows[i][0] for i in np.flatnonzero(keep)]
        self._colour_files = None
        far_colour = 0
        if (self.folder / "rgb.txt").is_file():
            rgb_times, rgb_rows = read_tum_list(self.folder / "rgb.txt", 2)
            if not len(rgb_times):
                raise SequenceError(f"{self.folder / 'rgb.txt'}: no colour image listed")
            nearest = nearest_within(self._timestamps, rgb_times, np.inf)
            far_colour = int((np.abs(rgb_times[nearest] - self._timestamps) > self.tolerance).sum())
            self._colour_files = [self.folder / rgb_rows[i][0] for i in nearest]
        self.description = f"TUM folder {self.folder} ({len(self._files)} frames"
        if self.camera_note:
            self.description += f", {self.camera_note}"
        if self.time_offset:
            self.description += f", poses taken {1000 * self.time_offset:+.1f} ms from the depth timestamps"
        if self._colour_files is not None:
            self.description += ", with colour"
            if far_colour:
                self.description += f" ({far_colour} more than {self.tolerance * 1000:g} ms from their colour image)"
        self.description += f", {self.skipped} without a pose within {self.tolerance * 1000:g} ms skipped)" if self.skipped else ")"
        if not self._files:
            raise SequenceError(
                f"TUM folder {self.folder}: no depth frame has a ground-truth pose within {self.tolerance * 1000:g} ms "
                f"({len(depth_times)} frames in depth.txt, {len(pose_times)} poses in groundtruth.txt)"
            )
        if camera is None:  # a camera given is checked against each image as it is read
            check_depth_size(self._intrinsics, self._files[0], camera_origin(self.folder, None), self.folder)

    def _resolve_camera(self, camera) -> Intrinsics:
        if isinstance(camera, Intrinsics):
            return camera
        if isinstance(camera, str) and "," in camera:
            return camera_from_text(camera, f"TUM folder {self.folder}: camera=")
        if camera is not None:
            return tum_preset(camera, f"TUM folder {self.folder}: camera=")
        file = metadata_path(self.folder)
        table = camera_table(self.metadata, file, allowed=("preset", *dataclasses.asdict(_DEFAULTS)))
        calibration = self.folder / CALIBRATION_FILE
        if not table and calibration.is_file():
            times, rows = read_depth_list(self.folder / "depth.txt")
            if not len(times):
                raise SequenceError(f"{self.folder / 'depth.txt'}: no depth image listed")
            self.camera_note = f"camera: {CALIBRATION_FILE}"
            return read_calibration(calibration, self.folder / rows[int(np.argmin(times))][0])
        if not table:
            named = benchmark_camera(self.folder)
            if named is not None:
                self.camera_note = f"camera: TUM's {named[0]} calibration ({named[1]})"
                return PRESETS[named[0]]
            raise SequenceError(
                f"TUM folder {self.folder}: no intrinsics: give --camera (camera=: one of {', '.join(PRESETS)}, "
                f"or fx,fy,cx,cy,width,height) or put a [camera] table (fx, fy, cx, cy, width, height; optional near, "
                f"far, preset) in {file}, or a {CALIBRATION_FILE} (one line: fx fy cx cy, pixel centres at integers)"
            )
        base = tum_preset(table["preset"], f"{file}: camera.preset") if "preset" in table else None
        if base is None:
            missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in table]
            if missing:
                raise SequenceError(f"{file}: [camera] lacks {', '.join(missing)} (or give camera.preset)")
        return intrinsics_with(base, table, file)

    @property
    def intrinsics(self) -> Intrinsics:
        return self._intrinsics

    def with_time_offset(self, seconds: float) -> TumSequence:
        """The same folder read with each depth frame's pose taken ``seconds`` after its timestamp (the pose
        clock's offset from the depth clock: :mod:`mabdi.stages.time_offset`); the other options as they were."""
        return TumSequence(self.folder, self._camera, self.tolerance, self.depth_scale, seconds)

    def __len__(self) -> int:
        return len(self._files)

    def read_frame(self, index: int) -> DepthFrame:
        depth = read_depth_png(self._files[index], self._intrinsics, self.depth_scale)
        colour = None
        if self._colour_files is not None:
            colour = read_colour_image(self._colour_files[index])
            if colour.shape[:2] != self._intrinsics.shape:
                raise SequenceError(
                    f"{self._colour_files[index]}: colour image is {colour.shape[1]}x{colour.shape[0]}, the depth "
                    f"{self._intrinsics.width}x{self._intrinsics.height}: TUM's colour and depth images are registered"
                )
        return DepthFrame(depth, self._intrinsics, self._poses[index], index, float(self._timestamps[index]), colour)

    @property
    def poses(self) -> np.ndarray:
        return self._poses.copy()

    @property
    def timestamps(self) -> np.ndarray:
        return self._timestamps.copy()

    @property
    def files(self) -> list[Path]:
        """The depth PNG of every frame."""
        return list(self._files)

    @property
    def has_colour(self) -> bool:
        return self._colour_files is not None


def write_tum(
    source: FrameSource, folder, *, extra: dict | None = None, overwrite: bool = False, depth_scale: float = DEPTH_SCALE
) -> Path:
    """Write every frame of ``source`` as a TUM RGB-D folder; returns the folder.

    ``depth/<timestamp>.png`` (16-bit, round(depth * 5000), 0 where there is
    no return, where depth <= 0 and beyond 65535 / 5000 = 13.107 m),
    ``depth.txt``, ``groundtruth.txt`` (poses with 17 significant digits, so
    they read back to within 1e-12 of the same matrices; quaternions scalar
    last with w >= 0) and ``mabdi.toml`` with the ``[camera]`` table and the
    ``extra`` tables (e.g. ``{"recorded": {"scene": "scenes/table.toml"}}``).
    Frames with colour images also get ``rgb/<timestamp>.png`` (8-bit RGB)
    and ``rgb.txt``, at the depth frames' times.
    ``depth_scale`` other than 5000 writes PNGs that only a reader told so
    (``depth_scale=``, ``--depth-scale``) reads right.
    Frames without a timestamp get ``index / 30`` s. Every file is written
    atomically. The folder is created; one that exists and is not empty is an
    error unless ``overwrite=True`` (files of the same name are replaced,
    others are left alone).
    """
    folder = Path(folder)
    prepare_folder(folder, overwrite, "a TUM sequence")
    (folder / "depth").mkdir(exist_ok=True)
    intrinsics = source.intrinsics
    times = frame_timestamps(source)
    names = [f"depth/{t:.6f}.png" for t in times]
    if len(set(names)) != len(names):
        raise SequenceError(f"cannot write a TUM sequence to {folder}: two frames share a timestamp (to the microsecond)")
    poses = np.empty((len(source), 4, 4))
    coloured = []
    for index in range(len(source)):
        frame = source.read(index)
        if frame.depth.shape != intrinsics.shape:
            raise SequenceError(f"cannot write frame {index} to {folder}: depth {frame.depth.shape} != intrinsics {intrinsics.shape}")
        write_depth_png(folder / names[index], frame.depth, depth_scale)
        poses[index] = frame.world_from_camera
        if frame.colour is not None:
            (folder / "rgb").mkdir(exist_ok=True)
            write_colour_png(folder / names[index].replace("depth/", "rgb/", 1), frame.colour)
            coloured.append(index)
    if coloured:
        if len(coloured) != len(source):
            raise SequenceError(f"cannot write {folder}: {len(coloured)} of {len(source)} frames have a colour image (all or none)")
        rgb_lines = [f"{t:.6f} {name.replace('depth/', 'rgb/', 1)}" for t, name in zip(times, names, strict=True)]
        write_text(folder / "rgb.txt", f"# mabdi recording: {source.description}\n# timestamp filename\n" + "\n".join(rgb_lines) + "\n")
    quaternions = quaternions_from_rotations(poses[:, :3, :3])
    header = "# mabdi recording: {}\n# timestamp {}\n"
    depth_lines = [f"{t:.6f} {name}" for t, name in zip(times, names, strict=True)]
    write_text(folder / "depth.txt", header.format(source.description, "filename") + "\n".join(depth_lines) + "\n")
    pose_lines = [
        f"{t:.6f} " + " ".join(f"{v:.17g}" for v in (*pose[:3, 3], *q))
        for t, pose, q in zip(times, poses, quaternions, strict=True)
    ]
    write_text(
        folder / "groundtruth.txt",
        header.format(source.description, "tx ty tz qx qy qz qw (world_from_camera, camera optical frame)")
        + "\n".join(pose_lines)
        + "\n",
    )
    write_metadata(folder, intrinsics, extra)
    return folder


def write_tum_trajectory(path, timestamps: np.ndarray, poses: np.ndarray, description: str = "") -> None:
    """A TUM trajectory file (atomically): one line ``timestamp tx ty tz qx qy qz qw`` per pose
    (world_from_camera; quaternion scalar last, w >= 0; 17 significant digits). Frames without a
    timestamp get ``index / 30`` s, as in :func:`write_tum`."""
    times = np.asarray(timestamps, dtype=np.float64)
    times = np.where(np.isfinite(times), times, np.arange(len(times)) / 30.0)
    poses = np.asarray(poses, dtype=np.float64)
    quaternions = quaternions_from_rotations(poses[:, :3, :3])
    lines = [
        f"{t:.6f} " + " ".join(f"{v:.17g}" for v in (*pose[:3, 3], *q)) for t, pose, q in zip(times, poses, quaternions, strict=True)
    ]
    header = f"# mabdi trajectory: {description}\n# timestamp tx ty tz qx qy qz qw (world_from_camera, camera optical frame)\n"
    write_text(path, header + "\n".join(lines) + "\n")


__all__ = [
    "DEPTH_SCALE",
    "METADATA_FILE",
    "PRESETS",
    "TumSequence",
    "read_depth_png",
    "tum_preset",
    "write_depth_png",
    "write_tum",
    "write_tum_trajectory",
]
