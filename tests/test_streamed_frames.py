"""Frames that stream: any iterable of DepthFrames (a generator, no length) runs the loop and maps as the same
frames given by index do (StreamedFrames, Mapper, map_frames, the runner)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy

import mabdi
from mabdi.camera import Intrinsics
from mabdi.config import load_run_config, with_overrides
from mabdi.depth import DepthFrame
from mabdi.loop.loop import MabdiLoop
from mabdi.loop.mapper import Mapper, map_frames
from mabdi.loop.mapping_run import MappingRun
from mabdi.simulate.rig import SimulatedRig
from mabdi.sources.frames import FrameList, StreamedFrames, StreamOrderError

REPO = Path(__file__).resolve().parents[1]
FRAMES = 4


def table(frames: int = FRAMES):
    return with_overrides(load_run_config(REPO / "scenes" / "table.toml"), {"run.frames": frames})


@pytest.fixture(scope="module")
def rendered():
    """The table's first frames, rendered once, with what the simulator states of them."""
    config = table()
    rig = SimulatedRig.from_config(config)
    frames = [rig.read(i) for i in range(len(rig))]
    stated = {"noise": rig.noise, "pose_accuracy": rig.pose_accuracy}
    rig.close()
    return config, frames, stated


@pytest.fixture(scope="module")
def indexed(rendered):
    """The run over the frames given by index (a FrameList: a source with a length)."""
    config, frames, stated = rendered
    simulation = MappingRun(config, source=FrameList(frames, **stated))
    result = simulation.run()
    simulation.loop.close()
    return result


def mesh_arrays(mesh):
    return vtk_to_numpy(mesh.GetPoints().GetData()), vtk_to_numpy(mesh.GetPolys().GetConnectivityArray())


def assert_same_map(mesh, expected):
    assert mesh.GetNumberOfCells() == expected.GetNumberOfCells() > 1000
    for got, want in zip(mesh_arrays(mesh), mesh_arrays(expected), strict=True):
        np.testing.assert_array_equal(got, want)


def synthetic(count: int):
    """``count`` small frames of a wall 2 m ahead, made with numpy (a generator)."""
    intrinsics = Intrinsics(fx=40.0, fy=40.0, cx=15.5, cy=11.5, width=32, height=24, near=0.5, far=4.0)
    for i in range(count):
        pose = np.eye(4)
        pose[0, 3] = 0.01 * i
        yield DepthFrame(np.full((24, 32), 2.0, dtype=np.float32), intrinsics, pose, timestamp=i / 30.0)


def test_a_generator_of_frames_with_no_length_runs_the_loop_and_maps_as_the_indexed_frames(rendered, indexed, tmp_path):
    config, frames, stated = rendered
    generator = (frame for frame in frames)
    with pytest.raises(TypeError):
        len(generator)
    config = with_overrides(config, {"output.checkpoint_every": 2})  # a stream cannot be resumed: none written
    seen = []
    accuracy = stated["pose_accuracy"]
    result = map_frames(generator, config, pose_accuracy=accuracy, out_dir=tmp_path / "run", progress=seen.append)
    assert [r.frame for r in result.records] == [r.frame for r in seen] == list(range(FRAMES))
    assert_same_map(result.mesh, indexed.mesh)
    assert [r.cells_total for r in result.records] == [r.cells_total for r in indexed.records]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["frames"] == FRAMES and summary["cells"] == result.mesh.GetNumberOfCells()
    assert np.load(tmp_path / "run" / "poses.npy").shape == (FRAMES, 4, 4)
    assert not (tmp_path / "run" / ".mabdi-partial").exists()


