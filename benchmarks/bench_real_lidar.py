"""Real LiDAR scans, held out: how close each map lies to scans it was never given, and how much of it they confirm.

A LiDAR recording has no ground-truth mesh, but each scan is a measurement.
Every K-th scan (``--every``, default 5) of a KITTI-layout folder
(:mod:`mabdi.sources.kitti`) or a folder of LiDAR scans beside their poses
(:mod:`mabdi.sources.scan_folder`) is held out and never integrated; each map is
built from the other scans, then compared with the held-out scans' points
(:mod:`mabdi.evaluate.held_out_scans`): the points of the scan files as
they are (not the range images), moved to the world by the given poses as
the reader has them (turned where their axes were told, :mod:`mabdi.sources.pose_axes`), keeping the returns within the range limits of the geometry the run
used (``range_min < r < range_max``):

* recall at 5 cm and 10 cm: the share of the held-out points within that
  distance of the map (point to nearest triangle);
* precision at 10 cm: the share of the map's area (one sample per 25 cm^2,
  at most 3 million) within 10 cm of a held-out point, counting only the
  samples some held-out scan could see: within its range limits and the
  vertical field of view of the run's geometry, and not hidden behind the
  map's own triangles (the ray from that scan's sensor meets nothing more
  than 3 cm before the sample);
* F at 10 cm: the harmonic mean of the two;
* supported: the share of the seen area that misses precision but lies
  within 10 cm of an integrated scan's return: surface the map was given
  returns for, where the held-out scans' rings lie too far apart to say.

Maps, all from the same integrated scans and the same given poses:

* ``mabdi`` (one per ``--surface``, default pixel_grid, quadtree and
  voxel_planes): the MABDI loop run as ``mabdi run --sequence PATH`` runs a
  recording with no config (default settings; the noise model a LiDAR
  recording that states none gets, ``range`` at 0.02 m; the geometry as the
  reader has it: the folder's ``[lidar]`` table, else learnt from the first
  scans; ``--set KEY=VALUE`` changes any setting, as ``mabdi run --set``), on
  the integrated scans only (:class:`~mabdi.sources.frames.FrameSubset`);
  it fits each scan to its map (:mod:`mabdi.stages.scan_registration`), so it
  may mesh a scan at a corrected pose: the map is scored at the held-out
  scans' given poses (``score``) and, where the run moved any pose, also at
  those poses corrected as the run corrected the scans around them
  (``score_corrected_pose``, :func:`~mabdi.evaluate.held_out.corrected_poses`:
  no held-out scan is used for it);
* ``poisson``: Open3D's screened Poisson reconstruction of the integrated
  scans' points (as PUMA meshes LiDAR scans): each scan's returns (same range
  limits) get normals from their neighbours (hybrid search: radius 3 voxels,
  at most 30 neighbours) turned towards that scan's sensor, all scans are
  gathered in the world frame, voxel-downsampled (5 cm; normals averaged and
  renormalised; a voxel whose normals cancel out is dropped), reconstructed
  at an octree depth (scale 1.1, no linear fit), and the vertices whose
  density is below a quantile (the trim) are dropped with their triangles.
  Default depth 12, trim 30% (its best on the recording docs/benchmarks.md
  measures); ``--tune`` runs every depth of ``--depths`` (default 10, 11,
  12) by every trim of ``--trims`` (default 5%, 10%, 20%, 30%, 40%),
  scores each the same way, and reports the one with the best F at 10 cm
  (chosen on these held-out scans: the peer at its best). Needs Open3D, as
  the scoring does.

Also per map: triangles; for mabdi the faces removal deleted (the run's
records, ``cells_removed``: as a count and as a share of the final map's
triangles) and the meshed poses against the given ones; time per scan,
measured in this one run (mabdi: everything after reading the scan,
``t_total_ms - t_depth_ms`` of the records; Poisson: normals, gathering,
downsampling, reconstruction and trim, divided by the integrated scans;
reading the files is not counted for either).

    .venv/bin/python benchmarks/bench_real_lidar.py PATH [--every 5] [--frames N]
        [--surface pixel_grid quadtree voxel_planes] [--tune [--depths 10 11 12] [--trims 0.05 0.10 0.20 0.30 0.40]]
        [--no-poisson] [--out results.json]

``--surface`` with no value runs no mabdi map (the peer alone).

Prints a markdown table; ``--out`` writes every number as JSON (atomically).
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from mabdi.config import RunConfig, settings_overrides, with_overrides
from mabdi.errors import ConfigError
from mabdi.evaluate.bench import machine_info
from mabdi.evaluate.held_out import corrected_poses, held_out_split, pose_differences
from mabdi.evaluate.held_out_scans import (
    MAX_SAMPLES,
    PRECISION_THRESHOLD_M,
    RECALL_THRESHOLDS_M,
    SAMPLE_AREA_M2,
    SEEN_TOLERANCE_M,
    HeldOutScans,
    scan_in_world,
    score_map,
)
from mabdi.evaluate.tsdf import open3d_status
from mabdi.io.atomic import write_text
from mabdi.loop.mapping_run import RECORDING_LIDAR_NOISE, MappingRun
from mabdi.polydata import triangles_polydata
from mabdi.sources.frames import FrameSubset
from mabdi.sources.kitti import KittiSequence, read_scan
from mabdi.sources.sequences import SequenceError, open_sequence
from mabdi.spherical import SphericalGeometry

SURFACES = ("pixel_grid", "quadtree", "voxel_planes")
#: The loop's stage times (ms) averaged into each mabdi row.
STAGES = (
    "t_depth_ms", "t_register_ms", "t_expected_ms", "t_classify_ms", "t_surface_ms", "t_append_ms", "t_refine_ms",
    "t_remove_ms", "t_total_ms",
)
#: The Poisson peer's voxel (m), the normals' search radius (in voxels) and most neighbours.
POISSON_VOXEL = 0.05
NORMAL_RADIUS_VOXELS = 3.0
NORMAL_NEIGHBOURS = 30
#: Default octree depth and density trim (quantile) of the peer: its best on the Ouster-class recording of
#: docs/benchmarks.md ("Real LiDAR scans, held out"); the grid ``--tune`` runs to find it on other scans.
POISSON_DEPTH = 12
POISSON_TRIM = 0.30
TUNE_DEPTHS = (10, 11, 12)
TUNE_TRIMS = (0.05, 0.10, 0.20, 0.30, 0.40)


def log(message: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


def git_state() -> dict:
    """The commit the numbers were measured at and the tracked files changed since (empty outside a git checkout)."""
    root = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10)
        status = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=root, capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.SubprocessError):
        return {}
    if head.returncode or status.returncode:
        return {}
    return {"head": head.stdout.strip(), "uncommitted": [line[3:] for line in status.stdout.splitlines() if line.strip()]}


def scored(mesh, held: HeldOutScans, integrated=None) -> tuple[dict, float]:
    """The map's score (``integrated``: the integrated scans' world points, for its ``supported`` share)."""
    start = time.perf_counter()
    score = score_map(mesh, held, integrated_points=integrated).as_dict()
    return score, time.perf_counter() - start


def run_mabdi(subset, held: HeldOutScans, surface: str, overrides: dict | None = None, replace_held=None, integrated=None) -> dict:
    """One mabdi map of ``subset`` scored on ``held``; ``replace_held(meshed)``: the held-out scans at the poses
    the run's corrections give them (:func:`~mabdi.evaluate.held_out.corrected_poses`), scored too where the run
    moved any pose."""
    # the settings mabdi run --sequence gives a LiDAR recording that states no noise model, then --set's
    stated = {"surface.method": surface, "sensor.kind": "lidar", "sensor.noise": RECORDING_LIDAR_NOISE, **(overrides or {})}
    config = with_overrides(RunConfig(), stated, where="bench_real_lidar")
    simulation = MappingRun(config, source=subset)
    name = f"mabdi ({surface})"
    log(f"{name}: running {len(subset)} scans")
    result = simulation.run()
    records = result.records
    after_read = np.array([r.t_total_ms - r.t_depth_ms for r in records])
    removed = int(sum(r.cells_removed for r in records))
    mesh = result.mesh
    triangles = int(mesh.GetNumberOfCells())
    statuses = {}
    for r in records:
        statuses[r.registration] = statuses.get(r.registration, 0) + 1
    meshed = simulation.meshed_poses()
    simulation.loop.close()
    log(f"{name}: {triangles:,} triangles, {after_read.mean():.0f} ms a scan ({result.seconds:.0f} s); scoring")
    score, seconds = scored(mesh, held, integrated)
    log(f"{name}: scored in {seconds:.0f} s: F@10cm {score['fscore']:.3f}")
    corrected = None
    if replace_held is not None and not np.allclose(meshed, subset.poses, rtol=0.0, atol=1e-9):
        corrected, _ = scored(mesh, replace_held(meshed))
        log(f"{name}: at the corrected held-out poses: F@10cm {corrected['fscore']:.3f}")
    return {
        "method": name,
        "surface": surface,
        "settings": f"defaults, surface {surface}" + "".join(f", {k} = {v!r}" for k, v in (overrides or {}).items()),
        "triangles": triangles,
        "ms_per_scan": float(after_read.mean()),
        "ms_per_scan_median": float(np.median(after_read)),
        "stage_ms": {
            stage: float(np.mean([getattr(r, stage) for r in records]))
            for stage in STAGES
        },
        "run_seconds": float(result.seconds),
        "faces_removed": removed,
        "faces_removed_of_map": removed / triangles if triangles else math.nan,
        "faces_removed_of_made": removed / (triangles + removed) if triangles + removed else 0.0,
        "area_removed_m2": float(sum(r.area_removed for r in records)),
        "meshed_poses_vs_given": pose_differences(subset.poses, meshed),
        "registration": statuses,
        "poor_fit": sum(r.poor_fit for r in records),
        "noise": config.sensor.noise,
        "score": score,
        "score_corrected_pose": corrected,
        "score_seconds": seconds,
    }


class PoissonPeer:
    """The integrated scans as one oriented point cloud (module docs), ready for Poisson at any depth."""

    def __init__(self, files, poses, range_min: float, range_max: float, voxel: float = POISSON_VOXEL) -> None:
        import open3d as o3d

        self.o3d = o3d
        self.voxel = voxel
        self.scans = len(files)
        points, normals = [], []
        self.read_seconds = 0.0
        start = time.perf_counter()
        search = o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_RADIUS_VOXELS * voxel, max_nn=NORMAL_NEIGHBOURS)
        for path, pose in zip(files, poses):
            read = time.perf_counter()
            xyz = read_scan(path).astype(np.float64)
            self.read_seconds += time.perf_counter() - read
            r = np.linalg.norm(xyz, axis=1)
            xyz = xyz[np.isfinite(xyz).all(axis=1) & (r > range_min) & (r < range_max)]
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
            cloud.estimate_normals(search)
            cloud.orient_normals_towards_camera_location(np.zeros(3))  # the sensor, in its own frame
            points.append(xyz @ pose[:3, :3].T + pose[:3, 3])
            normals.append(np.asarray(cloud.normals) @ pose[:3, :3].T)
        gathered = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(points)))
        gathered.normals = o3d.utility.Vector3dVector(np.concatenate(normals))
        self.points_gathered = len(gathered.points)
        self.cloud = gathered.voxel_down_sample(voxel)
        averaged = np.asarray(self.cloud.normals)
        length = np.linalg.norm(averaged, axis=1)
        keep = length > 1e-3  # a voxel whose normals cancel out has no direction to give Poisson
        self.cancelled = int((~keep).sum())
        self.cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(self.cloud.points)[keep]))
        self.cloud.normals = o3d.utility.Vector3dVector(averaged[keep] / length[keep, None])
        self.points = len(self.cloud.points)
        self.prepare_seconds = time.perf_counter() - start - self.read_seconds

    def reconstruct(self, depth: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """(vertices, triangles, densities, seconds) of the Poisson surface at octree ``depth``."""
        start = time.perf_counter()
        with self.o3d.utility.VerbosityContextManager(self.o3d.utility.VerbosityLevel.Error):
            mesh, densities = self.o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
                self.cloud, depth=depth, width=0, scale=1.1, linear_fit=False
            )
        seconds = time.perf_counter() - start
        return np.asarray(mesh.vertices).copy(), np.asarray(mesh.triangles).astype(np.int64), np.asarray(densities).copy(), seconds


def trimmed(vertices, triangles, densities, trim: float):
    """The triangles whose three vertices have a density at or above its ``trim`` quantile (a vtkPolyData)."""
    keep = densities >= np.quantile(densities, trim)
    return triangles_polydata(vertices, triangles[keep[triangles].all(axis=1)])


def poisson_name(depth: int, trim: float, voxel: float = POISSON_VOXEL) -> str:
    return f"poisson (voxel {voxel * 100:g} cm, depth {depth}, trim {trim * 100:g}%)"


def run_poisson(files, poses, geometry: SphericalGeometry, held: HeldOutScans, depths, trims, integrated=None) -> tuple[dict, list[dict]]:
    """(the peer's row, every setting's row): the best F at 10 cm of ``depths`` by ``trims``."""
    log(f"poisson: normals of {len(files)} scans")
    peer = PoissonPeer(files, poses, geometry.range_min, geometry.range_max)
    log(
        f"poisson: {peer.points_gathered:,} points gathered, {peer.points:,} after the {peer.voxel * 100:g} cm voxels "
        f"({peer.cancelled} dropped: normals cancelled out) "
        f"({peer.prepare_seconds:.0f} s, reading {peer.read_seconds:.0f} s not counted)"
    )
    rows = []
    for depth in depths:
        vertices, triangles, densities, seconds = peer.reconstruct(depth)
        log(f"poisson depth {depth}: {len(triangles):,} triangles in {seconds:.0f} s")
        for trim in trims:
            start = time.perf_counter()
            mesh = trimmed(vertices, triangles, densities, trim)
            trim_seconds = time.perf_counter() - start
            total = peer.prepare_seconds + seconds + trim_seconds
            name = poisson_name(depth, trim)
            score, score_seconds = scored(mesh, held, integrated)
            log(f"{name}: {mesh.GetNumberOfCells():,} triangles; scored in {score_seconds:.0f} s: F@10cm {score['fscore']:.3f}")
            rows.append(
                {
                    "method": name,
                    "settings": {
                        "voxel_m": peer.voxel,
                        "normal_radius_m": NORMAL_RADIUS_VOXELS * peer.voxel,
                        "normal_max_nn": NORMAL_NEIGHBOURS,
                        "depth": depth,
                        "scale": 1.1,
                        "linear_fit": False,
                        "density_trim_quantile": trim,
                    },
                    "triangles": int(mesh.GetNumberOfCells()),
                    "ms_per_scan": 1000.0 * total / peer.scans,
                    "seconds": {
                        "normals_and_voxels": peer.prepare_seconds,
                        "poisson": seconds,
                        "trim": trim_seconds,
                        "read_not_counted": peer.read_seconds,
                    },
                    "points_gathered": peer.points_gathered,
                    "points_after_voxels": peer.points,
                    "voxels_dropped_normals_cancelled": peer.cancelled,
                    "faces_removed": None,
                    "score": score,
                    "score_seconds": score_seconds,
                }
            )
    best = max(rows, key=lambda row: -math.inf if math.isnan(row["score"]["fscore"]) else row["score"]["fscore"])
    return best, rows


def percent(x) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100.0 * x:.1f}%"


def markdown(bench: dict) -> str:
    lines = [
        f"{bench['frames']} scans of {bench['source']}: {bench['integrated']} integrated, {bench['held_out']} held out "
        f"(every {bench['every']}th; {bench['held_out_points']:,} held-out points within {bench['range_limits_m'][0]:g}-"
        f"{bench['range_limits_m'][1]:g} m)",
        "",
        "| map | triangles | recall@5cm | recall@10cm | precision@10cm | F@10cm | faces removed (% of map) | ms / scan |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in bench["methods"]:
        removed = "-" if row["faces_removed"] is None else f"{row['faces_removed']:,} ({percent(row['faces_removed_of_map'])})"
        for name, s in ((row["method"], row["score"]), (f"{row['method']}, held out at corrected poses", row.get("score_corrected_pose"))):
            if s is None:
                continue
            lines.append(
                f"| {name} | {row['triangles']:,} | {percent(s['recall']['5cm'])} | {percent(s['recall']['10cm'])} "
                f"| {percent(s['precision'])} | {s['fscore']:.3f} | {removed} | {row['ms_per_scan']:.0f} |"
            )
    lines.append("")
    for row in bench["methods"]:
        s = row["score"]
        line = (
            f"- {row['method']}: {s['area_m2']:.0f} m^2 of map, {s['area_seen_m2']:.0f} m^2 of it seen from the held-out "
            f"scans ({s['samples_seen']:,} of {s['samples']:,} samples)"
        )
        bands = ", ".join(
            (f"{b['from_m']:g}-{b['to_m']:g} m" if b["to_m"] is not None else f"over {b['from_m']:g} m") + f" {percent(b['precision'])}"
            for b in s["by_range"]
        )
        line += f"; precision by distance from the nearest held-out sensor: {bands}"
        if not math.isnan(s.get("supported", math.nan)):
            supported = ", ".join(
                (f"{b['from_m']:g}-{b['to_m']:g} m" if b["to_m"] is not None else f"over {b['from_m']:g} m") + f" {percent(b['supported'])}"
                for b in s["by_range"]
            )
            line += (
                f"; of the seen area {percent(s['supported'])} has no held-out return but an integrated one within 10 cm "
                f"(by distance: {supported})"
            )
        if "meshed_poses_vs_given" in row:
            d = row["meshed_poses_vs_given"]
            line += (
                f"; meshed poses against the given ones: translation median {d['translation_mm_median']:.0f} mm (max "
                f"{d['translation_mm_max']:.0f}), rotation median {d['rotation_deg_median']:.2f} deg (max {d['rotation_deg_max']:.2f}); "
                f"registration {row['registration']}, {row.get('poor_fit', 0)} fitting the map poorly (no removal votes)"
            )
        lines.append(line)
    if bench.get("poisson_grid") and len(bench["poisson_grid"]) > 1:
        lines += [
            "",
            "Poisson settings tried (--tune; the best F@10cm is the peer above):",
            "",
            "| depth | trim | triangles | recall@10cm | precision@10cm | F@10cm | ms / scan |",
            "|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for row in bench["poisson_grid"]:
            s, k = row["score"], row["settings"]
            lines.append(
                f"| {k['depth']} | {percent(k['density_trim_quantile'])} | {row['triangles']:,} | {percent(s['recall']['10cm'])} "
                f"| {percent(s['precision'])} | {s['fscore']:.3f} | {row['ms_per_scan']:.0f} |"
            )
    lines.append("")
    for note in bench["notes"]:
        lines.append(f"- {note}")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequence", type=Path, help="a LiDAR recording: a KITTI-layout folder (velodyne/NNNNNN.bin, poses.txt) or a folder of LiDAR scans (.pcd, .bin) beside their poses")
    parser.add_argument("--every", type=int, default=5, help="hold out every K-th scan (default 5)")
    parser.add_argument("--frames", type=int, help="take the first N scans of the recording (default: all)")
    parser.add_argument(
        "--surface", nargs="*", default=list(SURFACES), help="mabdi surface filter(s) (default: all three; the option with no value: no mabdi map, the peer alone)"
    )
    parser.add_argument("--tune", action="store_true", help="run the Poisson peer at every --depths by --trims and report the best")
    parser.add_argument("--depths", type=int, nargs="+", default=list(TUNE_DEPTHS), help="--tune: Poisson octree depths (default 10 11 12)")
    parser.add_argument(
        "--trims", type=float, nargs="+", default=list(TUNE_TRIMS), help="--tune: density quantiles trimmed (default 0.05 0.10 0.20 0.30 0.40)"
    )
    parser.add_argument("--no-poisson", action="store_true", help="run no Poisson peer")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="set a mabdi config value (as mabdi run --set; repeatable)")
    parser.add_argument("--out", type=Path, help="write every number here as JSON")
    args = parser.parse_args(argv)
    try:
        overrides = settings_overrides(args.set)
    except ConfigError as exc:
        parser.error(str(exc))

    usable, reason = open3d_status()
    if not usable:
        parser.error(f"the scoring needs Open3D: {reason}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            source = open_sequence(args.sequence)
        except SequenceError as exc:
            parser.error(str(exc))
    where = str(args.sequence)
    notes = [str(w.message).replace(where, args.sequence.name) for w in caught]
    for note in notes:
        log(f"note: {note}")
    geometry = source.intrinsics
    if not isinstance(geometry, SphericalGeometry):
        parser.error(f"{args.sequence}: read as depth images, not LiDAR scans")
    if not isinstance(source, KittiSequence):
        parser.error(f"{args.sequence}: read as a {type(source).__name__}; the scoring reads scan files: a KITTI-layout folder or a folder of LiDAR scans")
    frames = len(source) if args.frames is None else min(args.frames, len(source))
    integrated, held_index = held_out_split(frames, args.every)
    subset = FrameSubset(source, integrated)
    files = source.scan_paths
    poses = source.poses
    log(f"{source.description}: {frames} scans, {len(integrated)} integrated, {len(held_index)} held out")

    held_scans = [read_scan(files[i]) for i in held_index]
    held = HeldOutScans.from_scans(
        held_scans, poses[held_index], geometry.range_min, geometry.range_max, (geometry.fov_down, geometry.fov_up)
    )
    # how many held-out returns lie outside the image's rows (no map built from range images can hold them)
    pooled = np.concatenate([s.astype(np.float64) for s in held_scans])
    r = np.linalg.norm(pooled, axis=1)
    returns = np.isfinite(pooled).all(axis=1) & (r > geometry.range_min) & (r < geometry.range_max)
    elevation = np.degrees(np.arcsin(np.clip(pooled[returns, 2] / r[returns], -1.0, 1.0)))
    outside_fov = float(np.mean((elevation < geometry.fov_down) | (elevation > geometry.fov_up))) if returns.any() else 0.0
    del pooled

    # the integrated scans' returns in the world at the given poses: what the maps were built from ("supported")
    integrated_points = np.concatenate(
        [scan_in_world(read_scan(files[i]), poses[i], geometry.range_min, geometry.range_max) for i in integrated]
    )

    def replace_held(meshed):
        # the held-out scans at their given poses corrected as the run corrected the scans around them
        at = corrected_poses(poses, integrated, meshed, held_index)
        return HeldOutScans.from_scans(held_scans, at, geometry.range_min, geometry.range_max, (geometry.fov_down, geometry.fov_up))

    git = git_state()
    if git.get("uncommitted"):
        notes.append(f"measured at {git['head'][:10]} with uncommitted changes to: {', '.join(git['uncommitted'])}")
    rows, grid = [], []
    started = time.perf_counter()
    for surface in args.surface:
        rows.append(run_mabdi(subset, held, surface, overrides, replace_held, integrated_points))
    mabdi_seconds = time.perf_counter() - started
    poisson_seconds = 0.0
    if not args.no_poisson:
        started = time.perf_counter()
        depths, trims = (args.depths, args.trims) if args.tune else ([POISSON_DEPTH], [POISSON_TRIM])
        best, grid = run_poisson([files[i] for i in integrated], poses[integrated], geometry, held, depths, trims, integrated_points)
        rows.append(best)
        poisson_seconds = time.perf_counter() - started
        if args.tune:
            notes.append(
                f"the Poisson peer is the best F@10cm of {len(grid)} settings (depth {', '.join(map(str, depths))} by trim "
                f"{', '.join(f'{t * 100:g}%' for t in trims)}), chosen on these held-out scans"
            )
    notes.append(
        f"held-out returns outside the run's vertical field of view ({geometry.fov_down:g} to {geometry.fov_up:g} deg): "
        f"{percent(outside_fov)} (counted in recall; no map built from the range images holds them)"
    )
    bench = {
        "source": source.description.replace(where, args.sequence.name),
        "sequence": args.sequence.name,
        "frames": frames,
        "every": args.every,
        "integrated": int(len(integrated)),
        "held_out": int(len(held_index)),
        "held_out_frames": held_index.tolist(),
        "held_out_points": len(held),
        "held_out_outside_fov_share": outside_fov,
        "geometry": {k: getattr(geometry, k) for k in ("beams", "columns", "fov_up", "fov_down", "range_min", "range_max")},
        "range_limits_m": [geometry.range_min, geometry.range_max],
        "recall_thresholds_m": list(RECALL_THRESHOLDS_M),
        "precision_threshold_m": PRECISION_THRESHOLD_M,
        "sample_area_m2": SAMPLE_AREA_M2,
        "max_samples": MAX_SAMPLES,
        "seen_tolerance_m": SEEN_TOLERANCE_M,
        "command": "benchmarks/bench_real_lidar.py "
        + " ".join(shlex.quote(a.replace(where, args.sequence.name)) for a in (argv if argv is not None else sys.argv[1:])),
        "machine": machine_info(),
        "git": git,
        "seconds": {"mabdi_runs_and_scoring": mabdi_seconds, "poisson_and_scoring": poisson_seconds},
        "methods": rows,
        "poisson_grid": grid,
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
