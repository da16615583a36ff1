"""FilterDepthImage: render a mesh from a sensor pose into a metric depth image.

vtkPolyData (or a composite dataset of polydata, drawn block by block) in,
depth image (see :mod:`mabdi.depth`) out. The filter renders off-screen in
one render window that it keeps across frames, multisampling off (with it,
the depth read back blends several samples instead of the pixel centre's), reads
the z-buffer, flips it to top-row-first and converts it to metres. Pixels
with no surface within [near, far] are NaN.

Noise models (:class:`SensorNoise`):

* ``none``
* ``zbuffer`` (seed 001): D_noisy = d + d N(0, sigma) on the normalised
  z-buffer value d (sigma = 0.001), then converted to metres; about 1, 6 and
  15 mm standard deviation at 1, 2 and 3 m for near = 0.5 m, far = 4 m. A
  value pushed to d >= 1 is beyond the far plane: NaN.
* ``kinect``: axial sigma(z) = 1.425e-3 z^2 m (Khoshelham & Elberink 2012),
  added in metres.

Noise is reproducible: frame i of a run with seed s always draws from the
random stream ``numpy.random.default_rng([s, i])``, independent of every
other frame and of the order frames are rendered in.

Backends: ``egl`` (default; Mesa llvmpipe on a CPU machine, the GPU driver
where there is one; no X server) or ``osmesa`` (needs Debian's libosmesa6).
"""

from __future__ import annotations

import ctypes.util
from dataclasses import dataclass

import numpy as np
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkFloatArray, vtkUnsignedCharArray
from vtkmodules.vtkCommonDataModel import (
    vtkCompositeDataSet,
    vtkDataObject,
    vtkDataObjectTreeIterator,
    vtkImageData,
    vtkPolyData,
)
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline
from vtkmodules.vtkRenderingCore import vtkActor, vtkMapper, vtkPolyDataMapper, vtkRenderer

import vtkmodules.vtkRenderingOpenGL2  # noqa: F401  (registers the OpenGL implementations)
from mabdi.algorithm import MabdiAlgorithm
from mabdi.camera import Intrinsics, check_pose, configure_vtk_camera, zbuffer_depth_derivative, zbuffer_to_depth
from mabdi.depth import fill_depth_image
from mabdi.errors import ConfigError



#: Depth noise models (see the module docs).
NOISE_MODELS = ("none", "zbuffer", "kinect")
#: Off-screen render backends; the first is the default.
BACKENDS = ("egl", "osmesa")


@dataclass(frozen=True)
class SensorNoise:
    """A depth noise model and its parameters (see the module docs)."""

    model: str = "none"
    zbuffer_sigma: float = 0.001
    kinect_coefficient: float = 1.425e-3

    def __post_init__(self) -> None:
        if self.model not in NOISE_MODELS:
            raise ConfigError(f"unknown noise model {self.model!r} (known: {', '.join(NOISE_MODELS)})")
        if not (self.zbuffer_sigma >= 0 and self.kinect_coefficient >= 0):
            raise ConfigError("noise parameters zbuffer_sigma and kinect_coefficient must be >= 0")

    @classmethod
    def of(cls, value: SensorNoise | str) -> SensorNoise:
        """``value`` itself if it is a SensorNoise, else the model of that name with default parameters."""
        return value if isinstance(value, SensorNoise) else cls(value)

    @classmethod
    def from_config(cls, sensor) -> SensorNoise:
        """The noise of a ``[sensor]`` config section (:class:`mabdi.config.SensorConfig`)."""
        return cls(sensor.noise, sensor.zbuffer_sigma, sensor.kinect_coefficient)

    def sigma(self, depth, near: float, far: float) -> np.ndarray:
        """Expected standard deviation (m) of a measurement at metric depth ``depth``.

        ``zbuffer``: sigma d |dz/dd| (first order); ``kinect``: c z^2; ``none``: 0.
        Computed in float32 for float32 input, float64 otherwise.
        """
        z = np.asarray(depth)
        if z.dtype != np.float32:
            z = z.astype(np.float64)
        if self.model == "zbuffer":
            d = far * (z - near) / (z * (far - near))
            return self.zbuffer_sigma * d * zbuffer_depth_derivative(z, near, far)
        if self.model == "kinect":
            return self.kinect_coefficient * z * z
        return np.zeros_like(z)

    def depth_from_zbuffer(self, zbuffer: np.ndarray, near: float, far: float, rng: np.random.Generator | None) -> np.ndarray:
        """Metric depth (float32, NaN = no return) from a z-buffer, with this model's noise drawn from ``rng``.

        Works in float32: the z-buffer holds 24 bits, and float32 metres
        resolve 0.5 um at 4 m.
        """
        d = np.asarray(zbuffer, dtype=np.float32)
        if self.model == "zbuffer" and rng is not None:
            valid = d < 1.0
            dv = d[valid]
            d = d.copy()
            d[valid] = dv + dv * (np.float32(self.zbuffer_sigma) * rng.standard_normal(dv.size, dtype=np.float32))
        depth = zbuffer_to_depth(d, near, far)
        if self.model == "kinect" and rng is not None:
            valid = np.isfinite(depth)
            zv = depth[valid]
            depth[valid] = zv + np.float32(self.kinect_coefficient) * zv * zv * rng.standard_normal(zv.size, dtype=np.float32)
        return depth


