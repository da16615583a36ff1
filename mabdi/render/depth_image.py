"""FilterDepthImage: render a mesh from a sensor pose into a metric depth image.

vtkPolyData (or a composite dataset of polydata, drawn block by block) in,
depth image (see :mod:`mabdi.depth`) out. The filter renders off-screen in
one render window that it keeps across frames, multisampling off (with it,
the depth read back blends several samples instead of the pixel centre's), reads
the z-buffer, flips it to top-row-first and converts it to metres. Pixels
with no surface within [near, far] are NaN.

Noise models: :mod:`mabdi.sensor_noise` (:class:`SensorNoise`); the filter draws its model's noise
into each image and writes the model into the image's field data.

Backends: ``egl`` (default; Mesa llvmpipe on a CPU machine, the GPU driver
where there is one; no X server) or ``osmesa`` (needs Debian's libosmesa6).
"""

from __future__ import annotations

import ctypes.util
from dataclasses import dataclass

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkFloatArray, vtkUnsignedCharArray
from vtkmodules.vtkCommonDataModel import vtkCompositeDataSet, vtkDataObject, vtkImageData, vtkPolyData
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline
from vtkmodules.vtkRenderingCore import vtkActor, vtkMapper, vtkPolyDataMapper, vtkRenderer

import vtkmodules.vtkRenderingOpenGL2  # noqa: F401  (registers the OpenGL implementations)
from mabdi.algorithm import MabdiAlgorithm
from mabdi.camera import (
    Intrinsics,
    check_pose,
    configure_vtk_camera,
    frustum_planes,
    zbuffer_to_depth,
)
from mabdi.depth import fill_depth_image
from mabdi.errors import ConfigError
from mabdi.face_identity import FaceCodes, FaceIdTable, block_address, face_rgb
from mabdi.render.range_rendering import TRIANGLE_RGB_ARRAY, RangeRenderer
from mabdi.polydata import FACE_RGB_ARRAY, named_leaves
from mabdi.sensor_noise import SensorNoise, noise_rng
from mabdi.spherical import SphericalGeometry

#: Off-screen render backends; the first is the default.
BACKENDS = ("egl", "osmesa")


def _check_backend_library(backend: str) -> None:
    from mabdi.errors import RenderBackendError  # a user's error: one line, no traceback
    library = {"egl": "EGL", "osmesa": "OSMesa"}[backend]
    if ctypes.util.find_library(library) is None:
        package = {"egl": "libegl1 libegl-mesa0 libgl1-mesa-dri", "osmesa": "libosmesa6"}[backend]
        raise RenderBackendError(
            f"render backend '{backend}' needs the system library lib{library}, which was not found; "
            f"on Debian/Ubuntu: apt-get install {package}"
        )


@dataclass
class _Drawn:
    """A leaf being drawn: the actor, the number of faces its codes were given for (face identity), and
    for a leaf of polygons the copy that carries its codes as colours."""

    leaf: vtkPolyData
    actor: vtkActor
    faces: int = -1
    copy: vtkPolyData | None = None
    last_render: int = 0


#: The fragment shader of a block of triangles drawn with face identity: triangle i of the draw is cell i of
#: the block, so its code is the block's first code plus the primitive's index (no colour array is made,
#: uploaded or kept: the codes cost nothing per face).
FACE_CODE_SHADER = """//VTK::Light::Impl
  int faceCode = faceBase + gl_PrimitiveID;
  gl_FragData[0] = vec4(float(faceCode & 255) / 255.0, float((faceCode >> 8) & 255) / 255.0,
                        float((faceCode >> 16) & 255) / 255.0, 1.0);
"""


#: Renders a block may go undrawn before its actor, upload and face codes are dropped.
KEEP_HIDDEN_RENDERS = 8


def _triangles_only(polydata: vtkPolyData) -> bool:
    """Whether every cell of ``polydata`` is a triangle among its polygons (no vertices, lines or strips), so
    that the mapper draws cell i as triangle i."""
    polys = polydata.GetPolys()
    return polydata.GetNumberOfCells() == polydata.GetNumberOfPolys() and (polys.GetNumberOfCells() == 0 or polys.IsHomogeneous() == 3)


