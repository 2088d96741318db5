"""Every view of both states registered at once (unposed RGB-D): one frame for the static part.

Within a state the whole scene is rigid; across the states only the static part is. So every
view of both states has one pose in the frame of the static part (the reference start camera: the
first, unless a larger group of views leaves it out, :func:`_finish_from_the_best_reference`), and
every pair of views constrains it: a pair of one state through all its matches, a pair across the
states through the matches on the static part (those on the moving part are outliers there and
become the labeler's motion hints). :func:`register_scene`:

1. matches every pair of views (both states: ``V (V - 1) / 2`` pairs for ``V`` views, each image's
   features computed once) and lifts them to 3D in each view's own camera frame;
2. grows components of views greedily (agglomerative): two components are merged by the robust
   transform of ALL their pooled matches (every pair between them, in the components' frames),
   so a view that matches no view of its own state is still placed through the other state's
   views of the same static part. Merges within a state come first (they cannot be fooled by the
   moving part); then across the states, largest consensus first. Thresholds grow with depth and
   adapt to the noise (:mod:`sparseart.align.noise`). Up to ``HYPOTHESES`` sequential fits are
   judged against the dense geometry where views of one state meet (:func:`_violations`): a
   transform must not put points where the other view sees through, must lay the views' points
   (and, with masks, the object) on each other, and must stand out among the plausible ones --
   repetitive texture (tiled floors, brick walls) otherwise wins with a shifted transform;
3. for metric clouds, a view features leave out gets the geometric fallback to a view of its state
   (:class:`sparseart.align.geometric.GeometricEdges`) and keeps that relative pose;
4. solves all feature-placed poses jointly: iteratively reweighted Gauss-Newton (soft-L1 weights)
   over the inlier matches of every pair, a rotation vector + translation per view, plus a
   per-view log depth scale for noisy metric depth (prior ``SCALE_PRIOR``, bound ``SCALE_LIMIT``;
   a reconstructor's or sensor's scale error) or relative depth (free); inliers are re-selected
   and the noise level re-estimated between two solves;
5. on clean depth only (:func:`~sparseart.align.noise.depth_roughness`), polishes each view by
   point-to-plane ICP against the other views of its state (kept when it raises the overlap);
6. checks the state alignment: enough static matches, spread out, the end surfaces not floating in
   space the start cameras saw through (free-space check), and warns when the moving part is
   nearly as strong as the static part. A check that fails leaves the states apart (alignment
   "none", each state registered on its own) with a warning, so an alignment that cannot be
   trusted is never used silently; the pipeline then registers the states on the static part.

Everything is reported per view (registered, how, inliers, residual, scale) and for the states.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from sparseart.align.features import PLANAR_FRACTION, THRESHOLD_FRACTION, FeatureMatches, match_view_features, view_features
from sparseart.align.geometric import (MAX_FREE_SPACE_VIOLATION, NOISY_MAX_FREE_SPACE_VIOLATION, GeometricEdges,
                                       view_mask_ids)
from sparseart.align.noise import MAX_CLEAN_ROUGHNESS, RHO_MAX, depth_roughness, estimate_rho, thresholds
from sparseart.align.ransac import DEGENERATE_FRACTION, AlignmentError, Similarity, ransac_similarity, umeyama
from sparseart.geometry.clouds import scene_size, spread, valid_points
from sparseart.geometry.icp import icp_polish
from sparseart.geometry.transforms import apply_transform, rotation_angle
from sparseart.parallel import in_parallel
from sparseart.types import Frame, Pointmap

STATES = ("start", "end")
MIN_PAIR_MATCHES = 6         # a pair with fewer lifted matches is not used
MIN_MERGE_INLIERS = 12       # pooled inliers needed to merge two components
MIN_MERGE_FRACTION = 0.05    # ... and this share of the pooled matches
MIN_STATE_INLIERS = 15       # static matches needed to trust the state alignment
AMBIGUOUS_RATIO = 0.70       # 2nd motion support / static support above this -> warning
MAX_SEEN_THROUGH = 0.60      # states: share of points in space the other state's cameras saw through
                             # (the smaller of the two directions; the moving part sweeps one of them)
MAX_WITHIN_SEEN_THROUGH = 0.10  # views of one state: the same (both directions); correct <= 0.05 measured
MIN_WITHIN_AGREEMENT = 0.25  # views of one state: share of points on the other's surface (correct >= 0.39)
MAX_SOLVE_MATCHES = 400      # matches per pair in the joint solve (evenly strided)
MIN_OBJECT_AGREEMENT = 0.2   # views of one state, with masks: share of object points on the other's object
                             # (measured: correct 0.36-0.98, shifted by repetitive texture ~0)
MIN_WITHIN_SHARE = 0.30      # views of one state without masks: share of their matches the transform explains
UNIQUE_RATIO = 1.8           # views of one state: support over the best different plausible transform
HYPOTHESES = 6               # sequential fits tried per merge
SCALE_PRIOR = 0.02           # sigma of the per-view log depth scale (metric depth) ...
SCALE_LIMIT = 0.05           # ... and its bound (realistic reconstructors: ~1 % scale + ~2 % warp)
SCALE_REPORTED = 0.003       # |scale - 1| below this is reported as 1 (metric depth)
RANSAC_ITERATIONS = 2000
WITH_SIFT = False
RANSAC_MAX_MATCHES = 1000     # RANSAC scores its hypotheses on at most this many matches


@dataclass
class PairMatches:
    """Lifted matches of views a < b (global indices), each side in its own camera frame."""

    a: int
    b: int
    points_a: np.ndarray
    points_b: np.ndarray
    distance: np.ndarray          # (K,) larger distance of the two points from their cameras
    cross: bool                   # the views belong to different states
    n_keypoints: tuple[int, int] = (0, 0)


@dataclass
class ViewInfo:
    """Registration outcome of one view (global index = start views, then end views)."""

    state: str
    index: int
    name: str                     # the image, STATE/rgb/NAME (Frame.image)
    how: str = "unregistered"     # reference | features | geometry | unregistered
    inliers: int = 0
    residual: float | None = None
    scale: float = 1.0
    reason: str = ""


@dataclass
class SceneRegistration:
    """Output of :func:`register_scene`.

    poses: per state, one (4, 4) float64 camera -> result frame per view (scale folded into the
        upper-left block), None for a view that could not be registered.
    reference: index of the start view whose camera frame is the result frame (identity pose).
    aligned: True when the end views share the start views' frame (the state alignment by features
        was found and trusted); otherwise each state is in the frame of its own reference view.
    candidates: start -> end rigid motions (result frame) among the cross-state matches the
        static part does not explain, strongest first (the moving parts' hints).
    views: per-view outcome; states: the state alignment's numbers (method, matches, inliers, rmse,
        checks); rho: the match noise level used (fraction of the distance from the camera);
        depth_noise: per-pixel depth noise / distance (median view, :func:`~sparseart.align.noise.depth_roughness`).
    """

    poses: dict[str, list[np.ndarray | None]]
    aligned: bool
    candidates: list = field(default_factory=list)
    views: list[ViewInfo] = field(default_factory=list)
    states: dict = field(default_factory=dict)
    rho: float = 0.0
    warnings: list[str] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    depth_noise: float = float("nan")
    reference: int = 0            # the start view whose camera frame the poses are in


# ----------------------------------------------------------------------------- matching


def _match_all(frames: list[Frame], pointmaps: list[Pointmap], n_start: int, matcher,
               with_sift: bool = False) -> list[PairMatches]:
    """Every pair of views matched once (SIFT features computed once per view; a learned matcher
    caches its per-image features itself); ``with_sift`` adds the SIFT matches to a learned
    matcher's. O(V^2 matcher)."""
    use_sift = matcher is None or with_sift
    features = [view_features(f, p) for f, p in zip(frames, pointmaps)] if use_sift else None
    out = []
    for a in range(len(frames)):
        for b in range(a + 1, len(frames)):
            parts = []
            if matcher is not None:
                parts.append(matcher.match(frames[a], pointmaps[a], frames[b], pointmaps[b]))
            if use_sift:
                parts.append(match_view_features(features[a], features[b]))
            m: FeatureMatches = parts[0] if len(parts) == 1 else FeatureMatches.concatenate(
                parts, [0] * len(parts), [0] * len(parts), parts[0].n_keypoints)
            distance = np.maximum(np.linalg.norm(m.points_a, axis=1), np.linalg.norm(m.points_b, axis=1))
            out.append(PairMatches(a, b, m.points_a, m.points_b, distance, (a < n_start) != (b < n_start),
                                   tuple(m.n_keypoints)))
    return out


