"""Moving points without masks: which rigid motion carries each moved point.

Without masks the moved points of a state come in connected pieces, and one piece can hold
several parts (twin drawers side by side are one piece). So parts are found as motions, not as
pieces. The motions start from the assignment of pieces (:mod:`.correspondence`, with its
physics-aware cost); every motion then rates every moved point of both states:

* 1 when the motion carries it onto a moved point of the other state (a hit),
* ``HIDDEN_CREDIT`` (just below 1: a hit wins a tie) when it lands where the other state's views
  cannot see (a drawer pushed shut hides its sides in the carcass),
* 0 when it lands on some other surface the views saw, -1 when the views saw through that spot.

Moved points the split marked unseen (far from the other state's cloud, but hidden in its views:
the base under a lid that closed over it) have no vote: they add nothing to the selection objective,
earn nothing from landing hidden or on each other, and only join a chosen motion that carries them
onto the other state's moved points. Slides along the static body's own axes (its Manhattan
frame) by the lengths the moved points vote for are candidates too (a drawer pulled towards the
camera hides its closed pose, so no registration finds its slide). A turning slab (lid, door)
also gets its mirrored twins as candidates (the motion composed with the slab's half-turns,
which registration cannot tell apart); the objective's physics charge decides. Turns about the
lines where a moved plane of the start meets one of the end are candidates too (a lid turned
far, seen from above closed and face-on open, is out of reach of registration), unless a
candidate already turns that way. Only motions that earn the price from hits alone (landing
hidden adds value but cannot make a part), and only turns that a hinge on the static body can
make (no shift along their own axis, the axis passing by the static points; an arm present in
one state, carried onto the patch it hides, does neither), are selected. Chosen motions
whose layers touch and agree (the larger one's motion carries the smaller one's points within the
full inlier radius, or both turn alike and differ only by a shift in the plane of the slab they
form: a flat lid slid within its plane still lands on itself) are merged.

Moved points that no motion explains (rated <= 0 by all: e.g. a twin drawer's front that the
other drawer's motion puts in free space) form residual pieces; each is registered onto the other
state's unexplained moved points and its motion joins when it hits at least a part's worth of
points in both states and a joint anchored on the static body could make it (few blocked steps,
a slide out of its slot). Each point then follows the motion rating it best (a hit that lands on
another colour counts as none here: a hand or sleeve in one state lands on the wall or cabinet
patch it hides, by position a hit); ties and hidden-only points go to the motion whose hits lie
nearest, and a layer's piece (its points of one state linked at the inlier radius) without a
single hit stays unassigned: landing hidden is
no evidence of being attached (a hand on a door in one state, carried back by the door's turn,
lands behind the cabinet as the door's own sides do). A layer whose hits all land on unseen
points joins a touching layer with seen hits that turns about the same axis (a strip of a lid
under a hand, carried onto the table the lid revealed). A motion whose layer holds too few
points to be a part leaves the chosen set, and the points are assigned again among the others
(the ties it took go back to their part); the selection then runs again without it, and is
taken when it makes more parts (a spurious motion can have kept a part's own motion out).
Parts too small to pay the price (an oven's wire racks beside its doors) are sought afterwards
among the moved points the layers leave (:mod:`.small_slides`).
Cost O(M N (log N + V)) for M motions and N moved points, plus one registration per residual
piece.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..geometry.clouds import nearest_gap, radius_components, slab_axes
from ..geometry.transforms import axis_angle_deg, rotation_angle
from .correspondence import PHYSICS_WEIGHT, SLIDE_WEIGHT, PairContext, apply, motion_size, register_sets, slide_direction
from .motion_candidates import PLANE_HINGE_SAME_TURN_DEG, frame_slides, plane_hinges, slab_mirrors, twin_slides
from .motion_ratings import Ratings
from .small_slides import small_slides

RESIDUAL_ROUNDS = 2
PIECE_SHARE = 0.03          # moved pieces at least this share of the moved points are registered on their own
LAYER_MIN_SHARE = 0.1       # a layer must hold this share of each state's moved points
PRICE_SHARE = 0.03          # a motion (part) must explain more than this share of the moved points
MAX_TURN_DEG = 150.0        # candidate motions turning more are left out (real joints rarely do)
RESELECT_ROUNDS = 3         # selections again without motions whose layers were too small to be parts
MERGE_HIT_SHARE = 0.6      # a touching layer the larger one's motion explains this much joins it


@dataclass
class Doubt:
    """Why the labeler trusts a layer's motion less: ``trust`` in (0, 1) (the part's labeler
    confidence takes the lowest of its doubts) and ``why``, the sentence the part's warning gives."""

    trust: float
    why: str


