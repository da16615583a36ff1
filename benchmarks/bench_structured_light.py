"""A scene under the structured-light noise model, over several draws of the noise: mabdi against the TSDF.

For each noise seed (``[run] seed``: every frame's noise is drawn from it), the scene is run through the
MABDI loop (quad-tree, defaults) and through Open3D's TSDF at 1 and 2 cm with the settings tuned in
docs/benchmarks.md (truncation 4 voxels, weight above 0.5, half-pixel centres, depth smoothed as the
surfaces smooth it), on the same frames. Prints F@1cm, precision and recall at 1 cm, F@2cm and triangles
per seed, and the mean difference mabdi - TSDF: one draw of the noise says little about a gap of a
thousandth, the spread over draws says whether it is the method's.

    python benchmarks/bench_structured_light.py                        # Run 2, seeds 2-5
    python benchmarks/bench_structured_light.py --scene table --seeds 0 1 2 3
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import numpy as np

import mabdi  # noqa: F401  (selects the EGL window before VTK loads)
from mabdi.config import load_run_config, set_value
from mabdi.evaluate import evaluate_run
from mabdi.evaluate.metrics import evaluate_map, observed_ground_truth, scenes_per_pose
from mabdi.evaluate.tsdf import TsdfSettings, open3d_status, run_tsdf
from mabdi.io.atomic import write_text
from mabdi.loop import MappingRun

REPO = Path(__file__).resolve().parents[1]


def one_seed(scene: str, seed: int) -> dict:
    """mabdi (quad-tree) and the TSDF at 1 and 2 cm on ``scene`` with structured-light noise drawn from ``seed``."""
    config = load_run_config(REPO / "scenes" / f"{scene}.toml")
    config.surface.method = "quadtree"
    set_value(config, "sensor.noise", "structured_light")
    set_value(config, "run.seed", seed)
    simulation = MappingRun(config)
    result = simulation.run()
    metrics = evaluate_run(simulation, result)
    rows = {"mabdi": {"fscore_1cm": metrics.fscore_1cm, "precision_1cm": metrics.precision_1cm,
                      "recall_1cm": metrics.recall_1cm, "fscore_2cm": metrics.fscore_2cm,
                      "triangles": int(result.mesh.GetNumberOfCells())}}  # fmt: skip
    rig = simulation.rig
    frames = len(rig)
    truth = rig.scene.mesh_at(frames - 1)
    observed = observed_ground_truth(truth, scenes_per_pose(rig.scene, frames), rig.true_poses, rig.intrinsics)
    for voxel in (0.01, 0.02):
        settings = TsdfSettings.tuned(voxel)
        run = run_tsdf(rig, settings, mesh_every=None, noise=rig.sensor.noise)
        tsdf = evaluate_map(run.mesh, truth, observed)
        rows[f"TSDF {voxel * 100:g} cm"] = {"fscore_1cm": tsdf.fscore_1cm, "precision_1cm": tsdf.precision_1cm,
                                            "recall_1cm": tsdf.recall_1cm, "fscore_2cm": tsdf.fscore_2cm,
                                            "triangles": int(run.mesh.GetNumberOfCells())}  # fmt: skip
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="bunnies", help="a scene of scenes/ (default: bunnies, Run 2)")
    parser.add_argument("--seeds", nargs="+", type=int, default=[2, 3, 4, 5], help="noise seeds (default: 2 3 4 5)")
    parser.add_argument("--out", type=Path, help="write the rows as JSON here too")
    args = parser.parse_args()
    usable, reason = open3d_status()
    if not usable:
        raise SystemExit(f"the TSDF cannot run: {reason}")
    results = {}
    print("| seed | method | F@1cm | P@1cm | R@1cm | F@2cm | triangles |")
    print("|---:|---|---:|---:|---:|---:|---:|")
    for seed in args.seeds:
        results[seed] = one_seed(args.scene, seed)
        for method, row in results[seed].items():
            print(f"| {seed} | {method} | {row['fscore_1cm']:.4f} | {row['precision_1cm']:.4f} | {row['recall_1cm']:.4f} "
                  f"| {row['fscore_2cm']:.4f} | {row['triangles']:,} |", flush=True)  # fmt: skip
    for voxel in ("TSDF 1 cm", "TSDF 2 cm"):
        for key in ("fscore_1cm", "fscore_2cm"):
            gaps = np.array([results[s]["mabdi"][key] - results[s][voxel][key] for s in args.seeds])
            print(f"mabdi - {voxel}, {key}: mean {gaps.mean():+.4f}, from {gaps.min():+.4f} to {gaps.max():+.4f}")
    if args.out:
        write_text(args.out, json.dumps({"scene": args.scene, "machine": platform.processor() or platform.machine(), "rows": results}, indent=1))


if __name__ == "__main__":
    main()
