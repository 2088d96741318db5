"""The residual a perfect motion would still leave on a part: its sampling and noise floor.

A fit's RMS pair residual (``ModelFit.rms_residual``) has two sources: the motion's error, and
what no motion can remove -- the two states are different samples of the surface (points do not
fall on the same spots) and each point carries its own depth noise. The second grows with the
data's noise: on clean renders it is almost the whole residual (two disjoint samples of one state
pair at 97-110 % of a correct fit's residual), on sensor depth it grows with the noise, so a
confidence that reads the raw residual against a fixed share of the part's size calls a correct
fit on noisy depth less sure than the same fit on a clean render.

:func:`residual_floor` measures that floor from the part's own points: per state, two disjoint
random samples of the matching sample's size are paired exactly as the fit pairs the states
(:func:`~sparseart.joints.optimise.one_to_one_pairs`, same clip and normal gate, identity
motion); the RMS pair distance is the floor of that state. Per-pixel depth noise is independent
between the pixels of one capture, so the two samples carry it; smooth warps and registration
errors are shared within a state and do not show (they stay in the excess, as they should: they
do move the joint).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from sparseart.joints.cache import LRUCache
from sparseart.joints.clean import estimate_normals
from sparseart.joints.config import FitConfig
from sparseart.joints.optimise import one_to_one_pairs
from sparseart.joints.part import NORMAL_NEIGHBOURS, PartData, make_sample

MIN_FLOOR_POINTS = 30      # fewer points per half: no floor (0, the raw residual counts whole)
FLOOR_SEED_OFFSET = 7349   # the floor's own random generator: the fit's draws are untouched
_cache: LRUCache[float] = LRUCache(64)


def residual_floor(part: PartData, config: FitConfig) -> float:
    """RMS pair residual (normalised units, as ``ModelFit.rms_residual``) that the part's
    sampling and per-point noise leave under a perfect motion: the quadratic mean of the two
    states' :func:`state_floor`. 0 when a state has too few points to split.

    Cached per prepared part (``part.key``, which holds the fit config the part was prepared
    with, the one passed here): every candidate fit of a part reads the same floor. O(W log W +
    n log n + the sparse matching) for W working and n = matching-sample points per state
    (~20-40 ms at n = 1500)."""
    key = part.key
    cached = _cache.get(key) if key is not None else None
    if cached is not None:
        return cached
    rng = np.random.default_rng(config.seed + FLOOR_SEED_OFFSET)
    size = part.match.size
    floors = [state_floor(part.start, size, config, rng), state_floor(part.end, size, config, rng, part.end_tree)]
    value = float(np.sqrt(np.mean(np.square(floors)))) if all(f > 0 for f in floors) else 0.0
    if key is not None:
        _cache.put(key, value)
    return value


def state_floor(points: np.ndarray, size: int, config: FitConfig, rng: np.random.Generator,
                tree: cKDTree | None = None) -> float:
    """The floor of one state's points (W, 3), normalised units: two disjoint random samples of
    k = min(size, W // 2) points paired one to one (clip ``config.pair_tau_factor`` x the median
    nearest distance, normals within ``config.normal_gate_deg``), RMS of the pair distances. When
    k < size the halves are sparser than the fit's sample; the RMS is then scaled by sqrt(k /
    size) (surface sampling distances shrink with the square root of the density; the noise
    share does not, so the scaled floor errs low and the confidence never gains from it). 0 with
    fewer than ``MIN_FLOOR_POINTS`` per half or no pair. ``tree``: the points' k-d tree when the
    caller has one (the prepared part's end tree)."""
    half = min(int(size), len(points) // 2)
    if half < MIN_FLOOR_POINTS:
        return 0.0
    order = rng.permutation(len(points))
    first, second = order[:half], order[half:2 * half]
    tree = tree if tree is not None else cKDTree(points)
    normals = [estimate_normals(points, NORMAL_NEIGHBOURS, at=rows, tree=tree) for rows in (first, second)]
    sample = make_sample(points[first], points[second], normals[0], normals[1])
    rows, cols, _ = one_to_one_pairs(sample.start, sample, config.pair_tau_factor, normals[0],
                                     float(np.cos(np.radians(config.normal_gate_deg))))
    if rows.size == 0:
        return 0.0
    rms = float(np.sqrt(np.mean(np.sum((sample.start[rows] - sample.end[cols]) ** 2, axis=1))))
    return rms * float(np.sqrt(half / size))
