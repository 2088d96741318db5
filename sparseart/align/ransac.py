"""Alignment of unposed scenes: views of one state into one frame, then end state into start frame.

Features (:mod:`sparseart.align.features`) -> 3D matches through the pointmaps -> vectorised RANSAC
of a similarity (or rigid) transform -> least-squares (Umeyama) refit on the inliers. Views of one
state are chained through the best-connected view and polished with point-to-plane ICP; between
states the dominant transform is the static part and the outliers are searched for rigid motions
(the moving parts' candidates). Degenerate input ends in :class:`AlignmentError` or a warning.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from sparseart.align.features import (PLANAR_FRACTION, THRESHOLD_FRACTION, AlignmentError, FeatureMatches,
                             geometry_edge, icp_polish, match_features, match_view_features, scene_size,
                             spread, valid_points, view_features)
from sparseart.types import Frame, Pointmap

__all__ = ["AlignmentError", "FeatureMatches", "MotionCandidate", "Similarity", "StateAlignment",
           "align_states", "match_features", "ransac_similarity", "register_views",
           "transform_pointmap", "umeyama"]

MIN_MATCHES = 12                 # fewer matches after ratio test and lifting -> error
MIN_CONSENSUS_FRACTION = 0.15    # RANSAC consensus below max(6, 15 % of matches) -> error
DEGENERATE_FRACTION = 0.04       # inlier RMS spread along the 2nd principal axis / scene size
AMBIGUOUS_RATIO = 0.70           # 2nd motion support / static support above this -> warning
SCALE_RANGE = (0.2, 5.0)         # with_scale=True: scale outside -> warning
LOOP_DEG, LOOP_FRACTION = 5.0, 0.05   # loop-closure disagreement that is warned


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


@dataclass
class MotionCandidate:
    """A rigid motion among the outliers of the dominant similarity.

    transform: (4, 4) float64 start -> end motion of the points that follow it, in frame a.
    support: number of inlier matches; points: (support, 3) their start-frame (frame a) positions.
    """

    transform: np.ndarray
    support: int
    points: np.ndarray


@dataclass
class StateAlignment:
    """End state (frame b) -> start state (frame a); inliers are the static part."""

    transform: Similarity
    matches: FeatureMatches
    inliers: np.ndarray
    rmse: float
    candidates: list[MotionCandidate] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


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


def ransac_similarity(source: np.ndarray, target: np.ndarray, *, with_scale: bool, threshold: float,
                      iterations: int = 2000, seed: int = 0,
                      min_inliers: int = 6) -> tuple[Similarity, np.ndarray]:
    """Robust target ~ scale * R @ source + t from 3D matches (MSAC score, 3-point minimal sets).

    All minimal sets are drawn at once, solved by a batched SVD and scored with numpy in chunks:
    O(iterations * K) time, O(chunk * K) memory. The best model is refitted (Umeyama) on its
    inliers until the inlier set is stable (at most 5 rounds). ``threshold`` is in target units.

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
    rng = np.random.default_rng(seed)
    samples = rng.integers(0, k, size=(iterations, 3))
    distinct = ((samples[:, 0] != samples[:, 1]) & (samples[:, 0] != samples[:, 2])
                & (samples[:, 1] != samples[:, 2]))
    # Drop near-collinear minimal sets (triangle area below threshold^2 in both clouds).
    def area(points: np.ndarray) -> np.ndarray:
        p = points[samples]
        return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    target_area = area(target)
    samples = samples[distinct & (target_area > threshold ** 2) & (area(source) > 0)]
    if samples.shape[0] == 0:
        raise AlignmentError(f"RANSAC found no non-degenerate 3-point sample among {k} matches")
    scale, rotation, translation = _batched_umeyama(source[samples], target[samples], with_scale)
    best_cost, best = np.inf, 0
    chunk = max(1, 2_000_000 // max(k, 1))
    for lo in range(0, samples.shape[0], chunk):
        hi = lo + chunk
        moved = scale[lo:hi, None, None] * np.einsum("ijk,nk->inj", rotation[lo:hi], source)
        moved += translation[lo:hi, None, :]
        squared = np.sum((moved - target[None]) ** 2, axis=2)
        cost = np.minimum(squared, threshold ** 2).sum(axis=1)
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


def _describe(names_a: list[str], names_b: list[str]) -> str:
    return f"{', '.join(names_a)} vs {', '.join(names_b)}"


def fit_matches(matches: FeatureMatches, *, with_scale: bool, size: float, seed: int,
                names_a: list[str], names_b: list[str]) -> tuple[Similarity, np.ndarray, float]:
    """Dominant transform b -> a of lifted matches, with every degenerate case as AlignmentError.

    Returns (model, inliers, inlier rmse in frame-a units). O(2000 K).
    """
    where = _describe(names_a, names_b)
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


def transform_pointmap(pointmap: Pointmap, transform: np.ndarray) -> Pointmap:
    """A copy of ``pointmap`` with its points mapped by a (4, 4) transform (NaN stays NaN)."""
    points = pointmap.points @ transform[:3, :3].T + transform[:3, 3]
    return replace(pointmap, points=points)


def _widest_tree(n: int, weight: np.ndarray) -> np.ndarray:
    """Parent of every node in a maximum spanning tree grown from node 0 (Prim); -1 = unreached.

    The tree path from 0 maximises the weakest link (bottleneck) on the way. O(n^2)."""
    parent = np.full(n, -1)
    best = np.where(weight[0] > 0, weight[0], -1.0)
    best[0] = -1.0
    origin = np.zeros(n, int)
    done = np.zeros(n, bool)
    done[0] = True
    while True:
        candidate = np.where(done, -1.0, best)
        j = int(np.argmax(candidate))
        if candidate[j] <= 0:
            return parent
        done[j], parent[j] = True, origin[j]
        better = (~done) & (weight[j] > best)
        best[better], origin[better] = weight[j][better], j


def _angle_deg(rotation: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))


