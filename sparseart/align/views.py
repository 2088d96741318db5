"""Views of one state into one frame: every pair matched and fitted, a maximum spanning tree of the
inlier counts, a geometric fallback for views features cannot reach, loop-closure checks and an
ICP polish against the views already placed."""
from __future__ import annotations

import numpy as np

from sparseart.align.features import PLANAR_FRACTION, THRESHOLD_FRACTION, match_view_features, view_features
from sparseart.align.geometric import geometry_edge
from sparseart.align.ransac import AlignmentError, Similarity, fit_matches
from sparseart.geometry.clouds import scene_size, spread, valid_points
from sparseart.geometry.icp import icp_polish
from sparseart.geometry.transforms import apply_transform, rotation_angle
from sparseart.types import Frame, Pointmap

LOOP_DEG, LOOP_FRACTION = 5.0, 0.05   # loop-closure disagreement that is warned


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
            angle = float(np.degrees(rotation_angle(relative[:3, :3] / np.cbrt(np.linalg.det(relative[:3, :3])))))
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
            polished = icp_polish(clouds[j], target, transforms[j], THRESHOLD_FRACTION * size)
            if polished is None:
                warnings.append(f"{frames[j].rgb_path}: ICP polish did not improve the overlap; "
                                f"kept the registration as it was")
            else:
                transforms[j] = polished
            placed.append(apply_transform(transforms[j], clouds[j]))
    return [np.asarray(t, dtype=np.float64) for t in transforms], warnings
