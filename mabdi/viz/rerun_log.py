"""Every frame of the MABDI loop logged to Rerun (``mabdi run --rerun [FILE.rrd]``).

:class:`RerunLogger` sends, on the timeline ``frame`` (a sequence):

* ``world``: view coordinates right-handed, z up (static);
* ``world/camera``: the sensor's pose (``world_from_camera`` as a
  Transform3D) and a pinhole camera (the intrinsics, OpenCV camera frame: x
  right, y down, z forward); under it the images, which the viewer also
  projects into 3D: ``world/camera/D`` (measured depth, metres),
  ``world/camera/E`` (expected depth; only with the classifier on) and
  ``world/camera/labels`` (segmentation image: 0 no return, 1 known, 2
  novel, 3 contradicted, with the dashboard's colours; only with the
  classifier on), ``world/camera/rgb`` (the colour image, when the source
  has one); no return is depth 0, Rerun's "no data";
* ``world/novel``: this frame's novel surface (triangles, world coordinates);
* ``world/map/<block name>``: the map, one entity per block of the world
  mesh's vtkMultiBlockDataSet (``frame_<i>``, ``patch_<key>``): only blocks
  that are new or were replaced are sent, and blocks that left the map are
  cleared; each block in its vertex colours (the camera's, from a source
  with colour images), else coloured by the frame that made it;
* ``world/path``: the sensor's path up to this frame;
* ``metrics/...``: the frame's record as time series: ``novel_fraction``,
  ``cells_total``, ``cells_added``, and ``metrics/time_ms`` with one line per
  stage time of the record (``depth``, ``expected``, ..., ``total``: its
  ``t_*_ms`` fields).

``RerunLogger(path)`` saves a recording to ``path`` (``.rrd``); without a
path it spawns a viewer, or connects to one already running.
:func:`rerun_progress` makes the observer (:class:`RerunProgress`) that
``mabdi run --rerun`` gives the run's pipeline; it also serves as the
``progress`` callback of ``MappingRun.run(progress=...)``. Needs the optional
``rerun`` extra (``pip install "mabdi[rerun]"``); rerun is imported only here.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.errors import MabdiError
from mabdi.polydata import named_leaves
from mabdi.mesh_maps.mesh_map import COLOUR_LAYER
from mabdi.loop.run_pipeline import RunObserver

TIMELINE = "frame"
#: Colours of the classified image (RGB), as the dashboard draws it.
LABEL_CLASSES = (
    (0, "no return", (128, 128, 128)),
    (1, "known", (255, 255, 255)),
    (2, "novel", (0, 0, 0)),
    (3, "contradicted", (220, 30, 30)),
)
#: The numbers of a frame record sent as time series (the rest are counts of pixels).
METRICS = ("novel_fraction", "cells_total", "cells_added")


def _rerun():
    try:
        import rerun as rr
    except ImportError:
        raise MabdiError('logging to Rerun needs rerun-sdk: pip install "mabdi[rerun]"') from None
    return rr


def triangles_of(polydata: vtkPolyData) -> tuple[np.ndarray, np.ndarray]:
    """(points float32 (N, 3), triangles uint32 (M, 3)) of a polydata's polygons (others are triangulated)."""
    points = polydata.GetPoints()
    if points is None or polydata.GetNumberOfPolys() == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32)
    polys = polydata.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray())
    if not np.all(np.diff(offsets) == 3):
        from vtkmodules.vtkFiltersCore import vtkTriangleFilter

        triangulate = vtkTriangleFilter()
        triangulate.SetInputData(polydata)
        triangulate.PassVertsOff()
        triangulate.PassLinesOff()
        triangulate.Update()
        polydata = triangulate.GetOutput()
        polys = polydata.GetPolys()
    connectivity = vtk_to_numpy(polys.GetConnectivityArray())
    xyz = vtk_to_numpy(polydata.GetPoints().GetData())
    return xyz.astype(np.float32, copy=False), connectivity.reshape(-1, 3).astype(np.uint32, copy=False)


#: Viridis at 0, 1/4, 1/2, 3/4, 1 (RGB): colours of the map by frame, without loading matplotlib.
_VIRIDIS = np.array([(68, 1, 84), (59, 82, 139), (33, 145, 140), (94, 201, 98), (253, 231, 37)], dtype=np.float64)


