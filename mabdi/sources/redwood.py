"""Redwood / Open3D reconstruction folders: read them as a frame source, write any frame source in their layout.

The layout (the Redwood indoor scenes, and what Open3D's reconstruction
system reads and writes):

* ``depth/*.png``: 16-bit PNG in millimetres (:data:`DEPTH_SCALE`), 0 = no
  return; frames are the images in file-name order, numbers compared as
  numbers (``2.png`` before ``10.png``), of the camera's size;
* ``color/*.png`` or ``.jpg`` (also ``image/`` or ``rgb/``): colour images, as
  many as depth images, optional;
* ``trajectory.log`` (or the folder's only ``*.log``), Redwood's log format:
  per frame a metadata line of three integers (Open3D writes ``i i i+1``),
  then the 4x4 camera-to-world matrix, one row a line. The k-th entry is the
  pose of the k-th depth image; the number of entries must match the images.
* a camera JSON (``camera_intrinsic.json``, ``intrinsic.json``, ``camera.json``
  or the folder's only ``*.json``), Open3D's ``PinholeCameraIntrinsic``:
  ``width``, ``height`` and ``intrinsic_matrix``, the 3x3 K in column-major
  order, pixel centres at integers (mabdi's cx, cy are K's + 0.5). Without
  one, ``camera=`` or ``mabdi.toml`` give the camera (``--camera ros`` is
  Open3D's default PrimeSense camera, 525, 525, 319.5, 239.5).

Everything else is :mod:`mabdi.sources.image_sequence`'s.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mabdi.io.atomic import write_text
from mabdi.sources.frames import FrameSource
from mabdi.sources.image_sequence import (
    ImageSequence,
    intrinsics_from_matrix,
    matrix_text,
    read_number_rows,
    resolve_intrinsics,
    write_colour_png,
    write_range_metadata,
)
from mabdi.sources.sequence_files import SequenceError, camera_origin, check_depth_size, natural_sorted, prepare_folder
from mabdi.sources.tum import write_depth_png

#: Depth units per metre: millimetres.
DEPTH_SCALE = 1000.0
NO_RETURN = (0,)
TRAJECTORY_FILE = "trajectory.log"
CAMERA_FILES = ("camera_intrinsic.json", "intrinsic.json", "camera.json")
COLOUR_FOLDERS = ("color", "image", "rgb")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def trajectory_file(folder: Path) -> Path | None:
    """The folder's trajectory: ``trajectory.log``, else its only ``*.log``; None when there is none."""
    if (folder / TRAJECTORY_FILE).is_file():
        return folder / TRAJECTORY_FILE
    logs = sorted(folder.glob("*.log"))
    return logs[0] if len(logs) == 1 else None


def is_redwood(path: Path) -> bool:
    path = Path(path)
    return path.is_dir() and (path / "depth").is_dir() and trajectory_file(path) is not None


def read_trajectory_log(path: Path) -> tuple[np.ndarray, list[str]]:
    """(N, 4, 4) matrices of a Redwood ``.log`` file and, for each, "file:line" of its metadata line."""
    rows = read_number_rows(path, "trajectory")
    if len(rows) % 5:
        number = rows[-(len(rows) % 5)][0]
        raise SequenceError(f"{path}:{number}: trajectory: an entry is a metadata line and 4 matrix rows; the file ends mid-entry")
    poses, sources = [], []
    for start in range(0, len(rows), 5):
        number, meta = rows[start]
        if len(meta) != 3:
            raise SequenceError(f"{path}:{number}: trajectory: expected a metadata line of 3 integers, got {len(meta)} numbers")
        for line, values in rows[start + 1 : start + 5]:
            if len(values) != 4:
                raise SequenceError(f"{path}:{line}: trajectory: expected a matrix row of 4 numbers, got {len(values)}")
        poses.append([values for _, values in rows[start + 1 : start + 5]])
        sources.append(f"{path}:{number}")
    return np.array(poses, dtype=np.float64).reshape(-1, 4, 4), sources


