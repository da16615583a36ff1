"""The surface registry: surface filters found by name.

A surface filter turns the classifier's output (a depth image holding only
the novel pixels, :mod:`mabdi.stages.classifier`) into the triangles
appended to the map. Each is registered under the name a run config uses
(``[surface] method = "quadtree"``) with:

* ``parameters``: its parameter dataclass (frozen; defaults and checks in
  ``__post_init__``, raising :class:`~mabdi.errors.ConfigError`). It is the
  config's ``[surface.<name>]`` table, field for field; fields with
  ``metadata={"toml": False}`` are not config keys;
* ``make(parameters)``: builds the filter (a VTK algorithm with one
  depth-image input and a vtkPolyData output in world coordinates). The
  loop calls its ``mesh_frame(frame, whole)`` (a
  :class:`~mabdi.frame_values.Measured` holding the pixels to mesh, and all
  of D) where it has one, as the package's surfaces do; a filter with the
  VTK API only is fed the frame as a depth image (:func:`mesh_frame`);
* ``help``: one line for ``mabdi run --help``;
* ``capabilities``: what the filter can do beyond meshing a frame, which
  the loop uses (:class:`SurfaceCapabilities`; none by default). Declared
  here, never probed on the filter object;
* ``seam_pixels(parameters, noisy)``: how many pixels around the novel ones
  the filter needs to close the seam between a new patch and the map (the
  quad-tree's blocks need ``reduction`` where the depth is noisy); the loop
  sets the classifier's ``rim = "auto"`` to it (:func:`seam_pixels`). None
  (the default): one pixel.

A new surface filter is one module plus one :func:`register_surface_filter`
call: the config section, the ``--surface`` choice and its help follow.
Filters from outside the package register the same way before the config is
loaded (see the test that registers a trivial filter).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.algorithm import raise_pipeline_errors
from mabdi.depth import MEASURED_ARRAY
from mabdi.errors import ConfigError
from mabdi.frame_values import Measured
from mabdi.surfaces.pixel_grid import FilterPixelGrid, PixelGridParameters
from mabdi.surfaces.quadtree import FilterQuadTree, QuadTreeParameters
from mabdi.surfaces.voxel_planes import FilterVoxelPlanes, VoxelPlanesParameters


@dataclass(frozen=True)
class SurfaceCapabilities:
    """What a surface filter can do beyond meshing one frame's novel pixels (the loop acts on it)."""

    #: It keeps memory across frames (voxel statistics): ``reset()``, ``state()`` and ``set_state(state)``,
    #: emptied with the map and saved in checkpoints.
    keeps_state: bool = False
    #: Object removal reaches that memory: ``clear_faces_at(centres)`` forgets what made removed faces, and
    #: ``clear_free_space(origin, ends, margins)`` empties what rays that saw through them crossed.
    clears_space: bool = False
    #: Its faces may reach past a real edge by ``face_overhang`` metres (a property of the filter), so removal
    #: widens its edge margin by that much.
    overhang: bool = False


@dataclass(frozen=True)
class SurfaceFilterEntry:
    """One registered surface filter (see the module docs)."""

    name: str
    parameters: type
    make: Callable
    help: str
    capabilities: SurfaceCapabilities = SurfaceCapabilities()
    seam_pixels: Callable | None = None


_REGISTRY: dict[str, SurfaceFilterEntry] = {}


def register_surface_filter(
    name: str,
    parameters: type,
    make: Callable,
    help: str,
    replace_existing: bool = False,
    capabilities: SurfaceCapabilities = SurfaceCapabilities(),
    seam_pixels: Callable | None = None,
) -> None:
    """Register a surface filter under ``name`` (a config value: letters, digits, underscores)."""
    if not name.isidentifier():
        raise ValueError(f"surface filter name {name!r} must be letters, digits and underscores")
    if name in _REGISTRY and not replace_existing:
        raise ValueError(f"a surface filter named {name!r} is registered already")
    try:
        parameters()
    except TypeError as exc:
        raise TypeError(f"surface filter {name!r}: its parameters class must build with defaults alone ({exc})") from None
    if not isinstance(capabilities, SurfaceCapabilities):
        raise TypeError(f"surface filter {name!r}: capabilities must be a SurfaceCapabilities, got {type(capabilities).__name__}")
    _REGISTRY[name] = SurfaceFilterEntry(name, parameters, make, help, capabilities, seam_pixels)


