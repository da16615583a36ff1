"""The benchmark harness behind ``mabdi bench``: every method on the same frames, one table.

Methods, all fed the same depth frames: the scene's simulated rig
(:class:`~mabdi.simulate.rig.SimulatedRig`) is built once, its frames are
rendered once and kept in memory (:class:`~mabdi.sources.frames.FrameList`,
stating what the rig states: the noise model, and how far the given poses
are off, so that the registration weighs them as in ``mabdi run``), and
every method reads them from there:

* ``mabdi``: the MABDI loop with the config's surface filter and classifier;
* ``black_box``: the same runner with the classifier off;

  both are a :class:`~mabdi.loop.run_pipeline.RunPipeline` (nothing
  written; in a scene an object leaves, a
  :class:`~mabdi.evaluate.dynamic.GhostObserver` watches it);
* ``tsdf_1cm``, ``tsdf_2cm``: Open3D's VoxelBlockGrid TSDF (optional; see
  :mod:`mabdi.evaluate.tsdf`), skipped with a note when Open3D is missing.
  The peer runs at its best: with ``tune=True`` (the default of ``mabdi
  bench``) its settings are tuned per scene by
  :func:`~mabdi.evaluate.tsdf.tune_tsdf` (truncation 2-6 voxels, weight
  threshold 0.5-3, depth range, pixel convention, and depth smoothing by the
  sensor's noise model as the pixel grid and quad-tree do it; a coordinate search scored
  on :data:`TUNING_SAMPLES` ground-truth samples), then the best settings are
  run again and scored like every other method; the row records them.

Each map is scored against the same observed ground-truth samples
(:mod:`mabdi.evaluate.metrics`). The harness writes ``bench.json`` (all
numbers, the machine, the command), ``bench.md`` (the table) and
``elements.png`` (triangles per frame for every method).
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import subprocess
import sys
from functools import partial
from pathlib import Path

import numpy as np
import vtkmodules

from mabdi.config import RunConfig, with_overrides
from mabdi.evaluate.dynamic import GhostObserver, GhostTracker, departures
from mabdi.evaluate.metrics import SAMPLES, evaluate_map, evaluate_run, observed_ground_truth, scenes_per_pose
from mabdi.evaluate.tsdf import TsdfSettings, alignment_error, open3d_status, run_tsdf, tune_tsdf
from mabdi.sensor_noise import SensorNoise
from mabdi.io.atomic import write_text
from mabdi.io.plots import write_elements_plot
from mabdi.simulate.rig import SimulatedRig
from mabdi.io.run_folder import prepare_output_dir
from mabdi.loop.run_pipeline import RunPipeline
from mabdi.loop.mapping_run import MappingRun
from mabdi.sources.frames import FrameList

METHODS = ("mabdi", "black_box", "tsdf_1cm", "tsdf_2cm")
TSDF_VOXELS = {"tsdf_1cm": 0.01, "tsdf_2cm": 0.02}
#: Ground-truth samples for scoring each point of the TSDF's tuning (the chosen one is scored in full).
TUNING_SAMPLES = 20_000


def machine_info(rig: SimulatedRig | None = None) -> dict:
    """CPU, cores, GPU (nvidia-smi, if any), VTK render backend and versions."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    gpu = "none"
    if shutil.which("nvidia-smi"):
        try:
            gpu = subprocess.run(
                ["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True, timeout=10
            ).stdout.strip() or "none"
        except (OSError, subprocess.SubprocessError):
            pass
    info = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "gpu": gpu,
        "python": sys.version.split()[0],
        "vtk": vtkmodules.__version__,
        "numpy": np.__version__,
    }
    usable, _ = open3d_status()
    if usable:
        import open3d

        info["open3d"] = open3d.__version__
    if rig is not None:
        info["render"] = rig.render_backend()
    return info


def _evaluate(simulation: MappingRun, result, progress, method: str, observed):
    """The bench's evaluation step of a run: the map against the samples every method is scored on."""
    progress(f"{method}: evaluating {result.mesh.GetNumberOfCells():,} triangles")
    return evaluate_run(simulation, result, observed=observed)


