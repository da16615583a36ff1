"""The ``mabdi`` command line.

    mabdi run CONFIG [--frames N] [--out DIR] [--noise MODEL] [--seed N] [--surface NAME]
                     [--no-classifier] [--depth-images] [--backend B] [--quiet]
    mabdi export IN OUT [--layout mesh_tools|lvr2]   convert a map between VTP, PLY, OBJ, STL and HDF5
    mabdi info MAP               counts, bounds, layers, labels and cluster sets of a map
    mabdi view PATH [--colour frame|normal|LAYER] [--out PNG]   look at a map or a run folder
    mabdi plan MAP --start x,y,z --goal x,y,z [--planner dijkstra|fmm] [--out path.vtp]
    mabdi bench [--scene NAME|CONFIG] [--methods M ...] [--frames N] [--out DIR]

Options override the config file; the resolved config is written with the
outputs. Errors a user can cause (a bad config, a missing mesh) print one
line ``mabdi: error: ...`` and exit with status 2, without a traceback.
Heavy imports (VTK) happen inside the commands, so ``mabdi --help`` is quick.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mabdi", description="Mesh maps from a moving depth sensor (MABDI).")
    commands = parser.add_subparsers(dest="command", required=True)

    run = commands.add_parser("run", help="run the MABDI loop on a run config (scenes/*.toml) and write the map")
    run.add_argument("config", type=Path, help="run config (TOML), e.g. scenes/bunnies.toml")
    run.add_argument("--frames", type=int, help="number of frames (overrides run.frames)")
    run.add_argument("--out", type=Path, help="output folder (default: runs/<config name>)")
    run.add_argument("--noise", help="noise model: none, zbuffer or kinect (overrides sensor.noise)")
    run.add_argument("--seed", type=int, help="noise seed (overrides run.seed)")
    run.add_argument("--surface", help="surface filter: pixel_grid, quadtree or voxel_planes (overrides surface.method)")
    run.add_argument(
        "--no-classifier", action="store_true", help="black box: mesh every valid pixel every frame (classifier.enabled = false)"
    )
    run.add_argument("--depth-images", action="store_true", help="also write D, E and labels of every frame as VTI")
    run.add_argument("--h5", action="store_true", help="also write world_mesh.h5 with cost layers, labels, poses (output.h5)")
    run.add_argument("--movie", action="store_true", help="also write movie.mp4 of the dashboard and PNG snapshots (output.movie)")
    run.add_argument("--backend", help="render backend: egl or osmesa (overrides sensor.backend)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.add_argument("--no-eval", action="store_true", help="skip the evaluation against the ground truth")

    export = commands.add_parser("export", help="convert a saved map between VTP, PLY, OBJ, STL and HDF5 (.h5)")
    export.add_argument("source", type=Path, help="map file to read (.vtp, .ply, .obj, .stl, .h5)")
    export.add_argument("target", type=Path, help="file to write; the format follows the suffix")
    export.add_argument("--layout", default="mesh_tools", help="HDF5 layout: mesh_tools (default) or lvr2")

    info = commands.add_parser("info", help="counts, bounds, layers, labels and cluster sets of a map file")
    info.add_argument("map", type=Path, help="map file (.h5, .vtp, .ply, .obj, .stl)")

    view = commands.add_parser("view", help="show a map or a run folder (a PNG when there is no display)")
    view.add_argument("path", type=Path, help="map file (.vtp, .ply, .h5, ...) or run folder")
    view.add_argument("--colour", "--color", default="frame", help="frame (default), normal, or a layer name (cost, ...)")
    view.add_argument("--out", type=Path, help="write a PNG here instead of opening a window")

    plan = commands.add_parser("plan", help="plan a path on a map (Dijkstra or fast marching)")
    plan.add_argument("map", type=Path, help="map file (.h5, .vtp, .ply, .obj, .stl)")
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

    sweep = commands.add_parser("sweep", help="a grid of runs and their evaluations on Ray (SWEEP.toml), one table")
    sweep.add_argument("sweep", type=Path, help="sweep file (TOML: [sweep] configs, frames; [grid] dotted key = [values])")
    sweep.add_argument("--out", type=Path, help="output folder (default: runs/sweep_<name>)")
    sweep.add_argument("--workers", type=int, help="CPUs of the local Ray instance and most cells in flight (default: all cores)")
    sweep.add_argument("--address", help="an existing Ray cluster to run on (host:port or auto) instead of a local instance")
    return parser


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


def _apply_overrides(config, args) -> None:
    from mabdi.config import validate_run_config

    if args.frames is not None:
        config.run.frames = args.frames
    if args.noise is not None:
        config.sensor.noise = args.noise
    if getattr(args, "seed", None) is not None:
        config.run.seed = args.seed
    if getattr(args, "backend", None) is not None:
        config.sensor.backend = args.backend
    if getattr(args, "surface", None) is not None:
        config.surface.method = args.surface
    if getattr(args, "no_classifier", False):
        config.classifier.enabled = False
    if args.command == "run" and args.out is not None:
        config.output.dir = str(args.out)
    if getattr(args, "depth_images", False):
        config.output.depth_images = True
    if getattr(args, "h5", False):
        config.output.h5 = True
    if getattr(args, "movie", False):
        config.output.movie = True
    validate_run_config(config, where="command line")


class ProgressBar:
    """A one-line progress bar on stderr (only when stderr is a terminal)."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.total = total
        self.enabled = enabled and sys.stderr.isatty()

    def __call__(self, record) -> None:
        if not self.enabled:
            return
        done = record.frame + 1
        width = 30
        filled = int(width * done / self.total)
        bar = "#" * filled + "." * (width - filled)
        sys.stderr.write(f"\r[{bar}] frame {done}/{self.total}  map {record.cells_total:,} triangles ")
        sys.stderr.flush()
        if done == self.total:
            sys.stderr.write("\n")