def noise_rng(seed: int, frame: int) -> np.random.Generator:
    """The random stream of frame ``frame`` in a run with ``seed`` (independent per frame)."""
    return np.random.default_rng([int(seed), int(frame)])


def _check_backend_library(backend: str) -> None:
    library = {"egl": "EGL", "osmesa": "OSMesa"}[backend]
    if ctypes.util.find_library(library) is None:
        package = {"egl": "libegl1 libegl-mesa0 libgl1-mesa-dri", "osmesa": "libosmesa6"}[backend]
        raise RuntimeError(
            f"render backend '{backend}' needs the system library lib{library}, which was not found; "
            f"on Debian/Ubuntu: apt-get install {package}"
        )


def polydata_leaves(data) -> list[vtkPolyData]:
    """The vtkPolyData of ``data``: itself, or the non-empty leaves of a composite dataset."""
    if isinstance(data, vtkPolyData):
        return [data]
    if not isinstance(data, vtkCompositeDataSet):
        raise TypeError(
            "expected a vtkPolyData or a composite dataset of polydata, "
            f"got {data.GetClassName() if data is not None else None}"
        )
    leaves = []
    iterator = vtkDataObjectTreeIterator()
    iterator.SetDataSet(data)
    iterator.SkipEmptyNodesOn()
    iterator.VisitOnlyLeavesOn()
    iterator.InitTraversal()
    while not iterator.IsDoneWithTraversal():
        leaf = iterator.GetCurrentDataObject()
        if not isinstance(leaf, vtkPolyData):
            raise TypeError(f"composite dataset has a {leaf.GetClassName()} block; only vtkPolyData can be rendered")
        leaves.append(leaf)
        iterator.GoToNextItem()
    return leaves


