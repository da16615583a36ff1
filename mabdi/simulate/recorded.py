"""Recorded sequences in the loop: record a simulated run, and run the loop on a recording.

``record(config, out, format)`` writes the simulated rig's frames as a TUM
RGB-D folder (:mod:`mabdi.sources.tum`) or a ROS 2 bag
(:mod:`mabdi.sources.rosbag2`), with a ``[recorded]`` table in the
recording's ``mabdi.toml`` that names the scene it came from (the digest of
the config's ``[scene]`` and frame count, :func:`scene_digest`). The
recording's poses are the rig's given poses (with the config's
``[sensor.pose_noise]``, as a robot gives them); the true poses go beside
them, in ``poses_true.npy`` (:data:`TRUE_POSES`) in the recording's folder,
so the pose error can be scored.

``recorded_simulation(config, path)`` opens a recording and builds a
:class:`~mabdi.simulate.runner.Simulation` over it with the config's
classifier, surface and output settings. The ground truth for the
evaluation is the config's scene when the recording says it came from that
very scene (same digest); otherwise the evaluation is skipped, with a note
saying why. When the recording has ``poses_true.npy``, the evaluation judges
what the sensor saw from those (``Simulation.true_poses``).
"""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np

from mabdi.config import RunConfig, SceneConfig, dump_toml
from mabdi.io.atomic import atomic_output
from mabdi.io.run_folder import OutputError
from mabdi.simulate.rig import SimulatedRig
from mabdi.simulate.runner import Simulation
from mabdi.sources.scene import SourceScene

FORMATS = ("tum", "rosbag2")
#: The true poses of a recording made by :func:`record`, (N, 4, 4), in the recording's folder.
TRUE_POSES = "poses_true.npy"
#: The reader options each format takes (the others are an error when given).
READER_OPTIONS = {
    "tum": ("camera", "tolerance", "depth_scale"),
    "rosbag2": ("depth_topic", "info_topic", "pose_topic", "tolerance", "colour_topic"),
    "3dmatch": ("camera", "depth_scale"),
    "redwood": ("camera", "depth_scale"),
    "scannet": ("camera", "depth_scale"),
    "replica": ("camera", "depth_scale"),
}


def scene_digest(scene: SceneConfig, frames: int) -> str:
    """SHA-256 of a scene's resolved TOML and the run length its schedules are resolved against."""
    text = dump_toml(scene) + f"frames = {int(frames)}\n"
    return hashlib.sha256(text.encode()).hexdigest()


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
        else:
            from mabdi.sources.rosbag2 import write_rosbag2

            write_rosbag2(rig, out, storage=storage, encoding=encoding, extra=extra)
        with atomic_output(Path(out) / TRUE_POSES) as temporary:
            np.save(temporary, rig.true_poses)
    finally:
        rig.close()
    return Path(out)


def recorded_simulation(config: RunConfig, path, **options) -> tuple[Simulation, str | None]:
    """A Simulation over the recording at ``path`` (``options`` go to the reader), and a note when
    the ground truth is unknown (the evaluation is then skipped)."""
    from mabdi.errors import ConfigError
    from mabdi.sources.sequences import FORMATS, metadata_path, open_sequence, read_sequence_metadata, sequence_format

    kind = sequence_format(path)
    wanted = READER_OPTIONS[kind]
    for name, value in options.items():
        if value is not None and name not in wanted:
            flag = "--" + name.replace("_", "-")
            raise ConfigError(f"{path} is a {FORMATS[kind][0]}: {flag} does not apply to it")
    source = open_sequence(path, **{k: v for k, v in options.items() if v is not None and k in wanted})
    recorded = read_sequence_metadata(path).get("recorded", {})
    scene = None
    note = None
    if not config.scene.objects:
        note = f"{path}: no scene in the config, so no ground truth: the evaluation is skipped"
    elif recorded.get("scene_digest") != scene_digest(config.scene, recorded.get("frames", len(source))):
        note = (
            f"{path}: the recording does not say it came from this config's scene "
            "(its mabdi.toml [recorded] scene_digest differs or is absent): the evaluation is skipped"
        )
    else:
        base_dir = config.source.parent if config.source is not None else None
        scene = SourceScene(config.scene, frames=int(recorded["frames"]), base_dir=base_dir)
    simulation = Simulation(config, source=source, scene=scene)
    true_file = metadata_path(path).with_name(TRUE_POSES)  # beside the recording's mabdi.toml
    if scene is not None and true_file.is_file():
        true_poses = np.load(true_file, allow_pickle=False)
        if true_poses.shape == simulation.poses.shape:
            simulation.true_poses = true_poses
    return simulation, note