def cmd_run(args) -> int:
    from mabdi.config import load_run_config
    from mabdi.simulate import Simulation

    config = load_run_config(args.config)
    _apply_overrides(config, args)
    out_dir = Path(config.output.dir) if config.output.dir else Path("runs") / (config.run.name or args.config.stem)
    simulation = Simulation(config)
    progress = ProgressBar(config.run.frames, not args.quiet)
    movie = None
    if config.output.movie:
        from mabdi.viz.record import run_with_movie

        result, movie, dashboard_ms = run_with_movie(simulation, out_dir, config.output.snapshots or None, progress=progress)
    else:
        result = simulation.run(out_dir, progress=progress)
    summary = result.summary()
    mode = "classifier on" if summary["classifier"] else "black box (classifier off)"
    print(
        f"{summary['frames']} frames in {summary['seconds']:.1f} s ({summary['frames_per_second']:.1f} frames/s), "
        f"{mode}, surface {summary['surface']}"
    )
    print(f"map: {summary['cells']:,} triangles, {summary['points']:,} points, {summary['map_bytes'] / 2**20:.1f} MB")
    if not args.no_eval and config.scene.objects:
        import json

        from mabdi.evaluate import evaluate_run
        from mabdi.io.atomic import write_text

        metrics = evaluate_run(simulation, result)
        summary["metrics"] = metrics.as_dict()
        write_text(out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
        growth = metrics.growth_per_circle
        second = f", 2nd circle adds {100.0 * growth[1] / growth[0]:.1f}% of the 1st" if len(growth) > 1 and growth[0] else ""
        print(
            f"vs ground truth: F@1cm {metrics.fscore_1cm:.3f}, F@2cm {metrics.fscore_2cm:.3f}, "
            f"accuracy median {metrics.accuracy_median_mm:.2f} mm, redundancy {100.0 * (metrics.redundancy or 0.0):.1f}%{second}"
        )
    if movie is not None:
        print(f"movie: {movie} ({config.run.frames} frames, dashboard {dashboard_ms:.0f} ms per frame)")
    print(f"results in {out_dir}/ (world_mesh.vtp, world_mesh.ply, metrics.csv, summary.json, elements.png)")
    return 0


def cmd_view(args) -> int:
    from mabdi.viz.viewer import view

    written = view(args.path, colour=args.colour, screenshot=args.out)
    if written is not None:
        print(f"no display: wrote {written}" if args.out is None else f"wrote {written}")
    return 0


def cmd_bench(args) -> int:
    from mabdi.config import load_run_config
    from mabdi.evaluate.bench import METHODS, markdown_table, run_bench

    path = _find_config(args.scene)
    config = load_run_config(path)
    _apply_overrides(config, args)
    out_dir = args.out if args.out is not None else Path("runs") / f"bench_{config.run.name or path.stem}"
    command = "mabdi " + " ".join(sys.argv[1:]) if sys.argv[1:2] == ["bench"] else None
    bench = run_bench(config, args.methods or METHODS, out_dir, progress=lambda line: print(line, flush=True), command=command)
    print()
    print(markdown_table(bench))
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
    from mabdi.io.map_files import is_hdf5, load_map, save_map
    from mabdi.io.vtk_files import read_mesh_file, write_mesh_file

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
    from mabdi.io.map_files import is_hdf5, load_map

    mesh_map = load_map(args.map)
    low, high = mesh_map.bounds()
    layout = f" ({map_layout(args.map)} layout)" if is_hdf5(args.map) else ""
    print(f"{args.map}{layout}")
    print(f"  {mesh_map.number_of_vertices:,} vertices, {mesh_map.number_of_faces:,} triangles")
    print(f"  bounds: x {low[0]:.3f} .. {high[0]:.3f}, y {low[1]:.3f} .. {high[1]:.3f}, z {low[2]:.3f} .. {high[2]:.3f} m")
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
    from mabdi.io.map_files import load_map
    from mabdi.io.vtk_files import write_polydata
    from mabdi.maps.layers import add_cost_layers
    from mabdi.maps.planning import plan
    from mabdi.polydata import polyline

    start, goal = _point(args.start, "start"), _point(args.goal, "goal")
    mesh_map = load_map(args.map)
    if "lethal" not in mesh_map.vertex_layers:
        print("map has no cost layers: computing them (mabdi.maps.layers defaults)")
        add_cost_layers(mesh_map, faces=False)
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
    args = _parser().parse_args(argv)
    from mabdi.errors import MabdiError

    try:
        commands = {
            "run": cmd_run,
            "export": cmd_export,
            "info": cmd_info,
            "view": cmd_view,
            "plan": cmd_plan,
            "bench": cmd_bench,
            "sweep": cmd_sweep,
        }
        return commands[args.command](args)
    except (MabdiError, FileNotFoundError) as exc:
        print(f"mabdi: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mabdi: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
