"""Dashboard: one picture per MABDI iteration, laid out as seed 001 Fig. 6, rendered off-screen.

    +--------------------------+--------------------------+--------------------------+
    | third-person view: scene | same view: this frame's  | elements in the map      |
    | (grey), map coloured by  | novel surface only       | up to this frame         |
    | creation frame, frustum, |                          |                          |
    | helical path             |                          |                          |
    +--------------------------+--------------------------+--------------------------+
    | D, the measured depth    | E, the expected depth    | classified: novel black, |
    |                          | (rendered from the map)  | known white, contradicted|
    |                          |                          | red, no return grey      |
    +--------------------------+--------------------------+--------------------------+

Default size 1296 x 720 (six 432 x 360 panels; both sides multiples of 16
for video encoders). The third-person camera frames the scene and the whole
path, from their bounds, looking from the side of the path's first pose.
The map is drawn straight from the world mesh's blocks (a composite mapper:
a frame uploads only its new blocks), coloured on the viridis ramp from the
first frame (dark) to the last (bright), :func:`mabdi.mesh_maps.colours.colours_by_frame`,
or, when the source has colour images, in its vertex colours (the camera's).
Depth images share one colour range, fixed from the first frame's D
(2nd to 98th percentile), so frames compare.

Use :class:`Dashboard` with a :class:`mabdi.loop.MappingRun`: after each
``simulation.step(i)``, ``dashboard.render(i)`` returns the frame as a
(720, 1296, 3) uint8 array.
"""

from __future__ import annotations

import functools

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk
from vtkmodules.vtkCommonCore import vtkLookupTable, vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkImageData, vtkPolyData
from vtkmodules.vtkRenderingCore import vtkActor, vtkCompositePolyDataMapper, vtkImageActor, vtkPolyDataMapper

from mabdi.camera import Intrinsics
from mabdi.mesh_maps.mesh_map import COLOUR_LAYER
from mabdi.polydata import polyline

SIZE = (1296, 720)
LABEL_COLOURS = np.array([[128, 128, 128], [255, 255, 255], [0, 0, 0], [220, 40, 40]], dtype=np.uint8)
NAN_GREY = np.array([128, 128, 128], dtype=np.uint8)


@functools.cache
def _ramp(name: str) -> np.ndarray:
    """(256, 3) uint8 colours of a matplotlib colour map (built once per name)."""
    from matplotlib import colormaps

    return np.round(255 * colormaps[name](np.linspace(0, 1, 256))[:, :3]).astype(np.uint8)


def depth_colours(depth: np.ndarray, low: float, high: float) -> np.ndarray:
    """(H, W, 3) uint8: depth on the magma ramp from ``low`` (dark) to ``high`` (bright); NaN grey."""
    table = _ramp("magma")
    finite = np.isfinite(depth)
    scaled = np.clip((np.nan_to_num(depth, nan=low) - low) / max(high - low, 1e-9), 0, 1)
    out = table[(scaled * 255).astype(np.int64)]
    out[~finite] = NAN_GREY
    return out