class DepthRenderer:
    """One reusable off-screen render window that renders z-buffers of a mesh.

    ``render_zbuffer(data, intrinsics, pose)`` returns the (H, W) float32
    z-buffer, top row first, values in [0, 1] (1 = background). ``data`` is a
    vtkPolyData or a composite dataset of them (the map's chunks of blocks).
    Only the blocks in view are drawn: a block whose metadata has a
    BOUNDING_BOX outside the frustum is skipped with its children. Each drawn
    polydata gets its own mapper and actor, kept while it stays in view: a
    mapper uploads its geometry when it first draws it or when it changes, so
    a map that grows by new blocks uploads only those; a block that leaves the
    view is hidden, and released after :data:`KEEP_HIDDEN_RENDERS` renders.

    Colour: ``identity_array`` names a uint8 RGB cell array each leaf draws in
    (flat, no lighting; the simulator's object colours), or ``face_identity``
    draws each face in the colour of a 24-bit code the renderer assigns
    (:mod:`mabdi.face_identity`): :meth:`render_identity` reads the codes back
    and :attr:`identities` says which block each range of codes belongs to. A
    block of triangles (the map's) draws its codes in the fragment shader from
    the index of each triangle (:data:`FACE_CODE_SHADER`); a block with other
    polygons, which the mapper splits into triangles, carries them as a colour
    array on a shallow copy.
    """

    def __init__(self, backend: str = "egl", identity_array: str | None = None, face_identity: bool = False) -> None:
        if backend not in BACKENDS:
            raise ConfigError(f"unknown render backend {backend!r} (known: {', '.join(BACKENDS)})")
        self.backend = backend
        self.identity_array = FACE_RGB_ARRAY if face_identity else identity_array
        self.face_identity = face_identity
        self._window = None
        self._size: tuple[int, int] | None = None
        self._renderer = vtkRenderer()
        self._renderer.SetBackground(0.0, 0.0, 0.0)  # identity 0: no face
        self._actors: dict[int, _Drawn] = {}
        self._codes = FaceCodes()
        self._names: dict[int, str] = {}
        self._addresses: dict[int, int] = {}  # block_address of each drawn polydata
        self._renders = 0
        self._drawn: set[int] = set()
        self._zbuffer = vtkFloatArray()
        #: what the window's buffers hold: ((intrinsics, (id, MTime) of each leaf drawn), the pose), None: unknown
        self._last_scene = None
        #: a render of the same leaves from a pose within this many pixels of the last one's is served from the
        #: last one's buffers (:func:`pose_shift_px`); 0: only from the very same pose
        self.reuse_within_px = 0.0
        self._rgba = vtkUnsignedCharArray()

    def _sync_actors(self, leaves: list[tuple[str, vtkPolyData]]) -> None:
        """One actor per polydata of ``leaves``, shown; actors of polydata not drawn are hidden, and dropped
        (with their codes and upload) after :data:`KEEP_HIDDEN_RENDERS` renders without them, so a block at
        the edge of the view (seen by one of two nearby poses) is not uploaded again and again.

        Face codes are given out block by block as blocks change, so over a long run the free codes split into
        gaps; when a block finds none large enough, every actor is dropped and the blocks in view take their
        codes afresh from 1 (one upload of the view), and only if those alone hold more faces than there are
        codes is it an error."""
        try:
            self._sync_actors_once(leaves)
        except MemoryError:
            if not self.face_identity:
                raise
            for key in list(self._actors):
                self._drop(key)
            self._last_scene = None  # the window's buffers hold the old codes
            self._sync_actors_once(leaves)

    def _sync_actors_once(self, leaves: list[tuple[str, vtkPolyData]]) -> None:
        self._renders += 1
        drawn: set[int] = set()
        for name, leaf in leaves:
            key = id(leaf)
            entry = self._actors.get(key)
            if entry is not None and self.face_identity and entry.faces != leaf.GetNumberOfCells():
                self._drop(key)
                entry = None
            if entry is None:
                entry = self._actors[key] = self._new_actor(leaf)
            entry.actor.VisibilityOn()
            entry.last_render = self._renders
            self._names[key] = name
            self._addresses[key] = block_address(leaf)
            drawn.add(key)
        for key, entry in list(self._actors.items()):
            if key in drawn:
                continue
            if self._renders - entry.last_render > KEEP_HIDDEN_RENDERS:
                self._drop(key)
            else:
                entry.actor.VisibilityOff()
        self._drawn = drawn

    def _drop(self, key: int) -> None:
        entry = self._actors.pop(key)
        self._renderer.RemoveActor(entry.actor)
        self._codes.release(key)
        self._names.pop(key, None)
        self._addresses.pop(key, None)

    def _new_actor(self, leaf: vtkPolyData) -> _Drawn:
        drawn = leaf
        copy = None
        count = leaf.GetNumberOfCells()
        base = self._codes.allocate(id(leaf), count) if self.face_identity else 0
        by_primitive = self.face_identity and _triangles_only(leaf)
        if self.face_identity and not by_primitive:
            # the codes live on a shallow copy (points and cells shared, so moved points still show), never
            # on the map's own block
            copy = vtkPolyData()
            copy.ShallowCopy(leaf)
            rgb = numpy_to_vtk(face_rgb(base, count), deep=True)
            rgb.SetName(FACE_RGB_ARRAY)
            copy.GetCellData().AddArray(rgb)
            drawn = copy
        mapper = vtkPolyDataMapper()
        mapper.SetInputData(drawn)
        if by_primitive:
            mapper.ScalarVisibilityOff()
        elif self.identity_array is not None and drawn.GetCellData().GetArray(self.identity_array) is not None:
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
        if by_primitive:
            shader = actor.GetShaderProperty()
            shader.AddFragmentShaderReplacement("//VTK::Light::Impl", True, FACE_CODE_SHADER, False)
            shader.GetFragmentCustomUniforms().SetUniformi("faceBase", base)
        self._renderer.AddActor(actor)
        return _Drawn(leaf, actor, count, copy)

    @property
    def identities(self) -> FaceIdTable:
        """What the codes of the last :meth:`render_identity` mean (``face_identity`` renderers): block names,
        first codes and face counts of the blocks drawn."""
        names, bases, counts, addresses = [], [], [], []
        for key, (base, count) in self._codes.ranges.items():
            if key not in self._drawn:
                continue
            names.append(self._names[key])
            bases.append(base)
            counts.append(count)
            addresses.append(self._addresses[key])
        return FaceIdTable(names, np.array(bases, dtype=np.int64), np.array(counts, dtype=np.int64), np.array(addresses, dtype=np.int64))

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

    def draw(self, data, intrinsics: Intrinsics, world_from_camera) -> None:
        """Draw ``data`` from ``world_from_camera`` and read nothing back: for a caller that reads only the
        identities (:meth:`render_identity`), not the z-buffer (a LiDAR's sector renders, which cast their rays
        against the faces drawn). Always draws; a later :meth:`render_zbuffer` draws again."""
        self._prepare(data, intrinsics, world_from_camera)
        self._draw(intrinsics, world_from_camera)
        self._last_scene = None

    def _prepare(self, data, intrinsics: Intrinsics, world_from_camera):
        """The window at the intrinsics' size and the actors of the blocks of ``data`` in view from
        ``world_from_camera``; the scene's key (for :meth:`render_zbuffer`'s reuse)."""
        size = (intrinsics.width, intrinsics.height)
        if self._window is None or self._size != size:
            if self._window is not None:
                self._window.RemoveRenderer(self._renderer)
                self._window.Finalize()
            self._window = self._make_window(*size)
            self._size = size
        leaves = named_leaves(data, frustum_planes(intrinsics, world_from_camera))
        self._sync_actors(leaves)
        return (intrinsics, tuple((id(leaf), leaf.GetMTime()) for _, leaf in leaves))

    def _draw(self, intrinsics: Intrinsics, world_from_camera) -> None:
        configure_vtk_camera(self._renderer.GetActiveCamera(), intrinsics, world_from_camera)
        # Polygon offsets would bias depth; the setting is global in VTK, so restore it after.
        coincident = vtkMapper.GetResolveCoincidentTopology()
        vtkMapper.SetResolveCoincidentTopologyToOff()
        try:
            self._window.Render()
        finally:
            vtkMapper.SetResolveCoincidentTopology(coincident)

    def render_zbuffer(self, data, intrinsics: Intrinsics, world_from_camera) -> np.ndarray:
        """Draw ``data`` from ``world_from_camera`` and read its (H, W) z-buffer back (the class docs)."""
        scene = self._prepare(data, intrinsics, world_from_camera)
        # the same leaves, unchanged, from the same pose as the last render (E at a registered pose that is the
        # given one), or one within reuse_within_px of it: its buffers are still in the window, nothing is drawn again
        pose = np.asarray(world_from_camera, dtype=np.float64)
        width, height = intrinsics.width, intrinsics.height
        if self._last_scene is not None and scene == self._last_scene[0]:
            last = self._last_scene[1]
            if np.array_equal(last, pose) or (self.reuse_within_px > 0 and pose_shift_px(last, pose, intrinsics) <= self.reuse_within_px):
                return vtk_to_numpy(self._zbuffer).reshape(height, width)[::-1]
        self._last_scene = None
        self._draw(intrinsics, world_from_camera)
        self._window.GetZbufferData(0, 0, width - 1, height - 1, self._zbuffer)
        self._last_scene = (scene, pose.copy())
        return vtk_to_numpy(self._zbuffer).reshape(height, width)[::-1]

    def render_identity(self, out: np.ndarray | None = None) -> np.ndarray:
        """(H, W) int64 identity of the last render (top row first): the 24-bit RGB of the face seen, 0 = none;
        written into ``out`` instead ((H, W), uint32 or wider) when given, and ``out`` returned.

        Call right after :meth:`render_zbuffer` or :meth:`draw` (same frame); needs ``identity_array``.
        """
        width, height = self._size
        # RGBA read as one little-endian 32-bit word per pixel: red is the low byte, alpha (the high byte) masked off
        self._window.GetRGBACharPixelData(0, 0, width - 1, height - 1, 0, self._rgba, 0)
        words = vtk_to_numpy(self._rgba).reshape(-1).view("<u4").reshape(height, width)[::-1]
        if out is not None:
            return np.bitwise_and(words, np.uint32(0xFFFFFF), out=out)
        return (words & np.uint32(0xFFFFFF)).astype(np.int64)

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
            self._last_scene = None
            self._size = None


