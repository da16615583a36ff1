"""Real frames, held out: how well each map predicts depth images it was never given.

A recording has no ground-truth mesh, but each frame is a measurement. Every
K-th frame (``--every``, default 10) is held out and never integrated; each
map is built from the other frames, then ray-cast at every held-out frame's
pose with the recording's camera and compared with that frame's measured
depth (:mod:`mabdi.evaluate.held_out`: share of valid measured pixels within
2 cm and 5 cm, median |error| where both exist, coverage).

Maps, all from the same integrated frames and the same given poses:

* ``mabdi`` (one per ``--surface``): the MABDI loop run as ``mabdi run
  --sequence PATH`` runs a recording with no config (default settings,
  ``sensor.noise = "auto"`` for a depth camera:
  :func:`mabdi.loop.mapping_run.recorded_simulation`), on the integrated frames
  only (:class:`~mabdi.sources.frames.FrameSubset`). It registers each
  frame to its map, so it meshes each frame with a corrected pose; the map is
  scored at the held-out frames' given poses (``held_out``) and also at those
  poses corrected as the run corrected the frames around them
  (``held_out_corrected_pose``, :func:`~mabdi.evaluate.held_out.corrected_poses`:
  no held-out depth is used for it);
* ``tsdf_1cm``, ``tsdf_2cm``: Open3D's VoxelBlockGrid TSDF
  (:mod:`mabdi.evaluate.tsdf`) with :meth:`TsdfSettings.tuned` (truncation 4
  voxels, weight above 0.5, mabdi's cx, cy handed over as they are: Open3D's
  VoxelBlockGrid reads pixel ``int(u)`` for a continuous u, mabdi's
  convention), integrated at the given poses on the raw depth: on real frames
  the depth smoothed by the noise model the first mabdi run learnt (as mabdi's
  surfaces smooth it; ``--tsdf-smooth``) scored no better and took four times
  as long (docs/benchmarks.md), so the peer at its best runs without it.
  Skipped with a note when Open3D cannot be imported.

Also per map: triangles; for mabdi the faces removal deleted (the run's
records), the meshed poses against the given ones, and its second layer: the
share of its area within 1 cm (along the face's normal) of a face another
frame made (:func:`mabdi.evaluate.redundancy.redundancy`, ``LAYER_SAMPLES``
area-weighted samples); time per frame of
every method, measured in this one run (mabdi: everything after reading the
frame, ``t_total_ms - t_depth_ms`` of the records; TSDF: the integration,
its depth smoothing included where asked; reading a frame is not counted for either).

    .venv/bin/python benchmarks/bench_real.py PATH [--every 10] [--frames N] [--surface quadtree ...]
        [--no-registration] [--jitter M DEG] [--voxels 0.01 0.02] [--camera ...] [--depth-scale ...] [--min-confidence 0|1|2] [--out results.json]

``--jitter M DEG`` gives every map the integrated frames' poses jittered (N(0, M) metres and N(0, DEG)
degrees per axis, seeded; :class:`JitteredFrames`), as a poorer tracker would; the held-out frames are still
scored at the recording's poses. ``--no-registration`` runs mabdi as ``mabdi run --no-registration`` does
(every frame meshed at its given pose, as the TSDF is); ``--voxels`` with no
value runs no TSDF.

PATH is any recording :func:`mabdi.sources.sequences.open_sequence` reads
(TUM, ROS 2 bag, 3DMatch / 7-Scenes, Redwood, ScanNet, Replica). Prints a
markdown table; ``--out`` writes every number as JSON (atomically).
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from scipy.spatial.transform import Rotation

from mabdi.camera import Intrinsics
from mabdi.config import RunConfig, settings_overrides, with_overrides
from mabdi.evaluate.bench import machine_info
from mabdi.evaluate.held_out import THRESHOLDS, corrected_poses, held_out_split, pose_differences, score_map
from mabdi.evaluate.redundancy import redundancy
from mabdi.evaluate.sampling import sample_surface
from mabdi.evaluate.tsdf import TsdfSettings, open3d_status, run_tsdf
from mabdi.io.atomic import write_text
from mabdi.loop.mapping_run import RECORDING_NOISE, MappingRun, RecordedFrames, depth_range_stated
from mabdi.sources.depth_range import learn_depth_range
from mabdi.sources.frames import FrameSubset
from mabdi.sources.sequences import open_sequence
from mabdi.stages.time_offset import AUTO, learn_time_offset


def log(message: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


def held_out_frames(source, held):
    """The held-out frames, read one at a time (a generator: none is kept)."""
    for index in held:
        yield source.read(int(index))


class PosedFrames:
    """The held-out frames with other poses (the same depth and camera)."""

    def __init__(self, source, held, poses) -> None:
        self.source, self.held, self.poses = source, held, poses

    def __iter__(self):
        for index, pose in zip(self.held, self.poses):
            frame = self.source.read(int(index))
            frame.world_from_camera = pose
            yield frame


class PosedSubset(FrameSubset):
    """The integrated frames with other poses (one 4x4 world_from_camera per frame of the subset)."""

    def __init__(self, source, indices, poses: np.ndarray, description: str) -> None:
        super().__init__(source, indices)
        self.other_poses = np.asarray(poses, dtype=np.float64).copy()
        self.description = f"{self.description}, {description}"

    def read_frame(self, index: int):
        frame = super().read_frame(index)
        frame.world_from_camera = self.other_poses[index].copy()
        return frame

    @property
    def poses(self) -> np.ndarray:
        return self.other_poses.copy()


class JitteredFrames(PosedSubset):
    """The integrated frames with their given poses jittered: per frame, a translation of N(0, ``metres``) per
    axis and a turn about the camera centre of N(0, ``degrees``) per axis (seeded), as a poorer tracker would
    give them. The held-out frames keep the recording's poses (they are scored there)."""

    def __init__(self, source, indices, metres: float, degrees: float, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        poses = source.poses[np.asarray(indices)].copy()
        for pose in poses:
            turn = Rotation.from_rotvec(np.radians(rng.normal(0.0, degrees, 3))).as_matrix()
            pose[:3, :3] = turn @ pose[:3, :3]
            pose[:3, 3] += rng.normal(0.0, metres, 3)
        super().__init__(source, indices, poses, f"poses jittered by {metres * 1000:g} mm / {degrees:g} deg per axis")


def scored(mesh, frames) -> dict:
    pooled, per_frame = score_map(mesh, frames)
    out = pooled.as_dict()
    out["per_frame_within_2cm"] = [s.within[THRESHOLDS[0]] for s in per_frame]
    return out


#: Area-weighted samples of a mabdi map for its second layer (the share's standard error: about 0.4 points).
LAYER_SAMPLES = 20_000


def run_mabdi(source, subset, integrated, held, surface: str, registration: bool = True, settings=()) -> tuple[dict, object]:
    config = RunConfig()
    overrides = {"surface.method": surface}
    if not registration:
        overrides["registration.enabled"] = False  # as mabdi run --no-registration: frames meshed at their given poses
    if isinstance(source.intrinsics, Intrinsics):  # a depth camera's recording with no noise model stated
        overrides["sensor.noise"] = RECORDING_NOISE
    overrides.update(settings_overrides(settings, where="--set"))  # last: the user's word
    config = with_overrides(config, overrides, where="bench_real")
    simulation = MappingRun(config, source=subset)
    name = f"mabdi ({surface})" if registration else f"mabdi ({surface}, no registration)"
    if settings:
        name += " " + " ".join(f"--set {s}" for s in settings)
    log(f"{name}: running {len(subset)} frames")
    result = simulation.run()
    records = result.records
    after_read = np.array([r.t_total_ms - r.t_depth_ms for r in records])
    removed = int(sum(r.cells_removed for r in records))
    mesh = result.mesh
    triangles = int(mesh.GetNumberOfCells())
    meshed = simulation.meshed_poses()
    given_all = source.poses
    statuses = {}
    for r in records:
        statuses[r.registration] = statuses.get(r.registration, 0) + 1
    log(f"{name}: {triangles:,} triangles, {after_read.mean():.0f} ms a frame; scoring {len(held)} held-out frames")
    row = {
        "method": name,
        "registration_enabled": registration,
        "surface": surface,
        "triangles": triangles,
        "ms_per_frame": float(after_read.mean()),
        "ms_per_frame_median": float(np.median(after_read)),
        "stage_ms": {
            stage: float(np.mean([getattr(r, stage) for r in records]))
            for stage in ("t_depth_ms", "t_register_ms", "t_expected_ms", "t_classify_ms", "t_surface_ms", "t_append_ms", "t_refine_ms", "t_remove_ms", "t_total_ms")
        },
        "seconds": float(result.seconds),
        "faces_removed": removed,
        "faces_removed_share": removed / (triangles + removed) if triangles + removed else 0.0,
        "meshed_poses_vs_given": pose_differences(subset.poses, meshed),
        "meshed_poses_vs_recording": pose_differences(source.poses[integrated], meshed),
        "registration": statuses,
        "poor_fit": sum(r.poor_fit for r in records),
        "noise": config.sensor.noise,
        "noise_calibration": result.noise_calibration,
        "held_out": scored(mesh, held_out_frames(source, held)),
        "second_layer_1cm": redundancy(mesh, sample_surface(mesh, LAYER_SAMPLES), 0.01) if triangles else None,
    }
    corrected = corrected_poses(given_all, integrated, meshed, held)
    row["held_out_pose_correction"] = pose_differences(given_all[held], corrected)
    if registration:  # without it every frame is meshed at its given pose: nothing to correct
        row["held_out_corrected_pose"] = scored(mesh, PosedFrames(source, held, corrected))
    return row, simulation


def run_tsdf_row(source, subset, held, voxel: float, noise, smooth: bool = False, name: str = "", held_frames=None) -> dict:
    """The TSDF at ``voxel`` (m) integrated on ``subset`` and scored on the held-out frames (``held_frames``: an
    iterable of them at other poses; None: at the recording's)."""
    settings = TsdfSettings.tuned(voxel, noisy=smooth and noise is not None and noise.noisy)
    log(f"tsdf {voxel * 100:g} cm{name}: integrating {len(subset)} frames ({settings.as_dict()})")
    run = run_tsdf(subset, settings, mesh_every=None, noise=noise)
    triangles = int(run.mesh.GetNumberOfCells())
    log(f"tsdf {voxel * 100:g} cm: {triangles:,} triangles, {np.mean(run.t_integrate_ms):.0f} ms a frame; scoring")
    return {
        "method": f"tsdf_{voxel * 100:g}cm{name}",
        "settings": settings.as_dict(),
        "triangles": triangles,
        "ms_per_frame": float(np.mean(run.t_integrate_ms)),
        "ms_per_frame_median": float(np.median(run.t_integrate_ms)),
        "extract_ms": float(run.t_final_extract_ms.get(settings.weight_threshold, float("nan"))),
        "seconds": float(run.seconds),
        "volume_bytes": int(run.volume_bytes),
        "held_out": scored(run.mesh, held_out_frames(source, held) if held_frames is None else held_frames),
    }


def percent(x) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100.0 * x:.1f}%"


