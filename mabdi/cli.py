"""The ``mabdi`` command line.

    mabdi run CONFIG [--frames N] [--out DIR] [--noise MODEL] [--seed N] [--surface NAME]
                     [--no-classifier] [--depth-images] [--backend B] [--quiet]
    mabdi export IN OUT          convert a saved map between VTP, PLY, OBJ and STL

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
    run.add_argument("--surface", help="surface filter: pixel_grid (overrides surface.method)")
    run.add_argument(
        "--no-classifier", action="store_true", help="black box: mesh every valid pixel every frame (classifier.enabled = false)"
    )
    run.add_argument("--depth-images", action="store_true", help="also write D, E and labels of every frame as VTI")
    run.add_argument("--backend", help="render backend: egl or osmesa (overrides sensor.backend)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")

    export = commands.add_parser("export", help="convert a saved map between VTP, PLY, OBJ and STL")
    export.add_argument("source", type=Path, help="map file to read (.vtp, .ply, .obj, .stl)")
    export.add_argument("target", type=Path, help="file to write; the format follows the suffix")
    return parser


def _apply_overrides(config, args) -> None:
    from mabdi.config import validate_run_config

    if args.frames is not None:
        config.run.frames = args.frames
    if args.noise is not None:
        config.sensor.noise = args.noise
    if args.seed is not None:
        config.run.seed = args.seed
    if args.backend is not None:
        config.sensor.backend = args.backend
    if args.surface is not None:
        config.surface.method = args.surface
    if args.no_classifier:
        config.classifier.enabled = False
    if args.out is not None:
        config.output.dir = str(args.out)
    if args.depth_images:
        config.output.depth_images = True
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
    result = simulation.run(out_dir, progress=ProgressBar(config.run.frames, not args.quiet))
    summary = result.summary()
    mode = "classifier on" if summary["classifier"] else "black box (classifier off)"
    print(
        f"{summary['frames']} frames in {summary['seconds']:.1f} s ({summary['frames_per_second']:.1f} frames/s), "
        f"{mode}, surface {summary['surface']}"
    )
    print(f"map: {summary['cells']:,} triangles, {summary['points']:,} points, {summary['map_bytes'] / 2**20:.1f} MB")
    print(f"results in {out_dir}/ (world_mesh.vtp, world_mesh.ply, metrics.csv, summary.json, elements.png)")
    return 0


def cmd_export(args) -> int:
    from mabdi.io.vtk_files import read_mesh_file, write_mesh_file

    if args.source.resolve() == args.target.resolve():
        from mabdi.errors import ConfigError

        raise ConfigError(f"export: source and target are the same file ({args.source})")
    mesh = read_mesh_file(args.source)
    write_mesh_file(mesh, args.target)
    print(f"wrote {args.target} ({mesh.GetNumberOfPoints():,} points, {mesh.GetNumberOfCells():,} cells)")
    return 0


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    from mabdi.errors import MabdiError

    try:
        return {"run": cmd_run, "export": cmd_export}[args.command](args)
    except (MabdiError, FileNotFoundError) as exc:
        print(f"mabdi: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mabdi: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
