"""Joint-type selection (revolute vs prismatic) as pure functions.

Rule: the rigid motion of a part carries its own rotation angle whatever the pivot. The revolute
model is chosen when (a) its fitted angle is *significant* -- larger than ``z`` standard
deviations and than a floor ``min_angle`` -- and (b) it wins on BIC by a margin computed with an effective
sample count (dense surface residuals are correlated). A pure translation with noise gives an
insignificant angle (the revolute model mimics it with a far pivot and a tiny angle), so it is
prismatic; a small real rotation (5 deg of a door with 1 mm noise) gives an angle many sigmas
above zero and a large BIC gap, so it is revolute.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from sparseart.joints.config import FitConfig
    from sparseart.joints.optimise import ModelFit

#: Free parameters per model: revolute = axis (2) + pivot (2) + angle (1); prismatic = axis (2) + distance (1).
PARAMETER_COUNT = {"revolute": 5, "prismatic": 3}


def bic(rss: float, count: float, parameters: int) -> float:
    """Bayesian information criterion ``n ln(RSS / n) + k ln n`` (Gaussian residuals).

    rss: residual sum of squares (any consistent units); count: effective number of independent
    residuals (> 0); parameters: free parameter count. Tiny RSS is floored at 1e-300.
    """
    count = max(float(count), 1.0)
    return count * float(np.log(max(rss, 1e-300) / count)) + parameters * float(np.log(count))


@dataclass
class TypeDecision:
    """Outcome of ``select_joint_type``: chosen type, both BIC scores, and the reasons."""

    joint_type: str
    bic_revolute: float
    bic_prismatic: float
    angle_significant: bool
    reason: str


def angle_is_significant(angle: float, angle_sigma: float, z: float = 4.0,
                         min_angle: float = np.radians(0.1)) -> bool:
    """True when ``|angle|`` (rad) exceeds both ``z * angle_sigma`` and ``min_angle`` (rad)."""
    if not np.isfinite(angle):
        return False
    sigma = angle_sigma if np.isfinite(angle_sigma) else np.inf
    return abs(angle) > max(z * sigma, min_angle)


def select_joint_type(
    rss_revolute: float,
    rss_prismatic: float,
    count: float,
    angle: float,
    angle_sigma: float,
    z: float = 4.0,
    min_angle: float = np.radians(0.1),
    bic_margin: float = 10.0,
) -> TypeDecision:
    """Choose "revolute" or "prismatic" from the two fits of the same matched residuals.

    rss_*: residual sums of squares of the same residual set under each model (same units).
    count: effective number of independent residuals. angle / angle_sigma: fitted revolute angle
    and its standard deviation (rad). Revolute iff the angle is significant (see
    ``angle_is_significant``) and ``BIC_revolute < BIC_prismatic - bic_margin`` ("strong" evidence
    on the Kass-Raftery scale: the extra pivot parameters must buy a clearly better fit).
    """
    bic_revolute = bic(rss_revolute, count, PARAMETER_COUNT["revolute"])
    bic_prismatic = bic(rss_prismatic, count, PARAMETER_COUNT["prismatic"])
    significant = angle_is_significant(angle, angle_sigma, z, min_angle)
    if not significant:
        below = (f"below the {np.degrees(min_angle):.2g} deg a turn needs" if abs(angle) < min_angle
                 else f"within {z:g} sigma of none (sigma {np.degrees(angle_sigma):.2g} deg)")
        choice, reason = "prismatic", (f"rotation {np.degrees(abs(angle)):.3g} deg is not significant ({below}); "
                                       f"BIC revolute - prismatic {bic_revolute - bic_prismatic:.3g}")
    elif bic_revolute < bic_prismatic - bic_margin:
        choice, reason = "revolute", f"significant rotation and BIC lower by {bic_prismatic - bic_revolute:.3g}"
    else:
        choice, reason = "prismatic", f"BIC prefers prismatic by {bic_revolute - bic_prismatic:.3g}"
    return TypeDecision(choice, bic_revolute, bic_prismatic, significant, reason)


def type_test_angle_sigma(revolute: ModelFit, frame_turn: float = 0.0) -> float:
    """The sigma (rad) the rotation's significance is judged against: the revolute fit's Jacobian
    angle sigma and ``frame_turn`` (rad, 1-sigma turn of the static frame itself,
    ``uncertainty.frame_misfit``: 0 for states that agree) in quadrature. A frame turned by a
    smooth depth warp turns every part with it, so a slide then shows a rotation of about that
    size (measured on realistic renders: 1.1-2.4 deg false rotations against 1.0-2.5 deg turns)."""
    return float(np.hypot(np.sqrt(max(revolute.covariance[4, 4], 0.0)), frame_turn))


# A turn below this about a pivot beyond far_pivot_factor part radii is a slide. Spurious turns
# measured on slides: 2.4 deg (warped frame), 5.3 deg (mislabelled points); a 10 deg turn about a
# pivot 10 object sizes away (tests/test_stability.py::test_far_pivot) stays a rotation.
FAR_PIVOT_MAX_TURN_DEG = 8.0


def choose_type(revolute: ModelFit, prismatic: ModelFit, config: FitConfig,
                frame_turn: float = 0.0, pivot_factor: float = 0.0) -> tuple[TypeDecision, dict]:
    """``select_joint_type`` on two fits of the same part: RSS of the point-to-plane Chamfer
    distances of the shared Chamfer sample, each truncated at the smaller matching clip tau;
    effective count = distances / ``bic_correlation_factor``; the revolute angle and its
    ``type_test_angle_sigma`` (Jacobian sigma with the frame's turn, rad). A revolute answer that
    turns by less than ``FAR_PIVOT_MAX_TURN_DEG`` about a pivot more than
    ``config.far_pivot_factor`` part radii away (``pivot_factor``) becomes prismatic: such a
    motion is a translation to within the turn, and the turn is what a few mislabelled points or
    a warped frame give a slide (measured: a window pane without masks, 5.3 deg about a pivot
    18.9 radii away, BIC 728 lower, axis 90 deg off; the hinges of the rendered objects lie
    0.3-2.4 radii away). Returns the decision and its diagnostics (BIC scores, reason). O(c)."""
    tau = min(revolute.tau, prismatic.tau)
    rss = {fit.kind: float(np.sum(np.minimum(fit.chamfer_distances, tau) ** 2)) for fit in (revolute, prismatic)}
    count = revolute.chamfer_distances.size / config.bic_correlation_factor
    angle = float(revolute.x[4])
    angle_sigma = type_test_angle_sigma(revolute, frame_turn)
    decision = select_joint_type(rss["revolute"], rss["prismatic"], count, angle, angle_sigma,
                                 z=config.angle_z, min_angle=np.radians(config.min_angle_deg))
    if (decision.joint_type == "revolute" and pivot_factor > config.far_pivot_factor
            and np.degrees(abs(angle)) < FAR_PIVOT_MAX_TURN_DEG):
        decision = TypeDecision("prismatic", decision.bic_revolute, decision.bic_prismatic,
                                decision.angle_significant,
                                f"a {np.degrees(abs(angle)):.3g} deg turn about a pivot {pivot_factor:.3g} part radii "
                                "away is a slide")
    diagnostics = {"bic_revolute": decision.bic_revolute, "bic_prismatic": decision.bic_prismatic,
                   "type_reason": decision.reason, "type_choice": decision.joint_type,
                   "angle_significant": decision.angle_significant}
    return decision, diagnostics