def _mabdi_row(name: str, result) -> dict:
    summary = result.summary()
    return {
        "method": name,
        "metrics": result.scores.as_dict(),
        "ms_per_frame": summary["mean_ms"],
        "seconds": summary["seconds"],
        "triangles_per_frame": [int(c) for c in result.cells],
    }


def _dynamic(ghosts) -> dict:
    """The dynamic-scene numbers of a :class:`~mabdi.evaluate.dynamic.GhostRun` for a bench row."""
    return {
        "ghost_share_end": ghosts.final_share,
        "ghost_share_per_frame": [[int(f), float(v)] for f, v in ghosts.shares],
        "frames_to_clear": ghosts.frames_to_clear(),
        "static_loss": ghosts.static.as_dict(),
        "removal": None
        if ghosts.removal is None
        else {k: (None if isinstance(v, float) and v != v else v) for k, v in ghosts.removal.as_dict().items()},  # NaN: null
    }


def observed_samples(rig: SimulatedRig, config: RunConfig, samples: int):
    """The ground-truth samples that the run's poses saw (shared by every method of a bench)."""
    frames = len(rig)
    return observed_ground_truth(
        rig.scene.mesh_at(frames - 1),
        scenes_per_pose(rig.scene, frames),
        rig.true_poses,  # where the sensor saw from (the frames carry the given poses)
        rig.intrinsics,
        samples,
        config.sensor.backend,
    )


def bench_frames(config: RunConfig) -> tuple[SimulatedRig, FrameList]:
    """The scene's rig (built once) and its frames, rendered once and kept for every method, stating what
    the rig states (true poses, noise model, how far the given poses are off) as ``mabdi run`` does."""
    rig = SimulatedRig.from_config(config)
    frames = FrameList(
        [rig.read(i) for i in range(len(rig))],
        description=rig.description,
        true_poses=rig.true_poses,
        noise=rig.noise,
        pose_accuracy=rig.pose_accuracy,
    )
    return rig, frames


