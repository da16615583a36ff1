"""Folders of depth images beside one pose file, as capture apps and SLAM tools export them: a frame source.

The layout no dataset names, and many recordings have:

* ``depth/`` (or ``depths/``): a 16-bit PNG a frame, :data:`DEPTH_SCALE` units per metre (millimetres, the
  common choice; ``depth_scale=`` / ``--depth-scale`` otherwise), 0 = no return; or a NumPy ``.npy`` (H, W)
  array a frame: floats in metres (0, NaN and infinities no return), integers in units as a PNG's. Ordered
  by the numbers in their names (:func:`~mabdi.sources.pose_files.file_numbers`).
* one pose file in the folder, a name holding ``pose`` or ``traj`` (``.txt``, ``.csv``), camera to world
  (x right, y down, z forward, OpenCV's), in any of the forms :mod:`mabdi.sources.pose_files` reads. As many
  poses as images pair in order; otherwise timed poses are interpolated at the images' times (their names)
  and images outside the poses' span are skipped and counted. Poses in OpenGL's camera axes (x right, y up,
  z backward), as many capture apps write them, or inverted (view matrices), are told by the frames and
  turned (:mod:`mabdi.sources.pose_axes`).
* the camera: ``camera=`` (``--camera``), else a ``[camera]`` table in a ``mabdi.toml``, else a camera file
  in the folder (a name holding ``intrinsic``, or ``K.txt``, ``.txt``): a 3x3 (or 4x4) camera matrix with
  integer pixel centres; width and height from the depth images.
* colour (optional): ``rgb/``, ``color/``, ``colour/`` or ``images/``, an image a frame with the same
  numbers in its name as its depth image's.

Everything else (skipped non-finite poses, colour of another size, the rules for bad input) is
:mod:`mabdi.sources.image_sequence`'s. A folder another layout reads (TUM's ``depth.txt``, ScanNet's
``pose/``, ...) is read as that layout.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from mabdi.camera import PoseRepairs, pixel_rays
from mabdi.depth import DepthFrame
from mabdi.errors import PoseFileWarning
from mabdi.sources.image_sequence import ImageSequence, png_size, read_matrix_file, resolve_intrinsics
from mabdi.sources.pose_axes import AXES_WORDS, pose_axes, turned
from mabdi.sources.pose_files import (
    file_numbers,
    name_times,
    ordered_by_numbers,
    paired_by_time,
    pose_file,
    poses_of_lines,
    read_pose_lines,
)
from mabdi.sources.sequence_files import (
    SequenceError,
    camera_origin,
    check_depth_size,
    intrinsics_from_matrix,
    matrix_image_size,
    matrix_origin,
)

#: Depth units per metre unless told otherwise (millimetres).
DEPTH_SCALE = 1000.0
NO_RETURN = (0,)
DEPTH_FOLDERS = ("depth", "depths")
COLOUR_FOLDERS = ("rgb", "color", "colour", "images")
COLOUR_SUFFIXES = (".png", ".jpg", ".jpeg")


def _depth_files(folder: Path) -> list[Path]:
    """The depth images of ``folder``: its PNGs, else its ``.npy`` arrays."""
    return sorted(folder.glob("*.png")) or sorted(folder.glob("*.npy"))


def _depth_folder(path: Path) -> Path | None:
    return next((path / name for name in DEPTH_FOLDERS if (path / name).is_dir() and _depth_files(path / name)), None)


def read_depth_array(path: Path, scale: float, shape: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W) float32 metres of a ``.npy`` depth image (module docs), or a SequenceError naming it."""
    try:
        raw = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise SequenceError(f"{path}: cannot read the depth array: {exc}") from None
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[:, :, 0]
    if raw.ndim != 2 or not (np.issubdtype(raw.dtype, np.floating) or np.issubdtype(raw.dtype, np.integer)):
        raise SequenceError(f"{path}: a depth array is (H, W) numbers, got shape {raw.shape} of {raw.dtype}")
    if shape is not None and raw.shape != tuple(shape):
        raise SequenceError(f"{path}: depth array is {raw.shape[1]}x{raw.shape[0]}, the camera {shape[1]}x{shape[0]}")
    depth = raw.astype(np.float32) if np.issubdtype(raw.dtype, np.floating) else raw.astype(np.float32) / np.float32(scale)
    with np.errstate(invalid="ignore"):
        depth[~(np.isfinite(depth) & (depth > 0))] = np.nan
    return depth


def _image_size(file: Path) -> tuple[int, int]:
    """(width, height) of a depth image file."""
    if file.suffix == ".npy":
        shape = np.load(file, mmap_mode="r", allow_pickle=False).shape
        return int(shape[1]), int(shape[0])
    return png_size(file)


def is_depth_folder(path) -> bool:
    """Whether ``path`` holds depth images beside one pose file (module docs)."""
    path = Path(path)
    if not path.is_dir() or _depth_folder(path) is None:
        return False
    try:
        return pose_file(path) is not None
    except SequenceError:
        return True  # ours to read, and to say what is wrong with


