"""Benchmark: per-frame cost on a large place once the map has stopped growing (scenes/ring.toml).

A ring of 36 objects on a 30 m floor, the sensor circling it twice (600
frames, quad-tree, 640x480). The map stops growing after the first circle;
the goal is a flat cost after that: the mean per-frame time of the last 100
frames within 10% of frames 200-299, and E and append each within 10%.

Wall-clock stage times are what the loop records (``metrics.csv``); beside
them the process's CPU time per frame, which other jobs on the same cores do
not inflate. The goal is checked on both.

    python benchmarks/bench_ring.py [--frames 600] [--surface quadtree] [--json results.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from pathlib import Path

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import numpy as np  # noqa: E402

import mabdi  # noqa: E402
from mabdi.config import load_run_config, set_value  # noqa: E402
from mabdi.evaluate.bench import machine_info  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
STAGES = ("t_depth_ms", "t_register_ms", "t_expected_ms", "t_classify_ms", "t_surface_ms", "t_append_ms", "t_remove_ms", "t_total_ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--surface", default="quadtree")
    parser.add_argument("--out", type=Path, default=Path("/tmp/mabdi_ring"))
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    config = load_run_config(REPO / "scenes" / "ring.toml")
    set_value(config, "run.frames", args.frames)
    set_value(config, "surface.method", args.surface)
    set_value(config, "output.ply", False)
    simulation = mabdi.MappingRun(config)
    records, cpu = [], []
    last = [time.process_time()]

    def progress(record):
        now = time.process_time()
        records.append(record)
        cpu.append(1000.0 * (now - last[0]))
        last[0] = now

    shutil.rmtree(args.out, ignore_errors=True)
    simulation.run(args.out, progress=progress)
    windows = [(start, min(start + 100, len(records))) for start in range(0, len(records), 100)]
    table = []
    for start, end in windows:
        row = {"frames": f"{start}-{end - 1}", "triangles": records[end - 1].cells_total, "cpu_ms": float(np.mean(cpu[start:end]))}
        for stage in STAGES:
            row[stage] = float(np.mean([getattr(r, stage) for r in records[start:end]]))
        table.append(row)
    print("| frames | " + " | ".join(s[2:-3] for s in STAGES) + " | CPU ms/frame | triangles |")
    print("|---|" + "---:|" * (len(STAGES) + 2))
    for row in table:
        print(f"| {row['frames']} | " + " | ".join(f"{row[s]:.1f}" for s in STAGES) + f" | {row['cpu_ms']:.1f} | {row['triangles']:,} |")
    result = {"machine": machine_info(simulation.rig), "frames": args.frames, "surface": args.surface, "windows": table}
    if len(table) >= 6:
        reference, last_window = table[2], table[-1]
        ratios = {name: last_window[name] / reference[name] for name in ("t_total_ms", "t_expected_ms", "t_append_ms", "cpu_ms")}
        result["ratios_last_to_200_299"] = ratios
        result["goal_met"] = all(value <= 1.10 for value in ratios.values())
        print("last 100 frames / frames 200-299: " + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items()) + f"; goal met: {result['goal_met']}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
