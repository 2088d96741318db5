"""One part's two point sets made ready for fitting, once: ``prepare_part`` -> ``PartData``.

Everything that does not depend on a seed motion or a joint model is computed here and shared by
every fit of the part (all seed motions, both joint types, the uncertainty):

1. finite rows; at most ``FitConfig.max_work_points`` per state (random subset) -- O(N);
2. cleaning (``clean.clean_part_points``) and normalisation (centre of both states, RMS radius);
3. ONE fixed subsample per state for one-to-one matching (``max_match_points``), one for the
   Chamfer term (``max_chamfer_points``) and a screening subset of the matching sample
   (``screen_points``, for ``seeds.screen_seeds``), with their normals (PCA of 12 neighbours in the whole
   working cloud, so a row's normal does not depend on the sample) and k-d trees;
4. the part's own geometry: reference point, RMS radius, principal variances, the fraction of
   points off any surface (outlier test), the inlier radius and the end cloud's tree.

Cost O(W log W) for W = min(N, max_work_points) points per state (k-NN of cleaning, trees,
normals of <= 2 x 1500 rows), paid once per part: ``prepare_part`` keeps the last few results
keyed by a hash of the input arrays and the config, so repeated ``fit_joint`` calls on the same
part (the candidate search runs one per seed motion) reuse it. The cache cannot change a result:
``PartData`` is a pure function of (points, config).
"""
from __future__ import annotations

import hashlib
from dataclasses import astuple, dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from sparseart.geometry.clouds import median_spacing
from sparseart.geometry.sampling import random_subset
from sparseart.joints.cache import LRUCache
from sparseart.joints.clean import clean_part_points, estimate_normals
from sparseart.joints.config import FitConfig
from sparseart.joints.reliability import FitWarning, WarningCode, scatter_fraction

MIN_POINTS = 5
CACHE_SIZE = 4
NORMAL_NEIGHBOURS = 12


@dataclass(frozen=True)
class Sample:
    """A fixed subsample of both states (normalised units): points, unoriented normals, the end
    points' k-d tree and the matching scale of that density: ``spacing`` = median nearest-
    neighbour distance of the end points, pairs clipped within [floor, ceiling] = [2, 8] x spacing.
    start_confidence / end_confidence: the rows' depth confidences in [0, 1] (float64), or None
    when unknown (every point counts fully; ``optimise.confidence_pair_weights``)."""

    start: np.ndarray
    end: np.ndarray
    start_normals: np.ndarray
    end_normals: np.ndarray
    end_tree: cKDTree
    spacing: float
    start_confidence: np.ndarray | None = None
    end_confidence: np.ndarray | None = None

    @property
    def floor(self) -> float:
        return max(2.0 * self.spacing, 1e-9)

    @property
    def ceiling(self) -> float:
        return 8.0 * self.spacing

    @property
    def size(self) -> int:
        return min(len(self.start), len(self.end))


@dataclass(frozen=True)
class PartData:
    """A part ready to fit (see the module docstring). start / end: (N, 3) / (M, 3) cleaned
    working points, normalised ``(x - centre) / scale``; start_rows / end_rows: their rows in the
    caller's arrays (for colours); match / chamfer / screen: the fixed subsamples; reference:
    start centroid; part_radius: RMS distance of the start points to it; principal_variances:
    (3,) descending; scatter: ``uncertainty.scatter_fraction`` of the worse state; inlier_radius:
    4 x the 10 % quantile of the start points' nearest-neighbour distances; end_tree: k-d tree of
    ``end``; warnings: cleaning / size warnings; input_counts: (N, M) rows given; key: the hash
    of (points, config) it was cached under (None when not cached)."""

    start: np.ndarray
    end: np.ndarray
    start_rows: np.ndarray
    end_rows: np.ndarray
    centre: np.ndarray
    scale: float
    match: Sample
    chamfer: Sample
    screen: Sample
    reference: np.ndarray
    part_radius: float
    principal_variances: np.ndarray
    scatter: float
    inlier_radius: float
    end_tree: cKDTree
    warnings: tuple[FitWarning, ...]
    input_counts: tuple[int, int]
    key: tuple | None = None

    def normalise(self, transform: np.ndarray) -> np.ndarray:
        """A (4, 4) motion in input units -> normalised units."""
        normalise = np.eye(4)
        normalise[:3, :3] /= self.scale
        normalise[:3, 3] = -self.centre / self.scale
        denormalise = np.eye(4)
        denormalise[:3, :3] *= self.scale
        denormalise[:3, 3] = self.centre
        return normalise @ np.asarray(transform, dtype=np.float64) @ denormalise


