"""One run path: RunPipeline's steps, its observers, and the one override mechanism."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mabdi.config import load_run_config, set_value, with_overrides
from mabdi.errors import ConfigError
from mabdi.loop import MappingRun
from mabdi.loop.run_pipeline import STEPS, RunObserver, RunPipeline
from mabdi.sweep import apply_overrides

SCENES = Path(__file__).resolve().parents[1] / "scenes"

#: Measured before the run was one pipeline (MappingRun.run, then cli's evaluation and finish_run):
#: scenes/table.toml, 3 frames, pixel grid (the default surface then, set here); since the simulator states its poses exact, the map of
#: `--no-registration` (370,176 when the registration still moved the exact poses by a fraction of a mm).
TABLE_3_TRIANGLES = 370_182
SUMMARY_KEYS = {
    "cells", "cells_removed", "classifier", "frames", "frames_per_second", "intrinsics", "map_bytes", "mean_ms",
    "name", "noise", "noise_calibration", "pixel_holes_filled", "points", "registration", "removal", "render", "seconds", "seed", "source",
    "surface", "surface_parameters",
}
RUN_FILES = {
    ".mabdi-run.json", "config.toml", "elements.png", "metrics.csv", "path.vtp", "poses.npy", "poses_given.npy",
    "poses_true.npy", "scene.vtp", "summary.json", "trajectory.txt", "world_mesh.ply", "world_mesh.vtp",
}


def table(frames: int):
    config = load_run_config(SCENES / "table.toml")
    return with_overrides(config, {"run.frames": frames, "output.checkpoint_every": 2})


class Log(RunObserver):
    """Writes down every hook it is called with."""

    def __init__(self, name: str, events: list) -> None:
        self.name, self.events = name, events

    def on_start(self, pipeline):
        self.events.append((self.name, "start", pipeline.folder is not None))

    def on_frame(self, pipeline, record):
        self.events.append((self.name, "frame", record.frame, pipeline.simulation.loop.mesh().GetNumberOfCells()))

    def on_loop_end(self, pipeline, result):
        self.events.append((self.name, "loop_end", (result.out_dir / "summary.json").exists()))

    def on_finish(self, pipeline, result):
        self.events.append((self.name, "finish", (result.out_dir / "summary.json").exists()))

    def on_abort(self, pipeline, error):
        self.events.append((self.name, "abort", type(error).__name__))


def test_observers_see_every_frame_in_order_and_the_outputs_are_as_before(tmp_path):
    events: list = []
    scored = []

    def evaluate(simulation, result):
        scored.append(result.mesh.GetNumberOfCells())
        return None  # not scored here: the metrics have their own tests

    pipeline = RunPipeline(MappingRun(with_overrides(table(3), {"surface.method": "pixel_grid"})), tmp_path / "run", [Log("a", events), Log("b", events)], evaluate=evaluate)
    result = pipeline.run()
    frames = [(e[0], e[2]) for e in events if e[1] == "frame"]
    assert frames == [("a", 0), ("b", 0), ("a", 1), ("b", 1), ("a", 2), ("b", 2)]
    assert [e[1] for e in events if e[0] == "a"] == ["start", "frame", "frame", "frame", "loop_end", "finish"]
    assert ("a", "start", True) in events
    assert ("a", "loop_end", False) in events and ("a", "finish", True) in events  # summary.json comes after
    # each observer saw the map as that frame left it
    seen = [e[3] for e in events if e[0] == "a" and e[1] == "frame"]
    assert seen == [r.cells_total for r in result.records]
    assert [r.frame for r in result.records] == [0, 1, 2]
    assert STEPS == ("source", "outputs", "loop", "results", "evaluation", "summary")
    # the run's outputs: the same map, files and summary keys as before the pipeline
    assert result.mesh.GetNumberOfCells() == TABLE_3_TRIANGLES == seen[-1]
    assert scored == [TABLE_3_TRIANGLES]
    out = tmp_path / "run"
    assert {p.name for p in out.iterdir()} == RUN_FILES
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary) == SUMMARY_KEYS | {"evaluation"} and summary["cells"] == TABLE_3_TRIANGLES
    assert summary["frames"] == 3


def test_simulation_run_is_the_pipeline_and_an_observer_needs_only_its_hooks(tmp_path):
    frames = []

    class OnlyFrames:
        def on_frame(self, pipeline, record):
            frames.append(record.frame)

    simulation = MappingRun(table(2))
    via_pipeline = RunPipeline(simulation, observers=[OnlyFrames()]).run()
    via_run = simulation.run(progress=lambda record: frames.append(("progress", record.frame)))
    assert frames == [0, 1, ("progress", 0), ("progress", 1)]
    assert via_pipeline.mesh.GetNumberOfCells() == via_run.mesh.GetNumberOfCells() > 0
    assert via_run.evaluation is None and via_run.scores is None


def test_an_interrupted_run_tells_its_observers_and_resumes_to_the_same_map(tmp_path):
    from mabdi.loop.mapping_run import resume_run

    events: list = []

    class Stop(RunObserver):
        def on_frame(self, pipeline, record):
            if record.frame == 2:
                raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        RunPipeline(MappingRun(table(4)), tmp_path / "cut", [Log("a", events), Stop()]).run()
    assert events[-1] == ("a", "abort", "KeyboardInterrupt")
    assert [e[2] for e in events if e[1] == "frame"] == [0, 1, 2]
    resumed: list = []
    pipeline = resume_run(tmp_path / "cut", [Log("r", resumed)])
    result = pipeline.run()
    assert [e[2] for e in resumed if e[1] == "frame"] == [2, 3]  # from the checkpoint after frame 2
    assert [r.frame for r in result.records] == [0, 1, 2, 3]
    whole = MappingRun(table(4)).run()
    assert result.mesh.GetNumberOfCells() == whole.mesh.GetNumberOfCells()
    assert json.loads((tmp_path / "cut" / "summary.json").read_text())["frames"] == 4


def test_one_override_mechanism_for_the_command_line_the_sweep_and_set_value():
    base = load_run_config(SCENES / "table.toml")
    overrides = {"run.frames": 7, "surface.method": "quadtree", "surface.quadtree.n_t": 0.25, "scene.objects.0.position": [0.1, 0.2, 0.0]}
    new = with_overrides(base, overrides, where="here")
    assert new.run.frames == 7 and new.surface.method == "quadtree" and new.surface.parameters_of("quadtree").n_t == 0.25
    assert new.scene.objects[0].position == [0.1, 0.2, 0.0] and new.source == base.source
    assert base.run.frames == 30 and base.surface.method == "quadtree"  # the given config is not changed
    assert apply_overrides(base, overrides) == new  # the sweep's name for the same mechanism
    in_place = load_run_config(SCENES / "table.toml")
    for key, value in overrides.items():
        set_value(in_place, key, value)
    assert in_place == new
    with pytest.raises(ConfigError, match=r"^here: key 'classifier.tau_min': tau_min must be > 0"):
        with_overrides(base, {"run.frames": 3, "classifier.tau_min": -1.0}, where="here")
    with pytest.raises(ConfigError, match=r"here: key 'surface.quadtree.n_tt': unknown key 'n_tt' in \[surface.quadtree\]"):
        with_overrides(base, {"surface.quadtree.n_tt": 1.0}, where="here")
    with pytest.raises(ConfigError, match=r"'scene.objects' is a list of \d+ items, '9' is not an index in it"):
        with_overrides(base, {"scene.objects.9.position": [0, 0, 0]}, where="here")
    with pytest.raises(ConfigError, match="key 'classifier.tau_min': tau_min must be > 0"):
        set_value(in_place, "classifier.tau_min", 0.0)
    assert in_place == new  # a refused value leaves the config as it was
    with pytest.raises(ConfigError, match="key 'run.frames' must be at least 1"):
        with_overrides(in_place, {"run.frames": 0})  # the checks across sections: the whole config


def test_the_readme_run_pipeline_example_runs(tmp_path, monkeypatch):
    import mabdi

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    code = text.split("<!-- example: run pipeline -->")[1].split("```python")[1].split("```")[0]
    monkeypatch.chdir(tmp_path)
    namespace = {"mabdi": mabdi, "config": table(2)}
    exec(code, namespace)
    result, ghosts = namespace["result"], namespace["ghosts"].ghosts
    # a noise-free table: the map is the table (two frames: the quad-tree's faces stop short of a few silhouettes)
    assert 0.99 < result.scores.precision_1cm <= 1.0 and 0.97 < result.scores.fscore_1cm <= 1.0
    assert ghosts.final_share < 0.01 and [f for f, _ in ghosts.shares] == [0, 1]
    assert json.loads((tmp_path / "runs" / "mine" / "summary.json").read_text())["metrics"]["triangles"] == result.mesh.GetNumberOfCells()
