"""Small parts slid along the static body's axes, sought after the motion layers (no masks).

The motion layers (:mod:`.motion_layers`) price a part by a share of all moved points, so a part
much smaller than its neighbours cannot pay for itself: an oven's wire racks slid out under two
opened doors hold 2-4 % of the moved points. Worse, a thin part slid within its own plane lands on
itself: most of a rack's start points lie near its own end points and read as static, so its
start side has almost no moved points to vote with.

The search runs only where the two states agree where nothing moved (the unmoved start points a
median of at most ``AGREEMENT_RADII`` inlier radii from the end cloud: clean renders 0.000-0.010,
the real capture's still camera 0): on rough depth (robot-shaped renders, 0.28-0.30) a point far
from the other state is as often noise as motion, and the search made 46 parts of table and wall
patches over 84 joints (robot-1view, seeds 0-3) and 35 (robot-sensor-1view), each moved
background piece slid along the room's axes onto its own plane.

Here each piece of the end state's leftovers (seen moved points in no layer, linked at
``LINK_RADII`` inlier radii; leftovers within one inlier radius of a layer's points are that
layer's fringe -- a door's far edge just outside the hit radius -- and are set aside) is tried on
its own against the start points in no layer. For each axis of the static body's frame, both
ways, the lengths d (from ``MIN_TRAVEL_RADII`` inlier radii: a shorter slide carries a strip of a
lid by its hinge, which its turn barely moves, as well) at which the piece, slid back by d, lands
on those points are voted for
(:func:`~.motion_candidates.grouped_slide_votes`); the best ``PEAKS_PER_AXIS`` lengths, charged
for their travel as the pair cost does (``TRAVEL_PENALTY`` per object diameter: of two slides
that lay it alike the shorter wins, as a wire grid slid one pitch further lays its protruding end
as well), are rated, and the piece becomes a part with the best that passes every test:

* it lays at least ``MIN_POINTS`` and ``HIT_SHARE`` of the piece onto start points (its hits),
  at most ``VIOLATION_SHARE`` of the piece where the start views saw through, and at least
  ``SEEN_THROUGH_SHARE`` of its hits lie where the start views saw through, i.e. where nothing
  was at start (a strip of a faucet's spout or a window's sash read as moved by a margin lies on
  what the start saw there: 0-3 %; a rack slid less than its depth lies partly near its own
  start wires: 37-71 %), ``SEEN_THROUGH_SHARE_ESTIMATED`` where the states' frame is estimated
  rather than known (a static wall shifted off itself by a registration error: 58-61 %; racks
  76-98 %);
* no layer's motion lays more than ``LAYER_EXPLAINS_SHARE`` of its hits onto start points (a
  piece of a part already found);
* its partners -- start points in no layer and no layer's fringe, not taken by another small
  part, that the slide lays onto its hits -- are at least ``MIN_POINTS``, come within
  ``ATTACHED_RADII`` inlier radii of the static body (a slid part sits in its slot; a fragment of
  a turning lid does not), and at most ``STAYED_MAX_SHARE`` of their places are filled in the end
  (a static shelf read as moved, slid onto its twin shelf, left nothing);
* the slide carries it at most :data:`~.motion_ratings.ANCHOR_MAX_SLIDE` radii of itself
  (:func:`~.motion_ratings.detached`).

Its points are the hits and their partners. Parts with the same slide (within a hit radius) that
come within ``TOUCH_RADII`` inlier radii in either state are one part (a rack seen in pieces).

Measured (oven_7179_multi, clean renders, no masks, seed 0): posed, the three racks slide
0.212 / 0.159 / 0.349 for 0.215 / 0.162 / 0.351 and nothing else is a part; unposed, the same
three racks (one 0.421: its true slide laid under half its piece). Cost O(A (M log M + P log M +
K)) for A = 3 axes, M start points, P leftover points and K tube pairs, plus O(C log M) per rated
length of a piece of C points.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.clouds import nearest_gap, radius_components
from ..geometry.free_space import VIOLATION
from .correspondence import TRAVEL_PENALTY
from .motion_candidates import grouped_slide_votes
from .motion_ratings import Ratings, detached

MIN_POINTS = 30          # hits and partners a small part needs (the labeler's least segment)
HIT_SHARE = 0.5          # ... and this share of its piece's seen points must land on start points
VIOLATION_SHARE = 0.05   # at most this share of the points it lays down may land in seen free space
LINK_RADII = 2.0         # leftover points within this many inlier radii are one piece
TOUCH_RADII = 5.0        # parts with one slide this close (either state) are one part
PEAKS_PER_AXIS = 3       # local vote maxima rated per axis and piece
MIN_TRAVEL_RADII = 3.0   # slides shorter than this many inlier radii are not sought (a lid's strip by its hinge)
STAYED_MAX_SHARE = 0.9   # a part whose start points' places the end still fills more than this did not leave them
SEEN_THROUGH_SHARE = 0.25  # at least this share of its hits must lie where the start views saw through ...
SEEN_THROUGH_SHARE_ESTIMATED = 0.65  # ... this share where the states' frame is estimated, not known
LAYER_EXPLAINS_SHARE = 0.5  # a piece a larger part's motion lays this much of onto the start is that part's
AGREEMENT_RADII = 0.1    # the search runs where the unmoved points lie a median of at most this from the other state
AGREEMENT_SAMPLE = 5000  # ... over at most this many of them
ATTACHED_RADII = 2.0     # a slid part sits in its slot: at start it comes this many inlier radii near the static body
RIVAL_SHARE = 0.85       # a slide of another length laying this share of its points as well makes the part ambiguous
LEAST_TRUST = 0.3        # the labeler's trust in an ambiguous slide is at least this


@dataclass
class SlidPart:
    """A small part found by a slide: (4, 4) start->end pure translation, the work-cloud indices of
    its start / end points, and its rival: the support of the best slide of another length along
    any axis (its laid points less the travel charge) over its own, 0 without one."""

    transform: np.ndarray
    start: np.ndarray
    end: np.ndarray
    rival: float = 0.0

    def trust(self) -> float:
        """The labeler's trust in the slide: 1 unless a rival lays at least ``RIVAL_SHARE`` as much
        (a wire rack slid one pitch further lays its protruding end as well), then falling linearly
        to ``LEAST_TRUST`` as the rival reaches the slide's own support."""
        if self.rival < RIVAL_SHARE:
            return 1.0
        return max(LEAST_TRUST, (1.0 - self.rival) / (1.0 - RIVAL_SHARE))


