"""What the readers and writers of recorded depth sequences share: errors, the ``mabdi.toml`` beside a sequence,
pose interpolation and quaternions, colour images, output folders.

Every format module (:mod:`~mabdi.sources.tum`, :mod:`~mabdi.sources.rosbag2`,
:mod:`~mabdi.sources.image_sequence` and the dataset layouts) imports from
here; :mod:`mabdi.sources.sequences`, which tells the formats apart and opens
any of them, sits above them all and re-exports these names.

``mabdi.toml``: any sequence may carry one in its folder with a ``[camera]``
table (intrinsics in mabdi's conventions: pixel (u, v) has its centre at
(u + 0.5, v + 0.5); focal lengths and principal point in pixels, near and far
in metres), optionally a ``[sequence]`` table whose ``format`` names the
format to read the folder as (for a folder holding the files of two), and
any other tables a writer put there (``[recorded]`` with the scene a
simulated sequence came from, for example); :func:`read_sequence_metadata`
returns them.

A depth image of another size than its camera's is refused
(:func:`check_depth_size`), and frames numbered without zero padding are
listed in natural order (:func:`natural_sorted`).

Pillow is imported inside the functions that use it (a start-up memory
choice: ``import mabdi`` and a run of a simulated scene do not load it).
"""

from __future__ import annotations

import dataclasses
import io
import re
import struct
import tomllib
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from mabdi.camera import Intrinsics
from mabdi.errors import ConfigError
from mabdi.io.atomic import atomic_output, write_text
from mabdi.io.toml_writer import toml_lines
from mabdi.sources.png import decode_rgb8_png

#: The metadata file a recorded sequence may carry in its folder.
METADATA_FILE = "mabdi.toml"

#: Keys of the ``[camera]`` table: the intrinsics' fields (``preset`` is the TUM reader's extra key).
CAMERA_KEYS = tuple(f.name for f in dataclasses.fields(Intrinsics))


class SequenceError(ConfigError):
    """A recorded sequence (a TUM folder, a ROS 2 bag) cannot be read or written; the message names the file or topic."""


def metadata_path(path) -> Path:
    """Where the ``mabdi.toml`` of a sequence at ``path`` (a folder, or a bag file) lives."""
    path = Path(path)
    return (path.parent if path.is_file() else path) / METADATA_FILE


def read_sequence_metadata(path) -> dict:
    """The tables of the ``mabdi.toml`` beside a sequence (a folder or a bag file); ``{}`` when there is none.

    A file that is not valid TOML is a :class:`SequenceError` naming it.
    """
    file = metadata_path(path)
    if not file.is_file():
        return {}
    try:
        with open(file, "rb") as stream:
            return tomllib.load(stream)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SequenceError(f"{file}: not valid TOML: {exc}") from None


def camera_table(metadata: dict, file, allowed=CAMERA_KEYS) -> dict:
    """The ``[camera]`` table of ``metadata`` (``{}`` if absent), checked: known keys, numbers where numbers go."""
    table = metadata.get("camera", {})
    if not isinstance(table, dict):
        raise SequenceError(f"{file}: 'camera' must be a table")
    for key, value in table.items():
        if key not in allowed:
            raise SequenceError(f"{file}: unknown key 'camera.{key}' (known: {', '.join(allowed)})")
        if key in CAMERA_KEYS and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise SequenceError(f"{file}: 'camera.{key}' must be a number, got {value!r}")
    return table


def intrinsics_with(base: Intrinsics | None, table: dict, file) -> Intrinsics:
    """``base`` (or the :class:`Intrinsics` defaults) with the keys of a ``[camera]`` table replaced."""
    values = dataclasses.asdict(base) if base is not None else {}
    values.update({k: v for k, v in table.items() if k in CAMERA_KEYS})
    try:
        return Intrinsics(**values)
    except (ConfigError, TypeError) as exc:
        raise SequenceError(f"{file}: [camera]: {exc}") from None


def camera_from_text(text: str, where) -> Intrinsics:
    """:class:`Intrinsics` of ``"fx,fy,cx,cy,width,height"`` (mabdi's pixel centres, as in ``mabdi.toml``)."""
    try:
        values = [float(field) for field in text.split(",")]
        if len(values) != 6:
            raise ValueError
        return Intrinsics(*values[:4], width=int(values[4]), height=int(values[5]))
    except (ValueError, TypeError) as exc:
        detail = f": {exc}" if str(exc) else ""
        raise SequenceError(f"{where}: camera {text!r} is not fx,fy,cx,cy,width,height{detail}") from None


