"""SimulatedRig: the simulated sensor as a source of depth frames.

Scene (:class:`~mabdi.sources.scene.SourceScene`, objects switched on and
off by their schedules) + off-screen depth sensor
(:class:`~mabdi.render.depth_image.FilterDepthImage`, with its noise model)
+ path (the helix of the run config's ``[path]``). A LiDAR (``[sensor] kind =
"lidar"``) renders range images (:mod:`mabdi.render.range_rendering`), its
x axis along the path's view direction and z up
(:func:`mabdi.simulate.path.path_from_config` with ``axes="lidar"``); its frames carry no colour. Frame i is the scene as it
stands at frame i, seen from pose i, with noise drawn from the stream of
(seed, i): reading a frame twice, or out of order, gives the same image.

Poses: the sensor renders frame i from the *true* pose i (the path), and
the frame carries the *given* pose i, the true one with the run config's
``[sensor.pose_noise]`` (:class:`~mabdi.pose_noise.PoseNoise`, drawn from the
run seed), as a robot's odometry or SLAM would give it. ``poses`` are the
given poses, ``true_poses`` the true ones; without pose noise they are equal.

A LiDAR's sweep (``[sensor.lidar] sweep``, :class:`~mabdi.simulate.lidar_sweep.SweepSettings`): ``"instant"``
(the default) renders each range image from the frame's pose, every return at its pixel's centre;
``"deskewed"`` fires each column from its own pose along the path during the sweep that ends at frame i,
deskews the returns into frame i's pose and bins them into the range image
(:mod:`mabdi.simulate.lidar_sweep`). A tilted mount (``mount_tilt``, ``mount_roll``) turns the sensor on
the path's poses: the frames' poses are the path's times the mount.

Timestamps: the simulated sensor runs at :data:`FRAME_RATE` frames per
second (frame i at i / 30 s), like the Kinect it imitates, unless the path
gives times (``timestamps``: a waypoint path's rate, a trajectory's file;
:func:`mabdi.simulate.path.path_timestamps`).

Colour: when the scene has coloured objects (``colour`` in the config), or
with ``colour=True``, every frame also carries a colour image registered to
its depth: the same render draws each object flat in its colour (no
lighting, no noise), read back from the render window's colour buffer; the
background (no object) is black.
"""

from __future__ import annotations

import numpy as np
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkUnsignedCharArray

from mabdi.camera import Intrinsics
from mabdi.config import RunConfig
from mabdi.depth import DepthFrame, depth_array
from mabdi.render.depth_image import FilterDepthImage
from mabdi.sensor_noise import SensorNoise
from mabdi.pose_noise import PoseNoise
from mabdi.simulate.lidar_sweep import SceneRayCaster, Sweep, SweepSettings, simulate_sweep, sweep_noise_rng
from mabdi.simulate.path import path_from_config, path_timestamps
from mabdi.sources.range_images import range_image_and_returns
from mabdi.sources.frames import FrameSource
from mabdi.sources.scene import OBJECT_COLOUR_ARRAY, SourceScene
from mabdi.spherical import SphericalGeometry

#: Frames per second of the simulated sensor (sets the timestamps).
FRAME_RATE = 30.0


