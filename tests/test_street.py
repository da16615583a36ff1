"""The street scanned by a spinning LiDAR (``scenes/street.toml``), each surface: the map is right (F@2cm against
the scene as it stands), stops growing on the way back, and the car that drove off half way leaves it. Full runs
(76 scans each): marked slow (CI runs them). docs/benchmarks.md has the same figures from
``benchmarks/bench_street.py``."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import simulation
from mabdi.evaluate import evaluate_run, run_with_ghosts

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("surface", ["pixel_grid", "quadtree", "voxel_planes"])
def test_the_street_is_mapped_and_the_car_that_left_is_taken_out(surface):
    sim = simulation("street", surface)
    ghosts = run_with_ghosts(sim, every=19)  # SA and DA count the vertices of every map measured
    scores = evaluate_run(sim, ghosts.result)
    added = np.array([r.cells_added for r in ghosts.result.records])
    half = len(added) // 2
    removal = ghosts.removal
    summary = (surface, scores.fscore_2cm, added[:half].sum(), added[half:].sum(), ghosts.final_share,
               removal.static_accuracy, removal.dynamic_accuracy)  # fmt: skip
    assert scores.fscore_2cm >= 0.95, summary
    assert added[half:].sum() <= 0.15 * added[:half].sum(), summary  # the way back adds at most 15% of the way out
    assert ghosts.final_share <= 0.01, summary
    assert removal.static_accuracy >= 0.99, summary
    assert removal.dynamic_accuracy >= 0.95, summary
