"""The simulation runner: a run config in, the sensor's depth images out.

``Simulation(config)`` builds the pipeline

    SourceScene (frame i) --> FilterDepthImage (pose i, noise stream i) --> D_i

and ``run(out_dir)`` renders every frame of the helical path and writes

* ``config.toml``: the resolved config (every default filled in);
* ``scene.vtp``: the ground-truth scene at the last frame (``object_id``);
* ``path.vtp``: the sensor positions as a polyline;
* ``poses.npy``: (N, 4, 4) world_from_camera poses;
* ``depth/000000.vti`` ...: the measured depth images D (field data included).

The MABDI loop (classifier, surface, world mesh) builds on :meth:`frames`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

from mabdi.algorithm import raise_pipeline_errors
from mabdi.config import RunConfig, dump_toml
from mabdi.filters.depth_image import FilterDepthImage, SensorNoise
from mabdi.io.atomic import atomic_output, write_text
from mabdi.io.vtk_files import write_image, write_polydata
from mabdi.simulate.path import path_from_config
from mabdi.sources.scene import SourceScene


def polyline(points: np.ndarray) -> vtkPolyData:
    """A vtkPolyData with one polyline through ``points`` (N, 3)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    mesh = vtkPolyData()
    vtk_points = vtkPoints()
    vtk_points.SetData(numpy_to_vtk(points, deep=True))
    mesh.SetPoints(vtk_points)
    lines = vtkCellArray()
    n = len(points)
    lines.SetData(
        numpy_to_vtkIdTypeArray(np.array([0, n], dtype=np.int64), deep=True),
        numpy_to_vtkIdTypeArray(np.arange(n, dtype=np.int64), deep=True),
    )
    mesh.SetLines(lines)
    return mesh


@dataclass
class RunSummary:
    """What a run did: frames rendered, wall time per stage (s), output folder."""

    frames: int
    out_dir: Path | None
    seconds: dict[str, float] = field(default_factory=dict)


class Simulation:
    """A run of the simulated sensor along its path (see the module docs)."""

    def __init__(self, config: RunConfig) -> None:
        self.config = config
        base_dir = config.source.parent if config.source is not None else None
        self.scene = SourceScene(config.scene, frames=config.run.frames, base_dir=base_dir)
        sensor = config.sensor
        self.sensor = FilterDepthImage(
            intrinsics=sensor.intrinsics(),
            noise=SensorNoise(sensor.noise, sensor.zbuffer_sigma, sensor.kinect_coefficient),
            seed=config.run.seed,
            backend=sensor.backend,
        )
        self.sensor.SetInputConnection(self.scene.GetOutputPort())
        self.poses = path_from_config(config.run.frames, config.path)

    def frames(self):
        """Yield ``(i, depth_image)`` for every frame; the image is the sensor's output object (copy to keep)."""
        for i, pose in enumerate(self.poses):
            self.scene.set_frame(i)
            self.sensor.pose = pose
            self.sensor.frame = i
            self.sensor.Update()
            raise_pipeline_errors(self.scene, self.sensor)
            yield i, self.sensor.GetOutput()

    def run(self, out_dir=None, progress=None) -> RunSummary:
        """Render every frame; write the outputs listed in the module docs when ``out_dir`` is given."""
        summary = RunSummary(frames=len(self.poses), out_dir=Path(out_dir) if out_dir else None)
        if summary.out_dir is not None:
            (summary.out_dir / "depth").mkdir(parents=True, exist_ok=True)
            write_text(summary.out_dir / "config.toml", dump_toml(self.config))
            with atomic_output(summary.out_dir / "poses.npy") as temporary:
                np.save(temporary, self.poses)
            write_polydata(polyline(self.poses[:, :3, 3]), summary.out_dir / "path.vtp")
        render = write = 0.0
        start = time.perf_counter()
        for i, image in self.frames():
            now = time.perf_counter()
            render += now - start
            if summary.out_dir is not None:
                write_image(image, summary.out_dir / "depth" / f"{i:06d}.vti")
            start = time.perf_counter()
            write += start - now
            if progress is not None:
                progress(i, image)
        if summary.out_dir is not None:
            write_polydata(self.scene.mesh_at(len(self.poses) - 1), summary.out_dir / "scene.vtp")
        summary.seconds = {"render": render, "write": write}
        return summary
