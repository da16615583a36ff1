"""The ``mabdi`` command line.

    mabdi run CONFIG [--frames N] [--out DIR] [--noise MODEL] [--seed N] [--surface NAME] [--set KEY=VALUE]
                     [--no-classifier] [--no-removal] [--no-registration] [--device D] [--refinement] [--depth-images] [--h5] [--movie]
                     [--rerun [FILE.rrd]] [--backend B] [--overwrite] [--quiet] [--no-eval]
    mabdi run --sequence PATH [CONFIG] [--frames N] [--camera PRESET|fx,fy,cx,cy,w,h[,near,far]] [--depth-scale UNITS] ...
    mabdi run --resume OUT [--quiet] [--no-eval]   finish an interrupted run from its last checkpoint (its inputs
                                                   must be unchanged; the run's own options are kept)
    mabdi record CONFIG --format tum|rosbag2|kitti --out PATH [--storage sqlite3|mcap] [--encoding 32FC1|16UC1]
    mabdi export IN OUT [--layout mesh_tools|lvr2]   convert a map between VTP, PLY, OBJ, STL and HDF5
    mabdi info MAP               counts, bounds, layers, labels and cluster sets of a map
    mabdi view PATH [--colour frame|normal|rgb|LAYER] [--out PNG] [--from-frame N] [--up AXIS|X,Y,Z]   look at a map or a run folder
    mabdi plan MAP --start x,y,z --goal x,y,z [--planner dijkstra|fmm] [--out path.vtp]
    mabdi bench [--scene NAME|CONFIG] [--methods M ...] [--frames N] [--out DIR] [--no-tune]
    mabdi sweep SWEEP.toml [--workers N] [--address ADDR] [--out DIR]

Options override the config file; the resolved config is written with the
outputs. Errors a user can cause (a bad config, a missing mesh) print one
line ``mabdi: error: ...`` and exit with status 2, without a traceback;
warnings print ``mabdi: warning: ...``; Ctrl-C exits with 130; ``mabdi run``
exits 1 when the map it made is empty (the warning says why).
Heavy imports (VTK) happen inside the commands, so ``mabdi --help`` is quick.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def _time_offset(text: str) -> float | str:
    """``--time-offset``: ``auto`` or a number of seconds (argparse names the option when it is neither)."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected auto or a number of seconds, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected auto or a finite number of seconds, got {text!r}")
    return value


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mabdi", description="Mesh maps from a moving depth sensor (MABDI).")
    try:
        from importlib.metadata import version

        mabdi_version = version("mabdi")
    except Exception:  # noqa: BLE001 - not installed (a source tree on sys.path): say so
        mabdi_version = "unknown (not installed)"
    parser.add_argument("--version", action="version", version=f"%(prog)s {mabdi_version}")
    commands = parser.add_subparsers(dest="command", required=True)

    surfaces = _surface_help()
    run = commands.add_parser("run", help="run the MABDI loop on a run config (scenes/*.toml) or a recorded sequence")
    run.add_argument(
        "config", type=Path, nargs="?", help="run config (TOML), e.g. scenes/bunnies.toml (optional with --sequence)"
    )
    run.add_argument(
        "--frames", type=int,
        help="number of frames (overrides run.frames); with --sequence, the recording's first N frames (all when it has fewer)",
    )
    run.add_argument("--out", type=Path, help="output folder (default: runs/<config name>)")
    run.add_argument(
        "--noise",
        help="noise model: none, zbuffer, kinect, structured_light, or auto (learnt from the run: recordings) (overrides sensor.noise)",
    )
    run.add_argument("--seed", type=int, help="noise seed (overrides run.seed)")
    run.add_argument("--surface", help=f"surface filter (overrides surface.method): {surfaces}")
    run.add_argument(
        "--no-classifier", action="store_true", help="black box: mesh every valid pixel every frame (classifier.enabled = false)"
    )
    run.add_argument(
        "--no-removal", action="store_true",
        help="keep every face: no object removal by free-space contradiction (removal.enabled = false)",
    )
    run.add_argument(
        "--no-registration", action="store_true",
        help="use the poses as given: no frame-to-map registration (registration.enabled = false)",
    )
    run.add_argument(
        "--device", metavar="DEVICE",
        help="where the per-pixel work that has a GPU path runs: cpu (default), cuda, cuda:N, or warp-cpu (the GPU "
        "kernels on the CPU): registration's ICP (registration.device; all but cpu need mabdi[gpu])",
    )
    run.add_argument(
        "--refinement", action="store_true",
        help="later, better looks refine or replace known faces with any noise model (refinement.enabled = true; "
        "the default \"auto\" refines where the noise model's errors are correlated between pixels)",
    )
    run.add_argument(
        "--rerun", nargs="?", const="", metavar="FILE.rrd",
        help="log every frame to Rerun: to a viewer (spawned or connected), or to a .rrd recording (needs mabdi[rerun])",
    )
    run.add_argument(
        "--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
        help="set any config value by its dotted key, e.g. --set surface.quadtree.n_t=0.05 (TOML value syntax; repeatable)",
    )
    run.add_argument("--depth-images", action="store_true", help="also write D, E and labels of every frame as VTI")
    run.add_argument("--h5", action="store_true", help="also write world_mesh.h5 with cost layers, labels, poses (output.h5)")
    run.add_argument("--movie", action="store_true", help="also write movie.mp4 of the dashboard and PNG snapshots (output.movie)")
    run.add_argument("--backend", help="render backend: egl or osmesa (overrides sensor.backend)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.add_argument("--no-eval", action="store_true", help="skip the evaluation against the ground truth")
    run.add_argument(
        "--overwrite", action="store_true",
        help="write into an output folder that holds files mabdi did not write (they are left as they are)",
    )
    run.add_argument(
        "--resume", type=Path, metavar="OUT",
        help="finish the interrupted run in folder OUT from its last checkpoint (output.checkpoint_every)",
    )
    sequence = run.add_argument_group("recorded sequences (--sequence)")
    sequence.add_argument(
        "--sequence", type=Path,
        help="run on a recorded sequence (a TUM RGB-D folder, a ROS 2 or ROS 1 bag, or a 3DMatch / 7-Scenes, Redwood / Open3D, "
        "ScanNet, Replica (NICE-SLAM), Stray Scanner or KITTI-style LiDAR folder, told apart by their files) instead of the simulated sensor; "
        "CONFIG then gives the classifier, surface and output settings (its [sensor] noise sets the thresholds; "
        "when neither CONFIG's [sensor] nor --noise names a noise model, a depth camera's is learnt from the run, noise = auto)",
    )
    sequence.add_argument(
        "--camera",
        help="the camera when the sequence has none (or to replace it): a preset (TUM fr1, fr2, fr3, ros; 7scenes; "
        "replica) or fx,fy,cx,cy,width,height in pixels (pixel centres at +0.5, as in mabdi.toml; width and height "
        "whole numbers), optionally ,near,far in metres (default 0.5 and 4)",
    )
    sequence.add_argument(
        "--depth-scale", type=float,
        help="depth PNG units per metre, replacing the layout's own (TUM 5000, 3DMatch / Redwood / ScanNet / Stray Scanner 1000, Replica 6553.5)",
    )
    sequence.add_argument("--depth-topic", help="ROS bag: the depth image topic (when there are several)")
    sequence.add_argument("--info-topic", help="ROS bag: the CameraInfo topic (when there are several)")
    sequence.add_argument("--pose-topic", help="ROS bag: a PoseStamped topic for the poses (default: /tf when present)")
    sequence.add_argument("--cloud-topic", help="ROS bag: a PointCloud2 topic of LiDAR scans to read instead of depth images")
    sequence.add_argument("--colour-topic", help="ROS bag: the rgb8 / bgr8 colour image topic registered to the depth (when there are several)")
    sequence.add_argument(
        "--tolerance", type=float, help="TUM, ROS bag: largest time between a depth frame and its pose, seconds (default 0.02)"
    )
    sequence.add_argument(
        "--min-confidence", type=int, choices=(0, 1, 2),
        help="Stray Scanner: the least ARKit confidence a depth pixel needs, 0 low, 1 medium (the default), 2 high",
    )
    sequence.add_argument(
        "--time-offset", type=_time_offset,
        help="TUM, ROS bag: seconds from a depth frame's timestamp to the time its pose is taken at, or auto (the default: "
        "learnt from the depth where the pose clock and the depth clock disagree; 0 keeps the recording's pairing)",
    )

    record = commands.add_parser("record", help="write a simulated run's depth frames as a TUM folder or a ROS 2 bag")
    record.add_argument("config", type=Path, help="run config (TOML), e.g. scenes/table.toml")
    record.add_argument(
        "--format", required=True, choices=("tum", "rosbag2", "kitti"),
        help="tum (TUM RGB-D folder), rosbag2, or kitti (a LiDAR's scans as a KITTI-style folder)",
    )
    record.add_argument("--out", type=Path, required=True, help="folder to create (must not exist or be empty)")
    record.add_argument("--storage", default="sqlite3", choices=("sqlite3", "mcap"), help="ROS 2 bag storage (default sqlite3)")
    record.add_argument(
        "--encoding", default="32FC1", choices=("32FC1", "16UC1"), help="ROS 2 depth encoding: 32FC1 metres (default) or 16UC1 mm"
    )
    record.add_argument("--frames", type=int, help="number of frames (overrides run.frames)")
    record.add_argument("--noise", help="noise model: none, zbuffer, kinect or structured_light (overrides sensor.noise)")
    record.add_argument("--seed", type=int, help="noise seed (overrides run.seed)")
    record.add_argument("--overwrite", action="store_true", help="replace a previous recording in --out")

    export = commands.add_parser("export", help="convert a saved map between VTP, PLY, OBJ, STL and HDF5 (.h5)")
    export.add_argument(
        "source", type=Path, help="map file to read (.vtp, .ply, .obj, .stl, .h5), or a run folder (its world_mesh.h5, .vtp or .ply)"
    )
    export.add_argument("target", type=Path, help="file to write; the format follows the suffix")
    export.add_argument("--layout", default="mesh_tools", help="HDF5 layout: mesh_tools (default) or lvr2")

    info = commands.add_parser("info", help="counts, bounds, layers, labels and cluster sets of a map file")
    info.add_argument(
        "map", type=Path, help="map file (.h5, .vtp, .ply, .obj, .stl), or a run folder (its world_mesh.h5, .vtp or .ply)"
    )

    view = commands.add_parser("view", help="show a map or a run folder (a PNG when there is no display)")
    view.add_argument("path", type=Path, help="map file (.vtp, .ply, .h5, ...) or run folder")
    view.add_argument("--colour", "--color", default="frame", help="frame (default), normal, rgb (the map's vertex colours), or a layer name (cost, ...)")
    view.add_argument("--out", type=Path, help="write a PNG here instead of opening a window")
    view.add_argument(
        "--from-frame", type=int, metavar="N",
        help="look from the sensor's pose of frame N (a run folder) instead of framing the whole map from above and aside",
    )
    view.add_argument(
        "--up", metavar="AXIS|X,Y,Z",
        help="the world's up for the default view: z, y, ... or x,y,z; a leading minus needs '=': --up=-y "
        "(default: the run's cameras' mean up, snapped to a world axis within 20 degrees, else +z)",
    )

    plan = commands.add_parser("plan", help="plan a path on a map (Dijkstra or fast marching)")
    plan.add_argument(
        "map", type=Path, help="map file (.h5, .vtp, .ply, .obj, .stl), or a run folder (its world_mesh.h5, .vtp or .ply)"
    )
    plan.add_argument("--start", required=True, help="start point x,y,z (m)")
    plan.add_argument("--goal", required=True, help="goal point x,y,z (m)")
    plan.add_argument("--planner", default="fmm", help="fmm (default) or dijkstra")
    plan.add_argument("--out", type=Path, help="write the path as a polyline (.vtp)")

    bench = commands.add_parser("bench", help="every method on the same frames, scored against the ground truth")
    bench.add_argument("--scene", default="table", help="scene name in scenes/ or a run config path (default: table)")
    bench.add_argument(
        "--methods", nargs="+", default=None, help="mabdi, black_box, tsdf_1cm, tsdf_2cm (default: all)"
    )
    bench.add_argument("--frames", type=int, help="number of frames (overrides run.frames)")
    bench.add_argument("--noise", help="noise model (overrides sensor.noise)")
    bench.add_argument("--surface", help="surface filter of the mabdi and black_box methods (overrides surface.method)")
    bench.add_argument("--out", type=Path, help="output folder (default: runs/bench_<scene>)")
    bench.add_argument(
        "--no-tune", action="store_true",
        help="run the TSDF with its plain settings instead of tuning it per scene (faster; the peer is then not at its best)",
    )

    sweep = commands.add_parser("sweep", help="a grid of runs and their evaluations on Ray (SWEEP.toml), one table")
    sweep.add_argument("sweep", type=Path, help="sweep file (TOML: [sweep] configs, frames; [grid] dotted key = [values])")
    sweep.add_argument("--out", type=Path, help="output folder (default: runs/sweep_<name>)")
    sweep.add_argument("--workers", type=int, help="CPUs of the local Ray instance and most cells in flight (default: all cores)")
    sweep.add_argument("--address", help="an existing Ray cluster to run on (host:port or auto) instead of a local instance")
    return parser


def _surface_help() -> str:
    """The registered surface filters with their help lines (the registry is the one list)."""
    from mabdi.surfaces.registry import surface_filter, surface_filter_names

    return "; ".join(f"{name} ({surface_filter(name).help})" for name in surface_filter_names())


def _find_config(scene: str) -> Path:
    """A run config from a path or a scene name in ./scenes."""
    path = Path(scene)
    if path.is_file():
        return path
    candidate = Path("scenes") / f"{scene}.toml"
    if candidate.is_file():
        return candidate
    from mabdi.errors import ConfigError

    known = sorted(p.stem for p in Path("scenes").glob("*.toml")) if Path("scenes").is_dir() else []
    raise ConfigError(
        f"scene {scene!r}: no such config file, and no scenes/{scene}.toml here"
        + (f" (scenes here: {', '.join(known)})" if known else "")
    )


def _apply_overrides(config, args):
    """The config with the command line's options and ``--set KEY=VALUE`` values on it, through
    :func:`mabdi.config.with_overrides` (typed and checked as a config file is); returns the new config."""
    from mabdi.config import settings_overrides, with_overrides

    options = {
        "run.frames": getattr(args, "frames", None),
        "sensor.noise": getattr(args, "noise", None),
        "run.seed": getattr(args, "seed", None),
        "sensor.backend": getattr(args, "backend", None),
        "surface.method": getattr(args, "surface", None),
        "classifier.enabled": False if getattr(args, "no_classifier", False) else None,
        "removal.enabled": False if getattr(args, "no_removal", False) else None,
        "refinement.enabled": True if getattr(args, "refinement", False) else None,
        "registration.enabled": False if getattr(args, "no_registration", False) else None,
        "registration.device": getattr(args, "device", None),
        "output.dir": str(args.out) if args.command == "run" and args.out is not None else None,
        "output.depth_images": True if getattr(args, "depth_images", False) else None,
        "output.h5": True if getattr(args, "h5", False) else None,
        "output.movie": True if getattr(args, "movie", False) else None,
    }
    overrides = {key: value for key, value in options.items() if value is not None}
    overrides.update(settings_overrides(getattr(args, "settings", [])))  # after the options: --set has the last word
    return with_overrides(config, overrides, where="command line") if overrides else config


def cmd_run(args) -> int:
    """``mabdi run``: one :class:`~mabdi.loop.run_pipeline.RunPipeline`, its observers chosen by the options."""
    from mabdi.config import RunConfig, load_run_config
    from mabdi.errors import ConfigError
    from mabdi.loop import MappingRun
    from mabdi.loop.run_pipeline import InterruptCheck, ProgressBar, RunPipeline

    if args.resume is not None:
        from mabdi.loop.mapping_run import resume_run

        if args.config is not None or args.sequence is not None:
            raise ConfigError("run: --resume OUT takes the config and source of the run in OUT; give neither CONFIG nor --sequence")
        given = _resume_refused_options(args)
        if given:
            raise ConfigError(
                f"run: --resume OUT finishes the run in OUT with its own settings; {', '.join(given)} cannot be given "
                "with it (only --quiet and --no-eval, which change no map); start a new run to change them"
            )
        report = RunReport(heading=f"resumed {args.resume}")
        pipeline = resume_run(
            args.resume, [ProgressBar(None, not args.quiet), InterruptCheck(), report], evaluate=_evaluate, no_eval=args.no_eval or None
        )
        if args.no_eval and not pipeline.run_options.get("no_eval"):
            report.heading += "\nnote: --no-eval: the resumed run is not evaluated (its map is the same)"
        return _report_run(pipeline, pipeline.run(), None)
    if args.config is None and args.sequence is None:
        raise ConfigError("run: give a run config (e.g. scenes/table.toml), or --sequence PATH")
    config = load_run_config(args.config) if args.config is not None else RunConfig()
    config = _apply_overrides(config, args)
    _check_run_options(args, config)
    note = None
    recording = None
    if args.sequence is not None:
        from mabdi.loop.mapping_run import recorded_simulation

        name = config.run.name or args.sequence.resolve().name
        options = {
            "camera": args.camera,
            "depth_scale": args.depth_scale,
            "depth_topic": args.depth_topic,
            "info_topic": args.info_topic,
            "pose_topic": args.pose_topic,
            "colour_topic": args.colour_topic,
            "cloud_topic": args.cloud_topic,
            "tolerance": args.tolerance,
            "time_offset": args.time_offset,
            "min_confidence": args.min_confidence,
        }
        noise_stated = "sensor.noise" in config.stated  # by the config file, --noise or --set
        frames = config.run.frames if "run.frames" in config.stated else None  # --frames, [run] frames or --set
        simulation, note = recorded_simulation(config, args.sequence, noise_stated=noise_stated, frames=frames, **options)
        if simulation.learnt_time_offset is not None:
            print(f"note: {simulation.learnt_time_offset.note()}")
        used = getattr(simulation.source, "time_offset", None)  # a reader with a pose clock: the offset it reads with
        if used is not None:
            options["time_offset"] = used  # a resume reads the recording as this run did, without learning again
        recording = {"path": str(args.sequence.resolve()), "options": options, "frames": frames}
        print(f"source: {simulation.source.description}")
        source = simulation.source
        if frames is not None and frames > source.available:
            asked = "--frames" if args.frames is not None else "run.frames"
            print(f"note: {asked} {frames}, but the recording has {source.available} frames: all {source.available} are run")
        elif frames is not None and args.frames is None and frames < source.available:
            set_keys = {setting.partition("=")[0].strip() for setting in args.settings}
            where = "--set" if "run.frames" in set_keys else str(args.config)
            print(
                f"note: run.frames = {frames} ({where}) runs the first {frames} of the recording's {source.available} frames; "
                "--frames N runs another number (all of them when N is past the end)"
            )
        if not noise_stated and simulation.config.sensor.noise != config.sensor.noise:
            unstated = "the config does not set [sensor] noise" if args.config is not None else "no config"
            sensor = simulation.config.sensor
            if sensor.noise == "auto":
                print(f"noise: auto (learnt from the run: {unstated} and no --noise name the camera's model)")
            else:  # a LiDAR's recording: its datasheet-class default
                sigma = sensor.noise_parameters.range_sigma
                print(f"noise: {sensor.noise}, {sigma:g} m (a LiDAR's default: {unstated} and no --noise name the sensor's model)")
    else:
        for option in ("camera", "depth_scale", "depth_topic", "info_topic", "pose_topic", "colour_topic", "cloud_topic", "tolerance", "time_offset", "min_confidence"):
            if getattr(args, option) is not None:
                raise ConfigError(f"run: --{option.replace('_', '-')} is for recorded sequences; use it with --sequence")
        if not config.scene.objects:
            raise ConfigError(
                f"{args.config}: nothing to map: the scene has no objects (add [[scene.objects]] tables; see scenes/table.toml)"
            )
        name = config.run.name or args.config.stem
        simulation = MappingRun(config)
    out_dir = Path(config.output.dir) if config.output.dir else Path("runs") / name
    observers = [ProgressBar(simulation.frames, not args.quiet), InterruptCheck()]
    if args.rerun is not None:
        from mabdi.viz.rerun_log import rerun_progress

        observers.append(rerun_progress(simulation, args.rerun or None))
    movie = None
    if config.output.movie:
        from mabdi.viz.record import MovieObserver

        movie = MovieObserver(config.output.snapshots or None)
        observers.append(movie)
    observers.append(RunReport())
    pipeline = RunPipeline(
        simulation, out_dir, observers, evaluate=_evaluate, overwrite=args.overwrite, recording=recording,
        run_options={"no_eval": bool(args.no_eval)}, note=note,
    )
    return _report_run(pipeline, pipeline.run(), movie)


def _evaluate(simulation, result):
    """``mabdi run``'s evaluation step: :func:`mabdi.evaluate.evaluate_run`, its warnings not shown."""
    import warnings

    from mabdi.evaluate import evaluate_run

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return evaluate_run(simulation, result)


#: Options of ``mabdi run`` that --resume takes (the others could change the map, or are the run's own).
_RESUME_OPTIONS = ("quiet", "no_eval")


def _resume_refused_options(args) -> list[str]:
    """The options given with --resume that it does not take, as the user wrote them (--frames, --set, ...)."""
    defaults = {"settings": []}
    given = []
    for name, value in vars(args).items():
        if name in ("command", "resume", "config", "sequence", *_RESUME_OPTIONS):
            continue
        if value is None or value is False or value == defaults.get(name, None):
            continue
        given.append("--set" if name == "settings" else "--" + name.replace("_", "-"))
    return given


def _check_run_options(args, config) -> None:
    """Options a run would only fail on late, checked before any frame: the render backend's library,
    and where --rerun saves."""
    from mabdi.errors import ConfigError
    from mabdi.render.depth_image import _check_backend_library

    _check_backend_library(config.sensor.backend)
    if args.rerun:
        target = Path(args.rerun)
        if target.is_dir():
            raise ConfigError(f"run: --rerun {target}: that is a folder; give a file to save to, e.g. {target / 'run.rrd'}")
        if not target.parent.is_dir():
            raise ConfigError(f"run: --rerun {target}: folder {target.parent} does not exist")


def registration_line(registration: dict) -> str:
    """One line on how the frames' poses fared (summary.json's ``registration``)."""
    statuses = registration["statuses"]
    if set(statuses) == {"off"}:
        return "poses: used as given (registration off)"
    if set(statuses) == {"exact"}:
        return "poses: stated exact by the source, used as given (no registration needed)"
    frames = sum(statuses.values())
    line = f"poses: {registration['registered']} of {frames} frames registered to the map"
    if statuses.get("exact"):
        line = f"poses: {statuses['exact']} of {frames} stated exact by the source and used as given, {registration['registered']} registered to the map"
    if registration.get("device", "cpu") != "cpu":
        line += f" on {registration['device']}"
    if registration["median_correction_mm"] is not None:
        line += f" (median correction {registration['median_correction_mm']:.1f} mm, {registration['median_correction_deg']:.3f} deg)"
    others = {k: v for k, v in statuses.items() if k not in ("registered", "off", "no_map", "exact")}
    if others:
        listed = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in sorted(others.items()))
        line += f"; {registration['not_registered'] - statuses.get('no_map', 0)} not ({listed}): meshed unregistered, no removal votes"
    if registration.get("poor_fit"):
        from mabdi.stages.fit_check import POOR_FIT

        line += (
            f"; {registration['poor_fit']} fit the map over {POOR_FIT:g} times worse than the run's frames: "
            "meshed, no removal votes"
        )
    return line


