"""Does a fitted motion put its part where the cameras saw empty space? The physical test of a joint.

A joint is a hypothesis about where every point of the part goes. Moved into the other state, each
start point must land on a surface the end views saw, or where something nearer hides it; a point
that lands where an end view saw THROUGH (farther depth, or background) contradicts the hypothesis,
and the same holds for the end points moved back into the start views
(:class:`~sparseart.geometry.free_space.StateViews`). The fit's own loss (pairs and Chamfer
between the surfaces each state saw) cannot tell the front of a thick door from its inside when
each state sees a different face: it fits a hinge line beside the true one (measured on a clean
posed safe: the fitted line 0.1 object units off, 31 % of the moved start points and 46 % of the
moved end points in seen-through space; the true motion 0 % and 0 %).

:func:`check_free_space` reads that share for a fitted turn and, when it is high, searches the
hinge line across the fitted axis, turning by the fitted angle or by its opposite, for the motion
the views contradict least (the axis direction and the angle's size, which the fit gets right in
these cases, are kept). A clearly better
motion replaces the fitted hinge line and angle, with a warning; otherwise nothing changes.

The depth tolerance is read off the scene, not set: the static part does not move, so the
smallest of a few multiples of the point spacing under which the static start points are not
seen through by the end views (at most ``STATIC_TOLERATED`` of them) is the margin. Noisy depth
or a rough state alignment widen it on their own.
"""
from __future__ import annotations

from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from sparseart.geometry.clouds import median_spacing, rms_radius
from sparseart.geometry.free_space import VIOLATION, StateViews, state_views
from sparseart.geometry.transforms import apply_transform, transform_from_revolute
from sparseart.types import JointEstimate, LabelledCloud, Scene

MARGIN_SPACINGS = (3.0, 6.0, 12.0, 24.0)  # depth tolerances tried, in point spacings (smallest that fits the static part)
STATIC_TOLERATED = 0.05      # share of static start points the end views may see through at the chosen margin
CHECK_SAMPLE = 500           # points per state moved and projected per hypothesis
MIN_VIOLATION = 0.1          # a fitted turn contradicted by less than this share is left alone
GAIN = 0.5                   # a searched motion replaces the fit when its violation is below this share of the fit's ...
MIN_DROP = 0.1               # ... and lower by at least this much, and when it lays the part on its other
MISFIT_RATIO = 2.0           # state's points no worse than this x the fit (a turn reversed into hiding is not)
VIOLATION_TIE = 0.02         # violation shares this close are a tie, broken by the misfit ...
MISFIT_MARGINS = 3.0         # ... the mean nearest distance to the part in this many margins, clipped at 1
PIVOT_SPAN_RADII = 1.0       # the hinge line is searched within this many part radii of the fitted one ...
PIVOT_GRID = 9               # ... on this many places per direction across the axis
SEARCH_ROUNDS = 3            # rounds of the pivot search, each a third as wide


def scene_views(start: LabelledCloud, end: LabelledCloud, scene: Scene | None,
                static_start: np.ndarray) -> tuple[StateViews, StateViews] | None:
    """Both states' views for the free-space test, or None without depth images (RGB-only input,
    clouds given without a scene). static_start: (N,) bool, the static part's start points.
    The margin is the smallest of ``MARGIN_SPACINGS`` (x the start cloud's median point spacing)
    at which the end views see through at most ``STATIC_TOLERATED`` of the static start points;
    the largest when none does. O(H W) per frame + O(S V) per margin tried."""
    if scene is None or len(start) < 10 or len(end) < 10:
        return None
    spacing = median_spacing(start.points, sample=4000, rng=np.random.default_rng(0))
    static = _sample(start.points[static_start])
    margin = MARGIN_SPACINGS[-1] * spacing
    end_views = state_views(end, scene, margin)
    if not end_views:
        return None
    if len(static) >= 10:
        for factor in MARGIN_SPACINGS:
            end_views.margin = factor * spacing
            if float(np.mean(end_views.classify(static) == VIOLATION)) <= STATIC_TOLERATED:
                margin = end_views.margin
                break
    end_views.margin = margin
    start_views = state_views(start, scene, margin)
    return (start_views, end_views) if start_views else None


def _sample(points: np.ndarray) -> np.ndarray:
    return points[np.linspace(0, len(points) - 1, min(len(points), CHECK_SAMPLE)).astype(np.int64)]


class MotionCost:
    """The cost of a start->end motion of one part, ``(violation, misfit)`` compared in that order
    (:meth:`__call__`): the share of its moved points the other state's views saw through (both
    ways, averaged), then the mean distance from each moved point to the other state's part
    points in units of ``MISFIT_MARGINS`` x the views' margin, clipped at 1 (among motions the
    views contradict alike, the one that lays the part on itself). Violations closer than
    ``VIOLATION_TIE`` count as equal. Both terms are unit-free shares in [0, 1]. part_start
    (N, 3), part_end (M, 3) float64, scene frame. O(S (V + log M)) per call for S = ``CHECK_SAMPLE``."""

    def __init__(self, part_start: np.ndarray, part_end: np.ndarray, views: tuple[StateViews, StateViews]) -> None:
        self.part_start, self.part_end = part_start, part_end
        self.start, self.end = _sample(part_start), _sample(part_end)
        self.start_views, self.end_views = views
        self.margin = self.end_views.margin

    @cached_property
    def trees(self) -> tuple[cKDTree, cKDTree]:
        """KD-trees of the whole part in each state, built on the first :meth:`misfit` (the
        violation alone needs none). O((N + M) log (N + M))."""
        return cKDTree(self.part_start), cKDTree(self.part_end)

    def violation(self, transform: np.ndarray) -> float:
        inverse = np.linalg.inv(transform)
        forward = self.end_views.classify(apply_transform(transform, self.start))
        backward = self.start_views.classify(apply_transform(inverse, self.end))
        return 0.5 * (float(np.mean(forward == VIOLATION)) + float(np.mean(backward == VIOLATION)))

    def misfit(self, transform: np.ndarray) -> float:
        inverse = np.linalg.inv(transform)
        scale = MISFIT_MARGINS * self.margin
        start_tree, end_tree = self.trees
        forward = end_tree.query(apply_transform(transform, self.start), k=1, distance_upper_bound=scale)[0]
        backward = start_tree.query(apply_transform(inverse, self.end), k=1, distance_upper_bound=scale)[0]
        return 0.5 * float(np.mean(np.minimum(forward / scale, 1.0)) + np.mean(np.minimum(backward / scale, 1.0)))

    def __call__(self, transform: np.ndarray) -> tuple[float, float]:
        violation = self.violation(transform)
        return round(violation / VIOLATION_TIE) * VIOLATION_TIE, self.misfit(transform)