REVEALED_TRUST = 0.25   # the labeler's trust in a layer that lands only on what another part revealed
REVEALED_DOUBT = ("its motion lays it almost only onto surfaces the other state could not see, beside a part whose "
                  "motion uncovered them: it may be such a surface, not a part")
RIVAL_LENGTH_DOUBT = ("a slide of another length lays its points almost as well (repeated structure, e.g. a wire "
                      "rack one pitch further)")


@dataclass
class MotionLayer:
    """One kept motion: (4, 4) start->end transform, its physics share, and the work-cloud
    indices of the start / end points that follow it; ``doubts``: why its motion is trusted less
    (:func:`_flag_revealed`, a small slide's rival length)."""

    transform: np.ndarray
    physics: float
    start: np.ndarray
    end: np.ndarray
    charge: float = 0.0     # the objective's physics charge per claimed point (blocked share, slide sine)
    doubts: list[Doubt] = field(default_factory=list)


def motion_layers(context: PairContext, start_moved: np.ndarray, end_moved: np.ndarray,
                  motions: list[np.ndarray], min_points: int,
                  pieces: tuple[list[np.ndarray], list[np.ndarray]] = ([], []),
                  unseen: tuple[np.ndarray, np.ndarray] | None = None,
                  posed: bool = False) -> tuple[list[MotionLayer], list[str]]:
    """Split the moved points of both states into rigid motions (module doc), then seek the small
    slid parts among what they leave (:mod:`.small_slides`; ``posed``: the states' frame is known
    -- cameras, a trusted feature alignment or a still camera -- not a geometric estimate).

    context: the pair context of the two states (work clouds, radius, views, static frame);
    start_moved / end_moved: work-cloud indices of the moved points; motions: candidate (4, 4)
    start->end motions (the assigned moving pieces' first); pieces: the moved pieces of each
    state (work indices), each also registered onto all moved points of the other state.
    Returns the layers (largest first) and notes for the warnings.
    """
    notes: list[str] = []
    if len(start_moved) == 0 or len(end_moved) == 0:
        return [], notes
    ratings = Ratings(context, start_moved, end_moved, unseen)
    rng = np.random.default_rng(context.seed + 7)
    pool = list(motions)
    big = max(min_points, int(PIECE_SHARE * (len(start_moved) + len(end_moved)) / 2))
    for piece in pieces[0]:
        if len(piece) >= big:
            pool.append(register_sets(context, piece, end_moved, rng)[1])
    for piece in pieces[1]:
        if len(piece) >= big:
            pool.append(register_sets(context, start_moved, piece, rng)[1])
    # Each batch of candidates is tightened and rated side by side (Ratings.tighten_all, add_all), in order.
    ratings.add_all(ratings.tighten_all(_within_turn_limit(pool)))
    ratings.add_all(ratings.tighten_all(twin_slides(ratings, min_points) + frame_slides(ratings, min_points)))
    _add_turns(ratings, [mirrored for k in range(len(ratings.motions)) for mirrored in slab_mirrors(ratings, k)])
    turns = [motion[:3, :3] for motion in ratings.motions]
    # own generator: the residual rounds below draw the same samples with or without these
    # (a plane hinge whose turn registration found already would only add a pivot)
    _add_turns(ratings, [hinge for hinge in plane_hinges(ratings, min_points, np.random.default_rng(context.seed + 11))
                         if not any(np.degrees(rotation_angle(hinge[:3, :3] @ turn.T)) < PLANE_HINGE_SAME_TURN_DEG
                                    for turn in turns)])
    price = max(float(min_points), PRICE_SHARE * (len(start_moved) + len(end_moved)))
    chosen = _select(ratings, price)
    for _ in range(RESIDUAL_ROUNDS):
        found = [register_sets(context, piece_s, piece_e, rng)[1]
                 for piece_s, piece_e in _residual_pieces(ratings, chosen, context.radius, min_points)]
        before = len(ratings.motions)
        ratings.add_all(ratings.tighten_all(_within_turn_limit(found)))
        if len(ratings.motions) == before:
            break
        chosen = _select(ratings, price)
    floors = (max(min_points, LAYER_MIN_SHARE * len(start_moved)), max(min_points, LAYER_MIN_SHARE * len(end_moved)))
    layers = _layers_with_reselection(ratings, price, chosen, floors)
    layers.sort(key=lambda layer: -(len(layer.start) + len(layer.end)))
    _flag_revealed(ratings, layers)
    for part in small_slides(ratings, layers, posed):
        doubts = [] if part.trust() >= 1.0 else [Doubt(part.trust(), RIVAL_LENGTH_DOUBT)]
        layers.append(MotionLayer(part.transform, 0.0, part.start, part.end, doubts=doubts))
        notes.append(f"a small part slid {np.linalg.norm(part.transform[:3, 3]):.3g} along an axis of the static body "
                     f"was found among the points no larger part explains ({len(part.start)} / {len(part.end)} points)")
    return layers, notes


