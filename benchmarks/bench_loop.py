"""Benchmark: the MABDI loop on the seed's runs 1-3, beside the black box, per stage.

For each run config (table, bunnies, bunnies_dynamic), in the same process:

* MABDI (classifier on, the config's defaults);
* the black box (classifier off: every valid pixel meshed every frame), on
  the same D images (same scene, poses, noise seed);
* MABDI without speck removal (min_width = 1, min_region = 0), to show what
  the speck filter does to the growth of the map;
* MABDI with E rendered from one merged polydata rebuilt every frame (what a
  map kept as a single mesh costs: merge + full re-upload), to show what the
  map's blocks save.

Prints a markdown table: mean ms per frame by stage (D, registration, E,
classification, removal, surface, append), frames per second, triangles and
MB of the map at the end, and the second circle's growth as a share of the
first's. A three-frame run of the table goes first and is not reported: it
compiles the numba kernels (a fresh machine has no cache), so the first run
reported pays no compilation.

    python benchmarks/bench_loop.py [--frames N] [--runs table bunnies bunnies_dynamic street]
                                    [--variants mabdi "black box" "no speck filter" "E from merged map"]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import numpy as np  # noqa: E402

import mabdi  # noqa: E402
from mabdi.config import set_value  # noqa: E402
from mabdi.evaluate.bench import machine_info  # noqa: E402
from mabdi.loop.mapping_run import MappingRun  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


VARIANTS = ("mabdi", "black box", "no speck filter", "E from merged map")


class MergedMapSimulation(MappingRun):
    """E rendered from the whole map merged into one polydata, rebuilt every frame."""

    def step(self, i):
        start = time.perf_counter()
        self.loop.expected.SetInputDataObject(0, self.loop.world.mesh())
        merge_ms = 1000.0 * (time.perf_counter() - start)
        record = super().step(i)
        record.t_expected_ms += merge_ms
        record.t_total_ms += merge_ms
        return record


def one(name: str, variant: str, frames: int | None):
    config = mabdi.load_run_config(REPO / "scenes" / f"{name}.toml")
    if frames:
        config.run.frames = frames
    if variant == "black box":
        set_value(config, "classifier.enabled", False)
    elif variant == "no speck filter":
        set_value(config, "classifier.min_width", 1)
        set_value(config, "classifier.min_region", 0)
    simulation_class = MergedMapSimulation if variant == "E from merged map" else MappingRun
    result = simulation_class(config).run()
    summary = result.summary()
    added = np.array([r.cells_added for r in result.records])
    half = len(added) // 2
    growth = added[half:].sum() / max(added[:half].sum(), 1)
    total = np.array([r.t_total_ms for r in result.records])
    # Frame 0 sets up the renderers and the map (and is the whole map's first mesh): each circle's
    # time a frame is the median over its frames, frame 0 left out.
    circles = (float(np.median(total[1:half])), float(np.median(total[half:])))
    return summary, growth, circles


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=None, help="frames per run (default: the config's)")
    parser.add_argument("--runs", nargs="+", default=["table", "bunnies", "bunnies_dynamic"])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    args = parser.parse_args()
    one("table", "mabdi", 3)  # compiles the numba kernels; not reported
    info = machine_info()
    print(f"machine: {info['cpu']}, {info['cores']} cores, GPU {info['gpu']}; Python {info['python']}")
    print()
    print(
        "| run | method | D ms | register ms | E ms | classify ms | refine + remove ms | surface ms | append ms | total ms "
        "| frames/s | triangles | map MB | 2nd circle / 1st | ms a frame, 1st / 2nd circle (median) |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    renderer = None
    for name in args.runs:
        for variant in args.variants:
            summary, growth, circles = one(name, variant, args.frames)
            renderer = summary["render"].get("gl_renderer", renderer)
            ms = summary["mean_ms"]
            print(
                f"| {name} | {variant} | {ms['t_depth_ms']:.1f} | {ms['t_register_ms']:.1f} | {ms['t_expected_ms']:.1f} "
                f"| {ms['t_classify_ms']:.1f} | {ms['t_remove_ms'] + ms['t_refine_ms']:.1f} | {ms['t_surface_ms']:.1f} | {ms['t_append_ms']:.1f} | {ms['t_total_ms']:.1f} "
                f"| {summary['frames_per_second']:.1f} | {summary['cells']:,} | {summary['map_bytes'] / 2**20:.0f} "
                f"| {100 * growth:.1f}% | {circles[0]:.0f} / {circles[1]:.0f} |",
                flush=True,
            )
    print()
    print(f"OpenGL renderer: {renderer}")


if __name__ == "__main__":
    main()