#: A recording's run whose removal took at least this share of the faces it made says what that may mean.
REMOVED_SHARE_NOTE = 0.05


def removal_line(removed: int, kept: int, recording: bool) -> str:
    """One line on what removal took: ``removed`` faces of the ``removed + kept`` made; on a ``recording`` (no
    ground truth to tell) a share of :data:`REMOVED_SHARE_NOTE` or more names what takes a static scene's faces."""
    made = removed + kept
    share = removed / made if made else 0.0
    line = f"removal: {removed:,} faces removed ({100.0 * share:.1f}% of the {made:,} made)"
    if recording and share >= REMOVED_SHARE_NOTE:
        line += (
            "; if nothing in the scene moved, that much says the poses disagree with the depth (a pose source's "
            "clock or jumps, drift) or the noise is not the sensor's; --no-removal keeps every face"
        )
    return line


class RunReport:
    """Prints a run's totals as its loop ends, before the evaluation: an observer of the run's
    :class:`~mabdi.loop.run_pipeline.RunPipeline` (its one hook; the others are optional)."""

    def __init__(self, heading: str | None = None) -> None:
        self.heading = heading

    def on_loop_end(self, pipeline, result) -> None:
        if self.heading:
            print(self.heading)
        summary = result.summary()
        mode = "classifier on" if summary["classifier"] else "black box (classifier off)"
        print(
            f"{summary['frames']} frames in {summary['seconds']:.1f} s ({summary['frames_per_second']:.1f} frames/s), "
            f"{mode}, surface {summary['surface']}"
        )
        print(f"map: {summary['cells']:,} triangles, {summary['points']:,} points, {summary['map_bytes'] / 2**20:.1f} MB")
        if summary["removal"]:
            print(removal_line(summary["cells_removed"], summary["cells"], pipeline.simulation.scene is None))
        print(registration_line(summary["registration"]))
        if pipeline.note is not None and not pipeline.no_eval:
            print(f"note: {pipeline.note}")


