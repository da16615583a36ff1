"""Experiment sweeps: a grid of runs, each one run plus its evaluation, on Ray.

``mabdi sweep SWEEP.toml`` (or :func:`run_sweep`) runs every cell of a grid
over run configs and overrides as one Ray task, and writes one table.

SWEEP.toml::

    [sweep]
    name = "surfaces"                                  # default: the file's stem
    configs = ["scenes/table.toml", "scenes/bunnies.toml"]
    frames = 5                                         # optional: run.frames of every cell
    samples = 100000                                   # optional: evaluation samples a side

    [set]                                              # optional: overrides of every cell
    "sensor.noise" = "kinect"

    [grid]                                             # dotted key -> list of values
    "surface.method" = ["pixel_grid", "quadtree"]
    "run.seed" = [0, 1]

The cells are the product configs x every grid list; a key is a dotted path
into the run config (:mod:`mabdi.config`). A bad override fails only its
cell. Each cell is keyed by a hash of its resolved config, the evaluation
settings and the content of every mesh file its scene reads, runs in
``OUT/cells/<id>/`` and writes ``row.json``; a cell whose row exists is not
run again. The sweep writes ``results.csv``, ``results.md`` and
``fscore_triangles.png`` into ``OUT``. Ray (the ``sweep`` extra) runs a
local instance of ``workers`` CPUs or joins a cluster at ``address``.
The rules in full: docs/architecture.md (``mabdi.sweep``).
"""

from __future__ import annotations

import csv
import hashlib
import io
import itertools
import json
import math
import os
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from mabdi.errors import ConfigError, MabdiError

#: The measured columns of a row, after the cell's identity and grid keys.
MEASURES = (
    "fscore_1cm",
    "fscore_2cm",
    "precision_1cm",
    "recall_1cm",
    "precision_2cm",
    "recall_2cm",
    "accuracy_median_mm",
    "triangles",
    "redundancy",
    "seconds",
    "frames_per_second",
    "eval_seconds",
)
#: The identity columns of a row.
IDENTITY = ("cell", "config", "surface", "seed", "frames", "overrides")
#: Bumped when a row's meaning changes, so old rows are not reused.
ROW_VERSION = 1

SWEEP_KEYS = ("name", "configs", "frames", "samples")
TOP_KEYS = ("sweep", "grid", "set")


@dataclass
class SweepSpec:
    """A parsed SWEEP.toml (see the module docs)."""

    name: str
    configs: list[Path]
    grid: dict[str, list] = field(default_factory=dict)
    set: dict[str, object] = field(default_factory=dict)
    frames: int | None = None
    samples: int | None = None
    source: Path | None = None


@dataclass
class Cell:
    """One cell of a sweep: a config file and its overrides, resolved (or the error that stopped it)."""

    index: int
    config_path: Path
    overrides: dict
    id: str
    config: object | None = None  # the resolved RunConfig
    error: str = ""


@dataclass
class SweepResult:
    """A finished sweep: one row per cell (dicts with :data:`IDENTITY`, the grid keys, :data:`MEASURES`, ``error``)."""

    spec: SweepSpec
    out_dir: Path
    rows: list[dict]
    ran: int  # cells run in this call
    reused: int  # cells whose row.json was already there
    seconds: float
    workers: int | None = None
    files: list[Path] = field(default_factory=list)

    @property
    def failed(self) -> list[dict]:
        return [row for row in self.rows if row.get("error")]

    @property
    def ok(self) -> bool:
        return not self.failed


# ---------------------------------------------------------------------------
# The sweep file


def _flatten(table: dict, prefix: str = "") -> dict:
    """``{"surface": {"method": [...]}}`` -> ``{"surface.method": [...]}`` (quoted dotted keys stay as they are)."""
    flat = {}
    for key, value in table.items():
        name = f"{prefix}.{key}" if prefix else key
        if isinstance(value, dict):
            flat.update(_flatten(value, name))
        else:
            flat[name] = value
    return flat


def _resolve_config_path(entry: str, base: Path | None, where: str) -> Path:
    candidates = []
    path = Path(entry)
    if path.is_absolute():
        candidates.append(path)
    else:
        if base is not None:
            candidates.append(base / path)
        candidates.append(Path.cwd() / path)
        if path.suffix == "" and len(path.parts) == 1:
            candidates.append(Path.cwd() / "scenes" / f"{entry}.toml")
    for candidate in candidates:
        if candidate.is_file():
            return candidate.resolve()
    raise ConfigError(f"{where}: key 'sweep.configs': run config {entry!r} not found (looked at {', '.join(map(str, candidates))})")


