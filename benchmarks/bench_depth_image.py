"""Benchmark: FilterDepthImage per 640x480 frame against a bare VTK render + z-buffer read.

For each mesh (the table and bunnies scenes, and a 1M-triangle sphere for
reference) the same poses are rendered by

* bare VTK: one EGL render window, a vtkPolyDataMapper, camera set from the
  pose, ``Render()`` + ``GetZbufferData()`` into a reused vtkFloatArray;
* mabdi: ``FilterDepthImage.Update()`` (render, read-back, flip, z-buffer to
  metres, output image with field data), noise off;

alternating frame by frame, so both see the same machine state. Reports the
median ms per frame and the ratio. Then the noise models' own cost (on top
of the conversion) per frame.

    python benchmarks/bench_depth_image.py [--frames N] [--repeats R]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import numpy as np  # noqa: E402
import vtk  # noqa: E402
from vtkmodules.vtkFiltersSources import vtkSphereSource  # noqa: E402
from vtkmodules.vtkRenderingOpenGL2 import vtkEGLRenderWindow  # noqa: E402

import mabdi  # noqa: E402
from mabdi.camera import configure_vtk_camera, look_at  # noqa: E402
from mabdi.evaluate.bench import machine_info  # noqa: E402
from mabdi.render.depth_image import FilterDepthImage  # noqa: E402
from mabdi.sensor_noise import SensorNoise, noise_rng
from mabdi.simulate.path import path_from_config  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


class BareRender:
    """The peer: the least a VTK program does to get a z-buffer of a mesh."""

    def __init__(self, mesh, intrinsics):
        self.intrinsics = intrinsics
        self.window = vtkEGLRenderWindow()
        self.window.SetOffScreenRendering(1)
        self.window.SetMultiSamples(0)
        self.window.SetSize(intrinsics.width, intrinsics.height)
        self.renderer = vtk.vtkRenderer()
        self.window.AddRenderer(self.renderer)
        mapper = vtk.vtkPolyDataMapper()
        mapper.SetInputData(mesh)
        actor = vtk.vtkActor()
        actor.SetMapper(mapper)
        actor.GetProperty().LightingOff()  # as FilterDepthImage: depth needs no shading
        self.renderer.AddActor(actor)
        self.zbuffer = vtk.vtkFloatArray()

    def __call__(self, pose):
        configure_vtk_camera(self.renderer.GetActiveCamera(), self.intrinsics, pose)
        self.window.Render()
        w, h = self.intrinsics.width, self.intrinsics.height
        self.window.GetZbufferData(0, 0, w - 1, h - 1, self.zbuffer)
        return self.zbuffer


def machine() -> dict:
    """The machine (mabdi.evaluate.bench.machine_info) and the OpenGL renderer of an EGL window."""
    info = machine_info()
    probe = vtkEGLRenderWindow()
    probe.SetOffScreenRendering(1)
    probe.SetSize(8, 8)
    probe.Render()
    caps = probe.ReportCapabilities()
    info["gl_renderer"] = next((line.split(":", 1)[1].strip() for line in caps.splitlines() if "renderer string" in line), "?")
    probe.Finalize()
    return info


def scene_case(name: str, frames: int):
    config = mabdi.load_run_config(REPO / "scenes" / f"{name}.toml")
    scene = mabdi.SourceScene(config.scene, frames=config.run.frames)
    mesh = scene.mesh_at(config.run.frames - 1)
    return name, mesh, path_from_config(frames, config.path)


def sphere_case(frames: int):
    source = vtkSphereSource()
    source.SetRadius(0.8)
    source.SetCenter(0, 0, 0.8)
    source.SetThetaResolution(1001)
    source.SetPhiResolution(501)
    source.Update()
    poses = np.stack([look_at([2.5 * np.cos(a), 2.5 * np.sin(a), 1.5], [0, 0, 0.8]) for a in np.linspace(0, 2 * np.pi, frames)])
    return "sphere 1M", source.GetOutput(), poses


def bench_case(name, mesh, poses, repeats):
    intrinsics = mabdi.Intrinsics()
    bare = BareRender(mesh, intrinsics)
    sensor = FilterDepthImage(intrinsics=intrinsics)
    sensor.SetInputDataObject(mesh)
    for pose in poses[:3]:  # warm up: shader compilation, first upload
        bare(pose)
        sensor.pose = pose
        sensor.Update()
    bare_ms, ours_ms = [], []
    for _ in range(repeats):
        for pose in poses:
            t0 = time.perf_counter()
            bare(pose)
            t1 = time.perf_counter()
            sensor.pose = pose
            sensor.Update()
            t2 = time.perf_counter()
            bare_ms.append(1000 * (t1 - t0))
            ours_ms.append(1000 * (t2 - t1))
    b, o = statistics.median(bare_ms), statistics.median(ours_ms)
    return {"case": name, "triangles": mesh.GetNumberOfCells(), "bare_ms": b, "mabdi_ms": o, "ratio": o / b}


def bench_noise(repeats: int = 50):
    intrinsics = mabdi.Intrinsics()
    rng = np.random.default_rng(0)
    zbuffer = rng.uniform(0.3, 0.95, size=intrinsics.shape).astype(np.float32)
    zbuffer[:, :100] = 1.0  # some background
    rows = []
    for model in ("none", "zbuffer", "kinect"):
        noise = SensorNoise(model)
        times = []
        for frame in range(repeats):
            t0 = time.perf_counter()
            generator = None if model == "none" else noise_rng(0, frame)
            noise.depth_from_zbuffer(zbuffer, intrinsics.near, intrinsics.far, generator)
            times.append(1000 * (time.perf_counter() - t0))
        rows.append({"model": model, "ms": statistics.median(times)})
    base = rows[0]["ms"]
    for row in rows:
        row["added_ms"] = row["ms"] - base
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, GPU {info['gpu']}; OpenGL: {info['gl_renderer']}; VTK {info['vtk']}")
    print()
    print("| mesh | triangles | bare VTK render + z-buffer read (ms) | FilterDepthImage (ms) | ratio |")
    print("|---|---:|---:|---:|---:|")
    for name, mesh, poses in (
        scene_case("table", args.frames),
        scene_case("bunnies", args.frames),
        sphere_case(args.frames),
    ):
        row = bench_case(name, mesh, poses, args.repeats)
        print(f"| {row['case']} | {row['triangles']:,} | {row['bare_ms']:.2f} | {row['mabdi_ms']:.2f} | {row['ratio']:.2f}x |")
    print()
    print("| noise model | z-buffer to metres incl. noise (ms) | added by the noise (ms) |")
    print("|---|---:|---:|")
    for row in bench_noise():
        print(f"| {row['model']} | {row['ms']:.2f} | {row['added_ms']:.2f} |")


if __name__ == "__main__":
    main()