def markdown(bench: dict) -> str:
    lines = [
        f"{bench['frames']} frames of {bench['source']}: {bench['integrated']} integrated, {bench['held_out']} held out (every {bench['every']}th)",
        "",
        "| map | within 2 cm | within 5 cm | median abs error (mm) | coverage | triangles | ms / frame |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]

    def line(name, score, row):
        lines.append(
            f"| {name} | {percent(score['within_2cm'])} | {percent(score['within_5cm'])} | {score['median_abs_error_mm']:.1f} "
            f"| {percent(score['coverage'])} | {row['triangles']:,} | {row['ms_per_frame']:.0f} |"
        )

    for row in bench["methods"]:
        line(row["method"], row["held_out"], row)
        if "held_out_corrected_pose" in row:
            line(row["method"] + ", held-out poses corrected as the run's", row["held_out_corrected_pose"], row)
    for row in bench["methods"]:
        if "meshed_poses_vs_given" in row:
            d, c = row["meshed_poses_vs_given"], row["held_out_pose_correction"]
            lines += [
                "",
                f"- {row['method']}: meshed poses against the given ones: translation median {d['translation_mm_median']:.0f} mm "
                f"(max {d['translation_mm_max']:.0f}), rotation median {d['rotation_deg_median']:.2f} deg (max {d['rotation_deg_max']:.2f}); "
                f"held-out poses corrected by median {c['translation_mm_median']:.0f} mm / {c['rotation_deg_median']:.2f} deg; "
                f"faces removed {row['faces_removed']:,} ({percent(row['faces_removed_share'])} of the faces made); "
                f"area within 1 cm of another frame's face {percent(row.get('second_layer_1cm'))}; "
                f"registration {row['registration']}, {row.get('poor_fit', 0)} fitting the map poorly (no removal votes)",
            ]
            r = row.get("meshed_poses_vs_recording")
            if r is not None and r != d:  # the given poses were jittered: the meshed ones against the recording's
                lines[-1] += (
                    f"; against the recording's poses: translation median {r['translation_mm_median']:.1f} mm "
                    f"(max {r['translation_mm_max']:.0f}), rotation median {r['rotation_deg_median']:.2f} deg"
                )
    for note in bench["notes"]:
        lines.append(f"- {note}")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequence", type=Path, help="a recording in a layout mabdi reads (mabdi run --sequence PATH)")
    parser.add_argument("--every", type=int, default=10, help="hold out every K-th frame (default 10)")
    parser.add_argument("--frames", type=int, help="take the first N frames of the recording (default: all)")
    parser.add_argument("--surface", nargs="+", default=["quadtree"], help="mabdi surface filter(s) (default quadtree)")
    parser.add_argument(
        "--no-registration", action="store_true", help="mabdi meshes every frame at its given pose (as mabdi run --no-registration)"
    )
    parser.add_argument("--voxels", type=float, nargs="*", default=[0.01, 0.02], help="TSDF voxel sizes in metres (none: no TSDF)")
    parser.add_argument(
        "--tsdf-smooth", action="store_true",
        help="smooth the TSDF's depth by the noise model mabdi's run learnt (default: the raw depth, the TSDF's best on real frames)",
    )  # fmt: skip
    parser.add_argument("--camera", help="the camera, when the recording has none (as mabdi run --camera)")
    parser.add_argument(
        "--time-offset", default=AUTO,
        help="TUM: seconds from a depth timestamp to its pose, or auto (learnt, as mabdi run does; the default)",
    )
    parser.add_argument("--depth-scale", type=float, help="depth units per metre (as mabdi run --depth-scale)")
    parser.add_argument("--min-confidence", type=int, choices=(0, 1, 2), help="Stray Scanner: as mabdi run --min-confidence")
    parser.add_argument(
        "--jitter", type=float, nargs=2, metavar=("M", "DEG"),
        help="jitter the integrated frames' poses by N(0, M) metres and N(0, DEG) degrees per axis (seeded) for every map",
    )  # fmt: skip
    parser.add_argument(
        "--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
        help="set a config value of mabdi's runs by its dotted key, as mabdi run --set (repeatable)",
    )  # fmt: skip
    parser.add_argument(
        "--tsdf-at-run-poses", action="store_true",
        help="also integrate each TSDF at the first mabdi run's meshed poses and score it at the held-out poses corrected as "
        "that run's: whether the run's poses or the recording's make the more consistent map, by the TSDF's own measure",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, help="write every number here as JSON")
    args = parser.parse_args(argv)

    options = {k: v for k, v in (("camera", args.camera), ("depth_scale", args.depth_scale), ("min_confidence", args.min_confidence)) if v is not None}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        source = open_sequence(args.sequence, **options)
    # the recording's folder by its name only (the numbers go into documents; where it lies here does not)
    where = str(args.sequence)
    notes = [str(w.message).replace(where, args.sequence.name) for w in caught]
    for note in notes:
        log(f"note: {note}")
    frames = len(source) if args.frames is None else min(args.frames, len(source))
    integrated, held = held_out_split(frames, args.every)
    if args.time_offset == AUTO and getattr(source, "pose_samples", None) is not None:
        # as mabdi run does, learnt from the integrated frames only; every map then has the same poses
        found = learn_time_offset(
            lambda i: source.read(int(integrated[i])).depth, source.timestamps[integrated], *source.pose_samples,
            source.intrinsics,
        )
        if found is not None:
            log(f"note: {found.note()}")
            if found.applied:
                source = source.with_time_offset(found.seconds)
    elif args.time_offset not in (None, AUTO):
        source = source.with_time_offset(float(args.time_offset))
    frames = min(frames, len(source))  # poses taken at other times may leave a frame at either end without one
    if isinstance(source.intrinsics, Intrinsics) and not depth_range_stated(args.sequence, args.camera):
        # as mabdi run does: near and far from the frames where the recording states none
        depth_range = learn_depth_range(source, frames)
        if depth_range is not None:
            log(f"note: {depth_range.note()}")
            source = RecordedFrames(source, frames, path=args.sequence, depth_range=depth_range)
    integrated, held = held_out_split(frames, args.every)
    subset = FrameSubset(source, integrated) if args.jitter is None else JitteredFrames(source, integrated, *args.jitter)
    log(f"{source.description}: {frames} frames, {len(integrated)} integrated, {len(held)} held out")

    rows = []
    noise = None
    run_poses = None  # the first run's meshed poses (world) and the held-out poses corrected as its
    for surface in args.surface:
        row, simulation = run_mabdi(source, subset, integrated, held, surface, registration=not args.no_registration, settings=args.settings)
        rows.append(row)
        if noise is None:
            noise = simulation.loop.noise  # the curve this run learnt, for the TSDF's smoothing
            meshed = simulation.meshed_poses()
            run_poses = (meshed, corrected_poses(source.poses, integrated, meshed, held))
        simulation.loop.close()
    if args.voxels:
        usable, reason = open3d_status()
        if not usable:
            notes.append(f"TSDF skipped: {reason}")
        else:
            for voxel in args.voxels:
                rows.append(run_tsdf_row(source, subset, held, voxel, noise, smooth=args.tsdf_smooth))
                if args.tsdf_at_run_poses and run_poses is not None:
                    meshed, corrected = run_poses
                    at_run = PosedSubset(source, integrated, meshed, "at the first mabdi run's meshed poses")
                    rows.append(run_tsdf_row(
                        source, at_run, held, voxel, noise, smooth=args.tsdf_smooth, name=" at the run's poses",
                        held_frames=PosedFrames(source, held, corrected),
                    ))  # fmt: skip
    bench = {
        "source": source.description.replace(where, args.sequence.name),
        "sequence": args.sequence.name,
        "frames": frames,
        "every": args.every,
        "integrated": int(len(integrated)),
        "held_out": int(len(held)),
        "held_out_frames": held.tolist(),
        "intrinsics": {k: getattr(source.intrinsics, k) for k in ("fx", "fy", "cx", "cy", "width", "height", "near", "far")},
        "thresholds_m": list(THRESHOLDS),
        "command": "benchmarks/bench_real.py "
        + " ".join(shlex.quote(a.replace(where, args.sequence.name)) for a in (argv if argv is not None else sys.argv[1:])),
        "machine": machine_info(),
        "methods": rows,
        "notes": notes,
    }
    text = markdown(bench)
    print(text)
    if args.out is not None:
        write_text(args.out, json.dumps(bench, indent=2, default=float) + "\n")
        log(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
