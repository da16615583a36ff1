"""The RGB-D dataset layouts: milliseconds per ``read(i)`` of a 640x480 frame, depth alone and with colour; and
what colour costs the MABDI loop.

Reading: ~40 Kinect-like depth frames (``bench_sequences.kinect_like_frames``) with a colour image each (a
smooth shading per surface plus camera-like noise, so PNG and JPEG compress as photographs do), written in
each layout as the datasets ship them: TUM and 3DMatch colour as PNG; Redwood, ScanNet and Replica colour
as JPEG (quality 95); ScanNet's colour at its own 1296x968 with ``intrinsic_color.txt`` (sampled along each
depth ray when read). ``read(i)`` is timed over every frame (a few passes, shuffled), once with the colour
images hidden (depth alone) and once with them.

The loop: Run 1 (the table, pixel grid, quad-tree and voxel planes, ``kinect`` noise) with and without
colours on its objects, ms per frame by stage (the simulated sensor renders colour in the same pass as depth
and reads the colour buffer back; the surfaces colour their vertices, voxel planes through per-voxel colour
sums; and VoxelMap.add_points alone with and without colours).

    .venv/bin/python benchmarks/bench_datasets.py [--frames 40] [--passes 3] [--loop-frames 12] [--surfaces ...]
    .venv/bin/python benchmarks/bench_datasets.py --frames 0 --surfaces voxel_planes   # one surface's loop rows

Prints markdown tables for docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).parent))
from bench_sequences import kinect_like_frames, size_mb, time_reads  # noqa: E402

from mabdi.camera import Intrinsics  # noqa: E402
from mabdi.depth import DepthFrame  # noqa: E402
from mabdi.sources import write_3dmatch, write_redwood, write_replica, write_scannet, write_tum  # noqa: E402
from mabdi.sources.frames import FrameList  # noqa: E402
from mabdi.sources.image_sequence import camera_matrix_text  # noqa: E402
from mabdi.sources.sequences import open_sequence  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
#: Run 1's objects, each its own colour.
COLOURS = {
    "floor": [90, 140, 60], "table_top": [150, 100, 50], "leg_1": [40, 40, 200], "leg_2": [40, 200, 200],
    "leg_3": [200, 40, 200], "leg_4": [200, 200, 40], "cup_1": [220, 30, 30], "cup_2": [250, 250, 250],
}
SCANNET_COLOUR = dataclasses.replace(Intrinsics(), fx=1170.0, fy=1170.0, cx=648.0, cy=484.0, width=1296, height=968)


def with_colour(frames: list[DepthFrame], seed: int = 0) -> list[DepthFrame]:
    """The frames with a photograph-like colour image each: shading by depth and by pixel, camera noise."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:480, 0:640]
    out = []
    for frame in frames:
        z = np.nan_to_num(frame.depth, nan=0.0)
        base = np.stack([60 + 40 * z, 90 + 0.1 * u, 120 + 0.1 * v], axis=-1)
        colour = np.clip(base + rng.normal(0, 3, base.shape), 0, 255).astype(np.uint8)
        out.append(dataclasses.replace(frame, colour=colour))
    return out


def as_jpeg(files: list[Path], size: tuple[int, int] | None = None) -> None:
    """Re-save colour PNGs as JPEG (quality 95; resized to ``size`` when given), as the datasets ship them."""
    for file in files:
        with Image.open(file) as image:
            image = image.resize(size, Image.BILINEAR) if size is not None else image.copy()
        image.save(file.with_suffix(".jpg"), quality=95)
        file.unlink()


def write_layouts(source: FrameList, root: Path) -> dict[str, Path]:
    folders = {
        "TUM (PNG colour)": write_tum(source, root / "tum"),
        "3DMatch / 7-Scenes (PNG colour)": write_3dmatch(source, root / "3dmatch"),
        "Redwood / Open3D (JPEG colour)": write_redwood(source, root / "redwood"),
        "ScanNet (JPEG colour 1296x968)": write_scannet(source, root / "scannet"),
        "Replica NICE-SLAM (JPEG colour)": write_replica(source, root / "replica"),
    }
    as_jpeg(sorted((root / "redwood" / "color").glob("*.png")))
    as_jpeg(sorted((root / "replica" / "results").glob("frame*.png")))
    as_jpeg(sorted((root / "scannet" / "color").glob("*.png")), (SCANNET_COLOUR.width, SCANNET_COLOUR.height))
    (root / "scannet" / "intrinsic" / "intrinsic_color.txt").write_text(camera_matrix_text(SCANNET_COLOUR, 4))
    return folders


def hide_colour(folder: Path) -> Path:
    """A copy of ``folder`` without its colour images (the same depth): the depth-only case."""
    target = folder.with_name(folder.name + "_depth_only")
    shutil.copytree(folder, target)
    for pattern in ("rgb.txt", "rgb", "*.color.png", "color", "results/frame*"):
        for path in target.glob(pattern):
            shutil.rmtree(path) if path.is_dir() else path.unlink()
    return target