def unregister_surface_filter(name: str) -> None:
    """Remove a registered surface filter (tests; the built-in ones stay available by re-registering)."""
    _REGISTRY.pop(name, None)


def surface_filter_names() -> tuple[str, ...]:
    """The registered names, in registration order (the built-in three first)."""
    return tuple(_REGISTRY)


def surface_filter(name: str) -> SurfaceFilterEntry:
    """The entry of ``name``, or a ConfigError listing the known names."""
    entry = _REGISTRY.get(name)
    if entry is None:
        raise ConfigError(f"unknown surface filter {name!r} (known: {', '.join(_REGISTRY)})")
    return entry


def make_surface_filter(name: str, parameters=None):
    """A new filter of surface ``name`` with ``parameters`` (default: the filter's defaults)."""
    entry = surface_filter(name)
    if parameters is None:
        parameters = entry.parameters()
    if not isinstance(parameters, entry.parameters):
        raise TypeError(f"surface filter {name!r} takes {entry.parameters.__name__}, got {type(parameters).__name__}")
    return entry.make(parameters)


def mesh_frame(surface, frame: Measured, whole: np.ndarray | None = None) -> vtkPolyData:
    """The triangles ``surface`` (a filter :func:`make_surface_filter` made) meshes of ``frame`` (the pixels to
    mesh; ``whole``: all of D, or None when the frame is all of D), in the world of the frame's pose: its own
    ``mesh_frame``, else (a filter with the VTK API only) its output for the frame as a depth image, ``whole``
    as the image's ``measured_depth`` point array."""
    if hasattr(surface, "mesh_frame"):
        return surface.mesh_frame(frame, whole)
    image = frame.to_image()
    if whole is not None:
        array = numpy_to_vtk(np.ascontiguousarray(whole, dtype=np.float32).ravel(), deep=True)
        array.SetName(MEASURED_ARRAY)
        image.GetPointData().AddArray(array)
    surface.SetInputDataObject(0, image)
    surface.Update()
    raise_pipeline_errors(surface)
    output = vtkPolyData()
    output.ShallowCopy(surface.GetOutput())
    return output


register_surface_filter(
    "pixel_grid",
    PixelGridParameters,
    FilterPixelGrid,
    "two triangles per 2x2 pixels (seed 001)",
)
register_surface_filter(
    "quadtree",
    QuadTreeParameters,
    # The loop counts triangles: quad-tree faces are always triangulated there.
    lambda parameters: FilterQuadTree(replace(parameters, triangles=True)),
    "quad-tree faces merged over flat regions (seed 002)",
    seam_pixels=QuadTreeParameters.seam_pixels,
)
register_surface_filter(
    "voxel_planes",
    VoxelPlanesParameters,
    FilterVoxelPlanes,
    "incremental voxel-plane patches (seed 000)",
    capabilities=SurfaceCapabilities(keeps_state=True, clears_space=True, overhang=True),
)


def seam_pixels(name: str, parameters, noisy: bool) -> int:
    """The classifier's rim (pixels) surface ``name`` with ``parameters`` needs to close the seam between a new
    patch and the map, for depth that is ``noisy`` or not: its entry's ``seam_pixels``, else 1 (the pixel grid's:
    a triangle needs its four corners)."""
    entry = surface_filter(name)
    return 1 if entry.seam_pixels is None else int(entry.seam_pixels(parameters, noisy))
