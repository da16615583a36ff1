"""Stray Scanner folders (an iPhone's or iPad's LiDAR depth with ARKit's poses): read them as a frame source, and write any.

The layout the Stray Scanner app exports:

* ``depth/NNNNNN.png``: 16-bit PNG in millimetres (:data:`DEPTH_SCALE`), 0 =
  no return; ARKit's scene depth, 256 x 192 on the devices so far;
* ``confidence/NNNNNN.png`` (optional): 8-bit, ARKit's confidence of each depth
  pixel, 0 (low), 1 (medium), 2 (high). Pixels below ``min_confidence``
  (:data:`MIN_CONFIDENCE`, medium) become no return: ARKit marks low the
  depth it interpolated across edges and read off dark or distant surfaces;
* ``odometry.csv``: a header line, then ``timestamp, frame, x, y, z, qx, qy,
  qz, qw`` a frame (seconds, the frame's number, metres, a unit quaternion),
  newer versions followed by the colour camera's ``fx, fy, cx, cy`` and
  distortion centre (not read: ``camera_matrix.csv`` gives the camera). The
  pose is ``world_from_camera`` with the camera frame x right, y down, z
  forward (OpenCV's, as mabdi's: the app turns ARKit's camera frame so), the
  world ARKit's (gravity along -y);
* ``camera_matrix.csv``: the colour camera's 3x3 K (comma-separated, integer
  pixel centres), for the colour video ``rgb.mp4``. The depth image is the
  colour image scaled down by one factor in both axes, so the depth camera is K
  scaled by depth width / colour width; the colour width is read from
  ``rgb.mp4``'s header, else it is the capture width among
  :data:`COLOUR_WIDTHS` (and the depth width itself) nearest twice K's cx, which
  must lie within 3% of it (a refusal names the file; ``--camera`` or a
  ``[camera]`` table in ``mabdi.toml`` then gives the camera).

Frames are the depth images, in the order of their numbers; each takes the
odometry row of its number (a depth image without one is a
:class:`SequenceError` naming it) and its timestamp. The colour video is not
read. Everything else (``camera=``, ``mabdi.toml``, poses written to a few
digits) is :mod:`mabdi.sources.image_sequence`'s.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from mabdi.depth import DepthFrame
from mabdi.io.atomic import atomic_output, write_text
from mabdi.sources.frames import FrameSource
from mabdi.sources.image_sequence import ImageSequence, intrinsics_from_matrix, read_number_rows, resolve_intrinsics
from mabdi.sources.png import decode_gray8_png
from mabdi.sources.sequence_files import (
    SequenceError,
    camera_origin,
    check_depth_size,
    depth_png_size,
    numbered_files,
    poses_from_translations_quaternions,
    prepare_folder,
)
from mabdi.sources.tum import write_depth_png

#: Depth units per metre: millimetres.
DEPTH_SCALE = 1000.0
NO_RETURN = (0,)
#: ARKit's confidence levels: a depth pixel below this one is no return (0 low, 1 medium, 2 high).
MIN_CONFIDENCE = 1
#: Widths (pixels) of the colour images ARKit captures, for a folder whose ``rgb.mp4`` is not there.
COLOUR_WIDTHS = (640, 1280, 1440, 1920, 3840, 4032)
#: Twice K's cx lies within this share of the colour width (a real camera's principal point is near the centre).
CENTRE_SHARE = 0.03
ODOMETRY = "odometry.csv"
CAMERA_MATRIX = "camera_matrix.csv"
COLOUR_VIDEO = "rgb.mp4"


def is_stray(path: Path) -> bool:
    path = Path(path)
    return path.is_dir() and (path / ODOMETRY).is_file() and (path / "depth").is_dir()


def _boxes(data: bytes, start: int, end: int):
    """(kind, body start, body end) of the MP4 boxes in ``data[start:end]``."""
    position = start
    while position + 8 <= end:
        size, kind = struct.unpack(">I4s", data[position : position + 8])
        header = 8
        if size == 1 and position + 16 <= end:
            (size,) = struct.unpack(">Q", data[position + 8 : position + 16])
            header = 16
        elif size == 0:
            size = end - position
        if size < header or position + size > end:
            return
        yield kind, position + header, position + size
        position += size


def mp4_video_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of the first video track of an MP4 file (its ``tkhd`` box), or None where the file is
    missing or holds none. Only the top-level boxes' headers and the ``moov`` box are read, not the video."""
    try:
        with open(path, "rb") as stream:
            total = stream.seek(0, 2)
            position, moov = 0, None
            while position + 8 <= total and moov is None:
                stream.seek(position)
                head = stream.read(16)
                size, kind = struct.unpack(">I4s", head[:8])
                header = 8
                if size == 1 and len(head) == 16:
                    (size,) = struct.unpack(">Q", head[8:16])
                    header = 16
                elif size == 0:
                    size = total - position
                if size < header:
                    return None
                if kind == b"moov":
                    stream.seek(position + header)
                    moov = stream.read(size - header)
                position += size
    except (OSError, struct.error):
        return None
    if moov is None:
        return None
    for track, t_start, t_end in _boxes(moov, 0, len(moov)):
        if track != b"trak":
            continue
        for part, p_start, p_end in _boxes(moov, t_start, t_end):
            if part == b"tkhd" and p_end - p_start >= 8:
                width, height = struct.unpack(">II", moov[p_end - 8 : p_end])
                if width and height:
                    return width >> 16, height >> 16
    return None