def label_colours(labels: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 of classifier labels: no return grey, known white, novel black, contradicted red."""
    return LABEL_COLOURS[np.clip(np.asarray(labels, dtype=np.int64), 0, 3)]


def frustum(pose: np.ndarray, intrinsics: Intrinsics, depth: float) -> vtkPolyData:
    """Lines of the sensor's viewing pyramid to ``depth`` metres (world frame)."""
    k = intrinsics
    corners = np.array([[0, 0], [k.width, 0], [k.width, k.height], [0, k.height]], dtype=np.float64)
    rays = np.column_stack([(corners[:, 0] - k.cx) / k.fx, (corners[:, 1] - k.cy) / k.fy, np.ones(4)]) * depth
    points = np.vstack([[0.0, 0.0, 0.0], rays]) @ pose[:3, :3].T + pose[:3, 3]
    lines = [(0, 1), (0, 2), (0, 3), (0, 4), (1, 2), (2, 3), (3, 4), (4, 1)]
    data = vtkPolyData()
    vtk_points = vtkPoints()
    vtk_points.SetData(numpy_to_vtk(points, deep=True))
    data.SetPoints(vtk_points)
    cells = vtkCellArray()
    for a, b in lines:
        cells.InsertNextCell(2)
        cells.InsertCellPoint(a)
        cells.InsertCellPoint(b)
    data.SetLines(cells)
    return data


def fit_camera(camera, bounds_min: np.ndarray, bounds_max: np.ndarray, from_point: np.ndarray) -> None:
    """Point a VTK camera at the box's centre from the side of ``from_point``, far enough to see it all."""
    centre = 0.5 * (bounds_min + bounds_max)
    radius = 0.5 * float(np.linalg.norm(bounds_max - bounds_min))
    side = np.asarray(from_point, dtype=np.float64) - centre
    side[2] = 0.0
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-9 else np.array([1.0, 0.0, 0.0])
    direction = side + np.array([0.0, 0.0, 0.8])
    direction /= np.linalg.norm(direction)
    angle = 30.0
    distance = 1.05 * radius / np.sin(np.radians(angle / 2))
    camera.SetViewAngle(angle)
    camera.SetFocalPoint(*centre)
    camera.SetPosition(*(centre + distance * direction))
    camera.SetViewUp(0.0, 0.0, 1.0)
    camera.SetClippingRange(0.05 * distance, 3.0 * distance)


class Dashboard:
    """Renders the six-panel picture of a running :class:`~mabdi.loop.MappingRun` (see the module docs)."""

    def __init__(self, simulation, size: tuple[int, int] = SIZE) -> None:
        import pyvista as pv

        width, height = size
        if width % 48 or height % 16:
            raise ValueError(
                f"dashboard size {width}x{height}: need a width that is a multiple of 48 (3 panels, 16 for encoders) "
                "and a height that is a multiple of 16"
            )
        self.simulation = simulation
        self.loop = simulation.loop
        self.size = (int(width), int(height))
        frames = len(simulation.poses)
        self._frames = frames
        self._intrinsics = self.loop.intrinsics
        self._counts: list[int] = []
        self._depth_range: tuple[float, float] | None = None
        # The ground truth is drawn faintly when it is known (simulated or recorded from a known scene).
        self._scene = simulation.scene
        self._active = self._scene.active_objects(frames - 1) if self._scene is not None else ()
        plotter = pv.Plotter(off_screen=True, shape=(2, 3), window_size=self.size, border=False)
        self.plotter = plotter
        scene = self._scene.mesh_at(frames - 1) if self._scene is not None else vtkPolyData()
        path_points = simulation.poses[:, :3, 3]
        if scene.GetNumberOfPoints():
            low = np.minimum(np.array(scene.GetBounds())[0::2], path_points.min(axis=0))
            high = np.maximum(np.array(scene.GetBounds())[1::2], path_points.max(axis=0))
        else:  # no scene: the path and what the sensor can see from it
            reach = self._intrinsics.far
            low, high = path_points.min(axis=0) - reach, path_points.max(axis=0) + reach

        coloured = bool(getattr(simulation.source, "has_colour", False))
        self._scene_actors = []
        first = "map in the camera's colours" if coloured else "map by creation frame"
        for column, title in ((0, first), (1, "novel surface (orange), removed (red)")):
            plotter.subplot(0, column)
            plotter.set_background("white")
            actor = self._polydata_actor(scene, (0.75, 0.75, 0.75), opacity=0.35 if column == 1 else 0.25)
            plotter.add_actor(actor)
            self._scene_actors.append(actor)
            plotter.add_actor(self._polydata_actor(polyline(path_points), (0.1, 0.1, 0.1), line_width=2))
            plotter.add_text(title, font_size=9, color="black", position="upper_left")
            fit_camera(plotter.renderer.GetActiveCamera(), low, high, path_points[0])
            plotter.renderer.camera_set = True  # keep pyvista from resetting it on the first render
        self._frustum_actors = []
        for column in (0, 1):
            plotter.subplot(0, column)
            actor = self._polydata_actor(vtkPolyData(), (0.85, 0.1, 0.1), line_width=2)
            plotter.add_actor(actor)
            self._frustum_actors.append(actor)

        plotter.subplot(0, 0)
        lut = vtkLookupTable()
        lut.SetNumberOfTableValues(256)
        from matplotlib import colormaps

        for i, rgba in enumerate(colormaps["viridis"](np.linspace(0, 1, 256))):
            lut.SetTableValue(i, *rgba)
        lut.Build()
        mapper = vtkCompositePolyDataMapper()
        mapper.SetInputDataObject(self.loop.world.map)
        if coloured:
            mapper.SetScalarModeToUsePointFieldData()
            mapper.SelectColorArray(COLOUR_LAYER)
            mapper.SetColorModeToDirectScalars()
        else:
            mapper.SetScalarModeToUseCellFieldData()
            mapper.SelectColorArray("frame")
            mapper.SetLookupTable(lut)
            mapper.SetScalarRange(0, max(frames - 1, 1))
            mapper.SetUseLookupTableScalarRange(False)
        mapper.ScalarVisibilityOn()
        map_actor = vtkActor()
        map_actor.SetMapper(mapper)
        plotter.add_actor(map_actor)

        plotter.subplot(0, 1)
        novel_mapper = vtkPolyDataMapper()
        novel_mapper.SetInputDataObject(self.loop.novel_surface())
        novel_mapper.ScalarVisibilityOff()
        novel_actor = vtkActor()
        novel_actor.SetMapper(novel_mapper)
        novel_actor.GetProperty().SetColor(0.95, 0.55, 0.1)
        plotter.add_actor(novel_actor)
        # faces that object removal took out of the map this frame, in red
        self._removed_actor = self._polydata_actor(vtkPolyData(), (0.85, 0.05, 0.05))
        plotter.add_actor(self._removed_actor)

        plotter.subplot(0, 2)
        chart = pv.Chart2D(x_label="frame", y_label="triangles in the map")
        chart.title = "elements in the map"
        self._line = chart.line([0.0], [0.0], color="tab:blue", width=2.0)
        chart.x_range = [0, max(frames - 1, 1)]
        self._chart = chart
        plotter.add_chart(chart)

        self._images = []
        for column, title in ((0, "D: measured depth"), (1, "E: expected depth (from the map)"), (2, "novel (black), known, contradicted (red)")):
            plotter.subplot(1, column)
            plotter.set_background("white")
            image = vtkImageData()
            image.SetDimensions(self._intrinsics.width, self._intrinsics.height, 1)
            actor = vtkImageActor()
            actor.GetMapper().SetInputData(image)
            plotter.add_actor(actor)
            plotter.add_text(title, font_size=9, color="black", position="upper_left")
            self._images.append(image)
            self._fit_image_camera(plotter.renderer.GetActiveCamera())
            plotter.renderer.camera_set = True

    def _fit_image_camera(self, camera) -> None:
        w, h = self._intrinsics.width, self._intrinsics.height
        camera.ParallelProjectionOn()
        camera.SetFocalPoint(w / 2 - 0.5, h / 2 - 0.5, 0.0)
        camera.SetPosition(w / 2 - 0.5, h / 2 - 0.5, 1000.0)
        camera.SetViewUp(0.0, 1.0, 0.0)
        panel_aspect = (self.size[0] / 3) / (self.size[1] / 2)
        camera.SetParallelScale(0.5 * max(h * 1.12, w / panel_aspect))  # room for the title
        camera.SetClippingRange(1.0, 2000.0)

    @staticmethod
    def _polydata_actor(data: vtkPolyData, colour, opacity: float = 1.0, line_width: float = 1.0) -> vtkActor:
        mapper = vtkPolyDataMapper()
        mapper.SetInputData(data)
        mapper.ScalarVisibilityOff()
        actor = vtkActor()
        actor.SetMapper(mapper)
        actor.GetProperty().SetColor(*colour)
        actor.GetProperty().SetOpacity(opacity)
        actor.GetProperty().SetLineWidth(line_width)
        return actor

    @staticmethod
    def _set_rgb(image: vtkImageData, rgb: np.ndarray) -> None:
        flipped = np.ascontiguousarray(rgb[::-1].reshape(-1, 3))  # VTK images start at the bottom row
        array = numpy_to_vtk(flipped, deep=True)
        array.SetName("rgb")
        image.GetPointData().SetScalars(array)
        image.Modified()

    def render(self, frame: int) -> np.ndarray:
        """The dashboard after ``simulation.step(frame)``: a (height, width, 3) uint8 picture."""
        loop = self.loop
        frame_values = loop.last_frame
        pose = frame_values.measured.pose
        for actor in self._frustum_actors:
            actor.GetMapper().SetInputData(frustum(pose, self._intrinsics, 0.6))
        active = self._scene.active_objects(frame) if self._scene is not None else ()
        if active != self._active:  # a dynamic scene: an object appeared or went
            self._active = active
            scene = self._scene.mesh_at(frame)
            for actor in self._scene_actors:
                actor.GetMapper().SetInputData(scene)
        self._removed_actor.GetMapper().SetInputData(loop.removed_surface())
        self._counts.append(loop.world.number_of_cells)
        x = np.arange(len(self._counts), dtype=float)
        self._line.update(x, np.asarray(self._counts, dtype=float))
        self._chart.y_range = [0, max(max(self._counts), 1) * 1.05]

        measured = frame_values.measured.depth
        if self._depth_range is None:
            finite = measured[np.isfinite(measured)]
            self._depth_range = (float(np.percentile(finite, 2)), float(np.percentile(finite, 98))) if finite.size else (0.5, 5.0)
        low, high = self._depth_range
        self._set_rgb(self._images[0], depth_colours(measured, low, high))
        if loop.classifier_enabled:
            expected = frame_values.expected.depth
            labels = loop.labels()
        else:
            expected = np.full_like(measured, np.nan)
            labels = np.where(np.isfinite(measured), 2, 0)
        self._set_rgb(self._images[1], depth_colours(expected, low, high))
        self._set_rgb(self._images[2], label_colours(labels))
        self.plotter.render()
        return self.plotter.screenshot(return_img=True)

    def close(self) -> None:
        self.plotter.close()