def _layers_with_reselection(ratings: Ratings, price: float, chosen: list[int],
                             floors: tuple[float, float]) -> list[MotionLayer]:
    """The layers of the chosen motions over the point floors (:func:`_layers_over_floor`); when
    some motions fell below the floor beside layers that stand, the selection runs again without
    them (at most ``RESELECT_ROUNDS`` times) and its answer replaces the layers when it makes more
    parts.

    Why: a motion that lands another part's points on the other state by coincidence claims
    them in the selection and keeps that part's own motion out (its gain over the price is gone),
    then holds too few points of its own to be a part and is dropped, and the other part is
    never found. Measured on a robot view of a storage unit (door and drawer): a 69 deg turn
    with 415 door and 395 background hits was chosen beside the door's turn, whose 36 deg
    motion also landed 345 of the closed drawer's points; the drawer's slide (569 of its own
    hits) was left out, the 69 deg layer dropped. Selected again without it, the slide is a
    part (1.9 deg). A reselection that only adds a motion joining a layer that stands (a lid's
    mirrored turn, which merges into the lid) is not taken: it adds no part and moved the real
    laptop's hinge line from 1.6 to 6.7 mm. When no layer stands the caller falls back to the
    pieces' own pairing, as before (a sliding glass pane whose hits change colour is found so).
    O(R (selection + assignment)) for R <= ``RESELECT_ROUNDS``."""
    layers, dropped = _layers_over_floor(ratings, chosen, *floors)
    excluded: set[int] = set()
    for _ in range(RESELECT_ROUNDS):
        if not dropped or not layers:
            break
        excluded |= dropped
        again = _select(ratings, price, excluded)
        if again == [k for k in chosen if k not in dropped]:
            break
        again_layers, again_dropped = _layers_over_floor(ratings, again, *floors)
        if len(again_layers) <= len(layers):
            break
        chosen, layers, dropped = again, again_layers, again_dropped
    return layers


def _add_turns(ratings: Ratings, transforms: list[np.ndarray]) -> None:
    """Rate candidate turns once tightened (side by side), in order, leaving out those that then
    turn more than ``MAX_TURN_DEG`` or equal a rated motion."""
    ratings.add_all(_within_turn_limit(ratings.tighten_all(transforms)))


def _within_turn_limit(transforms: list[np.ndarray | None]) -> list[np.ndarray]:
    """The motions that exist and turn by at most ``MAX_TURN_DEG`` (real joints rarely turn more)."""
    return [t for t in transforms if t is not None and motion_size(t)[0] <= MAX_TURN_DEG]


