"""How well each map follows a changing world: ghosts, frames to clear them, static surface lost.

Runs 3-5 (``scenes/bunnies_dynamic.toml``: the middle bunny appears half
way; ``scenes/bunnies_leaving.toml``: it leaves half way;
``scenes/door.toml``: a door opens at 1/3 and closes at 2/3), each scene's
frames rendered once and fed to every method: the MABDI loop with each
surface (pixel_grid, quadtree, voxel_planes) and Open3D's TSDF at 1 cm.

Per method (definitions in :mod:`mabdi.evaluate.dynamic`):

* ghost share after each measured frame (MABDI: every ``--every`` frames;
  TSDF: its mesh extracted every ``--tsdf-every`` frames) and at the end;
* frames to clear each departed object's ghost (from the first frame that
  sees its place until its ghost is below 1 % of the map's area);
* static loss (m^2, and as a share of the static surface the map covered);
* static and dynamic accuracy (SA, DA) and their geometric mean (AA), the
  KTH DynamicMap benchmark's scores (:mod:`mabdi.evaluate.removal_accuracy`),
  on the vertices of every measured map;
* F@1cm of the final map against the final scene (observed samples);
* frames per second of the method alone (MABDI: the loop's steps; TSDF:
  reading + integrating, without the extractions done for the measuring).

    .venv/bin/python benchmarks/bench_removal.py [--scenes door ...] [--methods quadtree tsdf_1cm ...]
        [--no-removal] [--every 1] [--out benchmarks/results/removal.json]

Prints a markdown table and writes the JSON (every series included).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path


from mabdi.config import load_run_config, set_value
from mabdi.evaluate.bench import bench_frames, machine_info
from mabdi.evaluate.distance import distances_within
from mabdi.evaluate.dynamic import GhostTracker, run_with_ghosts
from mabdi.evaluate.metrics import fscore, observed_ground_truth, scenes_per_pose
from mabdi.evaluate.sampling import sample_surface
from mabdi.evaluate.tsdf import TsdfMapper, TsdfSettings, open3d_status
from mabdi.loop import MappingRun

REPO = Path(__file__).resolve().parents[1]
SCENES = {
    "bunnies_dynamic": "scenes/bunnies_dynamic.toml",
    "bunnies_leaving": "scenes/bunnies_leaving.toml",
    "door": "scenes/door.toml",
}
SURFACES = ("pixel_grid", "quadtree", "voxel_planes")
METHODS = (*SURFACES, "tsdf_1cm")
F_SAMPLES = 50_000


def f_at_1cm(mesh, ground_truth, observed) -> float:
    """F-score at 1 cm: map samples against the final scene, observed scene samples against the map."""
    points = sample_surface(mesh, F_SAMPLES).points
    if len(points) == 0 or len(observed) == 0:
        return 0.0
    precision = float((distances_within(points, ground_truth, cap=0.05) <= 0.01).mean())
    recall = float((distances_within(observed.points, mesh, cap=0.05) <= 0.01).mean())
    return fscore(precision, recall)


def run_mabdi(config, surface, rig, frames, every, static_every, removal):
    method_config = copy.deepcopy(config)
    set_value(method_config, "surface.method", surface)
    set_value(method_config, "removal.enabled", removal)
    simulation = MappingRun(method_config, source=frames, scene=rig.scene)
    run = run_with_ghosts(simulation, every=every, static_every=static_every)
    return run, run.result.mesh, len(frames) / run.loop_seconds


def run_tsdf_tracked(config, rig, frames, every, static_every):
    settings = TsdfSettings(voxel_size=0.01, depth_max=max(5.0, config.sensor.camera.far))
    mapper = TsdfMapper(settings, frames.intrinsics)
    count = len(frames)
    tracker = GhostTracker(
        rig.scene, count, rig.poses, frames.intrinsics, static_every=static_every, backend=config.sensor.backend
    )
    seconds = 0.0
    mesh = None
    for i in range(count):
        start = time.perf_counter()
        frame = frames.read(i)
        mapper.integrate(frame.depth, frame.world_from_camera)
        seconds += time.perf_counter() - start
        last = i == count - 1
        if i % every == 0 or last:
            mesh = mapper.extract()
            tracker.measure(i, mesh, final=last)
    return tracker.finish(loop_seconds=seconds), mesh, count / seconds


def bench_scene(name, path, methods, every, tsdf_every, static_every, removal=True, progress=print) -> dict:
    config = load_run_config(REPO / path)
    progress(f"{name}: rendering {config.run.frames} frames")
    rig, frames = bench_frames(config)
    count = len(frames)
    final_scene = rig.scene.mesh_at(count - 1)
    observed = observed_ground_truth(
        final_scene, scenes_per_pose(rig.scene, count), rig.poses, rig.intrinsics, F_SAMPLES, config.sensor.backend
    )
    rows = []
    for method in methods:
        start = time.perf_counter()
        if method == "tsdf_1cm":
            usable, reason = open3d_status()
            if not usable:
                progress(f"{name}: {method} skipped: {reason}")
                continue
            run, mesh, fps = run_tsdf_tracked(config, rig, frames, tsdf_every, static_every)
        else:
            run, mesh, fps = run_mabdi(config, method, rig, frames, every, static_every, removal)
        clear = run.frames_to_clear()
        row = {
            "method": method,
            "removal": None if method == "tsdf_1cm" else removal,
            "ghost_final": run.final_share,
            "ghost_max": max((s for _, s in run.shares), default=0.0),
            "ghost_per_frame": run.shares,
            "object_ghost_per_frame": run.by_object,
            "object_ghost_final": {k: (v[-1][1] if v else 0.0) for k, v in run.by_object.items()},
            "departures": {d.name: {"left_at": d.frame, "seen_at": d.seen_at} for d in run.departures},
            "frames_to_clear": clear,
            "static_loss": run.static.as_dict(),
            "removal_accuracy": run.removal.as_dict() if run.removal is not None else None,
            "f1cm": f_at_1cm(mesh, final_scene, observed),
            "triangles": int(mesh.GetNumberOfCells()),
            "fps": fps,
            "seconds": time.perf_counter() - start,
        }
        rows.append(row)
        progress(
            f"{name}: {method}{'' if method == 'tsdf_1cm' else ' removal ' + ('on' if removal else 'off')}: ghost {100 * row['ghost_final']:.1f}%, clear {clear}, "
            f"static loss {row['static_loss']['area_m2']:.3f} m^2, F@1cm {row['f1cm']:.3f}, {fps:.2f} fps"
        )
    return {"scene": name, "config": path, "frames": count, "noise": config.sensor.noise, "methods": rows}


def markdown(results: list[dict]) -> str:
    lines = [
        "| run | method | removal | ghost at end | ghost max | departed object's ghost at end | frames to clear (seen at) "
        "| static loss m^2 (share) | SA | DA | AA | F@1cm | triangles | fps |",
        "|---|---|---|---:|---:|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for scene in results:
        for row in scene["methods"]:
            objects = ", ".join(f"{k} {100 * v:.1f}%" for k, v in row["object_ghost_final"].items()) or "-"
            clear = (
                ", ".join(
                    f"{k} {'never' if v is None else v} ({row['departures'][k]['seen_at']})"
                    for k, v in row["frames_to_clear"].items()
                )
                or "-"
            )
            loss = row["static_loss"]
            accuracy = row.get("removal_accuracy") or {}
            scores = " | ".join(
                "-" if accuracy.get(k) is None or accuracy[k] != accuracy[k] else f"{accuracy[k]:.4f}"
                for k in ("static_accuracy", "dynamic_accuracy", "associated_accuracy")
            )
            lines.append(
                f"| {scene['scene']} | {row['method']} | {'-' if row['removal'] is None else ('on' if row['removal'] else 'off')} | {100 * row['ghost_final']:.1f}% | {100 * row['ghost_max']:.1f}% "
                f"| {objects} | {clear} | {loss['area_m2']:.3f} ({100 * loss['share']:.1f}%) | {scores} | {row['f1cm']:.3f} "
                f"| {row['triangles']:,} | {row['fps']:.2f} |"
            )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    parser.add_argument("--every", type=int, default=1, help="measure the MABDI map every N frames")
    parser.add_argument("--tsdf-every", type=int, default=5, help="extract and measure the TSDF mesh every N frames")
    parser.add_argument("--static-every", type=int, default=5, help="update the static coverage every N measurements")
    parser.add_argument("--no-removal", action="store_true", help="MABDI without object removal (the 'before' baseline)")
    parser.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "removal.json"))
    args = parser.parse_args(argv)
    results = []
    started = time.perf_counter()
    for name in args.scenes:
        results.append(
            bench_scene(
                name, SCENES[name], args.methods, args.every, args.tsdf_every, args.static_every,
                removal=not args.no_removal, progress=print,
            )
        )
        sys.stdout.flush()
    table = markdown(results)
    print(table)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    document = {
        "command": " ".join(["benchmarks/bench_removal.py", *(argv if argv is not None else sys.argv[1:])]),
        "machine": machine_info(),
        "seconds": time.perf_counter() - started,
        "scenes": results,
        "table": table,
    }
    out.write_text(json.dumps(document, indent=2, default=float) + "\n")
    print(f"written {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
