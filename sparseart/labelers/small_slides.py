"""Small parts slid along the static body's axes, sought after the motion layers (no masks).

The motion layers (:mod:`.motion_layers`) price a part by a share of all moved points, so a part
much smaller than its neighbours cannot pay for itself: an oven's wire racks slid out under two
opened doors hold 2-4 % of the moved points. Worse, a thin part slid within its own plane lands on
itself: most of a rack's start points lie near its own end points and read as static, so its
start side has almost no moved points to vote with.

Here each piece of the end state's leftovers (moved points, seen or unseen, in no layer; linked at
``LINK_RADII`` inlier radii) is tried on its own, against every start point in no layer:

* leftovers within one inlier radius of a layer's points of the same state are that layer's fringe
  (a door's far edge just outside the hit radius), not a part, and are set aside;
* for each axis of the static body's frame, both ways, the slide lengths d at which the piece's
  seen points, slid back by d, land on start points (:func:`~.motion_candidates.grouped_slide_votes`);
  the best few local peaks per axis are rated: hits (seen points landing within the hit radius),
  violations (landing where the start views saw through), partners (start points in no layer that
  the slide carries onto the piece's hits);
* the piece becomes a part with its slide of most hits when the hits are at least ``MIN_POINTS``
  and ``HIT_SHARE`` of its seen points, the partners at least ``MIN_POINTS``, the violations at
  most ``VIOLATION_SHARE`` of the points it lays down, and the slide carries the part at most
  :data:`~.motion_ratings.ANCHOR_MAX_SLIDE` radii of itself (:func:`~.motion_ratings.detached`);
  its points are the hits and their partners;
* parts with the same slide (within a hit radius) that touch (``TOUCH_RADII`` inlier radii) are one.

Measured (oven_7179_multi, clean posed renders, no masks): the three racks' pieces pick slides
within 0.01 object units of their true travels (0.212 / 0.159 / 0.349 for 0.215 / 0.162 / 0.351,
212-306 hits, no violation); the doors' leftovers (42-341 points) lie all within one inlier radius
of their doors' layers. Cost O(A (M log M + P log M + K)) for A = 3 axes, M start points, P
leftover points and K tube pairs, plus O(C log M) per rated peak of a piece of C points.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.clouds import radius_components
from .consistency import VIOLATION
from .motion_candidates import grouped_slide_votes
from .motion_ratings import Ratings, detached

MIN_POINTS = 30          # hits and partners a small part needs (the labeler's least segment)
HIT_SHARE = 0.5          # ... and this share of its piece's seen points must land on start points
VIOLATION_SHARE = 0.05   # at most this share of the points it lays down may land in seen free space
LINK_RADII = 2.0         # leftover points within this many inlier radii are one piece
TOUCH_RADII = 5.0        # parts with one slide this close (either state) are one part
PEAKS_PER_AXIS = 3       # local vote maxima rated per axis and piece
STAYED_MAX_SHARE = 0.9   # a part whose start points' places the end still fills more than this did not leave them
SEEN_THROUGH_SHARE = 0.65  # at least this share of its end points must lie where the start views saw through
LAYER_EXPLAINS_SHARE = 0.5  # a piece a larger part's motion lays this much of onto the start is that part's


def small_slides(ratings: Ratings, layers: list) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Small slid parts among the leftovers of the motion layers (module doc).

    ratings: the motion layers' ratings (work clouds, moved points, views, static frame);
    layers: the kept :class:`~.motion_layers.MotionLayer` s. Returns (transform (4, 4) start->end
    pure translation, start work indices, end work indices) per part found, largest first."""
    context = ratings.context
    if context.frame is None or not layers:
        return []
    start, end = ratings.start.points, ratings.end.points
    in_layer_start = np.zeros(len(start), dtype=bool)
    in_layer_end = np.zeros(len(end), dtype=bool)
    for layer in layers:
        in_layer_start[layer.start] = True
        in_layer_end[layer.end] = True
    leftovers = ratings.end_moved[~in_layer_end[ratings.end_moved]]
    leftovers = leftovers[~_fringe(end, leftovers, np.flatnonzero(in_layer_end), context.radius)]
    free_start = np.flatnonzero(~in_layer_start)
    fringe_start = np.zeros(len(start), dtype=bool)
    fringe_start[free_start[_fringe(start, free_start, np.flatnonzero(in_layer_start), context.radius)]] = True
    if len(leftovers) < MIN_POINTS or len(free_start) < MIN_POINTS:
        return []
    seen = np.ones(len(end), dtype=bool)
    seen[ratings.end_moved[ratings.end_unseen]] = False
    pieces = radius_components(end[leftovers], LINK_RADII * context.radius)
    sizes = np.bincount(pieces[seen[leftovers]], minlength=pieces.max() + 1)
    tried = [k for k in np.argsort(-sizes, kind="stable") if sizes[k] >= MIN_POINTS]
    if not tried:
        return []
    free_tree = cKDTree(start[free_start])
    hit = ratings.radius
    lengths = np.arange(2.0 * hit, context.diameter, 0.5 * hit)
    grid = np.concatenate([-lengths[::-1], lengths])
    voters = np.concatenate([leftovers[(pieces == k) & seen[leftovers]] for k in tried])
    group = np.repeat(np.arange(len(tried)), [sizes[k] for k in tried])
    axes = np.asarray(context.frame, dtype=np.float64).T
    votes = [grouped_slide_votes(end[voters], group, len(tried), free_tree, -axis, grid, hit) for axis in axes]
    claimed = fringe_start.copy()   # a layer's fringe is no part's partner
    found: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for slot, k in enumerate(tried):
        piece = leftovers[(pieces == k) & seen[leftovers]]
        best = None
        for axis, axis_votes in zip(axes, votes):
            for i in _peaks(axis_votes[slot], MIN_POINTS):
                rated = _rate(ratings, layers, free_start, free_tree, claimed, piece, grid[i] * axis)
                if rated is not None and (best is None or len(rated[2]) > len(best[2])):
                    best = rated
        if best is None:
            continue
        transform, partners, hits = best
        claimed[partners] = True
        found.append((transform, partners, hits))
    return _join_touching(found, start, end, context.radius, hit)


