"""When is a joint estimate unreliable whatever its stated sigma: warnings with codes, confidence.

Every warning is a ``FitWarning`` (a ``WarningCode`` + the sentence users read); the confidence is
lowered by codes, never by searching the text. ``JointEstimate.warnings`` keeps the sentences and
``diagnostics["warning_codes"]`` the codes, in the same order. The thresholds are module constants
shared with ``sparseart.bench.stability`` (it imports them to mark "unreliable" rows the same way).
The warning functions are O(1) on the fit's summary numbers; ``scatter_fraction`` and
``inlier_fraction`` measure the outlier test's two inputs; ``covered_fraction`` the confidence's coverage term;
``measurable_motion`` whether a fitted motion is a measurement at all (it beats no motion beyond the noise).
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
from scipy.spatial import cKDTree

ILL_CONDITIONED = 1e6        # Jacobian condition number above which the fit is called ill-conditioned
# Outliers: more than MAX_SCATTER_FRACTION of the cleaned points off any surface
# (uncertainty.scatter_fraction) AND fewer than MIN_INLIER_FRACTION of the start points landing on
# the end cloud under the fit (uncertainty.inlier_fraction). Either alone also fires on good fits
# (thin shells scatter; partial overlap leaves points unmatched: 0.23-0.38 seen on PartNet renders).
MAX_SCATTER_FRACTION = 0.4
MIN_INLIER_FRACTION = 0.5
MAX_AXIS_SIGMA_DEG = 5.0     # stated axis 1-sigma above this: "uncertainty large" (2 sigma = the 10 deg success bar)
MAX_RELATIVE_SIGMA = 0.25    # stated angle / distance 1-sigma above this fraction of the estimate: "uncertainty large"
COLLINEAR_RATIO = 1e-4       # second / first principal variance below this: a thin rod
PLANAR_RATIO = 1e-4          # third / first principal variance below this: a flat part
CONFIDENCE_RESIDUAL = 0.1    # confidence halves when the residual is this fraction of the part radius
MEASURABLE_Z = 3.0           # a motion is measured when it covers more of the part than no motion by
                             # this many standard errors (measurable_motion)
HALF_TURN_DEG = 150.0        # a turn above this is most likely a symmetric part's flipped match: real
                             # joints of furniture and appliances turn less (the 21 rendered joints
                             # 37-75 deg, the real laptop 96 deg)


class WarningCode(Enum):
    """What a fit warning says; ``lowers_confidence`` marks the ones that halve the confidence."""

    CLEANED = "cleaned"                        # cleaning removed > 30 % of a state's points
    FEW_POINTS = "few_points"                  # fewer than FitConfig.few_points points
    COLLINEAR = "collinear"                    # thin rod: rotation about its own line unobservable
    PLANAR = "planar"                          # flat part: axis relies on the in-plane shape
    ILL_CONDITIONED = "ill_conditioned"
    SMALL_ANGLE = "small_angle"                # rotation below FitConfig.small_angle_deg
    FAR_PIVOT = "far_pivot"                    # revolute pivot far away: revolute vs prismatic ambiguous
    AXIAL_SLIDE = "axial_slide"                # a revolute motion that also slides along its axis
    TINY_SLIDE = "tiny_slide"                  # a slide comparable with the noise
    OUTLIERS = "outliers"
    TURN_AS_SLIDE = "turn_as_slide"            # a prismatic answer to a motion that turns
    HALF_TURN = "half_turn"                    # a turn > HALF_TURN_DEG: likely a symmetric part's flip
    LARGE_UNCERTAINTY = "large_uncertainty"

    @property
    def lowers_confidence(self) -> bool:
        return self in _LOWERS_CONFIDENCE


_LOWERS_CONFIDENCE = {WarningCode.ILL_CONDITIONED, WarningCode.SMALL_ANGLE, WarningCode.FAR_PIVOT,
                      WarningCode.TINY_SLIDE, WarningCode.OUTLIERS, WarningCode.TURN_AS_SLIDE,
                      WarningCode.LARGE_UNCERTAINTY, WarningCode.HALF_TURN}


@dataclass(frozen=True)
class FitWarning:
    code: WarningCode
    message: str


def shape_warnings(principal_variances: np.ndarray, condition: float) -> list[FitWarning]:
    """A thin-rod or flat part (principal variances, descending) and an ill-conditioned Jacobian."""
    found = []
    first, second, third = principal_variances
    if second < COLLINEAR_RATIO * first:
        found.append(FitWarning(WarningCode.COLLINEAR, "part is nearly collinear (thin rod): rotation about its "
                                                       "own line is unobservable"))
    elif third < PLANAR_RATIO * first:
        found.append(FitWarning(WarningCode.PLANAR, "part is nearly planar: axis estimate relies on the in-plane shape"))
    if condition > ILL_CONDITIONED:
        found.append(FitWarning(WarningCode.ILL_CONDITIONED, f"ill-conditioned fit (Jacobian condition number "
                                                             f"{condition:.3g})"))
    return found


def revolute_warnings(angle: float, pivot_distance: float, part_radius: float, slide: float, slide_limit: float,
                      unit_slide: float, small_angle_deg: float, far_pivot_factor: float) -> list[FitWarning]:
    """angle (rad) below ``small_angle_deg`` or above ``HALF_TURN_DEG``; pivot farther than ``far_pivot_factor`` part radii
    (normalised units); |slide| along the axis above ``slide_limit`` (normalised; ``unit_slide``:
    the same in input units, for the message)."""
    found = []
    if np.degrees(angle) < small_angle_deg:
        found.append(FitWarning(WarningCode.SMALL_ANGLE, f"rotation of {np.degrees(angle):.3g} deg < "
                                                         f"{small_angle_deg} deg: axis poorly defined"))
    if np.degrees(abs(angle)) > HALF_TURN_DEG:
        found.append(FitWarning(WarningCode.HALF_TURN, f"turn of {np.degrees(abs(angle)):.3g} deg > {HALF_TURN_DEG:.0f} "
                                                       "deg: most likely a symmetric part matched flipped (a door "
                                                       "seen edge-on?); axis and angle may be wrong"))
    if pivot_distance > far_pivot_factor * part_radius:
        found.append(FitWarning(WarningCode.FAR_PIVOT, f"pivot is {pivot_distance / part_radius:.3g} x the part "
                                                       "radius away: revolute vs prismatic ambiguous"))
    if abs(slide) > slide_limit:
        found.append(FitWarning(WarningCode.AXIAL_SLIDE, f"motion slides {unit_slide:.3g} along the axis: "
                                                         "not a pure rotation"))
    return found


def prismatic_warnings(distance: float, noise: float, unit_distance: float) -> list[FitWarning]:
    """A slide shorter than 3 x its noise (both normalised)."""
    if distance < 3.0 * noise:
        return [FitWarning(WarningCode.TINY_SLIDE, f"slide of {unit_distance:.3g} is tiny compared with the noise: "
                                                   "axis poorly defined")]
    return []


def reliability_warnings(kind: str, uncertainty: dict, angle: float | None, distance: float | None,
                         scattered: float, inliers: float, turn_deg: float, pivot_factor: float,
                         small_angle_deg: float, far_pivot_factor: float) -> list[FitWarning]:
    """Outliers (many points scatter off any surface and few land on the other state), a
    prismatic answer to a motion that turns by more than ``small_angle_deg`` about a far pivot
    (small angle x large radius ~ translation), a stated uncertainty large against the estimate.
    uncertainty: the stated sigma in input units; angle (rad) / distance (input units) or None."""
    found = []
    if scattered > MAX_SCATTER_FRACTION and inliers < MIN_INLIER_FRACTION:
        found.append(FitWarning(WarningCode.OUTLIERS, f"many outliers: {100 * scattered:.0f} % of the points scatter "
                                f"off any surface (> {100 * MAX_SCATTER_FRACTION:.0f} %) and only {100 * inliers:.0f} "
                                f"% land on the other state under the fitted motion (< "
                                f"{100 * MIN_INLIER_FRACTION:.0f} %); estimate unreliable"))
    turn = abs(turn_deg)
    if kind == "prismatic" and turn > small_angle_deg and pivot_factor > far_pivot_factor:
        found.append(FitWarning(WarningCode.TURN_AS_SLIDE, f"the rigid motion turns by {turn:.3g} deg, which a "
                                f"rotation about a pivot {pivot_factor:.3g} x the part radius away explains as well "
                                "as a slide: revolute vs prismatic ambiguous"))
    large = []
    if uncertainty["axis_deg"] > MAX_AXIS_SIGMA_DEG:
        large.append(f"axis +-{uncertainty['axis_deg']:.3g} deg > {MAX_AXIS_SIGMA_DEG:g} deg")
    if angle is not None and uncertainty["angle"] > MAX_RELATIVE_SIGMA * abs(angle):
        large.append(f"angle +-{np.degrees(uncertainty['angle']):.3g} deg of {np.degrees(angle):.3g} deg")
    if distance is not None and uncertainty["distance"] > MAX_RELATIVE_SIGMA * abs(distance):
        large.append(f"distance +-{uncertainty['distance']:.3g} of {abs(distance):.3g}")
    if large:
        found.append(FitWarning(WarningCode.LARGE_UNCERTAINTY,
                                "uncertainty large relative to the estimate: " + ", ".join(large)))
    return found


def residual_excess(residual: float, floor: float) -> float:
    """The residual beyond the noise floor, sqrt(max(residual^2 - floor^2, 0)), in the unit of
    both (:func:`~sparseart.joints.noise_floor.residual_floor`). O(1)."""
    return float(np.sqrt(max(residual ** 2 - floor ** 2, 0.0)))


def confidence(covered: float, residual: float, part_radius: float, warnings: list[FitWarning],
               floor: float = 0.0) -> float:
    """In [0, 1]: the covered fraction (:func:`covered_fraction`: how much of the part the motion
    lays onto itself), divided by 1 + (excess / (0.1 part radius))^2, halved
    when any warning ``lowers_confidence``. excess = sqrt(max(residual^2 - floor^2, 0)): the
    residual beyond what the part's own sampling and depth noise leave under a perfect motion
    (``floor``, :func:`~sparseart.joints.noise_floor.residual_floor`; same units as ``residual``),
    so noise alone does not read as a bad fit."""
    relative = residual_excess(residual, floor) / max(part_radius, 1e-12)
    value = float(np.clip(covered, 0, 1) / (1.0 + (relative / CONFIDENCE_RESIDUAL) ** 2))
    if any(w.code.lowers_confidence for w in warnings):
        value *= 0.5
    return float(np.clip(value, 0.0, 1.0))


def covered_fraction(start: np.ndarray, end: np.ndarray, end_tree: cKDTree, rotation: np.ndarray,
                     translation: np.ndarray, radius: float) -> float:
    """How much of the part the fitted motion lays onto itself: the mean of the share of start
    points (n, 3) that land within ``radius`` of an end point (m, 3; ``end_tree`` its k-d tree)
    and the share of end points with a moved start point within ``radius``.

    Unlike the fit's one-to-one match fraction it does not depend on how densely each state's
    camera sampled the part: two random samples of one surface seen at different angles pair
    only 80-85 % one to one under a perfect motion (clean laptop renders), while every point
    lands. A region seen in one state only still lowers it. O((n + m) log(n + m)).
    """
    if len(start) == 0 or len(end) == 0:
        return 0.0
    moved = start @ rotation.T + translation
    forward = end_tree.query(moved, distance_upper_bound=radius)[0] < radius
    backward = cKDTree(moved).query(end, distance_upper_bound=radius)[0] < radius
    return float(0.5 * (forward.mean() + backward.mean()))


def measurable_motion(covered: float, unmoved: float, n_start: int, n_end: int) -> bool:
    """Is the fitted motion measurable at all: does it lay more of the part onto the other state
    than no motion does, by more than the two shares' sampling error?

    ``covered`` and ``unmoved`` are :func:`covered_fraction` of the part's n_start and n_end
    matching points under the fitted motion and under the identity, within the same radius (the
    fit's pair radius: 3 x the points' median spacing, which the depth noise widens). Where
    nothing moved -- or a part moved less than the depth noise, or slid within its own featureless
    plane -- the two states agree without any motion as closely as under the fit, so the fitted
    motion is not a measurement: the answer is "no joint", not a joint of whatever size the
    optimiser drifted to. Each share is a mean of two Bernoulli shares, variance p (1 - p) (1 /
    n_start + 1 / n_end) / 4; the motion is measurable when the gain exceeds ``MEASURABLE_Z``
    standard errors of the difference. Unit-free; O(1).
    """
    if n_start <= 0 or n_end <= 0:
        return False
    per_point = (1.0 / n_start + 1.0 / n_end) / 4.0
    variance = sum(p * (1.0 - p) for p in (float(np.clip(covered, 0, 1)), float(np.clip(unmoved, 0, 1)))) * per_point
    return covered - unmoved > MEASURABLE_Z * float(np.sqrt(variance))


def inlier_fraction(start: np.ndarray, end: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                    spacing_quantile: float = 0.1, tolerance: float = 4.0) -> float:
    """Fraction of start points (n, 3) that land on the end cloud (m, 3) under the fitted motion.

    "On" = an end point within ``tolerance`` x the surface spacing, the ``spacing_quantile``
    quantile of the start cloud's nearest-neighbour distances (a low quantile: scattered outliers
    are sparse and must not set the scale). Surface points seen in both states count, points of a
    region seen in one state only and scattered outliers do not. O((n + m) log m).
    """
    if len(start) < 2 or len(end) < 1:
        return 0.0
    own = cKDTree(start).query(start, k=2)[0][:, 1]
    radius = tolerance * max(float(np.quantile(own, spacing_quantile)), 1e-12)
    distance = cKDTree(end).query(start @ rotation.T + translation)[0]
    return float(np.mean(distance <= radius))


def scatter_fraction(points: np.ndarray, rng: np.random.Generator, neighbours: int = 10,
                     max_points: int = 4000, threshold: float = 0.1, tree: cKDTree | None = None) -> float:
    """Fraction of points (n, 3) not lying on a surface or curve: the smallest eigenvalue of their
    ``neighbours``-NN covariance exceeds ``threshold`` x the eigenvalue sum ("surface variation";
    ~0 on a sampled surface or wire, ~0.2-0.3 for points scattered in a volume). Estimated on at
    most ``max_points`` random points (neighbours from the whole cloud; ``tree``: its prebuilt
    cKDTree). O(n log n)."""
    if len(points) <= neighbours:
        return 0.0
    pick = rng.choice(len(points), min(max_points, len(points)), replace=False)
    tree = tree if tree is not None else cKDTree(points)
    _, index = tree.query(points[pick], k=neighbours + 1)
    local = points[index] - points[index].mean(axis=1, keepdims=True)
    eigen = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", local, local))
    variation = eigen[:, 0] / np.maximum(eigen.sum(axis=1), 1e-300)
    return float(np.mean(variation > threshold))