class DepthRenderer:
    """One reusable off-screen render window that renders z-buffers of a mesh.

    ``render_zbuffer(data, intrinsics, pose)`` returns the (H, W) float32
    z-buffer, top row first, values in [0, 1] (1 = background). ``data`` is a
    vtkPolyData or a composite dataset of them (the map's blocks). Each
    polydata gets its own mapper and actor, kept for as long as the polydata
    is part of the input: a mapper uploads its geometry when it first draws it
    or when it changes, so a map that grows by new blocks uploads only those.
    """

    def __init__(self, backend: str = "egl", identity_array: str | None = None) -> None:
        if backend not in BACKENDS:
            raise ConfigError(f"unknown render backend {backend!r} (known: {', '.join(BACKENDS)})")
        self.backend = backend
        #: With a name: draw each cell in the colour of its uint8 RGB cell array of that name (flat, no
        #: lighting), so the colour buffer says which face each pixel shows (:meth:`render_identity`).
        self.identity_array = identity_array
        self._window = None
        self._size: tuple[int, int] | None = None
        self._renderer = vtkRenderer()
        self._renderer.SetBackground(0.0, 0.0, 0.0)  # identity 0: no face
        self._actors: dict[int, tuple[vtkPolyData, vtkActor]] = {}
        self._zbuffer = vtkFloatArray()
        self._rgb = vtkUnsignedCharArray()

    def _sync_actors(self, data) -> None:
        """One actor per polydata of ``data``; actors of polydata no longer there are dropped."""
        current: dict[int, tuple[vtkPolyData, vtkActor]] = {}
        for leaf in polydata_leaves(data):
            entry = self._actors.get(id(leaf))
            if entry is None:
                mapper = vtkPolyDataMapper()
                mapper.SetInputData(leaf)
                if self.identity_array is not None and leaf.GetCellData().GetArray(self.identity_array) is not None:
                    mapper.ScalarVisibilityOn()
                    mapper.SetScalarModeToUseCellFieldData()
                    mapper.SelectColorArray(self.identity_array)
                    mapper.SetColorModeToDirectScalars()
                else:
                    mapper.ScalarVisibilityOff()
                actor = vtkActor()
                actor.SetMapper(mapper)
                actor.GetProperty().LightingOff()
                if self.identity_array is not None:
                    actor.GetProperty().SetColor(0.0, 0.0, 0.0)  # a block without identities reads as "no face"
                self._renderer.AddActor(actor)
                entry = (leaf, actor)
            current[id(leaf)] = entry
        for key, (_, actor) in self._actors.items():
            if key not in current:
                self._renderer.RemoveActor(actor)
        self._actors = current

    def _make_window(self, width: int, height: int):
        _check_backend_library(self.backend)
        if self.backend == "egl":
            from vtkmodules.vtkRenderingOpenGL2 import vtkEGLRenderWindow as window_class
        else:
            from vtkmodules.vtkRenderingOpenGL2 import vtkOSOpenGLRenderWindow as window_class
        window = window_class()
        window.SetOffScreenRendering(1)
        window.SetShowWindow(False)
        window.SetMultiSamples(0)
        window.SetSize(width, height)
        window.AddRenderer(self._renderer)
        return window

    @property
    def window(self):
        """The render window (None before the first render)."""
        return self._window

    def render_zbuffer(self, data, intrinsics: Intrinsics, world_from_camera) -> np.ndarray:
        size = (intrinsics.width, intrinsics.height)
        if self._window is None or self._size != size:
            if self._window is not None:
                self._window.RemoveRenderer(self._renderer)
                self._window.Finalize()
            self._window = self._make_window(*size)
            self._size = size
        self._sync_actors(data)
        configure_vtk_camera(self._renderer.GetActiveCamera(), intrinsics, world_from_camera)
        # Polygon offsets would bias depth; the setting is global in VTK, so restore it after.
        coincident = vtkMapper.GetResolveCoincidentTopology()
        vtkMapper.SetResolveCoincidentTopologyToOff()
        try:
            self._window.Render()
        finally:
            vtkMapper.SetResolveCoincidentTopology(coincident)
        width, height = size
        self._window.GetZbufferData(0, 0, width - 1, height - 1, self._zbuffer)
        return vtk_to_numpy(self._zbuffer).reshape(height, width)[::-1]

    def render_identity(self) -> np.ndarray:
        """(H, W) int64 identity of the last render (top row first): the 24-bit RGB of the face seen, 0 = none.

        Call right after :meth:`render_zbuffer` (same frame); needs ``identity_array``.
        """
        width, height = self._size
        self._window.GetPixelData(0, 0, width - 1, height - 1, 0, self._rgb, 0)
        rgb = vtk_to_numpy(self._rgb).reshape(height, width, 3)[::-1].astype(np.int64)
        return rgb[..., 0] | (rgb[..., 1] << 8) | (rgb[..., 2] << 16)

    def describe(self) -> dict:
        """The backend that drew the frames: name, window class and OpenGL renderer string."""
        if self._window is None:
            return {"backend": self.backend}
        renderer = "?"
        for line in self._window.ReportCapabilities().splitlines():
            if "renderer string" in line:
                renderer = line.split(":", 1)[1].strip()
                break
        return {"backend": self.backend, "window": self._window.GetClassName(), "gl_renderer": renderer}

    def close(self) -> None:
        """Release the render window (a later render makes a new one)."""
        if self._window is not None:
            self._window.RemoveRenderer(self._renderer)
            self._window.Finalize()
            self._window = None
            self._size = None


