"""A surface in front of the map is meshed once it has been seen there in a few frames (``[classifier]
front_frames``; "auto": 3 for a real camera, whose noise model is learnt from its frames, 1 for the simulator's).

A real camera's look at a known surface falls in front of the map now and then (the poses drift between two
visits, a rim spreads over a silhouette); meshed at once, each such look was a second copy of the surface in front
of the map. A new object stays in front frame after frame and is meshed in the third."""

from __future__ import annotations

import numpy as np
import pytest

import mabdi
from mabdi.camera import Intrinsics
from mabdi.depth import DepthFrame
from mabdi.errors import ConfigError
from mabdi.frame_values import Expected, Measured
from mabdi.noise_calibration import NoiseCurve
from mabdi.sensor_noise import SensorNoise
from mabdi.sources.frames import FrameList
from mabdi.stages.classifier import KNOWN, NOVEL, ClassifierParameters, FilterClassifier
from mabdi.stages.front_confirmation import VOXEL, FrontConfirmation, voxel_centres, voxel_keys
from mabdi.stages.registration import RegistrationParameters

CAMERA = Intrinsics(fx=80.0, fy=80.0, cx=40.0, cy=30.0, width=80, height=60)
BOX = (slice(20, 40), slice(30, 50))  # 20 x 20 pixels in the middle of the image


def wall(depth: float = 2.0) -> np.ndarray:
    return np.full(CAMERA.shape, depth, np.float32)


def with_box(in_front: float = 0.5) -> np.ndarray:
    """The wall at 2 m with a box ``in_front`` metres nearer over :data:`BOX`."""
    depth = wall()
    depth[BOX] -= in_front
    return depth


def classify(depth: np.ndarray, memory: FrontConfirmation | None, pose: np.ndarray | None = None, expected=None):
    pose = np.eye(4) if pose is None else pose
    measured = Measured(depth, CAMERA, pose, SensorNoise("kinect"), 1)
    e = Expected(wall() if expected is None else expected, CAMERA, pose, 1)
    return FilterClassifier(ClassifierParameters(rim=0, gradual=False)).classify(measured, e, front_memory=memory)


def box_meshed(classified) -> bool:
    meshed = np.isfinite(classified.depth[BOX])
    assert meshed.all() or not meshed.any()  # the box waits or is meshed as one
    return bool(meshed.all())


def test_a_new_object_in_front_of_the_map_is_meshed_in_the_third_frame_that_sees_it():
    memory = FrontConfirmation(3)
    for frame in (1, 2):
        waited = classify(with_box(), memory)
        assert not box_meshed(waited), frame
        assert (waited.labels[BOX] == NOVEL).all()  # still novel: only its meshing waits
        assert waited.counts["novel"] == 0
    assert box_meshed(classify(with_box(), memory))
    assert memory.voxels == 0  # meshed: the map holds the surface in front now
    # without a memory (front_frames 1) it is meshed in the first frame, as before
    assert box_meshed(classify(with_box(), None))
    assert box_meshed(classify(with_box(), FrontConfirmation(1)))


def test_a_look_in_front_that_the_next_frame_confirms_is_forgotten():
    """A look in front, then a frame that sees the map's surface there: the count starts again."""
    memory = FrontConfirmation(3)
    assert not box_meshed(classify(with_box(), memory))
    confirming = classify(wall(), memory)
    assert (confirming.labels == KNOWN).all()
    assert memory.voxels == 0
    for _ in range(2):
        assert not box_meshed(classify(with_box(), memory))  # the count is 1, then 2: still waiting
    assert box_meshed(classify(with_box(), memory))


def test_a_look_in_front_that_alternates_with_the_map_is_never_meshed():
    memory = FrontConfirmation(3)
    for frame in range(8):
        assert not box_meshed(classify(with_box() if frame % 2 == 0 else wall(), memory)), frame


