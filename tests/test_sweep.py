"""mabdi sweep: a grid of runs on Ray, one table; done cells reused; a broken cell reported, the others run."""

from __future__ import annotations

import csv
import json

import pytest

from mabdi.errors import ConfigError
from mabdi.sweep import apply_overrides, load_sweep, run_cell, run_sweep, sweep_cells, sweep_from_dict

from conftest import SCENES

#: Evaluation samples a side in these tests (the default 100,000 only makes them slower).
SAMPLES = 20_000


def _spec(grid: dict) -> dict:
    return {"sweep": {"name": "test", "configs": [str(SCENES / "table.toml")], "frames": 5, "samples": SAMPLES}, "grid": grid}


GRID = {"surface.method": ["pixel_grid", "quadtree"], "run.seed": [0, 1]}


@pytest.fixture(scope="module")
def ray_session():
    """One local Ray instance with two CPUs for every test here (starting Ray takes seconds)."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def sweep_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("sweep")


@pytest.fixture(scope="module")
def first_sweep(ray_session, sweep_dir):
    return run_sweep(_spec(GRID), sweep_dir, workers=2)


def test_the_sweep_file_is_checked(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(f'[sweep]\nconfigs = ["{SCENES / "table.toml"}"]\nframe = 5\n')
    with pytest.raises(ConfigError, match=r"bad\.toml.*'sweep\.frame'"):
        load_sweep(path)
    path.write_text(f'[sweep]\nconfigs = ["{SCENES / "table.toml"}"]\n[grid]\n"run.seed" = 1\n')
    with pytest.raises(ConfigError, match=r"bad\.toml.*'grid\.run\.seed' must be a non-empty list"):
        load_sweep(path)
    path.write_text('[sweep]\nconfigs = ["no_such_scene.toml"]\n')
    with pytest.raises(ConfigError, match="no_such_scene"):
        load_sweep(path)


def test_cells_are_the_product_and_unquoted_dotted_keys_mean_the_same(tmp_path, monkeypatch):
    path = tmp_path / "grid.toml"
    path.write_text(
        '[sweep]\nconfigs = ["table"]\nframes = 3\n[set]\n"sensor.noise" = "kinect"\n'
        '[grid]\nsurface.method = ["pixel_grid", "quadtree"]\n"run.seed" = [0, 1, 2]\n'
    )
    monkeypatch.chdir(SCENES.parent)  # a bare name is scenes/<name>.toml in the working folder
    spec = load_sweep(path)
    assert spec.grid == {"surface.method": ["pixel_grid", "quadtree"], "run.seed": [0, 1, 2]}
    cells = sweep_cells(spec)
    assert len(cells) == 6 and not any(c.error for c in cells)
    assert [(c.config.surface.method, c.config.run.seed) for c in cells[:3]] == [("pixel_grid", 0), ("pixel_grid", 1), ("pixel_grid", 2)]
    assert all(c.config.run.frames == 3 and c.config.sensor.noise == "kinect" for c in cells)
    assert len({c.id for c in cells}) == 6  # keyed by the resolved config


def test_an_unknown_override_is_that_cells_error():
    cells = sweep_cells(sweep_from_dict(_spec({"surface.metod": ["quadtree"], "run.seed": [0]})))
    assert len(cells) == 1 and cells[0].config is None
    assert "metod" in cells[0].error


def test_an_error_inside_a_run_is_returned_not_raised(tmp_path):
    cells = sweep_cells(sweep_from_dict(_spec({"scene.objects.0.type": ["mesh"], "scene.objects.0.mesh": ["no_such_mesh.ply"]})))
    measured = run_cell(cells[0].config, tmp_path, SAMPLES)
    assert "no_such_mesh.ply" in measured["error"]


@pytest.mark.slow
def test_a_sweep_on_ray_equals_the_runs_made_one_by_one(first_sweep, sweep_dir):
    from mabdi.config import load_run_config
    from mabdi.evaluate import evaluate_run
    from mabdi.loop import MappingRun

    assert first_sweep.ok and first_sweep.ran == 4 and first_sweep.reused == 0
    with open(sweep_dir / "results.csv", newline="") as stream:
        table = list(csv.DictReader(stream))
    assert len(table) == 4
    assert [(r["surface.method"], r["run.seed"]) for r in table] == [("pixel_grid", "0"), ("pixel_grid", "1"), ("quadtree", "0"), ("quadtree", "1")]
    assert "| quadtree | 1 |" in (sweep_dir / "results.md").read_text()
    assert (sweep_dir / "fscore_triangles.png").stat().st_size > 0
    for row, csv_row in zip(first_sweep.rows, table, strict=True):
        assert json.loads((sweep_dir / "cells" / row["cell"] / "row.json").read_text())["triangles"] == row["triangles"]
        assert (sweep_dir / "cells" / row["cell"] / "world_mesh.vtp").is_file()
        overrides = {"run.frames": 5, "surface.method": row["surface.method"], "run.seed": row["run.seed"]}
        config = apply_overrides(load_run_config(SCENES / "table.toml"), overrides)
        simulation = MappingRun(config)
        result = simulation.run()
        metrics = evaluate_run(simulation, result, samples=SAMPLES)
        assert row["triangles"] == metrics.triangles == int(csv_row["triangles"])
        # same frames, same samples: the same numbers, to the last bit
        assert row["fscore_1cm"] == metrics.fscore_1cm and row["fscore_2cm"] == metrics.fscore_2cm
        assert float(csv_row["fscore_1cm"]) == metrics.fscore_1cm


@pytest.mark.slow
def test_a_rerun_runs_no_cell(first_sweep, sweep_dir):
    again = run_sweep(_spec(GRID), sweep_dir, workers=2)
    assert again.ran == 0 and again.reused == 4
    assert again.rows == first_sweep.rows


@pytest.mark.slow
def test_a_broken_cell_is_reported_and_the_others_complete(first_sweep, sweep_dir, capsys):
    from mabdi.cli import main

    spec = sweep_dir / "broken.toml"
    spec.write_text(
        f'[sweep]\nname = "broken"\nconfigs = ["{SCENES / "table.toml"}"]\nframes = 5\nsamples = {SAMPLES}\n'
        '[grid]\n"run.seed" = [0, 1, 2, -1]\n'
    )
    status = main(["sweep", str(spec), "--out", str(sweep_dir), "--workers", "2"])
    out = capsys.readouterr().out
    assert status == 1
    assert "run.seed" in out and "must be >= 0" in out
    with open(sweep_dir / "results.csv", newline="") as stream:
        table = list(csv.DictReader(stream))
    assert [r["run.seed"] for r in table] == ["0", "1", "2", "-1"]
    assert [bool(r["error"]) for r in table] == [False, False, False, True]
    assert all(float(r["fscore_1cm"]) > 0.9 for r in table[:3])
    # seeds 0 and 1 of the pixel grid were cells of the first sweep: reused, only seed 2 ran
    assert "1 cells run, 2 already done, 1 failed" in out
