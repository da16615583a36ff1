"""The street scene scanned by a 64-beam LiDAR (``scenes/street.toml``), each surface in the MABDI loop.

Per surface (definitions in :mod:`mabdi.evaluate.metrics`, :mod:`mabdi.evaluate.dynamic` and
:mod:`mabdi.evaluate.removal_accuracy`):

* F@2cm (and precision, recall) of the final map against the final scene's observed samples;
* map growth per pass: triangles added on the way out (first half of the frames) and back (second half);
* ghost share of the final map, and the departed car's share of it;
* static and dynamic accuracy (SA, DA) on the vertices of every measured map;
* milliseconds per scan: the range image D, the expected range image E, the loop's total (medians).

    .venv/bin/python benchmarks/bench_street.py [--surfaces pixel_grid quadtree voxel_planes] [--frames N]
        [--every 19] [--out benchmarks/results/street.json]

Prints a markdown table and writes the JSON.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from mabdi.config import load_run_config, set_value
from mabdi.evaluate.bench import machine_info
from mabdi.evaluate.dynamic import run_with_ghosts
from mabdi.evaluate.metrics import evaluate_run
from mabdi.loop import Simulation

ROOT = Path(__file__).resolve().parents[1]


def bench_surface(surface: str, frames: int | None, every: int) -> dict:
    config = load_run_config(ROOT / "scenes" / "street.toml")
    set_value(config, "surface.method", surface)
    if frames:
        set_value(config, "run.frames", frames)
    simulation = Simulation(config)
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--surfaces", nargs="+", default=["pixel_grid", "quadtree", "voxel_planes"])
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--every", type=int, default=19)
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "street.json"))
    args = parser.parse_args()
    rows = [bench_surface(s, args.frames, args.every) for s in args.surfaces]
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
            f"| {r['ms_depth']:.0f} / {r['ms_expected']:.0f} / {r['ms_total']:.0f} |"
        )


if __name__ == "__main__":
    main()