def sweep_from_dict(data: dict, where: str = "<sweep>", base_dir=None) -> SweepSpec:
    """Build a :class:`SweepSpec` from parsed TOML; config paths relative to ``base_dir``."""
    base = Path(base_dir) if base_dir is not None else None
    unknown = [k for k in data if k not in TOP_KEYS]
    if unknown:
        raise ConfigError(f"{where}: unknown table '{unknown[0]}' (known: {', '.join(TOP_KEYS)})")
    sweep = data.get("sweep", {})
    if not isinstance(sweep, dict):
        raise ConfigError(f"{where}: 'sweep' must be a table")
    unknown = [k for k in sweep if k not in SWEEP_KEYS]
    if unknown:
        raise ConfigError(f"{where}: unknown key 'sweep.{unknown[0]}' (known keys: {', '.join(SWEEP_KEYS)})")
    configs = sweep.get("configs")
    if not isinstance(configs, list) or not configs or not all(isinstance(c, str) for c in configs):
        raise ConfigError(f"{where}: key 'sweep.configs' must be a non-empty list of run config paths")
    for key in ("frames", "samples"):
        value = sweep.get(key)
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ConfigError(f"{where}: key 'sweep.{key}' must be a positive integer, got {value!r}")
    name = sweep.get("name", "")
    if not isinstance(name, str):
        raise ConfigError(f"{where}: key 'sweep.name' must be a string, got {name!r}")
    for table in ("grid", "set"):
        if not isinstance(data.get(table, {}), dict):
            raise ConfigError(f"{where}: '{table}' must be a table of dotted keys")
    grid = _flatten(data.get("grid", {}))
    for key, values in grid.items():
        if not isinstance(values, list) or not values:
            raise ConfigError(f"{where}: key 'grid.{key}' must be a non-empty list of values, got {values!r}")
    return SweepSpec(
        name=name or (Path(where).stem if where != "<sweep>" else "sweep"),
        configs=[_resolve_config_path(c, base, where) for c in configs],
        grid=grid,
        set=_flatten(data.get("set", {})),
        frames=sweep.get("frames"),
        samples=sweep.get("samples"),
    )