class FilterDepthImage(MabdiAlgorithm):
    """Render the input mesh from ``pose`` into a metric depth image (see the module docs).

    Properties: ``pose`` (4x4 world_from_camera, required), ``intrinsics``,
    ``noise`` (:class:`SensorNoise` or a model name), ``seed`` and ``frame``
    (select the noise stream; ``frame`` is also stored in the output).
    """

    def __init__(
        self,
        intrinsics: Intrinsics | None = None,
        noise: SensorNoise | str = "none",
        seed: int = 0,
        backend: str = "egl",
    ) -> None:
        super().__init__(nInputPorts=1, inputType="vtkDataObject", nOutputPorts=1, outputType="vtkImageData")
        self._intrinsics = intrinsics if intrinsics is not None else Intrinsics()
        self._noise = SensorNoise.of(noise)
        self._seed = int(seed)
        self._frame = 0
        self._pose: np.ndarray | None = None
        self.renderer = DepthRenderer(backend)

    # -- properties --------------------------------------------------------
    @property
    def pose(self) -> np.ndarray | None:
        return None if self._pose is None else self._pose.copy()

    @pose.setter
    def pose(self, value) -> None:
        self._set("_pose", check_pose(value, "FilterDepthImage.pose"))

    @property
    def intrinsics(self) -> Intrinsics:
        return self._intrinsics

    @intrinsics.setter
    def intrinsics(self, value: Intrinsics) -> None:
        if not isinstance(value, Intrinsics):
            raise TypeError(f"intrinsics must be mabdi.camera.Intrinsics, got {type(value).__name__}")
        self._set("_intrinsics", value)

    @property
    def noise(self) -> SensorNoise:
        return self._noise

    @noise.setter
    def noise(self, value: SensorNoise | str) -> None:
        self._set("_noise", SensorNoise.of(value))

    @property
    def seed(self) -> int:
        return self._seed

    @seed.setter
    def seed(self, value: int) -> None:
        self._set("_seed", int(value))

    @property
    def frame(self) -> int:
        return self._frame

    @frame.setter
    def frame(self, value: int) -> None:
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
            raise ValueError(f"FilterDepthImage.frame must be an integer >= 0, got {value!r}")
        self._set("_frame", int(value))

    # -- pipeline ----------------------------------------------------------
    def RequestInformation(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        info = outInfo.GetInformationObject(0)
        width, height = self._intrinsics.width, self._intrinsics.height
        info.Set(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT(), (0, width - 1, 0, height - 1, 0, 0), 6)
        info.Set(vtkImageData.SPACING(), (1.0, 1.0, 1.0), 3)
        info.Set(vtkImageData.ORIGIN(), (0.0, 0.0, 0.0), 3)
        return 1

    def RequestData(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        data = vtkDataObject.GetData(inInfo[0], 0)
        if not isinstance(data, (vtkPolyData, vtkCompositeDataSet)):
            raise TypeError(
                "FilterDepthImage: input must be a vtkPolyData or a composite dataset of polydata, "
                f"got {data.GetClassName() if data is not None else None}"
            )
        if self._pose is None:
            raise ValueError("FilterDepthImage: pose is not set (assign a 4x4 world_from_camera to .pose)")
        intr = self._intrinsics
        zbuffer = self.renderer.render_zbuffer(data, intr, self._pose)
        rng = None if self._noise.model == "none" else noise_rng(self._seed, self._frame)
        depth = self._noise.depth_from_zbuffer(zbuffer, intr.near, intr.far, rng)
        fill_depth_image(vtkImageData.GetData(outInfo), depth, intr, self._pose, self._frame)
        return 1