def colour_width(folder: Path, matrix: np.ndarray, depth_width: int) -> tuple[int, str]:
    """The width of the colour images ``camera_matrix.csv`` (``matrix``) is for, and words for where it came from
    (see the module docs)."""
    size = mp4_video_size(folder / COLOUR_VIDEO)
    if size is not None:
        return size[0], f"{folder / COLOUR_VIDEO}'s header"
    implied = 2.0 * (float(matrix[0, 2]) + 0.5)
    candidates = np.array((depth_width, *COLOUR_WIDTHS), dtype=np.float64)
    nearest = float(candidates[np.argmin(np.abs(candidates - implied))])
    if not (np.isfinite(implied) and abs(implied - nearest) <= CENTRE_SHARE * nearest):
        raise SequenceError(
            f"{folder / CAMERA_MATRIX}: no {COLOUR_VIDEO} to read the colour image's size from, and its principal "
            f"point (cx {matrix[0, 2]:g}) is near the centre of none of the widths ARKit captures "
            f"({', '.join(str(w) for w in COLOUR_WIDTHS)}): give the depth camera with --camera fx,fy,cx,cy,width,height"
        )
    return int(nearest), f"the capture width whose centre its principal point is ({COLOUR_VIDEO} not there)"


def read_odometry(path: Path) -> tuple[dict[int, int], np.ndarray, np.ndarray]:
    """(frame number -> row, (N,) timestamps (s), (N, 4, 4) ``world_from_camera``) of an ``odometry.csv``.

    Each row needs at least the nine numbers of the module docs (later columns, empty ones too, are not read);
    a row that has not, a quaternion of (nearly) zero length, or a frame number twice is a
    :class:`SequenceError` naming file and line."""
    if not path.is_file():
        raise SequenceError(f"{path}: odometry missing")
    rows, lines = [], []
    with open(path, encoding="utf-8", errors="replace") as stream:
        for number, line in enumerate(stream, start=1):
            fields = [field.strip() for field in line.split(",")]
            if not any(fields) or (number == 1 and fields[0].lower() == "timestamp"):
                continue
            try:
                values = [float(field) for field in fields[:9]]
            except ValueError:
                raise SequenceError(f"{path}:{number}: odometry: expected numbers, got {line.strip()!r}") from None
            if len(values) < 9:
                raise SequenceError(
                    f"{path}:{number}: odometry: expected timestamp, frame, x, y, z, qx, qy, qz, qw; got {len(values)} numbers"
                )
            rows.append(values)
            lines.append(number)
    if not rows:
        raise SequenceError(f"{path}: odometry holds no rows")
    table = np.array(rows, dtype=np.float64)
    frames = {}
    for row, (frame, number) in enumerate(zip(table[:, 1], lines)):
        if frame != int(frame) or int(frame) in frames:
            raise SequenceError(f"{path}:{number}: odometry: frame {frame:g} is not a new frame number")
        frames[int(frame)] = row
    quaternions = table[:, 5:9]
    norms = np.linalg.norm(quaternions, axis=1)
    bad = np.flatnonzero(~(np.isfinite(quaternions).all(axis=1) & (np.abs(norms - 1.0) < 0.01)))
    if len(bad):
        raise SequenceError(
            f"{path}:{lines[bad[0]]}: odometry: the quaternion ({', '.join(f'{v:g}' for v in quaternions[bad[0]])}) "
            "is not of unit length"
        )
    return frames, table[:, 0], poses_from_translations_quaternions(table[:, 2:5], quaternions)