_cache: LRUCache[PartData] = LRUCache(CACHE_SIZE)


def fingerprint(array: np.ndarray) -> tuple:
    """Shape, dtype and a 128-bit hash of an array's bytes: a cache key. O(N)."""
    array = np.ascontiguousarray(array)
    return array.shape, str(array.dtype), hashlib.blake2b(array.view(np.uint8).ravel(), digest_size=16).digest()


def prepare_part(start_points: np.ndarray, end_points: np.ndarray, config: FitConfig | None = None,
                 cache: bool = True, start_confidence: np.ndarray | None = None,
                 end_confidence: np.ndarray | None = None) -> PartData:
    """``PartData`` of one part's start (N, 3) / end (M, 3) points (any frame and units).

    cache: reuse / remember the result for the same arrays and config (``CACHE_SIZE`` entries).
    start_confidence / end_confidence: optional (N,) / (M,) per-point confidences in [0, 1]
    (a scene's depth confidence), carried with the matching and Chamfer samples
    (``Sample.start_confidence``) so the fit can weight pairs by them. Ignored when
    ``config.confidence_weights`` is False or when both are None / all ones (then the result is
    exactly the one without them). Cleaning and sampling never look at them.
    Raises ValueError for a bad shape, fewer than 5 finite points per state or coincident points.
    O(W log W), W = min(N, ``config.max_work_points``) (+ O(N) hashing when cached).
    """
    config = config or FitConfig()
    start_points = _as_points(start_points, "start_points")
    end_points = _as_points(end_points, "end_points")
    confidences = _as_confidences(start_confidence, end_confidence, start_points, end_points, config)
    if not cache:
        return _prepare(start_points, end_points, config, confidences)
    key = (fingerprint(start_points), fingerprint(end_points), astuple(config))
    if confidences is not None:
        key += (fingerprint(confidences[0]), fingerprint(confidences[1]))
    hit = _cache.get(key)
    if hit is not None:
        return hit
    part = replace(_prepare(start_points, end_points, config, confidences), key=key)
    _cache.put(key, part)
    return part


def clear_cache() -> None:
    """Forget every remembered ``PartData``."""
    _cache.clear()


def _as_points(points: np.ndarray, name: str) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"fit_joint: {name} must have shape (N, 3), got {points.shape}")
    return points


def _as_confidences(start_confidence: np.ndarray | None, end_confidence: np.ndarray | None,
                    start_points: np.ndarray, end_points: np.ndarray,
                    config: FitConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """Both states' confidences as float64 (a missing side = ones), or None when they cannot
    change the fit (``confidence_weights`` off, none given, or all ones). ValueError for a wrong
    shape or a value outside [0, 1] (NaN included). O(N)."""
    if not config.confidence_weights or (start_confidence is None and end_confidence is None):
        return None
    result = []
    for name, confidence, points in (("start_confidence", start_confidence, start_points),
                                     ("end_confidence", end_confidence, end_points)):
        if confidence is None:
            result.append(np.ones(len(points)))
            continue
        confidence = np.asarray(confidence, dtype=np.float64)
        if confidence.shape != (len(points),):
            raise ValueError(f"fit_joint: {name} must have shape ({len(points)},), got {confidence.shape}")
        if not np.all((confidence >= 0.0) & (confidence <= 1.0)):
            raise ValueError(f"fit_joint: {name} must lie in [0, 1]")
        result.append(confidence)
    if all(np.all(c == 1.0) for c in result):
        return None
    return result[0], result[1]


def _prepare(start_points: np.ndarray, end_points: np.ndarray, config: FitConfig,
             confidences: tuple[np.ndarray, np.ndarray] | None = None) -> PartData:
    rng = np.random.default_rng(config.seed)
    warnings: list[FitWarning] = []
    start_rows = _working_rows(start_points, "start_points", config, rng, warnings)
    end_rows = _working_rows(end_points, "end_points", config, rng, warnings)
    start, end = start_points[start_rows], end_points[end_rows]
    start_conf = end_conf = None
    if confidences is not None:
        start_conf, end_conf = confidences[0][start_rows], confidences[1][end_rows]
    everything = np.concatenate([start, end])
    centre = everything.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((everything - centre) ** 2, axis=1))))
    if not np.isfinite(scale) or scale <= 1e-12 * max(1.0, float(np.abs(centre).max())):
        raise ValueError("fit_joint: all points coincide; no motion can be estimated")
    start, end = (start - centre) / scale, (end - centre) / scale
    start_tree, end_tree = cKDTree(start), cKDTree(end)
    match = _sample(start, end, start_tree, end_tree, config.max_match_points, rng, start_conf, end_conf)
    chamfer = _sample(start, end, start_tree, end_tree, config.max_chamfer_points, rng, start_conf, end_conf)
    screen = _subsample(match, config.screen_points, rng) if config.screen_points > 0 else match
    reference = start.mean(axis=0)
    centred = start - reference
    part_radius = float(np.sqrt(np.mean(np.sum(centred ** 2, axis=1))))
    principal = np.sort(np.linalg.eigvalsh(np.cov(centred.T)))[::-1]
    scatter_rng = np.random.default_rng(config.seed + 3571)
    scatter = max(scatter_fraction(start, scatter_rng, tree=start_tree),
                  scatter_fraction(end, scatter_rng, tree=end_tree))
    if len(start) >= 2:
        own = start_tree.query(start, k=2)[0][:, 1]
        inlier_radius = 4.0 * max(float(np.quantile(own, 0.1)), 1e-12)
    else:
        inlier_radius = 1e-12
    return PartData(start=start, end=end, start_rows=start_rows, end_rows=end_rows, centre=centre, scale=scale,
                    match=match, chamfer=chamfer, screen=screen, reference=reference, part_radius=part_radius,
                    principal_variances=principal, scatter=scatter, inlier_radius=inlier_radius,
                    end_tree=end_tree, warnings=tuple(warnings),
                    input_counts=(len(start_points), len(end_points)))