def _fringe(points: np.ndarray, leftovers: np.ndarray, layer_points: np.ndarray, radius: float) -> np.ndarray:
    """(len(leftovers),) bool: leftover points within ``radius`` of a layer's points (same state). O(P log N)."""
    if len(layer_points) == 0:
        return np.zeros(len(leftovers), dtype=bool)
    distance = cKDTree(points[layer_points]).query(points[leftovers], k=1, distance_upper_bound=radius)[0]
    return distance < radius


def _peaks(votes: np.ndarray, floor: int) -> list[int]:
    """Indices of the ``PEAKS_PER_AXIS`` highest local maxima of ``votes`` (within two grid steps)
    with at least ``floor`` votes, highest first (ties: the shorter index). O(L log L)."""
    peaks: list[int] = []
    for i in np.argsort(-votes, kind="stable"):
        if votes[i] < floor or len(peaks) == PEAKS_PER_AXIS:
            break
        if all(abs(int(i) - j) > 2 for j in peaks):
            peaks.append(int(i))
    return peaks


def _rate(ratings: Ratings, layers: list, free_start: np.ndarray, free_tree: cKDTree, claimed: np.ndarray,
          piece: np.ndarray, shift: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The part a slide by ``shift`` makes of an end piece (seen work indices ``piece``), or None
    when it fails a test of the module doc: (transform, partner start indices, hit end indices)."""
    hit = ratings.radius
    end, start = ratings.end.points, ratings.start.points
    back = end[piece] - shift
    landed = free_tree.query(back, k=1, distance_upper_bound=hit)[0] < hit
    if landed.sum() < max(MIN_POINTS, HIT_SHARE * len(piece)):
        return None
    hits = piece[landed]
    views = ratings.context.start_views
    if views:
        violations = int(np.count_nonzero(views.classify(back[~landed]) == VIOLATION))
        if violations > VIOLATION_SHARE * len(piece):
            return None
        if np.mean(views.classify(end[hits]) == VIOLATION) < SEEN_THROUGH_SHARE:
            return None
    for layer in layers:
        undo = np.linalg.inv(layer.transform)
        if np.mean(ratings.start_all.query(end[hits] @ undo[:3, :3].T + undo[:3, 3], k=1,
                                           distance_upper_bound=hit)[0] < hit) > LAYER_EXPLAINS_SHARE:
            return None
    near = cKDTree(end[hits]).query(start[free_start] + shift, k=1, distance_upper_bound=hit)[0] < hit
    partners = free_start[near & ~claimed[free_start]]
    if len(partners) < MIN_POINTS:
        return None
    stayed = ratings.end_all.query(start[partners], k=1, distance_upper_bound=hit)[0] < hit
    if stayed.mean() > STAYED_MAX_SHARE:
        return None
    transform = np.eye(4)
    transform[:3, 3] = shift
    if detached(transform, start[partners], ratings.static_tree()):
        return None
    return transform, partners, hits


def _join_touching(found: list[tuple[np.ndarray, np.ndarray, np.ndarray]], start: np.ndarray, end: np.ndarray,
                   radius: float, hit: float) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Parts whose slides differ by less than ``hit`` and whose end points come within
    ``TOUCH_RADII`` inlier radii are one part (a rack broken into pieces); largest first. O(F^2 P log P)."""
    joined: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for transform, partners, hits in found:
        for index, (other, other_partners, other_hits) in enumerate(joined):
            if np.linalg.norm(transform[:3, 3] - other[:3, 3]) >= hit:
                continue
            gap = min(_gap(end, other_hits, hits, TOUCH_RADII * radius),
                      _gap(start, other_partners, partners, TOUCH_RADII * radius))
            if gap < TOUCH_RADII * radius:
                joined[index] = (other, np.union1d(other_partners, partners), np.union1d(other_hits, hits))
                break
        else:
            joined.append((transform, partners, hits))
    joined.sort(key=lambda part: -(len(part[1]) + len(part[2])))
    return joined


def _gap(points: np.ndarray, a: np.ndarray, b: np.ndarray, bound: float) -> float:
    """Least distance between the points ``a`` and ``b`` (indices into ``points``), inf beyond ``bound``."""
    return float(np.min(cKDTree(points[a]).query(points[b], k=1, distance_upper_bound=bound)[0]))
