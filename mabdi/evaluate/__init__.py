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
from mabdi.evaluate.removal_accuracy import MapHistory, RemovalAccuracy, label_points, removal_accuracy
from mabdi.evaluate.sampling import SurfaceSamples, sample_surface

__all__ = [
    "Departure",
    "GhostObserver",
    "GhostRun",
    "GhostTracker",
    "MapHistory",
    "MapMetrics",
    "RemovalAccuracy",
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
    "label_points",
    "redundancy",
    "removal_accuracy",
    "sample_surface",
]