def read_camera_json(path: Path):
    """:class:`Intrinsics` of an Open3D ``PinholeCameraIntrinsic`` JSON file, or a :class:`SequenceError` naming it."""
    try:
        data = json.loads(Path(path).read_text())
        width, height = data["width"], data["height"]
        k = np.asarray(data["intrinsic_matrix"], dtype=np.float64)
    except json.JSONDecodeError as exc:
        raise SequenceError(f"{path}:{exc.lineno}: not valid JSON: {exc.msg}") from None
    except (KeyError, TypeError) as exc:
        raise SequenceError(f"{path}: camera JSON needs width, height and intrinsic_matrix (9 numbers), missing {exc}") from None
    except ValueError as exc:
        raise SequenceError(f"{path}: intrinsic_matrix is not numbers: {exc}") from None
    if k.shape != (9,):
        raise SequenceError(f"{path}: intrinsic_matrix must hold 9 numbers (3x3, column-major), got shape {k.shape}")
    return intrinsics_from_matrix(k.reshape(3, 3).T, width, height, path)


def camera_file(folder: Path) -> Path | None:
    for name in CAMERA_FILES:
        if (folder / name).is_file():
            return folder / name
    files = sorted(folder.glob("*.json"))
    return files[0] if len(files) == 1 else None


def _images(folder: Path) -> list[Path]:
    return natural_sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) if folder.is_dir() else []


class RedwoodSequence(ImageSequence):
    """A Redwood / Open3D folder (see the module docs); ``camera`` and ``depth_scale`` as for every layout."""

    layout = "Redwood / Open3D folder"

    def __init__(self, path, camera=None, depth_scale: float | None = None) -> None:
        path = Path(path)
        if not is_redwood(path):
            raise SequenceError(f"{self.layout} {path}: needs a depth/ folder and trajectory.log (or one *.log)")
        depth_files = [p for p in _images(path / "depth") if p.suffix.lower() == ".png"]
        if not depth_files:
            raise SequenceError(f"{self.layout} {path}: no PNG in depth/")
        log = trajectory_file(path)
        poses, sources = read_trajectory_log(log)
        if len(poses) != len(depth_files):
            raise SequenceError(f"{log}: {len(poses)} poses, but depth/ holds {len(depth_files)} images")
        colour_files = None
        for name in COLOUR_FOLDERS:
            images = _images(path / name)
            if images:
                if len(images) != len(depth_files):
                    raise SequenceError(f"{path / name}: {len(images)} colour images, but depth/ holds {len(depth_files)}")
                colour_files = images
                break
        json_file = camera_file(path)
        found = read_camera_json(json_file) if json_file is not None else None
        intrinsics = resolve_intrinsics(path, found, camera, {}, self.layout)
        origin = None if json_file is None else f"{json_file} says width {found.width}, height {found.height}"
        if camera is None:  # a camera given is checked against each image as it is read
            check_depth_size(intrinsics, depth_files[0], camera_origin(path, origin), path)
        self._setup(
            path, depth_files, poses, sources, intrinsics, DEPTH_SCALE if depth_scale is None else depth_scale, NO_RETURN,
            colour_files,
        )


def write_redwood(source: FrameSource, folder, *, overwrite: bool = False) -> Path:
    """Write every frame of ``source`` as a Redwood / Open3D folder (``depth/NNNNNN.png`` in mm,
    ``color/NNNNNN.png`` when the frames have colour, ``trajectory.log``, ``camera_intrinsic.json``; near and
    far in a ``mabdi.toml``), atomically file by file; returns the folder."""
    folder = Path(folder)
    prepare_folder(folder, overwrite, "a Redwood / Open3D folder")
    (folder / "depth").mkdir(exist_ok=True)
    intrinsics = source.intrinsics
    entries = []
    for index in range(len(source)):
        frame = source.read(index)
        write_depth_png(folder / "depth" / f"{index:06d}.png", frame.depth, DEPTH_SCALE)
        if frame.colour is not None:
            (folder / "color").mkdir(exist_ok=True)
            write_colour_png(folder / "color" / f"{index:06d}.png", frame.colour)
        entries.append(f"{index} {index} {index + 1}\n" + matrix_text(frame.world_from_camera))
    write_text(folder / TRAJECTORY_FILE, "".join(entries))
    k = [intrinsics.fx, 0.0, 0.0, 0.0, intrinsics.fy, 0.0, intrinsics.cx - 0.5, intrinsics.cy - 0.5, 1.0]
    camera = {"width": intrinsics.width, "height": intrinsics.height, "intrinsic_matrix": k}
    write_text(folder / CAMERA_FILES[0], json.dumps(camera, indent=1) + "\n")
    write_range_metadata(folder, intrinsics)
    return folder
