"""Robust similarity (or rigid) transforms from 3D matches: vectorised RANSAC, then a weighted
least-squares (Umeyama) refit on the inliers; degenerate or too-small match sets end in
:class:`AlignmentError`. Used by view registration (:mod:`sparseart.align.views`) and state
alignment (:mod:`sparseart.align.states`)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sparseart.align.features import THRESHOLD_FRACTION, AlignmentError, FeatureMatches
from sparseart.geometry.clouds import spread

MIN_MATCHES = 12                 # fewer matches after ratio test and lifting -> error
MIN_CONSENSUS_FRACTION = 0.15    # RANSAC consensus below max(6, 15 % of matches) -> error
DEGENERATE_FRACTION = 0.04       # inlier RMS spread along the 2nd principal axis / scene size


@dataclass
class Similarity:
    """x_a = scale * rotation @ x_b + translation (float64)."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def matrix(self) -> np.ndarray:
        """(4, 4) with the scale folded into the upper-left block."""
        out = np.eye(4)
        out[:3, :3] = self.scale * self.rotation
        out[:3, 3] = self.translation
        return out

    def apply(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return self.scale * points @ self.rotation.T + self.translation

    def inverse(self) -> "Similarity":
        rotation = self.rotation.T
        return Similarity(1.0 / self.scale, rotation, -(rotation @ self.translation) / self.scale)

    @staticmethod
    def from_matrix(matrix: np.ndarray) -> "Similarity":
        block = np.asarray(matrix, dtype=np.float64)[:3, :3]
        scale = float(np.cbrt(np.linalg.det(block)))
        return Similarity(scale, block / scale, np.asarray(matrix, dtype=np.float64)[:3, 3].copy())


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool,
            weights: np.ndarray | None = None) -> Similarity:
    """Weighted least-squares similarity with target ~ scale * R @ source + t (Umeyama 1991).

    The reflection case is fixed through the sign of det(U V^T). O(N).
    """
    source = np.asarray(source, dtype=np.float64).reshape(-1, 3)
    target = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    if source.shape != target.shape or source.shape[0] < 3:
        raise ValueError(f"umeyama needs two (N>=3, 3) arrays of equal shape, got {source.shape} "
                         f"and {target.shape}")
    w = np.ones(source.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (source.shape[0],) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError("umeyama weights must be (N,) non-negative with a positive sum")
    w = w / w.sum()
    mu_s, mu_t = w @ source, w @ target
    src, dst = source - mu_s, target - mu_t
    covariance = (dst * w[:, None]).T @ src
    u, d, vt = np.linalg.svd(covariance)
    sign = np.ones(3)
    sign[2] = np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0
    rotation = (u * sign) @ vt
    scale = 1.0
    if with_scale:
        variance = float(w @ np.einsum("ij,ij->i", src, src))
        if variance <= 0:
            raise ValueError("umeyama: source points coincide, the scale is undefined")
        scale = float((d * sign).sum() / variance)
    return Similarity(scale, rotation, mu_t - scale * rotation @ mu_s)


def _batched_umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool):
    """Unweighted Umeyama for I point sets at once: (I, m, 3) -> scale (I,), R (I,3,3), t (I,3)."""
    mu_s, mu_t = source.mean(axis=1), target.mean(axis=1)
    src, dst = source - mu_s[:, None], target - mu_t[:, None]
    covariance = np.einsum("imj,imk->ijk", dst, src) / source.shape[1]
    u, d, vt = np.linalg.svd(covariance)
    sign = np.ones_like(d)
    sign[:, 2] = np.where(np.linalg.det(u) * np.linalg.det(vt) < 0, -1.0, 1.0)
    rotation = np.einsum("ijk,ikl->ijl", u * sign[:, None, :], vt)
    if with_scale:
        variance = np.einsum("imj,imj->i", src, src) / source.shape[1]
        scale = (d * sign).sum(axis=1) / np.maximum(variance, 1e-300)
    else:
        scale = np.ones(source.shape[0])
    translation = mu_t - scale[:, None] * np.einsum("ijk,ik->ij", rotation, mu_s)
    return scale, rotation, translation


def _residuals(model: Similarity, source: np.ndarray, target: np.ndarray) -> np.ndarray:
    return np.linalg.norm(model.apply(source) - target, axis=1)