def _report_run(pipeline, result, movie) -> int:
    """Print a finished run's scores and where its files are (its totals were printed as its loop ended)."""
    scores = result.scores
    if scores is not None:
        growth = scores.growth_per_circle
        second = f", 2nd circle adds {100.0 * growth[1] / growth[0]:.1f}% of the 1st" if len(growth) > 1 and growth[0] else ""
        print(
            f"vs ground truth: F@1cm {scores.fscore_1cm:.3f}, F@2cm {scores.fscore_2cm:.3f}, "
            f"accuracy median {scores.accuracy_median_mm:.2f} mm, redundancy {100.0 * (scores.redundancy or 0.0):.1f}%{second}"
        )
    if movie is not None and movie.path is not None:
        print(f"movie: {movie.path} ({pipeline.simulation.frames} frames, dashboard {movie.mean_ms:.0f} ms per frame)")
    print(f"results in {result.out_dir}/ (world_mesh.vtp, world_mesh.ply, metrics.csv, summary.json, elements.png)")
    return 1 if result.mesh.GetNumberOfCells() == 0 else 0  # an empty map: the files are written (valid), the warning says why


def cmd_record(args) -> int:
    from mabdi.config import load_run_config
    from mabdi.simulate.recording import record

    config = load_run_config(args.config)
    config = _apply_overrides(config, args)
    written = record(config, args.out, args.format, storage=args.storage, encoding=args.encoding, overwrite=args.overwrite)
    lidar = config.sensor.kind == "lidar"
    kinds = {
        "tum": "TUM RGB-D folder",
        "kitti": "KITTI-style LiDAR folder",
        "rosbag2": f"ROS 2 bag ({args.storage}, {'PointCloud2' if lidar else args.encoding})",
    }
    kind = kinds.get(args.format, args.format)
    print(f"wrote {written} ({kind}, {config.run.frames} frames of {config.run.name or args.config.stem})")
    return 0


