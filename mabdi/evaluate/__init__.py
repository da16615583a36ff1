"""Evaluation against the ground truth of a simulated run: metrics, dynamic scenes (ghosts), baselines, the bench."""

from mabdi.evaluate.distance import distances_to_mesh
from mabdi.evaluate.dynamic import (
    Departure,
    GhostObserver,
    GhostRun,
    GhostTracker,
    StaticCoverage,
    StaticLoss,
    departures,
    first_seen,
    frames_to_clear,
    ghost_share,
    run_with_ghosts,
    static_loss,
    static_mesh,
)
from mabdi.evaluate.metrics import MapMetrics, evaluate_map, evaluate_run, observed_ground_truth
from mabdi.evaluate.redundancy import redundancy
from mabdi.evaluate.sampling import SurfaceSamples, sample_surface

__all__ = [
    "Departure",
    "GhostObserver",
    "GhostRun",
    "GhostTracker",
    "MapMetrics",
    "StaticCoverage",
    "StaticLoss",
    "departures",
    "first_seen",
    "frames_to_clear",
    "ghost_share",
    "run_with_ghosts",
    "static_loss",
    "static_mesh",
    "SurfaceSamples",
    "distances_to_mesh",
    "evaluate_map",
    "evaluate_run",
    "observed_ground_truth",
    "redundancy",
    "sample_surface",
]