def pose_shift_px(first: np.ndarray, second: np.ndarray, intrinsics: Intrinsics) -> float:
    """At most how far (pixels) a point moves in the image between two camera poses (4x4 world_from_camera): the
    rotation's angle plus the translation seen at the near limit, times the larger focal length."""
    relative = np.linalg.inv(first) @ second
    cosine = np.clip((np.trace(relative[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    angle = float(np.arccos(cosine))
    return max(intrinsics.fx, intrinsics.fy) * (angle + float(np.linalg.norm(relative[:3, 3])) / max(intrinsics.near, 1e-3))


class FilterDepthImage(MabdiAlgorithm):
    """Render the input mesh from ``pose`` into a metric depth image (see the module docs).

    Properties: ``pose`` (4x4 world_from_camera, required), ``intrinsics``,
    ``noise`` (:class:`SensorNoise` or a model name), ``seed`` and ``frame``
    (select the noise stream; ``frame`` is also stored in the output).
    """

    def __init__(
        self,
        intrinsics: Intrinsics | SphericalGeometry | None = None,
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
        #: A LiDAR's range images (:mod:`mabdi.render.range_rendering`), made at the first one.
        self.range_renderer: RangeRenderer | None = None

    # -- properties --------------------------------------------------------
    @property
    def pose(self) -> np.ndarray | None:
        return None if self._pose is None else self._pose.copy()

    @pose.setter
    def pose(self, value) -> None:
        self._set("_pose", check_pose(value, "FilterDepthImage.pose"))

    @property
    def intrinsics(self) -> Intrinsics | SphericalGeometry:
        """The sensor's geometry: a camera's intrinsics, or a LiDAR's :class:`~mabdi.spherical.SphericalGeometry`."""
        return self._intrinsics

    @intrinsics.setter
    def intrinsics(self, value: Intrinsics | SphericalGeometry) -> None:
        if not isinstance(value, (Intrinsics, SphericalGeometry)):
            raise TypeError(f"intrinsics must be mabdi.camera.Intrinsics or mabdi.spherical.SphericalGeometry, got {type(value).__name__}")
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
        rng = None if not self._noise.noisy else noise_rng(self._seed, self._frame)
        if intr.range_image:
            if self.range_renderer is None:
                self.range_renderer = RangeRenderer(DepthRenderer(self.renderer.backend, identity_array=TRIANGLE_RGB_ARRAY))
            depth = self._noise.ranges_with_noise(self.range_renderer.render(data, intr, self._pose), rng)
        else:
            zbuffer = self.renderer.render_zbuffer(data, intr, self._pose)
            depth = self._noise.depth_from_zbuffer(zbuffer, intr.near, intr.far, rng, intrinsics=intr)
        fill_depth_image(vtkImageData.GetData(outInfo), depth, intr, self._pose, self._frame, noise=self._noise)
        return 1


class SensorRenderer:
    """Noise-free images of a mesh for either sensor geometry, one window reused across frames:
    ``render(data, geometry, world_from_sensor)`` gives a camera's metric depth (:class:`DepthRenderer`)
    or a LiDAR's range image (:class:`~mabdi.render.range_rendering.RangeRenderer`), (H, W) float32, NaN
    where no surface lies within the range."""

    def __init__(self, backend: str = "egl") -> None:
        self.backend = backend
        self.camera = DepthRenderer(backend)
        self.lidar: RangeRenderer | None = None

    def render(self, data, geometry: Intrinsics | SphericalGeometry, world_from_sensor) -> np.ndarray:
        if geometry.range_image:
            if self.lidar is None:
                self.lidar = RangeRenderer(DepthRenderer(self.backend, identity_array=TRIANGLE_RGB_ARRAY))
            return self.lidar.render(data, geometry, world_from_sensor)
        zbuffer = self.camera.render_zbuffer(data, geometry, world_from_sensor)
        return zbuffer_to_depth(zbuffer, geometry.near, geometry.far)

    def close(self) -> None:
        self.camera.close()
        if self.lidar is not None:
            self.lidar.close()
