"""Registration under real poses and real cameras: what docs/benchmarks.md reports for #22.

Part 1, the ICP alone: Run 2's scene as a perfect map, D rendered from the true pose with z-buffer
noise, E from a pose off by jitter of 5 mm / 0.3 degrees per axis; pose error before and after, and
the cost per 640x480 frame (render of E and ICP apart).

Part 2, the loop: Run 2 (and the table with --table) on exact poses, jitter 2 mm / 0.15 and
5 mm / 0.3 degrees per axis, drift 1 cm and 0.5 degrees per sqrt(metre), and the structured-light
noise model; for each, the quad-tree with and without registration and Open3D's TSDF (1 and 2 cm,
the settings tuned on exact poses in docs/benchmarks.md: truncation 4 voxels, weight > 0.5,
half-pixel centres, depth smoothed as the surfaces smooth it: over the window the noise calls for) fed the same given poses. F@1cm, triangles, faces removed,
the registered frames and the registered poses' median error.

    python benchmarks/bench_registration.py [--table] [--quick] [--devices cpu cuda] [--no-loop] [--out runs/bench_registration.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

import mabdi  # noqa: F401  (selects the EGL window before VTK loads)
from mabdi.config import load_run_config, set_value
from mabdi.evaluate import evaluate_run
from mabdi.render.depth_image import DepthRenderer
from mabdi.sensor_noise import SensorNoise
from mabdi.stages.registration import IcpWorkspace, RegistrationParameters, register_depth, transform_size
from mabdi.loop import MappingRun
from mabdi.simulate.rig import SimulatedRig

REPO = Path(__file__).resolve().parents[1]

SCENARIOS = {
    "exact poses": {},
    "jitter 2 mm / 0.15 deg": {"sensor.pose_noise.jitter_translation": 0.002, "sensor.pose_noise.jitter_rotation": 0.15},
    "jitter 5 mm / 0.3 deg": {"sensor.pose_noise.jitter_translation": 0.005, "sensor.pose_noise.jitter_rotation": 0.3},
    "drift 1 cm / 0.5 deg per sqrt(m)": {"sensor.pose_noise.drift_translation": 0.01, "sensor.pose_noise.drift_rotation": 0.5},
    "structured light": {"sensor.noise": "structured_light"},
}


def icp_alone(frames: int = 16, device: str = "cpu") -> dict:
    config = load_run_config(REPO / "scenes" / "bunnies.toml")
    rig = SimulatedRig.from_config(config)
    mesh = rig.scene.mesh_at(0)
    renderer = DepthRenderer()
    noise = rig.sensor.noise
    rng = np.random.default_rng(0)
    before, after, render_ms, icp_ms = [], [], [], []
    workspace = IcpWorkspace()  # kept from frame to frame, as FilterRegistration keeps it
    for i in np.linspace(0, len(rig) - 1, frames).astype(int):
        frame = rig.read(int(i))
        true = frame.world_from_camera
        jitter = np.eye(4)
        jitter[:3, :3] = Rotation.from_rotvec(np.radians(rng.normal(0, 0.3, 3))).as_matrix()
        jitter[:3, 3] = rng.normal(0, 0.005, 3)
        given = true @ jitter
        start = time.perf_counter()
        zbuffer = renderer.render_zbuffer(mesh, frame.intrinsics, given)
        expected = SensorNoise().depth_from_zbuffer(zbuffer, frame.intrinsics.near, frame.intrinsics.far, None)
        middle = time.perf_counter()
        parameters = RegistrationParameters(device=device)
        result = register_depth(frame.depth, expected, frame.intrinsics, noise, parameters, workspace=workspace)
        end = time.perf_counter()
        render_ms.append(1000 * (middle - start))
        icp_ms.append(1000 * (end - middle))
        before.append(transform_size(np.linalg.inv(true) @ given))
        after.append(transform_size(np.linalg.inv(true) @ given @ result.transform))
    before, after = np.array(before), np.array(after)
    return {
        "device": device,
        "frames": frames,
        "before_median_mm": 1000 * float(np.median(before[:, 0])),
        "before_median_deg": float(np.median(before[:, 1])),
        "after_median_mm": 1000 * float(np.median(after[:, 0])),
        "after_median_deg": float(np.median(after[:, 1])),
        "icp_ms_median": float(np.median(icp_ms[1:])),  # the first call compiles nothing (cached) but warms up
        "render_ms_median": float(np.median(render_ms[1:])),
    }


def loop_row(scene: str, overrides: dict, registration: bool) -> dict:
    config = load_run_config(REPO / "scenes" / f"{scene}.toml")
    config.surface.method = "quadtree"
    for key, value in overrides.items():
        set_value(config, key, value)
    set_value(config, "registration.enabled", registration)
    simulation = MappingRun(config)
    start = time.perf_counter()
    result = simulation.run()
    seconds = time.perf_counter() - start
    metrics = evaluate_run(simulation, result).as_dict()
    true = simulation.true_poses
    trajectory = simulation.meshed_poses()
    errors = np.array([transform_size(np.linalg.inv(t) @ p) for t, p in zip(true, trajectory, strict=True)])
    records = result.records
    aligned_mm, aligned_deg = aligned_error(true, trajectory)
    return {
        "method": "mabdi quad-tree" + ("" if registration else ", no registration"),
        "fscore_1cm": metrics["fscore_1cm"],
        "triangles": int(result.mesh.GetNumberOfCells()),
        "removed": int(sum(r.cells_removed for r in records)),
        "removed_share": sum(r.cells_removed for r in records) / max(result.mesh.GetNumberOfCells(), 1),
        "registered": int(sum(r.registered for r in records)),
        "frames": len(records),
        "pose_error_mm": 1000 * float(np.median(errors[:, 0])),
        "pose_error_deg": float(np.median(errors[:, 1])),
        "aligned_error_mm": aligned_mm,
        "aligned_error_deg": aligned_deg,
        "register_ms": float(np.median([r.t_register_ms for r in records])),
        "growth_per_circle": metrics.get("growth_per_circle"),
        "seconds": seconds,
    }


def tsdf_rows(scene: str, overrides: dict) -> list[dict]:
    """Open3D's TSDF at 1 and 2 cm on the same frames and given poses (settings tuned on exact poses)."""
    from mabdi.evaluate.metrics import evaluate_map, observed_ground_truth, scenes_per_pose
    from mabdi.evaluate.tsdf import TsdfSettings, open3d_status, run_tsdf

    usable, reason = open3d_status()
    if not usable:
        return [{"method": "TSDF", "skipped": reason}]
    config = load_run_config(REPO / "scenes" / f"{scene}.toml")
    for key, value in overrides.items():
        set_value(config, key, value)
    rig = SimulatedRig.from_config(config)
    noise = config.sensor.sensor_noise()
    frames = len(rig)
    ground_truth = rig.scene.mesh_at(frames - 1)
    observed = observed_ground_truth(ground_truth, scenes_per_pose(rig.scene, frames), rig.true_poses, rig.intrinsics)
    rows = []
    for voxel in (0.01, 0.02):
        settings = TsdfSettings.tuned(voxel, noisy=noise.model != "none")
        run = run_tsdf(rig, settings, mesh_every=None, noise=noise)
        metrics = evaluate_map(run.mesh, ground_truth, observed).as_dict()
        rows.append({"method": f"TSDF {voxel * 100:g} cm", "fscore_1cm": metrics["fscore_1cm"], "triangles": int(run.mesh.GetNumberOfCells())})
    return rows