def load_sweep(path) -> SweepSpec:
    """Read and check a SWEEP.toml file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: sweep file not found")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    spec = sweep_from_dict(data, where=str(path), base_dir=path.resolve().parent)
    spec.source = path.resolve()
    return spec


# ---------------------------------------------------------------------------
# Overrides


def apply_overrides(config, overrides: dict, where: str = "<overrides>"):
    """A new RunConfig: ``config`` with dotted-key ``overrides`` applied and the whole validated
    (:func:`mabdi.config.with_overrides`, the one override mechanism; a :class:`ConfigError` names
    ``where`` and the key)."""
    from mabdi.config import with_overrides

    return with_overrides(config, overrides, where)


def config_hash(config, samples: int) -> str:
    """Hex digest of the resolved config (as TOML), the evaluation settings and the content of the scene's
    mesh files (:func:`mabdi.io.fingerprint.scene_mesh_digests`; a mesh that cannot be found counts by its
    name, and the cell's run reports it)."""
    from mabdi.config import dump_toml
    from mabdi.io.fingerprint import scene_mesh_digests

    meshes = "".join(f"mesh {digest}\n" for digest in scene_mesh_digests(config))
    text = f"row version {ROW_VERSION}\nsamples {samples}\n{meshes}{dump_toml(config)}"
    return hashlib.sha256(text.encode()).hexdigest()


def _label(overrides: dict) -> str:
    return " ".join(f"{k}={json.dumps(v)}" for k, v in overrides.items())


def sweep_cells(spec: SweepSpec) -> list[Cell]:
    """Every cell of ``spec``, resolved; a cell whose overrides fail carries the error instead of a config."""
    from mabdi.config import load_run_config
    from mabdi.evaluate.metrics import SAMPLES

    samples = spec.samples or SAMPLES
    keys = list(spec.grid)
    cells = []
    bases = {path: load_run_config(path) for path in spec.configs}  # a broken config file fails the sweep
    for index, (path, *values) in enumerate(itertools.product(spec.configs, *(spec.grid[k] for k in keys))):
        overrides = dict(zip(keys, values, strict=True))
        applied = {}
        if spec.frames is not None:
            applied["run.frames"] = spec.frames
        applied.update(spec.set)
        applied.update(overrides)
        where = f"{spec.source or spec.name}: cell {index} ({path.stem}{' ' + _label(overrides) if overrides else ''})"
        try:
            config = apply_overrides(bases[path], applied, where)
        except MabdiError as exc:
            digest = hashlib.sha256(f"{path}\n{json.dumps(applied, sort_keys=True)}".encode()).hexdigest()
            cells.append(Cell(index, path, overrides, f"{path.stem}_{digest[:10]}", error=str(exc)))
            continue
        cells.append(Cell(index, path, overrides, f"{path.stem}_{config_hash(config, samples)[:12]}", config=config))
    return cells


# ---------------------------------------------------------------------------
# One cell (runs in a Ray worker)


def run_cell(config, out_dir, samples: int | None = None) -> dict:
    """Run ``config`` into ``out_dir`` and score it: the measured columns of a row (:data:`MEASURES`).

    What ``mabdi run`` does for one config (its :class:`~mabdi.loop.run_pipeline.RunPipeline`, the
    evaluation with ``samples`` a side); any error becomes ``{"error": ...}``.
    """
    try:
        from functools import partial

        from mabdi.evaluate.metrics import SAMPLES, evaluate_run
        from mabdi.loop import MappingRun
        from mabdi.loop.run_pipeline import RunPipeline

        evaluate = partial(evaluate_run, samples=samples or SAMPLES)
        result = RunPipeline(MappingRun(config), Path(out_dir), evaluate=evaluate, evaluate_empty=True).run()
        metrics = result.scores
        if metrics is None:
            raise ValueError(f"the run was not evaluated: {result.evaluation}")
        eval_seconds = result.evaluation_seconds
        summary = result.summary()
        return {
            "fscore_1cm": metrics.fscore_1cm,
            "fscore_2cm": metrics.fscore_2cm,
            "precision_1cm": metrics.precision_1cm,
            "recall_1cm": metrics.recall_1cm,
            "precision_2cm": metrics.precision_2cm,
            "recall_2cm": metrics.recall_2cm,
            "accuracy_median_mm": metrics.accuracy_median_mm,
            "triangles": metrics.triangles,
            "redundancy": metrics.redundancy,
            "seconds": summary["seconds"],
            "frames_per_second": summary["frames_per_second"],
            "eval_seconds": eval_seconds,
            "error": "",
        }
    except Exception as exc:  # reported as the cell's error; the sweep goes on
        return {"error": f"{type(exc).__name__}: {exc}"}


def _identity(cell: Cell) -> dict:
    config = cell.config
    row = {
        "cell": cell.id,
        "config": str(_display_path(cell.config_path)),
        "surface": _surface_name(config) if config is not None else str(cell.overrides.get("surface.method", "")),
        "seed": config.run.seed if config is not None else cell.overrides.get("run.seed", ""),
        "frames": config.run.frames if config is not None else "",
        "overrides": dict(cell.overrides),
    }
    row.update({key: value for key, value in cell.overrides.items()})
    return row


def _surface_name(config) -> str:
    method = config.surface.method
    return method if isinstance(method, str) else str(method)


def _display_path(path: Path) -> Path:
    try:
        return path.relative_to(Path.cwd())
    except ValueError:
        return path


def _read_row(path: Path, cell_id: str) -> dict | None:
    try:
        row = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return row if isinstance(row, dict) and row.get("cell") == cell_id and not row.get("error") else None


# ---------------------------------------------------------------------------
# The sweep


def run_sweep(path_or_spec, out_dir=None, workers: int | None = None, address: str | None = None, progress=None) -> SweepResult:
    """Run every cell of a sweep (a SWEEP.toml path, a :class:`SweepSpec` or its parsed TOML dict) on Ray.

    ``out_dir`` defaults to ``runs/sweep_<name>``. ``workers``: CPUs of the
    local Ray instance (default: all) and the most cells in flight;
    ``address``: an existing Ray cluster (``"auto"`` or ``host:port``).
    ``progress(line)`` is called with a line per finished cell. Cells with a
    ``row.json`` already in ``out_dir`` are reused without starting Ray.
    Writes the table and plot even when cells fail (see :attr:`SweepResult.failed`).
    """
    from mabdi.evaluate.metrics import SAMPLES
    from mabdi.io.atomic import write_text
    from mabdi.io.run_folder import prepare_output_dir

    start = time.perf_counter()
    if isinstance(path_or_spec, SweepSpec):
        spec = path_or_spec
    elif isinstance(path_or_spec, dict):
        spec = sweep_from_dict(path_or_spec)
    else:
        spec = load_sweep(path_or_spec)
    if workers is not None and workers < 1:
        raise ConfigError(f"sweep: workers must be at least 1, got {workers}")
    out = prepare_output_dir(Path(out_dir) if out_dir is not None else Path("runs") / f"sweep_{spec.name}").resolve()
    samples = spec.samples or SAMPLES
    say = progress or (lambda line: None)

    cells = sweep_cells(spec)
    rows: dict[int, dict] = {}
    todo = []
    reused = 0
    for cell in cells:
        identity = _identity(cell)
        if cell.error:
            rows[cell.index] = {**identity, "error": cell.error}
            say(f"[{cell.index + 1}/{len(cells)}] {cell.id}: error: {cell.error}")
            continue
        stored = _read_row(out / "cells" / cell.id / "row.json", cell.id)
        if stored is not None:
            rows[cell.index] = {**stored, **identity}
            reused += 1
            continue
        todo.append(cell)
    if reused:
        say(f"{reused} of {len(cells)} cells already done in {out}/cells (not run again)")

    def finished(cell: Cell, measured: dict) -> None:
        row = {**_identity(cell), **measured}
        row.setdefault("error", "")
        rows[cell.index] = row
        if not row["error"]:
            write_text(out / "cells" / cell.id / "row.json", json.dumps(row, indent=2) + "\n")
            text = f"F@1cm {row['fscore_1cm']:.3f}, {row['triangles']:,} triangles, {row['seconds']:.1f} s"
        else:
            text = f"error: {row['error']}"
        label = _label(cell.overrides)
        say(f"[{cell.index + 1}/{len(cells)}] {cell.id}{' ' + label if label else ''}: {text}")

    if todo:
        for cell in todo:
            (out / "cells" / cell.id).mkdir(parents=True, exist_ok=True)
        _run_on_ray(todo, out, samples, workers, address, finished)

    ordered = [rows[cell.index] for cell in cells]
    result = SweepResult(
        spec=spec,
        out_dir=out,
        rows=ordered,
        ran=len(todo),
        reused=reused,
        seconds=0.0,
        workers=workers,
    )
    keys = list(spec.grid)
    write_text(out / "results.csv", results_csv(ordered, keys))
    write_text(out / "results.md", results_markdown(ordered, keys, title=spec.name))
    files = [out / "results.csv", out / "results.md"]
    plot = write_sweep_plot(ordered, out / "fscore_triangles.png", title=spec.name)
    if plot is not None:
        files.append(plot)
    result.files = files
    result.seconds = time.perf_counter() - start
    return result


def _run_on_ray(todo: list[Cell], out: Path, samples: int, workers, address, finished) -> None:
    """Run ``todo`` as Ray tasks, at most ``workers`` in flight; ``finished(cell, measured)`` as each ends."""
    try:
        import ray
    except ImportError:
        raise MabdiError('sweeps run on Ray, which is not installed: pip install "mabdi[sweep]"') from None

    started = False
    if not ray.is_initialized():
        import logging

        options = {"include_dashboard": False, "logging_level": logging.WARNING, "log_to_driver": False}
        if address:
            ray.init(address=address, **options)
        else:
            ray.init(num_cpus=workers or os.cpu_count() or 1, **options)
        started = True
    try:
        task = ray.remote(num_cpus=1, max_retries=1)(run_cell)
        limit = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
        waiting = list(todo)
        running: dict = {}
        while waiting or running:
            while waiting and len(running) < limit:
                cell = waiting.pop(0)
                running[task.remote(cell.config, str(out / "cells" / cell.id), samples)] = cell
            done, _ = ray.wait(list(running), num_returns=1)
            for ref in done:
                cell = running.pop(ref)
                try:
                    measured = ray.get(ref)
                except Exception as exc:  # the worker died (a crash in native code) or Ray failed the task
                    measured = {"error": f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"}
                finished(cell, measured)
    finally:
        if started:
            ray.shutdown()


# ---------------------------------------------------------------------------
# The table and the plot


def _columns(rows: list[dict], keys: list[str]) -> list[str]:
    return [*IDENTITY, *keys, *MEASURES, "error"]


def _csv_value(value) -> str:
    if value is None:
        return ""
    if isinstance(value, (dict, list)):
        return json.dumps(value)
    return str(value)


def results_csv(rows: list[dict], keys: list[str]) -> str:
    """results.csv: :data:`IDENTITY`, the grid keys, :data:`MEASURES`, ``error``; one row per cell."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    columns = _columns(rows, keys)
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_csv_value(row.get(c)) for c in columns])
    return buffer.getvalue()


def _cell_text(value, digits: int = 3) -> str:
    if value is None or value == "":
        return ""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.{digits}f}"
    if isinstance(value, (dict, list)):
        return json.dumps(value)
    return str(value).replace("|", "\\|").replace("\n", " ")


def results_markdown(rows: list[dict], keys: list[str], title: str = "") -> str:
    """results.md: the sweep as a Markdown table (the grid keys as columns)."""
    header = ["cell", "config", *(k for k in keys), "F@1cm", "F@2cm", "P@1cm", "R@1cm", "triangles", "redundancy", "run s", "frames/s", "error"]
    if "surface.method" not in keys:
        header.insert(2, "surface")
    lines = [f"# Sweep {title}", ""] if title else []
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in rows:
        values = [row.get("cell"), row.get("config")]
        if "surface.method" not in keys:
            values.append(row.get("surface"))
        values += [row.get(k) for k in keys]
        values += [row.get(m) for m in ("fscore_1cm", "fscore_2cm", "precision_1cm", "recall_1cm", "triangles")]
        redundancy = row.get("redundancy")
        values.append(f"{100.0 * redundancy:.1f}%" if isinstance(redundancy, float) else "")
        seconds, fps = row.get("seconds"), row.get("frames_per_second")
        values.append(f"{seconds:.1f}" if isinstance(seconds, float) else "")
        values.append(f"{fps:.1f}" if isinstance(fps, float) else "")
        values.append(row.get("error"))
        lines.append("| " + " | ".join(_cell_text(v) for v in values) + " |")
    failed = sum(1 for row in rows if row.get("error"))
    lines += ["", f"{len(rows)} cells, {failed} failed."]
    return "\n".join(lines) + "\n"


def write_sweep_plot(rows: list[dict], path, title: str = "") -> Path | None:
    """F@1cm against triangles (log scale), one colour per surface, written atomically as PNG; None without rows to plot."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from mabdi.io.atomic import atomic_output
    from mabdi.io.plots import COLOURS

    good = [r for r in rows if not r.get("error") and isinstance(r.get("triangles"), int)]
    if not good:
        return None
    figure = Figure(figsize=(8, 5), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    surfaces = list(dict.fromkeys(str(r.get("surface", "")) for r in good))
    for surface, colour in zip(surfaces, COLOURS * 4, strict=False):
        points = [r for r in good if str(r.get("surface", "")) == surface]
        axes.scatter([max(r["triangles"], 1) for r in points], [r["fscore_1cm"] for r in points], color=colour, label=surface, s=36)
    if len(good) <= 24:
        for r in good:
            note = ", ".join(f"{k.rsplit('.', 1)[-1]}={v}" for k, v in r.get("overrides", {}).items() if k != "surface.method")
            if note:
                axes.annotate(note, (max(r["triangles"], 1), r["fscore_1cm"]), fontsize=7, xytext=(4, 3), textcoords="offset points")
    axes.set_xscale("log")
    axes.set_xlabel("triangles in the map")
    axes.set_ylabel("F-score at 1 cm")
    axes.grid(True, alpha=0.3)
    axes.legend(title="surface")
    if title:
        axes.set_title(title)
    figure.tight_layout()
    with atomic_output(path) as temporary:
        figure.savefig(str(temporary), format="png")
    return Path(path)