def _layers_over_floor(ratings: Ratings, chosen: list[int], floor_start: float,
                       floor_end: float) -> tuple[list[MotionLayer], set[int]]:
    """The merged layers (:func:`_assign_points`, :func:`_merge_agreeing`) of the chosen motions
    that hold at least ``floor_start`` / ``floor_end`` points of each state. A motion whose layer
    falls below the floor is no part; it leaves the chosen set and the points are assigned again
    among the others, so the points it took by a tie go back to the part they belong to (they
    were lost with it: on the real laptop capture a 127 deg motion took a strip of the bent
    cardboard lid that the lid's own turn explains as well, and the lid kept 38045 points
    instead of 42312, confidence 0.60 instead of 0.67). Repeats until every layer passes;
    O(R (assignment + merge)) for R <= len(chosen) rounds. Returns the layers that pass and the
    indices of the chosen motions dropped for their layers' size."""
    removed: set[int] = set()
    while True:
        layers = _merge_agreeing(ratings, _assign_points(ratings, chosen))
        dropped = {id(layer.transform) for layer in layers
                   if len(layer.start) < floor_start or len(layer.end) < floor_end}
        below = {k for k in chosen if id(ratings.motions[k]) in dropped}
        remaining = [k for k in chosen if k not in below]
        if not dropped or len(remaining) == len(chosen) or not remaining:
            return [layer for layer in layers if id(layer.transform) not in dropped], removed | below
        removed |= below
        chosen = remaining


def _charge(ratings: Ratings, k: int) -> float:
    """Motion k's physics charge per claimed point (blocked share and slide sine, weighted as in
    the pair cost), one formula for the objective and the layers."""
    return PHYSICS_WEIGHT * ratings.physics[k] + SLIDE_WEIGHT * ratings.slides[k]


def _objective(seen: np.ndarray, charges: np.ndarray, chosen: list[int], price: float) -> float:
    """Whole-object explanation of a motion set: the sum over moved points that were seen (unseen
    points have no vote: they join a chosen motion afterwards) of their best rating (>= 0), minus
    ``price`` per motion and, per motion, its physics charge (``charges``: blocked share and slide
    sine, weighted as in the pair cost) times the points it claims. seen: (M, S) ratings of the
    M motions on the S seen moved points. O(len(chosen) S)."""
    if not chosen:
        return 0.0
    table = seen[chosen]
    owner = table.argmax(axis=0)
    best = np.take_along_axis(table, owner[None], axis=0)[0]
    value = float(np.clip(best, 0.0, None).sum()) - price * len(chosen)
    claimed = np.bincount(owner[best > 0.0], minlength=len(chosen))
    for slot, k in enumerate(chosen):
        value -= charges[k] * float(claimed[slot])
    return value


def _select(ratings: Ratings, price: float, excluded: set[int] | frozenset[int] = frozenset()) -> list[int]:
    """Greedy forward selection, then single removals and swaps while the objective improves,
    over the motions with more than ``price`` seen hits that are not
    :func:`~.motion_ratings.detached` (measured on robot-shaped renders: a 23 deg turn with no hit
    and 2024 hidden points was chosen over a door's hinge with 776 hits, and then dropped as
    hitless, leaving no part). Ties go to the
    earlier motion (the assigned pairs' motions come first). The ratings of the seen points are
    gathered once per call (they were re-gathered for each of the ~10^3 trial sets: 12 of 48 s
    on an unposed 4-drawer cabinet without masks). ``excluded``: motion indices left out (motions
    whose layers were too small to be parts, :func:`_layers_with_reselection`)."""
    seen = np.stack(ratings.rows)[:, ~ratings.unseen] if ratings.rows else np.zeros((0, 0))
    charges = np.array([_charge(ratings, k) for k in range(len(ratings.motions))])
    chosen: list[int] = []
    value = 0.0
    # a motion must earn its price from hits: landing hidden adds to its value but cannot make it
    pool = [k for k in range(len(ratings.motions)) if not ratings.detached[k] and k not in excluded
            and np.count_nonzero(seen[k] >= 1.0) > price]
    while True:
        best, best_value = None, value
        for k in pool:
            if k in chosen:
                continue
            trial = _objective(seen, charges, chosen + [k], price)
            if trial > best_value + 1e-9:
                best, best_value = k, trial
        if best is None:
            break
        chosen.append(best)
        value = best_value
    improved = True
    while improved and chosen:
        improved = False
        for slot in range(len(chosen)):
            for k in [None, *[m for m in pool if m not in chosen]]:
                trial_set = chosen[:slot] + chosen[slot + 1:] + ([k] if k is not None else [])
                trial = _objective(seen, charges, trial_set, price)
                if trial > value + 1e-9:
                    chosen, value, improved = trial_set, trial, True
                    break
            if improved:
                break
    return sorted(chosen)


