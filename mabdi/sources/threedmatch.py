"""3DMatch / 7-Scenes folders: read them as a frame source, write any frame source in their layout.

The layout (Microsoft's 7-Scenes, and 3DMatch's RGB-D scenes built on it):

* ``seq-XX/frame-NNNNNN.depth.png``: 16-bit PNG in millimetres
  (:data:`DEPTH_SCALE`), 0 and 65535 = no return (:data:`NO_RETURN`);
* ``seq-XX/frame-NNNNNN.pose.txt``: a 4x4 camera-to-world matrix, one row a
  line (camera frame x right, y down, z forward: mabdi's ``world_from_camera``
  as it is);
* ``seq-XX/frame-NNNNNN.color.png`` (or ``.color.jpg``): the colour image,
  optional;
* ``camera-intrinsics.txt``: the 3x3 camera matrix K (pixel centres at
  integers, so mabdi's cx, cy are K's + 0.5), in the sequence's folder or its
  parent (the scene). 7-Scenes itself ships none: ``--camera 7scenes`` is its
  published camera (585, 585, 320, 240).

PATH may be one sequence (a folder of ``frame-*.depth.png``) or the scene
folder: its ``seq-*`` sequences are read one after the other, in natural
name order, as one run (the datasets' poses of one scene share its world frame).
Frames are taken in file-name order, numbers compared as numbers
(``frame-2`` before ``frame-10``, as ``seq-2`` before ``seq-10``). K holds no
image size: the depth images' is taken when K's principal point lies near
their centre, and images of another size (K's principal point far from their
centre: twice or half the camera's resolution) are refused, naming both sizes. Everything else is
:mod:`mabdi.sources.image_sequence`'s (poses with NaN or infinity skipped
and counted, ``mabdi.toml``, ``camera=``, colour).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from mabdi.camera import Intrinsics
from mabdi.sources.frames import FrameSource
from mabdi.sources.image_sequence import (
    ImageSequence,
    camera_matrix_text,
    intrinsics_from_matrix,
    matching_files,
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
    natural_sorted,
    prepare_folder,
)
from mabdi.sources.tum import write_depth_png
from mabdi.io.atomic import write_text

#: Depth units per metre: millimetres.
DEPTH_SCALE = 1000.0
#: Raw depth values that mean "no return".
NO_RETURN = (0, 65535)
INTRINSICS_FILE = "camera-intrinsics.txt"
DEPTH_SUFFIX = ".depth.png"
POSE_SUFFIX = ".pose.txt"
COLOUR_SUFFIXES = (".color.png", ".color.jpg")

#: 7-Scenes' published camera (585, 585, 320, 240 with integer pixel centres), 640x480.
PRESETS = {"7scenes": dataclasses.replace(Intrinsics(), fx=585.0, fy=585.0, cx=320.5, cy=240.5, width=640, height=480)}


def sequence_folders(path: Path) -> list[Path]:
    """The sequence folders at ``path``: itself if it holds depth frames, else its ``seq-*`` folders that do."""
    path = Path(path)
    if any(path.glob("frame-*" + DEPTH_SUFFIX)):
        return [path]
    return natural_sorted(p for p in path.glob("seq-*") if p.is_dir() and any(p.glob("frame-*" + DEPTH_SUFFIX)))


def is_3dmatch(path: Path) -> bool:
    return Path(path).is_dir() and bool(sequence_folders(path))


class ThreeDMatchSequence(ImageSequence):
    """A 3DMatch / 7-Scenes sequence or scene folder (see the module docs).

    ``camera`` (an :class:`Intrinsics`, a preset name or ``"fx,fy,cx,cy,width,height"``)
    wins over ``camera-intrinsics.txt`` and ``mabdi.toml``; ``depth_scale``
    (units per metre) over :data:`DEPTH_SCALE`.
    """

    layout = "3DMatch / 7-Scenes folder"

    def __init__(self, path, camera=None, depth_scale: float | None = None) -> None:
        path = Path(path)
        folders = sequence_folders(path) if path.is_dir() else []
        if not folders:
            raise SequenceError(f"{self.layout} {path}: no frame-*{DEPTH_SUFFIX} here nor in a seq-* folder")
        depth_files, poses, sources, colour_files = [], [], [], []
        for folder in folders:
            files = natural_sorted(folder.glob("frame-*" + DEPTH_SUFFIX))
            stems = [file.name[: -len(DEPTH_SUFFIX)] for file in files]
            for stem in stems:
                pose_file = folder / (stem + POSE_SUFFIX)
                poses.append(read_matrix_file(pose_file, 4, 4, "pose"))
                sources.append(str(pose_file))
            colours = matching_files(folder, stems, COLOUR_SUFFIXES)
            colour_files = None if colours is None or colour_files is None else colour_files + colours
            depth_files += files
        found = origin = None
        for folder in (folders[0], folders[0].parent):
            file = folder / INTRINSICS_FILE
            if file.is_file():
                matrix = read_matrix_file(file, 3, 3, "camera matrix")
                found = intrinsics_from_matrix(matrix, *matrix_image_size(matrix, png_size(depth_files[0])), file)
                origin = matrix_origin(file, found)
                break
        intrinsics = resolve_intrinsics(path, found, camera, PRESETS, self.layout)
        if camera is None:  # a camera given is checked against each image as it is read
            check_depth_size(intrinsics, depth_files[0], camera_origin(path, origin), path)
        self._setup(
            path, depth_files, np.array(poses), sources, intrinsics, DEPTH_SCALE if depth_scale is None else depth_scale,
            NO_RETURN, colour_files or None,
        )
        self.sequences = folders


def write_3dmatch(source: FrameSource, folder, *, overwrite: bool = False) -> Path:
    """Write every frame of ``source`` as one 3DMatch sequence in ``folder`` (``frame-NNNNNN.depth.png`` in mm,
    ``.pose.txt``, ``.color.png`` when the frames have colour, ``camera-intrinsics.txt``; near and far in a
    ``mabdi.toml``), atomically file by file; returns the folder."""
    folder = Path(folder)
    prepare_folder(folder, overwrite, "a 3DMatch sequence")
    intrinsics = source.intrinsics
    for index in range(len(source)):
        frame = source.read(index)
        stem = folder / f"frame-{index:06d}"
        write_depth_png(f"{stem}{DEPTH_SUFFIX}", frame.depth, DEPTH_SCALE)
        write_text(f"{stem}{POSE_SUFFIX}", matrix_text(frame.world_from_camera))
        if frame.colour is not None:
            write_colour_png(f"{stem}{COLOUR_SUFFIXES[0]}", frame.colour)
    write_text(folder / INTRINSICS_FILE, camera_matrix_text(intrinsics))
    write_range_metadata(folder, intrinsics)
    return folder
