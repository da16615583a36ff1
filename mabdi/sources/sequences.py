"""Recorded depth sequences: open one whatever its format.

Formats read and written (each a :class:`~mabdi.sources.frames.FrameSource`):

* a TUM RGB-D benchmark folder (``depth/*.png``, ``depth.txt``,
  ``groundtruth.txt``): :mod:`mabdi.sources.tum`;
* a ROS 2 bag folder (``metadata.yaml`` with ``.db3`` or ``.mcap`` files), or a
  single ``.db3`` / ``.mcap`` file, or a ROS 1 ``.bag`` file: :mod:`mabdi.sources.rosbag2`;
* the common RGB-D dataset layouts (:mod:`mabdi.sources.image_sequence` has
  what they share): 3DMatch / 7-Scenes (:mod:`mabdi.sources.threedmatch`),
  Redwood / Open3D (:mod:`mabdi.sources.redwood`), ScanNet's exporter
  (:mod:`mabdi.sources.scannet`), Replica as NICE-SLAM ships it
  (:mod:`mabdi.sources.replica`) and the Stray Scanner app's iPhone / iPad
  LiDAR exports (:mod:`mabdi.sources.stray`);
* a KITTI-style LiDAR folder (``velodyne/*.bin``, ``poses.txt``, ``calib.txt``):
  :mod:`mabdi.sources.kitti`, its scans turned into range images; a folder of
  LiDAR scans beside their poses as other tools ship them: :mod:`mabdi.sources.scan_folder`;
* a folder of depth images beside one pose file (capture apps' and SLAM tools' exports):
  :mod:`mabdi.sources.depth_folder`.

:func:`open_sequence` tells them apart, in the order of
:func:`sequence_format`: ``depth.txt`` is TUM; ``metadata.yaml`` or a
``.db3`` / ``.mcap`` (or a ``.bag`` file) is a bag; ``velodyne/`` with ``poses.txt`` is KITTI; ``traj.txt`` with ``results/`` is Replica;
``depth/`` with ``pose/`` is ScanNet; ``depth/`` with ``odometry.csv`` is Stray Scanner; ``depth/`` with a ``.log`` is Redwood;
``frame-*.depth.png`` (here or in ``seq-*`` folders) is 3DMatch; ``depth/`` with a pose file is a depth image
folder; ``.pcd`` or ``.bin`` scans (here or in a folder below) with ``poses/`` or a pose file is a LiDAR scan folder. A folder
that holds the files of two formats is read as the first, with a warning
naming the other; a ``[sequence]`` table in its ``mabdi.toml`` with
``format = "3dmatch"`` (a name in :data:`FORMATS`) chooses.

This module sits above the format modules. What they share (the
``mabdi.toml`` a sequence may carry beside it, :class:`SequenceError`, pose
interpolation, colour images, ...) is in :mod:`mabdi.sources.sequence_files`,
below them all, and re-exported here.
"""

from __future__ import annotations

import importlib
import warnings
from pathlib import Path

from mabdi.camera import quaternions_from_rotations  # re-exported (it was defined here)
from mabdi.sources.depth_folder import is_depth_folder
from mabdi.sources.kitti import is_kitti
from mabdi.sources.scan_folder import is_scan_folder
from mabdi.sources.redwood import is_redwood
from mabdi.sources.replica import is_replica
from mabdi.sources.scannet import is_scannet
from mabdi.sources.stray import is_stray
from mabdi.sources.sequence_files import (  # re-exported: the helpers every format shares live there
    CAMERA_KEYS,
    METADATA_FILE,
    SequenceError,
    bad_quaternions,
    camera_table,
    frame_timestamps,
    interpolate_poses,
    intrinsics_with,
    metadata_path,
    metadata_toml,
    nearest_within,
    poses_from_translations_quaternions,
    prepare_folder,
    read_colour_image,
    read_sequence_metadata,
    write_colour_png,
    write_metadata,
)
from mabdi.sources.threedmatch import is_3dmatch