def _residual_pieces(ratings: Ratings, chosen: list[int], radius: float,
                     min_points: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Connected pieces of moved points no chosen motion explains (rating <= 0), each paired with
    the other state's unexplained moved points (all of its moved points when too few are left)."""

    n_start = len(ratings.start_moved)
    best = (np.stack([ratings.rows[k] for k in chosen]).max(axis=0) if chosen
            else np.zeros(n_start + len(ratings.end_moved)))
    loose_s = ratings.start_moved[(best[:n_start] <= 0) & ~ratings.start_unseen]
    loose_e = ratings.end_moved[(best[n_start:] <= 0) & ~ratings.end_unseen]
    pairs = []
    for loose, other_loose, cloud, other_all in ((loose_s, loose_e, ratings.start, ratings.end_moved),
                                                 (loose_e, loose_s, ratings.end, ratings.start_moved)):
        if len(loose) < min_points:
            continue
        labels = radius_components(cloud.points[loose], radius)
        counts = np.bincount(labels)
        for label in np.flatnonzero(counts >= min_points):
            piece = loose[labels == label]
            partner = other_loose if len(other_loose) >= min_points else other_all
            pairs.append((piece, partner) if cloud is ratings.start else (partner, piece))
    return pairs


def _hit_share(ratings: Ratings, transform: np.ndarray, start_idx: np.ndarray, end_idx: np.ndarray,
               radius: float) -> float:
    """Share of the given moved points (work indices) that ``transform`` carries within ``radius``
    of the other state's moved points (both directions). O(P log N)."""
    if len(start_idx) + len(end_idx) == 0:
        return 0.0
    forward = ratings.end_tree.query(apply(transform, ratings.start.points[start_idx]), k=1,
                                     distance_upper_bound=radius)[0] < radius
    backward = ratings.start_tree.query(apply(np.linalg.inv(transform), ratings.end.points[end_idx]), k=1,
                                        distance_upper_bound=radius)[0] < radius
    return float((forward.sum() + backward.sum()) / (len(start_idx) + len(end_idx)))


def _merge_agreeing(ratings: Ratings, layers: list[MotionLayer]) -> list[MotionLayer]:
    """Layers of one part: the selection rates hits with a tight radius (twins a radius apart stay
    apart), so one part whose registration is a little off in different places can come out as
    several nearly equal motions, each claiming a patch. A layer whose points the motion of a
    larger layer, which it touches, carries onto the other state within the full inlier radius
    (share >= ``MERGE_HIT_SHARE``), or whose motion differs from it only by a shift in the plane
    of the slab they form (:func:`_slid_in_plane`), joins it; the merged layer keeps the motion of the two that
    lays all of its points best (tight hit radius) net of its physics charge, as in the objective
    (the part's final registration refines it). A touching layer that is a blind piece of a
    larger or smaller sighted one (:func:`_blind_piece`) joins it with its seen points and under
    its motion; its unseen points stay unassigned. O(L^2 P log N)."""
    layers = sorted(layers, key=lambda layer: -(len(layer.start) + len(layer.end)))
    radius = ratings.context.radius
    merged = True
    while merged:
        merged = False
        for a in range(len(layers)):
            for b in range(a + 1, len(layers)):
                big, small = layers[a], layers[b]
                if not _touching(ratings, big, small, radius):
                    continue
                blind = _blind_piece(ratings, big, small)
                if blind is not None:
                    keep, piece = (big, small) if blind is small else (small, big)
                    at_s = np.searchsorted(ratings.start_moved, piece.start)
                    at_e = np.searchsorted(ratings.end_moved, piece.end)
                    layers[a] = MotionLayer(keep.transform, keep.physics,
                                            np.union1d(keep.start, piece.start[~ratings.start_unseen[at_s]]),
                                            np.union1d(keep.end, piece.end[~ratings.end_unseen[at_e]]), keep.charge)
                    del layers[b]
                    merged = True
                    break
                if ((_hit_share(ratings, big.transform, small.start, small.end, radius) >= MERGE_HIT_SHARE
                        and not _own_motion(ratings, big, small)) or _slid_in_plane(ratings, big, small)):
                    start_idx, end_idx = np.union1d(big.start, small.start), np.union1d(big.end, small.end)
                    # The merged layer follows whichever motion lays all of its points best.
                    keep = max((big, small), key=lambda layer: _hit_share(ratings, layer.transform, start_idx,
                                                                          end_idx, ratings.radius) - layer.charge)
                    layers[a] = MotionLayer(keep.transform, keep.physics, start_idx, end_idx, keep.charge)
                    del layers[b]
                    merged = True
                    break
            if merged:
                break
    return layers


TURNING_DEG = 5.0          # a layer whose motion turns by less is no hinge's (blind pieces, revealed layers)
BLIND_SHARE = 0.05         # a layer whose hits land on seen points less than this share is blind ...
SAME_HINGE_DEG = 15.0      # ... and joins a touching sighted layer that turns about an axis within this


def _sighted_share(ratings: Ratings, layer: MotionLayer) -> float:
    """Share of the layer's hits (its seen points that its own motion carries onto the other
    state's moved points in their colour; unseen points have no vote) that land on points the
    other state's views saw (not unseen); 1 without hits. O(N) for N moved points."""
    k = next(k for k, motion in enumerate(ratings.motions) if motion is layer.transform)
    at = np.concatenate([np.searchsorted(ratings.start_moved, layer.start),
                         len(ratings.start_moved) + np.searchsorted(ratings.end_moved, layer.end)])
    hits = (ratings.coloured_row(k)[at] >= 1.0) & ~ratings.unseen[at]
    return float(np.mean(~ratings.blind[k][at][hits])) if hits.any() else 1.0


def _blind_piece(ratings: Ratings, a: MotionLayer, b: MotionLayer) -> MotionLayer | None:
    """The one of two touching layers (both turning, about axes within ``SAME_HINGE_DEG``) that
    is a blind piece of the other's part, or None.

    Blind: under ``BLIND_SHARE`` of its hits (:func:`_sighted_share`) land on points the other
    state's views saw; it lands only on a surface that state could not see (a surface the
    part's motion revealed, which staying put explains as well), so nothing it claims needs its
    motion. The other layer's hits must be sighted. Why: on the real laptop capture (a person
    closes the lid; the hands cover its far strip in the end state) a 70 deg turn carries that
    strip onto the table the lid revealed behind it, and the strip came out as a second lid
    beside the true 96 deg one, or as the only lid, in 5 of 12 turns of the world frame about
    the vertical (the voxel grid decides which motion wins the tied points). A blind layer
    alone (a lid raised towards the camera, which hides its own closed pose) is left as it is.
    O(N) for N moved points."""
    turns = [Rotation.from_matrix(layer.transform[:3, :3]).as_rotvec() for layer in (a, b)]
    if min(np.linalg.norm(turn) for turn in turns) < np.radians(TURNING_DEG):
        return None
    if axis_angle_deg(*turns) > SAME_HINGE_DEG:
        return None
    blind = [_sighted_share(ratings, layer) < BLIND_SHARE for layer in (a, b)]
    if blind[0] == blind[1]:
        return None
    return a if blind[0] else b


SIGHTED_SHARE = 0.5        # a layer at least this share of whose hits land on seen points is sighted


def _flag_revealed(ratings: Ratings, layers: list[MotionLayer]) -> None:
    """Mark each blind layer (under ``BLIND_SHARE`` of its hits on seen points,
    :func:`_sighted_share`) that touches a sighted layer (at least ``SIGHTED_SHARE``) turning by
    ``TURNING_DEG`` or more, whatever its own axis: its motion lays its points almost only onto
    surfaces the other state could not see, which the sighted part's motion uncovered and which
    staying put explains as well. Unlike a blind piece (:func:`_blind_piece`, same hinge: it joins
    its part), it may be a part of its own, so it stays a part; the labeler lowers its confidence
    and says so.
    Measured on the real laptop capture with 1 % per-pixel depth noise in both states (one draw):
    a 127.6 deg turn 41 deg off the lid's axis, 4 % of its hits seen, beside the lid (all seen),
    came out as a second lid turning 72 deg at confidence 0.75. A blind layer alone (a lid raised
    towards the camera hides its own closed pose) is not marked. O(L^2 P log N) for L layers."""
    sighted = [_sighted_share(ratings, layer) for layer in layers]
    for k, layer in enumerate(layers):
        if sighted[k] >= BLIND_SHARE:
            continue
        if any(sighted[j] >= SIGHTED_SHARE
               and np.degrees(rotation_angle(other.transform[:3, :3])) >= TURNING_DEG
               and _touching(ratings, layer, other, ratings.context.radius)
               for j, other in enumerate(layers) if j != k):
            layer.doubts.append(Doubt(REVEALED_TRUST, REVEALED_DOUBT))


IN_PLANE_SAME_TURN_DEG = 2.0  # two motions of one slab turn alike within this ...
IN_PLANE_MAX_SINE = 0.26      # ... and differ by a shift within 15 deg of the slab's plane


def _slid_in_plane(ratings: Ratings, big: MotionLayer, small: MotionLayer) -> bool:
    """Are two touching layers one slab whose two motions differ only by a shift in its own
    plane? A flat lid slid within its plane still lands on itself, so two motions with the same
    turn and translations a fifth of the lid apart each claim a patch of it (a clean laptop without
    masks came out as two lids, share 0.58 < ``MERGE_HIT_SHARE``). Twin drawers side by side are
    not: their fronts are coplanar but their travels differ along the fronts' normal. O(P) for
    the P points of both layers."""
    relative = np.linalg.inv(big.transform) @ small.transform
    if motion_size(relative)[0] > IN_PLANE_SAME_TURN_DEG:
        return False
    start = ratings.start.points[np.union1d(big.start, small.start)]
    end = ratings.end.points[np.union1d(big.end, small.end)]
    if len(start) < 30 or len(end) < 30:
        return False
    slab = slab_axes(end)
    if slab is None:
        return False
    # where the two motions put the start part's centroid, in the end state's slab frame
    origin = np.append(start.mean(axis=0), 1.0)
    shift = (small.transform @ origin - big.transform @ origin)[:3]
    length = float(np.linalg.norm(shift))
    return length == 0.0 or abs(float(slab[1][2] @ shift)) <= IN_PLANE_MAX_SINE * length


OWN_MOTION_MARGIN = 0.25    # a layer laying this much more of its points than a neighbour's motion is its own part


def _own_motion(ratings: Ratings, big: MotionLayer, small: MotionLayer) -> bool:
    """Does ``small`` slide by its own motion? True when both slide and its motion lays at least
    ``OWN_MOTION_MARGIN`` more of its points (tight hit radius) than ``big``'s does. One part seen
    as patches is laid about as well by either patch's motion; twin drawers touching side by side,
    pulled out by 0.218 and 0.245 object units, are not (their travels differ by ~1 inlier radius,
    so the full-radius test alone merged them). Slides only: the patches of one turning lid
    differ more far from their hinge (a box lid came out as 3 parts); slides as
    :func:`~.correspondence.slide_direction` reads them (small turns about far pivots too). O(P log N)."""
    if any(slide_direction(layer.transform, ratings.start.points[layer.start]) is None for layer in (big, small)):
        return False
    own = _hit_share(ratings, small.transform, small.start, small.end, ratings.radius)
    other = _hit_share(ratings, big.transform, small.start, small.end, ratings.radius)
    return own - other >= OWN_MOTION_MARGIN


def _touching(ratings: Ratings, a: MotionLayer, b: MotionLayer, radius: float) -> bool:
    """Do two layers touch (a point of one within 3 inlier radii of the other) in either state?"""
    for cloud, ia, ib in ((ratings.start, a.start, b.start), (ratings.end, a.end, b.end)):
        if len(ia) and len(ib):
            probe = ib[:: max(1, len(ib) // 500)]
            if nearest_gap(cloud.points[ia], cloud.points[probe], 3.0 * radius) < 3.0 * radius:
                return True
    return False


def _assign_points(ratings: Ratings, chosen: list[int]) -> list[MotionLayer]:
    """Every moved point follows the motion rating it best (hits first; off-colour hits count as
    none, :meth:`~.motion_ratings.Ratings.coloured_row`); ties and hidden-only
    points go to the motion whose hits lie nearest. Points rated <= 0 by every motion, and the
    pieces of a layer without a hit (:func:`_drop_pieces_without_hits`), stay unassigned."""
    if not chosen:
        return []
    n_start = len(ratings.start_moved)
    table = np.stack([ratings.coloured_row(k) for k in chosen])
    best = table.max(axis=0)
    points = np.concatenate([ratings.start.points[ratings.start_moved], ratings.end.points[ratings.end_moved]])
    state = np.concatenate([np.zeros(n_start, dtype=bool), np.ones(len(ratings.end_moved), dtype=bool)])
    owner = np.full(len(best), -1, dtype=np.int64)
    top = table >= best[None, :] - 1e-12
    unique_hit = (best >= 1.0) & (top.sum(axis=0) == 1)
    owner[unique_hit] = table[:, unique_hit].argmax(axis=0)
    pending = np.flatnonzero((best > 0) & (owner < 0))
    if len(pending):
        distance = np.full((len(chosen), len(pending)), np.inf)
        for slot in range(len(chosen)):
            for flag in (False, True):
                anchors = np.flatnonzero((owner == slot) & (state == flag))
                here = pending[state[pending] == flag]
                if len(anchors) == 0 or len(here) == 0:
                    continue
                d = cKDTree(points[anchors]).query(points[here], k=1)[0]
                distance[slot, np.searchsorted(pending, here)] = d
        distance[~top[:, pending]] = np.inf
        nearest = distance.argmin(axis=0)
        reachable = np.isfinite(distance.min(axis=0))
        owner[pending[reachable]] = nearest[reachable]
    _drop_pieces_without_hits(ratings, table, owner, points, state)
    layers = []
    for slot, k in enumerate(chosen):
        start_idx = ratings.start_moved[owner[:n_start] == slot]
        end_idx = ratings.end_moved[owner[n_start:] == slot]
        layers.append(MotionLayer(ratings.motions[k], ratings.physics[k], start_idx, end_idx, _charge(ratings, k)))
    return layers


def _drop_pieces_without_hits(ratings: Ratings, table: np.ndarray, owner: np.ndarray, points: np.ndarray,
                              state: np.ndarray) -> None:
    """Unassign (owner -1, in place) every piece of a layer that its motion never carries onto the
    other state's moved points: within each state, the layer's points linked at the inlier radius
    form pieces, and a piece joins only with at least one hit. Hidden credit alone is no evidence
    of rigid attachment: a hand on a door in one state, carried back by the door's turn, lands
    behind the cabinet (hidden) as well as the door's own sides do; only the sides touch the
    door's seen hits. table: (chosen, N) ratings; points / state: (N, 3) / (N,) of the moved
    points of both states. O(N log N)."""
    for slot in range(len(table)):
        for flag in (False, True):
            members = np.flatnonzero((owner == slot) & (state == flag))
            if len(members) == 0:
                continue
            pieces = radius_components(points[members], ratings.context.radius)
            hit_pieces = np.unique(pieces[table[slot, members] >= 1.0])
            owner[members[~np.isin(pieces, hit_pieces)]] = -1
