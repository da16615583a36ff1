"""Evaluation against the ground truth of a simulated run: metrics, baselines, the benchmark harness."""

from mabdi.evaluate.distance import distances_to_mesh
from mabdi.evaluate.metrics import MapMetrics, evaluate_map, evaluate_run, observed_ground_truth
from mabdi.evaluate.redundancy import redundancy
from mabdi.evaluate.sampling import SurfaceSamples, sample_surface

__all__ = [
    "MapMetrics",
    "SurfaceSamples",
    "distances_to_mesh",
    "evaluate_map",
    "evaluate_run",
    "observed_ground_truth",
    "redundancy",
    "sample_surface",
]