def register_views(frames: list[Frame], pointmaps: list[Pointmap], *, with_scale: bool, seed: int = 0,
                   geometry_fallback: bool = True, matcher=None) -> tuple[list[np.ndarray], list[str]]:
    """Bring the views of one state (one rigid scene) into the camera frame of view 0.

    Every pair of views is matched and fitted (:func:`fit_matches`); each view is reached from
    view 0 through the maximum spanning tree of the inlier counts (so a view that only overlaps
    view 1 is chained through it). When features leave a view unreached and the clouds are metric
    (``with_scale=False``) with K, pairs without a feature fit get a geometric registration
    (:func:`~sparseart.align.features.geometry_edge`, with a warning naming the view; never for
    planar clouds); feature edges always rank above geometric ones. Edges off the tree are checked against it (loop
    closure) and disagreements warned. With ``with_scale=False`` each view is then polished by
    point-to-plane ICP against the views already placed. O(V^2 (M^2 + 2000 K + N log N)).

    Args:
        frames, pointmaps: the V views; pointmaps in each view's OWN camera frame.
        with_scale: per-view scale (relative-scale reconstructions); folded into the transforms.
        geometry_fallback: allow the geometric registration of pairs without feature matches.
        matcher: a pair matcher (``match(frame_a, pointmap_a, frame_b, pointmap_b) ->
            FeatureMatches``, e.g. :class:`~sparseart.align.lightglue.LightGlueMatcher`) used
            instead of SIFT; None = SIFT.

    Returns:
        ((4, 4) view_i camera frame -> view_0 camera frame for every view, identity first; warnings).

    Raises:
        AlignmentError: a view matches no other view (naming its image and the reasons).
    """
    if len(frames) != len(pointmaps) or not frames:
        raise ValueError("register_views needs one pointmap per frame")
    n = len(frames)
    if n == 1:
        return [np.eye(4)], []
    clouds = [valid_points(p) for p in pointmaps]
    size = scene_size(np.concatenate(clouds))
    features = None if matcher is not None else [view_features(f, p) for f, p in zip(frames, pointmaps)]
    names = [str(f.rgb_path) for f in frames]
    weight = np.zeros((n, n))
    pair_model: dict[tuple[int, int], Similarity] = {}
    how: dict[tuple[int, int], str] = {}
    reasons: dict[int, list[str]] = {i: [] for i in range(n)}

    def add(i: int, j: int, model: Similarity, w: float, kind: str) -> None:
        weight[i, j] = weight[j, i] = w
        pair_model[(i, j)], pair_model[(j, i)] = model, model.inverse()   # j -> i, i -> j
        how[(i, j)] = how[(j, i)] = kind

    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    for i, j in pairs:
        matches = (matcher.match(frames[i], pointmaps[i], frames[j], pointmaps[j]) if matcher is not None
                   else match_view_features(features[i], features[j]))
        try:
            model, inliers, _ = fit_matches(matches, with_scale=with_scale, size=size, seed=seed,
                                            names_a=[names[i]], names_b=[names[j]])
        except AlignmentError as error:
            reasons[i].append(str(error))
            reasons[j].append(str(error))
            continue
        add(i, j, model, 1.0 + float(inliers.sum()), f"{int(inliers.sum())} feature inliers")
    parent = _widest_tree(n, weight)
    if (geometry_fallback and not with_scale and np.any(parent[1:] < 0)
            and all(f.camera is not None for f in frames)):
        for i, j in pairs:
            if weight[i, j] == 0:
                edge = geometry_edge(j, i, frames, pointmaps, clouds, size, seed)
                if edge is None:
                    why = "geometric registration rejected (planar, little overlap or sees through)"
                    reasons[i].append(why)
                    reasons[j].append(why)
                else:
                    add(i, j, Similarity.from_matrix(edge[0]), edge[2], f"geometry only, {edge[1]:.0%} overlap")
        parent = _widest_tree(n, weight)
    warnings: list[str] = []
    transforms: list[np.ndarray | None] = [np.eye(4)] + [None] * (n - 1)
    order = [0]
    while len(order) < n:
        grown = [j for j in range(n) if transforms[j] is None and parent[j] >= 0
                 and transforms[parent[j]] is not None]
        if not grown:
            missing = next(j for j in range(n) if transforms[j] is None)
            why = "; ".join(dict.fromkeys(r.split(": ", 1)[-1] for r in reasons[missing])) or "no matches"
            raise AlignmentError(f"{frames[missing].rgb_path}: view could not be registered to any "
                                 f"other view of its state ({why})")
        for j in grown:
            p = int(parent[j])
            transforms[j] = transforms[p] @ pair_model[(p, j)].matrix()
            if p != 0 or not how[(p, j)].endswith("feature inliers"):
                warnings.append(f"{frames[j].rgb_path}: registered to {frames[p].rgb_path} by "
                                f"{how[(p, j)]}")
            order.append(j)
    for i, j in pairs:   # loop closure: edges off the tree must agree with it
        if weight[i, j] > 0 and parent[j] != i and parent[i] != j:
            relative = np.linalg.inv(transforms[i]) @ transforms[j] @ np.linalg.inv(pair_model[(i, j)].matrix())
            angle = _angle_deg(relative[:3, :3] / np.cbrt(np.linalg.det(relative[:3, :3])))
            if angle > LOOP_DEG or np.linalg.norm(relative[:3, 3]) > LOOP_FRACTION * size:
                warnings.append(f"{frames[j].rgb_path}: its direct registration to {frames[i].rgb_path} "
                                f"({how[(i, j)]}) disagrees with the chain by {angle:.1f} deg")
    if not with_scale:
        placed = [clouds[0]]
        for j in order[1:]:
            target = np.concatenate(placed)
            if spread(target)[2] < PLANAR_FRACTION * size or spread(clouds[j])[2] < PLANAR_FRACTION * size:
                warnings.append(f"{frames[j].rgb_path}: ICP polish on a planar cloud may slide "
                                f"along the plane")
            polished = icp_polish(clouds[j], target, transforms[j], size)
            if polished is None:
                warnings.append(f"{frames[j].rgb_path}: ICP polish did not improve the overlap; "
                                f"kept the registration as it was")
            else:
                transforms[j] = polished
            placed.append(clouds[j] @ transforms[j][:3, :3].T + transforms[j][:3, 3])
    return [np.asarray(t, dtype=np.float64) for t in transforms], warnings


