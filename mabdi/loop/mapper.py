"""Mapping frames a script has: :class:`Mapper` (one frame at a time) and :func:`map_frames` (any iterable).

Both run the MABDI loop of a run config over frames that come as they come
(:class:`~mabdi.sources.frames.StreamedFrames`: no length needed), as
``mabdi run`` runs it over a recording.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.config import RunConfig
from mabdi.depth import DepthFrame
from mabdi.loop.loop import FrameRecord, MabdiLoop
from mabdi.loop.run_outputs import RunResult
from mabdi.loop.mapping_run import MappingRun
from mabdi.polydata import transformed_polydata
from mabdi.pose_noise import PoseNoise
from mabdi.sources.frames import StreamedFrames


@dataclass(frozen=True, eq=False)
class FrameStep:
    """What one frame did (:meth:`Mapper.step`), in the world frame; copies, kept after later frames."""

    #: The frame's numbers: novel share, triangles added and removed, registration, times (:class:`FrameRecord`).
    record: FrameRecord
    #: (4, 4) world_from_camera the frame was meshed with: registered to the map, else as given.
    pose: np.ndarray
    #: (H, W) uint8 labels (0 no return, 1 known, 2 novel, 3 contradicted); None with the classifier off.
    labels: np.ndarray | None
    #: The surface meshed from this frame (what it added to the map).
    added: vtkPolyData
    #: The faces object removal took out of the map this frame.
    removed: vtkPolyData

    @property
    def frame(self) -> int:
        """The frame's index in the run (0, 1, ...)."""
        return self.record.frame

    @property
    def registered(self) -> bool:
        """Whether the frame's pose was registered to the map."""
        return self.record.registered


class _Inbox:
    """The frame :meth:`Mapper.step` hands in, as the iterator a :class:`StreamedFrames` reads."""

    def __init__(self) -> None:
        self.frame: DepthFrame | None = None

    def __iter__(self):
        return self

    def __next__(self) -> DepthFrame:
        frame, self.frame = self.frame, None
        if frame is None:
            raise StopIteration
        return frame


def _world_copy(polydata: vtkPolyData, world_from_map: np.ndarray) -> vtkPolyData:
    if not np.array_equal(world_from_map, np.eye(4)):
        return transformed_polydata(polydata, world_from_map)
    copy = vtkPolyData()
    copy.DeepCopy(polydata)
    return copy


class Mapper:
    """The MABDI loop of ``config`` (None: the defaults of :class:`RunConfig`) over frames handed in one at a time.

    ``step(frame)`` maps a :class:`~mabdi.depth.DepthFrame` (depth in metres, intrinsics, world_from_camera;
    every frame of a run has the first one's intrinsics) and returns its :class:`FrameStep`; ``mesh`` is the map
    so far; ``finish()`` ends the run (the check of its poses) and returns the map. The noise model is the
    config's ``[sensor]``; ``pose_accuracy``: how far the poses are off, when known (None: registration learns
    it); ``loses_returns``: whether a pixel without a return may still see a surface (a real camera's).
    """

    def __init__(
        self,
        config: RunConfig | None = None,
        *,
        pose_accuracy: PoseNoise | None = None,
        loses_returns: bool = False,
        description: str = "frames given to a Mapper",
    ) -> None:
        self.config = config if config is not None else RunConfig()
        self._inbox = _Inbox()
        #: The frames as the loop reads them (a stream: no length).
        self.source = StreamedFrames(self._inbox, description, pose_accuracy=pose_accuracy, loses_returns=loses_returns)
        #: The loop, made at the first frame (it needs the frames' intrinsics); None before.
        self.loop: MabdiLoop | None = None
        #: One record per frame mapped, in order.
        self.records: list[FrameRecord] = []
        self.finished = False

    def step(self, frame: DepthFrame) -> FrameStep:
        """Map one frame: registration, E, classifier, surface, world mesh, removal (:meth:`MabdiLoop.step`)."""
        if self.finished:
            raise RuntimeError("this Mapper has finished: make a new one for another run")
        if not isinstance(frame, DepthFrame):
            raise TypeError(f"Mapper.step takes a DepthFrame, got {type(frame).__name__}")
        self._inbox.frame = frame
        try:
            if self.loop is None:
                self.loop = MabdiLoop.from_config(self.config, self.source)
            record = self.loop.step(len(self.records))
        finally:
            self._inbox.frame = None
        self.records.append(record)
        loop = self.loop
        world_from_map = loop.world_from_map()
        labels = loop.labels()
        return FrameStep(
            record=record,
            pose=world_from_map @ loop.meshed_pose(record.frame),  # this frame's alone (trajectory() is every frame's)
            labels=None if labels is None else labels.copy(),
            added=_world_copy(loop.novel_surface(), world_from_map),
            removed=_world_copy(loop.removed_surface(), world_from_map),
        )

    @property
    def frames(self) -> int:
        """How many frames were mapped."""
        return len(self.records)

    @property
    def mesh(self) -> vtkPolyData:
        """The map so far (one vtkPolyData, cell data ``frame``, world frame); empty before the first frame."""
        return vtkPolyData() if self.loop is None else self.loop.mesh()

    def trajectory(self) -> np.ndarray:
        """(N, 4, 4) world_from_camera each frame was meshed with (registered, else as given)."""
        return np.zeros((0, 4, 4)) if self.loop is None else self.loop.trajectory()

    def finish(self) -> vtkPolyData:
        """End the run: a :class:`~mabdi.stages.registration_check.PosesDisagreeWarning` when its poses disagree
        with its depth; returns the map. A ValueError when no frame was mapped."""
        if self.loop is None:
            raise ValueError(f"{self.source.description}: no frame was mapped, so there is no map")
        if not self.finished:
            self.finished = True
            self.loop.finish()
        return self.loop.mesh()

    def close(self) -> None:
        """Release the render windows."""
        if self.loop is not None:
            self.loop.close()

    def __enter__(self) -> Mapper:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def map_frames(
    frames,
    config: RunConfig | None = None,
    *,
    pose_accuracy: PoseNoise | None = None,
    loses_returns: bool = False,
    out_dir=None,
    progress=None,
    description: str = "streamed frames",
) -> RunResult:
    """A run over ``frames``, any iterable of :class:`~mabdi.depth.DepthFrame` (a generator: no length needed):
    the loop of ``config`` (None: the defaults), frame by frame until the iterable ends, through the runner
    (:meth:`MappingRun.run <mabdi.loop.mapping_run.MappingRun.run>`: ``out_dir`` gets the run's files,
    ``progress(record)`` is called after each frame; not evaluated, and no checkpoints: a stream cannot be
    read again). Returns its :class:`RunResult` (``mesh``, ``records``). ``pose_accuracy`` and
    ``loses_returns`` as :class:`Mapper`'s. Frames that are empty: a ValueError."""
    config = config if config is not None else RunConfig()
    source = StreamedFrames(frames, description, pose_accuracy=pose_accuracy, loses_returns=loses_returns)
    simulation = MappingRun(config, source=source)
    try:
        return simulation.run(out_dir, progress)
    finally:
        simulation.loop.close()