class StraySequence(ImageSequence):
    """A Stray Scanner folder (see the module docs); ``camera`` and ``depth_scale`` as for every layout,
    ``min_confidence`` (0, 1 or 2) the least ARKit confidence a depth pixel needs."""

    layout = "Stray Scanner folder"

    def __init__(self, path, camera=None, depth_scale: float | None = None, min_confidence: int = MIN_CONFIDENCE) -> None:
        path = Path(path)
        if not is_stray(path):
            raise SequenceError(f"{self.layout} {path}: needs a depth/ folder and {ODOMETRY}")
        if min_confidence not in (0, 1, 2):
            raise SequenceError(f"{self.layout} {path}: min_confidence must be 0, 1 or 2 (ARKit's levels), got {min_confidence!r}")
        depth = numbered_files(path / "depth", ".png")
        if not depth:
            raise SequenceError(f"{self.layout} {path}: no NNNNNN.png in depth/")
        numbers = sorted(depth)
        depth_files = [depth[n] for n in numbers]
        frames, times, poses = read_odometry(path / ODOMETRY)
        missing = [n for n in numbers if n not in frames]
        if missing:
            raise SequenceError(f"{depth[missing[0]]}: no row of {path / ODOMETRY} has its frame number {missing[0]}")
        rows = np.array([frames[n] for n in numbers])
        found = origin = None
        if camera is None and (path / CAMERA_MATRIX).is_file():
            matrix = np.array([values for _, values in read_number_rows(path / CAMERA_MATRIX, "camera matrix")][:3])
            if matrix.shape != (3, 3):
                raise SequenceError(f"{path / CAMERA_MATRIX}: camera matrix: expected 3 rows of 3 numbers")
            width, height = depth_png_size(depth_files[0])
            colour, where = colour_width(path, matrix, width)
            scaled = matrix.copy()
            scale = width / colour
            scaled[:2, :2] *= scale
            scaled[:2, 2] = (matrix[:2, 2] + 0.5) * scale - 0.5  # the pixels' corners scale, not their centres
            found = intrinsics_from_matrix(scaled, width, height, path / CAMERA_MATRIX)
            origin = f"{path / CAMERA_MATRIX} for a {colour}-pixel-wide colour image ({where}), scaled to the depth"
        intrinsics = resolve_intrinsics(path, found, camera, {}, self.layout)
        if camera is None:
            check_depth_size(intrinsics, depth_files[0], camera_origin(path, origin), path)
        self.min_confidence = int(min_confidence)
        self._confidence = numbered_files(path / "confidence", ".png") if (path / "confidence").is_dir() else {}
        self._numbers = numbers
        self._setup(
            path, depth_files, poses[rows], [f"{path / ODOMETRY}: frame {n}" for n in numbers], intrinsics,
            DEPTH_SCALE if depth_scale is None else depth_scale, NO_RETURN, timestamps=times[rows],
        )  # fmt: skip
        if self._confidence and self.min_confidence > 0:
            self.description = self.description[:-1] + f", depth of ARKit confidence {self.min_confidence} and above)"

    def read_frame(self, index: int) -> DepthFrame:
        frame = super().read_frame(index)
        file = self._confidence.get(self._numbers[index]) if self.min_confidence > 0 else None
        if file is not None:
            confidence = read_confidence(file, self._intrinsics.shape)
            frame.depth[confidence < self.min_confidence] = np.nan
        return frame


def read_confidence(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) uint8 confidence levels of an 8-bit greyscale PNG, checked against ``shape`` (H, W); a missing,
    damaged or differently shaped image is a :class:`SequenceError` naming it."""
    try:
        levels = decode_gray8_png(Path(path).read_bytes())
    except (OSError, ValueError, struct.error) as exc:
        raise SequenceError(f"{path}: cannot read confidence PNG: {exc}") from None
    if levels is None:
        from PIL import Image, UnidentifiedImageError  # a PNG of another kind: Pillow (a start-up memory choice)

        try:
            with Image.open(path) as image:
                levels = np.asarray(image.convert("L"))
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
            raise SequenceError(f"{path}: cannot read confidence PNG: {exc}") from None
    if levels.shape != tuple(shape):
        raise SequenceError(f"{path}: confidence image is {levels.shape[1]}x{levels.shape[0]}, the depth {shape[1]}x{shape[0]}")
    return levels


def write_stray(source: FrameSource, folder, *, overwrite: bool = False, confidence=None) -> Path:
    """Write every frame of ``source`` as a Stray Scanner folder (``depth/NNNNNN.png`` in mm, ``odometry.csv``,
    ``camera_matrix.csv`` for a colour image of the depth's size; ``confidence/NNNNNN.png`` from
    ``confidence(index)`` -> (H, W) levels 0-2 when given, else every valid pixel high), atomically file by file.
    Returns the folder."""
    from PIL import Image  # on first use: a start-up memory choice

    from mabdi.camera import quaternions_from_rotations
    from mabdi.sources.image_sequence import camera_matrix_text, write_range_metadata

    folder = Path(folder)
    prepare_folder(folder, overwrite, "a Stray Scanner folder")
    for name in ("depth", "confidence"):
        (folder / name).mkdir(exist_ok=True)
    rows = ["timestamp, frame, x, y, z, qx, qy, qz, qw"]
    for index in range(len(source)):
        frame = source.read(index)
        write_depth_png(folder / "depth" / f"{index:06d}.png", frame.depth, DEPTH_SCALE)
        levels = confidence(index) if confidence is not None else np.where(np.isfinite(frame.depth), 2, 0)
        with atomic_output(folder / "confidence" / f"{index:06d}.png") as temporary:
            Image.fromarray(np.asarray(levels, dtype=np.uint8)).save(temporary, format="PNG")
        pose = frame.world_from_camera
        q = quaternions_from_rotations(pose[None, :3, :3])[0]
        time = frame.timestamp if np.isfinite(frame.timestamp) else index / 60.0
        rows.append(f"{time:.9f}, {index:06d}, " + ", ".join(f"{v:.17g}" for v in (*pose[:3, 3], *q)))
    write_text(folder / ODOMETRY, "\n".join(rows) + "\n")
    write_text(folder / CAMERA_MATRIX, camera_matrix_text(source.intrinsics).replace(" ", ", "))
    write_range_metadata(folder, source.intrinsics)
    return folder