def cmd_view(args) -> int:
    from mabdi.viz.viewer import view

    written = view(args.path, colour=args.colour, screenshot=args.out, from_frame=args.from_frame, up=args.up, log=print)
    if written is not None:
        print(f"no display: wrote {written}" if args.out is None else f"wrote {written}")
    return 0


def cmd_bench(args) -> int:
    from mabdi.config import load_run_config
    from mabdi.evaluate.bench import METHODS, dynamic_table, markdown_table, run_bench

    path = _find_config(args.scene)
    config = load_run_config(path)
    config = _apply_overrides(config, args)
    out_dir = args.out if args.out is not None else Path("runs") / f"bench_{config.run.name or path.stem}"
    command = "mabdi " + " ".join(sys.argv[1:]) if sys.argv[1:2] == ["bench"] else None
    bench = run_bench(
        config,
        args.methods or METHODS,
        out_dir,
        progress=lambda line: print(line, flush=True),
        command=command,
        tune=not args.no_tune,
    )
    print()
    print(markdown_table(bench))
    if dynamic_table(bench):
        print(dynamic_table(bench))
    for note in bench["notes"]:
        print(f"note: {note}")
    print(f"results in {out_dir}/ (bench.json, bench.md, elements.png)")
    return 0


def cmd_sweep(args) -> int:
    from mabdi.sweep import run_sweep

    result = run_sweep(args.sweep, args.out, workers=args.workers, address=args.address, progress=lambda line: print(line, flush=True))
    print()
    print((result.out_dir / "results.md").read_text(), end="")
    print(f"{result.ran} cells run, {result.reused} already done, {len(result.failed)} failed, in {result.seconds:.1f} s")
    print(f"results in {result.out_dir}/ ({', '.join(p.name for p in result.files)})")
    return 1 if result.failed else 0


