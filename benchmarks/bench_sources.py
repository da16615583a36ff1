"""Benchmark: the loop fed by a recorded sequence beside the same run simulated, and E's cost with face identity.

1. Record Run 1 (the table) with ``kinect`` noise as a TUM folder and as ROS 2
   bags (sqlite3, MCAP), then run the loop (quad-tree) on each recording and
   on the simulator: frames per second and ms per stage, map size.
2. Render E of a large map (Run 2's pixel-grid map, about 1.4 M triangles)
   from its poses with and without face identity (the same pass drawing each
   face in its identity colour, plus the colour read-back): ms per frame and
   the ratio (goal <= 1.15).

    python benchmarks/bench_sources.py [--frames 30] [--json results.json]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import numpy as np  # noqa: E402

import mabdi  # noqa: E402
from mabdi.config import load_run_config, set_value  # noqa: E402
from mabdi.evaluate.bench import machine_info  # noqa: E402
from mabdi.stages.expected_image import FilterExpectedImage  # noqa: E402
from mabdi.loop.mapping_run import recorded_simulation  # noqa: E402
from mabdi.simulate.recording import record  # noqa: E402
from mabdi.sources.frames import SourceDepthFrames  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
STAGES = ("t_depth_ms", "t_expected_ms", "t_classify_ms", "t_surface_ms", "t_append_ms", "t_refine_ms", "t_remove_ms", "t_total_ms")


def table_config(frames: int):
    config = load_run_config(REPO / "scenes" / "table.toml")
    set_value(config, "run.frames", frames)
    set_value(config, "sensor.noise", "kinect")
    set_value(config, "surface.method", "quadtree")
    return config


def loop_row(name: str, simulation) -> dict:
    simulation.step(0)  # warm-up: render windows, compiled kernels
    result = simulation.run()
    return {
        "source": name,
        "frames_per_second": len(result.records) / result.seconds,
        "ms": {stage: float(np.mean([getattr(r, stage) for r in result.records])) for stage in STAGES},
        "triangles": int(result.mesh.GetNumberOfCells()),
    }


def loop_on_recordings(frames: int) -> list[dict]:
    rows = []
    config = table_config(frames)
    rows.append(loop_row("simulated", mabdi.MappingRun(config)))
    with tempfile.TemporaryDirectory() as folder:
        for name, fmt, storage in (("TUM folder", "tum", "sqlite3"), ("ROS 2 bag (sqlite3)", "rosbag2", "sqlite3"), ("ROS 2 bag (MCAP)", "rosbag2", "mcap")):
            path = Path(folder) / name.replace(" ", "_").replace("(", "").replace(")", "")
            record(table_config(frames), path, fmt, storage=storage)
            simulation, _ = recorded_simulation(table_config(frames), path)
            rows.append(loop_row(name, simulation))
    return rows


def expected_image_cost(repeats: int = 3) -> dict:
    config = load_run_config(REPO / "scenes" / "bunnies.toml")
    set_value(config, "removal.enabled", False)
    set_value(config, "refinement.enabled", False)
    simulation = mabdi.MappingRun(config)
    simulation.run()
    world = simulation.loop.world
    measured = SourceDepthFrames(simulation.source)
    timings = {}
    for identity in (False, True, False, True):
        expected = FilterExpectedImage(identity=identity)
        expected.SetInputDataObject(0, world.map)
        expected.SetInputConnection(1, measured.GetOutputPort())
        measured.frame = 0
        expected.Update()  # upload the map once
        ms = []
        for _ in range(repeats):
            for i in range(0, len(simulation.source), 5):
                measured.frame = i
                measured.Update()
                start = time.perf_counter()
                expected.Update()
                ms.append(1000.0 * (time.perf_counter() - start))
        timings.setdefault(identity, []).append(float(np.median(ms)))
        expected.renderer.close()
    plain, with_identity = min(timings[False]), min(timings[True])
    return {"triangles": world.number_of_cells, "plain_ms": plain, "identity_ms": with_identity, "ratio": with_identity / plain}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    results = {"machine": machine_info(), "loop": loop_on_recordings(args.frames), "expected_image": expected_image_cost()}
    print("| source | frames/s | " + " | ".join(s[2:-3] for s in STAGES) + " | triangles |")
    print("|---|---:|" + "---:|" * len(STAGES) + "---:|")
    for row in results["loop"]:
        stages = " | ".join(f"{row['ms'][s]:.1f}" for s in STAGES)
        print(f"| {row['source']} | {row['frames_per_second']:.1f} | {stages} | {row['triangles']:,} |")
    e = results["expected_image"]
    print(f"\nE of a {e['triangles']:,}-triangle map: {e['plain_ms']:.1f} ms plain, {e['identity_ms']:.1f} ms with face identity ({e['ratio']:.2f}x)")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
