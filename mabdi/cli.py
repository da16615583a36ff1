"""The ``mabdi`` command line.

    mabdi run scenes/bunnies.toml [--frames N] [--out DIR] [--noise MODEL] [--seed S] [--backend B]

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

    run = commands.add_parser("run", help="simulate a run config: render the sensor's depth images along its path")
    run.add_argument("config", type=Path, help="run config (TOML), e.g. scenes/bunnies.toml")
    run.add_argument("--frames", type=int, help="number of frames (overrides run.frames)")
    run.add_argument("--out", type=Path, help="output folder (default: runs/<config name>)")
    run.add_argument("--noise", help="noise model: none, zbuffer or kinect (overrides sensor.noise)")
    run.add_argument("--seed", type=int, help="noise seed (overrides run.seed)")
    run.add_argument("--backend", help="render backend: egl or osmesa (overrides sensor.backend)")
    run.add_argument("--quiet", action="store_true", help="no progress output")
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
    validate_run_config(config, where="command line")


def cmd_run(args) -> int:
    from mabdi.config import load_run_config
    from mabdi.simulate import Simulation

    config = load_run_config(args.config)
    _apply_overrides(config, args)
    out_dir = args.out if args.out is not None else Path("runs") / (config.run.name or args.config.stem)
    simulation = Simulation(config)

    def progress(i, image):
        if not args.quiet:
            print(f"\rframe {i + 1}/{config.run.frames}", end="", flush=True)

    summary = simulation.run(out_dir, progress=progress)
    if not args.quiet:
        print()
    per_frame = 1000.0 * summary.seconds["render"] / max(summary.frames, 1)
    print(f"{summary.frames} frames rendered ({per_frame:.1f} ms per frame); outputs in {out_dir}")
    return 0


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    from mabdi.errors import MabdiError

    try:
        return {"run": cmd_run}[args.command](args)
    except (MabdiError, FileNotFoundError) as exc:
        print(f"mabdi: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mabdi: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