def _motion_candidates(points_a: np.ndarray, points_b_in_a: np.ndarray, total: int, size: float,
                       seed: int, max_candidates: int) -> list[MotionCandidate]:
    """Sequential RANSAC of rigid motions (start -> end, frame a) on the static outliers."""
    min_support = max(8, int(np.ceil(0.03 * total)))
    remaining = np.arange(points_a.shape[0])
    out: list[MotionCandidate] = []
    for attempt in range(4 * max_candidates):
        if len(out) >= max_candidates or remaining.size < min_support:
            break
        try:
            model, inliers = ransac_similarity(points_a[remaining], points_b_in_a[remaining],
                                               with_scale=False, threshold=THRESHOLD_FRACTION * size,
                                               seed=seed + 1 + attempt, min_inliers=min_support)
        except AlignmentError:
            break
        chosen = remaining[inliers]
        remaining = remaining[~inliers]
        if spread(points_a[chosen])[1] >= DEGENERATE_FRACTION * size:   # skip collinear sets
            out.append(MotionCandidate(model.matrix(), int(chosen.size), points_a[chosen].copy()))
    return sorted(out, key=lambda c: -c.support)


def align_states(start_frames: list[Frame], start_pointmaps: list[Pointmap], end_frames: list[Frame],
                 end_pointmaps: list[Pointmap], *, with_scale: bool, seed: int = 0,
                 max_candidates: int = 6, matcher=None) -> StateAlignment:
    """Map the end state into the start state's frame through the static part.

    Every start view is matched against every end view and the matches are pooled; the dominant
    RANSAC transform (similarity when ``with_scale``, e.g. separate relative-scale
    reconstructions; rigid for metric depth) is the static part. Its outliers, mapped into frame a,
    are searched for rigid motions (sequential RANSAC, support >= max(8, 3 % of matches)).
    O(S E (M^2 + 2000 K)).

    Args:
        start_pointmaps / end_pointmaps: in each state's own reference frame (its view 0).
        matcher: a pair matcher used instead of SIFT (see :func:`register_views`); None = SIFT.

    Raises:
        AlignmentError: too few matches, no consensus, or degenerate inliers (naming the images).
    """
    names_a = [str(f.rgb_path) for f in start_frames]
    names_b = [str(f.rgb_path) for f in end_frames]
    if matcher is None:
        fa = [view_features(f, p) for f, p in zip(start_frames, start_pointmaps)]
        fb = [view_features(f, p) for f, p in zip(end_frames, end_pointmaps)]

        def match(i: int, j: int) -> FeatureMatches:
            return match_view_features(fa[i], fb[j])
    else:
        def match(i: int, j: int) -> FeatureMatches:
            return matcher.match(start_frames[i], start_pointmaps[i], end_frames[j], end_pointmaps[j])
    views = [(i, j) for i in range(len(start_frames)) for j in range(len(end_frames))]
    parts = [match(i, j) for i, j in views]
    views_a, views_b = [i for i, _ in views], [j for _, j in views]
    # Keypoints per image, each image counted once (a pair reports (K_a, K_b)).
    per_a, per_b = [0] * len(start_frames), [0] * len(end_frames)
    for (i, j), part in zip(views, parts):
        per_a[i], per_b[j] = part.n_keypoints
    n_keypoints = (sum(per_a), sum(per_b))
    matches = FeatureMatches.concatenate(parts, views_a, views_b, n_keypoints)
    size = scene_size(np.concatenate([valid_points(p) for p in start_pointmaps]))
    model, inliers, rmse = fit_matches(matches, with_scale=with_scale, size=size, seed=seed,
                                       names_a=names_a, names_b=names_b)
    warnings: list[str] = []
    where = _describe(names_a, names_b)
    if with_scale and not SCALE_RANGE[0] <= model.scale <= SCALE_RANGE[1]:
        warnings.append(f"{where}: end-to-start scale {model.scale:.3g} is outside "
                        f"[{SCALE_RANGE[0]}, {SCALE_RANGE[1]}]; check the reconstructions")
    outliers = ~inliers
    candidates = _motion_candidates(matches.points_a[outliers], model.apply(matches.points_b[outliers]),
                                    len(matches), size, seed, max_candidates)
    static = int(inliers.sum())
    if candidates and candidates[0].support > AMBIGUOUS_RATIO * static:
        warnings.append(f"{where}: static part is ambiguous: a second motion has {candidates[0].support} "
                        f"matches vs {static} for the dominant one (the moving part may have won)")
    return StateAlignment(model, matches, inliers, rmse, candidates, warnings)