def cmd_export(args) -> int:
    from mabdi.errors import ConfigError
    from mabdi.io.mesh_map_files import MAP_FORMATS, is_hdf5, load_map, map_file, save_map
    from mabdi.io.vtk_files import read_mesh_file, write_mesh_file

    args.source = map_file(args.source)  # a run's folder: its map file
    for what, path in (("source", args.source), ("target", args.target)):
        if path.suffix.lower() not in MAP_FORMATS:
            raise ConfigError(f"export: {what} {path}: unknown format '{path.suffix}' (known: {', '.join(MAP_FORMATS)})")
    if args.source.resolve() == args.target.resolve():
        raise ConfigError(f"export: source and target are the same file ({args.source})")
    if is_hdf5(args.source) or is_hdf5(args.target):
        mesh_map = load_map(args.source)
        save_map(mesh_map, args.target, layout=args.layout)
        print(f"wrote {args.target} ({mesh_map.number_of_vertices:,} vertices, {mesh_map.number_of_faces:,} triangles)")
        return 0
    mesh = read_mesh_file(args.source)
    write_mesh_file(mesh, args.target)
    print(f"wrote {args.target} ({mesh.GetNumberOfPoints():,} points, {mesh.GetNumberOfCells():,} cells)")
    return 0


def _layer_line(name: str, values) -> str:
    import numpy as np

    values = np.asarray(values)
    shape = "" if values.ndim == 1 else f" x{int(np.prod(values.shape[1:]))}"
    finite = values[np.isfinite(values)] if values.dtype.kind == "f" else values
    span = f"{finite.min():.4g} .. {finite.max():.4g}" if finite.size else "no finite values"
    return f"    {name} ({values.dtype}{shape}): {span}"


