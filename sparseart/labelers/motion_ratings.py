"""How each candidate motion rates the moved points of both states (:class:`Ratings`, used by
:mod:`.motion_layers` and :mod:`.motion_candidates`): a hit when it carries a point onto a moved
point of the other state, ``HIDDEN_CREDIT`` when it lands where the other state's views cannot
see, 0 on another seen surface, -1 where the views saw through; plus each motion's physics
(blocked steps), slide sine, and whether it is a turn no hinge on the static body makes
(:func:`detached`). Each motion also marks its off-colour hits (the two points' CIELAB a*b* more
than ``HIT_COLOUR_AB`` and their rg chromaticity more than ``HIT_CHROMATICITY`` apart, after the
states' global colour offset, :func:`moved_chroma`): they
count for the selection, but a point does not join a part by one (:meth:`Ratings.coloured_row`).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.sweep import blocked_step_share
from ..geometry.transforms import screw_from_transform
from ..parallel import in_parallel
from ..geometry.free_space import HIDDEN, VIOLATION, StateViews
from .colour import chroma
from .correspondence import PairContext, apply, refine_icp, slide_sine_points

HIDDEN_CREDIT = 0.5
TIGHTEN_POINTS = 600
PHYSICS_SAMPLE = 400
SAME_MOTION_RADII = 1.0     # motions moving the points within this many radii of each other are one
HIT_RADIUS_SHARE = 0.5      # a hit lands within this share of the inlier radius (a motion blending
                            # two twins' slides a radius apart misses both)
ANCHOR_MIN_TURN_DEG = 10.0  # turns at least this large must be a hinge on the static body: ...
ANCHOR_MAX_PITCH = 0.5      # ... shift along their own axis at most this many part radii ...
ANCHOR_MAX_GAP = 2.0        # ... about an axis passing within this many part radii of the static points
ANCHOR_LINE_SAMPLES = 25
ANCHOR_MAX_SLIDE = 5.0      # a slide (a turn below ANCHOR_MIN_TURN_DEG) carries its points at most this
                            # many part radii (median travel)
STATIC_SAMPLE = 20000
SEEN_BOTH_SHARE = 0.5       # seen-on-seen hits of the state with fewer at least this share of the other's
HIT_COLOUR_AB = 10.0        # a hit is off-colour when its two points differ by more than this in CIELAB
HIT_CHROMATICITY = 0.04     # a*b* AND by more than this in rg chromaticity (r, g over r + g + b), after
                            # the two states' global colour offset. Measured on robot-shaped renders (JPEG,
                            # image noise): a*b* gaps of a part on itself median 2-8, of an arm on the patch
                            # it hides 11-31; a textured lid turning under the light changes its a*b* by a
                            # median 10.5 (shading moves a*b*, not the chromaticity), a black door's
                            # chromaticity is noise (its a*b* is not): each test alone demotes true hits


def detached(transform: np.ndarray, points: np.ndarray, static_tree: cKDTree | None,
             seen_both: bool = False) -> bool:
    """Is a motion one that no joint on the static body makes? A turn's screw axis (the
    rotation axis through the points it leaves fixed) must carry no shift along itself beyond
    ``ANCHOR_MAX_PITCH`` part radii (a hinge turns, it does not screw) and, across the part's
    extent along it, pass within ``ANCHOR_MAX_GAP`` part radii of the static points (median
    nearest distance: a hinge is attached to its parent). A slide (below ``ANCHOR_MIN_TURN_DEG``)
    must carry its points at most ``ANCHOR_MAX_SLIDE`` part radii (median travel): a drawer
    pulled out all the way travels about 2-4 radii of its visible points, while a registration
    that carries an arm or a stray patch onto some far surface the other state hides travels
    more (measured on a robot-shaped render of a nightstand, one view, an arm on the drawer:
    slides of 7.9 and 11.3 radii, the second chosen for its hidden credit over the drawer's
    0.6-radius slide, whose layer then fell below the floor and no part was found). The travel
    limit does not apply when ``seen_both``: the slide lays seen moved points onto seen moved
    points in both directions alike (:func:`seen_both_ways`), i.e. the part is seen at both of its
    poses, as an arm or a patch present in one state only is not. A small part sliding along a
    long slot travels many radii of itself (measured: a toaster's lever, 464 and 426 such hits,
    7 radii; ruled detached, its place went to two turns of the lever onto the patches it hides,
    and the joint came out 72 deg off at confidence 0.9).

    Why: an arm or hand present in one state only is carried by some registration onto the
    other state's occluded patch, and such a motion out-voted the true one (measured on
    robot-shaped renders with sensor depth: an arm's 79 deg turn shifting 7.2 part radii along
    its axis was chosen over a door's 32 deg hinge with pitch 0.00 and gap 0.14; a box lid, a
    microwave door and a washing machine lid lost alike to turns with gaps of 3.3-8.8 radii;
    seven true hinges measured pitch <= 0.03 and gap <= 0.85, the largest the real laptop's).
    points: (P, 3) the motion's hit points, start frame; part radius = their RMS distance to
    their centroid. Turns below ``ANCHOR_MIN_TURN_DEG`` are judged as slides (a slide with a tilt
    of noise has a far, ill-defined axis); empty inputs are never detached. O(P + 25 log S)."""
    if static_tree is None or len(points) < 10:
        return False
    centre = points.mean(axis=0)
    screw = screw_from_transform(transform[:3, :3], transform[:3, 3], reference=centre)
    radius = max(float(np.sqrt(((points - centre) ** 2).sum(axis=1).mean())), 1e-12)
    if np.degrees(abs(screw.angle)) < ANCHOR_MIN_TURN_DEG:
        if seen_both:
            return False
        travel = np.linalg.norm(points @ transform[:3, :3].T + transform[:3, 3] - points, axis=1)
        return float(np.median(travel)) > ANCHOR_MAX_SLIDE * radius
    offsets = (points - screw.pivot) @ screw.axis
    line = screw.pivot + np.linspace(offsets.min(), offsets.max(), ANCHOR_LINE_SAMPLES)[:, None] * screw.axis
    gap = float(np.median(static_tree.query(line)[0]))
    return abs(screw.slide) > ANCHOR_MAX_PITCH * radius or gap > ANCHOR_MAX_GAP * radius


def seen_both_ways(start_seen_hits: int, end_seen_hits: int, minimum: int = 10) -> bool:
    """Does a motion lay seen moved points onto seen moved points in both directions alike: at
    least ``minimum`` such hits in each state and the fewer at least ``SEEN_BOTH_SHARE`` of the
    more? (A part seen at both poses; an arm present in one state lands on the patch it hides,
    which that state's views could not see: hits one way only.) O(1)."""
    low, high = sorted((start_seen_hits, end_seen_hits))
    return low >= minimum and low >= SEEN_BOTH_SHARE * high


def off_colour(own: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(K,) bool: the (K, 4) :func:`chroma` rows differ by more than ``HIT_COLOUR_AB`` in a*b* and
    more than ``HIT_CHROMATICITY`` in rg chromaticity."""
    gap = own - target
    return ((np.linalg.norm(gap[:, :2], axis=1) > HIT_COLOUR_AB)
            & (np.linalg.norm(gap[:, 2:], axis=1) > HIT_CHROMATICITY))


def unmoved_sample(count: int, moved: np.ndarray) -> np.ndarray:
    """Indices of at most ``STATIC_SAMPLE`` (strided) of ``count`` points that are not in
    ``moved``. O(count)."""
    still = np.ones(count, dtype=bool)
    still[moved] = False
    still = np.flatnonzero(still)
    return still[:: max(1, len(still) // STATIC_SAMPLE)]


def moved_chroma(start, end, start_moved: np.ndarray, end_moved: np.ndarray,
                 end_tree: cKDTree) -> tuple[np.ndarray, np.ndarray]:
    """:func:`chroma` of the moved points of each state ((M_s, 4), (M_e, 4)), the end's corrected
    by the global colour offset between the states (white balance, exposure tint): the median
    difference of the start's unmoved points (:func:`unmoved_sample`) and their nearest end
    points. O(S log E)."""
    start_chroma, end_chroma = chroma(start.colors[start_moved]), chroma(end.colors[end_moved])
    still = unmoved_sample(len(start.points), start_moved)
    if len(still) >= 10:
        nearest = end_tree.query(start.points[still])[1]
        offset = np.median(chroma(end.colors[nearest]) - chroma(start.colors[still]), axis=0)
        end_chroma = end_chroma - offset
    return start_chroma, end_chroma


class Ratings:
    """Ratings of the moved points of both states under the motions."""

    def __init__(self, context: PairContext, start_moved: np.ndarray, end_moved: np.ndarray,
                 unseen: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        self.context = context
        self.start, self.end = context.start, context.end
        self.start_moved, self.end_moved = start_moved, end_moved
        if unseen is None:
            unseen = (np.zeros(len(start_moved), dtype=bool), np.zeros(len(end_moved), dtype=bool))
        self.start_unseen, self.end_unseen = (np.asarray(u, dtype=bool) for u in unseen)
        self.unseen = np.concatenate([self.start_unseen, self.end_unseen])
        self.radius = HIT_RADIUS_SHARE * context.radius
        self.start_tree = cKDTree(self.start.points[start_moved])
        self.end_tree = cKDTree(self.end.points[end_moved])
        self.start_all = cKDTree(self.start.points)
        self.end_all = cKDTree(self.end.points)
        self.start_chroma, self.end_chroma = moved_chroma(context.start, context.end, start_moved, end_moved,
                                                          self.end_all)
        self.motions: list[np.ndarray] = []
        self.rows: list[np.ndarray] = []      # (N_s + N_e,) ratings per motion
        self.off_colour: list[np.ndarray] = []  # (N_s + N_e,) bool: hits onto another colour
        self.blind: list[np.ndarray] = []       # (N_s + N_e,) bool: hits onto unseen points (blind hits)
        self.physics: list[float] = []
        self.slides: list[float] = []
        self.detached: list[bool] = []       # a turn no hinge on the static body makes (:func:`detached`)
        self._static_tree: cKDTree | None = None

    def _rate(self, points: np.ndarray, tree: cKDTree, views: StateViews, own_unseen: np.ndarray,
              target_unseen: np.ndarray, own_chroma: np.ndarray,
              target_chroma: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        distance, index = tree.query(points, k=1, distance_upper_bound=self.radius)
        hits = distance < self.radius
        # Unseen points (hidden in the other state, no vote in the split) earn nothing from each
        # other: two occluded table patches match under any slide along the table.
        hits[hits] &= ~(own_unseen[hits] & target_unseen[index[hits]])
        # A rigid part keeps its colour: a landing on a surface of another colour is no hit (an arm
        # in one state, carried onto the wall patch it hides, lands on the wall's colour).
        off = np.zeros(len(points), dtype=bool)
        off[hits] = off_colour(own_chroma[hits], target_chroma[index[hits]])
        blind = np.zeros(len(points), dtype=bool)
        blind[hits] = target_unseen[index[hits]]
        rating = hits.astype(np.float64)
        if views:
            labels = views.classify(points[~hits])
            rating[~hits] = np.where(labels == HIDDEN, HIDDEN_CREDIT, np.where(labels == VIOLATION, -1.0, 0.0))
        # An unseen point carried to where the other state cannot see either: no evidence at all.
        rating[own_unseen & (rating == HIDDEN_CREDIT)] = 0.0
        return rating, off, blind

    def rate(self, transform: np.ndarray) -> np.ndarray:
        return self.rate_with_colour(transform)[0]

    def rate_with_colour(self, transform: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ratings, off-colour hits, blind hits) of the moved points of both states under the
        motion, each (N_s + N_e,): a blind hit lands on a point the other state's views never saw
        (unseen in the split: a surface the motion revealed)."""
        forward = self._rate(apply(transform, self.start.points[self.start_moved]), self.end_tree,
                             self.context.end_views, self.start_unseen, self.end_unseen, self.start_chroma,
                             self.end_chroma)
        backward = self._rate(apply(np.linalg.inv(transform), self.end.points[self.end_moved]), self.start_tree,
                              self.context.start_views, self.end_unseen, self.start_unseen, self.end_chroma,
                              self.start_chroma)
        return tuple(np.concatenate([f, b]) for f, b in zip(forward, backward))

    def coloured_row(self, k: int) -> np.ndarray:
        """Motion k's ratings with its off-colour hits as 0: what a point's membership of the
        motion's part reads. The selection reads the plain rows: a part's colour varies across
        it (texture, a door's inside), and a motion's support is judged on where it lands."""
        return np.where(self.off_colour[k], 0.0, self.rows[k])

    def tighten(self, transform: np.ndarray) -> np.ndarray:
        """Refine a motion on the moved points it carries onto each other, with a tight trimming
        radius (a motion blending two twins' slides settles on the better supported one)."""
        row = self.rate(transform)
        n_start = len(self.start_moved)
        own_s = self.start_moved[row[:n_start] >= 1.0]
        own_e = self.end_moved[row[n_start:] >= 1.0]
        if len(own_s) < 10 or len(own_e) < 10:
            return transform
        own_s = own_s[:: max(1, len(own_s) // TIGHTEN_POINTS)]
        own_e = own_e[:: max(1, len(own_e) // TIGHTEN_POINTS)]
        return refine_icp(self.start.points[own_s], self.end.points[own_e], transform, self.radius,
                          schedule=(1.0, 0.5), iterations=6)

    def known(self, transform: np.ndarray, also: list[np.ndarray] | tuple = ()) -> bool:
        """Is an equal motion (points moved within ``SAME_MOTION_RADII`` radii) already rated (or
        among ``also``)?"""
        probe = self.start.points[self.start_moved[:: max(1, len(self.start_moved) // 500)]]
        for other in [*self.motions, *also]:
            gap = np.linalg.norm(apply(transform, probe) - apply(other, probe), axis=1)
            if len(gap) and np.median(gap) < SAME_MOTION_RADII * self.radius:
                return True
        return False

    def add_all(self, transforms: list[np.ndarray]) -> None:
        """Rate and append, in order, every motion of ``transforms`` not :meth:`known` (an equal
        one earlier in the list counts as known), as rating them one by one in turn would, with the
        ratings computed side by side (:func:`~sparseart.parallel.in_parallel`; each is a
        pure function of the motion). O(T (N log N + V N)) work for T motions."""
        fresh: list[np.ndarray] = []
        for transform in transforms:
            if not self.known(transform, also=fresh):
                fresh.append(transform)
        self.static_tree()      # built once here, not raced for by the threads
        for transform, (row, off, blind, physics, slide, loose) in zip(fresh, in_parallel(self._measure, fresh)):
            self.motions.append(transform)
            self.rows.append(row)
            self.off_colour.append(off)
            self.blind.append(blind)
            self.physics.append(physics)
            self.slides.append(slide)
            self.detached.append(loose)

    def tighten_all(self, transforms: list[np.ndarray]) -> list[np.ndarray]:
        """:meth:`tighten` of each motion, side by side (each a pure function of its motion), in
        order."""
        return in_parallel(self.tighten, transforms)

    def _measure(self, transform: np.ndarray) -> tuple:
        """(ratings row, off-colour hits, physics, slide sine, detached) of one motion."""
        row, off, blind = self.rate_with_colour(transform)
        n_start = len(self.start_moved)
        hit_s, hit_e = row[:n_start] >= 1.0, row[n_start:] >= 1.0
        own_s, own_e = self.start_moved[hit_s], self.end_moved[hit_e]
        physics = self.blocked(transform, own_s, own_e, self.start_moved[row[:n_start] > 0],
                               self.end_moved[row[n_start:] > 0])
        slide = (slide_sine_points(self.context, transform, self.start.points[own_s], self.end.points[own_e])
                 if len(own_s) and len(own_e) else 0.0)
        seen_both = seen_both_ways(int(np.count_nonzero(hit_s & ~self.start_unseen)),
                                   int(np.count_nonzero(hit_e & ~self.end_unseen)))
        loose = detached(transform, np.concatenate([self.start.points[own_s], apply(
            np.linalg.inv(transform), self.end.points[own_e])]), self.static_tree(), seen_both=seen_both)
        return row, off, blind, physics, slide, loose

    def static_tree(self) -> cKDTree | None:
        """KD-tree of at most ``STATIC_SAMPLE`` of the start points that did not move (None when
        fewer than 10)."""
        if self._static_tree is None:
            still = unmoved_sample(len(self.start.points), self.start_moved)
            if len(still) < 10:
                return None
            self._static_tree = cKDTree(self.start.points[still])
        return self._static_tree

    def blocked(self, transform: np.ndarray, own_start: np.ndarray, own_end: np.ndarray, part_start: np.ndarray,
                part_end: np.ndarray) -> float:
        """Blocked-step share (:func:`~.correspondence.blocked_share`) of the motion's hit points
        (own_*) in both states; the part's points (part_*: hit or hidden, they move along) are
        told apart from obstacles by checking the 8 nearest neighbours of a stepped point, and a
        step that meets a surface counts only when it runs into it, not along it (the normal of the
        cloud there, :func:`~sparseart.geometry.sweep.moves_into_surface`)."""
        shares = []
        for cloud, tree, owned, part, direction in ((self.start, self.start_all, own_start, part_start, 1.0),
                                                    (self.end, self.end_all, own_end, part_end, -1.0)):
            if len(owned) < 10:
                shares.append(0.0)
                continue
            mask = np.zeros(len(cloud), dtype=bool)
            mask[part] = True
            mask[owned] = True
            points = cloud.points[owned[:: max(1, len(owned) // PHYSICS_SAMPLE)]]

            def near_other(p: np.ndarray, tree=tree, mask=mask) -> np.ndarray:
                distance, index = tree.query(p, k=8, distance_upper_bound=self.radius)
                found = distance < self.radius
                index = np.where(found, index, 0)
                return np.any(found & ~mask[index], axis=1)

            shares.append(blocked_step_share(transform, direction, points, self.radius, near_other, surface=tree))
        return float(np.mean(shares))