def intrinsics_from_matrix(matrix: np.ndarray, width: int, height: int, where) -> Intrinsics:
    """:class:`Intrinsics` from a 3x3 camera matrix K whose pixel centres are at integers (OpenCV, ROS, Open3D
    and the datasets' files): mabdi's cx = K[0, 2] + 0.5, cy = K[1, 2] + 0.5; near and far the defaults."""
    k = np.asarray(matrix, dtype=np.float64)
    try:
        return Intrinsics(
            fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(k[0, 2]) + 0.5, cy=float(k[1, 2]) + 0.5,
            width=int(width), height=int(height),
        )
    except (ValueError, TypeError) as exc:
        raise SequenceError(f"{where}: {exc}") from None


# ---------------------------------------------------------------------------
# The depth images' size against the camera's


def depth_png_size(path) -> tuple[int, int]:
    """(width, height) of a depth PNG from its header, or a :class:`SequenceError` naming it."""
    try:
        with open(path, "rb") as stream:
            head = stream.read(24)
    except FileNotFoundError:
        raise SequenceError(f"{path}: depth image missing") from None
    except OSError as exc:
        raise SequenceError(f"{path}: cannot read depth PNG: {exc}") from None
    if head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise SequenceError(f"{path}: cannot read depth PNG: no PNG header")
    return struct.unpack(">II", head[16:24])


def matrix_image_size(matrix, size: tuple[int, int]) -> tuple[int, int]:
    """The image size a camera matrix K (integer pixel centres) without one is for: ``size`` (the depth images')
    when K's principal point lies within an eighth of it from its centre, as every real camera's does; else the
    size whose centre the principal point is (round(2 cx), round(2 cy) in mabdi's pixel centres), which
    :func:`check_depth_size` then refuses against the images."""
    k = np.asarray(matrix, dtype=np.float64)
    centre = np.array([k[0, 2], k[1, 2]]) + 0.5
    extent = np.asarray(size, dtype=np.float64)
    if np.all(np.abs(centre - extent / 2) <= extent / 8):
        return int(size[0]), int(size[1])
    implied = np.rint(2 * centre)
    if not np.isfinite(implied).all():
        return int(size[0]), int(size[1])  # Intrinsics names the bad principal point
    return max(int(implied[0]), 1), max(int(implied[1]), 1)


def matrix_origin(file, intrinsics: Intrinsics) -> str:
    """Words for a camera matrix file without an image size, whose size :func:`matrix_image_size` gave."""
    return (
        f"{file} gives no size; its principal point ({intrinsics.cx:g}, {intrinsics.cy:g}) is the centre of a "
        f"{intrinsics.width}x{intrinsics.height} image"
    )


def camera_origin(folder, found: str | None) -> str:
    """Words for where a sequence's camera size comes from when no ``camera=`` is given: the ``[camera]``
    table of its ``mabdi.toml``, else ``found`` (the layout's own file)."""
    file = metadata_path(folder)
    table = read_sequence_metadata(folder).get("camera", {})
    if isinstance(table, dict) and ("width" in table or "height" in table):
        return f"the [camera] table of {file}"
    if isinstance(table, dict) and "preset" in table:
        return f"camera.preset {table['preset']} in {file}"
    return found or "the default camera"


#: What to do about a depth image of another size than its camera's (the end of the messages that say so).
GIVE_THE_CAMERA = (
    "give the camera of these images: --camera fx,fy,cx,cy,width,height (camera= in Python; mabdi's pixel "
    "centres, +0.5 on OpenCV's cx, cy) or a [camera] table (fx, fy, cx, cy, width, height) in"
)


def check_depth_size(intrinsics: Intrinsics, depth_file, origin: str, folder) -> None:
    """A :class:`SequenceError` unless the depth image ``depth_file`` is ``intrinsics``' size; the message names
    both sizes, where the camera came from (``origin``) and how to give the right one (``folder``: the
    sequence's, where its ``mabdi.toml`` goes)."""
    width, height = depth_png_size(depth_file)
    if (width, height) == (intrinsics.width, intrinsics.height):
        return
    raise SequenceError(
        f"{depth_file}: image is {width}x{height}, intrinsics say {intrinsics.width}x{intrinsics.height} ({origin}); "
        f"a depth image read with another size's camera makes a distorted map: {GIVE_THE_CAMERA} {metadata_path(folder)}"
    )


# ---------------------------------------------------------------------------
# Writing mabdi.toml