def cmd_info(args) -> int:
    from mabdi.io.hdf5 import map_layout
    from mabdi.io.mesh_map_files import is_hdf5, load_map, map_file

    path = map_file(args.map)  # a run's folder: its map file
    mesh_map = load_map(path)
    low, high = mesh_map.bounds()
    layout = f" ({map_layout(path)} layout)" if is_hdf5(path) else ""
    print(f"{path}{layout}")
    print(f"  {mesh_map.number_of_vertices:,} vertices, {mesh_map.number_of_faces:,} triangles")
    if mesh_map.number_of_vertices:
        print(f"  bounds: x {low[0]:.3f} .. {high[0]:.3f}, y {low[1]:.3f} .. {high[1]:.3f}, z {low[2]:.3f} .. {high[2]:.3f} m")
    else:
        print("  bounds: none (an empty map)")
    for kind, layers in (("vertex", mesh_map.vertex_layers), ("face", mesh_map.face_layers)):
        print(f"  {kind} layers: {len(layers)}")
        for name, values in layers.items():
            print(_layer_line(name, values))
    print(f"  labels: {len(mesh_map.labels)}")
    for name, ids in mesh_map.labels.items():
        print(f"    {name}: {len(ids):,} faces")
    print(f"  cluster sets: {len(mesh_map.clustersets)}")
    for name, clusters in mesh_map.clustersets.items():
        sizes = sorted((len(ids) for ids in clusters.values()), reverse=True)
        print(f"    {name}: {len(clusters)} clusters (largest {', '.join(f'{s:,}' for s in sizes[:5])} faces)")
    if mesh_map.poses is not None:
        print(f"  source: {len(mesh_map.poses)} poses" + (", intrinsics" if mesh_map.intrinsics is not None else ""))
    return 0


