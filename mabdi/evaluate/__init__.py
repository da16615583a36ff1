"""Evaluation against the ground truth of a simulated run."""

from mabdi.evaluate.distance import distances_to_mesh

__all__ = ["distances_to_mesh"]