__all__ = [
    "CAMERA_KEYS",
    "FORMATS",
    "METADATA_FILE",
    "READER_OPTIONS",
    "SequenceError",
    "bad_quaternions",
    "camera_table",
    "frame_timestamps",
    "interpolate_poses",
    "intrinsics_with",
    "metadata_path",
    "metadata_toml",
    "nearest_within",
    "open_sequence",
    "poses_from_translations_quaternions",
    "prepare_folder",
    "quaternions_from_rotations",
    "read_colour_image",
    "read_sequence_metadata",
    "sequence_format",
    "write_colour_png",
    "write_metadata",
]

# ---------------------------------------------------------------------------
# Format detection


#: The formats :func:`open_sequence` reads: name -> (description, module, reader class).
FORMATS = {
    "tum": ("TUM RGB-D folder", "mabdi.sources.tum", "TumSequence"),
    "rosbag2": ("ROS 2 bag", "mabdi.sources.rosbag2", "Rosbag2Sequence"),
    "rosbag1": ("ROS 1 bag", "mabdi.sources.rosbag2", "Rosbag2Sequence"),
    "3dmatch": ("3DMatch / 7-Scenes folder", "mabdi.sources.threedmatch", "ThreeDMatchSequence"),
    "redwood": ("Redwood / Open3D folder", "mabdi.sources.redwood", "RedwoodSequence"),
    "scannet": ("ScanNet folder", "mabdi.sources.scannet", "ScanNetSequence"),
    "replica": ("Replica (NICE-SLAM) folder", "mabdi.sources.replica", "ReplicaSequence"),
    "stray": ("Stray Scanner folder", "mabdi.sources.stray", "StraySequence"),
    "kitti": ("KITTI-style LiDAR folder", "mabdi.sources.kitti", "KittiSequence"),
    "depth_folder": ("depth image folder", "mabdi.sources.depth_folder", "DepthFolderSequence"),
    "scans": ("LiDAR scan folder", "mabdi.sources.scan_folder", "ScanFolderSequence"),
}

#: The keyword options each format's reader takes (``open_sequence(path, **options)``; the CLI refuses the others).
READER_OPTIONS = {
    "tum": ("camera", "tolerance", "depth_scale", "time_offset"),
    "rosbag2": ("depth_topic", "info_topic", "pose_topic", "tolerance", "colour_topic", "cloud_topic", "time_offset"),
    "rosbag1": ("depth_topic", "info_topic", "pose_topic", "tolerance", "colour_topic", "cloud_topic", "time_offset"),
    "3dmatch": ("camera", "depth_scale"),
    "redwood": ("camera", "depth_scale"),
    "scannet": ("camera", "depth_scale"),
    "replica": ("camera", "depth_scale"),
    "stray": ("camera", "depth_scale", "min_confidence"),
    "kitti": (),
    "scans": (),
    "depth_folder": ("camera", "depth_scale"),
}

_WHAT_IS_READ = (
    "a TUM RGB-D folder (depth.txt), a ROS 2 bag (metadata.yaml, .db3 or .mcap), a ROS 1 bag (.bag), a 3DMatch / 7-Scenes folder "
    "(frame-*.depth.png, or seq-* folders of them), a Redwood / Open3D folder (depth/ and trajectory.log), "
    "a ScanNet folder (depth/ and pose/), a Replica NICE-SLAM folder (results/ and traj.txt), "
    "a Stray Scanner folder (depth/ and odometry.csv), "
    "a KITTI-style LiDAR folder (velodyne/ and poses.txt), "
    "a folder of LiDAR scans (.pcd or .bin, here or in a folder below) with their poses (poses/, or a file named *pose*.txt or .csv) "
    "or a folder of depth images (depth/) beside one pose file (*pose* or *traj*, .txt or .csv)"
)


#: What shows each format in a folder, for messages.
_CLUES = {
    "tum": "depth.txt",
    "rosbag2": "metadata.yaml, .db3 or .mcap",
    "rosbag1": ".bag",
    "kitti": "velodyne/ and poses.txt",
    "replica": "results/ and traj.txt",
    "scannet": "depth/ and pose/",
    "stray": "depth/ and odometry.csv",
    "redwood": "depth/ and a .log",
    "3dmatch": "frame-*.depth.png",
    "scans": ".pcd or .bin scans and their poses",
    "depth_folder": "depth/ and a pose file",
}