def run_bench(
    config: RunConfig,
    methods=METHODS,
    out_dir=None,
    samples: int = SAMPLES,
    progress=print,
    command: str | None = None,
    tune: bool = True,
) -> dict:
    """Run ``methods`` on the run ``config`` describes; return (and with ``out_dir`` write) the results.

    ``command`` (the command line that asked for it) is recorded with the numbers.
    The caller's config is not changed.
    """
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        from mabdi.errors import ConfigError

        raise ConfigError(f"unknown bench method {unknown[0]!r} (known: {', '.join(METHODS)})")
    out = prepare_output_dir(out_dir) if out_dir is not None else None
    progress(f"rendering {config.run.frames} frames of {config.run.name or 'the scene'}")
    rig, frames = bench_frames(config)
    observed = observed_samples(rig, config, samples)
    ground_truth = rig.scene.mesh_at(len(frames) - 1)
    #: a scene an object leaves: ghost share, frames to clear and static loss for every method
    dynamic = bool(departures(rig.scene, len(frames)))
    noise = SensorNoise.from_config(config.sensor)  # the TSDF may smooth its depth by it, as our surfaces do
    rows, notes = [], []
    for method in methods:
        if method in ("mabdi", "black_box"):
            method_config = with_overrides(config, {"classifier.enabled": method == "mabdi"}, where=f"bench method {method}")
            progress(f"{method}: running {len(frames)} frames")
            simulation = MappingRun(method_config, source=frames, scene=rig.scene)
            # in a scene an object leaves, the map after every few frames against the scene as it is then
            ghosts = GhostObserver(every=max(1, len(frames) // 25)) if dynamic else None
            evaluate = partial(_evaluate, progress=progress, method=method, observed=observed)
            result = RunPipeline(simulation, observers=[ghosts] if ghosts else [], evaluate=evaluate, evaluate_empty=True).run()
            rows.append(_mabdi_row(method, result))
            if dynamic:
                rows[-1]["dynamic"] = _dynamic(ghosts.ghosts)
            continue
        usable, reason = open3d_status()
        if not usable:
            note = f"{method} skipped: {reason}"
            progress(note)
            notes.append(note)
            continue
        voxel = TSDF_VOXELS[method]
        settings, tuning = TsdfSettings(voxel_size=voxel), None
        if tune:
            progress(f"{method}: tuning the TSDF on {len(frames)} frames")
            tuning_observed = observed_samples(rig, config, min(samples, TUNING_SAMPLES))

            def score(mesh, tuning_observed=tuning_observed):
                return evaluate_map(mesh, ground_truth, tuning_observed, samples=min(samples, TUNING_SAMPLES)).as_dict()

            tuning = tune_tsdf(frames, voxel, score, noise=noise)
            settings = tuning.best
            progress(f"{method}: best of {len(tuning.table)} settings: {settings.as_dict()}")
        progress(f"{method}: integrating {len(frames)} frames")
        run = run_tsdf(frames, settings, turns=config.path.turns, noise=noise)
        metrics = evaluate_map(run.mesh, ground_truth, observed, samples=samples)
        metrics.growth_per_circle = run.growth_per_circle(len(frames), config.path.turns)
        tsdf_dynamic = None
        if dynamic:  # the TSDF's final mesh against the final scene (its meshes along the way are not kept)
            tracker = GhostTracker(rig.scene, len(frames), rig.true_poses, rig.intrinsics, backend=config.sensor.backend)
            tracker.measure(len(frames) - 1, run.mesh, final=True)
            tsdf_dynamic = _dynamic(tracker.finish())
        extract_ms = float(np.mean([ms for _, _, ms in run.extractions])) if run.extractions else 0.0
        rows.append(
            {
                "method": method,
                "metrics": metrics.as_dict(),
                "ms_per_frame": {
                    "t_depth_ms": float(np.mean(run.t_depth_ms)),
                    "t_integrate_ms": float(np.mean(run.t_integrate_ms)),
                    "t_extract_ms": extract_ms,
                    "t_total_ms": float(np.mean(np.add(run.t_depth_ms, run.t_integrate_ms))),
                    "t_total_with_mesh_ms": float(np.mean(np.add(run.t_depth_ms, run.t_integrate_ms)) + extract_ms),
                },
                "seconds": run.seconds,
                "volume_bytes": run.volume_bytes,
                "triangles_at": [[frame, triangles] for frame, triangles, _ in run.extractions],
                "settings": settings.as_dict(),
                **({"dynamic": tsdf_dynamic} if tsdf_dynamic is not None else {}),
                "tuning": None
                if tuning is None
                else {"points": len(tuning.table), "volumes": tuning.integrations, "seconds": tuning.seconds},
            }
        )
    bench = {
        "scene": config.run.name,
        "frames": len(frames),
        "noise": config.sensor.noise,
        "seed": config.run.seed,
        "surface": config.surface.method,
        "samples": samples,
        "command": command,
        "machine": machine_info(rig),
        "methods": rows,
        "notes": notes,
    }
    if any(r["method"].startswith("tsdf") for r in rows):
        bench["tsdf_alignment_mm"] = 1000.0 * alignment_error(rig.noise_free(0), rig.scene.mesh_at(0))
    if out is not None:
        write_bench_outputs(bench, out)
    return bench


def markdown_table(bench: dict) -> str:
    """The bench as a markdown table (one row per method)."""
    lines = [
        "| method | F@1cm | F@2cm | P@1cm | R@1cm | accuracy median / p95 (mm) | redundancy | triangles | MB in memory "
        "| PLY MB | ms/frame | 2nd circle / 1st | total s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in bench["methods"]:
        m = row["metrics"]
        ms = row["ms_per_frame"]
        growth = m["growth_per_circle"]
        second = f"{100.0 * growth[1] / growth[0]:.1f}%" if len(growth) > 1 and growth[0] else "-"
        redundancy = "-" if m["redundancy"] is None else f"{100.0 * m['redundancy']:.1f}%"
        if "t_integrate_ms" in ms:
            memory = row.get("volume_bytes", m["memory_bytes"])
            timing = f"{ms['t_total_ms']:.1f} (+{ms['t_extract_ms']:.0f} mesh)"
        else:
            memory = m["memory_bytes"]
            timing = f"{ms['t_total_ms']:.1f}"
        lines.append(
            f"| {row['method']} | {m['fscore_1cm']:.3f} | {m['fscore_2cm']:.3f} | {m['precision_1cm']:.3f} "
            f"| {m['recall_1cm']:.3f} | {m['accuracy_median_mm']:.2f} / {m['accuracy_p95_mm']:.2f} "
            f"| {redundancy} | {m['triangles']:,} | {memory / 2**20:.1f} | {m['ply_bytes'] / 2**20:.1f} "
            f"| {timing} | {second} | {row['seconds']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def dynamic_table(bench: dict) -> str:
    """Ghost share at the end, frames to clear, static loss and the static / dynamic accuracy (SA, DA, AA:
    :mod:`mabdi.evaluate.removal_accuracy`), one row per method (dynamic scenes)."""
    rows = [r for r in bench["methods"] if "dynamic" in r]
    if not rows:
        return ""
    lines = [
        "| method | ghost share at the end | frames to clear | static loss (m^2) | SA | DA | AA |",
        "|---|---:|---|---:|---:|---:|---:|",
    ]
    for row in rows:
        d = row["dynamic"]
        clear = ", ".join(f"{k}: {'-' if v is None else v}" for k, v in d["frames_to_clear"].items()) or "-"
        if not row.get("triangles_per_frame"):
            clear = "(final mesh only)"
        removal = d.get("removal") or {}
        accuracy = " | ".join(
            "-" if removal.get(key) is None else f"{removal[key]:.4f}"
            for key in ("static_accuracy", "dynamic_accuracy", "associated_accuracy")
        )
        lines.append(
            f"| {row['method']} | {100.0 * d['ghost_share_end']:.2f}% | {clear} | {d['static_loss']['area_m2']:.4f} | {accuracy} |"
        )
    return "\n".join(lines) + "\n"


def stage_table(bench: dict) -> str:
    """Milliseconds per frame by stage, one row per method."""
    lines = ["| method | stage ms per frame |", "|---|---|"]
    for row in bench["methods"]:
        stages = ", ".join(f"{k[2:-3]} {v:.1f}" for k, v in row["ms_per_frame"].items())
        lines.append(f"| {row['method']} | {stages} |")
    return "\n".join(lines) + "\n"


def write_bench_outputs(bench: dict, out: Path) -> None:
    """bench.json, bench.md and elements.png in ``out`` (each written atomically)."""
    write_text(out / "bench.json", json.dumps(bench, indent=2) + "\n")
    machine = bench["machine"]
    render = machine.get("render", {})
    header = (
        f"# mabdi bench: {bench['scene']}, {bench['frames']} frames, noise {bench['noise']}\n\n"
        + (f"Command: `{bench['command']}`\n\n" if bench.get("command") else "")
        +
        f"Machine: {machine['cpu']}, {machine['cores']} cores, GPU {machine['gpu']}; "
        f"render {render.get('window', '?')} ({render.get('gl_renderer', '?')}); VTK {machine['vtk']}"
        + (f", Open3D {machine['open3d']}" if "open3d" in machine else "")
        + "\n\n"
    )
    notes = "".join(f"- {note}\n" for note in bench["notes"])
    for row in bench["methods"]:
        if "settings" in row:
            tuned = row.get("tuning")
            how = f"tuned over {tuned['points']} settings in {tuned['seconds']:.0f} s" if tuned else "not tuned"
            notes += f"- {row['method']} settings ({how}): {row['settings']}\n"
    if "tsdf_alignment_mm" in bench:
        notes += f"- TSDF alignment check (noise-free first frame, 1 cm voxels): median {bench['tsdf_alignment_mm']:.2f} mm\n"
    dynamic = dynamic_table(bench)
    body = markdown_table(bench) + "\n" + (dynamic + "\n" if dynamic else "") + stage_table(bench)
    write_text(out / "bench.md", header + body + ("\n" + notes if notes else ""))
    series = {}
    for row in bench["methods"]:
        if "triangles_per_frame" in row:
            counts = row["triangles_per_frame"]
            series[row["method"]] = (np.arange(len(counts)), np.array(counts))
        else:
            at = np.array(row["triangles_at"]).reshape(-1, 2)
            series[row["method"]] = (at[:, 0], at[:, 1])
    write_elements_plot(series, out / "elements.png", title=f"{bench['scene']}: triangles in the map")
