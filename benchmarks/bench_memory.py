"""Benchmark: resident memory at start-up (issue #23, item 4: what the process holds before the map).

Resident memory (VmRSS, split into anonymous memory and mapped files such as
shared libraries, and the peak VmHWM) of one process at each step of
a run of ``scenes/table.toml``: the interpreter alone, after ``import
mabdi``, after building the run (``load_run_config`` + ``MappingRun``),
after frame 1 and after 30 frames. Then what each heavy import costs on
its own: a fresh interpreter per module, RSS before and after importing
it, and its import time (so the numbers are not hidden by what another
import already loaded). Last, which optional heavy packages ``import
mabdi`` loaded (none should: they are imported where they are used).

    python benchmarks/bench_memory.py [--frames 30] [--surface pixel_grid] [--json results.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: Imported one at a time, each in a fresh interpreter.
IMPORTS = [
    "numpy",
    "mabdi",
    "vtkmodules.vtkCommonDataModel",
    "vtkmodules.vtkFiltersCore",
    "vtkmodules.vtkRenderingOpenGL2",
    "vtkmodules.all",
    "numba",
    "scipy.spatial",
    "scipy.sparse",
    "matplotlib.pyplot",
    "open3d",
    "h5py",
    "pyvista",
    "rerun",
    "rosbags.rosbag2",
    "PIL.Image",
]

#: Packages a run of the simulated table does not need (``import mabdi`` should not load them).
OPTIONAL = ["matplotlib", "open3d", "h5py", "pyvista", "rerun", "rosbags", "PIL", "vtkmodules.all", "vtkmodules.vtkIOXML"]

_ONE_IMPORT = """
import importlib, json, sys, time
def rss():
    with open('/proc/self/status') as status:
        for line in status:
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) * 1024
before = rss()
start = time.perf_counter()
try:
    importlib.import_module(sys.argv[1])
    error = None
except Exception as exc:
    error = f'{type(exc).__name__}: {exc}'
print(json.dumps({'before': before, 'after': rss(), 'seconds': time.perf_counter() - start, 'error': error}))
"""


def status_bytes(field: str) -> int:
    """A ``/proc/self/status`` field in bytes (VmRSS, VmHWM)."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    return 0


def import_cost(module: str) -> dict:
    """RSS before/after importing ``module`` alone in a fresh interpreter, and the seconds it took."""
    env = dict(os.environ, VTK_DEFAULT_OPENGL_WINDOW=os.environ.get("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow"))
    done = subprocess.run([sys.executable, "-c", _ONE_IMPORT, module], capture_output=True, text=True, env=env, cwd=REPO)
    lines = done.stdout.strip().splitlines()
    if done.returncode or not lines:
        return {"module": module, "error": (done.stderr.strip().splitlines() or ["failed"])[-1]}
    return {"module": module, **json.loads(lines[-1])}


def run_steps(frames: int, surface: str | None) -> tuple[list[dict], list[str]]:
    """RSS at each step of a run of the table, in this process (called before anything heavy is imported)."""
    steps = []

    def mark(name: str, seconds: float) -> None:
        steps.append(
            {
                "step": name,
                "rss": status_bytes("VmRSS"),
                "anon": status_bytes("RssAnon"),
                "file": status_bytes("RssFile"),
                "peak": status_bytes("VmHWM"),
                "seconds": seconds,
            }
        )

    mark("start (interpreter + this script)", 0.0)
    start = time.perf_counter()
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import mabdi

    mark("after import mabdi", time.perf_counter() - start)
    loaded = sorted(name for name in OPTIONAL if name in sys.modules)
    start = time.perf_counter()
    config = mabdi.config.load_run_config(REPO / "scenes" / "table.toml")
    if surface:
        mabdi.config.set_value(config, "surface.method", surface)
    mabdi.config.set_value(config, "run.frames", max(frames, 1))
    from mabdi.loop.mapping_run import MappingRun

    simulation = MappingRun(config)
    mark("after building the run", time.perf_counter() - start)
    start = time.perf_counter()
    simulation.step(0)
    mark("after frame 1", time.perf_counter() - start)
    start = time.perf_counter()
    for i in range(1, frames):
        simulation.step(i)
    mark(f"after {frames} frames", time.perf_counter() - start)
    steps[-1]["map_bytes"] = int(simulation.loop.memory_bytes()) if hasattr(simulation.loop, "memory_bytes") else None
    return steps, loaded


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--surface", default=None, help="surface.method (default: the scene's)")
    parser.add_argument("--no-imports", action="store_true", help="skip the per-import table")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    steps, loaded = run_steps(args.frames, args.surface)
    mb = 1 / 2**20
    print(f"Resident memory, a run of scenes/table.toml ({args.frames} frames)")
    print("| step | RSS MB | anon MB | file MB | peak MB | seconds |\n|---|---:|---:|---:|---:|---:|")
    for step in steps:
        print(
            f"| {step['step']} | {step['rss'] * mb:.1f} | {step['anon'] * mb:.1f} | {step['file'] * mb:.1f} | "
            f"{step['peak'] * mb:.1f} | {step['seconds']:.2f} |"
        )
    if steps[-1].get("map_bytes") is not None:
        print(f"map bytes (MabdiLoop.memory_bytes): {steps[-1]['map_bytes'] * mb:.2f} MB")
    print(f"optional packages loaded by import mabdi: {', '.join(loaded) or 'none'}")

    costs = [] if args.no_imports else [import_cost(module) for module in IMPORTS]
    if costs:
        print("\nEach import alone, in a fresh interpreter")
        print("| module | RSS before MB | after MB | + MB | seconds |\n|---|---:|---:|---:|---:|")
        for cost in costs:
            if cost.get("error"):
                print(f"| {cost['module']} | - | - | - | not importable: {cost['error']} |")
                continue
            print(
                f"| {cost['module']} | {cost['before'] * mb:.1f} | {cost['after'] * mb:.1f} | "
                f"{(cost['after'] - cost['before']) * mb:.1f} | {cost['seconds']:.2f} |"
            )
    if args.json:
        args.json.write_text(json.dumps({"steps": steps, "loaded_by_import": loaded, "imports": costs}, indent=2))


if __name__ == "__main__":
    main()