def _point(text: str, what: str):
    import numpy as np

    from mabdi.errors import ConfigError

    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not np.all(np.isfinite(values)):
        raise ConfigError(f"plan: --{what} must be three numbers x,y,z in metres, got {text!r}")
    return np.array(values)


def cmd_plan(args) -> int:
    from mabdi.io.mesh_map_files import load_map
    from mabdi.io.vtk_files import write_polydata
    from mabdi.mesh_maps.layers import add_cost_layers
    from mabdi.mesh_maps.planning import plan
    from mabdi.polydata import polyline

    start, goal = _point(args.start, "start"), _point(args.goal, "goal")
    mesh_map = load_map(args.map)
    layers = mesh_map.vertex_layers
    if "lethal" not in layers and "cost" not in layers:
        add_cost_layers(mesh_map, faces=False)
        print(
            f"mabdi: warning: {args.map} has no cost layers: computed the default ones (roughness, height "
            "difference, lethal, cost; mabdi.mesh_maps.layers) and planned on them, not on costs of your own",
            file=sys.stderr,
        )
    elif "cost" not in layers:
        print(f"mabdi: warning: {args.map} has a 'lethal' layer but no 'cost' layer: planning by length", file=sys.stderr)
    elif "lethal" not in layers:
        print(f"mabdi: warning: {args.map} has a 'cost' layer but no 'lethal' layer: no vertex is excluded", file=sys.stderr)
    result = plan(mesh_map, start, goal, planner=args.planner)
    if not result.reachable:
        print(f"goal unreachable: no free path from vertex {result.start_vertex} to vertex {result.goal_vertex} ({args.planner})")
        return 1
    print(f"{args.planner}: path of {len(result.path)} points, length {result.length:.3f} m, cost {result.cost:.3f}")
    if args.out is not None:
        write_polydata(polyline(result.path), args.out)
        print(f"wrote {args.out}")
    return 0