def test_a_part_of_the_map_out_of_view_keeps_its_count():
    """Between two looks in front, a frame that does not see that part of the map (turned away) neither
    counts nor forgets it."""
    memory = FrontConfirmation(3)
    assert not box_meshed(classify(with_box(), memory))
    turned = np.eye(4)
    turned[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]  # looking along +x: the wall at z = 2 is out of view
    classify(wall(), memory, pose=turned)
    assert memory.voxels > 0
    assert not box_meshed(classify(with_box(), memory))  # two frames
    assert box_meshed(classify(with_box(), memory))  # three


def test_the_memory_goes_on_from_its_checkpointed_state():
    memory = FrontConfirmation(3)
    for _ in range(2):
        classify(with_box(), memory)
    restored = FrontConfirmation(3)
    restored.set_state(memory.state())
    assert restored.voxels == memory.voxels > 0
    assert box_meshed(classify(with_box(), restored))
    memory.reset()
    assert memory.voxels == 0


def test_voxel_keys_name_the_voxel_and_give_back_its_centre():
    points = np.array([[0.001, 0.0, 0.0], [-0.001, 5.019, -3.0], [123.4, -56.7, 8.9]])
    keys = voxel_keys(points)
    centres = voxel_centres(keys)
    assert np.all(np.abs(centres - points) <= VOXEL / 2 + 1e-12)
    assert len(set(voxel_keys(np.array([[0.001, 0, 0], [-0.001, 0, 0], [0, 0.001, 0], [0, -0.001, 0]])).tolist())) == 3
    with pytest.raises(ValueError, match="from the map's origin"):
        voxel_keys(np.array([[1e5, 0.0, 0.0]]))


@pytest.mark.parametrize("value", [0, -1, 2.5, "three", True])
def test_front_frames_other_than_a_positive_integer_or_auto_is_an_error_naming_it(value):
    with pytest.raises(ConfigError, match="front_frames"):
        ClassifierParameters(front_frames=value)


def test_auto_waits_for_a_real_cameras_learnt_noise_only():
    parameters = ClassifierParameters()
    assert parameters.front_frames == "auto"
    assert parameters.front_frames_for(SensorNoise("auto")) == 3
    for model in ("none", "kinect", "structured_light"):
        assert parameters.front_frames_for(SensorNoise(model)) == 1
    assert ClassifierParameters(front_frames=2).front_frames_for(SensorNoise("kinect")) == 2


def wobbling_wall_frames(frames: int, wobble: bool = True) -> FrameList:
    """A static wall 2 m ahead; every other frame sees a patch of it 5 cm nearer (a pose a little off at a
    silhouette, as a real camera's look falls now and then; ``wobble`` False: never), with Kinect noise."""
    rng = np.random.default_rng(0)
    sigma = float(SensorNoise("kinect").sigma(np.array([2.0]), CAMERA.near, CAMERA.far)[0])
    depths = []
    for i in range(frames):
        depth = with_box(0.05) if i % 2 and wobble else wall()
        depths.append((depth + rng.normal(0.0, 0.2 * sigma, depth.shape)).astype(np.float32))
    return FrameList([DepthFrame(d, CAMERA, np.eye(4), i, i / 30) for i, d in enumerate(depths)])


@pytest.mark.parametrize("front_frames", [1, 3])
def test_a_wobbling_look_at_a_static_wall_leaves_one_surface(front_frames):
    """The loop: with the look in front meshed at once (1) the patch is meshed in front of the wall in frame 1,
    contradicted and removed, and meshed again; with 3 it never is, and the map is the one the steady wall makes."""

    def faces_added(wobble: bool) -> list[int]:
        frames = wobbling_wall_frames(8, wobble)
        loop = mabdi.MabdiLoop(
            frames, surface="quadtree", noise="kinect", classifier=ClassifierParameters(front_frames=front_frames),
            registration=RegistrationParameters(enabled=False),
        )  # fmt: skip
        assert (loop.front_memory is not None) == (front_frames > 1)
        return [loop.step(i).cells_added for i in range(len(frames))]

    steady, wobbling = faces_added(False), faces_added(True)
    assert steady[0] > 0 and sum(steady[2:]) == 0
    if front_frames == 1:
        assert wobbling[1] > steady[1] + 20 and sum(wobbling[2:]) > 20, (wobbling, steady)
    else:
        assert wobbling == steady


