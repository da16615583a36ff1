"""Benchmark: FilterQuadTree on the table scene, against n_t (seed 002 Fig. 6) and beside the pixel grid.

For each n_t, over ten poses of Run 1 (noise-free, 640x480, reduction 3):
faces (triangles) per frame, ms per frame, and the accuracy of the faces
(distance of their centres to the scene: median and maximum). The pixel grid
on the same frames is the reference row. Writes docs/figures/quadtree_nt.png
(faces against n_t).

    python benchmarks/bench_quadtree.py
"""

from __future__ import annotations

import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import numpy as np  # noqa: E402
from vtkmodules.util.numpy_support import vtk_to_numpy  # noqa: E402

import mabdi  # noqa: E402
from mabdi.evaluate import distances_to_mesh  # noqa: E402
from mabdi.evaluate.bench import machine_info  # noqa: E402
from mabdi.surfaces.pixel_grid import FilterPixelGrid  # noqa: E402
from mabdi.surfaces.quadtree import FilterQuadTree, QuadTreeParameters  # noqa: E402
from mabdi.io.plots import write_line_plot  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
N_T = (0.0, 0.01, 0.02, 0.05, 0.1, 0.2, 0.4)


def measure(surface, sensor, poses, ground_truth):
    faces, times, distances = [], [], []
    surface.SetInputConnection(sensor.GetOutputPort())
    for pose in poses:
        sensor.pose = pose
        sensor.Update()
        start = time.perf_counter()
        surface.Update()
        times.append(1000.0 * (time.perf_counter() - start))
        mesh = surface.GetOutput()
        points = vtk_to_numpy(mesh.GetPoints().GetData()).astype(np.float64)
        triangles = vtk_to_numpy(mesh.GetPolys().GetConnectivityArray()).reshape(-1, 3)
        faces.append(len(triangles))
        distances.append(distances_to_mesh(points[triangles].mean(axis=1), ground_truth))
    d = np.concatenate(distances)
    return statistics.mean(faces), statistics.median(times), 1000 * float(np.median(d)), 1000 * float(d.max())


def main():
    config = mabdi.load_run_config(REPO / "scenes" / "table.toml")
    scene = mabdi.SourceScene(config.scene, frames=config.run.frames)
    sensor = mabdi.FilterDepthImage()
    sensor.SetInputConnection(scene.GetOutputPort())
    poses = mabdi.simulate.path_from_config(config.run.frames, config.path)[::3]
    truth = scene.mesh_at(0)
    info = machine_info()
    print(f"machine: {info['cpu']}, {info['cores']} cores, GPU {info['gpu']}; VTK {info['vtk']}")
    print()
    print("| surface | n_t | triangles per frame | ms per frame | face centre to scene: median / max (mm) |")
    print("|---|---:|---:|---:|---:|")
    rows = []
    for n_t in N_T:
        faces, ms, median, worst = measure(FilterQuadTree(QuadTreeParameters(n_t=n_t, triangles=True)), sensor, poses, truth)
        rows.append((n_t, faces))
        print(f"| quadtree | {n_t} | {faces:,.0f} | {ms:.1f} | {median:.2f} / {worst:.1f} |", flush=True)
    faces, ms, median, worst = measure(FilterPixelGrid(), sensor, poses, truth)
    print(f"| pixel grid | - | {faces:,.0f} | {ms:.1f} | {median:.2f} / {worst:.1f} |")
    n_t, counts = zip(*rows, strict=True)
    path = write_line_plot(
        {"quadtree": (np.array(n_t), np.array(counts))},
        REPO / "docs" / "figures" / "quadtree_nt.png",
        x_label="n_t",
        y_label="triangles per frame",
        title="table scene: faces against n_t (reduction 3)",
    )
    print(f"\nplot: {path}")


if __name__ == "__main__":
    main()
