"""The simulation runner: a run config in, a map and its per-frame records out.

``Simulation(config)`` builds the MABDI loop of seed 001 Fig. 3-4 from the
filters, connected as a VTK pipeline:

    SourceScene (frame i) --> FilterDepthImage (pose i, noise) ----------> D --+
    FilterWorldMesh.map  --> FilterDepthImage (pose i, no noise) --------> E --+--> FilterClassifier
         ^                                                                              |
         +---------- FilterWorldMesh <-- surface filter (pixel_grid) <-----------------+

E is rendered from the map as it stood after the previous frame: the
expected-image filter reads the world mesh's live map, and the world mesh
appends frame i's surface only at the end of frame i. With the classifier
off (the "black box") the surface filter meshes D itself: every valid pixel,
every frame.

``run(out_dir)`` steps through the path and returns a :class:`RunResult`;
with an output folder it writes (each file to a temporary name, then renamed):

* ``config.toml``: the resolved config (every default filled in);
* ``world_mesh.vtp`` (cell data ``frame``) and ``world_mesh.ply`` (binary);
* ``metrics.csv``: one row per frame, columns :data:`METRICS_COLUMNS`;
* ``summary.json``: totals, timings, the machine's render backend;
* ``elements.png``: triangles in the map per frame (seed 001 Fig. 7);
* ``poses.npy``, ``path.vtp`` and ``scene.vtp`` (the ground truth at the last frame);
* with ``output.depth_images``: ``depth/D_000000.vti``, ``E_...``, ``labels_...``.
"""

from __future__ import annotations

import csv
import io
import json
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.algorithm import raise_pipeline_errors
from mabdi.config import SURFACES, RunConfig, dump_toml
from mabdi.errors import MabdiError
from mabdi.filters.classifier import ClassifierParameters, FilterClassifier
from mabdi.filters.depth_image import FilterDepthImage, SensorNoise
from mabdi.filters.depth_to_surface import FilterDepthImageToSurface
from mabdi.filters.quadtree import FilterQuadTree, QuadTreeParameters
from mabdi.filters.voxel_planes import FilterVoxelPlanes, VoxelPlanesParameters
from mabdi.filters.world_mesh import FilterWorldMesh
from mabdi.io.atomic import atomic_output, write_text
from mabdi.io.hdf5 import write_map
from mabdi.io.plots import write_elements_plot
from mabdi.io.vtk_files import write_image, write_mesh_file, write_polydata
from mabdi.maps.colours import colours_by_normal
from mabdi.maps.labels import label_floor, planar_clusters
from mabdi.maps.layers import add_cost_layers
from mabdi.maps.mesh_map import MeshMap
from mabdi.polydata import polyline
from mabdi.simulate.path import path_from_config
from mabdi.sources.scene import SourceScene

#: The first columns of metrics.csv, in this order (counts are triangles; times in ms).
METRICS_COLUMNS = (
    "frame",
    "novel_fraction",
    "cells_added",
    "cells_total",
    "t_depth_ms",
    "t_expected_ms",
    "t_classify_ms",
    "t_surface_ms",
    "t_append_ms",
    "t_total_ms",
)


class OutputError(MabdiError, OSError):
    """A run's output folder or file cannot be written."""


@dataclass
class FrameRecord:
    """What one frame did. Counts of cells are triangles; ``cells_added`` is the map's net change."""

    frame: int
    novel_fraction: float
    cells_added: int
    cells_total: int
    t_depth_ms: float
    t_expected_ms: float
    t_classify_ms: float
    t_surface_ms: float
    t_append_ms: float
    t_total_ms: float
    points_total: int = 0
    valid_pixels: int = 0
    novel_pixels: int = 0
    speck_pixels: int = 0
    contradicted_pixels: int = 0


@dataclass
class RunResult:
    """A finished run: its config, one record per frame, the map (one merged vtkPolyData)."""

    config: RunConfig
    records: list[FrameRecord]
    mesh: vtkPolyData
    map_bytes: int
    seconds: float
    out_dir: Path | None = None
    backend: dict = field(default_factory=dict)

    @property
    def cells(self) -> np.ndarray:
        """Triangles in the map after each frame."""
        return np.array([r.cells_total for r in self.records])

    def summary(self) -> dict:
        """Totals for ``summary.json`` and the command line."""
        records = self.records
        n = max(len(records), 1)
        stages = ("t_depth_ms", "t_expected_ms", "t_classify_ms", "t_surface_ms", "t_append_ms", "t_total_ms")
        return {
            "name": self.config.run.name,
            "frames": len(records),
            "classifier": self.config.classifier.enabled,
            "surface": self.config.surface.method,
            "noise": self.config.sensor.noise,
            "seed": self.config.run.seed,
            "cells": int(self.mesh.GetNumberOfCells()),
            "points": int(self.mesh.GetNumberOfPoints()),
            "map_bytes": int(self.map_bytes),
            "seconds": self.seconds,
            "frames_per_second": len(records) / self.seconds if self.seconds > 0 else None,
            "mean_ms": {s: float(sum(getattr(r, s) for r in records) / n) for s in stages},
            "render": self.backend,
        }


