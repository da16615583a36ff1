"""Filters: one module per VTK algorithm of the MABDI pipeline."""

from mabdi.filters.depth_image import DepthRenderer, FilterDepthImage, SensorNoise

__all__ = ["DepthRenderer", "FilterDepthImage", "SensorNoise"]
