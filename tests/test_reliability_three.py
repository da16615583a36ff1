"""Reliability, round three (issue 24): one run per output folder, broken TF trees, resume that checks its
inputs, checkpoints that hold data only, sweeps keyed by content, TUM poses interpolated, and clear errors."""

from __future__ import annotations

import json
import os
import pickle
import signal
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from scipy.spatial.transform import Rotation, Slerp

from conftest import REPO, SCENES
from mabdi.camera import look_at
from mabdi.config import load_run_config, set_value
from mabdi.errors import ConfigError
from mabdi.io.checkpoint import CheckpointError, decode, encode, read_tree, write_tree
from mabdi.io.run_folder import LOCK, STAGING, OutputError, RunFolder
from mabdi.loop import MappingRun
from mabdi.loop.run_outputs import CHECKPOINT, OLD_CHECKPOINT
from mabdi.sources.frames import FrameList
from mabdi.sources.rosbag2 import _TYPESTORE, Rosbag2Sequence, write_rosbag2
from mabdi.sources.sequences import SequenceError, interpolate_poses

from test_sequences import TIMES, _frames


def table(frames: int, surface: str = "pixel_grid", **values):
    config = load_run_config(SCENES / "table.toml")
    set_value(config, "run.frames", frames)
    set_value(config, "surface.method", surface)
    for key, value in values.items():
        set_value(config, key.replace("__", "."), value)
    return config


def interrupt_at(frame: int):
    def progress(record):
        if record.frame == frame:
            raise KeyboardInterrupt

    return progress


def _cli(*args, **kwargs) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "mabdi.cli", *map(str, args)],
        cwd=REPO,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kwargs,
    )


# ---------------------------------------------------------------------------
# 1. one run at a time per output folder


def test_a_second_run_into_a_busy_folder_is_refused_and_changes_nothing(tmp_path):
    out = tmp_path / "busy"
    first = RunFolder.prepare(out)
    (first.path("metrics.csv")).write_text("first\n")
    with pytest.raises(OutputError, match=rf"output folder {out} is in use by another mabdi run \(process {os.getpid()}\)"):
        MappingRun(table(2)).run(out)
    with pytest.raises(OutputError, match="in use by another mabdi run"):
        RunFolder.resume(out)
    assert (out / STAGING / "metrics.csv").read_text() == "first\n"  # the first run's staging is untouched
    first.complete()
    assert not (out / LOCK).exists() and (out / "metrics.csv").read_text() == "first\n"
    MappingRun(table(2)).run(out)  # free again
    assert json.loads((out / "summary.json").read_text())["frames"] == 2


def test_a_run_killed_with_sigkill_leaves_no_stuck_lock(tmp_path):
    out = tmp_path / "killed"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from mabdi.io.run_folder import RunFolder; "
         "held = RunFolder.prepare(sys.argv[1]); print('held', flush=True); time.sleep(600)", str(out)],
        cwd=REPO, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(OutputError, match=rf"in use by another mabdi run \(process {holder.pid}\)"):
            RunFolder.prepare(out)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert (out / LOCK).exists()  # left behind by the killed run, but not held
    MappingRun(table(2)).run(out)
    assert json.loads((out / "summary.json").read_text())["frames"] == 2 and not (out / LOCK).exists()


#: A second ``mabdi`` that imports everything first and starts its run when the file argv[1] appears.
_WAITING_MABDI = (
    "import sys, time, pathlib\n"
    "from mabdi.cli import main\n"
    "import mabdi.simulate, vtkmodules.vtkRenderingCore\n"
    "go = pathlib.Path(sys.argv[1])\n"
    "while not go.exists():\n"
    "    time.sleep(0.005)\n"
    "sys.exit(main(sys.argv[2:]))\n"
)


