"""Benchmark: what the dashboard movie costs (issue: see a run).

Runs ``mabdi run`` in child processes on the table scene (Run 1) for
``--frames`` frames (300 by default; the helix circles the table twice
whatever the count), with and without ``--movie``, and reports frames/s,
the dashboard's ms per frame and each child's peak resident memory
(ru_maxrss).

    python benchmarks/bench_movie.py [--frames 300]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def run(frames: int, movie: bool, folder: Path) -> dict:
    out = folder / ("movie" if movie else "plain")
    command = [sys.executable, "-m", "mabdi.cli", "run", str(REPO / "scenes" / "table.toml"), "--frames", str(frames)]
    command += ["--out", str(out), "--quiet", "--no-eval"] + (["--movie"] if movie else [])
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    start = time.perf_counter()
    printed = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # the largest child so far (kB)
    summary = json.loads((out / "summary.json").read_text())
    dashboard = None
    for line in printed.splitlines():
        if line.startswith("movie:"):
            dashboard = float(line.split("dashboard ")[1].split(" ms")[0])
    return {
        "movie": movie,
        "frames_per_second": summary["frames_per_second"],
        "wall_s": seconds,
        "peak_rss_mb": peak / 1024.0,
        "peak_grew": peak > before,
        "dashboard_ms": dashboard,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        rows = [run(args.frames, False, Path(folder)), run(args.frames, True, Path(folder))]
    print("| run | frames/s | dashboard ms/frame | peak memory (MB) |\n|---|---:|---:|---:|")
    for row in rows:
        name = f"{args.frames} frames" + (" --movie" if row["movie"] else "")
        dashboard = f"{row['dashboard_ms']:.0f}" if row["dashboard_ms"] else "-"
        print(f"| {name} | {row['frames_per_second']:.1f} | {dashboard} | {row['peak_rss_mb']:.0f} |")


if __name__ == "__main__":
    main()