def small_slides(ratings: Ratings, layers: list, posed: bool = False) -> list[SlidPart]:
    """Small slid parts among the leftovers of the motion layers (module doc).

    ratings: the motion layers' ratings (work clouds, moved points, views, static frame);
    layers: the kept :class:`~.motion_layers.MotionLayer` s; posed: the states' frame is known
    (cameras, a trusted feature alignment or a still camera), not a geometric estimate whose
    error could be mistaken for motion. Returns the parts found (:class:`SlidPart`), largest first."""
    context = ratings.context
    if context.frame is None or not layers or not _states_agree(ratings):
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
    lengths = np.arange(MIN_TRAVEL_RADII * context.radius, context.diameter, 0.5 * hit)
    grid = np.concatenate([-lengths[::-1], lengths])
    seen_pieces = [leftovers[(pieces == k) & seen[leftovers]] for k in tried]
    voters = np.concatenate(seen_pieces)
    group = np.repeat(np.arange(len(tried)), [len(piece) for piece in seen_pieces])
    axes = np.asarray(context.frame, dtype=np.float64).T
    votes = [grouped_slide_votes(end[voters], group, len(tried), free_tree, -axis, grid, hit) for axis in axes]
    claimed = fringe_start.copy()   # a layer's fringe is no part's partner
    found: list[SlidPart] = []
    for slot, piece in enumerate(seen_pieces):
        best, best_support, supports = None, 0.0, []
        for axis, axis_votes in zip(axes, votes):
            for i in _peaks(axis_votes[slot] * _travel_factor(grid, context.diameter), MIN_POINTS):
                shift = grid[i] * axis
                landed = _landed(free_tree, end[piece] - shift, hit)
                # the slide's support: what it lays (a rated part's hits are exactly these) less its travel charge
                support = len(landed) * _travel_factor(np.linalg.norm(shift), context.diameter)
                supports.append((shift, support))
                rated = _rate(ratings, layers, posed, free_start, free_tree, claimed, piece, shift, landed)
                if rated is not None and (best is None or support > best_support):
                    best, best_support = rated, support
        if best is None:
            continue
        transform, partners, hits = best
        rival = max((support for shift, support in supports
                     if np.linalg.norm(shift - transform[:3, 3]) > 2.0 * hit), default=0.0)
        claimed[partners] = True
        found.append(SlidPart(transform, partners, hits, rival / best_support))
    return _join_touching(found, start, end, context.radius, hit)