def bench_reading(frames: int, passes: int) -> None:
    root = Path(tempfile.mkdtemp(prefix="bench_datasets_"))
    source = FrameList(with_colour(kinect_like_frames(frames)), "kinect-like room, coloured")
    rng = np.random.default_rng(1)
    rows = []
    for name, folder in write_layouts(source, root).items():
        timings = []
        for path in (hide_colour(folder), folder):
            sequence = open_sequence(path)
            sequence.read(0)  # warm: first decode, file caches, compiled kernels
            timings.append(time_reads(sequence, passes, rng))
        rows.append((name, *(np.median(t) for t in timings), *(np.percentile(t, 95) for t in timings), size_mb(folder)))
    shutil.rmtree(root)
    print(f"\n{frames} frames 640x480, {passes} passes in shuffled order; {platform.processor() or platform.machine()}, "
          f"Python {platform.python_version()}\n")
    print("| layout | depth: median (ms) | with colour: median (ms) | depth: p95 | with colour: p95 | MB |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, depth, colour, depth95, colour95, mb in rows:
        print(f"| {name} | {depth:.2f} | {colour:.2f} | {depth95:.2f} | {colour95:.2f} | {mb:.1f} |")


def bench_loop(frames: int, repeats: int = 2, surfaces=("pixel_grid", "quadtree", "voxel_planes")) -> None:
    from mabdi.config import load_run_config, set_value
    from mabdi.loop import MappingRun

    text = (REPO / "scenes" / "table.toml").read_text()
    coloured = text
    for name, colour in COLOURS.items():
        coloured = coloured.replace(f'name = "{name}"\n', f'name = "{name}"\ncolour = {colour}\n')
    folder = Path(tempfile.mkdtemp(prefix="bench_colour_loop_"))
    (folder / "plain.toml").write_text(text)
    (folder / "coloured.toml").write_text(coloured)
    stages = ("t_depth_ms", "t_register_ms", "t_expected_ms", "t_classify_ms", "t_surface_ms", "t_append_ms", "t_total_ms")
    print(f"\nRun 1 (table), kinect noise, {frames} frames, 640x480; ms per frame by stage: the mean over frames 2..N of "
          f"each run, the lower of {repeats} runs done in turn with and without colour (the machine is shared)\n")
    print("| surface | colour | " + " | ".join(s[2:-3] for s in stages) + " | triangles |")
    print("|---|---|" + "---:|" * (len(stages) + 1))
    readback = []
    for surface in surfaces:
        best = {}
        for _ in range(repeats):
            for name in ("plain", "coloured"):
                config = load_run_config(folder / f"{name}.toml")
                set_value(config, "run.frames", frames)
                set_value(config, "sensor.noise", "kinect")
                set_value(config, "surface.method", surface)
                simulation = MappingRun(config)
                result = simulation.run()
                means = np.array([np.mean([getattr(r, s) for r in result.records[1:]]) for s in stages])
                best[name] = np.minimum(best[name], means) if name in best else means
                cells = result.mesh.GetNumberOfCells()
                if name == "coloured" and not readback:
                    rig = simulation.source
                    for _ in range(20):
                        start = time.perf_counter()
                        rig._read_colour()
                        readback.append(time.perf_counter() - start)
        for name in ("plain", "coloured"):
            print(f"| {surface} | {'yes' if name == 'coloured' else 'no'} | " + " | ".join(f"{m:.1f}" for m in best[name])
                  + f" | {cells:,} |")
    print(f"\nThe simulated sensor's colour read-back (640x480 RGB from the render window): median "
          f"{np.median(readback) * 1e3:.2f} ms per frame")
    shutil.rmtree(folder)


def bench_voxel_colour(repeats: int = 15) -> None:
    """VoxelMap.add_points with and without colours: a floor of 300k and of 20k points over 4 m x 4 m, added
    to a map that holds them already (its blocks allocated, as in a running loop); median of ``repeats``, the
    lower of two rounds."""
    from mabdi.voxels.voxel_map import VoxelMap

    rng = np.random.default_rng(0)
    print("\nVoxelMap.add_points (5 cm voxels, blocks allocated), ms: median of each round, the lower of 2\n")
    print("| points | no colour | with colour |")
    print("|---:|---:|---:|")
    for count in (300_000, 20_000):
        points = np.column_stack([rng.uniform(-2, 2, (count, 2)), rng.normal(0, 0.005, count)])
        colours = rng.integers(0, 256, (count, 3), dtype=np.uint8)
        best = {}
        for _ in range(2):
            for name, rgb in (("plain", None), ("colour", colours)):
                voxels = VoxelMap()
                voxels.add_points(points, rgb)
                times = []
                for _ in range(repeats):
                    start = time.perf_counter()
                    voxels.add_points(points, rgb)
                    times.append(time.perf_counter() - start)
                best[name] = min(best.get(name, np.inf), float(np.median(times)) * 1e3)
        print(f"| {count:,} | {best['plain']:.2f} | {best['colour']:.2f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--loop-frames", type=int, default=12)
    parser.add_argument("--surfaces", nargs="+", default=["pixel_grid", "quadtree", "voxel_planes"], help="surfaces of the loop table")
    args = parser.parse_args()
    if args.frames:  # --frames 0: the loop table only
        bench_reading(args.frames, args.passes)
    if args.loop_frames:
        bench_loop(args.loop_frames, surfaces=args.surfaces)
    if "voxel_planes" in args.surfaces:
        bench_voxel_colour()


if __name__ == "__main__":
    main()
