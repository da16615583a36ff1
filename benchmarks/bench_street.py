"""The street scene scanned by a 64-beam LiDAR (``scenes/street.toml``), each surface in the MABDI loop.

Per surface (definitions in :mod:`mabdi.evaluate.metrics`, :mod:`mabdi.evaluate.dynamic` and
:mod:`mabdi.evaluate.removal_accuracy`):

* F@2cm (and precision, recall) of the final map against the final scene's observed samples;
* map growth per pass: triangles added on the way out (first half of the frames) and back (second half);
* ghost share of the final map, and the departed car's share of it;
* static and dynamic accuracy (SA, DA) on the vertices of every measured map;
* milliseconds per scan: the range image D, the expected range image E, the loop's total (medians).

Beside them, the TSDF peer (Open3D's VoxelBlockGrid fused along each beam, :mod:`mabdi.evaluate.tsdf`)
on the same scans, tuned on them: every voxel size and truncation of ``--tsdf-voxels`` x
``--tsdf-trunc`` is integrated once and meshed at every weight threshold (0.5, 1, 2, 3); the best
F@2cm (ties: fewer triangles) against a 50,000-sample set of the observed scene is then run again
and measured like the surfaces (its maps every ``--every`` scans, against the full sample set).

    .venv/bin/python benchmarks/bench_street.py [--surfaces pixel_grid quadtree voxel_planes] [--frames N]
        [--every 19] [--tsdf-voxels 0.08 0.1] [--tsdf-trunc 6 8 10] [--no-tsdf]
        [--out benchmarks/results/street.json]

Prints a markdown table and writes the JSON.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from mabdi.config import load_run_config, set_value
from mabdi.evaluate.bench import bench_frames, machine_info, observed_samples
from mabdi.evaluate.dynamic import GhostTracker, run_with_ghosts
from mabdi.evaluate.metrics import SAMPLES, evaluate_map, evaluate_run
from mabdi.evaluate.tsdf import TsdfMapper, TsdfSettings, open3d_status
from mabdi.loop import MappingRun

#: Samples of the observed scene the TSDF is tuned against (the final score uses the full set).
TUNING_SAMPLES = 50_000
#: The weight thresholds every tuned volume is meshed at.
WEIGHT_THRESHOLDS = (0.5, 1.0, 2.0, 3.0)

ROOT = Path(__file__).resolve().parents[1]


def bench_surface(surface: str, frames: int | None, every: int) -> dict:
    config = _street_config(frames)
    set_value(config, "surface.method", surface)
    simulation = MappingRun(config)
    start = time.perf_counter()
    ghosts = run_with_ghosts(simulation, every=every)
    seconds = time.perf_counter() - start
    result = ghosts.result
    scores = evaluate_run(simulation, result)
    records = result.records
    added = np.array([r.cells_added for r in records])
    half = len(added) // 2
    car = ghosts.by_object.get("car_leaving", [])
    removal = ghosts.removal
    return {
        "surface": surface,
        "frames": len(records),
        "fscore_2cm": scores.fscore_2cm,
        "precision_2cm": scores.precision_2cm,
        "recall_2cm": scores.recall_2cm,
        "accuracy_median_mm": scores.accuracy_median_mm,
        "redundancy": scores.redundancy,
        "triangles": scores.triangles,
        "added_out": int(added[:half].sum()),
        "added_back": int(added[half:].sum()),
        "growth_back_share": float(added[half:].sum() / max(added[:half].sum(), 1)),
        "ghost_share_final": ghosts.final_share,
        "car_ghost_final": car[-1][1] if car else None,
        "static_accuracy": None if removal is None else removal.static_accuracy,
        "dynamic_accuracy": None if removal is None else removal.dynamic_accuracy,
        "ms_depth": float(np.median([r.t_depth_ms for r in records])),
        "ms_expected": float(np.median([r.t_expected_ms for r in records])),
        "ms_total": float(np.median([r.t_total_ms for r in records])),
        "loop_seconds": ghosts.loop_seconds,
        "seconds": seconds,
    }


def _street_config(frames: int | None):
    config = load_run_config(ROOT / "scenes" / "street.toml")
    if frames:
        set_value(config, "run.frames", frames)
    return config


def bench_tsdf(frames_count: int | None, every: int, voxels, truncs) -> dict:
    """The TSDF peer on the street's scans: tuned (voxel size, truncation, weight threshold), then measured."""
    config = _street_config(frames_count)
    rig, frames = bench_frames(config)
    count = len(frames)
    ground_truth = rig.scene.mesh_at(count - 1)
    tuning_observed = observed_samples(rig, config, TUNING_SAMPLES)
    # every volume starts with room for the street at these voxel sizes (Open3D grows it if not)
    base = TsdfSettings(depth_max=rig.intrinsics.far, block_resolution=8, block_count=20_000)
    table = []
    for voxel in voxels:
        for trunc in truncs:
            mapper = TsdfMapper(base.replace(voxel_size=voxel, trunc_voxels=trunc), rig.intrinsics)
            start = time.perf_counter()
            for i in range(count):
                frame = frames.read(i)
                mapper.integrate(frame.depth, frame.world_from_camera)
            seconds = time.perf_counter() - start
            for weight in WEIGHT_THRESHOLDS:
                mesh = mapper.extract(weight)
                scores = evaluate_map(mesh, ground_truth, tuning_observed, samples=TUNING_SAMPLES)
                table.append(
                    {"voxel_size": voxel, "trunc_voxels": trunc, "weight_threshold": weight, "fscore_2cm": scores.fscore_2cm,
                     "precision_2cm": scores.precision_2cm, "recall_2cm": scores.recall_2cm, "triangles": scores.triangles,
                     "integrate_s": seconds}
                )
                print(f"tsdf voxel {voxel} trunc {trunc} weight {weight}: F@2cm {scores.fscore_2cm:.3f} "
                      f"({scores.precision_2cm:.3f} / {scores.recall_2cm:.3f}), {scores.triangles:,} triangles", flush=True)
    best = min(table, key=lambda r: (-r["fscore_2cm"], r["triangles"]))
    settings = base.replace(voxel_size=best["voxel_size"], trunc_voxels=best["trunc_voxels"], weight_threshold=best["weight_threshold"])
    # the best settings again, measured like the loop's maps: every ``every`` scans and after the last
    mapper = TsdfMapper(settings, rig.intrinsics)
    tracker = GhostTracker(rig.scene, count, rig.true_poses, rig.intrinsics, backend=config.sensor.backend)
    integrate_ms, extract_ms, triangles_at = [], [], {}
    mesh = None
    for i in range(count):
        frame = frames.read(i)
        t0 = time.perf_counter()
        mapper.integrate(frame.depth, frame.world_from_camera)
        integrate_ms.append(1000.0 * (time.perf_counter() - t0))
        if (i + 1) % every == 0 or i == count - 1 or i == count // 2 - 1:
            t0 = time.perf_counter()
            mesh = mapper.extract()
            extract_ms.append(1000.0 * (time.perf_counter() - t0))
            triangles_at[i] = mesh.GetNumberOfCells()
            if (i + 1) % every == 0 or i == count - 1:
                tracker.measure(i, mesh, final=i == count - 1)
    ghosts = tracker.finish()
    scores = evaluate_map(mesh, ground_truth, observed_samples(rig, config, SAMPLES), samples=SAMPLES)
    out = triangles_at[count // 2 - 1]
    car = ghosts.by_object.get("car_leaving", [])
    removal = ghosts.removal
    return {
        "surface": "tsdf",
        "settings": settings.as_dict(),
        "tuning": table,
        "frames": count,
        "fscore_2cm": scores.fscore_2cm,
        "precision_2cm": scores.precision_2cm,
        "recall_2cm": scores.recall_2cm,
        "accuracy_median_mm": scores.accuracy_median_mm,
        "triangles": scores.triangles,
        "added_out": int(out),
        "added_back": int(triangles_at[count - 1] - out),
        "growth_back_share": float((triangles_at[count - 1] - out) / max(out, 1)),
        "ghost_share_final": ghosts.final_share,
        "car_ghost_final": car[-1][1] if car else None,
        "static_accuracy": None if removal is None else removal.static_accuracy,
        "dynamic_accuracy": None if removal is None else removal.dynamic_accuracy,
        "ms_depth": float("nan"),
        "ms_integrate": float(np.median(integrate_ms)),
        "ms_extract": float(np.median(extract_ms)),
        "ms_total": float(np.median(integrate_ms)),
        "volume_bytes": mapper.memory_bytes(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--surfaces", nargs="*", default=["pixel_grid", "quadtree", "voxel_planes"])
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--every", type=int, default=19)
    parser.add_argument("--tsdf-voxels", nargs="+", type=float, default=[0.08, 0.1])
    parser.add_argument("--tsdf-trunc", nargs="+", type=float, default=[6.0, 8.0, 10.0])
    parser.add_argument("--no-tsdf", action="store_true", help="leave out the TSDF peer")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "street.json"))
    args = parser.parse_args()
    rows = [bench_surface(s, args.frames, args.every) for s in args.surfaces]
    usable, reason = open3d_status()
    if not args.no_tsdf and not usable:
        print(f"the TSDF peer left out: {reason}")
    elif not args.no_tsdf:
        rows.append(bench_tsdf(args.frames, args.every, args.tsdf_voxels, args.tsdf_trunc))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"machine": machine_info(), "rows": rows}, indent=2))
    print("| surface | F@2cm | precision / recall @2cm | triangles | added out / back | back/out | ghost share (car) "
          "| SA | DA | ms D / E / loop per scan |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        car = "-" if r["car_ghost_final"] is None else f"{100 * r['car_ghost_final']:.2f}%"
        print(
            f"| {r['surface']} | {r['fscore_2cm']:.3f} | {r['precision_2cm']:.3f} / {r['recall_2cm']:.3f} | {r['triangles']:,} "
            f"| {r['added_out']:,} / {r['added_back']:,} | {100 * r['growth_back_share']:.1f}% "
            f"| {100 * r['ghost_share_final']:.2f}% ({car}) | {r['static_accuracy']:.3f} | {r['dynamic_accuracy']:.3f} "
            + (f"| {r['ms_depth']:.0f} / {r['ms_expected']:.0f} / {r['ms_total']:.0f} |" if r["surface"] != "tsdf"
               else f"| integrate {r['ms_integrate']:.0f}, mesh {r['ms_extract']:.0f} |")
        )


if __name__ == "__main__":
    main()