def _working_rows(points: np.ndarray, name: str, config: FitConfig, rng: np.random.Generator,
                  warnings: list[FitWarning]) -> np.ndarray:
    """Rows of ``points`` to fit: finite, at most ``max_work_points`` (random), cleaned.
    ValueError when fewer than ``MIN_POINTS`` are finite. O(N) + O(W log W)."""
    rows = np.flatnonzero(np.all(np.isfinite(points), axis=1))
    if rows.size < MIN_POINTS:
        raise ValueError(f"fit_joint: {name} has {rows.size} finite points; at least {MIN_POINTS} needed")
    rows = rows[random_subset(rows.size, config.max_work_points, rng)]
    if config.clean:
        mask = clean_part_points(points[rows])
        kept = int(np.count_nonzero(mask))
        if kept >= MIN_POINTS:
            if kept < 0.7 * rows.size:
                warnings.append(FitWarning(WarningCode.CLEANED,
                                           f"{name}: cleaning removed {rows.size - kept} of {rows.size} points"))
            rows = rows[mask]
    if rows.size < config.few_points:
        warnings.append(FitWarning(WarningCode.FEW_POINTS, f"{name}: only {rows.size} points; estimate is fragile"))
    return rows


def _pick(values: np.ndarray | None, rows: np.ndarray) -> np.ndarray | None:
    return None if values is None else values[rows]


def _sample(start: np.ndarray, end: np.ndarray, start_tree: cKDTree, end_tree: cKDTree, count: int,
            rng: np.random.Generator, start_conf: np.ndarray | None = None,
            end_conf: np.ndarray | None = None) -> Sample:
    pick_start = random_subset(len(start), count, rng)
    pick_end = random_subset(len(end), count, rng)
    return make_sample(start[pick_start], end[pick_end],
                       estimate_normals(start, NORMAL_NEIGHBOURS, at=pick_start, tree=start_tree),
                       estimate_normals(end, NORMAL_NEIGHBOURS, at=pick_end, tree=end_tree),
                       _pick(start_conf, pick_start), _pick(end_conf, pick_end))


def _subsample(sample: Sample, count: int, rng: np.random.Generator) -> Sample:
    if sample.size <= count:
        return sample
    pick_start = random_subset(len(sample.start), count, rng)
    pick_end = random_subset(len(sample.end), count, rng)
    return make_sample(sample.start[pick_start], sample.end[pick_end], sample.start_normals[pick_start],
                       sample.end_normals[pick_end], _pick(sample.start_confidence, pick_start),
                       _pick(sample.end_confidence, pick_end))


def make_sample(start: np.ndarray, end: np.ndarray, start_normals: np.ndarray, end_normals: np.ndarray,
                start_confidence: np.ndarray | None = None, end_confidence: np.ndarray | None = None) -> Sample:
    """A :class:`Sample` of start (n, 3) / end (m, 3) points with their normals (and
    confidences): builds the end tree and the spacing. O(m log m)."""
    tree = cKDTree(end)
    spacing = median_spacing(end, tree=tree) if len(end) > 1 else 0.0
    return Sample(start, end, start_normals, end_normals, tree, spacing, start_confidence, end_confidence)
