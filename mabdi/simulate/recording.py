"""Record a simulated run as the recordings robots make (the loop runs them with :mod:`mabdi.loop.mapping_run`).

``record(config, out, format)`` writes the simulated rig's frames as a TUM
RGB-D folder (:mod:`mabdi.sources.tum`), a ROS 2 bag
(:mod:`mabdi.sources.rosbag2`; a LiDAR's scans as PointCloud2) or, for a
LiDAR, a KITTI-style folder (:mod:`mabdi.sources.kitti`), with a ``[recorded]`` table in the
recording's ``mabdi.toml`` that names the scene it came from (the digest of
the config's ``[scene]`` and frame count, :func:`scene_digest`). The
recording's poses are the rig's given poses (with the config's
``[sensor.pose_noise]``, as a robot gives them); the true poses go beside
them, in ``poses_true.npy`` (:data:`TRUE_POSES`) in the recording's folder,
so the pose error can be scored.

``recorded_simulation(config, path)`` (:func:`mabdi.loop.mapping_run.recorded_simulation`)
opens a recording and builds a :class:`~mabdi.loop.mapping_run.MappingRun`
over it with the config's classifier, surface and output settings. The
ground truth for the evaluation is the config's scene when the recording
says it came from that very scene (same digest); otherwise the evaluation is
skipped, with a note saying why. When the recording has ``poses_true.npy``,
the evaluation judges what the sensor saw from those (``MappingRun.true_poses``).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from mabdi.config import RunConfig, scene_digest
from mabdi.io.atomic import atomic_output
from mabdi.io.run_folder import OutputError
from mabdi.simulate.rig import SimulatedRig

#: The true poses (N, 4, 4, world) beside a recording made by :func:`record` (read back by
#: :func:`mabdi.loop.mapping_run.recorded_simulation`) and in a run's folder, for scoring the pose error.
TRUE_POSES = "poses_true.npy"

#: The formats :func:`record` writes.
FORMATS = ("tum", "rosbag2", "kitti")


def record(config: RunConfig, out, format: str, storage: str = "sqlite3", encoding: str = "32FC1", overwrite: bool = False) -> Path:
    """Write the simulated run of ``config`` as a recording in ``out``; returns the folder written."""
    if format not in FORMATS:
        raise ValueError(f"unknown recording format {format!r} (known: {', '.join(FORMATS)})")
    out = Path(out)
    occupied = any(out.iterdir()) if out.is_dir() else out.exists()
    if occupied:
        from mabdi.sources.sequences import read_sequence_metadata

        if not overwrite:
            raise OutputError(f"{out} exists and is not empty: choose a new folder, or --overwrite to replace a recording")
        if not (out.is_dir() and "recorded" in read_sequence_metadata(out)):
            raise OutputError(f"{out} is not a recording made by mabdi record: it is left as it is; choose a new folder")
        shutil.rmtree(out)
    rig = SimulatedRig.from_config(config)
    extra = {
        "recorded": {
            "name": config.run.name,
            "config": str(config.source) if config.source is not None else "",
            "scene_digest": scene_digest(config.scene, config.run.frames),
            "frames": len(rig),
            "noise": config.sensor.noise,
            "seed": config.run.seed,
        }
    }
    try:
        if format == "tum":
            from mabdi.sources.tum import write_tum

            write_tum(rig, out, extra=extra)
        elif format == "kitti":
            from mabdi.sources.kitti import write_kitti

            write_kitti(rig, out, extra=extra)
        else:
            from mabdi.sources.rosbag2 import write_lidar_rosbag2, write_rosbag2

            if rig.intrinsics.range_image:  # a LiDAR's scans: PointCloud2 (encoding is for images)
                write_lidar_rosbag2(rig, out, storage=storage, extra=extra)
            else:
                write_rosbag2(rig, out, storage=storage, encoding=encoding, extra=extra)
        with atomic_output(Path(out) / TRUE_POSES) as temporary:
            np.save(temporary, rig.true_poses)
    finally:
        rig.close()
    return Path(out)