def _states_agree(ratings: Ratings) -> bool:
    """Do the two states agree where nothing moved, so that a point of one state far from the
    other is a sign of motion rather than of noise? True when the unmoved start points (at most
    ``AGREEMENT_SAMPLE`` of the motion ratings' static sample) lie a median of at most
    ``AGREEMENT_RADII`` inlier radii from the end cloud. O(S log N)."""
    static = ratings.static_tree()
    if static is None:
        return False
    sample = static.data[:: max(1, len(static.data) // AGREEMENT_SAMPLE)]
    return float(np.median(ratings.end_all.query(sample, k=1)[0])) <= AGREEMENT_RADII * ratings.context.radius


def _travel_factor(length, diameter: float):
    """1 less the pair cost's travel charge (``TRAVEL_PENALTY`` per object diameter travelled),
    for a length or an array of them: of two slides that lay as many points, the shorter wins (a
    grid of wires slid by one more pitch lays its protruding end as well). O(1) per length."""
    return 1.0 - TRAVEL_PENALTY * np.abs(length) / diameter


def _landed(free_tree: cKDTree, points: np.ndarray, hit: float) -> np.ndarray:
    """Indices into ``points`` (slid back, (P, 3)) of those within ``hit`` of a free start point. O(P log M)."""
    return np.flatnonzero(free_tree.query(points, k=1, distance_upper_bound=hit)[0] < hit)


def _fringe(points: np.ndarray, leftovers: np.ndarray, layer_points: np.ndarray, radius: float) -> np.ndarray:
    """(len(leftovers),) bool: leftover points within ``radius`` of a layer's points (same state). O(P log N)."""
    if len(layer_points) == 0:
        return np.zeros(len(leftovers), dtype=bool)
    distance = cKDTree(points[layer_points]).query(points[leftovers], k=1, distance_upper_bound=radius)[0]
    return distance < radius


def _peaks(votes: np.ndarray, floor: float) -> list[int]:
    """Indices of the ``PEAKS_PER_AXIS`` highest of ``votes`` (support per length, travel charged)
    at least ``floor`` and at least two grid steps apart, highest first (ties: the lower index).
    O(L log L)."""
    peaks: list[int] = []
    for i in np.argsort(-votes, kind="stable"):
        if votes[i] < floor or len(peaks) == PEAKS_PER_AXIS:
            break
        if all(abs(int(i) - j) > 2 for j in peaks):
            peaks.append(int(i))
    return peaks


def _rate(ratings: Ratings, layers: list, posed: bool, free_start: np.ndarray, free_tree: cKDTree, claimed: np.ndarray,
          piece: np.ndarray, shift: np.ndarray,
          landed_at: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The part a slide by ``shift`` makes of an end piece (seen work indices ``piece``; those of
    its positions that land on a free start point: ``landed_at``, :func:`_landed`), or None when it
    fails a test of the module doc: (transform, partner start indices, hit end indices)."""
    hit = ratings.radius
    end, start = ratings.end.points, ratings.start.points
    back = end[piece] - shift
    landed = np.zeros(len(piece), dtype=bool)
    landed[landed_at] = True
    if landed.sum() < max(MIN_POINTS, HIT_SHARE * len(piece)):
        return None
    hits = piece[landed]
    views = ratings.context.start_views
    if views:
        violations = int(np.count_nonzero(views.classify(back[~landed]) == VIOLATION))
        if violations > VIOLATION_SHARE * len(piece):
            return None
        least = SEEN_THROUGH_SHARE if posed else SEEN_THROUGH_SHARE_ESTIMATED
        if np.mean(views.classify(end[hits]) == VIOLATION) < least:
            return None
    for layer in layers:
        undo = np.linalg.inv(layer.transform)
        if np.mean(ratings.start_all.query(end[hits] @ undo[:3, :3].T + undo[:3, 3], k=1,
                                           distance_upper_bound=hit)[0] < hit) > LAYER_EXPLAINS_SHARE:
            return None
    # the free start points within a hit radius of a hit slid back: those the slide lays onto a hit
    near = free_tree.query_ball_point(end[hits] - shift, r=hit, return_sorted=False)
    partners = free_start[np.unique(np.fromiter((j for group in near for j in group), dtype=np.int64))]
    partners = partners[~claimed[partners]]
    if len(partners) < MIN_POINTS:
        return None
    static = ratings.static_tree()
    if static is not None and static.query(start[partners], k=1)[0].min() > ATTACHED_RADII * ratings.context.radius:
        return None
    stayed = ratings.end_all.query(start[partners], k=1, distance_upper_bound=hit)[0] < hit
    if stayed.mean() > STAYED_MAX_SHARE:
        return None
    transform = np.eye(4)
    transform[:3, 3] = shift
    if detached(transform, start[partners], static):
        return None
    return transform, partners, hits


def _join_touching(found: list[SlidPart], start: np.ndarray, end: np.ndarray, radius: float,
                   hit: float) -> list[SlidPart]:
    """Parts whose slides differ by less than ``hit`` and whose points come within ``TOUCH_RADII``
    inlier radii in either state are one part (a rack seen in pieces; its rival is the larger of
    theirs); largest first. O(F^2 P log P)."""
    joined: list[SlidPart] = []
    for part in found:
        for other in joined:
            if np.linalg.norm(part.transform[:3, 3] - other.transform[:3, 3]) >= hit:
                continue
            gap = min(nearest_gap(end[other.end], end[part.end], TOUCH_RADII * radius),
                      nearest_gap(start[other.start], start[part.start], TOUCH_RADII * radius))
            if gap < TOUCH_RADII * radius:
                other.start, other.end = np.union1d(other.start, part.start), np.union1d(other.end, part.end)
                other.rival = max(other.rival, part.rival)
                break
        else:
            joined.append(part)
    joined.sort(key=lambda part: -(len(part.start) + len(part.end)))
    return joined
