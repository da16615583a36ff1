"""Sources of depth frames: where the measured image D comes from.

A :class:`FrameSource` yields, frame by frame, a :class:`~mabdi.depth.DepthFrame`:
a metric depth image in the project's layout (float32 metres, row 0 at the
top, NaN = no return), its intrinsics, the ``world_from_camera`` pose, the
frame index and a timestamp (seconds). Kinds:

* the simulated rig (scene + off-screen sensor + helical path),
  :class:`mabdi.simulate.rig.SimulatedRig`;
* recorded sequences: TUM RGB-D folders (:mod:`mabdi.sources.tum`), ROS 2
  bags (:mod:`mabdi.sources.rosbag2`) and the common RGB-D dataset layouts
  (3DMatch / 7-Scenes, Redwood / Open3D, ScanNet, Replica:
  :mod:`mabdi.sources.sequences` lists them).

A frame may carry a colour image registered to its depth (``DepthFrame.colour``).

Frames are read by index (``read(i)``, 0 <= i < ``len(source)``), so a run can
start in the middle (``--resume``) and a benchmark can feed the same frame to
several methods. :class:`SourceDepthFrames` makes D of a frame: as a value
(``measured(i)``, what the loop calls) or at the head of a VTK pipeline (set
its ``frame``; the output image carries the frame index, pose, timestamp and
noise model in its field data).

What counts as a return is decided once, in :func:`mabdi.depth.returns`
(finite and near < z < far); :meth:`FrameSource.read` applies it to every
source's depth, so a loop, a TSDF or a recorder sees the same frames.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkImageData
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline

from mabdi.algorithm import MabdiAlgorithm
from mabdi.camera import Intrinsics
from mabdi.depth import NO_NOISE, DepthFrame, only_returns
from mabdi.frame_values import Measured
from mabdi.depth_holes import fill_pixel_holes, is_fragmented
from mabdi.errors import check_switch
from mabdi.pose_noise import PoseNoise
from mabdi.sensor_noise import SensorNoise


class FrameSource:
    """Depth frames by index (see the module docs).

    Subclasses implement ``intrinsics``, ``__len__`` and ``read_frame(index)``
    (called with a checked index); :meth:`read` adds the one rule for returns.
    ``poses`` and ``timestamps`` default to reading every frame; sources that
    know them without decoding depth (recordings, the simulated path) override them.
    """

    #: A short description for messages and ``summary.json`` ("simulated table", "TUM folder ...").
    description: str = "depth frames"
    #: Whether the sensor loses returns on surfaces within its range (glass, black or shiny surfaces, grazing
    #: incidence), so that a pixel without a return says nothing about free space: every recording a reader
    #: opens (:func:`mabdi.sources.sequences.open_sequence`); the simulator's sensors return every surface.
    loses_returns: bool = False

    @property
    def intrinsics(self) -> Intrinsics:
        raise NotImplementedError

    def __len__(self) -> int:
        raise NotImplementedError

    @property
    def frames_known(self) -> int | None:
        """The number of frames when it is known (``len(self)``); None for a stream whose end is not reached yet
        (:class:`StreamedFrames`, whose ``len()`` raises TypeError)."""
        return len(self)

    def has_frame(self, index: int) -> bool:
        """Whether frame ``index`` exists: ``index < len(self)`` (a stream reads ahead to find out)."""
        return 0 <= index < len(self)

    def read(self, index: int) -> DepthFrame:
        """Frame ``index``: depth (float32 metres, NaN = no return), intrinsics, pose, ``frame == index``, timestamp.

        Every depth that is not a return (:func:`mabdi.depth.returns`: NaN, 0,
        negative, infinite, outside (near, far)) is NaN here, whatever the source.
        """
        frame = self.read_frame(self.check_index(index))
        intrinsics = frame.intrinsics
        frame.depth = only_returns(frame.depth, intrinsics.near, intrinsics.far)
        return frame

    def read_frame(self, index: int) -> DepthFrame:
        """Frame ``index`` as the source has it (``read`` cleans it); ``index`` is checked already."""
        raise NotImplementedError

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) world_from_camera of every frame."""
        return np.stack([self.read(i).world_from_camera for i in range(len(self))])

    @property
    def timestamps(self) -> np.ndarray:
        """(N,) timestamps in seconds (NaN where unknown)."""
        return np.array([self.read(i).timestamp for i in range(len(self))], dtype=np.float64)

    @property
    def has_colour(self) -> bool:
        """Whether the frames carry colour images (known without reading a frame; sources with colour say so)."""
        return False

    @property
    def true_poses(self) -> np.ndarray | None:
        """(N, 4, 4) the poses the sensor really had, when the source knows them (a simulation with pose
        noise: ``poses`` are the given ones), else None. Use them to judge what the sensor saw, or how far
        off the given poses are; the map is built with ``poses``."""
        return None

    @property
    def noise(self) -> SensorNoise | None:
        """The sensor's noise model, when the source knows it (the simulator: the model it draws from);
        None when it does not (recordings: the run's ``[sensor] noise`` says what the camera is). D carries
        it in its field data (:class:`SourceDepthFrames`)."""
        return None

    @property
    def pose_accuracy(self) -> PoseNoise | None:
        """How far ``poses`` are off, when the source says (the simulator: its ``[sensor.pose_noise]``, all
        zero for exact poses), as jitter and drift rates; None when it does not (recordings: the
        registration learns it from the run, :mod:`mabdi.stages.map_anchor`)."""
        return None

    def check_index(self, index: int) -> int:
        """``index`` as an int, or IndexError naming the source and its length."""
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < len(self):
            raise IndexError(f"{self.description}: frame {index!r} out of range (0 .. {len(self) - 1})")
        return int(index)

    def __iter__(self) -> Iterator[DepthFrame]:
        for i in range(len(self)):
            yield self.read(i)

    def close(self) -> None:
        """Release files or render windows the source holds (reading again reopens them)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def check_statements(owner: str, noise, pose_accuracy) -> None:
    """A TypeError naming ``owner`` unless what a source states about its frames has the right types: its
    ``noise`` a :class:`SensorNoise` and its ``pose_accuracy`` a :class:`PoseNoise` (or None: not stated)."""
    if noise is not None and not isinstance(noise, SensorNoise):
        raise TypeError(f"{owner}: noise must be a SensorNoise or None, got {noise!r}")
    if pose_accuracy is not None and not isinstance(pose_accuracy, PoseNoise):
        raise TypeError(f"{owner}: pose_accuracy must be a PoseNoise or None, got {pose_accuracy!r}")


class FrameList(FrameSource):
    """A source over frames already in memory (tests, or frames a user built with numpy).

    ``true_poses``, ``noise`` and ``pose_accuracy`` are what the maker of the frames knows and states (the
    bench keeps a simulation's frames here and states what the simulator does, so a method run on them
    is run as ``mabdi run`` runs it); None: not stated (as a recording).
    """

    def __init__(
        self,
        frames: list[DepthFrame],
        description: str = "frames in memory",
        true_poses=None,
        noise: SensorNoise | None = None,
        pose_accuracy: PoseNoise | None = None,
    ) -> None:
        if not frames:
            raise ValueError("FrameList needs at least one frame")
        check_statements("FrameList", noise, pose_accuracy)
        self._frames = list(frames)
        self.description = description
        self._noise = noise
        self._pose_accuracy = pose_accuracy
        self._true_poses = None if true_poses is None else np.array(true_poses, dtype=np.float64)
        if self._true_poses is not None and self._true_poses.shape != (len(self._frames), 4, 4):
            raise ValueError(f"FrameList: true_poses must be ({len(self._frames)}, 4, 4), got shape {self._true_poses.shape}")

    @property
    def intrinsics(self) -> Intrinsics:
        return self._frames[0].intrinsics

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def poses(self) -> np.ndarray:
        return np.stack([frame.world_from_camera for frame in self._frames])

    @property
    def timestamps(self) -> np.ndarray:
        return np.array([frame.timestamp for frame in self._frames], dtype=np.float64)

    @property
    def true_poses(self) -> np.ndarray | None:
        return None if self._true_poses is None else self._true_poses.copy()

    @property
    def noise(self) -> SensorNoise | None:
        return self._noise

    @property
    def pose_accuracy(self) -> PoseNoise | None:
        return self._pose_accuracy

    @property
    def has_colour(self) -> bool:
        return self._frames[0].colour is not None

    def read_frame(self, index: int) -> DepthFrame:
        frame = self._frames[index]
        return replace(frame, frame=index)


class StreamOrderError(IndexError):
    """A frame of a :class:`StreamedFrames` asked for out of order: one already passed, or one ahead of the next."""


class StreamedFrames(FrameSource):
    """A source over any iterable of :class:`~mabdi.depth.DepthFrame` (a generator, a camera's feed), read in order.

    Reading frame ``i`` pulls the iterable's next frame; the current frame is kept, so it may be read again,
    but a frame already passed, or one beyond the next, raises :class:`StreamOrderError`. The length is not
    known: ``len()`` raises TypeError and :attr:`frames_known` is None until the iterable ends. ``intrinsics``
    are the first frame's (read ahead when asked before frame 0; an iterable with no frame is a ValueError).
    ``poses`` and ``timestamps`` are the frames' read so far. ``noise``, ``pose_accuracy`` and
    ``loses_returns`` are what the maker of the frames states (as :class:`FrameList`); frames are renumbered
    0, 1, ... in the order they come.
    """

    def __init__(
        self,
        frames,
        description: str = "streamed frames",
        noise: SensorNoise | None = None,
        pose_accuracy: PoseNoise | None = None,
        loses_returns: bool = False,
    ) -> None:
        check_statements("StreamedFrames", noise, pose_accuracy)
        self._iterator = iter(frames)
        self.description = description
        self._noise = noise
        self._pose_accuracy = pose_accuracy
        self.loses_returns = bool(loses_returns)
        self._pulled: list[DepthFrame] = []  # at most two: the current frame and one read ahead
        self._first = 0  # the index of self._pulled[0]
        self._ended = False
        self._poses: list[np.ndarray] = []
        self._timestamps: list[float] = []
        self._first_frame: DepthFrame | None = None

    def _pull(self) -> bool:
        """Take the iterable's next frame (False when it has ended)."""
        if self._ended:
            return False
        try:
            frame = next(self._iterator)
        except StopIteration:
            self._ended = True
            return False
        index = self._first + len(self._pulled)
        if not isinstance(frame, DepthFrame):
            raise TypeError(f"{self.description}: frame {index} is a {type(frame).__name__}, not a DepthFrame")
        if self._first_frame is None:
            self._first_frame = frame
        if frame.intrinsics != self._first_frame.intrinsics:
            raise ValueError(
                f"{self.description}: frame {index} has other intrinsics than frame 0 "
                f"({frame.intrinsics} != {self._first_frame.intrinsics})"
            )
        self._pulled.append(frame)
        self._poses.append(np.array(frame.world_from_camera, dtype=np.float64))
        self._timestamps.append(float(frame.timestamp))
        return True

    @property
    def intrinsics(self):
        if self._first_frame is None and not self._pull():
            raise ValueError(f"{self.description}: the frames are empty (the iterable yielded no frame)")
        return self._first_frame.intrinsics

    def __len__(self) -> int:
        raise TypeError(f"{self.description}: a stream of frames has no length (frames_known is None until it ends)")

    @property
    def frames_known(self) -> int | None:
        return self._first + len(self._pulled) if self._ended else None

    @property
    def frames_read(self) -> int:
        """How many frames the iterable has given so far."""
        return len(self._poses)

    def has_frame(self, index: int) -> bool:
        while index >= self._first + len(self._pulled) and self._pull():
            pass
        return 0 <= index < self._first + len(self._pulled)

    def check_index(self, index: int) -> int:
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 0:
            raise IndexError(f"{self.description}: frame {index!r} out of range (frames are 0, 1, ...)")
        index = int(index)
        if index < self._first:
            raise StreamOrderError(
                f"{self.description}: frame {index} was passed already (the stream is at frame {self._first}): "
                "streamed frames are read once, in order"
            )
        if index > self._first + len(self._pulled):
            raise StreamOrderError(
                f"{self.description}: frame {index} is ahead of the stream (its next frame is "
                f"{self._first + len(self._pulled)}): streamed frames are read in order"
            )
        if index == self._first + len(self._pulled) and not self._pull():
            ended = self._first + len(self._pulled)
            raise IndexError(f"{self.description}: frame {index} out of range (the stream ended after {ended} frames)")
        return index

    def read_frame(self, index: int) -> DepthFrame:
        drop = index - self._first  # frames before this one are passed
        del self._pulled[:drop]
        self._first = index
        frame = self._pulled[0]
        return replace(frame, frame=index)

    @property
    def poses(self) -> np.ndarray:
        """(n, 4, 4) the given poses of the frames read so far."""
        return np.array(self._poses, dtype=np.float64).reshape(-1, 4, 4)

    @property
    def timestamps(self) -> np.ndarray:
        """(n,) the timestamps of the frames read so far."""
        return np.array(self._timestamps, dtype=np.float64)

    @property
    def has_colour(self) -> bool:
        try:
            self.intrinsics  # the first frame, read ahead
        except ValueError:
            return False
        return self._first_frame.colour is not None

    @property
    def noise(self) -> SensorNoise | None:
        return self._noise

    @property
    def pose_accuracy(self) -> PoseNoise | None:
        return self._pose_accuracy

    def __iter__(self) -> Iterator[DepthFrame]:
        """The frames from the current one (the first, before any is read) to the end of the stream."""
        index = self._first
        while self.has_frame(index):
            yield self.read(index)
            index += 1


class FrameSubset(FrameSource):
    """The frames ``indices`` of ``source``, renumbered 0 .. len - 1 (read lazily, one at a time).

    The source's statements (noise, pose accuracy, true poses) are passed on for those frames.
    """

    def __init__(self, source: FrameSource, indices) -> None:
        indices = np.asarray(indices, dtype=np.int64)
        if indices.ndim != 1 or len(indices) == 0:
            raise ValueError("FrameSubset needs a non-empty 1-D list of frame indices")
        if indices.min() < 0 or indices.max() >= len(source):
            raise IndexError(f"{source.description}: frame indices must be in 0 .. {len(source) - 1}")
        self.base = source
        self.indices = indices
        self.description = f"{source.description}: {len(indices)} of its frames"

    @property
    def intrinsics(self):
        return self.base.intrinsics

    def __len__(self) -> int:
        return len(self.indices)

    def read_frame(self, index: int) -> DepthFrame:
        frame = self.base.read(int(self.indices[index]))
        return replace(frame, frame=index)

    @property
    def poses(self) -> np.ndarray:
        return self.base.poses[self.indices]

    @property
    def timestamps(self) -> np.ndarray:
        return self.base.timestamps[self.indices]

    @property
    def has_colour(self) -> bool:
        return self.base.has_colour

    @property
    def loses_returns(self) -> bool:
        return self.base.loses_returns

    @property
    def true_poses(self):
        true = self.base.true_poses
        return None if true is None else true[self.indices]

    @property
    def noise(self):
        return self.base.noise

    @property
    def pose_accuracy(self):
        return self.base.pose_accuracy

    def close(self) -> None:
        self.base.close()


class SourceDepthFrames(MabdiAlgorithm):
    """D of a :class:`FrameSource`'s frames: :meth:`measured` (a value), or as a VTK source: no input, the
    depth image of frame ``frame`` out.

    The output is D with field data ``intrinsics``, ``world_from_camera``,
    ``frame``, ``timestamp`` and the sensor's noise model (``noise``; None: the
    source's own statement, :attr:`FrameSource.noise`; an image without one is
    read as noise-free), and the point array ``colour`` when the frame has a
    colour image; depths that are not returns are NaN. With ``noise = "auto"``
    D carries the calibrated curve as it stands when D is made.

    ``pixel_holes``: a camera's one-pixel holes filled where the pixels on
    either side agree (:mod:`mabdi.depth_holes`): ``"auto"`` (the default) on
    fragmented frames only, true on every frame, false never; ``filled_pixels``
    says how many the last frame got. Range images are left as they are.
    """

    def __init__(self, source: FrameSource, noise: SensorNoise | str | None = None, pixel_holes: bool | str = "auto") -> None:
        super().__init__(nInputPorts=0, nOutputPorts=1, outputType="vtkImageData")
        check_switch("pixel_holes", pixel_holes)
        self._source = source
        self._frame = 0
        self._noise = SensorNoise.of(noise) if noise is not None else source.noise
        self._pixel_holes = pixel_holes
        #: One-pixel holes filled in the last frame made (:mod:`mabdi.depth_holes`).
        self.filled_pixels = 0

    @property
    def source(self) -> FrameSource:
        return self._source

    @property
    def noise(self) -> SensorNoise | None:
        """The sensor's noise model D carries (None: none stated)."""
        return self._noise

    @property
    def frame(self) -> int:
        """The frame index the next update reads."""
        return self._frame

    @frame.setter
    def frame(self, value: int) -> None:
        self._set("_frame", self._source.check_index(value))

    def _fills_holes(self, depth: np.ndarray, geometry) -> bool:
        if self._pixel_holes is False or not isinstance(geometry, Intrinsics):
            return False
        return self._pixel_holes is True or is_fragmented(depth)

    def RequestInformation(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        intrinsics = self._source.intrinsics
        info = outInfo.GetInformationObject(0)
        extent = (0, intrinsics.width - 1, 0, intrinsics.height - 1, 0, 0)
        info.Set(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT(), extent, 6)
        info.Set(vtkImageData.SPACING(), (1.0, 1.0, 1.0), 3)
        info.Set(vtkImageData.ORIGIN(), (0.0, 0.0, 0.0), 3)
        return 1

    def measured(self, index: int) -> Measured:
        """D of frame ``index`` (:class:`~mabdi.frame_values.Measured`: depth with one-pixel holes filled as
        ``pixel_holes`` says, the given pose, the noise model as it stands now); sets :attr:`filled_pixels`."""
        frame = self._source.read(self._source.check_index(index))
        depth = frame.depth.copy()  # D owns its buffers
        self.filled_pixels = 0
        if self._fills_holes(depth, frame.intrinsics):
            geometry = frame.intrinsics
            noisy = self._noise is not None and self._noise.noisy
            sigma = (lambda z: self._noise.sigma(z, geometry.near, geometry.far)) if noisy else None
            depth, self.filled_pixels = fill_pixel_holes(depth, sigma)
        geometry = frame.intrinsics
        noise = NO_NOISE if self._noise is None else self._noise.snapshot()
        colour = None if frame.colour is None else frame.colour.copy()
        depth = only_returns(np.asarray(depth, dtype=np.float32), geometry.near, geometry.far)
        return Measured(
            depth, geometry, np.asarray(frame.world_from_camera, dtype=np.float64), noise, int(index), frame.timestamp, colour,
            frame.return_points,
        )  # fmt: skip

    def RequestData(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        self.measured(self._frame).fill(vtkImageData.GetData(outInfo))
        return 1