def _formats_in(folder: Path) -> list[str]:
    """Every format whose files the folder holds, in the order :func:`sequence_format` tries them."""
    found = []
    if (folder / "depth.txt").is_file():
        found.append("tum")
    if (folder / "metadata.yaml").is_file() or any(folder.glob("*.db3")) or any(folder.glob("*.mcap")):
        found.append("rosbag2")
    for name, test in (("kitti", is_kitti), ("replica", is_replica), ("scannet", is_scannet), ("stray", is_stray), ("redwood", is_redwood), ("3dmatch", is_3dmatch), ("depth_folder", is_depth_folder), ("scans", is_scan_folder)):
        if test(folder):
            found.append(name)
    return found


def _named_format(folder: Path) -> str | None:
    """The format a ``[sequence]`` table of the folder's ``mabdi.toml`` names (``format = "..."``), or None."""
    table = read_sequence_metadata(folder).get("sequence")
    if table is None:
        return None
    file = metadata_path(folder)
    if not isinstance(table, dict):
        raise SequenceError(f"{file}: 'sequence' must be a table")
    for key in table:
        if key != "format":
            raise SequenceError(f"{file}: unknown key 'sequence.{key}' (known: format)")
    name = table.get("format")
    if name is None:
        return None
    if name not in FORMATS:
        raise SequenceError(f"{file}: 'sequence.format' is {name!r}; known formats: {', '.join(FORMATS)}")
    return name


def _choose_format(path: Path) -> tuple[str, list[str]]:
    """The format of the sequence at ``path`` and the others whose files it also holds (none when the
    ``mabdi.toml`` names the format)."""
    if not path.exists():
        raise SequenceError(f"recorded sequence {path} does not exist")
    if path.is_file():
        if path.suffix in (".db3", ".mcap"):
            return "rosbag2", []
        if path.suffix == ".bag":
            return "rosbag1", []
        raise SequenceError(f"{path}: not a recorded sequence (expected {_WHAT_IS_READ})")
    named = _named_format(path)
    if named is not None:
        return named, []
    found = _formats_in(path)
    if not found:
        raise SequenceError(f"{path}: not a recorded sequence: expected {_WHAT_IS_READ}")
    return found[0], found[1:]


def sequence_format(path) -> str:
    """The name in :data:`FORMATS` of the sequence at ``path``, or a :class:`SequenceError` saying what was found.

    A folder's ``mabdi.toml`` may name it (``[sequence]`` ``format = "..."``);
    else the first format whose files the folder holds, in the module docs' order.
    """
    return _choose_format(Path(path))[0]


def open_sequence(path, **options):
    """Open a recorded depth sequence as a :class:`~mabdi.sources.frames.FrameSource`, whatever its format.

    :func:`sequence_format` tells the formats apart (:data:`FORMATS`), with a
    warning when a folder holds the files of another format too;
    ``options`` go to that reader (``camera=``, ``depth_scale=``,
    ``tolerance=``, ``time_offset=`` (seconds) for TUM; ``camera=``, ``depth_scale=`` for the dataset
    layouts; ``depth_topic=``, ``pose_topic=``, ``cloud_topic=``, ... for bags).
    """
    path = Path(path)
    kind, others = _choose_format(path)
    if others:
        also = "; ".join(f"a {FORMATS[other][0]} ({_CLUES[other]})" for other in others)
        warnings.warn(
            f"{path}: read as a {FORMATS[kind][0]} ({_CLUES[kind]}), but it also holds {also}; to read it as "
            f'the {FORMATS[others[0]][0]}, put [sequence] format = "{others[0]}" in {metadata_path(path)} '
            f"(the formats: {', '.join(FORMATS)})",
            UserWarning,
            stacklevel=2,
        )
    _, module, name = FORMATS[kind]
    reader = getattr(importlib.import_module(module), name)
    if kind == "rosbag2" and path.is_dir() and not (path / "metadata.yaml").is_file():
        files = sorted(path.glob("*.db3")) + sorted(path.glob("*.mcap"))
        if len(files) != 1:
            raise SequenceError(
                f"{path}: no metadata.yaml and {len(files)} storage files ({', '.join(f.name for f in files)}): "
                "open one of them, or restore metadata.yaml"
            )
        path = files[0]
    recording = reader(path, **options)
    recording.loses_returns = True  # a real sensor's, or of unknown origin: a pixel without a return is not free space
    return recording
