"""Reading recorded sequences: milliseconds per ``read(i)`` of a 640x480 frame, TUM folders and ROS 2 bags.

Writes ~60 synthetic frames (a room of tilted planes and a box seen from a
moving camera, depth quantised like a Kinect v1: disparity in 1/8 pixel steps,
noise growing with z^2, 3 % dropped pixels and a blind stripe, so PNG
compression works as on real recordings) as a TUM folder and as bags
(sqlite3 and MCAP, 32FC1 and 16UC1), then times ``read(i)`` over every frame
(a few passes, in shuffled order) and the opening (index) of each.

    .venv/bin/python benchmarks/bench_sequences.py [--frames 60] [--passes 3] [--out DIR]

Prints a markdown table: median and p95 ms per frame, open ms, MB on disk.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from mabdi.camera import Intrinsics, look_at
from mabdi.depth import DepthFrame
from mabdi.sources.frames import FrameList
from mabdi.sources.rosbag2 import Rosbag2Sequence, write_rosbag2
from mabdi.sources.tum import TumSequence, write_tum


def kinect_like_frames(count: int, seed: int = 0) -> list[DepthFrame]:
    """Depth of a floor, two walls and a box from a camera on a circle, with Kinect-v1-like quantisation and noise."""
    intrinsics = Intrinsics()
    rng = np.random.default_rng(seed)
    rays = intrinsics.rays().reshape(-1, 3)
    planes = [  # (normal, offset): n . x = d in the world (z up)
        (np.array([0.0, 0.0, 1.0]), 0.0),
        (np.array([1.0, 0.0, 0.0]), -2.5),
        (np.array([0.0, 1.0, 0.0]), -2.5),
        (np.array([0.0, 0.0, 1.0]), 0.6),  # the box top, clipped below
    ]
    frames = []
    for i in range(count):
        angle = 2 * np.pi * i / count
        pose = look_at([1.2 * np.cos(angle), 1.2 * np.sin(angle), 1.3], [-0.5, -0.5, 0.3])
        directions = rays @ pose[:3, :3].T
        best = np.full(len(rays), np.inf)
        for normal, offset in planes:
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (offset - pose[:3, 3] @ normal) / (directions @ normal)
            hit = pose[:3, 3] + t[:, None] * directions
            ok = t > 0
            if offset == 0.6:
                ok &= (np.abs(hit[:, 0]) < 0.4) & (np.abs(hit[:, 1]) < 0.4)
            best = np.where(ok & (t < best), t, best)
        depth = best.reshape(intrinsics.shape)  # rays have z = 1, so t is z-depth
        depth = depth + rng.normal(0.0, 0.0015, depth.shape) * depth**2
        k = 8 * 0.075 * 580.0  # 1/8 px disparity steps, 7.5 cm baseline, f = 580 px
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = k / np.round(k / depth)
        depth[(rng.random(depth.shape) < 0.03) | ~np.isfinite(depth) | (depth > 8.0)] = np.nan
        depth[:, :16] = np.nan
        frames.append(DepthFrame(depth.astype(np.float32), intrinsics, pose, i, 1_700_000_000.0 + i / 30.0))
    return frames


def size_mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 1e6


def time_reads(sequence, passes: int, rng) -> np.ndarray:
    times = []
    for _ in range(passes):
        for index in rng.permutation(len(sequence)):
            start = time.perf_counter()
            sequence.read(int(index))
            times.append(time.perf_counter() - start)
    return np.array(times) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None, help="folder for the sequences (default: a temporary one)")
    args = parser.parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="bench_sequences_"))
    source = FrameList(kinect_like_frames(args.frames), "kinect-like room")
    rng = np.random.default_rng(1)

    cases = [("TUM folder (16-bit PNG)", lambda p: write_tum(source, p), TumSequence)]
    for storage in ("sqlite3", "mcap"):
        for encoding in ("32FC1", "16UC1"):
            cases.append(
                (
                    f"ROS 2 bag {storage} {encoding}",
                    lambda p, s=storage, e=encoding: write_rosbag2(source, p, storage=s, encoding=e),
                    Rosbag2Sequence,
                )
            )
    rows = []
    for index, (name, write, reader) in enumerate(cases):
        path = root / f"case{index}"
        start = time.perf_counter()
        write(path)
        write_s = time.perf_counter() - start
        start = time.perf_counter()
        sequence = reader(path)
        open_ms = (time.perf_counter() - start) * 1e3
        sequence.read(0)  # warm (first decode, file caches)
        reads = time_reads(sequence, args.passes, rng)
        sequence.close()
        rows.append((name, np.median(reads), np.percentile(reads, 95), open_ms, write_s * 1e3 / len(source), size_mb(path)))

    print(f"{len(source)} frames 640x480, {args.passes} passes in shuffled order; {platform.processor() or platform.machine()}, "
          f"Python {platform.python_version()}\n")
    print("| sequence | read median (ms) | read p95 (ms) | open (ms) | write (ms/frame) | MB |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, median, p95, open_ms, write_ms, mb in rows:
        print(f"| {name} | {median:.2f} | {p95:.2f} | {open_ms:.0f} | {write_ms:.1f} | {mb:.1f} |")


if __name__ == "__main__":
    main()