def metadata_toml(intrinsics: Intrinsics, extra: dict | None = None) -> str:
    """TOML text: a ``[camera]`` table with ``intrinsics`` (mabdi's pixel centres) and the tables of ``extra``.

    ``extra`` maps table names to dicts (nested dicts become sub-tables); a
    ``camera`` entry in it is refused (the camera table is written from the intrinsics).
    """
    extra = dict(extra or {})
    if "camera" in extra:
        raise SequenceError(f"extra tables for {METADATA_FILE} may not include 'camera' (written from the intrinsics)")
    for key, value in extra.items():
        if not isinstance(value, dict):
            raise SequenceError(f"extra entry {key!r} for {METADATA_FILE} must be a table (a dict), got {type(value).__name__}")
    lines = [
        "# Intrinsics in mabdi's conventions: pixel (u, v) has its centre at (u + 0.5, v + 0.5);",
        "# fx, fy, cx, cy in pixels; near, far in metres.",
    ]
    camera = {name: getattr(intrinsics, name) for name in CAMERA_KEYS}
    camera = {k: (float(v) if k not in ("width", "height") else int(v)) for k, v in camera.items()}
    try:
        lines.extend(toml_lines({"camera": camera, **extra}))
    except TypeError as exc:
        raise SequenceError(f"{exc} (writing {METADATA_FILE})") from None
    return "\n".join(lines) + "\n"


def write_metadata(folder, intrinsics: Intrinsics, extra: dict | None = None) -> Path:
    """Write ``mabdi.toml`` into ``folder`` atomically; returns its path."""
    file = Path(folder) / METADATA_FILE
    write_text(file, metadata_toml(intrinsics, extra))
    return file


# ---------------------------------------------------------------------------
# Helpers shared by the readers and writers


def natural_key(name) -> tuple:
    """Sort key of a file name (or path) with its numbers compared as numbers: ``frame-2`` before ``frame-10``."""
    text = str(name)
    parts = re.split(r"(\d+)", text)
    return tuple(int(part) if i % 2 else part for i, part in enumerate(parts)), text


def numbered_files(folder: Path, suffix: str) -> dict[int, Path]:
    """{N: path} of the files ``N<suffix>`` in ``folder`` whose stem is a whole number (ScanNet's ``depth/N.png``,
    Stray Scanner's ``depth/NNNNNN.png``)."""
    return {int(p.stem): p for p in Path(folder).glob(f"*{suffix}") if p.stem.isdigit()}


def natural_sorted(names) -> list:
    """``names`` (strings or paths) in natural order (:func:`natural_key`), as dataset tools list frames
    numbered without zero padding (``frame-1``, ``frame-2``, ..., ``frame-10``)."""
    return sorted(names, key=natural_key)


