"""The point budget: clouds larger than this are subsampled (seeded, order kept) before any
O(N log N) or worse stage, so 10 million points behave like ``POINT_BUDGET`` points.

Why a budget and not "all points": every stage already caps its own work (segments keep at most
``max_points_per_segment`` samples, spacing is estimated on samples), but the KD-trees over whole
states, the motion split and the fit residuals are built over every point; at 10 M points per
state ``run_clouds`` ran out of time and memory and found no joint where 1 M points worked.
1 M points per state is ~ the lift of three 640x480 views, so ordinary scenes are untouched.
"""
from __future__ import annotations

import numpy as np

from sparseart.geometry.sampling import random_subset
from sparseart.types import LabelledCloud

POINT_BUDGET = 1_000_000   # points per state


def subsample_to_budget(cloud: LabelledCloud, budget: int = POINT_BUDGET, seed: int = 0) -> LabelledCloud:
    """``cloud`` itself when it has at most ``budget`` points, else a seeded random subset of
    exactly ``budget`` points in their original order (every per-point array subset alike). O(N)."""
    if len(cloud) <= budget:
        return cloud
    return cloud.subset(random_subset(len(cloud), budget, np.random.default_rng(seed)))


def budget_clouds(start: LabelledCloud, end: LabelledCloud, budget: int = POINT_BUDGET,
                  seed: int = 0) -> tuple[LabelledCloud, LabelledCloud]:
    """:func:`subsample_to_budget` for both states (independent draws of one seed)."""
    return subsample_to_budget(start, budget, seed), subsample_to_budget(end, budget, seed + 1)
