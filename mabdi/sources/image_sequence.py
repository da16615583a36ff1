"""What the RGB-D dataset layouts share: a depth PNG per frame, a pose per frame, a camera, maybe colour.

The readers of the common layouts (:mod:`~mabdi.sources.threedmatch`,
:mod:`~mabdi.sources.redwood`, :mod:`~mabdi.sources.scannet`,
:mod:`~mabdi.sources.replica`, :mod:`~mabdi.sources.stray`) each find their files and parse their own
pose and intrinsics files; :class:`ImageSequence` then reads the frames, so
the rules below are written once:

* **Depth**: a 16-bit single-channel PNG per frame, ``depth_scale`` units per
  metre (the layout's own scale, or the ``depth_scale=`` the user gives);
  the layout's ``no_return`` values (0, and 65535 for some) become NaN.
* **Poses**: 4x4 ``world_from_camera`` (camera-to-world, camera frame x
  right, y down, z forward as OpenCV's) matrices, used as they are. A pose
  that holds a NaN or an infinity (ScanNet marks frames its tracking lost
  so) is skipped and counted (``skipped``, and in ``description``). A rotation
  block written to a few digits is replaced by its nearest rotation
  (:func:`mabdi.camera.pose_from_file`; one :class:`~mabdi.errors.PoseFileWarning`
  says how many and by how much); a finite pose that is not rigid is a
  :class:`SequenceError` naming its file and line.
* **Intrinsics**: the layout's camera file (if it has one), then the keys of
  a ``[camera]`` table in the folder's ``mabdi.toml`` replace its values
  (``near`` / ``far`` alone, say), then a ``camera=`` argument (an
  :class:`Intrinsics`, a preset name, or ``"fx,fy,cx,cy,width,height"``) wins
  over both. Width and height default to the first depth image's.
* **Colour** (optional): an 8-bit RGB image per frame (PNG or JPEG). One of
  the depth image's size is registered to it pixel for pixel; one of another
  size needs the colour camera's intrinsics (ScanNet's), and is sampled at the
  pixel where each depth pixel's ray meets it (the two cameras share their
  optical centre and axes, as the layouts' exported frames do).
* **Timestamps** are unknown (NaN) unless the layout has them.

Bad input (a missing file, a line that is not numbers, a matrix of the wrong
size) is a :class:`SequenceError` naming the file and line.

Pillow is imported inside the functions that use it (a start-up memory
choice: ``import mabdi`` and a run of a simulated scene do not load it).
"""

from __future__ import annotations

import math
import struct
import warnings
from pathlib import Path

import numpy as np

from mabdi.camera import Intrinsics, PoseRepairs
from mabdi.depth import DepthFrame
from mabdi.errors import PoseError, PoseFileWarning
from mabdi.sources.frames import FrameSource
from mabdi.sources.sequence_files import (  # noqa: F401 (read_colour_image, write_colour_png, intrinsics_from_matrix: the readers' and writers' own)
    SequenceError,
    camera_from_text,
    camera_table,
    intrinsics_from_matrix,
    intrinsics_with,
    metadata_path,
    read_colour_image,
    read_sequence_metadata,
    write_colour_png,
)
from mabdi.sources.tum import PRESETS as TUM_PRESETS
from mabdi.sources.tum import depth_from_units, read_depth_units


def read_number_rows(path: Path, what: str = "file") -> list[tuple[int, list[float]]]:
    """(line number, numbers) of every non-blank line of a text file of numbers (``#`` comments skipped).

    ``nan`` and ``inf`` read as numbers (a pose may hold them); any other
    field that is not a number is a :class:`SequenceError` naming file and line.
    """
    path = Path(path)
    if not path.is_file():
        raise SequenceError(f"{path}: {what} missing")
    rows = []
    with open(path, encoding="utf-8", errors="replace") as stream:
        for number, line in enumerate(stream, start=1):
            fields = line.split("#", 1)[0].replace(",", " ").split()
            if not fields:
                continue
            try:
                rows.append((number, [float(field) for field in fields]))
            except ValueError:
                raise SequenceError(f"{path}:{number}: {what}: expected numbers, got {line.strip()!r}") from None
    return rows