def search_turn(cost: MotionCost, axis: np.ndarray, pivot: np.ndarray, angle: float,
                radius: float) -> tuple[tuple[float, float], np.ndarray, float]:
    """The (cost, pivot, angle) of least ``cost`` among turns by ``angle`` or by ``-angle`` (the
    turn the other way) about lines parallel to ``axis``: the pivot on a ``PIVOT_GRID`` square
    grid across the axis, within ``PIVOT_SPAN_RADII`` x ``radius`` of ``pivot`` in the first of
    ``SEARCH_ROUNDS`` rounds and a third as wide about the best line in each round after. The fit
    gets the angle's size right where it gets the line wrong (the views leave the angle loosely
    fixed: hidden points are no evidence), so only its sign is searched. O(R G^2) cost calls."""
    across = np.linalg.svd(np.eye(3) - np.outer(axis, axis))[0][:, :2]
    span = PIVOT_SPAN_RADII * radius
    best = (cost(transform_from_revolute(axis, pivot, angle)), pivot, angle)
    for round_ in range(SEARCH_ROUNDS):
        offsets = np.linspace(-span, span, PIVOT_GRID)
        centre = best[1]
        for at in ((angle, -angle) if round_ == 0 else (best[2],)):
            for p in (centre + u * across[:, 0] + v * across[:, 1] for u in offsets for v in offsets):
                value = cost(transform_from_revolute(axis, p, at))
                if value < best[0]:
                    best = (value, p, float(at))
        span /= 3
    return best


def check_free_space(joint: JointEstimate, part_start: np.ndarray, part_end: np.ndarray,
                     views: tuple[StateViews, StateViews]) -> None:
    """For a revolute ``joint``: its moved points' share in seen-through space
    (``diagnostics["free_space_violation"]``), and when that exceeds ``MIN_VIOLATION`` the
    :func:`search_turn` result replaces the hinge line and angle if its violation share is
    below ``GAIN`` x the fit's and lower by ``MIN_DROP``, and its misfit (:meth:`MotionCost.misfit`)
    at most ``MISFIT_RATIO`` x the fit's: a turn reversed so that the part lands behind what the
    views saw is hidden, not right (measured on the real laptop, a second labelling: the lid
    turned the other way, 1 % contradicted against the fit's 12 %, misfit 1.0 against 0.22; the
    safes' moved hinge lines 0.42-0.58 against 0.35-0.47) (axis direction and angle size kept; the
    origin's sigma raised to at least the search's resolution; a warning says so). Slides are left alone. In place. Cost about 0.2-0.5 s per searched turn."""
    if joint.type != "revolute" or joint.angle is None:
        return
    cost = MotionCost(part_start, part_end, views)
    violation = cost.violation(joint.transform)
    joint.diagnostics["free_space_violation"] = violation
    if violation <= MIN_VIOLATION:
        return
    axis = np.asarray(joint.axis, dtype=np.float64)
    _, pivot, angle = search_turn(cost, axis, np.asarray(joint.origin, dtype=np.float64), float(joint.angle),
                                  rms_radius(part_start))
    searched_turn = transform_from_revolute(axis, pivot, angle)
    searched = cost.violation(searched_turn)
    misfits = cost.misfit(joint.transform), cost.misfit(searched_turn)
    joint.diagnostics["free_space_search"] = {"violation": searched, "angle": angle, "misfit": misfits[1],
                                              "fitted_misfit": misfits[0]}
    if not (searched < GAIN * violation and searched < violation - MIN_DROP
            and misfits[1] <= MISFIT_RATIO * misfits[0]):
        return
    moved = float(np.linalg.norm(np.cross(pivot - joint.origin, axis)))
    reversed_ = angle * float(joint.angle) < 0
    joint.warnings.append(
        f"the fitted turn put {violation:.0%} of the part where the cameras saw empty space: hinge line moved "
        f"{moved:.3g}{' and the turn reversed' if reversed_ else ''} to the turn the views contradict least "
        f"({searched:.0%})")
    joint.origin = pivot - float(np.dot(pivot - joint.origin, axis)) * axis   # the new line, nearest the old origin
    joint.angle = angle
    joint.transform = transform_from_revolute(axis, joint.origin, angle)
    # the search's own resolution: its finest pivot step and angle step
    last = 3 ** (SEARCH_ROUNDS - 1)
    resolution = 2 * PIVOT_SPAN_RADII * rms_radius(part_start) / last / (PIVOT_GRID - 1)
    joint.uncertainty["origin"] = max(float(joint.uncertainty.get("origin", 0.0)), resolution)
    joint.diagnostics["free_space_moved"] = {"origin": moved, "reversed": reversed_}