def main(argv=None) -> int:
    from mabdi import interrupts

    watching = interrupts.watch()  # for the whole command: a Ctrl-C a library swallows still stops it (mabdi/interrupts.py)
    args = _parser().parse_args(argv)
    import re

    from vtkmodules.vtkCommonCore import vtkLogger, vtkOutputWindow, vtkStringOutputWindow

    from mabdi.errors import MabdiError

    # VTK's own messages (raw, with terminal colour codes) are collected rather than printed:
    # shown at the end with MABDI_VTK_MESSAGES=1, else only counted when a command fails.
    show_vtk = os.environ.get("MABDI_VTK_MESSAGES", "").strip() not in ("", "0")
    previous_window, verbosity = vtkOutputWindow.GetInstance(), vtkLogger.GetCurrentVerbosityCutoff()
    vtk_messages = vtkStringOutputWindow()
    vtkOutputWindow.SetInstance(vtk_messages)
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    import warnings

    def show_warning(message, category, filename, lineno, file=None, line=None) -> None:
        # One line, like the errors: "mabdi: warning: ..." (no source line, no traceback)
        ours = category.__module__.startswith("mabdi")
        print(f"mabdi: warning: {message}" if ours else f"mabdi: warning ({category.__name__}): {message}", file=sys.stderr)

    previous_show, warnings.showwarning = warnings.showwarning, show_warning
    failed = True
    try:
        commands = {
            "run": cmd_run,
            "record": cmd_record,
            "export": cmd_export,
            "info": cmd_info,
            "view": cmd_view,
            "plan": cmd_plan,
            "bench": cmd_bench,
            "sweep": cmd_sweep,
        }
        interrupts.raise_if_interrupted()  # one that came while mabdi was imported
        with interrupts.interrupts_unwrapped():  # Ctrl-C that a library wrapped in an error of its own (numba's)
            status = commands[args.command](args)
        sys.stdout.flush()  # a closed pipe shows here, inside the try
        failed = status != 0
        return status
    except (MabdiError, FileNotFoundError) as exc:
        print(f"mabdi: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mabdi: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader went away (mabdi info MAP | head -1): stop quietly, as Unix tools do, and
        # point stdout at /dev/null so that Python's own flush at exit does not complain.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
        return 141  # 128 + SIGPIPE, the status of a tool the pipe stopped
    finally:
        interrupts.clear()  # the next command in this process (a notebook's) starts clean
        if watching:
            interrupts.unwatch()
        warnings.showwarning = previous_show
        vtkOutputWindow.SetInstance(previous_window)
        vtkLogger.SetStderrVerbosity(verbosity)
        text = re.sub(r"\x1b\[[0-9;]*[A-Za-z]", "", vtk_messages.GetOutput() or "").strip()
        if text and show_vtk:
            print("mabdi: VTK said:\n" + text, file=sys.stderr)
        elif text and failed:
            count = len(re.findall(r"(?m)^(?:ERROR|Warning|Generic Warning)", text)) or 1
            print(f"mabdi: note: VTK printed {count} message(s); MABDI_VTK_MESSAGES=1 shows them", file=sys.stderr)


def console() -> None:
    """The ``mabdi`` command: :func:`main`, then the process ends with its status. After Ctrl-C (130) it ends at
    once, once the output is flushed: Python's teardown would otherwise stop the native libraries' threads that
    the interrupt left running (an EGL render, a TBB pool), and that can crash the process on its way out.
    Everything a run writes is complete or removed by then (mabdi.io.atomic, the run folder's staging)."""
    status = main()
    if status == 130:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # a reader gone, a stream closed: nothing more to say
                pass
        os._exit(status)
    sys.exit(status)


if __name__ == "__main__":
    console()