class Simulation:
    """The MABDI loop along a run config's path (see the module docs)."""

    def __init__(self, config: RunConfig) -> None:
        self.config = config
        base_dir = config.source.parent if config.source is not None else None
        frames = config.run.frames
        sensor = config.sensor
        noise = SensorNoise.from_config(sensor)
        intrinsics = sensor.intrinsics()

        self.scene = SourceScene(config.scene, frames=frames, base_dir=base_dir)
        self.sensor = FilterDepthImage(intrinsics=intrinsics, noise=noise, seed=config.run.seed, backend=sensor.backend)
        self.sensor.SetInputConnection(self.scene.GetOutputPort())

        self.world = FilterWorldMesh()
        self.expected = FilterDepthImage(intrinsics=intrinsics, noise="none", backend=sensor.backend)
        self.expected.SetInputDataObject(self.world.map)

        c = config.classifier
        self.classifier = FilterClassifier(
            ClassifierParameters(c.tau_min, c.k_sigma, c.min_width, c.min_region, c.rim), noise=noise
        )
        self.classifier.SetInputConnection(0, self.sensor.GetOutputPort())
        self.classifier.SetInputConnection(1, self.expected.GetOutputPort())

        self.surface = make_surface_filter(config, noise)
        source = self.classifier if c.enabled else self.sensor
        self.surface.SetInputConnection(source.GetOutputPort())
        self.world.SetInputConnection(self.surface.GetOutputPort())

        self.poses = path_from_config(frames, config.path)
        self._algorithms = (self.scene, self.sensor, self.expected, self.classifier, self.surface, self.world)

    def step(self, i: int) -> FrameRecord:
        """Run frame ``i``: measure D, render E, classify, mesh, append. Times each stage."""
        pose = self.poses[i]
        start = time.perf_counter()
        self.scene.set_frame(i)
        self.sensor.pose = pose
        self.sensor.frame = i
        self.sensor.Update()
        t_depth = time.perf_counter()
        t_expected = t_classify = t_depth
        if self.config.classifier.enabled:
            self.expected.pose = pose
            self.expected.frame = i
            self.expected.Update()
            t_expected = time.perf_counter()
            self.classifier.Update()
            t_classify = time.perf_counter()
        self.surface.Update()
        t_surface = time.perf_counter()
        self.world.Update()
        t_append = time.perf_counter()
        raise_pipeline_errors(*self._algorithms)

        if self.config.classifier.enabled:
            counts = self.classifier.counts
        else:
            valid = int(np.count_nonzero(np.isfinite(self._sensor_depth())))
            counts = {"valid": valid, "novel": valid, "specks": 0, "contradicted": 0}
        ms = 1000.0
        return FrameRecord(
            frame=i,
            novel_fraction=counts["novel"] / counts["valid"] if counts["valid"] else 0.0,
            cells_added=self.world.cells_added,
            cells_total=self.world.number_of_cells,
            t_depth_ms=ms * (t_depth - start),
            t_expected_ms=ms * (t_expected - t_depth),
            t_classify_ms=ms * (t_classify - t_expected),
            t_surface_ms=ms * (t_surface - t_classify),
            t_append_ms=ms * (t_append - t_surface),
            t_total_ms=ms * (t_append - start),
            points_total=self.world.number_of_points,
            valid_pixels=counts["valid"],
            novel_pixels=counts["novel"],
            speck_pixels=counts["specks"],
            contradicted_pixels=counts["contradicted"],
        )

    def _sensor_depth(self) -> np.ndarray:
        from mabdi.depth import depth_array

        return depth_array(self.sensor.GetOutput())

    def run(self, out_dir=None, progress=None) -> RunResult:
        """Run every frame; write the outputs of the module docs when ``out_dir`` is given.

        ``progress(record)`` is called after each frame.
        """
        out = prepare_output_dir(out_dir) if out_dir is not None else None
        if out is not None:
            write_text(out / "config.toml", dump_toml(self.config))
        self.world.reset()
        records = []
        start = time.perf_counter()
        for i in range(len(self.poses)):
            records.append(self.step(i))
            if out is not None and self.config.output.depth_images:
                self._write_depth_images(out, i)
            if progress is not None:
                progress(records[-1])
        seconds = time.perf_counter() - start
        result = RunResult(
            config=self.config,
            records=records,
            mesh=self.world.mesh(),
            map_bytes=self.world.memory_bytes(),
            seconds=seconds,
            out_dir=out,
            backend=render_backend(self.sensor),
        )
        if out is not None:
            write_run_outputs(result, self)
        return result

    def _write_depth_images(self, out: Path, i: int) -> None:
        folder = out / "depth"
        folder.mkdir(exist_ok=True)
        write_image(self.sensor.GetOutput(), folder / f"D_{i:06d}.vti")
        if self.config.classifier.enabled:
            write_image(self.expected.GetOutput(), folder / f"E_{i:06d}.vti")
            write_image(self.classifier.GetOutput(), folder / f"labels_{i:06d}.vti")