class SimulatedRig(FrameSource):
    """A scene seen by the simulated sensor along a path of poses (a :class:`FrameSource`)."""

    def __init__(
        self,
        scene: SourceScene,
        poses: np.ndarray,
        intrinsics: Intrinsics | SphericalGeometry | None = None,
        noise: SensorNoise | str = "none",
        seed: int = 0,
        backend: str = "egl",
        description: str = "simulated sensor",
        pose_noise: PoseNoise | None = None,
        colour: bool | None = None,
        timestamps=None,
        sweep: SweepSettings | None = None,
    ) -> None:
        self.scene = scene
        self._true_poses = np.asarray(poses, dtype=np.float64)
        if self._true_poses.ndim != 3 or self._true_poses.shape[1:] != (4, 4) or len(self._true_poses) == 0:
            raise ValueError(f"SimulatedRig: poses must be (N, 4, 4) with N >= 1, got shape {self._true_poses.shape}")
        #: A LiDAR's sweep and mount (None: the ideal instant range image, no mount).
        self.sweep = sweep if sweep is not None and (sweep.deskewed or sweep.mounted) else None
        if self.sweep is not None:
            if not isinstance(intrinsics, SphericalGeometry):
                raise ValueError("SimulatedRig: a sweep and a mount are a LiDAR's (intrinsics must be a SphericalGeometry)")
            if self.sweep.mounted:  # the path carries the vehicle; the sensor sits on it turned by the mount
                self._true_poses = self._true_poses @ self.sweep.base_from_sensor()
            # a deskewed sweep's range image has pixels no ray was cast along (rows the motion moved its returns
            # out of, at the image's edges): there, as in a real scan, a pixel without a return is not free space
            self.loses_returns = bool(self.sweep.deskewed)
        #: The noise of the given poses (the frames' poses); the sensor renders from the true ones.
        self.pose_noise = pose_noise if pose_noise is not None else PoseNoise()
        self._poses = self.pose_noise.given_poses(self._true_poses, seed)
        count = len(self._true_poses)
        self._timestamps = np.arange(count) / FRAME_RATE if timestamps is None else np.asarray(timestamps, dtype=np.float64)
        if self._timestamps.shape != (count,):
            raise ValueError(f"SimulatedRig: {count} poses but timestamps of shape {self._timestamps.shape}")
        self.sensor = FilterDepthImage(intrinsics=intrinsics, noise=noise, seed=seed, backend=backend)
        self.sensor.SetInputConnection(scene.GetOutputPort())
        self.description = description
        #: Whether frames carry a colour image (None: when the scene has coloured objects; never for a LiDAR).
        lidar = self.sensor.intrinsics.range_image
        if lidar and colour:
            raise ValueError("SimulatedRig: a LiDAR's range images carry no colour image")
        self.colour = False if lidar else scene.coloured if colour is None else bool(colour)
        self._rgb = vtkUnsignedCharArray()
        self._caster: tuple[tuple[int, ...], SceneRayCaster] | None = None
        if self.colour:  # the depth render draws each triangle in its object's colour: one render gives both
            self.sensor.renderer.identity_array = OBJECT_COLOUR_ARRAY

    @classmethod
    def from_config(cls, config: RunConfig) -> SimulatedRig:
        """The rig of a run config: its scene, ``[sensor]`` (intrinsics, noise, backend, pose noise), ``[path]`` and seed."""
        base_dir = config.source.parent if config.source is not None else None
        frames = config.run.frames
        scene = SourceScene(config.scene, frames=frames, base_dir=base_dir)
        sensor = config.sensor
        geometry = sensor.geometry()
        # a LiDAR's poses in its own axes (x forward, z up): the path says where the sensor looks
        axes = "lidar" if geometry.range_image else "camera"
        return cls(
            scene,
            path_from_config(frames, config.path, base_dir, axes=axes),
            timestamps=path_timestamps(frames, config.path, base_dir),
            intrinsics=geometry,
            noise=sensor.sensor_noise(),
            seed=config.run.seed,
            backend=sensor.backend,
            description=f"simulated {config.run.name or 'scene'}",
            pose_noise=sensor.pose_noise,
            sweep=sensor.sweep_settings() if geometry.range_image else None,
        )

    @property
    def intrinsics(self) -> Intrinsics | SphericalGeometry:
        """The sensor's geometry: a camera's intrinsics or a LiDAR's range image (:mod:`mabdi.spherical`)."""
        return self.sensor.intrinsics

    @property
    def has_colour(self) -> bool:
        return self.colour

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) the given poses: those the frames carry (the true ones with the pose noise)."""
        return self._poses.copy()

    @property
    def true_poses(self) -> np.ndarray:
        """(N, 4, 4) the poses the sensor renders from."""
        return self._true_poses.copy()

    @property
    def noise(self) -> SensorNoise:
        """The noise model the sensor draws from."""
        return self.sensor.noise

    @property
    def pose_accuracy(self) -> PoseNoise:
        """The simulator knows how far its given poses are off: its pose noise (all zero: exact)."""
        return self.pose_noise

    @property
    def timestamps(self) -> np.ndarray:
        return self._timestamps.copy()

    def __len__(self) -> int:
        return len(self._poses)

    def read_frame(self, index: int) -> DepthFrame:
        """Render frame ``index``: the scene at that frame, from true pose ``index``, with its noise; the
        frame carries the given pose ``index``. A deskewed sweep's frame: :meth:`read_sweep`'s points binned into
        the range image (:func:`mabdi.sources.range_images.range_image`)."""
        if self.sweep is not None and self.sweep.deskewed:
            depth, return_points = range_image_and_returns(self.read_sweep(index).points, self.sensor.intrinsics)
            return DepthFrame(depth, self.sensor.intrinsics, self._poses[index], index, float(self._timestamps[index]), None, return_points)
        self.scene.set_frame(index)
        self.sensor.pose = self._true_poses[index]
        self.sensor.frame = index
        self.sensor.Update()
        # Each render hands out a new array, so the frame may keep it.
        depth = depth_array(self.sensor.GetOutput(), raw=True)
        colour = self._read_colour() if self.colour else None
        return DepthFrame(depth, self.sensor.intrinsics, self._poses[index], index, float(self._timestamps[index]), colour)

    def sweep_time(self) -> float:
        """Seconds one sweep takes: the sweep's ``duration``, else the time between frames (their median step;
        1 / :data:`FRAME_RATE` for a single frame)."""
        if self.sweep is not None and self.sweep.duration > 0:
            return self.sweep.duration
        steps = np.diff(self._timestamps)
        steps = steps[np.isfinite(steps) & (steps > 0)]
        return float(np.median(steps)) if len(steps) else 1.0 / FRAME_RATE

    def read_sweep(self, index: int) -> Sweep:
        """The deskewed sweep that ends at frame ``index`` (:func:`mabdi.simulate.lidar_sweep.simulate_sweep`):
        the scene as it stands at that frame, each column from its true pose along the path, the frame's noise,
        the points in the sensor frame of true pose ``index``."""
        if self.sweep is None or not self.sweep.deskewed:
            raise ValueError('SimulatedRig.read_sweep: the sensor is not a deskewed sweep ([sensor.lidar] sweep = "deskewed")')
        if not 0 <= index < len(self):
            raise IndexError(f"frame {index} is outside 0 .. {len(self) - 1}")
        noise = self.sensor.noise
        return simulate_sweep(
            self._scene_caster(index), self.sensor.intrinsics, float(self._timestamps[index]), self.sweep_time(),
            self._timestamps, self._true_poses, self._true_poses[index], noise, sweep_noise_rng(noise, self.sensor.seed, index),
        )

    def _scene_caster(self, index: int) -> SceneRayCaster:
        """The ray caster of the scene as it stands at frame ``index`` (kept while the same objects exist)."""
        active = self.scene.active_objects(index)
        if self._caster is None or self._caster[0] != active:
            objects = [self.scene.objects[i] for i in active]
            offsets = np.cumsum([0] + [len(o.points) for o in objects[:-1]])
            points = np.concatenate([o.points for o in objects]) if objects else np.zeros((0, 3))
            triangles = (np.concatenate([o.triangles + k for o, k in zip(objects, offsets, strict=True)])
                         if objects else np.zeros((0, 3), dtype=np.int64))  # fmt: skip
            self._caster = (active, SceneRayCaster(points, triangles))
        return self._caster[1]

    def _read_colour(self) -> np.ndarray:
        """(H, W, 3) uint8 colour buffer of the last render (each object flat in its colour), top row first."""
        width, height = self.sensor.intrinsics.width, self.sensor.intrinsics.height
        self.sensor.renderer.window.GetPixelData(0, 0, width - 1, height - 1, 0, self._rgb, 0)
        return vtk_to_numpy(self._rgb).reshape(height, width, 3)[::-1].copy()

    def noise_free(self, index: int) -> DepthFrame:
        """Frame ``index`` without noise (for alignment checks), the rig's noise model left as it was."""
        noise = self.sensor.noise
        self.sensor.noise = "none"
        try:
            return self.read(index)
        finally:
            self.sensor.noise = noise

    def render_backend(self) -> dict:
        """The render backend that drew the frames (:meth:`DepthRenderer.describe`)."""
        renderer = self.sensor.range_renderer or self.sensor.renderer
        return renderer.describe()

    def close(self) -> None:
        self.sensor.renderer.close()
        if self.sensor.range_renderer is not None:
            self.sensor.range_renderer.close()