def aligned_error(true: np.ndarray, poses: np.ndarray) -> tuple[float, float]:
    """Median pose error (mm, degrees) after the best rigid alignment of the whole trajectory (ATE-style)."""
    rotation = Rotation.from_matrix(np.einsum("nij,nkj->nik", poses[:, :3, :3], true[:, :3, :3])).mean().as_matrix()
    translation = np.mean(poses[:, :3, 3] - true[:, :3, 3] @ rotation.T, axis=0)
    align = np.eye(4)
    align[:3, :3], align[:3, 3] = rotation, translation
    errors = np.array([transform_size(np.linalg.inv(align @ t) @ p) for t, p in zip(true, poses, strict=True)])
    return 1000 * float(np.median(errors[:, 0])), float(np.median(errors[:, 1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--table", action="store_true", help="also the table scene")
    parser.add_argument("--quick", action="store_true", help="exact poses and jitter 2 mm only")
    parser.add_argument("--scenarios", nargs="*", type=int, help="which scenarios (0-4, in the order of SCENARIOS)")
    parser.add_argument("--no-icp", action="store_true", help="skip part 1 (the ICP alone)")
    parser.add_argument(
        "--devices", nargs="+", default=["cpu"], metavar="DEVICE",
        help="part 1 on each registration device (cpu, warp-cpu, cuda, cuda:N); e.g. --devices cpu cuda on a GPU machine",
    )
    parser.add_argument("--no-loop", action="store_true", help="skip part 2 (the loop)")
    parser.add_argument("--out", default="runs/bench_registration.json")
    args = parser.parse_args()
    report = {"machine": f"{platform.node()} {platform.processor() or platform.machine()}"}
    if not args.no_icp:
        report["icp"] = [icp_alone(device=device) for device in args.devices]
        print(json.dumps(report["icp"], indent=1), flush=True)
    scenes = [] if args.no_loop else ["bunnies"] + (["table"] if args.table else [])
    scenarios = dict(list(SCENARIOS.items())[:2]) if args.quick else SCENARIOS
    if args.scenarios:
        scenarios = {name: SCENARIOS[name] for index, name in enumerate(SCENARIOS) if index in args.scenarios}
    rows = []
    for scene in scenes:
        for name, overrides in scenarios.items():
            for registration in (True, False):
                row = {"scene": scene, "scenario": name, **loop_row(scene, overrides, registration)}
                rows.append(row)
                print(json.dumps(row), flush=True)
            for row in tsdf_rows(scene, overrides):
                row = {"scene": scene, "scenario": name, **row}
                rows.append(row)
                print(json.dumps(row), flush=True)
    report["loop"] = rows
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