def test_two_concurrent_mabdi_runs_into_one_folder_never_mix(tmp_path):
    """The issue's case: the second run starts while the first writes; it is refused, the first completes."""
    out, go = tmp_path / "c", tmp_path / "go"
    second = subprocess.Popen(
        [sys.executable, "-c", _WAITING_MABDI, str(go), "run", str(SCENES / "table.toml"), "--frames", "8", "--quiet",
         "--no-eval", "--surface", "pixel_grid", "--out", str(out)],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    first = _cli("run", SCENES / "table.toml", "--frames", 40, "--quiet", "--no-eval", "--out", out)
    end = time.monotonic() + 120
    while not (out / LOCK).exists() and first.poll() is None and time.monotonic() < end:
        time.sleep(0.005)
    go.touch()
    second_out, second_err = second.communicate(timeout=300)
    first_out, first_err = first.communicate(timeout=300)
    assert first.returncode == 0, first_err
    assert second.returncode == 2, (second_out, second_err)
    assert f"mabdi: error: output folder {out} is in use by another mabdi run" in second_err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 40 and summary["surface"] == "quadtree"
    assert len((out / "metrics.csv").read_text().splitlines()) == 41 and len(np.load(out / "poses.npy")) == 40
    assert not (out / STAGING).exists() and not (out / LOCK).exists()


# ---------------------------------------------------------------------------
# 2, 6, 7. TF trees: missing links, bad quaternions, sparse links


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    """5 frames; /tf world -> camera_link per frame, /tf_static camera_link -> camera_depth_optical_frame."""
    return write_rosbag2(FrameList(_frames(), "test frames"), tmp_path_factory.mktemp("bag") / "bag")


def _rewrite(source, target, change=None, keep=None):
    """Copy a bag: change(topic, index, message) -> message; keep(topic, index) -> bool drops messages."""
    with Reader(source) as reader, Writer(target, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        out = {c.topic: writer.add_connection(c.topic, c.msgtype, typestore=_TYPESTORE) for c in reader.connections}
        counts: dict[str, int] = {}
        for connection, stamp, raw in reader.messages():
            index = counts[connection.topic] = counts.get(connection.topic, -1) + 1
            if keep is not None and not keep(connection.topic, index):
                continue
            message = _TYPESTORE.deserialize_cdr(raw, connection.msgtype)
            if change is not None:
                message = change(connection.topic, index, message)
            writer.write(out[connection.topic], stamp, _TYPESTORE.serialize_cdr(message, connection.msgtype))
    return target


def test_a_disconnected_tf_tree_is_an_error_naming_the_missing_link(bag, tmp_path, capsys):
    def to_base_link(topic, index, message):
        if topic == "/tf":
            message.transforms[0].child_frame_id = "base_link"  # map -> base_link, and nothing -> camera_link
        return message

    path = _rewrite(bag, tmp_path / "bag", change=to_base_link)
    with pytest.raises(SequenceError, match=r"'camera_depth_optical_frame' is not connected to world: missing link \? -> camera_link"):
        Rosbag2Sequence(path, pose_topic="/tf")
    from mabdi.cli import main

    assert main(["run", "--sequence", str(path), "--pose-topic", "/tf", "--quiet", "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "missing link ? -> camera_link" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "run" / "world_mesh.vtp").exists()


@pytest.mark.parametrize("quaternion", [(np.nan, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 0.0)])
def test_a_nan_or_zero_quaternion_in_tf_is_an_error_naming_the_message(bag, tmp_path, quaternion):
    def spoil(topic, index, message):
        if topic == "/tf" and index == 2:
            r = message.transforms[0].transform.rotation
            r.x, r.y, r.z, r.w = quaternion
        return message

    path = _rewrite(bag, tmp_path / "bag", change=spoil)
    stamp = f"{TIMES[2]:.9f}"[:-3]
    with pytest.raises(SequenceError, match=rf"/tf: transform world -> camera_link at stamp {stamp}\d+ s: the quaternion .* is not finite or has zero length"):
        Rosbag2Sequence(path, pose_topic="/tf")


def test_a_sparse_tf_link_is_interpolated_within_its_span(bag, tmp_path):
    """Only the first and last of five /tf messages (133 ms apart, as a slowly published map -> odom): every
    frame between gets the link interpolated (linear position, slerp rotation), none is refused."""
    path = _rewrite(bag, tmp_path / "bag", keep=lambda topic, index: topic != "/tf" or index in (0, 4))
    full = Rosbag2Sequence(bag, pose_topic="/tf").poses
    sparse = Rosbag2Sequence(path, pose_topic="/tf")
    assert sparse.skipped == 0 and len(sparse) == 5
    alpha = (TIMES - TIMES[0]) / (TIMES[4] - TIMES[0])
    start, end = _link(full[0]), _link(full[4])
    rotations = Slerp([0.0, 1.0], Rotation.from_matrix([start[:3, :3], end[:3, :3]]))(alpha).as_matrix()
    for i, a in enumerate(alpha):
        link = np.eye(4)
        link[:3, :3] = rotations[i]
        link[:3, 3] = (1 - a) * start[:3, 3] + a * end[:3, 3]
        np.testing.assert_allclose(sparse.poses[i], link @ np.linalg.inv(start) @ full[0], atol=1e-9)


def _link(optical_pose):
    """world_from_camera_link of a frame, from its world_from_optical pose (the writer's fixed optical rotation)."""
    from mabdi.sources.rosbag2 import LINK_FROM_OPTICAL

    return optical_pose @ np.linalg.inv(LINK_FROM_OPTICAL)


def test_interpolate_poses_slerps_and_holds_within_tolerance():
    times = np.array([0.0, 1.0])
    a, b = np.eye(4), np.eye(4)
    b[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    b[:3, 3] = [2.0, 0.0, 0.0]
    query = np.array([-0.5, -0.01, 0.0, 0.25, 1.0, 1.01, 2.0])
    out = interpolate_poses(query, times, np.stack([a, b]), tolerance=0.02)
    assert np.isnan(out[0]).all() and np.isnan(out[6]).all()  # beyond the tolerance past the ends
    np.testing.assert_array_equal(out[1], a)  # held from the nearest sample within tolerance
    np.testing.assert_array_equal(out[2], a) and np.testing.assert_array_equal(out[4], b)  # exact at samples
    np.testing.assert_array_equal(out[5], b)
    assert np.isnan(out[3]).all()  # 250 ms from both samples: a gap, not bridged...
    bridged = interpolate_poses(query, times, np.stack([a, b]), tolerance=0.02, bridge_gaps=True)
    np.testing.assert_allclose(bridged[3][:3, 3], [0.5, 0.0, 0.0], atol=1e-12)  # ...unless asked (tf links)
    np.testing.assert_allclose(Rotation.from_matrix(bridged[3][:3, :3]).as_euler("xyz", degrees=True), [0, 0, 22.5], atol=1e-9)


# ---------------------------------------------------------------------------
# 8. TUM ground truth interpolated


def test_tum_poses_are_interpolated_and_the_map_sits_within_half_a_millimetre(tmp_path):
    """30 Hz depth, 100 Hz ground truth (offset, so no depth stamp has its own sample): the map's vertices
    lie within 0.5 mm of the table scene (the nearest sample alone puts them millimetres off)."""
    from mabdi.evaluate.distance import distances_to_mesh
    from mabdi.stages.registration_check import PosesDisagreeWarning
    from mabdi.loop.loop import MabdiLoop
    from mabdi.simulate.rig import FRAME_RATE, SimulatedRig
    from mabdi.sources.scene import SourceScene
    from mabdi.sources.tum import TumSequence, write_tum

    from mabdi.camera import Intrinsics

    config = table(6)
    intrinsics = Intrinsics(fx=131.25, fy=131.25, cx=80.0, cy=60.0, width=160, height=120, near=0.5, far=6.0)

    def pose(t):  # circling the table at 0.6 rad/s, 2.5 m out: about 1.5 m/s
        angle = 0.6 * np.asarray(t)
        return np.array([look_at([2.5 * np.cos(a), 2.5 * np.sin(a), 1.6], [0.0, 0.0, 0.8]) for a in np.atleast_1d(angle)])

    frames = 6
    depth_times = np.arange(frames) / FRAME_RATE
    scene = SourceScene(config.scene, frames=frames, base_dir=SCENES)
    rig = SimulatedRig(scene, pose(depth_times), intrinsics=intrinsics)
    folder = write_tum(rig, tmp_path / "tum")
    rig.close()
    gt_times = np.arange(-0.05, frames / FRAME_RATE + 0.05, 0.01) + 0.0037
    gt = pose(gt_times)
    quaternions = Rotation.from_matrix(gt[:, :3, :3]).as_quat()
    lines = [f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*p[:3, 3], *q)) for t, p, q in zip(gt_times, gt, quaternions, strict=True)]
    (folder / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n")

    sequence = TumSequence(folder)
    assert sequence.skipped == 0
    offset = np.linalg.norm(sequence.poses[:, :3, 3] - pose(depth_times)[:, :3, 3], axis=1)
    assert offset.max() < 1e-4  # interpolated: 0.1 mm (the nearest sample is up to 5 ms = 7 mm away)
    loop = MabdiLoop.from_config(config, sequence)
    with warnings.catch_warnings():
        # no frame of this small, fast camera gets the samples to register, but none sees through the map:
        # the poses are right, and the run must not blame them (mabdi.stages.registration_check)
        warnings.simplefilter("error", PosesDisagreeWarning)
        for i in range(frames):
            loop.step(i)
    points = np.asarray(loop.mesh().GetPoints().GetData())
    distance = distances_to_mesh(points, scene.mesh_at(0))
    loop.close()
    assert np.percentile(distance, 99) < 0.5e-3, np.percentile(distance, [50, 99, 100])


def test_tum_errors_print_plain_numbers(tmp_path):
    from mabdi.sources.tum import read_groundtruth

    path = tmp_path / "groundtruth.txt"
    path.write_text("1305031102.1716 1 2 3 0 0 0 x\n")
    with pytest.raises(SequenceError) as error:
        read_groundtruth(path)
    assert "timestamp 1305031102.1716 has a field" in str(error.value) and "np.float64" not in str(error.value)
    path.write_text("1305031102.1716 1 2 3 0 0 0 0\n")
    with pytest.raises(SequenceError, match=r"pose at timestamp 1305031102.1716 is not finite or has a zero quaternion"):
        read_groundtruth(path)


# ---------------------------------------------------------------------------
# 3, 7. --resume checks its inputs and its options


def _interrupted(out, config, at: int, **run):
    with pytest.raises(KeyboardInterrupt):
        MappingRun(config).run(out, progress=interrupt_at(at), **run)
    assert (out / STAGING / CHECKPOINT).is_file()


def test_resume_refuses_a_changed_recording(tmp_path, capsys):
    from mabdi.cli import main
    from mabdi.loop.mapping_run import recorded_simulation
    from mabdi.simulate.recording import record

    recording = record(table(12, output__checkpoint_every=4), tmp_path / "tum", "tum")
    config = table(12, output__checkpoint_every=4)
    simulation, _ = recorded_simulation(config, recording)
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        simulation.run(out, progress=interrupt_at(9), recording={"path": str(recording), "options": {}})
    depth_txt = recording / "depth.txt"
    depth_txt.write_text("".join(depth_txt.read_text().splitlines(keepends=True)[:8]))  # 12 frames -> 5 or so
    assert main(["run", "--resume", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"cannot resume {out}: an input changed since the run started (recording file {depth_txt.resolve()} changed)" in err
    assert not (out / "summary.json").exists() and (out / STAGING / CHECKPOINT).is_file()  # still resumable


def test_resume_refuses_a_changed_scene_mesh(tmp_path):
    from mabdi.io.vtk_files import write_mesh_file
    from vtkmodules.vtkFiltersSources import vtkCubeSource

    cube = vtkCubeSource()
    cube.Update()
    mesh_file = tmp_path / "crate.vtp"
    write_mesh_file(cube.GetOutput(), mesh_file)
    text = (SCENES / "table.toml").read_text() + (
        '\n[[scene.objects]]\nname = "crate"\ntype = "mesh"\nmesh = "crate.vtp"\nscale = 0.3\nposition = [0.0, 1.2, 0.0]\n'
    )
    config_file = tmp_path / "crate.toml"
    config_file.write_text(text)
    config = load_run_config(config_file)
    set_value(config, "run.frames", 8)
    set_value(config, "output.checkpoint_every", 4)
    out = tmp_path / "run"
    _interrupted(out, config, 5)
    cube.SetXLength(2.0)
    cube.Update()
    write_mesh_file(cube.GetOutput(), mesh_file)  # same path, other content
    with pytest.raises(OutputError, match=rf"an input changed since the run started \(scene mesh {mesh_file.resolve()} changed\)"):
        MappingRun.resume(out)
    assert (out / STAGING / CHECKPOINT).is_file()
    config_file.write_text(text + "\n# edited\n")
    with pytest.raises(OutputError, match=rf"config file {config_file.resolve()} changed"):
        MappingRun.resume(out)


def test_resume_refuses_options_and_keeps_no_eval(tmp_path, capsys):
    from mabdi.cli import main

    out = tmp_path / "run"
    config = table(12, "quadtree", output__checkpoint_every=4)
    _interrupted(out, config, 9, run_options={"no_eval": True})
    for options in (["--frames", "50"], ["--surface", "pixel_grid"], ["--set", "surface.quadtree.n_t=0.05"], ["--overwrite"]):
        assert main(["run", "--resume", str(out), "--quiet", *options]) == 2
        err = capsys.readouterr().err
        assert f"{options[0]} cannot be given with it" in err and err.count("\n") == 1
    assert main(["run", "--resume", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 12 and "metrics" not in summary and summary["evaluation"] == "skipped (--no-eval)"


def test_a_resumed_runs_seconds_count_the_whole_run(tmp_path):
    out = tmp_path / "run"
    _interrupted(out, table(12, "quadtree", output__checkpoint_every=4), 9)
    _, result = MappingRun.resume(out)
    frames_ms = sum(r.t_total_ms for r in result.records)
    assert result.seconds >= 0.9 * frames_ms / 1000.0  # not only the 4 frames run after the resume
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames_per_second"] == pytest.approx(12 / summary["seconds"])


# ---------------------------------------------------------------------------
# 4. checkpoints hold data only


class _Payload:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (open, (str(self.marker), "w"))  # unpickling creates the marker file


def test_a_crafted_checkpoint_runs_no_code(tmp_path, capsys):
    from mabdi.cli import main

    out = tmp_path / "run"
    _interrupted(out, table(8, output__checkpoint_every=4), 5)
    marker = tmp_path / "pwned"
    (out / STAGING / CHECKPOINT).unlink()
    (out / STAGING / OLD_CHECKPOINT).write_bytes(pickle.dumps({"version": 1, "x": _Payload(marker)}))
    assert main(["run", "--resume", str(out), "--quiet"]) == 2
    assert "is a pickle from an older mabdi, which is not loaded" in capsys.readouterr().err
    assert not marker.exists()
    # an .npz that smuggles a pickled object array
    with open(out / STAGING / CHECKPOINT, "wb") as stream:
        np.savez(stream, header=np.frombuffer(b'{"format": "mabdi-checkpoint", "version": 2, "tree": {"array": "a0"}}', np.uint8),
                 a0=np.array([_Payload(marker)], dtype=object))  # fmt: skip
    assert main(["run", "--resume", str(out), "--quiet"]) == 2
    assert "is damaged or not a checkpoint" in capsys.readouterr().err
    assert not marker.exists()


def test_checkpoint_trees_round_trip_and_refuse_objects(tmp_path):
    tree = {
        "world": {"patches": [["block 1", {"points": np.arange(6, dtype=np.float32).reshape(2, 3)}]], "next": np.int64(4)},
        "registration": {"poses": np.eye(4)[None], "sigma": 0.25, "status": "registered", "nan": float("nan")},
        3: [True, None, "text", np.float32(1.5)],
    }
    write_tree(tmp_path / "c.npz", tree)
    back = read_tree(tmp_path / "c.npz")
    assert list(back) == ["world", "registration", 3]
    assert back["world"]["patches"][0][0] == "block 1" and back["world"]["patches"][0][1]["points"].dtype == np.float32
    np.testing.assert_array_equal(back["registration"]["poses"], np.eye(4)[None])
    assert np.isnan(back["registration"]["nan"]) and back[3][:3] == [True, None, "text"]
    assert type(back[3][3]) is np.float32 and type(back["world"]["next"]) is np.int64
    node, arrays = encode({"a": [np.zeros(2)]})
    assert decode(json.loads(json.dumps(node)), arrays)["a"][0].shape == (2,)
    from vtkmodules.vtkCommonDataModel import vtkPolyData

    with pytest.raises(CheckpointError, match=r"state.loop.surface is a vtkPolyData, not plain data"):
        encode({"loop": {"surface": vtkPolyData()}})
    with pytest.raises(CheckpointError, match="dtype object"):
        encode({"x": np.array([None], dtype=object)})


def test_voxel_planes_and_refinement_state_is_plain_data_and_resumes_exactly(tmp_path):
    """Every part of the loop's state goes into a checkpoint (no object), and back: voxel planes with refinement."""
    config = table(10, "voxel_planes", sensor__noise="kinect", refinement__enabled=True)
    if hasattr(config, "registration"):
        set_value(config, "registration.enabled", False)  # registration's own state is its author's to add
    whole = MappingRun(config)
    whole.loop.reset()
    for i in range(6):
        whole.step(i)
    write_tree(tmp_path / "state.npz", whole.loop.state())
    restored = MappingRun(config)
    restored.loop.set_state(read_tree(tmp_path / "state.npz"))
    for i in range(6, 10):
        a, b = whole.step(i), restored.step(i)
        assert (a.cells_total, a.vertices_refined, a.novel_fraction) == (b.cells_total, b.vertices_refined, b.novel_fraction)
    assert np.array_equal(np.asarray(whole.loop.mesh().GetPoints().GetData()), np.asarray(restored.loop.mesh().GetPoints().GetData()))


# ---------------------------------------------------------------------------
# 5. sweeps keyed by content


def test_a_sweep_cell_is_keyed_by_the_content_of_its_meshes(tmp_path):
    from mabdi.io.vtk_files import write_mesh_file
    from mabdi.sweep import sweep_cells, sweep_from_dict
    from vtkmodules.vtkFiltersSources import vtkCubeSource

    cube = vtkCubeSource()
    cube.Update()
    write_mesh_file(cube.GetOutput(), tmp_path / "crate.vtp")
    (tmp_path / "crate.toml").write_text(
        (SCENES / "table.toml").read_text()
        + '\n[[scene.objects]]\nname = "crate"\ntype = "mesh"\nmesh = "crate.vtp"\nposition = [0.0, 1.2, 0.0]\n'
    )
    spec = {"sweep": {"name": "t", "configs": [str(tmp_path / "crate.toml")], "frames": 3}, "grid": {"run.seed": [0, 1]}}
    before = [c.id for c in sweep_cells(sweep_from_dict(spec))]
    assert before == [c.id for c in sweep_cells(sweep_from_dict(spec))]  # the same content: the same cells
    cube.SetXLength(3.0)
    cube.Update()
    write_mesh_file(cube.GetOutput(), tmp_path / "crate.vtp")
    after = [c.id for c in sweep_cells(sweep_from_dict(spec))]
    assert not set(before) & set(after)  # changed content at the same path: new cells, run again


# ---------------------------------------------------------------------------
# 6, 7. clear one-line errors


def test_a_missing_render_library_is_a_one_line_error(monkeypatch, tmp_path, capsys):
    import ctypes.util

    from mabdi.cli import main

    real = ctypes.util.find_library
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None if name == "OSMesa" else real(name))
    assert main(["run", str(SCENES / "table.toml"), "--backend", "osmesa", "--frames", "2", "--quiet", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mabdi: error: render backend 'osmesa' needs the system library libOSMesa") and err.count("\n") == 1
    assert not (tmp_path / "o").exists()


def test_rerun_given_a_folder_is_a_one_line_error(tmp_path, capsys):
    from mabdi.cli import main

    assert main(["run", str(SCENES / "table.toml"), "--rerun", str(tmp_path), "--frames", "2", "--quiet", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert f"--rerun {tmp_path}: that is a folder" in err and err.count("\n") == 1


def test_a_mesh_without_type_mesh_says_so(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('[[scene.objects]]\nname = "bunny"\nmesh = "bunny"\n')
    with pytest.raises(ConfigError, match=r"'scene.objects\[0\].mesh' is only used with type = \"mesh\" .*add type = \"mesh\""):
        load_run_config(path)


def test_a_compressed_depth_topic_of_another_codec_says_so(bag, tmp_path):
    """A bag whose depth is only a CompressedImage topic, its payload not a PNG (another codec, rvl say): the
    topic is taken as the depth (compressed depth is read), and the error names the format and the remedy."""
    path = tmp_path / "bag"
    compressed = "sensor_msgs/msg/CompressedImage"
    with Reader(bag) as reader, Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        out = {c.topic: writer.add_connection(c.topic, c.msgtype, typestore=_TYPESTORE) for c in reader.connections if "image" not in c.topic}
        packed = writer.add_connection("/camera/depth/image/compressedDepth", compressed, typestore=_TYPESTORE)
        for connection, stamp, raw in reader.messages():
            if connection.topic in out:
                writer.write(out[connection.topic], stamp, raw)
            elif connection.topic == "/camera/depth/image":
                image = _TYPESTORE.deserialize_cdr(raw, connection.msgtype)
                message = _TYPESTORE.types[compressed](header=image.header, format="16UC1; compressedDepth", data=np.zeros(4, np.uint8))
                writer.write(packed, stamp, _TYPESTORE.serialize_cdr(message, compressed))
    with pytest.raises(SequenceError) as error:
        Rosbag2Sequence(path)
    text = str(error.value)
    assert "topic /camera/depth/image/compressedDepth" in text
    assert "compressed depth of format '16UC1; compressedDepth' is not a PNG" in text and "republish it raw" in text


def test_view_of_an_empty_map_says_it_is_empty(tmp_path, capsys):
    from mabdi.cli import main
    from mabdi.io.vtk_files import write_mesh_file
    from vtkmodules.vtkCommonDataModel import vtkPolyData

    write_mesh_file(vtkPolyData(), tmp_path / "world_mesh.vtp")
    assert main(["view", str(tmp_path), "--out", str(tmp_path / "v.png")]) == 2
    err = capsys.readouterr().err
    assert "is an empty map (no triangles): nothing to show" in err and "maps from mabdi run have it" not in err