def test_the_loop_waits_for_a_real_cameras_looks_in_front_by_default():
    learnt = SensorNoise("auto", calibration=NoiseCurve(0.0, 1.4e-3, 2.0))
    loop = mabdi.MabdiLoop(wobbling_wall_frames(2), noise=learnt)
    assert loop.classifier_parameters.front_frames == 3 and loop.front_memory is not None
    assert mabdi.MabdiLoop(wobbling_wall_frames(2), noise="kinect").front_memory is None


def test_a_voxel_as_much_on_the_map_as_in_front_of_it_is_confirmed_not_counted():
    """Per voxel of the map's surface, a frame counts only where more of its pixels lie in front of the map than on
    it: a rim that covers part of a voxel whose other pixels see the map (a silhouette a pixel or two off) is the
    map confirmed. A wall 0.3 m away: about five pixels a voxel each way."""
    near_wall = wall(0.3)
    rows, cols = np.indices(CAMERA.shape)
    few = (rows % 2 == 0) & (cols % 2 == 0)  # a pixel in four in front of the map, the others on it
    memory = FrontConfirmation(2)
    for _ in range(3):
        assert memory.waiting(few, ~few, near_wall, CAMERA, np.eye(4)).sum() == few.sum()  # all wait
        assert memory.voxels == 0  # and none is counted
    mostly = ~few  # three pixels in four in front
    assert memory.waiting(mostly, ~mostly, near_wall, CAMERA, np.eye(4)).sum() == mostly.sum()
    assert memory.voxels > 0
    assert not memory.waiting(mostly, ~mostly, near_wall, CAMERA, np.eye(4)).any()  # the second frame: meshed


def test_the_loops_checkpoint_carries_the_memory(tmp_path):
    """A run resumed from a checkpoint file goes on counting where it stopped: the frame that was the third look
    meshes the surface in front in the resumed run as in the whole one."""
    from mabdi.io.checkpoint import read_tree, write_tree

    depths = [wall()] + [with_box(0.3)] * 3  # the box stands in front of the wall from frame 1 on
    steady_box = FrameList([DepthFrame(d, CAMERA, np.eye(4), i, i / 30) for i, d in enumerate(depths)])

    def loop():
        return mabdi.MabdiLoop(
            steady_box, surface="quadtree", noise="kinect", classifier=ClassifierParameters(front_frames=3),
            registration=RegistrationParameters(enabled=False),
        )  # fmt: skip

    whole = loop()
    added = [whole.step(i).cells_added for i in range(4)]
    assert added[1] == added[2] == 0 < added[3]
    first = loop()
    for i in range(3):
        first.step(i)
    assert first.front_memory.voxels > 0
    write_tree(tmp_path / "state.ckpt", first.state())
    resumed = loop()
    resumed.set_state(read_tree(tmp_path / "state.ckpt"))
    assert resumed.front_memory.voxels == first.front_memory.voxels
    assert resumed.step(3).cells_added == added[3]


def test_pixels_where_the_map_has_no_surface_are_neither_counted_nor_confirming():
    memory = FrontConfirmation(3)
    expected = wall()
    expected[:, :10] = np.nan  # no surface of the map there
    everywhere = np.ones(CAMERA.shape, dtype=bool)
    waiting = memory.waiting(everywhere, ~everywhere, expected, CAMERA, np.eye(4))
    assert waiting[:, 10:].all() and not waiting[:, :10].any()
    assert memory.voxels > 0