# ----------------------------------------------------------------------------- robust fits


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def _matrix_scale(matrix: np.ndarray) -> float:
    return float(np.cbrt(abs(np.linalg.det(matrix[:3, :3]))))


@dataclass
class _Pool:
    """Matches between two components, in the components' frames: x_a ~ T x_b."""

    source: np.ndarray        # component-b frame
    target: np.ndarray        # component-a frame
    distance: np.ndarray      # in component-a units
    cross: np.ndarray         # (K,) bool
    pairs: list[tuple[int, int]]

    def __len__(self) -> int:
        return int(self.source.shape[0])


def _pool(pairs: list[PairMatches], members_a: set[int], members_b: set[int], poses: list[np.ndarray]) -> _Pool:
    source, target, distance, cross, used = [], [], [], [], []
    for p in pairs:
        if p.a in members_a and p.b in members_b:
            ia, pa, ib, pb = p.a, p.points_a, p.b, p.points_b
        elif p.b in members_a and p.a in members_b:
            ia, pa, ib, pb = p.b, p.points_b, p.a, p.points_a
        else:
            continue
        if len(pa) == 0:
            continue
        target.append(_apply(poses[ia], pa))
        source.append(_apply(poses[ib], pb))
        distance.append(p.distance * _matrix_scale(poses[ia]))
        cross.append(np.full(len(pa), p.cross))
        used.append((ia, ib))
    if not source:
        z = np.zeros((0, 3))
        return _Pool(z, z, np.zeros(0), np.zeros(0, bool), [])
    return _Pool(np.concatenate(source), np.concatenate(target), np.concatenate(distance),
                 np.concatenate(cross), used)


@dataclass
class _Fit:
    model: Similarity
    inliers: np.ndarray
    rho: float
    rmse: float

    @property
    def support(self) -> int:
        return int(self.inliers.sum())


def _robust_fit(source: np.ndarray, target: np.ndarray, distance: np.ndarray, *, with_scale: bool, size: float,
                seed: int, min_inliers: int = 6, rho: float | None = None) -> _Fit:
    """RANSAC target ~ T source with depth-growing thresholds: loose first (``RHO_MAX``), then the
    noise level re-estimated from the inliers (:func:`~sparseart.align.noise.estimate_rho`) and the
    inliers refitted twice at that level; a fixed ``rho`` skips the estimate. O(2000 K)."""
    start_rho = RHO_MAX if rho is None else rho
    subset = np.arange(len(source))
    if subset.size > RANSAC_MAX_MATCHES:   # hypotheses scored on an even subset, refitted on all
        subset = subset[np.linspace(0, subset.size - 1, RANSAC_MAX_MATCHES).astype(int)]
    model, _ = ransac_similarity(source[subset], target[subset], with_scale=with_scale,
                                 threshold=thresholds(distance[subset], size, start_rho), seed=seed,
                                 iterations=RANSAC_ITERATIONS,
                                 min_inliers=max(3, int(np.ceil(min_inliers * subset.size / len(source)))))
    inliers = np.linalg.norm(model.apply(source) - target, axis=1) < thresholds(distance, size, start_rho)
    level = start_rho
    for _ in range(2):
        residuals = np.linalg.norm(model.apply(source) - target, axis=1)
        if rho is None:
            level = estimate_rho(residuals, distance, inliers)
        updated = residuals < thresholds(distance, size, level)
        if updated.sum() < max(3, min_inliers):
            break
        inliers = updated
        model = umeyama(source[inliers], target[inliers], with_scale)
    residuals = np.linalg.norm(model.apply(source) - target, axis=1)
    inliers = residuals < thresholds(distance, size, level)
    if inliers.sum() < max(3, min_inliers):
        raise AlignmentError(f"consensus of only {int(inliers.sum())} of {len(source)} matches")
    rmse = float(np.sqrt(np.mean(residuals[inliers] ** 2)))
    return _Fit(model, inliers, level, rmse)


# ----------------------------------------------------------------------------- dense check


