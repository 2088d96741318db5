"""Part correspondence between the two states as one assignment problem.

Every start group (the merged segments of one state that form a part candidate) is paired with
every end group it could be; each pair gets its best start->end rigid motion and a cost, and the
Hungarian algorithm picks the one-to-one pairing of least total cost. The cost carries:

* **appearance**: the symmetric overlap of the moved start group with the end group (and back),
  over the points the other state's views could see (a closed drawer shows only its front: the
  sides it hides inside the carcass are not charged), times colour agreement;
* **displacement relative to size**: a small charge per object diameter the pairing moves its
  points (identical siblings also register onto each other; the articulated pairing moves less);
* **physics**: the motion must be one a joint anchored on the static body can make. A small step
  along it from either state must not push the part into a surface of that state it was not
  already touching: a drawer slides out along its front's normal into free space, never sideways
  through the carcass rail or a neighbour; a door swings about a hinge on the body's edge;
* **mask ids**, when the masks agree across images (each group carries one id, no two groups of
  a state share one, and the states share their ids): a pair with equal ids is cheaper.

The pairing that costs least is kept; the best pairing that changes a moving pair is the
runner-up, and a small cost gap between the two makes the labeler say so (honest ambiguity).

Speed: pairs are screened before any registration (size ratio; a pair whose start group already
stays put on another end group is not registered), registered coarse (a few hundred points, cheap
hypotheses) and refined only when the coarse motion explains enough of both groups.
Cost O(G_s G_e (R_c + S log M)) for G groups per state, a coarse registration R_c, S samples
scored against M group points, plus O(P R_f) refinements of the P surviving pairs.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..geometry.axis_turns import axis_turns
from ..geometry.clouds import pca_normals
from ..geometry.planes import manhattan_frame
from ..geometry.sweep import blocked_step_share
from ..joints.config import FitConfig
from ..joints.select import FAR_PIVOT_MAX_TURN_DEG
from ..parallel import in_parallel
from ..types import LabelledCloud
from .colour import rg_chromaticity
from ..geometry.free_space import StateViews, visible_fraction

TRAVEL_PENALTY = 0.25       # cost per object diameter a pairing moves its points
PHYSICS_WEIGHT = 1.5        # cost per share of a part pushed into a surface by a step of its motion
MASK_ID_WEIGHT = 0.15       # cost bonus for equal mask ids (only when ids agree across images)
SLIDE_WEIGHT = 0.3          # cost per sine between a slide and the outward normal of the part's slot
SLIDE_MAX_DEG = 5.0         # motions turning less than this are slides for that cost
FRONT_SHARE = 0.4           # a part's front: the static axis at least this share of its common surface faces
IDENTITY_PREFERENCE = 0.05  # a motion must beat "stayed put" by this overlap share to be taken
IDENTITY_TRUSTED_SCORE = 0.6  # identity overlap above which "stayed put" is preferred on near-ties
SETTLED_STATIC_SCORE = 0.85  # a start group staying put this well on an end group is not registered elsewhere
COARSE_POINTS = 150         # points per group in the coarse registration
COARSE_KEEP = 0.5           # a coarse motion below this share of the minimum match score is dropped
GLOBAL_POINTS = 300         # ... on this many points
GLOBAL_PER_GROUP = 2        # ... for at most this many pairs of each start group
GLOBAL_BELOW = 0.75         # a refined pair scoring below this also tries the global registration
TURN_TIE = 0.05             # scores this close count as tied: the smaller rotation wins
ICP_POINTS = 600            # refine_icp works on at most this many points per set
SCREEN_RADII = 3.0          # the quick screen counts points within this many inlier radii ...
SUBPART_REFINE = 4          # ... and this many of its best hypotheses are refined and scored
STEP_SAMPLE = 400           # physics (geometry.sweep): steps of at most this many points per state
UNMATCHED = 1e3             # cost of a pair that may not be matched
AMBIGUITY_MARGIN = 0.08     # runner-up pairing within this total cost: the pairing is ambiguous


@dataclass
class Group:
    """Merged segments of one state: segment ids, point indices (into the state's cloud), the
    (single) mask id when the masks carry one, and scratch data."""

    segments: list[int]
    indices: np.ndarray
    mask_ids: frozenset = frozenset()
    part: int = -1
    extra: dict = field(default_factory=dict)


@dataclass
class PairCandidate:
    """A (start group i, end group j) pairing and its best motion.

    transform: (4, 4) start->end; score: appearance in [0, 1]; identity: the "stayed put" score;
    travel: median displacement of the start samples (labeler units); physics: blocked-step share
    in [0, 1]; slide: for slides, the sine between the slide and the outward normal of the face of
    the static body the part sits at (0 = straight out of its slot); mask: +1 equal mask ids, -1 different, 0 unknown; how: "identity" | "registration" | "hint";
    named_conflict: both groups carry an id that both states agree on (``Group.mask_ids``) and
    the ids differ -- the user's masks say these are different parts, so the pair is not allowed.
    """

    i: int
    j: int
    transform: np.ndarray
    score: float
    identity: float
    travel: float = 0.0
    physics: float = 0.0
    slide: float = 0.0
    mask: float = 0.0
    how: str = "identity"
    named_conflict: bool = False


@dataclass
class PairContext:
    """Everything pair scoring needs about the two states (labeler frame, one unit)."""

    start: LabelledCloud
    end: LabelledCloud
    start_groups: list[Group]
    end_groups: list[Group]
    radius: float
    diameter: float
    start_views: StateViews
    end_views: StateViews
    samples: int
    registration_points: int
    seed: int
    frame: np.ndarray | None = None     # (3, 3) principal axes of the static body (guess)
    box: tuple[np.ndarray, np.ndarray] | None = None  # its bounding box (min, max) in that frame
    start_samples: list[np.ndarray] = field(default_factory=list)
    end_samples: list[np.ndarray] = field(default_factory=list)
    start_trees: list[cKDTree] = field(default_factory=list)
    end_trees: list[cKDTree] = field(default_factory=list)
    start_obstacles: list[cKDTree | None] = field(default_factory=list)
    _state_trees: dict = field(default_factory=dict)
    end_obstacles: list[cKDTree | None] = field(default_factory=list)
    turning_in_place: set[tuple[int, int]] = field(default_factory=set)  # (i, j) scored without brightness

    def prepare(self) -> None:
        """Samples, group trees and the per-group obstacle trees (the state without the group)."""
        rng = np.random.default_rng(self.seed + 1)
        self.start_samples = [_sample(g.indices, self.samples, rng) for g in self.start_groups]
        self.end_samples = [_sample(g.indices, self.samples, rng) for g in self.end_groups]
        self.start_trees = [cKDTree(self.start.points[g.indices]) for g in self.start_groups]
        self.end_trees = [cKDTree(self.end.points[g.indices]) for g in self.end_groups]
        self.start_obstacles = [None] * len(self.start_groups)
        self.end_obstacles = [None] * len(self.end_groups)
        if self.frame is None and self.start_groups:
            self.set_static(self.start_groups[0].indices)

    def set_static(self, indices: np.ndarray) -> None:
        """Take the start points ``indices`` as the static body: its principal frame and box."""
        points = self.start.points[indices]
        if len(points) < 3:
            return
        self.frame = manhattan_frame(points)
        local = points @ self.frame
        self.box = (np.percentile(local, 1, axis=0), np.percentile(local, 99, axis=0))

    def outward_normal(self, start_points: np.ndarray, end_points: np.ndarray, start_common: np.ndarray,
                       end_common: np.ndarray) -> np.ndarray | None:
        """Unit outward normal of a part's slot (up to sign), or None.

        The static box face the part's centre sticks out of by more than 2 inlier radii in either
        state; else the part's front: the static frame axis that the normals of the commonly seen
        points face most (at least ``FRONT_SHARE`` of them within 25 deg, and 1.5 x the next axis).
        """
        if self.frame is None:
            return None
        if self.box is not None:
            low, high = self.box
            for points in (start_points, end_points):
                if len(points) == 0:
                    continue
                centre = points.mean(axis=0) @ self.frame
                outside = np.concatenate([low - centre, centre - high])
                if outside.max() > 2.0 * self.radius:
                    return self.frame[:, int(np.argmax(outside)) % 3]
        normals = [self.normals(state, points) for state, points in (("start", start_common), ("end", end_common))]
        normals = np.concatenate([n for n in normals if len(n)]) if any(len(n) for n in normals) else np.zeros((0, 3))
        if len(normals) < 10:
            return None
        facing = (np.abs(normals @ self.frame) > np.cos(np.radians(25.0))).sum(axis=0) / len(normals)
        order = np.argsort(-facing)
        if facing[order[0]] < FRONT_SHARE or facing[order[0]] < 1.5 * facing[order[1]]:
            return None
        return self.frame[:, order[0]]

    def obstacles(self, state: str, k: int) -> cKDTree | None:
        """KD-tree over the state's points outside group k (built on first use)."""
        cache = self.start_obstacles if state == "start" else self.end_obstacles
        if cache[k] is None:
            cloud = self.start if state == "start" else self.end
            group = (self.start_groups if state == "start" else self.end_groups)[k]
            keep = np.ones(len(cloud), dtype=bool)
            keep[group.indices] = False
            cache[k] = cKDTree(cloud.points[keep]) if keep.any() else False
        return cache[k] or None

    def normals(self, state: str, points: np.ndarray, limit: int = 400) -> np.ndarray:
        """Unit surface normals (local PCA over 10 neighbours in the state's cloud) of up to
        ``limit`` of ``points``. O(L log N)."""
        if len(points) == 0:
            return np.zeros((0, 3))
        points = points[:: max(1, len(points) // limit)]
        if state not in self._state_trees:
            self._state_trees[state] = cKDTree((self.start if state == "start" else self.end).points)
        cloud = (self.start if state == "start" else self.end).points
        return pca_normals(cloud, points, 10, tree=self._state_trees[state])


def _sample(indices: np.ndarray, limit: int, rng: np.random.Generator) -> np.ndarray:
    if len(indices) <= limit:
        return indices
    return indices[np.sort(rng.choice(len(indices), limit, replace=False))]


def apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ transform[:3, :3].T + transform[:3, 3]


def motion_size(transform: np.ndarray) -> tuple[float, float]:
    """(rotation angle in degrees, translation length) of a (4, 4) rigid motion."""
    angle = float(np.degrees(np.linalg.norm(Rotation.from_matrix(transform[:3, :3]).as_rotvec())))
    return angle, float(np.linalg.norm(transform[:3, 3]))


def pair_score(ctx: PairContext, i: int, j: int, transform: np.ndarray,
               samples: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """Appearance score of start group i moved by ``transform`` onto end group j, in [0, 1]
    (:func:`set_score` on the groups' samples). O(S (log M + V))."""
    source_idx, target_idx = samples or (ctx.start_samples[i], ctx.end_samples[j])
    return set_score(ctx.start, ctx.end, source_idx, target_idx, ctx.start_trees[i], ctx.end_trees[j],
                     ctx.end_groups[j].indices, transform, ctx.radius, ctx.start_views, ctx.end_views,
                     without_brightness=(i, j) in ctx.turning_in_place)


def set_score(start: LabelledCloud, end: LabelledCloud, source_idx: np.ndarray, target_idx: np.ndarray,
              source_tree: cKDTree, target_tree: cKDTree, target_members: np.ndarray, transform: np.ndarray,
              radius: float, start_views: StateViews, end_views: StateViews,
              without_brightness: bool = False) -> float:
    """Symmetric overlap of a start point set moved by ``transform`` and an end point set, over
    what the views could judge, times colour agreement; in [0, 1].

    source_idx / target_idx: sample indices (into the state clouds); source_tree / target_tree:
    KD-trees over ALL points of the start / end set, the latter in the order of ``target_members``
    (their indices). Forward: the share of moved start samples landing within ``radius`` of the
    end set among those the end views could judge (:func:`~sparseart.geometry.free_space.visible_fraction`; all
    without views); backward the same for the end samples moved back. Colour: 1 - 0.5 min(1,
    mean |difference| / 0.25) over the forward hits, of their RGB, or ``without_brightness`` of
    their rg chromaticity (a part turning in place changes its shading point by point while
    standing still keeps it: :mod:`~sparseart.labelers.colour`). O(S (log M + V)).
    """
    source, target = start.points[source_idx], end.points[target_idx]
    moved = apply(transform, source)
    distance, nearest = target_tree.query(moved, k=1, distance_upper_bound=radius)
    hits = distance < radius
    forward = visible_fraction(end_views.classify(moved), hits) if end_views else float(hits.mean())
    back = apply(np.linalg.inv(transform), target)
    back_hits = source_tree.query(back, k=1, distance_upper_bound=radius)[0] < radius
    backward = (visible_fraction(start_views.classify(back), back_hits) if start_views
                else float(back_hits.mean()))
    if hits.any():
        end_colours = end.colors[target_members]
        colours = (start.colors[source_idx][hits], end_colours[nearest[hits]])
        if without_brightness:
            colours = tuple(rg_chromaticity(c) for c in colours)
        difference = np.abs(colours[0] - colours[1]).mean()
        colour = 1.0 - 0.5 * min(1.0, difference / 0.25)
    else:
        colour = 0.5
    return 0.5 * (forward + backward) * colour


def register_sets(ctx: PairContext, start_idx: np.ndarray, end_idx: np.ndarray,
                  rng: np.random.Generator) -> tuple[float, np.ndarray | None]:
    """Register any start point set onto any end point set (indices into the state clouds) the
    way :func:`_register_pair` registers groups. Returns (score, motion)."""
    if len(start_idx) < 3 or len(end_idx) < 3:
        return -1.0, None
    group_s, group_e = Group([-1], np.asarray(start_idx)), Group([-1], np.asarray(end_idx))
    sub = PairContext(ctx.start, ctx.end, [group_s], [group_e], ctx.radius, ctx.diameter, ctx.start_views,
                      ctx.end_views, ctx.samples, ctx.registration_points, ctx.seed, frame=ctx.frame, box=ctx.box)
    sub.start_samples = [_sample(group_s.indices, ctx.samples, rng)]
    sub.end_samples = [_sample(group_e.indices, ctx.samples, rng)]
    sub.start_trees = [cKDTree(ctx.start.points[group_s.indices])]
    sub.end_trees = [cKDTree(ctx.end.points[group_e.indices])]
    return _register_pair(sub, 0, 0, 0.0, _coarse_samples(sub, 0, 0, rng))


def blocked_share(ctx: PairContext, i: int, j: int, transform: np.ndarray) -> float:
    """Physics: the share of a part pushed into another surface by a small step of its motion.

    From the start state, group i's samples are moved a step along the motion (screw
    interpolation, :func:`~sparseart.geometry.sweep.blocked_step_share`: at least 3 inlier radii
    for the median point); a sample that lands within the inlier radius of a start point outside
    the group, where it was not already touching one, moving into that surface rather than along
    it, is blocked. From the end state, group j's samples step back along the inverse motion the
    same way. Returns the mean over both states of the largest blocked share over the steps, in
    [0, 1]; 0 for motions too small to step. O(S log N) per step.
    """
    shares = []
    for state, k, idx, direction in (("start", i, ctx.start_samples[i], 1.0),
                                     ("end", j, ctx.end_samples[j], -1.0)):
        cloud = ctx.start if state == "start" else ctx.end
        obstacles = ctx.obstacles(state, k)
        points = cloud.points[idx[:: max(1, len(idx) // STEP_SAMPLE)]]
        if obstacles is None or len(points) == 0:
            shares.append(0.0)
            continue
        shares.append(blocked_step_share(
            transform, direction, points, ctx.radius,
            lambda p, tree=obstacles: tree.query(p, k=1, distance_upper_bound=ctx.radius)[0] < ctx.radius,
            surface=obstacles))
    return float(np.mean(shares))


def slide_sine(ctx: PairContext, i: int, j: int, transform: np.ndarray) -> float:
    """A slide (rotation below ``SLIDE_MAX_DEG``) should leave the part's slot along the slot's
    outward normal (a drawer slides along its front's normal; a slide across its face passes
    through the carcass or a neighbour). Returns the sine between the slide and that normal; 0 for
    turns or when no normal is found. The normal (:meth:`PairContext.outward_normal`) is the
    static box face the part sticks out of, else the part's front: the static frame axis most of
    the surface seen in both states faces. O(S log N)."""
    source = ctx.start.points[ctx.start_samples[i]]
    target = ctx.end.points[ctx.end_samples[j]]
    hits_s = ctx.end_trees[j].query(apply(transform, source), k=1, distance_upper_bound=ctx.radius)[0] < ctx.radius
    hits_e = ctx.start_trees[i].query(apply(np.linalg.inv(transform), target), k=1,
                                      distance_upper_bound=ctx.radius)[0] < ctx.radius
    return slide_sine_points(ctx, transform, source, target, source[hits_s], target[hits_e])


def slide_sine_points(ctx: PairContext, transform: np.ndarray, start_points: np.ndarray,
                      end_points: np.ndarray, start_common: np.ndarray | None = None,
                      end_common: np.ndarray | None = None) -> float:
    """:func:`slide_sine` for a part given by its points in both states (and the points of each
    state that the motion carries onto the other: the commonly seen surface; all when None)."""
    direction = slide_direction(transform, start_points)
    if direction is None:
        return 0.0
    normal = ctx.outward_normal(start_points, end_points,
                                start_points if start_common is None else start_common,
                                end_points if end_common is None else end_common)
    if normal is None:
        return 0.0
    cosine = abs(float(direction @ normal))
    return float(np.sqrt(max(0.0, 1.0 - cosine * cosine)))


def slide_direction(transform: np.ndarray, start_points: np.ndarray) -> np.ndarray | None:
    """(3,) unit direction of a motion that is a slide, else None: turning less than
    ``SLIDE_MAX_DEG``, or less than ``FAR_PIVOT_MAX_TURN_DEG`` about a pivot more than
    ``FitConfig.far_pivot_factor`` part radii away (then the part's centroid displacement): the
    joint fitter's type test (:func:`~sparseart.joints.select.choose_type`) reads such a motion as a
    slide, with the same two bounds. Why: twin drawers side by side were paired
    by a 6.9 deg "turn" that carried one drawer a whole drawer width sideways into its neighbour's
    place, and escaped the slot charge. start_points (N, 3) the part at start. O(N)."""
    angle, shift = motion_size(transform)
    if angle < SLIDE_MAX_DEG:
        return transform[:3, 3] / shift if shift > 0 else None
    if angle >= FAR_PIVOT_MAX_TURN_DEG or len(start_points) == 0:
        return None
    centre = start_points.mean(axis=0)
    displacement = transform[:3, :3] @ centre + transform[:3, 3] - centre
    length = float(np.linalg.norm(displacement))
    radius = float(np.sqrt(((start_points - centre) ** 2).sum(axis=1).mean()))
    pivot_distance = length / (2.0 * np.sin(np.radians(angle) / 2.0))
    if pivot_distance <= FitConfig.far_pivot_factor * radius:
        return None
    return displacement / length


NAMED_ID_SHARE = 0.5        # ids occurring in both states must cover this share of each state's mask points
NAMED_SAME_PLACE = 0.6      # ... and this share (by points) of an id's views must cover one place
BOX_PAD_SHARE = 0.02        # segment boxes are padded by this share of the cloud's extent


def named_mask_ids(start: LabelledCloud, end: LabelledCloud) -> frozenset[int]:
    """The mask ids that name parts across images, before any grouping: the ids occurring in both
    states, when there are at least two of them, their points make up at least ``NAMED_ID_SHARE``
    of each state's mask points, and one id's segments in different images of a state cover one
    place (:func:`_ids_keep_their_place`); empty otherwise. Scrambled ids rarely repeat; a per-image
    segmenter's ids (1..k in every image: SAM, the built-in one) repeat but name different
    surfaces in different images -- measured: without the place test the built-in segmenter's
    segments stopped merging across views and a scene took minutes instead of 5 s.
    Two segments with different named ids are never merged (:func:`~.rules._merge_across_frames`:
    touching parts stay apart), and two groups with different named ids are never paired
    (:func:`pair_cost`), even when a part is too small to form a group in one state. O(N)."""
    def id_counts(cloud: LabelledCloud) -> dict[int, int]:
        segments, counts = np.unique(cloud.segment[cloud.segment >= 0], return_counts=True)
        found: dict[int, int] = {}
        for segment, count in zip(segments.tolist(), counts.tolist()):
            if segment in cloud.segment_source:
                mask_id = cloud.segment_source[segment][1]
                found[mask_id] = found.get(mask_id, 0) + count
        return found

    start_ids, end_ids = id_counts(start), id_counts(end)
    shared = set(start_ids) & set(end_ids)
    if len(shared) < 2:
        return frozenset()
    for found in (start_ids, end_ids):
        if sum(found[i] for i in shared) < NAMED_ID_SHARE * max(sum(found.values()), 1):
            return frozenset()
    if not all(_ids_keep_their_place(cloud, shared) for cloud in (start, end)):
        return frozenset()
    return frozenset(int(i) for i in shared)


def _ids_keep_their_place(cloud: LabelledCloud, ids: set[int]) -> bool:
    """Does each id mark one place across the state's images? For every id seen in two frames,
    every pair of its frame segments is judged: their bounding boxes (1st-99th percentile, padded
    by ``BOX_PAD_SHARE`` of the cloud's extent: a flat rack has a flat box) must overlap on every
    axis by at least half of the smaller one. True when the agreeing pairs hold at least
    ``NAMED_SAME_PLACE`` of the judged pairs' points (the smaller segment of each pair), or when no
    id is seen twice. O(N log N + P) for P segment pairs (the points are grouped by one sort)."""
    pad = BOX_PAD_SHARE * float(np.linalg.norm(np.ptp(cloud.points, axis=0))) if len(cloud) else 0.0
    order = np.argsort(cloud.segment, kind="stable")
    segments, first, counts = np.unique(cloud.segment[order], return_index=True, return_counts=True)
    boxes: dict[int, list[tuple[np.ndarray, np.ndarray, int]]] = {}
    for segment, start, count in zip(segments.tolist(), first.tolist(), counts.tolist()):
        mask_id = cloud.segment_source[segment][1] if segment in cloud.segment_source else None
        if mask_id not in ids or count < 10:
            continue
        points = cloud.points[order[start:start + count]]
        low, high = np.percentile(points, [1, 99], axis=0)
        boxes.setdefault(mask_id, []).append((low - pad, high + pad, len(points)))
    agree = judged = 0.0
    for views in boxes.values():
        for k, (low_a, high_a, n_a) in enumerate(views):
            for low_b, high_b, n_b in views[k + 1:]:
                overlap = np.minimum(high_a, high_b) - np.maximum(low_a, low_b)
                smaller = np.minimum(high_a - low_a, high_b - low_b)
                weight = float(min(n_a, n_b))
                judged += weight
                agree += weight * bool(np.all(overlap >= 0.5 * smaller))
    return judged == 0.0 or agree >= NAMED_SAME_PLACE * judged


def mask_agreement(start: LabelledCloud, end: LabelledCloud, start_groups: list[Group],
                   end_groups: list[Group], named: frozenset[int] = frozenset(),
                   split: frozenset[int] = frozenset()) -> np.ndarray | None:
    """(G_s, G_e) +1 / -1 for equal / different mask ids, 0 where a group carries several ids (a
    mask merge), or None when the ids do not agree across images: at least two ids, half of each
    state's single ids, and the ids of half of each state's groups must occur in both states.
    Judged per group, so one merged or split mask (ragged real masks) no longer silences the ids of
    every other part (it did: a cabinet with four look-alike drawers lost its only cue to which
    drawer is which). Also records on
    every group its id when both states carry it, in a group or among the points (``named``, from
    :func:`named_mask_ids`: a part too small to form a group in one state still owns its id)
    (``Group.mask_ids``; empty otherwise): such ids name distinct parts (:func:`distinct_by_masks`).
    ``split``: ids found to be split pieces of other parts (:func:`~.mask_repair.split_mask_ids`):
    a group carrying one counts as carrying no single id. O(G_s G_e)."""
    def ids(cloud: LabelledCloud, groups: list[Group]) -> list[int | None]:
        result = []
        for group in groups:
            found = {cloud.segment_source[s][1] for s in group.segments if s in cloud.segment_source}
            result.append(next(iter(found)) if len(found) == 1 and not found & split else None)
        return result

    start_ids, end_ids = ids(start, start_groups), ids(end, end_groups)
    start_single = {i for i in start_ids if i is not None}
    end_single = {i for i in end_ids if i is not None}
    shared = start_single & end_single
    if len(shared) < 2 or len(shared) < 0.5 * len(start_single) or len(shared) < 0.5 * len(end_single):
        return None
    if any(sum(i in shared for i in found) < 0.5 * len(found) for found in (start_ids, end_ids)):
        return None     # most groups carry several ids or unshared ones: ids do not name parts
    for groups, found in ((start_groups, start_ids), (end_groups, end_ids)):
        for group, mask_id in zip(groups, found):
            group.mask_ids = frozenset({mask_id}) if mask_id in shared | named else frozenset()
    agreement = np.zeros((len(start_ids), len(end_ids)))
    for i, a in enumerate(start_ids):
        for j, b in enumerate(end_ids):
            if a is not None and b is not None:
                agreement[i, j] = 1.0 if a == b else -1.0
    return agreement


def distinct_by_masks(a: Group, b: Group) -> bool:
    """True when two groups of one state carry different mask ids that both states agree on
    (:func:`mask_agreement`): the user's masks say they are different parts, whatever their
    motions (two adjacent drawers pulled out by similar lengths). A piece split off by a new id in
    one view has no agreed id and may still join its part."""
    return bool(a.mask_ids) and bool(b.mask_ids) and a.mask_ids != b.mask_ids


def score_pairs(ctx: PairContext, match_min_score: float, motion_hints: list[np.ndarray],
                mask_ids: np.ndarray | None) -> dict[tuple[int, int], PairCandidate]:
    """The best motion of every plausible pair (module doc: screening, coarse-to-fine).

    Returns {(i, j): PairCandidate} for the pairs scored (pairs ruled out by size are absent).
    """
    candidates: dict[tuple[int, int], PairCandidate] = {}
    eye = np.eye(4)
    identity = {}
    for i, group_i in enumerate(ctx.start_groups):
        for j, group_j in enumerate(ctx.end_groups):
            ratio = len(group_i.indices) / max(len(group_j.indices), 1)
            if ratio > 20 or ratio < 0.05:
                continue
            identity[(i, j)] = pair_score(ctx, i, j, eye)
    # A start group that stays put on an end group, better than on any other, is settled: neither
    # it nor that end group is registered against anything else (overlap rules those pairs out).
    settled_start, settled_end = set(), set()
    for (i, j), value in identity.items():
        if value < SETTLED_STATIC_SCORE:
            continue
        row = max(v for (a, _), v in identity.items() if a == i)
        column = max(v for (_, b), v in identity.items() if b == j)
        if value >= row and value >= column:
            settled_start.add(i)
            settled_end.add(j)
    if settled_start:
        ctx.set_static(np.concatenate([ctx.start_groups[i].indices for i in sorted(settled_start)]))
    rng = np.random.default_rng(ctx.seed + 3)
    keys = [key for key in sorted(identity) if key[0] not in settled_start and key[1] not in settled_end]
    # Pairs whose identity overlap is trusted may be a part turning about its own round body (a
    # faucet's cap with its lever): they search turns about the static axes, and all their motions,
    # standing still included, are compared without brightness (a turn changes the shading)
    ctx.turning_in_place = {key for key in keys if identity[key] >= IDENTITY_TRUSTED_SCORE}
    for key in sorted(ctx.turning_in_place):
        identity[key] = pair_score(ctx, *key, eye)
    # the coarse samples drawn in key order, then the pairs registered side by side (pure given them)
    draws = [_coarse_samples(ctx, i, j, rng) for i, j in keys]
    registered = in_parallel(lambda item: _register_pair(ctx, *item[0], match_min_score, item[1],
                                                         item[0] in ctx.turning_in_place),
                             list(zip(keys, draws)))
    registrations = dict(zip(keys, registered))
    # Pairs the cheap hypotheses explain poorly get the global registration too: the best
    # ``GLOBAL_PER_GROUP`` such pairs of every start group (the rest are not its partner anyway).
    for i in sorted({key[0] for key in registrations}):
        row = sorted((-value[0], key) for key, value in registrations.items()
                     if key[0] == i and value[1] is not None and value[0] < GLOBAL_BELOW)
        for _, key in row[:GLOBAL_PER_GROUP]:
            registrations[key] = _global_retry(ctx, key[0], key[1], registrations[key])
    for (i, j), stay in sorted(identity.items()):
        best_score, best_transform, how = stay, eye, "identity"
        registered_score, registered = -1.0, None
        if i not in settled_start and j not in settled_end:
            registered_score, registered = registrations[(i, j)]
        if motion_hints:
            hint_scores = [pair_score(ctx, i, j, h) for h in motion_hints]
            k = int(np.argmax(hint_scores))
            if hint_scores[k] > registered_score:
                source = ctx.start.points[ctx.start_samples[i]]
                target = ctx.end.points[ctx.end_samples[j]]
                polished = refine_icp(source, target, motion_hints[k], ctx.radius)
                polished_score = pair_score(ctx, i, j, polished)
                registered_score, registered = max((hint_scores[k], motion_hints[k]), (polished_score, polished),
                                                   key=lambda st: st[0])
                how = "hint"
        # The preference protects well-seen static surfaces; a weak identity overlap (a part
        # mostly hidden in one state, whose visible edge happens to land on itself) earns none.
        preference = IDENTITY_PREFERENCE if stay >= IDENTITY_TRUSTED_SCORE else 0.0
        if registered is not None and registered_score > stay + preference:
            best_score, best_transform = registered_score, registered
            how = how if how == "hint" else "registration"
        else:
            how = "identity"
        source = ctx.start.points[ctx.start_samples[i]]
        travel = float(np.median(np.linalg.norm(apply(best_transform, source) - source, axis=1))) if len(source) else 0.0
        candidate = PairCandidate(i, j, best_transform, float(best_score), float(stay), travel=travel,
                                  mask=float(mask_ids[i, j]) if mask_ids is not None else 0.0, how=how,
                                  named_conflict=distinct_by_masks(ctx.start_groups[i], ctx.end_groups[j]))
        if how != "identity" and best_score >= match_min_score:
            candidate.physics = blocked_share(ctx, i, j, best_transform)
            candidate.slide = slide_sine(ctx, i, j, best_transform)
        candidates[(i, j)] = candidate
    return candidates


def _coarse_samples(ctx: PairContext, i: int, j: int,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
    """The coarse points of a pair (``COARSE_POINTS`` random sample indices of start group i and
    of end group j; None when either has fewer than 3), drawn from ``rng``."""
    start_idx, end_idx = ctx.start_samples[i], ctx.end_samples[j]
    if len(start_idx) < 3 or len(end_idx) < 3:
        return None
    coarse_s = start_idx[np.sort(rng.choice(len(start_idx), min(COARSE_POINTS, len(start_idx)), replace=False))]
    coarse_e = end_idx[np.sort(rng.choice(len(end_idx), min(COARSE_POINTS, len(end_idx)), replace=False))]
    return coarse_s, coarse_e


def _register_pair(ctx: PairContext, i: int, j: int, match_min_score: float,
                   coarse_samples: tuple[np.ndarray, np.ndarray] | None,
                   stays_on_itself: bool = False) -> tuple[float, np.ndarray | None]:
    """Coarse-to-fine registration of start group i onto end group j, from its coarse points
    (:func:`_coarse_samples`; None: too few points, no registration).

    Coarse: every cheap hypothesis (centroid shift, principal-frame turns, the smaller group's
    box slid against each face of the larger one -- a closed drawer shows only its front) is
    screened on ``COARSE_POINTS`` points per group; the best ``SUBPART_REFINE`` are refined by
    symmetric trimmed ICP on those points. A pair that ``stays_on_itself`` (its identity overlap is
    trusted, ``IDENTITY_TRUSTED_SCORE``: a part turning about its own round body, whose cap lands on
    itself) also gets the best turns about each static axis
    (:func:`~sparseart.geometry.axis_turns.axis_turns`: every angle, the shift by correlation):
    the screen keeps near-identity hypotheses there, and stayed-put wins unless a turn beats it. A pair whose best coarse score is below ``COARSE_KEEP``
    x ``match_min_score`` is dropped there; otherwise the best is refined on the full samples.
    Returns (score on the full samples, motion). O(H S_c log S_c + I S log S).
    """
    if coarse_samples is None:
        return -1.0, None
    start_idx, end_idx = ctx.start_samples[i], ctx.end_samples[j]
    coarse_s, coarse_e = coarse_samples
    source, target = ctx.start.points[coarse_s], ctx.end.points[coarse_e]
    hypotheses = _hypotheses(source, target) + _box_slides(source, target, ctx.frame)
    # Screen by the share of near points both ways (no views, a loose radius: a hypothesis a few
    # radii off is refined below), then refine and score the best few in full.
    loose = SCREEN_RADII * ctx.radius
    source_tree, target_tree = cKDTree(source), cKDTree(target)
    quick = []
    for k, t in enumerate(hypotheses):
        forward = target_tree.query(apply(t, source), k=1, distance_upper_bound=loose)[0] < loose
        backward = source_tree.query(apply(np.linalg.inv(t), target), k=1, distance_upper_bound=loose)[0] < loose
        quick.append((-(forward.mean() + backward.mean()), k))
    quick.sort()
    options = []
    for _, k in quick[:SUBPART_REFINE]:
        refined = refine_icp(source, target, hypotheses[k], ctx.radius, source_tree=source_tree,
                             target_tree=target_tree)
        options += [(pair_score(ctx, i, j, option, coarse_samples), option) for option in (hypotheses[k], refined)]
    if stays_on_itself:   # the screen above keeps the near-identity hypotheses of such a part
        options += _turns_about_static_axes(ctx, i, j, coarse_samples, source_tree, target_tree)
    best_score, best = prefer_small_turns(options)
    if best is None or best_score < COARSE_KEEP * match_min_score:
        return (pair_score(ctx, i, j, best) if best is not None else -1.0), best
    fine = refine_icp(ctx.start.points[start_idx], ctx.end.points[end_idx], best, ctx.radius)
    return prefer_small_turns([(pair_score(ctx, i, j, best), best), (pair_score(ctx, i, j, fine), fine)])


def _turns_about_static_axes(ctx: PairContext, i: int, j: int, coarse_samples: tuple[np.ndarray, np.ndarray],
                             source_tree: cKDTree, target_tree: cKDTree) -> list[tuple[float, np.ndarray]]:
    """(coarse score, motion) of the best turns of start group i onto end group j about each of the
    static body's axes (its principal axes when no body is known yet), found on the groups' samples
    (:func:`~sparseart.geometry.axis_turns.axis_turns`) and refined by ICP on the coarse points
    (whose trees are given). O(K A G log G + K I S_c log S_c)."""
    source, target = ctx.start.points[coarse_samples[0]], ctx.end.points[coarse_samples[1]]
    group = ctx.start.points[ctx.start_samples[i]]
    axes = ctx.frame.T if ctx.frame is not None else np.linalg.svd(group - group.mean(axis=0), full_matrices=False)[2]
    options = []
    for turn in axis_turns(group, ctx.end.points[ctx.end_samples[j]], axes, ctx.radius):
        refined = refine_icp(source, target, turn, ctx.radius, source_tree=source_tree, target_tree=target_tree)
        options.append((pair_score(ctx, i, j, refined, coarse_samples), refined))
    return options


def _global_retry(ctx: PairContext, i: int, j: int, current: tuple[float, np.ndarray]) -> tuple[float, np.ndarray]:
    """The global registration's hypotheses with point-to-plane ICP (turning parts seen from
    changing sides), kept when it scores better than ``current`` (or ties with a smaller turn)."""
    from sparseart.geometry.icp import register_rigid

    found = register_rigid(ctx.start.points[ctx.start_samples[i]], ctx.end.points[ctx.end_samples[j]],
                           max_points=GLOBAL_POINTS, use_fpfh=False, seed=ctx.seed).transform
    return prefer_small_turns([current, (pair_score(ctx, i, j, found), found)])


def prefer_small_turns(options: list[tuple[float, np.ndarray]]) -> tuple[float, np.ndarray | None]:
    """The best-scoring (score, motion), except that among motions within ``TURN_TIE`` of the best
    score the smallest rotation wins (a flat or symmetric part registers onto itself turned
    over almost as well; real joints rarely turn that far). (-1, None) for no options."""
    if not options:
        return -1.0, None
    top = max(score for score, _ in options)
    ties = [(motion_size(m)[0], -score, k) for k, (score, m) in enumerate(options) if score >= top - TURN_TIE]
    _, _, k = min(ties)
    return options[k]


def _hypotheses(source: np.ndarray, target: np.ndarray) -> list[np.ndarray]:
    """Centroid shift and the four proper principal-frame turns taking source onto target."""
    source_centre, target_centre = source.mean(axis=0), target.mean(axis=0)
    shift = np.eye(4)
    shift[:3, 3] = target_centre - source_centre
    result = [shift]
    if len(source) >= 4 and len(target) >= 4:
        frames = []
        for cloud, centre in ((source, source_centre), (target, target_centre)):
            frame = np.linalg.svd(cloud - centre, full_matrices=False)[2].T
            if np.linalg.det(frame) < 0:
                frame[:, 2] *= -1
            frames.append(frame)
        for flip in ([1, 1, 1], [-1, -1, 1], [-1, 1, -1], [1, -1, -1]):
            rotation = frames[1] @ np.diag(flip) @ frames[0].T
            transform = np.eye(4)
            transform[:3, :3] = rotation
            transform[:3, 3] = target_centre - rotation @ source_centre
            result.append(transform)
    return result


def refine_icp(source: np.ndarray, target: np.ndarray, init: np.ndarray, radius: float,
               schedule: tuple[float, ...] = (4.0, 2.0, 1.0), iterations: int = 8,
               source_tree: cKDTree | None = None, target_tree: cKDTree | None = None) -> np.ndarray:
    """Symmetric trimmed point-to-point ICP (deterministic, stable on flat parts where
    point-to-plane ICP slides away): correspondences both ways within ``schedule`` x ``radius``,
    least-squares rigid fit, ``iterations`` per distance. Returns the (4, 4) source -> target
    motion (``init`` when too few correspondences). O(I (N + M) log(N + M))."""
    from sparseart.geometry.transforms import kabsch

    if source_tree is None and len(source) > ICP_POINTS:
        source = source[np.linspace(0, len(source) - 1, ICP_POINTS).astype(np.int64)]
    if target_tree is None and len(target) > ICP_POINTS:
        target = target[np.linspace(0, len(target) - 1, ICP_POINTS).astype(np.int64)]
    source_tree = source_tree if source_tree is not None else cKDTree(source)
    target_tree = target_tree if target_tree is not None else cKDTree(target)
    transform = np.asarray(init, dtype=np.float64).copy()
    for factor in schedule:
        limit = factor * radius
        for _ in range(iterations):
            moved = apply(transform, source)
            forward, f_index = target_tree.query(moved, k=1, distance_upper_bound=limit)
            inverse = np.eye(4)
            inverse[:3, :3] = transform[:3, :3].T
            inverse[:3, 3] = -transform[:3, :3].T @ transform[:3, 3]
            back = apply(inverse, target)
            backward, b_index = source_tree.query(back, k=1, distance_upper_bound=limit)
            f_ok, b_ok = forward < limit, backward < limit
            if f_ok.sum() + b_ok.sum() < 6:
                return transform
            p = np.concatenate([source[f_ok], source[b_index[b_ok]]])
            q = np.concatenate([target[f_index[f_ok]], target[b_ok]])
            rotation, translation = kabsch(p, q)
            update = np.eye(4)
            update[:3, :3], update[:3, 3] = rotation, translation
            change = np.abs(update - transform).max()
            transform = update
            if change < 1e-4 * max(radius, 1e-12):
                break
    return transform


def _box_slides(source: np.ndarray, target: np.ndarray, frame: np.ndarray | None) -> list[np.ndarray]:
    """Pure translations putting the source's bounding box against the target's: per axis of
    ``frame`` (3, 3 columns; the static body's axes) the two boxes' minima, maxima, 2nd or 98th
    percentiles (a stray point does not move those; a thin front seen at a slant may hold fewer
    than 2 % of a part's points, which the extremes keep), or centres coincide (125 motions). O(N)."""
    frame = np.eye(3) if frame is None else frame
    a, b = source @ frame, target @ frame
    qa = np.percentile(a, [0, 2, 98, 100], axis=0)
    qb = np.percentile(b, [0, 2, 98, 100], axis=0)
    options = []
    for axis in range(3):
        shifts = [qb[k, axis] - qa[k, axis] for k in range(4)]
        shifts.append(0.5 * (qb[0, axis] + qb[3, axis] - qa[0, axis] - qa[3, axis]))
        options.append(shifts)
    grid = np.array(np.meshgrid(*options, indexing="ij")).reshape(3, -1).T
    result = []
    for shift in grid:
        transform = np.eye(4)
        transform[:3, 3] = frame @ shift
        result.append(transform)
    return result


def pair_cost(candidate: PairCandidate, diameter: float, match_min_score: float) -> float:
    """Hungarian cost of one pair (module doc); ``UNMATCHED`` below the minimum score."""
    if candidate.score < match_min_score or candidate.named_conflict:
        return UNMATCHED
    return (-candidate.score + TRAVEL_PENALTY * candidate.travel / max(diameter, 1e-12)
            + PHYSICS_WEIGHT * candidate.physics + SLIDE_WEIGHT * candidate.slide - MASK_ID_WEIGHT * candidate.mask)


@dataclass
class Assignment:
    """The chosen pairing and its runner-up.

    pairs: chosen (i, j); cost: its total; runner_up: the best pairing that changes a moving
    pair (None when no other pairing exists), runner_up_cost its total; margin = the difference.
    """

    pairs: list[tuple[int, int]]
    cost: float
    runner_up: list[tuple[int, int]] | None = None
    runner_up_cost: float = float("inf")

    @property
    def margin(self) -> float:
        return self.runner_up_cost - self.cost


def assign(candidates: dict[tuple[int, int], PairCandidate], n_start: int, n_end: int, diameter: float,
           match_min_score: float, moving: set[tuple[int, int]]) -> Assignment:
    """Hungarian pairing of least cost, and the runner-up: the cheapest pairing without one of the
    chosen moving pairs (``moving``: the pairs whose motion is not "stayed put"). O(K n^3) for K
    chosen moving pairs and n groups per state."""
    cost = np.full((n_start, n_end), UNMATCHED)
    for (i, j), candidate in candidates.items():
        cost[i, j] = pair_cost(candidate, diameter, match_min_score)

    def solve(matrix: np.ndarray) -> tuple[list[tuple[int, int]], float]:
        rows, cols = linear_sum_assignment(matrix)
        chosen = [(int(r), int(c)) for r, c in zip(rows, cols) if matrix[r, c] < UNMATCHED]
        return sorted(chosen), float(sum(matrix[r, c] for r, c in chosen))

    pairs, total = solve(cost)
    result = Assignment(pairs, total)
    for pair in pairs:
        if pair not in moving:
            continue
        blocked = cost.copy()
        blocked[pair] = UNMATCHED
        other, other_total = solve(blocked)
        if other_total < result.runner_up_cost and other != pairs:
            result.runner_up, result.runner_up_cost = other, other_total
    return result