def frame_colour(t: float) -> np.ndarray:
    """RGB uint8 of viridis at ``t`` in [0, 1] (linear between five anchors)."""
    x = np.linspace(0.0, 1.0, len(_VIRIDIS))
    return np.round([np.interp(t, x, _VIRIDIS[:, c]) for c in range(3)]).astype(np.uint8)


class RerunLogger:
    """Logs a :class:`mabdi.loop.loop.MabdiLoop` frame by frame to Rerun (see the module docs).

    ``path``: a ``.rrd`` file to save, or None to spawn / connect to a viewer.
    ``frames``: the run's length, for the colours of the map by frame.
    ``name``: the recording's name. ``images``: also send D, E and labels
    (about 2.8 MB a frame at 640x480).
    """

    def __init__(self, path=None, frames: int | None = None, name: str = "mabdi", images: bool = True) -> None:
        rr = _rerun()
        self.rr = rr
        self.path = Path(path) if path is not None else None
        self.frames = frames
        self.images = images
        self.stream = rr.RecordingStream("mabdi", recording_id=f"{name}-{time.time_ns()}")
        if self.path is not None:
            if not self.path.parent.is_dir():
                raise FileNotFoundError(f"cannot write {self.path}: folder {self.path.parent} does not exist")
            self.stream.save(str(self.path))
        else:
            try:
                self.stream.spawn()
            except Exception as exc:  # no viewer binary, no display...
                raise MabdiError(f"cannot start or reach a Rerun viewer ({exc}); give a file instead: --rerun run.rrd") from None
        if hasattr(self.stream, "send_recording_name"):
            self.stream.send_recording_name(name)
        self._blocks: dict[str, tuple[str, int]] = {}
        self._path_points: list[np.ndarray] = []
        self._pinhole = None
        self._stages: list[str] = []
        self._colours: dict[int, np.ndarray] = {}
        self.seconds = 0.0  # time spent logging, in total
        self.logged_frames = 0
        self._log_static()

    def _log_static(self) -> None:
        rr, log = self.rr, self.stream.log
        log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        log(
            "world/camera/labels",
            rr.AnnotationContext([(i, label, colour) for i, label, colour in LABEL_CLASSES]),
            static=True,
        )

    def _colour(self, frame: int) -> np.ndarray:
        colour = self._colours.get(frame)
        if colour is None:
            span = max((self.frames or 1) - 1, 1)
            colour = self._colours[frame] = frame_colour(min(max(frame, 0), span) / span)
        return colour

    def log_frame(self, loop, record) -> None:
        """Log what ``loop`` (a MabdiLoop) produced in the frame of ``record`` (its FrameRecord)."""
        start = time.perf_counter()
        rr, log = self.rr, self.stream.log
        self.stream.set_time(TIMELINE, sequence=int(record.frame))
        measured = loop.last_frame.measured
        pose = measured.pose
        intrinsics = loop.intrinsics

        log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        key = (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, intrinsics.width, intrinsics.height)
        if key != self._pinhole:  # the intrinsics change rarely: log them when they do
            self._pinhole = key
            log(
                "world/camera",
                rr.Pinhole(
                    image_from_camera=[[intrinsics.fx, 0.0, intrinsics.cx], [0.0, intrinsics.fy, intrinsics.cy], [0.0, 0.0, 1.0]],
                    resolution=[intrinsics.width, intrinsics.height],
                    camera_xyz=rr.ViewCoordinates.RDF,
                    image_plane_distance=0.3,
                ),
            )
        if self.images:
            log("world/camera/D", rr.DepthImage(np.fmax(measured.depth, np.float32(0.0)), meter=1.0))
            if measured.colour is not None:
                log("world/camera/rgb", rr.Image(measured.colour, color_model="RGB"))
            expected = loop.last_frame.expected
            if expected is not None:
                log("world/camera/E", rr.DepthImage(np.fmax(expected.depth, np.float32(0.0)), meter=1.0))
            labels = loop.labels()
            if labels is not None:
                log("world/camera/labels", rr.SegmentationImage(labels))

        points, triangles = triangles_of(loop.novel_surface())
        if len(triangles):
            log("world/novel", rr.Mesh3D(vertex_positions=points, triangle_indices=triangles, albedo_factor=self._colour(record.frame)))
        else:
            log("world/novel", rr.Clear(recursive=False))
        self._log_map(loop.world.map, record.frame)

        self._path_points.append(pose[:3, 3].astype(np.float32))
        log("world/path", rr.LineStrips3D([np.array(self._path_points)], colors=[(255, 140, 0)]))

        values = dataclasses.asdict(record) if dataclasses.is_dataclass(record) else dict(vars(record))
        for name in METRICS:
            if name in values:
                log(f"metrics/{name}", rr.Scalars(float(values[name])))
        stages = [name for name in values if name.startswith("t_") and name.endswith("_ms")]
        if stages:  # one multi-series entity: one call, one line per stage
            if stages != self._stages:
                self._stages = stages
                log("metrics/time_ms", rr.SeriesLines(names=[name[2:-3] for name in stages]), static=True)
            log("metrics/time_ms", rr.Scalars([float(values[name]) for name in stages]))
        self.logged_frames += 1
        self.seconds += time.perf_counter() - start

    def _log_map(self, blocks, frame: int) -> None:
        """Send the blocks that are new or replaced since the last frame; clear the ones that left."""
        rr, log = self.rr, self.stream.log
        seen = set()
        for name, block in named_leaves(blocks):
            name = name or "map"
            seen.add(name)
            stamp = (block.GetAddressAsString("vtkObject"), block.GetMTime())
            if self._blocks.get(name) == stamp:
                continue
            self._blocks[name] = stamp
            points, triangles = triangles_of(block)
            frames = block.GetCellData().GetArray("frame")
            made = int(frames.GetTuple1(0)) if frames is not None and frames.GetNumberOfTuples() else frame
            colours = block.GetPointData().GetArray(COLOUR_LAYER)
            if colours is not None:  # the camera's colours, per vertex
                mesh = rr.Mesh3D(vertex_positions=points, triangle_indices=triangles, vertex_colors=vtk_to_numpy(colours))
            else:
                mesh = rr.Mesh3D(vertex_positions=points, triangle_indices=triangles, albedo_factor=self._colour(made))
            log(f"world/map/{name}", mesh)
        for name in [n for n in self._blocks if n not in seen]:
            del self._blocks[name]
            log(f"world/map/{name}", rr.Clear(recursive=True))

    def close(self) -> None:
        """Flush and finish the recording (the file is complete after this)."""
        stream = self.stream
        if stream is None:
            return
        stream.flush()
        stream.disconnect()
        self.stream = None

    def __enter__(self) -> RerunLogger:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RerunProgress(RunObserver):
    """Logs each frame of a MappingRun's run: an observer of :class:`~mabdi.loop.run_pipeline.RunPipeline`,
    or a ``progress(record)`` callback; the recording is finished after the last frame (or when the run stops)."""

    def __init__(self, simulation, path=None, images: bool = True) -> None:
        frames = getattr(simulation, "frames", None) or len(simulation.poses)
        name = simulation.config.run.name or "mabdi"
        self.simulation = simulation
        self.frames = frames
        self.logger = RerunLogger(path, frames=frames, name=name, images=images)

    def __call__(self, record) -> None:
        self.logger.log_frame(self.simulation.loop, record)
        if record.frame + 1 >= self.frames:
            self.close()

    def on_frame(self, pipeline, record) -> None:
        self(record)

    def on_abort(self, pipeline, error) -> None:
        self.close()

    def close(self) -> None:
        self.logger.close()

    @property
    def seconds(self) -> float:
        """Time spent logging so far."""
        return self.logger.seconds


def rerun_progress(simulation, path_or_none=None, images: bool = True) -> RerunProgress:
    """The progress callback for ``simulation.run(progress=...)`` that logs every frame to Rerun.

    ``path_or_none``: a ``.rrd`` file to save, or None to spawn / connect to a
    viewer. The recording is finished after the run's last frame (or by
    ``.close()``). ``images=False`` leaves out D, E and the labels (most of
    the cost and of the file).
    """
    return RerunProgress(simulation, path_or_none, images)
