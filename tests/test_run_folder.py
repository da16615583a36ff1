"""Output folders and long runs: a re-run replaces its previous outputs whole, foreign files are refused,
the input config is never overwritten, checkpoints let an interrupted run finish with the same map."""

from __future__ import annotations

import json

import pytest

from conftest import REPO
from mabdi.config import load_run_config, set_value
from mabdi.errors import ConfigError
from mabdi.io.run_folder import MANIFEST, STAGING, OutputError, RunFolder
from mabdi.loop import MappingRun
from mabdi.loop.run_outputs import CHECKPOINT


def table(frames: int, surface: str = "pixel_grid", **values):
    config = load_run_config(REPO / "scenes" / "table.toml")
    set_value(config, "run.frames", frames)
    set_value(config, "surface.method", surface)
    for key, value in values.items():
        set_value(config, key.replace("__", "."), value)
    return config


def test_a_rerun_leaves_no_file_of_the_previous_run(tmp_path):
    out = tmp_path / "run"
    MappingRun(table(4, output__depth_images=True, output__h5=True)).run(out)
    assert (out / "depth" / "D_000003.vti").is_file() and (out / "world_mesh.h5").is_file()
    MappingRun(table(2)).run(out)
    names = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert "world_mesh.h5" not in names and not any(n.startswith("depth/") for n in names)
    assert not (out / "depth").exists()
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["complete"] and sorted(manifest["files"]) == sorted(n for n in names if n != MANIFEST)


def test_a_folder_with_foreign_files_is_refused_unless_overwrite(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("my notes")
    with pytest.raises(OutputError, match=r"holds files mabdi did not write \(notes.txt\).*--overwrite"):
        MappingRun(table(2)).run(out)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    MappingRun(table(2)).run(out, overwrite=True)
    assert (out / "notes.txt").read_text() == "my notes" and (out / "world_mesh.vtp").is_file()


def test_the_input_config_is_never_overwritten(tmp_path):
    folder = tmp_path / "exp"
    folder.mkdir()
    config_path = folder / "config.toml"
    text = "# my hand-written config\n" + (REPO / "scenes" / "table.toml").read_text().replace("frames = 30", "frames = 2")
    config_path.write_text(text)
    config = load_run_config(config_path)
    for overwrite in (False, True):
        with pytest.raises(OutputError, match="own config file"):
            MappingRun(config).run(folder, overwrite=overwrite)
    assert config_path.read_text() == text


def interrupt_at(frame: int):
    def progress(record):
        if record.frame == frame:
            raise KeyboardInterrupt

    return progress


@pytest.mark.parametrize("surface", ["quadtree", "voxel_planes"])
def test_resume_after_an_interrupt_gives_the_same_map(tmp_path, surface):
    """--resume after an interrupt at frame 17 of 30: the map is byte-identical to the uninterrupted run's."""
    whole = tmp_path / "whole"
    MappingRun(table(30, surface, output__checkpoint_every=5)).run(whole)
    cut = tmp_path / "cut"
    with pytest.raises(KeyboardInterrupt):
        MappingRun(table(30, surface, output__checkpoint_every=5)).run(cut, progress=interrupt_at(17))
    assert (cut / STAGING / CHECKPOINT).is_file() and not (cut / "summary.json").exists()
    assert not json.loads((cut / STAGING / MANIFEST).read_text())["complete"] and not (cut / MANIFEST).exists()
    simulation, result = MappingRun.resume(cut)
    assert [r.frame for r in result.records] == list(range(30))
    for name in ("world_mesh.vtp", "world_mesh.ply", "poses.npy"):
        assert (cut / name).read_bytes() == (whole / name).read_bytes(), name
    assert not (cut / STAGING).exists() and json.loads((cut / MANIFEST).read_text())["complete"]
    with pytest.raises(OutputError, match="complete already"):
        MappingRun.resume(cut)


def test_auto_checkpoints_space_out_once_writing_them_takes_a_twentieth_of_the_loop():
    """``checkpoint_every = "auto"`` (the default): every 10 frames while a checkpoint writes quickly; a
    checkpoint that took 2 s puts the next 40 s of loop time later (a long run's large map would otherwise
    spend a quarter of its time writing); a number of frames keeps its exact spacing."""
    from mabdi.config import RunConfig
    from mabdi.loop.run_pipeline import AUTO_CHECKPOINT_SPACING, Checkpoints

    assert RunConfig().output.checkpoint_every == "auto"
    auto = Checkpoints("auto")
    assert not auto.due(5, 1.0) and auto.due(10, 2.0)  # the first: at 10 frames
    auto._last_loop_seconds, auto._write_seconds = 2.0, 0.01
    assert auto.due(20, 4.0)  # a small map: every 10 frames
    auto._last_loop_seconds, auto._write_seconds = 100.0, 2.0
    assert not auto.due(110, 100.0 + 0.5 * AUTO_CHECKPOINT_SPACING * 2.0)
    assert not auto.due(115, 200.0)  # not a multiple of 10 frames
    assert auto.due(120, 100.0 + AUTO_CHECKPOINT_SPACING * 2.0)
    fixed = Checkpoints(4)
    fixed._last_loop_seconds, fixed._write_seconds = 100.0, 2.0
    assert fixed.due(8, 100.1) and not fixed.due(10, 500.0)


def test_a_checkpoint_spacing_that_is_neither_auto_nor_frames_is_refused(tmp_path):
    path = tmp_path / "run.toml"
    for value, message in (('"often"', "must be \"auto\" or >= 0 frames"), ("-1", "must be \"auto\" or >= 0 frames"), ("2.5", "checkpoint_every")):
        path.write_text(f"[output]\ncheckpoint_every = {value}\n")
        with pytest.raises(ConfigError, match=message):
            load_run_config(path)
    path.write_text('[output]\ncheckpoint_every = "auto"\n')
    assert load_run_config(path).output.checkpoint_every == "auto"


def test_a_failed_run_leaves_the_previous_run_whole(tmp_path):
    out = tmp_path / "run"
    MappingRun(table(2, output__h5=True)).run(out)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    with pytest.raises(KeyboardInterrupt):
        MappingRun(table(4)).run(out, progress=interrupt_at(1))
    after = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert after == before  # the interrupted run is staged beside it, in .mabdi-partial
    assert (out / STAGING).is_dir()
    MappingRun(table(2)).run(out)  # a new run replaces the staged one and the previous one
    assert not (out / STAGING).exists() and not (out / "world_mesh.h5").exists()


def test_resume_needs_a_run_folder(tmp_path):
    with pytest.raises(OutputError, match="not a mabdi run folder"):
        RunFolder.resume(tmp_path)


def test_mabdi_run_resume_finishes_an_interrupted_run_from_the_command_line(tmp_path, capsys):
    from mabdi.cli import main

    out = tmp_path / "cut"
    with pytest.raises(KeyboardInterrupt):
        MappingRun(table(12, "quadtree", output__checkpoint_every=4)).run(out, progress=interrupt_at(9))
    assert main(["run", "--resume", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 12 and summary["metrics"]["fscore_1cm"] > 0.9
    assert main(["run", "--resume", str(out), "--quiet"]) == 2  # complete: nothing to resume
    assert "complete already" in capsys.readouterr().err