def test_the_mapper_steps_frame_by_frame_to_the_same_map(rendered, indexed):
    config, frames, stated = rendered
    mapper = Mapper(config, pose_accuracy=stated["pose_accuracy"])
    assert mapper.mesh.GetNumberOfCells() == 0  # before the first frame: an empty map
    steps = [mapper.step(frame) for frame in frames]
    mesh = mapper.finish()
    mapper.close()
    assert_same_map(mesh, indexed.mesh)
    assert [s.frame for s in steps] == list(range(FRAMES))
    assert [s.record.cells_total for s in steps] == [r.cells_total for r in indexed.records]
    first = steps[0]
    assert first.pose.shape == (4, 4) and first.labels.shape == frames[0].depth.shape
    assert first.added.GetNumberOfCells() == first.record.cells_added > 0  # frame 0: all of its surface is new
    assert first.removed.GetNumberOfCells() == 0
    np.testing.assert_allclose(np.stack([s.pose for s in steps]), mapper.trajectory())
    with pytest.raises(RuntimeError, match="has finished"):
        mapper.step(frames[0])


def test_the_loop_over_a_stream_grows_its_per_frame_arrays(rendered):
    config, frames, stated = rendered
    source = StreamedFrames(iter(frames[:2]), noise=stated["noise"], pose_accuracy=stated["pose_accuracy"])
    loop = MabdiLoop.from_config(config, source)
    assert loop.trajectory().shape == (0, 4, 4)
    for i in range(2):
        loop.step(i)
    assert loop.trajectory().shape == (2, 4, 4) and np.isfinite(loop.trajectory()).all()
    assert source.frames_known is None and not source.has_frame(2) and source.frames_known == 2
    assert loop.state()["poses"].shape == (2, 4, 4)
    loop.finish()
    loop.close()


def test_streamed_frames_are_read_in_order():
    source = StreamedFrames(synthetic(3), description="wall")
    with pytest.raises(TypeError, match="no length"):
        len(source)
    assert source.frames_known is None
    assert source.intrinsics.width == 32  # the first frame's, read ahead
    assert source.read(0).frame == 0 and source.read(1).frame == 1
    assert source.read(1).timestamp == pytest.approx(1 / 30.0)  # the current frame may be read again
    with pytest.raises(StreamOrderError, match="frame 0 was passed already"):
        source.read(0)
    with pytest.raises(StreamOrderError, match="frame 3 is ahead of the stream"):
        source.read(3)
    assert source.read(2).frame == 2
    with pytest.raises(IndexError, match="the stream ended after 3 frames"):
        source.read(3)
    assert source.frames_known == 3 and source.poses.shape == (3, 4, 4)


def test_a_stream_without_frames_is_a_clear_error():
    with pytest.raises(ValueError, match="yielded no frame"):
        map_frames(iter(()), table())
    mapper = Mapper(table())
    assert mapper.mesh.GetNumberOfCells() == 0
    with pytest.raises(ValueError, match="no frame was mapped"):
        mapper.finish()


def test_a_stream_refuses_what_is_not_a_frame_of_the_run():
    frames = list(synthetic(2))
    small = Intrinsics(fx=20.0, fy=20.0, cx=7.5, cy=5.5, width=16, height=12)
    other = DepthFrame(np.full((12, 16), 2.0), small, np.eye(4))
    source = StreamedFrames(iter([frames[0], other]))
    source.read(0)
    with pytest.raises(ValueError, match="frame 1 has other intrinsics than frame 0"):
        source.read(1)
    source = StreamedFrames(iter([frames[0], "not a frame"]))
    source.read(0)
    with pytest.raises(TypeError, match="frame 1 is a str, not a DepthFrame"):
        source.read(1)


def test_the_readme_streamed_frames_example_runs(monkeypatch, capsys):
    text = (REPO / "README.md").read_text()
    code = text.split("<!-- example: streamed frames -->")[1].split("```python")[1].split("```")[0]
    monkeypatch.chdir(REPO)
    namespace = {"mabdi": mabdi, "config": table(2)}
    exec(compile(code, "README.md example", "exec"), namespace)
    mesh, result = namespace["mesh"], namespace["result"]
    assert_same_map(mesh, result.mesh)
    assert len(result.records) == 2