def camera_file(path: Path) -> Path | None:
    """The folder's camera matrix file (module docs), or None."""
    found = sorted(p for p in path.glob("*.txt") if "intrinsic" in p.stem.lower() or p.stem in ("K", "k"))
    return found[0] if found else None


class DepthFolderSequence(ImageSequence):
    """A folder of depth images and one pose file (module docs); ``camera`` and ``depth_scale`` as for every
    layout."""

    layout = "depth image folder"

    def __init__(self, path, camera=None, depth_scale: float | None = None) -> None:
        path = Path(path)
        folder = _depth_folder(path) if path.is_dir() else None
        file = pose_file(path) if folder is not None else None
        if folder is None or file is None:
            raise SequenceError(f"{self.layout} {path}: needs a depth/ folder of PNG (or .npy) images and a pose file (a name holding 'pose' or 'traj')")
        depth_files = ordered_by_numbers(_depth_files(folder), f"{self.layout} {path}")
        repairs = PoseRepairs()
        rows = read_pose_lines(file)
        poses, times = poses_of_lines(rows, file, repairs)
        if (note := repairs.note(str(file))) is not None:
            warnings.warn(note, PoseFileWarning, stacklevel=2)
        frame_times, outside = times, 0
        if len(poses) != len(depth_files):
            depth_files, poses, frame_times, outside = paired_by_time(
                depth_files, name_times(depth_files), times, poses, str(file), "depth images"
            )
        found = origin = None
        if (matrix_file := camera_file(path)) is not None:
            matrix = read_matrix_file(matrix_file, 3, 3, "camera matrix")
            found = intrinsics_from_matrix(matrix, *matrix_image_size(matrix, _image_size(depth_files[0])), matrix_file)
            origin = matrix_origin(matrix_file, found)
        intrinsics = resolve_intrinsics(path, found, camera, {}, self.layout)
        if camera is None and depth_files[0].suffix == ".png":  # a camera given is checked as each image is read
            check_depth_size(intrinsics, depth_files[0], camera_origin(path, origin), path)
        self._setup(
            path, depth_files, poses, [str(file)] * len(depth_files), intrinsics, DEPTH_SCALE if depth_scale is None else depth_scale, NO_RETURN,
            self._colour_files(path, depth_files), None, frame_times,
        )
        if outside:
            self.description = self.description[:-1] + f", {outside} outside the poses' times skipped)"
        self._poses = self._poses_in_opencv_axes(self._poses)

    def _camera_points(self, index: int) -> np.ndarray:
        """(N, 3) camera-frame points (m) of frame ``index``'s depth."""
        depth = self.read_frame(index).depth
        return (pixel_rays(self._intrinsics) * depth[..., None]).reshape(-1, 3)

    def _poses_in_opencv_axes(self, poses: np.ndarray) -> np.ndarray:
        """``poses`` as written, or turned into the camera's world-from-sensor poses where the frames say they are
        written another way (OpenGL's axes, inverted; :mod:`mabdi.sources.pose_axes`), said once."""
        found = pose_axes(poses, self._camera_points, "camera")
        if not found.turned:
            return poses
        warnings.warn(
            f"{self.layout} {self.path}: {found.describe()}: mabdi reads the poses so and turns them into the "
            "camera's world-from-sensor poses",
            PoseFileWarning,
            stacklevel=3,
        )
        self.description = self.description[:-1] + f", poses read as {AXES_WORDS[found.axes]})"
        return turned(poses, found.axes)

    def read_frame(self, index: int) -> DepthFrame:
        file = self._files[index]
        if file.suffix != ".npy":
            return super().read_frame(index)
        depth = read_depth_array(file, self.depth_scale, self._intrinsics.shape)
        colour = None if self._colour_files is None else self.read_colour(index)
        return DepthFrame(depth, self._intrinsics, self._poses[index], index, float(self._timestamps[index]), colour)

    @staticmethod
    def _colour_files(path: Path, depth_files: list[Path]) -> list[Path] | None:
        """The colour image of each depth image, by the numbers in their names, or None (module docs)."""
        for name in COLOUR_FOLDERS:
            images = [p for p in (path / name).glob("*") if p.suffix.lower() in COLOUR_SUFFIXES] if (path / name).is_dir() else []
            if not images:
                continue
            by_numbers = {file_numbers(p): p for p in images}
            files = [by_numbers.get(file_numbers(d)) for d in depth_files]
            missing = [d for d, c in zip(depth_files, files, strict=True) if c is None]
            if missing:
                raise SequenceError(f"{path / name}: no colour image for depth image {missing[0].name} (other frames have one)")
            return files
        return None


__all__ = ["DepthFolderSequence", "camera_file", "is_depth_folder", "read_depth_array"]
