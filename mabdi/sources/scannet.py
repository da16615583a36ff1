"""ScanNet scenes as its exporter (``SensReader``) writes them: read as a frame source, write any frame source so.

The layout (``python reader.py --export_depth_images --export_poses
--export_intrinsics --export_color_images``):

* ``depth/N.png``: 16-bit PNG in millimetres (:data:`DEPTH_SCALE`), 0 = no
  return; frames in the order of N (an integer, not the file name's order);
* ``pose/N.txt``: the 4x4 camera-to-world matrix, one row a line. ScanNet
  marks frames its tracking lost with ``-inf`` (or NaN) poses: those frames
  are skipped and counted;
* ``intrinsic/intrinsic_depth.txt``: the depth camera's 4x4 matrix whose
  upper-left 3x3 is K (pixel centres at integers: mabdi's cx, cy are K's
  + 0.5); the image size is the depth images' (refused, naming both sizes,
  when K's principal point is far from their centre: images of another
  resolution than K's);
* ``color/N.jpg`` (or ``.png``), optional, with
  ``intrinsic/intrinsic_color.txt``: ScanNet's colour camera is larger
  (1296x968) than its depth camera (640x480); the exporter's frames share
  the optical centre and axes (its extrinsics are identities), so each depth
  pixel takes the colour where its ray meets the colour image.

Everything else is :mod:`mabdi.sources.image_sequence`'s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mabdi.io.atomic import write_text
from mabdi.sources.frames import FrameSource
from mabdi.sources.image_sequence import (
    ImageSequence,
    camera_matrix_text,
    intrinsics_from_matrix,
    matrix_text,
    png_size,
    read_matrix_file,
    resolve_intrinsics,
    write_colour_png,
    write_range_metadata,
)
from mabdi.sources.sequence_files import (
    SequenceError,
    camera_origin,
    check_depth_size,
    matrix_image_size,
    matrix_origin,
    numbered_files,
    prepare_folder,
)
from mabdi.sources.tum import write_depth_png

#: Depth units per metre: millimetres.
DEPTH_SCALE = 1000.0
NO_RETURN = (0,)
DEPTH_INTRINSICS = "intrinsic/intrinsic_depth.txt"
COLOUR_INTRINSICS = "intrinsic/intrinsic_color.txt"
COLOUR_SUFFIXES = (".jpg", ".png")


def is_scannet(path: Path) -> bool:
    path = Path(path)
    return path.is_dir() and (path / "depth").is_dir() and (path / "pose").is_dir()


class ScanNetSequence(ImageSequence):
    """A ScanNet exporter folder (see the module docs); ``camera`` and ``depth_scale`` as for every layout."""

    layout = "ScanNet folder"

    def __init__(self, path, camera=None, depth_scale: float | None = None) -> None:
        path = Path(path)
        if not is_scannet(path):
            raise SequenceError(f"{self.layout} {path}: needs depth/ and pose/ folders")
        depth = numbered_files(path / "depth", ".png")
        if not depth:
            raise SequenceError(f"{self.layout} {path}: no N.png in depth/")
        numbers = sorted(depth)
        depth_files = [depth[n] for n in numbers]
        pose_files = [path / "pose" / f"{n}.txt" for n in numbers]
        poses = np.array([read_matrix_file(file, 4, 4, "pose") for file in pose_files])
        found = origin = None
        if (path / DEPTH_INTRINSICS).is_file():
            matrix = read_matrix_file(path / DEPTH_INTRINSICS, 3, 3, "camera matrix")
            found = intrinsics_from_matrix(matrix, *matrix_image_size(matrix, png_size(depth_files[0])), path / DEPTH_INTRINSICS)
            origin = matrix_origin(path / DEPTH_INTRINSICS, found)
        intrinsics = resolve_intrinsics(path, found, camera, {}, self.layout)
        if camera is None:  # a camera given is checked against each image as it is read
            check_depth_size(intrinsics, depth_files[0], camera_origin(path, origin), path)
        colour_files = colour_camera = None
        for suffix in COLOUR_SUFFIXES:
            colour = numbered_files(path / "color", suffix)
            if colour:
                missing = [n for n in numbers if n not in colour]
                if missing:
                    raise SequenceError(f"{path / 'color' / f'{missing[0]}{suffix}'}: colour image missing (other frames have one)")
                colour_files = [colour[n] for n in numbers]
                if (path / COLOUR_INTRINSICS).is_file():
                    size = png_size(colour_files[0])
                    matrix = read_matrix_file(path / COLOUR_INTRINSICS, 3, 3, "camera matrix")
                    colour_camera = intrinsics_from_matrix(matrix, *size, path / COLOUR_INTRINSICS)
                break
        self._setup(
            path, depth_files, poses, [str(f) for f in pose_files], intrinsics,
            DEPTH_SCALE if depth_scale is None else depth_scale, NO_RETURN, colour_files, colour_camera,
        )


def write_scannet(source: FrameSource, folder, *, overwrite: bool = False, lost=()) -> Path:
    """Write every frame of ``source`` as a ScanNet exporter folder (``depth/N.png`` in mm, ``pose/N.txt``,
    ``intrinsic/intrinsic_depth.txt``; ``color/N.png`` and ``intrinsic_color.txt`` when the frames have
    colour; near and far in a ``mabdi.toml``), atomically file by file; frames in ``lost`` get ScanNet's
    ``-inf`` pose. Returns the folder."""
    folder = Path(folder)
    prepare_folder(folder, overwrite, "a ScanNet folder")
    for name in ("depth", "pose", "intrinsic"):
        (folder / name).mkdir(exist_ok=True)
    intrinsics = source.intrinsics
    for index in range(len(source)):
        frame = source.read(index)
        write_depth_png(folder / "depth" / f"{index}.png", frame.depth, DEPTH_SCALE)
        pose = np.full((4, 4), -np.inf) if index in lost else frame.world_from_camera
        write_text(folder / "pose" / f"{index}.txt", matrix_text(pose))
        if frame.colour is not None:
            (folder / "color").mkdir(exist_ok=True)
            write_colour_png(folder / "color" / f"{index}.png", frame.colour)
            write_text(folder / COLOUR_INTRINSICS, camera_matrix_text(intrinsics, 4))
    write_text(folder / DEPTH_INTRINSICS, camera_matrix_text(intrinsics, 4))
    write_range_metadata(folder, intrinsics)
    return folder
