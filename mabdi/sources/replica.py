"""Replica as the NICE-SLAM / iMAP renders ship it: read as a frame source, write any frame source so.

The layout (``Replica/room0`` and the other scenes of NICE-SLAM's download):

* ``results/depthNNNNNN.png``: 16-bit PNG, 6553.5 units per metre
  (:data:`DEPTH_SCALE`: 65535 is 10 m), 0 = no return;
* ``results/frameNNNNNN.jpg`` (or ``.png``): the colour images, optional;
* ``traj.txt``: one 4x4 camera-to-world matrix a line, 16 numbers row-major;
  the camera frame is OpenCV's (x right, y down, z forward: NICE-SLAM flips
  y and z only for its own renderer), so it is mabdi's ``world_from_camera``
  as it is. Line k is the pose of the k-th depth image (in name order,
  numbers compared as numbers: ``depth2`` before ``depth10``).
* no camera file: the intrinsics come from a ``mabdi.toml`` ``[camera]``
  table, or ``camera=`` (``--camera``): ``replica`` is the camera of
  NICE-SLAM's ``replica.yaml`` (1200x680, f = 600, cx 599.5, cy 339.5 with
  integer pixel centres), or ``fx,fy,cx,cy,width,height``.

Everything else is :mod:`mabdi.sources.image_sequence`'s.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from mabdi.camera import Intrinsics
from mabdi.io.atomic import write_text
from mabdi.sources.frames import FrameSource
from mabdi.sources.image_sequence import ImageSequence, matching_files, read_number_rows, resolve_intrinsics, write_colour_png
from mabdi.sources.sequence_files import SequenceError, camera_origin, check_depth_size, natural_sorted, prepare_folder, write_metadata
from mabdi.sources.tum import write_depth_png

#: Depth units per metre (NICE-SLAM's ``png_depth_scale``).
DEPTH_SCALE = 6553.5
NO_RETURN = (0,)
TRAJECTORY_FILE = "traj.txt"
COLOUR_SUFFIXES = (".jpg", ".png")

#: NICE-SLAM's Replica camera (replica.yaml: fx = fy = 600, cx = 599.5, cy = 339.5, integer pixel centres).
PRESETS = {"replica": dataclasses.replace(Intrinsics(), fx=600.0, fy=600.0, cx=600.0, cy=340.0, width=1200, height=680, far=10.0)}


def is_replica(path: Path) -> bool:
    path = Path(path)
    return path.is_dir() and (path / TRAJECTORY_FILE).is_file() and (path / "results").is_dir()


def read_traj(path: Path) -> tuple[np.ndarray, list[str]]:
    """(N, 4, 4) matrices of a ``traj.txt`` (16 numbers a line, row-major) and "file:line" of each."""
    rows = read_number_rows(path, "trajectory")
    for number, values in rows:
        if len(values) != 16:
            raise SequenceError(f"{path}:{number}: trajectory: expected 16 numbers (a 4x4 matrix, row-major), got {len(values)}")
    return np.array([values for _, values in rows], dtype=np.float64).reshape(-1, 4, 4), [f"{path}:{n}" for n, _ in rows]


class ReplicaSequence(ImageSequence):
    """A NICE-SLAM Replica folder (see the module docs); ``camera`` and ``depth_scale`` as for every layout."""

    layout = "Replica (NICE-SLAM) folder"

    def __init__(self, path, camera=None, depth_scale: float | None = None) -> None:
        path = Path(path)
        if not is_replica(path):
            raise SequenceError(f"{self.layout} {path}: needs traj.txt and a results/ folder")
        depth_files = natural_sorted((path / "results").glob("depth*.png"))
        if not depth_files:
            raise SequenceError(f"{self.layout} {path}: no results/depth*.png")
        poses, sources = read_traj(path / TRAJECTORY_FILE)
        if len(poses) != len(depth_files):
            raise SequenceError(f"{path / TRAJECTORY_FILE}: {len(poses)} poses, but results/ holds {len(depth_files)} depth images")
        stems = ["frame" + file.stem[len("depth") :] for file in depth_files]
        colour_files = matching_files(path / "results", stems, COLOUR_SUFFIXES)
        intrinsics = resolve_intrinsics(path, None, camera, PRESETS, self.layout)
        if camera is None:  # a camera given is checked against each image as it is read
            check_depth_size(intrinsics, depth_files[0], camera_origin(path, None), path)
        self._setup(
            path, depth_files, poses, sources, intrinsics, DEPTH_SCALE if depth_scale is None else depth_scale, NO_RETURN,
            colour_files,
        )


def write_replica(source: FrameSource, folder, *, overwrite: bool = False) -> Path:
    """Write every frame of ``source`` as a NICE-SLAM Replica folder (``results/depthNNNNNN.png`` at 6553.5 units
    per metre, ``results/frameNNNNNN.png`` when the frames have colour, ``traj.txt``, the camera in a
    ``mabdi.toml``), atomically file by file; returns the folder."""
    folder = Path(folder)
    prepare_folder(folder, overwrite, "a Replica folder")
    (folder / "results").mkdir(exist_ok=True)
    lines = []
    for index in range(len(source)):
        frame = source.read(index)
        write_depth_png(folder / "results" / f"depth{index:06d}.png", frame.depth, DEPTH_SCALE)
        if frame.colour is not None:
            write_colour_png(folder / "results" / f"frame{index:06d}.png", frame.colour)
        lines.append(" ".join(f"{v:.17g}" for v in frame.world_from_camera.ravel()))
    write_text(folder / TRAJECTORY_FILE, "\n".join(lines) + "\n")
    write_metadata(folder, source.intrinsics)
    return folder
