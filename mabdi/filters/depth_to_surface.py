"""The pixel-grid surface's former module name; see :mod:`mabdi.filters.pixel_grid`."""

from mabdi.filters.pixel_grid import FilterDepthImageToSurface, FilterPixelGrid, pixel_grid_triangles

__all__ = ["FilterDepthImageToSurface", "FilterPixelGrid", "pixel_grid_triangles"]
