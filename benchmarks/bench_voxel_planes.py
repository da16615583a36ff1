"""Benchmark: voxel planes (seed 000 §V) against marching cubes and point triangulations, on our scans.

Data: noisy (Kinect model) depth images of the bunnies scene (Run 2) from
poses along its helix, back-projected into one cloud with each point's
sensor position. The seed's thermolab/thermogauss scans are not available
offline; our cloud has the same character (a few overlapping range scans of
planar and curved surfaces).

Measured, as the seed does:

* **speed**: wall time to build the surface from N points, N from 25k to
  800k: voxel planes (statistics + every block meshed from scratch), and
  marching cubes as the seed ran it (an unsigned distance field from the
  points, ``vtkUnsignedDistance``, iso-surface at half a voxel with
  ``vtkFlyingEdges3D``: a double-sided surface) and as a stronger baseline
  (a signed field from oriented points, ``vtkPCANormalEstimation`` normals
  turned towards each point's sensor, ``vtkSignedDistance``, iso 0);
* **error**: cross-validation, 90% of the points build the surface, the mean
  distance of the other 10% to it;
* **size** by the seed's accounting (4-byte floats and ints): 10 floats per
  occupied voxel for voxel planes, 1 float per grid voxel for marching
  cubes, 3 floats per point + 3 ints per triangle for a point triangulation:
  Open3D's ball pivoting stands in for PCL's greedy projection, and Poisson
  joins (both need the ``[compare]`` extra);
* **error against size** over several voxel sizes (point counts for the
  triangulations).

Writes docs/figures/voxel_planes_speed.png, voxel_planes_error_size.png and
benchmarks/results/voxel_planes.json; prints markdown tables.

    python benchmarks/bench_voxel_planes.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import numpy as np  # noqa: E402
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy  # noqa: E402
from vtkmodules.vtkCommonCore import vtkPoints  # noqa: E402
from vtkmodules.vtkCommonDataModel import vtkPolyData  # noqa: E402
from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D  # noqa: E402
from vtkmodules.vtkFiltersPoints import vtkPCANormalEstimation, vtkSignedDistance, vtkUnsignedDistance  # noqa: E402

import mabdi  # noqa: E402
from mabdi.camera import backproject  # noqa: E402
from mabdi.evaluate import distances_to_mesh  # noqa: E402
from mabdi.evaluate.bench import machine_info  # noqa: E402
from mabdi.surfaces.voxel_planes import FilterVoxelPlanes, VoxelPlanesParameters  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
FIGURES = REPO / "docs" / "figures"
RESULTS = REPO / "benchmarks" / "results"


def scans(frames: int = 12):
    """(N, 3) noisy world points of ``frames`` Kinect-model depth images of Run 2, and their sensor positions."""
    config = mabdi.load_run_config(REPO / "scenes" / "bunnies.toml")
    config.sensor.noise = "kinect"
    scene = mabdi.SourceScene(config.scene, frames=config.run.frames)
    sensor = mabdi.FilterDepthImage(noise="kinect", seed=7)
    sensor.SetInputConnection(scene.GetOutputPort())
    poses = mabdi.simulate.path_from_config(config.run.frames, config.path)
    points, origins = [], []
    for i in np.linspace(0, len(poses) - 1, frames).astype(int):
        sensor.pose = poses[i]
        sensor.frame = int(i)
        sensor.Update()
        depth = mabdi.depth.depth_array(sensor.GetOutput())
        world = backproject(depth, sensor.intrinsics, poses[i])
        points.append(world)
        origins.append(np.broadcast_to(poses[i][:3, 3], world.shape))
    return np.concatenate(points), np.concatenate(origins)


def polydata_of_points(points: np.ndarray, normals: np.ndarray | None = None) -> vtkPolyData:
    data = vtkPolyData()
    vtk_points = vtkPoints()
    vtk_points.SetData(numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float32), deep=True))
    data.SetPoints(vtk_points)
    if normals is not None:
        array = numpy_to_vtk(np.ascontiguousarray(normals, dtype=np.float32), deep=True)
        array.SetName("Normals")
        data.GetPointData().SetNormals(array)
    return data


def grid_dimensions(points: np.ndarray, voxel: float) -> tuple[list[float], list[int]]:
    low = points.min(axis=0) - 2 * voxel
    high = points.max(axis=0) + 2 * voxel
    dims = np.ceil((high - low) / voxel).astype(int) + 1
    return [float(low[0]), float(high[0]), float(low[1]), float(high[1]), float(low[2]), float(high[2])], dims.tolist()


def voxel_planes(points: np.ndarray, voxel: float, window: int = 2):
    surface = FilterVoxelPlanes(VoxelPlanesParameters(voxel_size=voxel, window=window, block_size=voxel * round(1.0 / voxel)))
    start = time.perf_counter()
    surface.add_points(points)
    mesh = surface.mesh()
    seconds = time.perf_counter() - start
    occupied = len(surface.map.occupied_voxels())
    return mesh, seconds, 10 * 4 * occupied


def marching_cubes_unsigned(points: np.ndarray, voxel: float):
    start = time.perf_counter()
    bounds, dims = grid_dimensions(points, voxel)
    distance = vtkUnsignedDistance()
    distance.SetInputData(polydata_of_points(points))
    distance.SetBounds(bounds)
    distance.SetDimensions(dims)
    distance.SetRadius(3 * voxel)
    distance.CappingOn()
    distance.SetCapValue(3 * voxel)
    surface = vtkFlyingEdges3D()
    surface.SetInputConnection(distance.GetOutputPort())
    surface.SetValue(0, 0.5 * voxel)
    surface.ComputeNormalsOff()
    surface.Update()
    mesh = vtkPolyData()
    mesh.ShallowCopy(surface.GetOutput())
    return mesh, time.perf_counter() - start, 4 * int(np.prod(dims))


def oriented_normals(points: np.ndarray, origins: np.ndarray, k: int = 20) -> np.ndarray:
    estimate = vtkPCANormalEstimation()
    estimate.SetInputData(polydata_of_points(points))
    estimate.SetSampleSize(k)
    estimate.SetNormalOrientationToPoint()
    estimate.SetOrientationPoint(0.0, 0.0, 0.0)
    estimate.Update()
    normals = vtk_to_numpy(estimate.GetOutput().GetPointData().GetNormals()).astype(np.float64)
    facing = np.einsum("ij,ij->i", normals, origins - points) < 0
    normals[facing] *= -1.0
    return normals


def marching_cubes_signed(points: np.ndarray, origins: np.ndarray, voxel: float):
    start = time.perf_counter()
    normals = oriented_normals(points, origins)
    bounds, dims = grid_dimensions(points, voxel)
    distance = vtkSignedDistance()
    distance.SetInputData(polydata_of_points(points, normals))
    distance.SetBounds(bounds)
    distance.SetDimensions(dims)
    distance.SetRadius(3 * voxel)
    surface = vtkFlyingEdges3D()
    surface.SetInputConnection(distance.GetOutputPort())
    surface.SetValue(0, 0.0)
    surface.ComputeNormalsOff()
    surface.Update()
    mesh = vtkPolyData()
    mesh.ShallowCopy(surface.GetOutput())
    return mesh, time.perf_counter() - start, 4 * int(np.prod(dims))


def open3d_cloud(points, origins):
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.normals = o3d.utility.Vector3dVector(oriented_normals(points, origins))
    return cloud


def ball_pivoting(points, origins, spacing):
    import open3d as o3d

    start = time.perf_counter()
    cloud = open3d_cloud(points, origins)
    radii = o3d.utility.DoubleVector([spacing, 2 * spacing, 4 * spacing])
    result = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(cloud, radii)
    seconds = time.perf_counter() - start
    return triangle_mesh_polydata(result), seconds


def poisson(points, origins, depth=8):
    import open3d as o3d

    start = time.perf_counter()
    cloud = open3d_cloud(points, origins)
    result, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=depth)
    seconds = time.perf_counter() - start
    return triangle_mesh_polydata(result), seconds


def triangle_mesh_polydata(result) -> vtkPolyData:
    from mabdi.polydata import triangles_polydata

    return triangles_polydata(np.asarray(result.vertices), np.asarray(result.triangles))


def triangulation_bytes(mesh: vtkPolyData) -> int:
    return 4 * (3 * mesh.GetNumberOfPoints() + 3 * mesh.GetNumberOfCells())


def cross_validation_error(mesh: vtkPolyData, test_points: np.ndarray) -> float:
    if mesh.GetNumberOfCells() == 0:
        return float("nan")
    return float(np.mean(distances_to_mesh(test_points, mesh)))


def plot(series, path, x_label, y_label, title, log=True):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(7, 4.5), dpi=110)
    for label, (x, y) in series.items():
        axes.plot(x, y, marker="o", label=label)
    if log:
        axes.set_xscale("log")
        axes.set_yscale("log")
    axes.set_xlabel(x_label)
    axes.set_ylabel(y_label)
    axes.set_title(title)
    axes.grid(True, which="both", alpha=0.3)
    axes.legend()
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer sizes (a smoke run)")
    args = parser.parse_args()
    rng = np.random.default_rng(20261122)
    points, origins = scans(6 if args.quick else 12)
    order = rng.permutation(len(points))
    points, origins = points[order], origins[order]
    print(f"cloud: {len(points):,} points from noisy Kinect-model scans of the bunnies scene")
    results = {"machine": machine_info(), "points": len(points)}

    # speed against the number of points, at 5 cm voxels
    sizes = [25_000, 100_000, 400_000] if args.quick else [25_000, 50_000, 100_000, 200_000, 400_000, 800_000]
    speed = {"voxel planes": [], "marching cubes (unsigned)": [], "marching cubes (signed)": []}
    for n in sizes:
        subset, subset_origins = points[:n], origins[:n]
        speed["voxel planes"].append(min(voxel_planes(subset, 0.05)[1] for _ in range(2)))
        speed["marching cubes (unsigned)"].append(marching_cubes_unsigned(subset, 0.05)[1])
        speed["marching cubes (signed)"].append(marching_cubes_signed(subset, subset_origins, 0.05)[1])
    results["speed"] = {"points": sizes, "seconds": speed}
    print("\n| points | voxel planes (s) | MC unsigned (s) | MC signed (s) | MC unsigned / VP | MC signed / VP |")
    print("|---|---|---|---|---|---|")
    for i, n in enumerate(sizes):
        vp, mu, ms = (speed[k][i] for k in speed)
        print(f"| {n:,} | {vp:.3f} | {mu:.3f} | {ms:.3f} | {mu / vp:.1f}x | {ms / vp:.1f}x |")
    plot(
        {k: (sizes, v) for k, v in speed.items()},
        FIGURES / "voxel_planes_speed.png",
        "points",
        "seconds",
        "Surface from N points (bunnies scene, Kinect noise, 5 cm voxels)",
    )

    # cross-validation error and representation size against voxel size
    n = 200_000 if args.quick else 400_000
    build, build_origins, test = points[: int(0.9 * n)], origins[: int(0.9 * n)], points[int(0.9 * n) : n]
    voxels = (0.1, 0.05, 0.03) if args.quick else (0.2, 0.1, 0.07, 0.05, 0.03, 0.02)
    table = []
    for voxel in voxels:
        for name, make in (
            ("voxel planes", lambda v: voxel_planes(build, v)),
            ("voxel planes, window 4", lambda v: voxel_planes(build, v, window=4)),
            ("marching cubes (unsigned)", lambda v: marching_cubes_unsigned(build, v)),
            ("marching cubes (signed)", lambda v: marching_cubes_signed(build, build_origins, v)),
        ):
            if name.endswith("window 4") and voxel > 0.05:
                continue
            mesh, seconds, size = make(voxel)
            table.append(
                {"method": name, "voxel": voxel, "bytes": size, "error": cross_validation_error(mesh, test), "seconds": seconds, "triangles": mesh.GetNumberOfCells()}
            )
    try:
        import open3d  # noqa: F401

        for keep in ((20_000, 50_000) if args.quick else (10_000, 25_000, 50_000, 100_000)):
            sample, sample_origins = build[:keep], build_origins[:keep]
            spacing = float(np.sqrt(4.0 / keep)) * 1.5  # about 4 m^2 of surface in the scene
            mesh, seconds = ball_pivoting(sample, sample_origins, spacing)
            table.append({"method": "ball pivoting", "points": keep, "bytes": triangulation_bytes(mesh), "error": cross_validation_error(mesh, test), "seconds": seconds, "triangles": mesh.GetNumberOfCells()})
        for depth in (6, 7, 8) if args.quick else (6, 7, 8, 9):
            mesh, seconds = poisson(build[:100_000], build_origins[:100_000], depth)
            table.append({"method": "poisson", "depth": depth, "bytes": triangulation_bytes(mesh), "error": cross_validation_error(mesh, test), "seconds": seconds, "triangles": mesh.GetNumberOfCells()})
    except ImportError:
        print("open3d not installed: ball pivoting and Poisson skipped (pip install -e '.[compare]')")
    results["error_size"] = table
    print("\n| method | setting | size (KB) | CV error (mm) | triangles | seconds |")
    print("|---|---|---|---|---|---|")
    for row in table:
        setting = f"{row['voxel'] * 100:g} cm voxels" if "voxel" in row else (f"{row['points']:,} points" if "points" in row else f"depth {row['depth']}")
        print(f"| {row['method']} | {setting} | {row['bytes'] / 1024:,.0f} | {1000 * row['error']:.2f} | {row['triangles']:,} | {row['seconds']:.2f} |")
    series = {}
    for row in table:
        series.setdefault(row["method"], ([], []))
        series[row["method"]][0].append(row["bytes"] / 1024)
        series[row["method"]][1].append(1000 * row["error"])
    plot(series, FIGURES / "voxel_planes_error_size.png", "representation size (KB)", "cross-validation error (mm)", "Error against size (lower left is better)")
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "voxel_planes.json").write_text(json.dumps(results, indent=1, default=float))
    print(f"\nmachine: {results['machine']}")


if __name__ == "__main__":
    main()