def read_matrix_file(path: Path, rows: int, columns: int, what: str = "matrix") -> np.ndarray:
    """A ``rows`` x ``columns`` matrix written one row per line (extra rows of a 4x4 camera file are allowed
    when ``rows`` is 3: its upper-left block is taken)."""
    lines = read_number_rows(path, what)
    if len(lines) < rows:
        raise SequenceError(f"{path}: {what}: expected {rows} lines of {columns} numbers, found {len(lines)} lines")
    for number, values in lines[:rows]:
        if len(values) < columns:
            raise SequenceError(f"{path}:{number}: {what}: expected {columns} numbers, got {len(values)}")
    return np.array([values[:columns] for _, values in lines[:rows]], dtype=np.float64)


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file (the PNG header; Pillow for others), or a :class:`SequenceError` naming it."""
    from PIL import Image, UnidentifiedImageError  # on first use: a start-up memory choice (module docs)

    try:
        with open(path, "rb") as stream:
            head = stream.read(24)
        if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
            return struct.unpack(">II", head[16:24])
        with Image.open(path) as image:
            return image.size
    except FileNotFoundError:
        raise SequenceError(f"{path}: image missing") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise SequenceError(f"{path}: cannot read image: {exc}") from None


def camera_matrix_text(intrinsics: Intrinsics, rows: int = 3) -> str:
    """The camera matrix K of ``intrinsics`` with integer pixel centres (the datasets' convention), ``rows``
    (3 or 4) lines of numbers; the inverse of :func:`intrinsics_from_matrix`."""
    k = np.eye(rows)
    k[0, 0], k[1, 1] = intrinsics.fx, intrinsics.fy
    k[0, 2], k[1, 2] = intrinsics.cx - 0.5, intrinsics.cy - 0.5
    return matrix_text(k)


def parse_camera_option(camera, presets: dict[str, Intrinsics], where: str) -> Intrinsics:
    """A ``camera=`` argument as :class:`Intrinsics`: itself, a preset name, or ``"fx,fy,cx,cy,width,height"``
    (mabdi's pixel centres, as in ``mabdi.toml``)."""
    if isinstance(camera, Intrinsics):
        return camera
    if isinstance(camera, str) and camera in presets:
        return presets[camera]
    if isinstance(camera, str) and "," in camera:
        return camera_from_text(camera, where)
    raise SequenceError(
        f"{where}: unknown camera {camera!r} (known presets: {', '.join(presets)}; or give fx,fy,cx,cy,width,height)"
    )


def resolve_intrinsics(folder: Path, found: Intrinsics | None, camera, presets: dict[str, Intrinsics], layout: str) -> Intrinsics:
    """The intrinsics by the rule in the module docs: ``found`` (the layout's file), ``mabdi.toml``'s
    ``[camera]`` over it, ``camera=`` over both."""
    presets = {**TUM_PRESETS, **presets}
    if camera is not None:
        return parse_camera_option(camera, presets, f"{layout} {folder}: camera=")
    file = metadata_path(folder)
    table = camera_table(read_sequence_metadata(folder), file, allowed=("preset", *Intrinsics.__dataclass_fields__))
    base = found
    if "preset" in table:
        base = parse_camera_option(table["preset"], presets, f"{file}: camera.preset")
    if base is None:
        missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in table]
        if missing:
            raise SequenceError(
                f"{layout} {folder}: no intrinsics: pass camera= (--camera: a preset, one of {', '.join(presets)}, "
                f"or fx,fy,cx,cy,width,height) or put a [camera] table (fx, fy, cx, cy, width, height) in {file}"
            )
    return intrinsics_with(base, table, file)


def matrix_text(matrix: np.ndarray) -> str:
    """A matrix one row a line, 17 significant digits (reads back to the same float64)."""
    return "\n".join(" ".join(f"{v:.17g}" for v in row) for row in np.asarray(matrix, dtype=np.float64)) + "\n"


def write_range_metadata(folder: Path, intrinsics: Intrinsics) -> None:
    """A ``mabdi.toml`` with only ``[camera]`` ``near`` and ``far`` (m): the layouts' own files hold the rest."""
    from mabdi.io.atomic import write_text

    text = "# The depth range (metres); the intrinsics are in the layout's own camera file.\n"
    write_text(Path(folder) / "mabdi.toml", text + f"[camera]\nnear = {intrinsics.near!r}\nfar = {intrinsics.far!r}\n")


def colour_lookup(depth: Intrinsics, colour: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) row and column in a colour image (intrinsics ``colour``) of each depth pixel's ray (intrinsics
    ``depth``): the nearest colour pixel to where the ray meets the colour image (shared optical centre and
    axes), clipped to the image."""
    u = (np.arange(depth.width) + 0.5 - depth.cx) / depth.fx * colour.fx + colour.cx
    v = (np.arange(depth.height) + 0.5 - depth.cy) / depth.fy * colour.fy + colour.cy
    columns = np.clip(np.floor(u).astype(np.int64), 0, colour.width - 1)
    rows = np.clip(np.floor(v).astype(np.int64), 0, colour.height - 1)
    return rows, columns


class ImageSequence(FrameSource):
    """Frames as files: a depth PNG, a pose and maybe a colour image each (see the module docs).

    ``depth_files`` (N paths), ``poses`` (N, 4, 4) with ``pose_sources`` (N
    strings naming where each pose was read, "file:line", for messages),
    ``intrinsics``, ``depth_scale`` (units per metre), ``no_return`` (raw
    values that are no return), ``colour_files`` (N paths or None),
    ``colour_intrinsics`` (for colour images of another size), ``timestamps``
    (N seconds, or None). Frames with non-finite poses are skipped here.
    """

    #: The layout's name for messages ("ScanNet folder", ...); subclasses set it.
    layout = "image sequence"

    def _setup(
        self,
        path: Path,
        depth_files: list[Path],
        poses: np.ndarray,
        pose_sources: list[str],
        intrinsics: Intrinsics,
        depth_scale: float,
        no_return=(0,),
        colour_files: list[Path] | None = None,
        colour_intrinsics: Intrinsics | None = None,
        timestamps: np.ndarray | None = None,
    ) -> None:
        self.path = Path(path)
        if not (isinstance(depth_scale, (int, float)) and math.isfinite(depth_scale) and depth_scale > 0):
            raise SequenceError(f"{self.layout} {self.path}: depth scale must be a positive number of units per metre, got {depth_scale!r}")
        if not depth_files:
            raise SequenceError(f"{self.layout} {self.path}: no depth images")
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(poses) != len(depth_files):
            raise SequenceError(f"{self.layout} {self.path}: {len(depth_files)} depth images but {len(poses)} poses")
        finite = np.isfinite(poses).all(axis=(1, 2))
        repairs = PoseRepairs()
        for index in np.flatnonzero(finite):
            try:
                poses[index] = repairs.read(poses[index], "pose")
            except PoseError as exc:
                raise SequenceError(f"{pose_sources[index]}: {exc}") from None
        if (note := repairs.note(f"{self.layout} {self.path}")) is not None:
            warnings.warn(note, PoseFileWarning, stacklevel=3)
        self.skipped = int((~finite).sum())
        keep = np.flatnonzero(finite)
        if not len(keep):
            raise SequenceError(f"{self.layout} {self.path}: every one of the {len(poses)} poses holds NaN or infinity: no frame to map")
        self._intrinsics = intrinsics
        self.depth_scale = float(depth_scale)
        self.no_return = tuple(int(v) for v in no_return)
        self._files = [Path(depth_files[i]) for i in keep]
        self._poses = poses[keep]
        self._colour_files = None if colour_files is None else [Path(colour_files[i]) for i in keep]
        self._colour_intrinsics = colour_intrinsics
        self._lookup = None
        self._lookup_size = None
        times = np.full(len(depth_files), np.nan) if timestamps is None else np.asarray(timestamps, dtype=np.float64)
        self._timestamps = times[keep]
        colour = ", with colour" if self._colour_files is not None else ""
        self.description = f"{self.layout} {self.path} ({len(self._files)} frames{colour}"
        self.description += f", {self.skipped} with a NaN or infinite pose skipped)" if self.skipped else ")"

    @property
    def intrinsics(self) -> Intrinsics:
        return self._intrinsics

    def __len__(self) -> int:
        return len(self._files)

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

    def read_frame(self, index: int) -> DepthFrame:
        raw = read_depth_units(self._files[index], self._intrinsics.shape)
        depth = depth_from_units(raw, self.depth_scale, self.no_return)
        colour = None if self._colour_files is None else self.read_colour(index)
        return DepthFrame(depth, self._intrinsics, self._poses[index], index, float(self._timestamps[index]), colour)

    def read_colour(self, index: int) -> np.ndarray:
        """(H, W, 3) uint8 colour of frame ``index``, registered to its depth pixel for pixel."""
        file = self._colour_files[index]
        camera = self._colour_intrinsics
        colour = read_colour_image(file, None if camera is None else (self._intrinsics.width, self._intrinsics.height))
        if colour.shape[:2] == self._intrinsics.shape:
            return colour
        if camera is None:
            raise SequenceError(
                f"{file}: colour image is {colour.shape[1]}x{colour.shape[0]}, the depth {self._intrinsics.width}x"
                f"{self._intrinsics.height}, and there are no colour intrinsics to register it to the depth"
            )
        if (colour.shape[1], colour.shape[0]) != (self._lookup_size if self._lookup is not None else None):
            scale = colour.shape[1] / camera.width  # 1, or JPEG's 1/2, 1/4, 1/8 when decoded smaller
            if abs(colour.shape[0] - camera.height * scale) > 1:
                raise SequenceError(
                    f"{file}: colour image is {colour.shape[1]}x{colour.shape[0]}, its intrinsics say {camera.width}x{camera.height}"
                )
            scaled = Intrinsics(
                fx=camera.fx * scale, fy=camera.fy * scale, cx=camera.cx * scale, cy=camera.cy * scale,
                width=colour.shape[1], height=colour.shape[0],
            )
            self._lookup = colour_lookup(self._intrinsics, scaled)
            self._lookup_size = (colour.shape[1], colour.shape[0])
        rows, columns = self._lookup
        return colour.take(rows, axis=0).take(columns, axis=1)  # separable: two takes, not a 2-D fancy index


def matching_files(folder: Path, stems: list[str], suffixes: tuple[str, ...]) -> list[Path] | None:
    """For each stem, the file ``folder/stem + suffix`` of the first suffix that exists for the first stem;
    None when there is none for the first stem. A later stem without its file is a :class:`SequenceError`."""
    for suffix in suffixes:
        if (folder / (stems[0] + suffix)).is_file():
            files = [folder / (stem + suffix) for stem in stems]
            for file in files:
                if not file.is_file():
                    raise SequenceError(f"{file}: colour image missing (the first frame has one)")
            return files
    return None
