"""Nothing a user saved is lost to a run: ``--overwrite`` never replaces a file mabdi did not write, and
a run folder inside a recording (its own ``--out`` included) is no part of the recording's fingerprint."""

from __future__ import annotations

import json

import pytest

from conftest import REPO
from mabdi.config import load_run_config, set_value
from mabdi.io.fingerprint import recording_files
from mabdi.io.run_folder import LOCK, MANIFEST, STAGING, OutputError, RunFolder, run_writes
from mabdi.loop import MappingRun
from mabdi.loop.run_outputs import CHECKPOINT
from mabdi.loop.mapping_run import recorded_simulation

TABLE = str(REPO / "scenes" / "table.toml")

#: A user's own files under names a run writes.
USER_FILES = {
    "trajectory.txt": b"precious\n",
    "summary.json": b'{"mine": true}\n',
    "metrics.csv": b"frame,my_column\n0,1\n",
    "config.toml": b"# a config that is not this run's\n",
}


def table(frames: int, **values):
    config = load_run_config(REPO / "scenes" / "table.toml")
    set_value(config, "run.frames", frames)
    for key, value in values.items():
        set_value(config, key.replace("__", "."), value)
    return config


def interrupt_at(frame: int):
    def progress(record):
        if record.frame == frame:
            raise KeyboardInterrupt

    return progress


def test_overwrite_refuses_a_user_file_under_a_name_the_run_writes_before_any_frame(tmp_path, capsys):
    """The user tour's case: `mabdi run ... --overwrite` into a folder holding the user's trajectory.txt,
    summary.json, metrics.csv and config.toml keeps every byte, and says which files are in the way."""
    from mabdi.cli import main

    out = tmp_path / "o"
    out.mkdir()
    for name, data in USER_FILES.items():
        (out / name).write_bytes(data)
    argv = ["run", TABLE, "--frames", "3", "--out", str(out), "--overwrite", "--no-eval", "--quiet"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    for name in USER_FILES:
        assert name in err, err
    assert "--overwrite" in err and str(out) in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == USER_FILES  # nothing staged, no lock left


def test_a_run_never_replaces_a_file_that_appeared_while_it_ran(tmp_path):
    """A user file saved into the folder during the run, under a name the run writes: the run's completion
    is refused, naming it; the user's bytes stay and the run's own files stay staged."""
    out = tmp_path / "run"
    run = RunFolder.prepare(out)
    run.path("trajectory.txt").write_text("mabdi's")
    (out / "trajectory.txt").write_bytes(b"precious\n")
    with pytest.raises(OutputError, match=r"trajectory\.txt"):
        run.complete()
    assert (out / "trajectory.txt").read_bytes() == b"precious\n"
    assert (out / STAGING / "trajectory.txt").read_text() == "mabdi's"
    assert not (out / LOCK).exists()  # the refused run let go of the folder


def test_a_run_refuses_to_write_under_the_name_of_a_user_file(tmp_path):
    """A name outside mabdi's usual ones: the run's path() for it is refused, naming it; the user's file stays."""
    out = tmp_path / "run"
    out.mkdir()
    (out / "extra.dat").write_bytes(b"mine")
    run = RunFolder.prepare(out, overwrite=True)
    with pytest.raises(OutputError, match=r"extra\.dat"):
        run.path("extra.dat")
    run.release()
    assert (out / "extra.dat").read_bytes() == b"mine"


def test_the_names_a_run_writes_are_all_known_up_front(tmp_path):
    """Every file of a run with every optional output is one that the up-front check knows (RUN_FILES)."""
    out = tmp_path / "run"
    MappingRun(table(2, output__depth_images=True, output__h5=True)).run(out)
    files = json.loads((out / MANIFEST).read_text())["files"]
    assert "world_mesh.h5" in files and any(name.startswith("depth/") for name in files)
    assert [name for name in files if not run_writes(name)] == []


def test_a_resume_refuses_a_user_file_under_a_name_the_run_writes(tmp_path):
    out = tmp_path / "cut"
    with pytest.raises(KeyboardInterrupt):
        MappingRun(table(4, output__checkpoint_every=2)).run(out, progress=interrupt_at(2))
    (out / "summary.json").write_bytes(b"mine\n")
    with pytest.raises(OutputError, match=r"summary\.json"):
        MappingRun.resume(out)
    assert (out / "summary.json").read_bytes() == b"mine\n"


def test_the_fingerprint_of_a_recording_leaves_out_run_folders_inside_it(tmp_path):
    recording = tmp_path / "seq"
    (recording / "depth").mkdir(parents=True)
    (recording / "depth" / "0.png").write_bytes(b"png")
    (recording / "depth.txt").write_text("0 depth/0.png\n")
    done = recording / "runs" / "done"  # a completed run: its manifest
    done.mkdir(parents=True)
    (done / MANIFEST).write_text(json.dumps({"complete": True, "files": ["poses.npy"]}))
    (done / "poses.npy").write_bytes(b"x")
    running = recording / "run"  # a run under way: its lock and staging folder
    (running / STAGING).mkdir(parents=True)
    (running / LOCK).write_text("123\n")
    (running / STAGING / MANIFEST).write_text(json.dumps({"complete": False, "files": []}))
    (running / STAGING / CHECKPOINT).write_bytes(b"x")
    names = sorted(p.relative_to(recording.resolve()).as_posix() for p in recording_files(recording))
    assert names == ["depth.txt", "depth/0.png"]


def test_the_fingerprint_of_a_recording_that_is_a_run_folder_leaves_out_the_runs_files(tmp_path):
    recording = tmp_path / "seq"
    (recording / STAGING).mkdir(parents=True)
    (recording / "depth.txt").write_text("0 depth/0.png\n")
    (recording / MANIFEST).write_text(json.dumps({"complete": True, "files": ["poses.npy"]}))
    (recording / "poses.npy").write_bytes(b"x")
    (recording / LOCK).write_text("123\n")
    (recording / STAGING / CHECKPOINT).write_bytes(b"x")
    assert [p.name for p in recording_files(recording)] == ["depth.txt"]


def test_a_run_whose_out_lies_inside_the_recording_resumes(tmp_path):
    """--out inside the recording's folder: the resume goes on (the run's lock and checkpoint are no input),
    while a real change to a recording file is still refused, naming it."""
    from mabdi.cli import main

    recording = tmp_path / "seq" / "table"
    assert main(["record", TABLE, "--format", "tum", "--out", str(recording), "--frames", "4"]) == 0
    out = recording / "run"
    config = table(4, output__checkpoint_every=2)
    simulation, _ = recorded_simulation(config, recording)
    with pytest.raises(KeyboardInterrupt):
        simulation.run(out, progress=interrupt_at(2), recording={"path": str(recording.resolve()), "options": {}})
    assert (out / STAGING / CHECKPOINT).is_file()
    changed = recording / "groundtruth.txt"
    original = changed.read_bytes()
    changed.write_bytes(original + b"# edited\n")
    with pytest.raises(OutputError, match=r"groundtruth\.txt changed") as refused:
        MappingRun.resume(out)
    assert LOCK not in str(refused.value) and CHECKPOINT not in str(refused.value)
    changed.write_bytes(original)
    _, result = MappingRun.resume(out)
    assert [r.frame for r in result.records] == [0, 1, 2, 3]
    assert json.loads((out / MANIFEST).read_text())["complete"] and (out / "world_mesh.vtp").is_file()
