"""End state into the start state's frame: every start view matched against every end view, the
pooled matches' dominant RANSAC transform is the static part, and its outliers are searched for
rigid motions (the moving parts' candidates, handed to the labeler as hints)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sparseart.align.features import (THRESHOLD_FRACTION, FeatureMatches, match_view_features,
                                      view_features)
from sparseart.align.ransac import (DEGENERATE_FRACTION, AlignmentError, Similarity, describe_pairs,
                                    fit_matches, ransac_similarity)
from sparseart.geometry.clouds import scene_size, spread, valid_points
from sparseart.types import Frame, Pointmap

AMBIGUOUS_RATIO = 0.70           # 2nd motion support / static support above this -> warning


SCALE_RANGE = (0.2, 5.0)         # with_scale=True: scale outside -> warning


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
    where = describe_pairs(names_a, names_b)
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
