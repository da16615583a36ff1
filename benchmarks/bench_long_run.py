"""Benchmark: a long run's memory and speed (10,000 frames of the table, quad-tree, 640x480).

Resident memory (RSS) of the process every 100 frames beside the map's own
bytes (``MabdiLoop.memory_bytes``), frames per second over the run, and the
cost of a checkpoint (the loop's state written every ``--checkpoint-every``
frames). The goal: RSS grows by at most the map's bytes + 50 MB.

    python benchmarks/bench_long_run.py [--frames 10000] [--out /tmp/long_run] [--json results.json]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import mabdi  # noqa: E402
from mabdi.config import load_run_config, set_value  # noqa: E402
from mabdi.evaluate.bench import machine_info  # noqa: E402
from mabdi.loop.run_pipeline import FrameCallback, RunPipeline  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def rss_bytes() -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10_000)
    parser.add_argument("--surface", default="quadtree")
    parser.add_argument("--checkpoint-every", type=int, default=1000)
    parser.add_argument("--out", type=Path, default=Path("/tmp/mabdi_long_run"))
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    config = load_run_config(REPO / "scenes" / "table.toml")
    set_value(config, "run.frames", args.frames)
    set_value(config, "surface.method", args.surface)
    set_value(config, "output.checkpoint_every", args.checkpoint_every)
    set_value(config, "output.ply", False)
    simulation = mabdi.MappingRun(config)
    samples = []
    start = time.perf_counter()
    last = [start, time.process_time()]

    def progress(record):
        if record.frame % 100 == 0 or record.frame == args.frames - 1:
            now, cpu = time.perf_counter(), time.process_time()
            samples.append(
                {
                    "frame": record.frame,
                    "rss_mb": rss_bytes() / 2**20,
                    "map_mb": simulation.loop.memory_bytes() / 2**20,
                    "cells": record.cells_total,
                    "seconds": now - start,
                    "fps_window": 100.0 / (now - last[0]) if record.frame else None,
                    # CPU seconds of this process per frame over the window: the cost, whatever else runs beside
                    "cpu_ms_per_frame": 1000.0 * (cpu - last[1]) / 100.0 if record.frame else None,
                }
            )
            last[0], last[1] = now, cpu
            s = samples[-1]
            cpu_ms = f"{s['cpu_ms_per_frame']:6.1f}" if s["cpu_ms_per_frame"] is not None else "     -"
            print(f"frame {s['frame']:6d}  RSS {s['rss_mb']:7.1f} MB  map {s['map_mb']:6.1f} MB  {s['cells']:,} triangles  "
                  f"CPU {cpu_ms} ms/frame", flush=True)

    import shutil

    shutil.rmtree(args.out, ignore_errors=True)
    pipeline = RunPipeline(simulation, args.out, [FrameCallback(progress)])
    original_write = pipeline.write_checkpoint
    checkpoint_ms = []

    def timed_checkpoint(next_frame):
        t = time.perf_counter()
        original_write(next_frame)
        checkpoint_ms.append(1000.0 * (time.perf_counter() - t))

    pipeline.write_checkpoint = timed_checkpoint  # what the pipeline's Checkpoints observer calls
    result = pipeline.run()
    seconds = time.perf_counter() - start
    first = next(s for s in samples if s["frame"] >= 100)
    end = samples[-1]
    growth = end["rss_mb"] - first["rss_mb"]
    map_growth = end["map_mb"] - first["map_mb"]
    summary = {
        "machine": machine_info(simulation.rig),
        "frames": args.frames,
        "surface": args.surface,
        "seconds": seconds,
        "frames_per_second": args.frames / seconds,
        "rss_mb_at_100": first["rss_mb"],
        "rss_mb_end": end["rss_mb"],
        "rss_growth_mb": growth,
        "map_growth_mb": map_growth,
        "goal_met": growth <= map_growth + 50.0,
        "checkpoint_ms": checkpoint_ms,
        "checkpoint_mb": (args.out / "checkpoint.pkl").stat().st_size / 2**20 if (args.out / "checkpoint.pkl").exists() else None,
        "samples": samples,
        "cells": int(result.mesh.GetNumberOfCells()),
    }
    print(
        f"\n{args.frames} frames in {seconds:.0f} s ({summary['frames_per_second']:.1f} frames/s); RSS {first['rss_mb']:.0f} -> "
        f"{end['rss_mb']:.0f} MB (+{growth:.1f} MB) while the map grew {map_growth:.1f} MB; goal met: {summary['goal_met']}; "
        f"checkpoint {sum(checkpoint_ms) / max(len(checkpoint_ms), 1):.0f} ms on average ({len(checkpoint_ms)} written)"
    )
    if args.json:
        args.json.write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
