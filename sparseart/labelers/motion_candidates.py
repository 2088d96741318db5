"""Candidate motions for the motion layers (:mod:`.motion_layers`) beyond the registrations of
the moved pieces: the mirrored twins of a turning slab, slides along the rated slides' directions
(twin drawers) and along the static body's own axes (a drawer pulled towards the camera), and
turns about the lines where a moved plane of the start meets one of the end (a lid turned far).
Each takes the ratings of the moved points (:class:`~.motion_ratings.Ratings`) and returns (4, 4)
start->end transforms; the caller tightens them, drops those it knows, and its selection decides.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.clouds import radius_components, slab_axes
from ..geometry.planes import best_by_truncated_chamfer, hinge_turns, ransac_plane
from ..types import LabelledCloud
from .correspondence import SLIDE_MAX_DEG, motion_size
from .motion_ratings import Ratings

MIRROR_MIN_TURN_DEG = 10.0  # turning motions of slabs get their mirrored twins as candidates


def slab_mirrors(ratings: Ratings, k: int) -> list[np.ndarray]:
    """A turning motion composed with the half-turns that map its part onto itself when the part
    is a slab (a lid, a door: two principal extents well above the thickness): T S_a for the
    half-turn S_a about each in-plane principal axis through the part's centroid. Registration
    cannot tell these apart on a symmetric slab (a lid closed by 96 deg and the lid flipped onto
    itself by 84 deg land on the same plane); the whole-object objective (hits, and physics: a
    hinge's sweep must not pass through seen surfaces) decides."""
    transform = ratings.motions[k]
    if motion_size(transform)[0] < MIRROR_MIN_TURN_DEG:
        return []
    row = ratings.rows[k]
    own = ratings.start_moved[row[:len(ratings.start_moved)] >= 1.0]
    if len(own) < 30:
        return []
    slab = slab_axes(ratings.start.points[own])
    if slab is None:
        return []
    centre, axes = slab
    result = []
    for axis in axes[:2]:
        half = np.eye(4)
        half[:3, :3] = 2.0 * np.outer(axis, axis) - np.eye(3)
        half[:3, 3] = centre - half[:3, :3] @ centre
        result.append(transform @ half)
    return result


TWIN_SLIDE_SAME_DEG = 5.0   # slide directions closer than this are one direction for the length search


def twin_slides(ratings: Ratings, min_points: int) -> list[np.ndarray]:
    """Slides along each rated slide's direction by the other lengths the moved points support.

    Twin drawers share their slot direction but not their travel, and when they touch they come
    in one moved piece, whose registration blends their motions (measured: 4 drawers side by side
    without masks, the piece of two drawers registered to a slide 0.04 object units sideways that
    carried neither). For every distinct direction u of a rated motion turning less than
    ``SLIDE_MAX_DEG``, each start moved point p votes for the lengths d at which p + d u lands on
    an end moved point; lengths with at least ``min_points`` votes that are local maxima become
    pure translations d u (the caller drops those equal to a rated motion). Lengths are searched from 2 hit
    radii to the diameter in steps of half a hit radius: O(U (E log E + S log E + K)) for U
    directions, S start and E end moved points and K tube pairs (:func:`slide_votes`)."""
    directions: list[np.ndarray] = []
    for transform in ratings.motions:
        angle, shift = motion_size(transform)
        if angle >= SLIDE_MAX_DEG or shift <= 0:
            continue
        u = transform[:3, 3] / shift
        if any(np.degrees(np.arccos(min(1.0, abs(float(u @ v))))) < TWIN_SLIDE_SAME_DEG for v in directions):
            continue
        directions.append(u)
    if not directions:
        return []
    points = ratings.start.points[ratings.start_moved[~ratings.start_unseen]]
    if len(points) < min_points:
        return []
    points = points[:: max(1, len(points) // 3000)]
    scale = max(1, len(ratings.start_moved[~ratings.start_unseen]) // 3000)
    step = 0.5 * ratings.radius
    grid = np.arange(2.0 * ratings.radius, ratings.context.diameter, step)
    found = []
    for u in directions:
        votes = scale * slide_votes(points, ratings.end_tree, u, grid, ratings.radius)
        found.extend(vote_peaks(votes, grid, u, min_points))
    return found


def slide_votes(points: np.ndarray, tree: cKDTree, direction: np.ndarray, lengths: np.ndarray,
                radius: float) -> np.ndarray:
    """(L,) int: for each length d of the ascending ``lengths``, how many of ``points`` (P, 3) land
    within ``radius`` of a point of ``tree`` (its M targets) after the slide d * ``direction``.
    One group of :func:`grouped_slide_votes`."""
    return grouped_slide_votes(points, np.zeros(len(points), dtype=np.int64), 1, tree, direction, lengths,
                               radius)[0]


def grouped_slide_votes(points: np.ndarray, group: np.ndarray, groups: int, tree: cKDTree,
                        direction: np.ndarray, lengths: np.ndarray, radius: float) -> np.ndarray:
    """(G, L) int: for each group g < ``groups`` of ``points`` (P, 3; ``group`` (P,) its labels)
    and each length d of the ascending ``lengths``, how many of the group's points land within
    ``radius`` of a point of ``tree`` (its M targets) after the slide d * ``direction``.

    Exact, without a query per length: a point p lands on target q after the slide d u iff q lies
    in the tube of radius r around p's line along u, and d is within h = sqrt(r^2 - |q - p|_perp^2)
    of (q - p) . u. So the targets of a point are the pairs within r of it across u (a 2-D k-d
    tree of the targets projected onto the plane normal to u, built once for all groups), each
    pair covers the lengths of one interval, and a point votes once for every length one of its
    intervals covers. O(M log M + P log M + K + V) for K tube pairs and V (point, length) votes.
    """
    votes = np.zeros((groups, len(lengths)), dtype=np.int64)
    if len(points) == 0:
        return votes
    u = np.asarray(direction, dtype=np.float64)
    u = u / np.linalg.norm(u)
    basis = np.linalg.svd(u[None, :])[2][1:]                  # (2, 3): the plane normal to u
    targets = tree.data
    pairs = cKDTree(targets @ basis.T).query_ball_point(points @ basis.T, r=radius)
    counts = np.fromiter((len(p) for p in pairs), dtype=np.int64, count=len(pairs))
    if counts.sum() == 0:
        return votes
    voter = np.repeat(np.arange(len(points)), counts)
    target = np.fromiter((j for p in pairs for j in p), dtype=np.int64, count=int(counts.sum()))
    offset = targets[target] - points[voter]
    along = offset @ u
    across = np.sum(offset ** 2, axis=1) - along ** 2
    half = np.sqrt(np.maximum(radius ** 2 - across, 0.0))
    first = np.searchsorted(lengths, along - half, side="right")
    stop = np.searchsorted(lengths, along + half, side="left")
    # lengths strictly inside (along - half, along + half): |p + d u - q| < r
    span = np.maximum(stop - first, 0)
    if span.sum() == 0:
        return votes
    index = np.repeat(first - np.cumsum(span) + span, span) + np.arange(int(span.sum()))
    key = np.unique(np.repeat(voter, span) * len(lengths) + index)
    cell = np.asarray(group, dtype=np.int64)[key // len(lengths)] * len(lengths) + key % len(lengths)
    return np.bincount(cell, minlength=groups * len(lengths)).reshape(groups, len(lengths)).astype(np.int64)


def vote_peaks(votes: np.ndarray, lengths: np.ndarray, direction: np.ndarray, min_points: int) -> list[np.ndarray]:
    """Pure translations ``lengths[i] * direction`` ((4, 4) each) at the local maxima of ``votes``
    (within two grid steps; the first of equal neighbours) with at least ``min_points`` votes. O(L)."""
    found = []
    for i in range(len(lengths)):
        low, high = max(0, i - 2), min(len(lengths), i + 3)
        if votes[i] < min_points or votes[i] < votes[low:high].max() or (i > low and votes[i] == votes[i - 1]):
            continue
        transform = np.eye(4)
        transform[:3, 3] = lengths[i] * direction
        found.append(transform)
    return found


PLANE_HINGE_PIECES = 2      # the largest moved pieces of each state whose planes propose hinges ...
PLANE_HINGE_PLANES = 2      # ... and the planes taken from each (the second from the first's outliers)
PLANE_HINGE_SAMPLE = 2000   # plane points per side that rank a hinge's four turns
PLANE_HINGE_SAME_TURN_DEG = 5.0  # a candidate already turning within this of a plane hinge makes it redundant


def plane_hinges(ratings: Ratings, min_points: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Turns about the lines where a moved plane of the start meets a moved plane of the end:
    for every pair of the ``PLANE_HINGE_PLANES`` largest planes (>= ``min_points`` points within
    the inlier radius) of the ``PLANE_HINGE_PIECES`` largest moved pieces of each state, the one of
    :func:`~sparseart.geometry.planes.hinge_turns` that lays the one plane's points nearest the
    other's (truncated Chamfer, clipped at 3 radii).

    Why: a door or lid that turned far is out of reach of registration from identity or from
    its pieces' shapes (a lid seen from above closed and edge-on open); measured on robot-shaped
    renders with sensor depth, the candidates of a box lid turned by 75 deg were turns of 0.5-16
    deg, and the lid was reported as two slides 88 deg off. Its hinge is where its two planes
    meet. Moved pieces here include the unseen points (a closed lid's top is hidden behind the
    opened lid in the end views). The selection decides among these as among all candidates.
    O(P (N log N + R S)) for the P <= 2 pieces of N points per state and R RANSAC rounds over S
    points, plus O(16 C log C) for the truncated Chamfer of C <= ``PLANE_HINGE_SAMPLE`` points."""
    radius = ratings.context.radius

    def planes(cloud: LabelledCloud, moved: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        labels = radius_components(cloud.points[moved], radius)
        pieces = sorted((moved[labels == k] for k in np.unique(labels)), key=len, reverse=True)
        found = []
        for piece in pieces[:PLANE_HINGE_PIECES]:
            points = cloud.points[piece]
            for _ in range(PLANE_HINGE_PLANES):
                plane = ransac_plane(points, radius, rng) if len(points) >= min_points else None
                if plane is None:
                    break
                normal, centre = plane
                on = np.abs((points - centre) @ normal) < radius
                if on.sum() < min_points:
                    break
                found.append((normal, points[on].mean(axis=0), points[on]))
                points = points[~on]
        return found

    hinges = []
    for normal_s, centre_s, on_s in planes(ratings.start, ratings.start_moved):
        for normal_e, centre_e, on_e in planes(ratings.end, ratings.end_moved):
            turns = hinge_turns((normal_s, centre_s), (normal_e, centre_e), MIRROR_MIN_TURN_DEG)
            if turns:
                hinges.append(best_by_truncated_chamfer(turns, on_s[:: max(1, len(on_s) // PLANE_HINGE_SAMPLE)],
                                                        on_e[:: max(1, len(on_e) // PLANE_HINGE_SAMPLE)],
                                                        3.0 * radius))
    return hinges


FRAME_SLIDE_POINTS = 1500   # moved points per state that vote for a slide length along a frame axis


def frame_slides(ratings: Ratings, min_points: int) -> list[np.ndarray]:
    """Slides along the static body's own axes (its Manhattan frame), by the lengths the moved
    points support, both ways and both signs.

    Drawers, trays and sliding doors move along their carcass' axes. Registration of a moved
    piece finds their slide only when the piece's two states look alike; a drawer pulled towards
    a static camera hides its own closed pose (unseen, no shape to register against) and the
    registration settled on turns (measured: a robot-shaped drawer cabinet with depth noise, the
    candidates were turns of 18 and 54 deg and no slide). Here every seen moved point of either
    state votes for the lengths d at which it lands on a moved point (seen or unseen) of the other
    state after a slide of d along a frame axis; local maxima with at least ``min_points`` votes
    become candidate slides (the selection decides). O(3 (M log M + P log M + K + V)) for P <= 2
    ``FRAME_SLIDE_POINTS`` voters and the tube pairs K and votes V of :func:`slide_votes`, grid
    step r / 2 up to the diameter D (V <= 4 K)."""
    frame = ratings.context.frame
    if frame is None:
        return []
    voters = []
    for moved, unseen, cloud, tree, sign in ((ratings.start_moved, ratings.start_unseen, ratings.start,
                                              ratings.end_tree, 1.0),
                                             (ratings.end_moved, ratings.end_unseen, ratings.end,
                                              ratings.start_tree, -1.0)):
        points = cloud.points[moved[~unseen]]
        if len(points):
            stride = max(1, len(points) // FRAME_SLIDE_POINTS)
            voters.append((points[::stride], tree, sign, float(stride)))
    if not voters:
        return []
    step = 0.5 * ratings.radius
    lengths = np.arange(2.0 * ratings.radius, ratings.context.diameter, step)
    grid = np.concatenate([-lengths[::-1], lengths])
    found = []
    for u in np.asarray(frame, dtype=np.float64).T:
        votes = np.zeros(len(grid))
        for points, tree, sign, weight in voters:
            votes += weight * slide_votes(points, tree, sign * u, grid, ratings.radius)
        found.extend(vote_peaks(votes, grid, u, min_points))
    return found