def make_surface_filter(config: RunConfig, noise: SensorNoise | None = None):
    """The surface filter named by ``config.surface.method`` (``noise``: the sensor's, for thresholds)."""
    surface = config.surface
    if surface.method == "pixel_grid":
        return FilterDepthImageToSurface(max_jump=surface.max_jump)
    if surface.method == "quadtree":
        return FilterQuadTree(
            QuadTreeParameters(
                n_t=surface.n_t, d_t=surface.d_t, reduction=surface.reduction, max_jump=surface.max_jump, triangles=True
            ),
            noise=noise or "none",
        )
    if surface.method == "voxel_planes":
        return FilterVoxelPlanes(
            VoxelPlanesParameters(
                voxel_size=surface.voxel_size,
                epsilon=surface.epsilon,
                window=surface.window,
                min_points=surface.min_points,
            )
        )
    raise MabdiError(f"unknown surface filter {surface.method!r} (known: {', '.join(SURFACES)})")


def prepare_output_dir(out_dir) -> Path:
    """Create the output folder or raise :class:`OutputError` saying why it cannot be."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        blocker = next((p for p in [out, *out.parents] if p.exists() and not p.is_dir()), out)
        raise OutputError(f"cannot create output folder {out}: {blocker} is a file, not a folder") from None
    except OSError as exc:
        raise OutputError(f"cannot create output folder {out}: {exc.strerror}") from None
    probe = out / ".mabdi-write-test"
    try:
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise OutputError(f"cannot write into output folder {out}: {exc.strerror}") from None
    return out


def render_backend(sensor: FilterDepthImage) -> dict:
    """The render backend that drew the frames: the window class and OpenGL renderer string."""
    window = sensor.renderer.window
    if window is None:
        return {"backend": sensor.renderer.backend}
    renderer = "?"
    for line in window.ReportCapabilities().splitlines():
        if "renderer string" in line:
            renderer = line.split(":", 1)[1].strip()
            break
    return {"backend": sensor.renderer.backend, "window": window.GetClassName(), "gl_renderer": renderer}


def metrics_csv(records: list[FrameRecord]) -> str:
    """metrics.csv text: the :data:`METRICS_COLUMNS` first, then the remaining record fields."""
    names = [f.name for f in fields(FrameRecord)]
    columns = list(METRICS_COLUMNS) + [n for n in names if n not in METRICS_COLUMNS]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for record in records:
        values = asdict(record)
        writer.writerow([f"{values[c]:.3f}" if isinstance(values[c], float) else values[c] for c in columns])
    return buffer.getvalue()


def annotated_map(mesh: vtkPolyData, poses: np.ndarray, intrinsics) -> MeshMap:
    """The run's map as a MeshMap with cost layers, colours by normal, a floor label and planar clusters."""
    mesh_map = MeshMap.from_polydata(mesh)
    mesh_map.vertex_layers = {}  # the merged mesh's point data is not a map layer
    mesh_map.face_layers = {k: v for k, v in mesh_map.face_layers.items() if k == "frame"}
    if mesh_map.number_of_faces:
        add_cost_layers(mesh_map)
        mesh_map.vertex_layers["rgb_colors"] = colours_by_normal(mesh_map.vertex_layers["normals"])
        label_floor(mesh_map)
        planar_clusters(mesh_map, min_faces=10)
    mesh_map.poses = np.asarray(poses, dtype=np.float64)
    mesh_map.intrinsics = intrinsics.to_array()
    return mesh_map


def write_run_outputs(result: RunResult, simulation: Simulation) -> None:
    """Write a finished run's files into ``result.out_dir`` (each atomically)."""
    out = result.out_dir
    config = result.config
    if config.output.vtp:
        write_mesh_file(result.mesh, out / "world_mesh.vtp")
    if config.output.ply:
        write_mesh_file(result.mesh, out / "world_mesh.ply")
    if config.output.h5:
        write_map(annotated_map(result.mesh, simulation.poses, config.sensor.intrinsics()), out / "world_mesh.h5")
    write_text(out / "metrics.csv", metrics_csv(result.records))
    write_text(out / "summary.json", json.dumps(result.summary(), indent=2) + "\n")
    frames = np.array([r.frame for r in result.records])
    label = "mabdi" if config.classifier.enabled else "black box"
    write_elements_plot({label: (frames, result.cells)}, out / "elements.png", title=config.run.name)
    with atomic_output(out / "poses.npy") as temporary:
        np.save(temporary, simulation.poses)
    write_polydata(polyline(simulation.poses[:, :3, 3]), out / "path.vtp")
    write_polydata(simulation.scene.mesh_at(len(simulation.poses) - 1), out / "scene.vtp")