def ransac_similarity(source: np.ndarray, target: np.ndarray, *, with_scale: bool,
                      threshold: float | np.ndarray, iterations: int = 2000, seed: int = 0,
                      min_inliers: int = 6) -> tuple[Similarity, np.ndarray]:
    """Robust target ~ scale * R @ source + t from 3D matches (MSAC score, 3-point minimal sets).

    All minimal sets are drawn at once, solved by a batched SVD and scored with numpy in chunks:
    O(iterations * K) time, O(chunk * K) memory. The best model is refitted (Umeyama) on its
    inliers until the inlier set is stable (at most 5 rounds). ``threshold`` is in target units:
    one number, or (K,) per match (e.g. growing with depth, :func:`sparseart.align.noise.thresholds`).

    Returns:
        (model, inlier mask (K,) bool).

    Raises:
        AlignmentError: fewer than ``min_inliers`` (or 3) matches agree on one model.
    """
    source = np.asarray(source, dtype=np.float64).reshape(-1, 3)
    target = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    k = source.shape[0]
    if k < max(3, min_inliers):
        raise AlignmentError(f"RANSAC needs at least {max(3, min_inliers)} matches, got {k}")
    threshold = np.asarray(threshold, dtype=np.float64)
    if threshold.ndim and threshold.shape != (k,):
        raise ValueError(f"ransac_similarity: threshold must be a number or ({k},), got {threshold.shape}")
    squared_threshold = threshold ** 2
    rng = np.random.default_rng(seed)
    samples = rng.integers(0, k, size=(iterations, 3))
    distinct = ((samples[:, 0] != samples[:, 1]) & (samples[:, 0] != samples[:, 2])
                & (samples[:, 1] != samples[:, 2]))
    # Drop near-collinear minimal sets (triangle area below threshold^2 in both clouds).
    def area(points: np.ndarray) -> np.ndarray:
        p = points[samples]
        return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    target_area = area(target)
    smallest = squared_threshold[samples].min(axis=1) if threshold.ndim else squared_threshold
    samples = samples[distinct & (target_area > smallest) & (area(source) > 0)]
    if samples.shape[0] == 0:
        raise AlignmentError(f"RANSAC found no non-degenerate 3-point sample among {k} matches")
    scale, rotation, translation = _batched_umeyama(source[samples], target[samples], with_scale)
    best_cost, best = np.inf, 0
    chunk = max(1, 250_000 // max(k, 1))
    source_t, target_t = np.ascontiguousarray(source.T), np.ascontiguousarray(target.T)
    for lo in range(0, samples.shape[0], chunk):
        hi = lo + chunk
        # one coordinate at a time: (chunk, 3) @ (3, K) BLAS products into small (chunk, K) arrays
        block = scale[lo:hi, None, None] * rotation[lo:hi]
        squared = np.zeros((block.shape[0], k))
        for c in range(3):
            difference = block[:, c, :] @ source_t
            difference += translation[lo:hi, c, None]
            difference -= target_t[c][None]
            squared += difference * difference
        cost = np.minimum(squared, squared_threshold).sum(axis=1)
        i = int(np.argmin(cost))
        if cost[i] < best_cost:
            best_cost, best = float(cost[i]), lo + i
    model = Similarity(float(scale[best]), rotation[best], translation[best])
    inliers = _residuals(model, source, target) < threshold
    for _ in range(5):
        if inliers.sum() < 3:
            break
        model = umeyama(source[inliers], target[inliers], with_scale)
        updated = _residuals(model, source, target) < threshold
        if np.array_equal(updated, inliers):
            break
        inliers = updated
    if inliers.sum() < max(3, min_inliers):
        raise AlignmentError(f"RANSAC consensus of only {int(inliers.sum())} of {k} matches "
                             f"(need {max(3, min_inliers)})")
    return model, inliers


def describe_pairs(names_a: list[str], names_b: list[str]) -> str:
    return f"{', '.join(names_a)} vs {', '.join(names_b)}"


def fit_matches(matches: FeatureMatches, *, with_scale: bool, size: float, seed: int,
                names_a: list[str], names_b: list[str]) -> tuple[Similarity, np.ndarray, float]:
    """Dominant transform b -> a of lifted matches, with every degenerate case as AlignmentError.

    Returns (model, inliers, inlier rmse in frame-a units). O(2000 K).
    """
    where = describe_pairs(names_a, names_b)
    k = len(matches)
    if k < MIN_MATCHES:
        raise AlignmentError(
            f"{where}: too few feature matches ({k} with 3D points, {matches.n_ratio_passed} passed the "
            f"ratio test, keypoints {matches.n_keypoints[0]}/{matches.n_keypoints[1]}; need "
            f"{MIN_MATCHES}): textureless or non-overlapping images")
    need = max(6, int(np.ceil(MIN_CONSENSUS_FRACTION * k)))
    try:
        model, inliers = ransac_similarity(matches.points_b, matches.points_a, with_scale=with_scale,
                                           threshold=THRESHOLD_FRACTION * size, seed=seed,
                                           min_inliers=need)
    except AlignmentError as error:
        raise AlignmentError(f"{where}: no consistent transform: {error}") from None
    extent = spread(matches.points_a[inliers])
    if extent[1] < DEGENERATE_FRACTION * size:
        raise AlignmentError(
            f"{where}: degenerate matches: the {int(inliers.sum())} inliers are collinear or in a tiny "
            f"region (spread {extent[0]:.3g} x {extent[1]:.3g}, scene size {size:.3g})")
    rmse = float(np.sqrt(np.mean(_residuals(model, matches.points_b[inliers],
                                            matches.points_a[inliers]) ** 2)))
    return model, inliers, rmse