def nearest_within(query, reference, tolerance: float):
    """For each time in ``query``, the index of the nearest time in ``reference`` (any order), or -1 if none is within ``tolerance``.

    Times in seconds (or any one unit, the same for all three). Ties go to the earlier reference time.
    """
    query = np.asarray(query, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    if reference.size == 0:
        return np.full(query.shape, -1, dtype=np.int64)
    order = np.argsort(reference, kind="stable")
    ordered = reference[order]
    right = np.minimum(np.searchsorted(ordered, query), len(ordered) - 1)
    left = np.maximum(right - 1, 0)
    take_right = np.abs(ordered[right] - query) < np.abs(query - ordered[left])
    best = np.where(take_right, right, left)
    found = np.abs(ordered[best] - query) <= tolerance
    return np.where(found, order[best], -1).astype(np.int64)


def interpolate_poses(query, times, poses, tolerance: float, bridge_gaps: bool = False) -> np.ndarray:
    """(Q, 4, 4) poses at the ``query`` times, interpolated between the two samples around each (linear in
    position, slerp in rotation); NaN where there is none. Times in seconds, ``poses`` (N, 4, 4) rigid.

    A query between two samples that are both within ``tolerance`` of it is interpolated; with
    ``bridge_gaps`` (a transform published slowly, as tf2 treats it) any two samples around it are.
    Otherwise (past the ends, or in a gap) the nearest sample is held if it is within ``tolerance``.
    A query at a sample's own time gets that sample exactly.
    """
    query = np.asarray(query, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    out = np.full((len(query), 4, 4), np.nan)
    if not len(times):
        return out
    order = np.argsort(times, kind="stable")
    times, poses = times[order], poses[order]
    nearest = nearest_within(query, times, tolerance)
    held = nearest >= 0
    out[held] = poses[nearest[held]]
    right = np.searchsorted(times, query, side="right")  # times[right - 1] <= query < times[right]
    left = right - 1
    inside = (left >= 0) & (right < len(times))
    left, right = np.clip(left, 0, len(times) - 1), np.clip(right, 0, len(times) - 1)
    span = times[right] - times[left]
    near = (query - times[left] <= tolerance) & (times[right] - query <= tolerance)
    blend = inside & (span > 0) & (query > times[left]) & (near | bridge_gaps)
    if blend.any():
        a, b = left[blend], right[blend]
        alpha = (query[blend] - times[a]) / span[blend]
        out[blend] = np.eye(4)
        out[blend, :3, 3] = (1.0 - alpha)[:, None] * poses[a, :3, 3] + alpha[:, None] * poses[b, :3, 3]
        start = Rotation.from_matrix(poses[a, :3, :3])
        step = (start.inv() * Rotation.from_matrix(poses[b, :3, :3])).as_rotvec()
        out[blend, :3, :3] = (start * Rotation.from_rotvec(alpha[:, None] * step)).as_matrix()
    exact = held & (np.abs(query - times[np.maximum(nearest, 0)]) == 0)
    out[exact] = poses[nearest[exact]]
    return out


def bad_quaternions(quaternions) -> np.ndarray:
    """(N,) True where an (x, y, z, w) quaternion is not finite or has (nearly) zero norm."""
    q = np.asarray(quaternions, dtype=np.float64).reshape(-1, 4)
    with np.errstate(invalid="ignore"):
        return ~np.isfinite(q).all(axis=1) | ~(np.linalg.norm(q, axis=1) > 1e-9)


def poses_from_translations_quaternions(translations, quaternions):
    """(N, 4, 4) poses from (N, 3) translations (m) and (N, 4) quaternions (x, y, z, w), normalised here."""
    translations = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
    poses = np.tile(np.eye(4), (len(translations), 1, 1))
    if len(translations):
        poses[:, :3, :3] = Rotation.from_quat(np.asarray(quaternions, dtype=np.float64).reshape(-1, 4)).as_matrix()
        poses[:, :3, 3] = translations
    return poses


def prepare_folder(folder: Path, overwrite: bool, what: str) -> None:
    """Create ``folder`` for a writer of ``what``; a file there, or a folder that is not empty (unless
    ``overwrite``), is a :class:`SequenceError`."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise SequenceError(f"cannot write {what} to {folder}: it is a file")
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise SequenceError(f"cannot write {what} to {folder}: the folder exists and is not empty (pass overwrite=True)")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SequenceError(f"cannot write {what} to {folder}: {exc}") from None


def read_colour_image(path: Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an 8-bit colour image (PNG, JPEG, ...; grey or RGBA converted), or a
    :class:`SequenceError` naming it. RGB PNGs are decoded by mabdi's own PNG reader (as depth PNGs are);
    a JPEG larger than ``size`` (width, height) may be decoded at a half, quarter or eighth of its size,
    no smaller than ``size`` (JPEG's own DCT scaling: much faster)."""
    from PIL import Image, UnidentifiedImageError  # on first use: a start-up memory choice (module docs)

    try:
        with open(path, "rb") as stream:
            data = stream.read()
        rgb = decode_rgb8_png(data)
        if rgb is not None:
            return rgb
        with Image.open(io.BytesIO(data)) as image:
            if size is not None and image.format == "JPEG":
                image.draft("RGB", size)
            if image.mode != "RGB":
                if image.mode not in ("L", "RGBA", "P", "RGBX", "CMYK", "YCbCr"):
                    raise SequenceError(f"{path}: not an 8-bit colour image (mode {image.mode})")
                image = image.convert("RGB")
            return np.asarray(image)
    except FileNotFoundError:
        raise SequenceError(f"{path}: colour image missing") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        if isinstance(exc, SequenceError):
            raise
        raise SequenceError(f"{path}: cannot read colour image: {exc}") from None


def write_colour_png(path, colour: np.ndarray, compress_level: int = 1) -> None:
    """Write (H, W, 3) uint8 RGB as an 8-bit PNG, atomically."""
    from PIL import Image  # on first use: a start-up memory choice (module docs)

    with atomic_output(path) as temporary:
        Image.fromarray(np.ascontiguousarray(colour, dtype=np.uint8), "RGB").save(temporary, format="PNG", compress_level=compress_level)


def frame_timestamps(source) -> np.ndarray:
    """Timestamps (s) to write for every frame of ``source``: its own, or ``index / 30`` where it has none (NaN).

    Recorded formats need a time for every frame; a source without them
    (simulated frames) is written as if it ran at 30 frames per second.
    """
    times = np.asarray(source.timestamps, dtype=np.float64)
    missing = ~np.isfinite(times)
    times[missing] = np.flatnonzero(missing) / 30.0
    return times
