"""Benchmark: mesh maps at robot scale (seed 003): HDF5 save/load, cost layers, planners, picking.

Synthetic terrain (a regular triangulation of a gently bumpy 20 m square with
box-shaped lethal obstacles), so sizes are exact:

* save and load of a 1M-triangle map with three layers, both HDF5 layouts,
  beside binary PLY (time and bytes);
* the cost layers on a 1M-vertex map;
* Dijkstra and fast marching across the 1M-vertex map (corner to corner);
* picking: rays from above onto the 1M-triangle map, after the locator is built.

    python benchmarks/bench_maps.py
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import numpy as np  # noqa: E402

from mabdi.evaluate.bench import machine_info  # noqa: E402
from mabdi.io.hdf5 import read_map, write_map  # noqa: E402
from mabdi.io.vtk_files import write_mesh_file  # noqa: E402
from mabdi.mesh_maps.layers import cost_layers  # noqa: E402
from mabdi.mesh_maps.mesh_map import MeshMap  # noqa: E402
from mabdi.mesh_maps.picking import MapPicker  # noqa: E402
from mabdi.mesh_maps.planning import plan  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_maps import grid  # noqa: E402


def terrain(vertices_per_side: int, size: float = 20.0) -> MeshMap:
    spacing = size / (vertices_per_side - 1)
    return grid(size, size, spacing, z=lambda x, y: 0.05 * np.sin(x / 1.3) * np.cos(y / 0.9))


def timed(function, repeat: int = 3):
    best, value = float("inf"), None
    for _ in range(repeat):
        start = time.perf_counter()
        value = function()
        best = min(best, time.perf_counter() - start)
    return best, value


def main():
    print(f"machine: {machine_info()}")
    rows = []
    # 1M triangles: 708 x 708 vertices -> 2 * 707^2 = 999,698 triangles
    small = terrain(708)
    rng = np.random.default_rng(0)
    for name in ("roughness", "height_difference", "cost"):
        small.vertex_layers[name] = rng.uniform(0, 1, small.number_of_vertices).astype(np.float32)
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        for layout in ("mesh_tools", "lvr2"):
            path = folder / f"map_{layout}.h5"
            save, _ = timed(lambda path=path, layout=layout: write_map(small, path, layout))
            load, _ = timed(lambda path=path: read_map(path))
            rows.append((f"save {layout} .h5 ({small.number_of_faces:,} triangles, 3 layers)", save, path.stat().st_size))
            rows.append((f"load {layout} .h5", load, None))
        ply = folder / "map.ply"
        polydata = small.to_polydata()
        save_ply, _ = timed(lambda: write_mesh_file(polydata, ply))
        rows.append(("save binary PLY (geometry only, for size)", save_ply, ply.stat().st_size))

    big = terrain(1000)  # 1,000,000 vertices, 1,996,002 triangles
    obstacles = np.zeros(big.number_of_vertices, dtype=bool)
    for cx, cy in ((-4, -3), (0, 2), (5, -1), (3, 6), (-6, 5)):
        obstacles |= (np.abs(big.vertices[:, 0] - cx) < 1.0) & (np.abs(big.vertices[:, 1] - cy) < 0.6)
    layers_time, layers = timed(lambda: cost_layers(big), repeat=1)
    rows.append((f"cost layers ({big.number_of_vertices:,} vertices)", layers_time, None))
    big.vertex_layers.update(layers)
    big.vertex_layers["lethal"] = np.maximum(layers["lethal"], obstacles.astype(np.float32))
    for planner in ("dijkstra", "fmm"):
        seconds, result = timed(lambda planner=planner: plan(big, [-9.5, -9.5, 0], [9.5, 9.5, 0], planner, weld=0.0), repeat=1)
        rows.append((f"{planner} corner to corner ({big.number_of_vertices:,} vertices), length {result.length:.2f} m", seconds, None))
    picker_time, picker = timed(lambda: MapPicker(small), repeat=1)
    rows.append((f"picking: build the locator ({small.number_of_faces:,} triangles)", picker_time, None))
    origins = np.column_stack([rng.uniform(-9.9, 9.9, (1000, 2)), np.full(1000, 5.0)])
    start = time.perf_counter()
    hits = sum(picker.pick(o, [0.1, 0.05, -1.0]) is not None for o in origins)
    per_ray = (time.perf_counter() - start) / len(origins)
    rows.append((f"picking: one ray ({hits}/1000 hit)", per_ray, None))

    print("\n| operation | time | size |\n|---|---:|---:|")
    for name, seconds, size in rows:
        shown = f"{seconds * 1000:.3f} ms" if seconds < 0.01 else f"{seconds:.2f} s"
        print(f"| {name} | {shown} | {'' if size is None else f'{size / 2**20:.1f} MB'} |")


if __name__ == "__main__":
    main()