class _Surfaces:
    """What each view saw, for free-space checks: the nearest seen distance per pixel (5 x 5
    minimum, grazing surfaces change quickly), its empty background (7 x 7 dilation of the invalid
    pixels), an evenly subsampled cloud of its own points and, when the frame has a mask, which
    pixels are the object (mask > 0, dilated 3 px) and which samples lie on it. Views without K are
    not checked."""

    SAMPLE = 2000
    MIN_INSIDE = 50

    def __init__(self, frames: list[Frame], maps: list[Pointmap], clouds: list[np.ndarray]) -> None:
        import cv2

        self.views = []
        for frame, pointmap, cloud in zip(frames, maps, clouds):
            if frame.camera is None or len(cloud) == 0:
                self.views.append(None)
                continue
            h, w = pointmap.height, pointmap.width
            valid = pointmap.valid.reshape(h, w) & np.isfinite(pointmap.points).all(axis=1).reshape(h, w)
            distance = np.where(valid, np.linalg.norm(np.nan_to_num(pointmap.points), axis=1).reshape(h, w), np.inf)
            nearest = cv2.erode(distance.astype(np.float32), np.ones((5, 5), np.uint8)).astype(np.float64)
            background = cv2.dilate(valid.astype(np.uint8), np.ones((7, 7), np.uint8)) == 0
            pixels = np.flatnonzero(valid.reshape(-1))
            pixels = pixels[np.linspace(0, len(pixels) - 1, min(self.SAMPLE, len(pixels))).astype(int)]
            sample = pointmap.points[pixels]
            mask = getattr(frame, "mask", None)
            if mask is not None and np.shape(mask) == (h, w) and 0 < np.count_nonzero(mask) < mask.size:
                on_object = np.asarray(mask).reshape(-1)[pixels] > 0
                obj = cv2.dilate((np.asarray(mask) > 0).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
            else:
                on_object, obj = None, None
            self.views.append((frame.camera.K, nearest, background, sample, on_object, obj))

    def seen_through(self, a: int, b: int, b_to_a: np.ndarray, size: float, rho: float) -> tuple[int, int, int, int, int]:
        """(points of view b that land in view a's image, those of them in front of what a saw by
        more than twice their threshold or on a's empty background, those within twice their
        threshold of what a saw, b's sampled object points (0 without masks), those of them that land
        on a's object within twice their threshold); b_to_a maps b's camera frame into a's. O(SAMPLE)."""
        if self.views[a] is None or self.views[b] is None:
            return 0, 0, 0, 0, 0
        K, nearest, background, _, _, object_a = self.views[a]
        on_object = self.views[b][4] if object_a is not None else None
        local = apply_transform(b_to_a, self.views[b][3])
        front = local[:, 2] > 1e-9
        h, w = nearest.shape
        uv = local @ K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            col = np.rint(np.where(front, uv[:, 0] / uv[:, 2], -1)).astype(int)
            row = np.rint(np.where(front, uv[:, 1] / uv[:, 2], -1)).astype(int)
        inside = front & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        objects = int(on_object.sum()) if on_object is not None else 0
        if inside.sum() < self.MIN_INSIDE:
            return 0, 0, 0, objects, 0
        reach = np.linalg.norm(local[inside], axis=1)
        seen = nearest[row[inside], col[inside]]
        limit = 2.0 * thresholds(reach, size, rho)
        bad = background[row[inside], col[inside]] | (np.isfinite(seen) & (reach < seen - limit))
        agree = np.isfinite(seen) & (np.abs(reach - seen) <= limit)
        object_agree = 0
        if on_object is not None:
            object_agree = int((agree & on_object[inside] & object_a[row[inside], col[inside]]).sum())
        return int(inside.sum()), int(bad.sum()), int(agree.sum()), objects, object_agree


@dataclass
class _Dense:
    """Free-space numbers of a merge (see :func:`_violations`); None where no view pair overlaps."""

    within_seen_through: float | None = None
    within_agreement: float | None = None
    across_seen_through: float | None = None
    within_object_agreement: float | None = None


def _violations(surfaces: _Surfaces, members_a: set[int], members_b: set[int], poses: list[np.ndarray],
                b_to_a: np.ndarray, n_start: int, size: float, rho: float) -> _Dense:
    """Free-space numbers of a merge, pooled over the view pairs per direction (b's points into
    a's views, and a's into b's). Views of the same state: the LARGER seen-through share of the two
    directions (a rigid scene must pass both), the SMALLER share of sampled points that land on the
    other view's surface (a transform that pushes a view out of sight or behind the walls explains
    nothing) and, with masks, the SMALLER share of object points that land on the other view's
    object (repetitive walls and floors can agree with a shifted view; the object then does not).
    Across the states: the SMALLER seen-through share (the moving part sweeps through space one
    state saw as empty, in one direction only)."""
    counts = {(same, d): np.zeros(6) for same in (True, False) for d in (0, 1)}
    for a in members_a:
        for b in members_b:
            same = (a < n_start) == (b < n_start)
            forward = np.linalg.inv(poses[a]) @ b_to_a @ poses[b]
            for direction, (x, y, t) in enumerate(((a, b, forward), (b, a, np.linalg.inv(forward)))):
                numbers = surfaces.seen_through(x, y, t, size, rho)
                total = len(surfaces.views[y][3]) if surfaces.views[y] is not None else 0
                counts[(same, direction)] += (*numbers[:3], total, *numbers[3:])

    def share(same: bool, index: int, total: int, pick) -> float | None:
        values = [c[index] / c[total] for (s, _), c in counts.items() if s == same and c[0] and c[total]]
        return float(pick(values)) if values else None

    return _Dense(share(True, 1, 0, max), share(True, 2, 3, min), share(False, 1, 0, min), share(True, 5, 4, min))


# ----------------------------------------------------------------------------- components


@dataclass
class _Merge:
    a: int                 # component ids (a keeps its frame)
    b: int
    fit: _Fit
    pool: _Pool

    @property
    def support(self) -> int:
        return self.fit.support


class _Components:
    def __init__(self, n: int) -> None:
        self.of = list(range(n))
        self.poses = [np.eye(4) for _ in range(n)]   # view camera -> its component's frame

    def members(self, c: int) -> set[int]:
        return {v for v in range(len(self.of)) if self.of[v] == c}

    def ids(self) -> list[int]:
        return sorted(set(self.of))

    def merge(self, a: int, b: int, b_to_a: np.ndarray) -> None:
        for v in self.members(b):
            self.poses[v] = b_to_a @ self.poses[v]
            self.of[v] = a


def _hypotheses(pool: _Pool, *, with_scale: bool, size: float, seed: int, count: int) -> list[_Fit]:
    """Up to ``count`` transforms of a pool by sequential robust fits (each on the matches the
    earlier ones left over; support counted over the whole pool), strongest first. Repetitive
    texture (tiles, bricks) gives a shifted transform more support than the true one; the dense
    check of :func:`_try_merge` then decides between them."""
    out: list[_Fit] = []
    remaining = np.arange(len(pool))
    for k in range(count):
        if remaining.size < MIN_MERGE_INLIERS:
            break
        try:
            fit = _robust_fit(pool.source[remaining], pool.target[remaining], pool.distance[remaining],
                              with_scale=with_scale, size=size, seed=seed + k, min_inliers=MIN_MERGE_INLIERS)
        except AlignmentError:
            break
        residuals = np.linalg.norm(fit.model.apply(pool.source) - pool.target, axis=1)
        inliers = residuals < thresholds(pool.distance, size, fit.rho)
        out.append(_Fit(fit.model, inliers, fit.rho, float(np.sqrt(np.mean(residuals[inliers] ** 2)))))
        remaining = remaining[~inliers[remaining]]
    return sorted(out, key=lambda f: -f.support)


def _try_merge(ctx: "_Context", comps: _Components, a: int, b: int) -> tuple[_Merge | None, str]:
    """The transform b -> a of two components from their pooled matches, or (None, why).

    The strongest of ``HYPOTHESES`` sequential fits that passes the checks wins: enough inliers
    (``MIN_MERGE_INLIERS``, and ``MIN_MERGE_FRACTION`` of the pool unless the dense check below
    vouches for it), not degenerate, and -- where views of the same state meet -- no more than
    ``MAX_WITHIN_SEEN_THROUGH`` of either view's points in space the other one saw through."""
    size, members_a, members_b = ctx.size, comps.members(a), comps.members(b)
    pool = _pool(ctx.pairs, members_a, members_b, comps.poses)
    if len(pool) < MIN_MERGE_INLIERS:
        return None, f"too few matches ({len(pool)})"
    fits = _hypotheses(pool, with_scale=ctx.relative, size=size, seed=ctx.seed, count=HYPOTHESES)
    if not fits:
        return None, f"no consistent transform among {len(pool)} matches"
    why = ""
    judged = []
    for fit in fits:
        extent = spread(pool.target[fit.inliers])
        if extent[1] < DEGENERATE_FRACTION * size:
            why = why or (f"degenerate matches: the {fit.support} inliers are collinear or in a tiny region "
                          f"(spread {extent[0]:.3g} x {extent[1]:.3g}, scene size {size:.3g})")
            continue
        dense = _violations(ctx.surfaces, members_a, members_b, comps.poses, fit.model.matrix(), ctx.n_start,
                            size, fit.rho)
        problem = ""
        within = dense.within_seen_through
        if within is not None and within > MAX_WITHIN_SEEN_THROUGH:
            problem = (f"the best transform ({fit.support} of {len(pool)} matches) puts {within:.0%} of the "
                       f"points where another view of the state sees through (repetitive texture?)")
        elif dense.within_agreement is not None and dense.within_agreement < MIN_WITHIN_AGREEMENT:
            problem = (f"the best transform ({fit.support} of {len(pool)} matches) lays only "
                       f"{dense.within_agreement:.0%} of a view's points on the other views' surfaces")
        elif dense.within_object_agreement is not None and dense.within_object_agreement < MIN_OBJECT_AGREEMENT:
            problem = (f"the best transform ({fit.support} of {len(pool)} matches) lays only "
                       f"{dense.within_object_agreement:.0%} of the object (masks) on the object of the other views")
        judged.append((fit, dense, problem))
    for fit, dense, problem in judged:
        if problem:
            why = why or problem
            continue
        verified = dense.within_seen_through is not None
        need = MIN_MERGE_INLIERS if verified else max(MIN_MERGE_INLIERS, int(np.ceil(MIN_MERGE_FRACTION * len(pool))))
        if fit.support < need:
            why = why or f"consensus of only {fit.support} of {len(pool)} matches (need {need})"
            continue
        same_state = ~pool.cross
        if (verified and dense.within_object_agreement is None and same_state.any()
                and fit.inliers[same_state].mean() < MIN_WITHIN_SHARE):
            why = why or (f"only {int(fit.inliers[same_state].sum())} of {int(same_state.sum())} matches between "
                          f"views of one state agree (need {MIN_WITHIN_SHARE:.0%})")
            continue
        if verified:   # views of one state meet: the transform must stand out among the plausible ones
            rivals = [other.support for other, _, trouble in judged
                      if other is not fit and not trouble and not _same_transform(other.model, fit.model, size)]
            if rivals and fit.support < UNIQUE_RATIO * max(rivals):
                why = why or (f"ambiguous: two different transforms both fit ({fit.support} and {max(rivals)} of "
                              f"{len(pool)} matches; repetitive texture?)")
                return None, why
        return _Merge(a, b, fit, pool), ""
    return None, why


def _same_transform(a: Similarity, b: Similarity, size: float) -> bool:
    """Two transforms that differ by less than 2 deg and 2 % of the scene size (near-duplicate
    hypotheses of one sequential fit)."""
    relative = a.rotation.T @ b.rotation
    angle = float(np.degrees(rotation_angle(relative)))
    return angle < 2.0 and float(np.linalg.norm(a.translation - b.translation)) < THRESHOLD_FRACTION * size


def _grow(ctx: "_Context", reasons: dict[int, list[str]], across: bool = True) -> tuple[_Components, dict]:
    """Agglomerative merging: within-state merges first, then (``across``) any, largest consensus
    first. Returns the components and the numbers of the first merge across the states."""
    n, n_start = len(ctx.frames), ctx.n_start
    comps = _Components(n)
    state_of = [0 if v < n_start else 1 for v in range(n)]

    def states(c: int) -> set[int]:
        return {state_of[v] for v in comps.members(c)}

    first_cross: dict = {}
    for phase in ("within", "any") if across else ("within",):
        cache: dict[tuple[int, int], tuple[_Merge | None, str]] = {}
        while True:
            ids = comps.ids()
            best: _Merge | None = None
            for i, a in enumerate(ids):
                for b in ids[i + 1:]:
                    if phase == "within" and len(states(a) | states(b)) > 1:
                        continue
                    if (a, b) not in cache:
                        cache[(a, b)] = _try_merge(ctx, comps, a, b)
                    merge = cache[(a, b)][0]
                    if merge is not None and (best is None or merge.support > best.support):
                        best = merge
            if best is None:
                break
            if not first_cross and len(states(best.a) | states(best.b)) > 1:
                first_cross = {"matches": len(best.pool), "inliers": best.support, "rmse": best.fit.rmse}
            # The component holding the lowest view keeps its frame (view 0's frame in the end).
            if min(comps.members(best.a)) < min(comps.members(best.b)):
                comps.merge(best.a, best.b, best.fit.model.matrix())
            else:
                comps.merge(best.b, best.a, best.fit.model.inverse().matrix())
            cache = {k: v for k, v in cache.items() if not ({k[0], k[1]} & {best.a, best.b})}
        for (a, b), (merge, why) in cache.items():
            if merge is None and why:
                for v in comps.members(a) | comps.members(b):
                    reasons[v].append(why)
    return comps, first_cross


# ----------------------------------------------------------------------------- joint least squares


def _edges_for(pairs: list[PairMatches], views: list[int], poses: list[np.ndarray], size: float, rho: float,
               slack: float = 2.0) -> list[tuple[PairMatches, np.ndarray]]:
    """Each pair within ``views`` with its matches under ``slack`` x threshold at ``poses``."""
    chosen = set(views)
    out = []
    for p in pairs:
        if p.a not in chosen or p.b not in chosen or len(p.points_a) == 0:
            continue
        residual = np.linalg.norm(_apply(poses[p.a], p.points_a) - _apply(poses[p.b], p.points_b), axis=1)
        keep = residual < slack * thresholds(p.distance * _matrix_scale(poses[p.a]), size, rho)
        if keep.sum() >= 3:
            out.append((p, keep))
    return out


def _skew(q: np.ndarray) -> np.ndarray:
    """(K, 3) vectors -> (K, 3, 3) cross-product matrices [q]x."""
    out = np.zeros((q.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -q[:, 2], q[:, 1], -q[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = q[:, 2], -q[:, 1], q[:, 0]
    return out


def _joint_solve(pairs: list[PairMatches], views: list[int], anchor: int, poses: list[np.ndarray], *,
                 size: float, rho: float, scale_mode: str, iterations: int = 30) -> list[np.ndarray]:
    """Robust least squares over all poses of ``views`` (``anchor`` fixed) from their pairs' matches
    within twice their threshold: iteratively reweighted Gauss-Newton on the SE(3) / Sim(3) tangent
    (rotation vector, translation, log scale per view; X = s R p + t, updates R <- exp(w) R), residuals
    divided by half their threshold, soft-L1 weights 1 / sqrt(1 + r^2). scale_mode "fixed" (rigid),
    "prior" (metric depth: log scale ~ N(0, SCALE_PRIOR), bounded by +-SCALE_LIMIT) or "free"
    (relative depth). At most ``MAX_SOLVE_MATCHES`` matches per pair (evenly strided).
    O(iterations (M + (7 V)^3)) for M matches and V views."""
    from scipy.spatial.transform import Rotation

    free = [v for v in views if v != anchor]
    if not free:
        return poses
    edges = _edges_for(pairs, views, poses, size, rho)
    if not edges:
        return poses
    slot = {v: i for i, v in enumerate(free)}
    per = 6 if scale_mode == "fixed" else 7
    scale = {v: _matrix_scale(poses[v]) for v in views}
    rotation = {v: poses[v][:3, :3] / scale[v] for v in views}
    translation = {v: poses[v][:3, 3].copy() for v in views}
    data = []
    for p, keep in edges:
        index = np.flatnonzero(keep)
        if index.size > MAX_SOLVE_MATCHES:
            index = index[np.linspace(0, index.size - 1, MAX_SOLVE_MATCHES).astype(int)]
        sigma = 0.5 * thresholds(p.distance[index] * scale[p.a], size, rho)
        data.append((p.a, p.b, p.points_a[index], p.points_b[index], sigma))
    n = per * len(free)
    for _ in range(iterations):
        hessian, gradient = np.zeros((n, n)), np.zeros(n)
        for a, b, pa, pb, sigma in data:
            qa = scale[a] * pa @ rotation[a].T
            qb = scale[b] * pb @ rotation[b].T
            error = ((qa + translation[a]) - (qb + translation[b])) / sigma[:, None]
            weight = 1.0 / np.sqrt(1.0 + np.sum(error ** 2, axis=1))
            blocks = []
            for v, q, sign in ((a, qa, 1.0), (b, qb, -1.0)):
                if v == anchor:
                    continue
                jac = np.zeros((len(q), 3, per))
                jac[:, :, :3] = -_skew(q)
                jac[:, :, 3:6] = np.eye(3)
                if per == 7:
                    jac[:, :, 6] = q
                blocks.append((slot[v], sign * jac / sigma[:, None, None]))
            for i, ji in blocks:
                gradient[i * per:(i + 1) * per] += np.einsum("k,kri,kr->i", weight, ji, error)
                for j, jj in blocks:
                    hessian[i * per:(i + 1) * per, j * per:(j + 1) * per] += np.einsum("k,kri,krj->ij", weight, ji, jj)
        if scale_mode == "prior":
            for v in free:
                k = slot[v] * per + 6
                hessian[k, k] += 1.0 / SCALE_PRIOR ** 2
                gradient[k] += np.log(scale[v]) / SCALE_PRIOR ** 2
        hessian[np.diag_indices(n)] += 1e-9 + 1e-6 * np.diag(hessian)
        try:
            step = -np.linalg.solve(hessian, gradient)
        except np.linalg.LinAlgError:
            break
        for v in free:
            d = step[slot[v] * per:(slot[v] + 1) * per]
            rotation[v] = Rotation.from_rotvec(d[:3]).as_matrix() @ rotation[v]
            translation[v] = translation[v] + d[3:6]
            if per == 7:
                log_scale = float(np.log(scale[v]) + d[6])
                if scale_mode == "prior":
                    log_scale = float(np.clip(log_scale, -SCALE_LIMIT, SCALE_LIMIT))
                scale[v] = float(np.exp(log_scale))
        if np.max(np.abs(step)) < 1e-7 * max(1.0, size):
            break
    out = list(poses)
    for v in free:
        matrix = np.eye(4)
        matrix[:3, :3] = scale[v] * rotation[v]
        matrix[:3, 3] = translation[v]
        out[v] = matrix
    return out


# ----------------------------------------------------------------------------- motion candidates


def motion_candidates(points_a: np.ndarray, points_b_in_a: np.ndarray, limits: np.ndarray, total: int,
                      size: float, seed: int, max_candidates: int) -> list:
    """Sequential RANSAC of rigid start -> end motions (frame a) among the static part's outliers,
    per-match thresholds ``limits``; support >= max(8, 3 % of ``total`` matches); collinear sets are
    skipped. Returns :class:`~sparseart.align.states.MotionCandidate` strongest first."""
    from sparseart.align.states import MotionCandidate

    min_support = max(8, int(np.ceil(0.03 * total)))
    remaining = np.arange(points_a.shape[0])
    out = []
    for attempt in range(4 * max_candidates):
        if len(out) >= max_candidates or remaining.size < min_support:
            break
        try:
            model, inliers = ransac_similarity(points_a[remaining], points_b_in_a[remaining], with_scale=False,
                                               threshold=limits[remaining], seed=seed + 1 + attempt,
                                               min_inliers=min_support)
        except AlignmentError:
            break
        chosen = remaining[inliers]
        remaining = remaining[~inliers]
        if spread(points_a[chosen])[1] >= DEGENERATE_FRACTION * size:
            out.append(MotionCandidate(model.matrix(), int(chosen.size), points_a[chosen].copy()))
    return sorted(out, key=lambda c: -c.support)


# ----------------------------------------------------------------------------- the whole scene


def register_scene(frames: dict[str, list[Frame]], pointmaps: dict[str, list[Pointmap]], *, relative: bool = False,
                   seed: int = 0, matcher=None, geometry_fallback: bool = True, polish: bool = True,
                   max_candidates: int = 6) -> SceneRegistration:
    """Register every view of both states into the camera frame of the reference start view: the
    first, unless it lies apart from a larger group of views (:func:`_finish_from_the_best_reference`).

    Args:
        frames, pointmaps: {"start": [...], "end": [...]}; each pointmap in its view's OWN camera frame.
        relative: the depth has an unknown scale per view (free per-view scale); otherwise metric
            depth (rigid merges, per-view scale only with the ``SCALE_PRIOR`` prior).
        seed: seed of every RANSAC.
        matcher: a pair matcher (``match(frame_a, pointmap_a, frame_b, pointmap_b) ->
            FeatureMatches``, :class:`sparseart.align.matchers.LiftedMatcher`); None = SIFT.
        geometry_fallback: metric views no feature merge reaches get the geometric registration.
        polish: point-to-plane ICP of each view against the other views of its state (metric).

    Returns:
        :class:`SceneRegistration`. Views that cannot be registered have pose None (named in the
        warnings); the reference start view (``SceneRegistration.reference``) has the identity.
        O(V^2 (matcher + 2000 K)).
    """
    all_frames = list(frames["start"]) + list(frames["end"])
    all_maps = list(pointmaps["start"]) + list(pointmaps["end"])
    n_start, n = len(frames["start"]), len(all_frames)
    if n_start == 0 or len(all_maps) != n:
        raise ValueError("register_scene needs at least one start view and one pointmap per frame")
    clouds = [valid_points(p) for p in all_maps]
    size = scene_size(np.concatenate([c for c in clouds if len(c)] or [np.zeros((1, 3))]))
    began = time.perf_counter()
    pairs = _match_all(all_frames, all_maps, n_start, matcher, with_sift=WITH_SIFT)
    seconds = {"match": time.perf_counter() - began}
    reasons: dict[int, list[str]] = {v: [] for v in range(n)}
    for p in pairs:
        if len(p.points_a) < MIN_PAIR_MATCHES:
            reasons[p.a].append(f"{len(p.points_a)} feature matches with {all_frames[p.b].image}")
            reasons[p.b].append(f"{len(p.points_a)} feature matches with {all_frames[p.a].image}")
    began = time.perf_counter()
    roughness = [depth_roughness(p) for p in all_maps]
    roughness = float(np.nanmedian(roughness)) if np.isfinite(roughness).any() else float("nan")
    context = _Context(all_frames, all_maps, clouds, pairs, n_start, size, seed, relative, geometry_fallback,
                       polish, max_candidates, _Surfaces(all_frames, all_maps, clouds), roughness)
    comps, first_cross = _grow(context, reasons)
    seconds["merge"] = time.perf_counter() - began
    result = _finish_from_the_best_reference(context, comps, reasons, seconds)
    result.states["first_merge"] = first_cross
    if result.states.get("untrusted"):
        # The states were merged but the alignment is not trusted: register each state on its own,
        # so no view is placed through the untrusted cross-state matches.
        comps, _ = _grow(context, {v: [] for v in range(n)}, across=False)
        alone = _finish_from_the_best_reference(context, comps, reasons, seconds, allow_aligned=False)
        alone.warnings = [w for w in result.warnings if "not trusted" in w] + alone.warnings
        alone.states = result.states
        result = alone
    return result


@dataclass
class _Context:
    frames: list[Frame]
    maps: list[Pointmap]
    clouds: list[np.ndarray]
    pairs: list[PairMatches]
    n_start: int
    size: float
    seed: int
    relative: bool
    geometry_fallback: bool
    polish: bool
    max_candidates: int
    surfaces: _Surfaces
    roughness: float


def _finish_from_the_best_reference(ctx: _Context, comps: _Components, reasons: dict[int, list[str]],
                                   seconds: dict[str, float], allow_aligned: bool = True) -> SceneRegistration:
    """:func:`_finish` from the first start view's component; again from the largest component
    holding a start view when that one holds more views than the first registered in the end
    (geometric fallback included), kept when it registers more. Why: a view that matches none of
    the others (a plain white fridge seen from its side, the two other views of each state from
    the front) left the other four views of the scene out with it, and the door unseen (realistic
    fridge, seed 3: door unmatched; from the group of four, 3.0 deg). Taking the largest group
    every time placed view 0 by geometry instead, in scenes where the geometric fallback had
    placed the others, and moved six realistic joints both ways (a faucet 2.2 -> 10.8 deg). At
    most one more :func:`_finish`, only in those scenes."""
    result = _finish(ctx, comps, reasons, seconds, allow_aligned=allow_aligned)
    first = comps.of[0]
    largest = max({comps.of[g] for g in range(ctx.n_start)},
                  key=lambda c: (len(comps.members(c)), -min(comps.members(c))))
    if largest == first or len(comps.members(largest)) <= _registered(result):
        return result
    other = _finish(ctx, comps, reasons, seconds, allow_aligned=allow_aligned, reference=largest)
    if _registered(other) <= _registered(result):
        return result
    anchor = other.reference
    other.warnings.insert(0, f"{ctx.frames[0].image} could not be registered to the larger group of views; results "
                             f"are in the OpenCV frame of {ctx.frames[anchor].image} instead")
    return other


def _registered(registration: SceneRegistration) -> int:
    """How many views of both states ``registration`` placed."""
    return sum(pose is not None for state in ("start", "end") for pose in registration.poses[state])


def _finish(ctx: _Context, comps: _Components, reasons: dict[int, list[str]], seconds: dict[str, float],
            allow_aligned: bool = True, reference: int | None = None) -> SceneRegistration:
    """Components -> poses: joint solve per group, geometric fallback, ICP polish, state checks.
    ``reference``: the component whose lowest (start) view gives the frame (None: the first start
    view's). Adds the wall seconds of each step to ``seconds``."""
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        seconds[name] = seconds.get(name, 0.0) + now - clock
        clock = now

    n, n_start, frames = len(ctx.frames), ctx.n_start, ctx.frames
    info = [ViewInfo("start" if g < n_start else "end", g if g < n_start else g - n_start, f.image)
            for g, f in enumerate(frames)]
    warnings: list[str] = []
    reference = comps.of[0] if reference is None else reference
    aligned = allow_aligned and any(comps.of[g] == reference for g in range(n_start, n))
    groups = [reference]
    if not aligned and n > n_start:
        end_groups = [comps.of[g] for g in range(n_start, n)]
        groups.append(max(end_groups, key=lambda c: (len(comps.members(c)), -min(comps.members(c)))))
    poses = list(comps.poses)
    rho = RHO_MAX
    registered: set[int] = set()
    # Per-view depth scale: free for relative depth; for metric depth only when the depth is noisy
    # (a reconstructor or sensor, whose scale is off by ~1 %); exact depth keeps its scale.
    scale_mode = "free" if ctx.relative else ("prior" if ctx.roughness > MAX_CLEAN_ROUGHNESS else "fixed")
    for c in groups:
        views = sorted(comps.members(c))
        anchor = views[0]
        to_anchor = np.linalg.inv(poses[anchor])
        for v in views:
            poses[v] = to_anchor @ poses[v]
        for _ in range(2):
            rho = _group_rho(ctx.pairs, views, poses, ctx.size)
            poses = _joint_solve(ctx.pairs, views, anchor, poses, size=ctx.size, rho=rho, scale_mode=scale_mode)
        # States left apart: the end group may hold start views the reference group did not reach
        # (merged across the states through the static part). Its frame is then that of its first
        # END view, and its start views are not placed by it (their frame is not the start frame).
        kept = views if c == reference else [v for v in views if v >= n_start]
        if kept and kept[0] != anchor:
            to_kept = np.linalg.inv(poses[kept[0]])
            for v in views:
                poses[v] = to_kept @ poses[v]
        registered |= set(kept)
        for v in kept:
            info[v].how = "reference" if v == kept[0] else "features"
    lap("solve")
    if not ctx.relative and ctx.geometry_fallback and all(f.camera is not None for f in frames):
        _geometry(frames, ctx.maps, ctx.clouds, poses, registered, info, n_start, ctx.size, ctx.seed, reasons,
                  warnings, noisy=ctx.roughness > MAX_CLEAN_ROUGHNESS)
    lap("geometry")
    for v in range(n):
        if v not in registered:
            why = "; ".join(dict.fromkeys(reasons[v])) or "no matches"
            info[v].reason = why[:400]
            warnings.append(f"{frames[v].image}: view could not be registered to the other views "
                            f"({why[:400]}); it is left out")
    if ctx.polish and not ctx.relative and not ctx.roughness > MAX_CLEAN_ROUGHNESS:
        _polish(frames, ctx.clouds, poses, registered, info, n_start, ctx.size, warnings)
    lap("polish")
    candidates: list = []
    if aligned:
        states, candidates = _check_states(ctx.pairs, poses, registered, frames, ctx.surfaces, n_start, ctx.size, rho,
                                           ctx.seed, ctx.max_candidates, warnings)
        aligned = states["trusted"]
    else:
        states = {"method": "none", "trusted": False, "matches": 0, "inliers": 0, "rmse": None,
                  "reason": "no consistent transform between the views of the two states"}
        if allow_aligned and n > n_start:
            warnings.append(f"feature alignment of the states failed (no consistent transform between the "
                            f"views of start and end: {_reason_text(reasons, range(n))}); registering them "
                            f"through the static part instead")
    if not aligned:
        candidates = []
    lap("check")
    _report_views(ctx.pairs, poses, registered, info, ctx.size, rho, aligned, n_start, ctx.relative)
    out_poses = {"start": [poses[g] if g in registered else None for g in range(n_start)],
                 "end": [poses[g] if g in registered else None for g in range(n_start, n)]}
    return SceneRegistration(out_poses, aligned, candidates, info, states, rho, warnings, seconds, ctx.roughness,
                             reference=min(comps.members(reference)))


def _reason_text(reasons: dict[int, list[str]], views) -> str:
    text = "; ".join(dict.fromkeys(r for v in views for r in reasons[v]))
    return text[:400] if text else "no matches"


def _group_rho(pairs: list[PairMatches], views: list[int], poses: list[np.ndarray], size: float) -> float:
    """Noise level of a group at its current poses: within-state pairs only (the whole scene is
    rigid there), starting loose."""
    chosen = set(views)
    residual, distance = [], []
    for p in pairs:
        if p.cross or p.a not in chosen or p.b not in chosen or len(p.points_a) == 0:
            continue
        residual.append(np.linalg.norm(_apply(poses[p.a], p.points_a) - _apply(poses[p.b], p.points_b), axis=1))
        distance.append(p.distance * _matrix_scale(poses[p.a]))
    if not residual:
        for p in pairs:   # single view per state: the cross pairs (static inliers only) decide
            if p.a in chosen and p.b in chosen and len(p.points_a):
                residual.append(np.linalg.norm(_apply(poses[p.a], p.points_a) - _apply(poses[p.b], p.points_b), axis=1))
                distance.append(p.distance * _matrix_scale(poses[p.a]))
    if not residual:
        return RHO_MAX
    r, d = np.concatenate(residual), np.concatenate(distance)
    return estimate_rho(r, d, r < thresholds(d, size, RHO_MAX))


def _geometry(frames, maps, clouds, poses, registered, info, n_start, size, seed, reasons, warnings,
              noisy: bool = False) -> None:
    """Metric views no feature merge reached: the geometric registration to a registered view of
    their state (best edge weight wins), composed with that view's pose. Plain fits first, round
    after round (a view placed by geometry can reach the views tried before it); the mask ids'
    search (:class:`~sparseart.align.geometric.GeometricEdges`) only when no plain fit places any
    view, and then plain fits again from what it placed. ``noisy`` (depth rougher than
    ``MAX_CLEAN_ROUGHNESS``): plain fits may see through ``NOISY_MAX_FREE_SPACE_VIOLATION`` and
    are not polished at full resolution."""
    if len(registered) == len(frames):
        return
    edges = GeometricEdges(frames, maps, clouds, seed, [view_mask_ids(f, m) for f, m in zip(frames, maps)],
                           NOISY_MAX_FREE_SPACE_VIOLATION if noisy else MAX_FREE_SPACE_VIOLATION, polish=not noisy)
    # the size of each state's own views (the other state's moved part would change it)
    sizes = {}
    for is_start in (True, False):
        own = [clouds[u] for u in range(len(frames)) if (u < n_start) == is_start and len(clouds[u])]
        sizes[is_start] = scene_size(np.concatenate(own)) if own else size
    while _place_by_geometry(edges.plain, frames, poses, registered, info, n_start, sizes, warnings) or \
            _place_by_geometry(edges.searched, frames, poses, registered, info, n_start, sizes, warnings,
                               edges.notes):
        pass
    for v in range(len(frames)):
        if v not in registered:
            reasons[v].append("geometric registration rejected (planar, little overlap or sees through)")


def _place_by_geometry(edge_of, frames, poses, registered, info, n_start, sizes: dict[bool, float], warnings,
                       notes: dict | None = None) -> bool:
    """One pass over the unregistered views in order: each goes where its best edge to a registered
    view of its state (``edge_of(v, u, size of that state)``; ``sizes`` keyed by "is a start
    view") puts it; ``notes[v, u]`` joins the warning. True when a view was placed."""
    placed = False
    for v in range(len(frames)):
        if v in registered:
            continue
        same = [u for u in sorted(registered) if (u < n_start) == (v < n_start)]
        # the edges to every registered view side by side (each a pure function of the two views)
        edges = in_parallel(lambda u: edge_of(v, u, sizes[v < n_start]), same)
        found = [(u, edge) for u, edge in zip(same, edges) if edge is not None]
        if not found:
            continue
        u, (transform, overlap, _) = max(found, key=lambda item: item[1][2])
        poses[v] = poses[u] @ transform
        registered.add(v)
        placed = True
        info[v].how = "geometry"
        note = f"; {notes[v, u]}" if notes and (v, u) in notes else ""
        warnings.append(f"{frames[v].image}: registered to {frames[u].image} by geometry only, "
                        f"{overlap:.0%} overlap{note}")
    return placed


def _polish(frames, clouds, poses, registered, info, n_start, size, warnings) -> None:
    """Point-to-plane ICP of each registered view against the other registered views of its state
    (in view order); kept when it raises the overlap."""
    for state_views in ([v for v in sorted(registered) if v < n_start], [v for v in sorted(registered) if v >= n_start]):
        if len(state_views) < 2:
            continue
        placed = [apply_transform(poses[state_views[0]], clouds[state_views[0]])]
        for v in state_views[1:]:
            target = np.concatenate(placed)
            scale = _matrix_scale(poses[v])
            if spread(target)[2] < PLANAR_FRACTION * size or spread(clouds[v])[2] < PLANAR_FRACTION * size:
                warnings.append(f"{frames[v].image}: ICP polish on a planar cloud may slide along the plane")
            scaled = clouds[v] * scale
            init = poses[v].copy()
            init[:3, :3] /= scale
            polished = icp_polish(scaled, target, init, THRESHOLD_FRACTION * size)
            if polished is not None:
                polished = np.array(polished, dtype=np.float64)
                polished[:3, :3] *= scale
                poses[v] = polished
            placed.append(apply_transform(poses[v], clouds[v]))


def _check_states(pairs, poses, registered, frames, surfaces, n_start, size, rho, seed, max_candidates, warnings):
    """Numbers and checks of the state alignment at the final poses (module docstring, step 6)."""
    pa_all, pb_all, limits = [], [], []
    total = 0
    for p in pairs:
        if not p.cross or p.a not in registered or p.b not in registered or len(p.points_a) == 0:
            continue
        start_side, end_side = (p.points_a, p.points_b) if p.a < n_start else (p.points_b, p.points_a)
        vs, ve = (p.a, p.b) if p.a < n_start else (p.b, p.a)
        pa_all.append(_apply(poses[vs], start_side))
        pb_all.append(_apply(poses[ve], end_side))
        limits.append(thresholds(p.distance * _matrix_scale(poses[vs]), size, rho))
        total += len(p.points_a)
    names = f"{', '.join(frames[v].image for v in range(n_start))} vs " \
            f"{', '.join(frames[v].image for v in range(n_start, len(frames)))}"
    if not pa_all:
        return {"method": "none", "trusted": False, "reason": "no matches across the states"}, []
    points_a, points_b, limit = np.concatenate(pa_all), np.concatenate(pb_all), np.concatenate(limits)
    residual = np.linalg.norm(points_a - points_b, axis=1)
    static = residual < limit
    n_static = int(static.sum())
    rmse = float(np.sqrt(np.mean(residual[static] ** 2))) if n_static else None
    candidates = motion_candidates(points_a[~static], points_b[~static], limit[~static], total, size, seed,
                                   max_candidates)
    extent = spread(points_a[static]) if n_static >= 3 else np.zeros(3)
    starts = {v for v in registered if v < n_start}
    ends = {v for v in registered if v >= n_start}
    seen_through = _violations(surfaces, starts, ends, poses, np.eye(4), n_start, size, rho).across_seen_through
    states = {"method": "features", "matches": int(total), "inliers": n_static, "rmse": rmse,
              "second_motion": int(candidates[0].support) if candidates else 0,
              "seen_through": seen_through, "trusted": True}
    problems = []
    if n_static < MIN_STATE_INLIERS:
        problems.append(f"only {n_static} of {total} matches on the static part (need {MIN_STATE_INLIERS})")
    if extent[1] < DEGENERATE_FRACTION * size:
        problems.append("the static matches are collinear or in a tiny region")
    if seen_through is not None and seen_through > MAX_SEEN_THROUGH:
        problems.append(f"{seen_through:.0%} of the end surfaces land where the start cameras see through "
                        f"(allowed {MAX_SEEN_THROUGH:.0%})")
    if problems:
        states.update(trusted=False, untrusted=True, method="none", reason="; ".join(problems))
        warnings.append(f"{names}: the feature alignment of the states is not trusted ({'; '.join(problems)}); "
                        f"registering them through the static part instead")
    elif candidates and candidates[0].support > AMBIGUOUS_RATIO * n_static:
        warnings.append(f"{names}: static part is ambiguous: a second motion has {candidates[0].support} "
                        f"matches vs {n_static} for the dominant one (the moving part may have won)")
    return states, candidates


def _report_views(pairs, poses, registered, info, size, rho, aligned, n_start, relative) -> None:
    """Per-view inliers (matches to other registered views that agree with the poses; across the
    states only when they are aligned) and their RMS residual; the per-view scale."""
    count = {v: 0 for v in range(len(info))}
    squares = {v: 0.0 for v in range(len(info))}
    for p in pairs:
        if p.a not in registered or p.b not in registered or len(p.points_a) == 0:
            continue
        if p.cross and not aligned:
            continue
        residual = np.linalg.norm(_apply(poses[p.a], p.points_a) - _apply(poses[p.b], p.points_b), axis=1)
        good = residual < thresholds(p.distance * _matrix_scale(poses[p.a]), size, rho)
        for v in (p.a, p.b):
            count[v] += int(good.sum())
            squares[v] += float(np.sum(residual[good] ** 2))
    for v, view in enumerate(info):
        if v not in registered:
            view.how = "unregistered"
            continue
        view.inliers = count[v]
        view.residual = float(np.sqrt(squares[v] / count[v])) if count[v] else None
        scale = _matrix_scale(poses[v])
        view.scale = 1.0 if (not relative and abs(scale - 1.0) < SCALE_REPORTED) else scale
