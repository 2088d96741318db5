"""Whole-object consistency of the fitted joints: a part fitted as a turn that its sliding siblings'
direction explains about as well is a slide.

Parts of one object that slide (the drawers of a cabinet, the racks of an oven, the sashes of a
window) slide in parallel, along the body's rails. A thin or see-through part whose mask carries
much of what lies behind it (a wire rack's mask also covers the oven wall between the wires) is
registered by a small turn: its unmoved stray points pull the fit towards a pivot that keeps
them still. Its siblings' slide direction, held while only the distance is fitted, is then the
hypothesis the object as a whole supports.
"""
from __future__ import annotations

import numpy as np

from sparseart.geometry.clouds import rms_radius
from sparseart.joints.body_axes import along_body_axes
from sparseart.joints.fit import fit_joint
from sparseart.joints.reliability import HALF_TURN_DEG
from sparseart.types import JointEstimate

# A held sibling slide replaces a part's turn when its RMS residual is within this factor of the
# turn's. Measured on the realistic oven's wire racks (seeds 0-3): the racks fitted as 17-25 deg
# turns held along a sibling rack's slide at 0.93-1.38 x; the oven doors, the only other turns
# beside those slides, at 1.76-3.1 x.
SIBLING_RESIDUAL_RATIO = 1.4
# ... within this factor for a half-turn (> HALF_TURN_DEG): a symmetric part's flipped match, whose
# residual is no fair rival (measured: two twin drawers of a cabinet, unposed without masks, labelled
# as one part that slid 0.218 and 0.245 and fitted as a 174 deg turn; held along a sibling drawer's
# slide at 1.82-1.91 x).
HALF_TURN_SIBLING_RATIO = 2.0
# Siblings are alike in size: the turned part's RMS radius within this factor of the slide's (end state,
# where a pulled-out part is seen best).
SIBLING_SIZE_RATIO = 2.0
# A sibling slide whose stated axis sigma is above this does not fix a direction for others, unless
# it runs along an axis of the static body's faces (body_axes.along_body_axes: two independent
# readings agree; measured on the realistic oven, seed 3, a rack slide 5.3 deg off the truth and
# 8.2 deg off the body's axis, whose sigma a rival slide had widened to 15.9 deg; its sibling rack,
# fitted as a 17 deg turn 89 deg off, slides along it at 5.3 deg and 0.81 x the turn's residual).
SIBLING_MAX_AXIS_SIGMA_DEG = 10.0


def slides_like_siblings(joints: dict[int, JointEstimate], points: dict[int, tuple[np.ndarray, np.ndarray]],
                         fit_options: dict[int, dict], free_type: set[int],
                         body_axes: np.ndarray | None = None) -> dict[int, JointEstimate]:
    """Turns re-fitted as slides along a look-alike sibling's slide direction, where that fits as well.

    joints: part id -> its chosen fit; points: part id -> ((N, 3), (M, 3)) float64 start / end
    points, the fits' frame; fit_options: part id -> the keyword arguments of its fits (colours,
    config, confidences, frame error); free_type: the ids whose type may change (not given by
    the user or the labeler); body_axes: (3, 3) columns, the static body's Manhattan frame
    (:func:`~sparseart.joints.body_axes.static_body_axes`) or None. For every revolute part among
    them, every prismatic sibling whose axis sigma is at most ``SIBLING_MAX_AXIS_SIGMA_DEG`` (or
    whose axis runs along a body axis, :func:`~sparseart.joints.body_axes.along_body_axes`) and
    whose RMS radius (end state) is
    within ``SIBLING_SIZE_RATIO`` of the part's lends its axis; the part is fitted as a slide held
    to it (only the distance free), and the best such fit replaces the turn when its residual is
    within ``SIBLING_RESIDUAL_RATIO`` of the turn's (``HALF_TURN_SIBLING_RATIO`` for a half-turn).
    The replacement's axis sigma is the sibling's and its own in quadrature (the held fit has
    no direction error of its own); ``diagnostics["sibling_of"]`` names the sibling and keeps
    the turn's axis, angle and residual. Returns part id -> replacement (only the replaced
    parts). O(T S) held fits for T turns and S slides.
    """
    slides = {pid: j for pid, j in joints.items() if j.type == "prismatic" and j.distance
              and (float(j.uncertainty.get("axis_deg", 0.0)) <= SIBLING_MAX_AXIS_SIGMA_DEG
                   or along_body_axes(j.axis, body_axes))}
    radii = {pid: rms_radius(end) for pid, (_, end) in points.items()}   # end state: a pulled-out part seen best
    replaced: dict[int, JointEstimate] = {}
    for pid, turn in joints.items():
        if turn.type != "revolute" or pid not in free_type or not slides:
            continue
        start, end = points[pid]
        best: tuple[JointEstimate, int, np.ndarray] | None = None
        for sid, slide in slides.items():
            if max(radii[pid], radii[sid]) > SIBLING_SIZE_RATIO * max(min(radii[pid], radii[sid]), 1e-12):
                continue    # not alike in size
            seed = np.eye(4)
            seed[:3, 3] = slide.axis * float((end.mean(axis=0) - start.mean(axis=0)) @ slide.axis)
            try:
                held = fit_joint(start, end, joint_type="prismatic", initial_transform=seed, slide_axis=slide.axis,
                                 uncertainty=False, **fit_options[pid])
            except ValueError:
                continue
            if best is None or held.residual < best[0].residual:
                best = (held, sid, seed)
        flipped = np.degrees(abs(turn.angle or 0.0)) > HALF_TURN_DEG
        if best is None or best[0].residual > (HALF_TURN_SIBLING_RATIO if flipped else SIBLING_RESIDUAL_RATIO) \
                * turn.residual:
            continue
        _, sid, seed = best
        sibling = slides[sid]
        # the same fit with its full sigma (fit_joint remembers the model fit: same point estimate)
        held = fit_joint(start, end, joint_type="prismatic", initial_transform=seed, slide_axis=sibling.axis,
                         **fit_options[pid])
        sigma = float(np.hypot(held.uncertainty.get("axis_deg", 0.0), sibling.uncertainty.get("axis_deg", 0.0)))
        held.uncertainty["axis_deg"] = sigma
        held.diagnostics["sibling_of"] = {"part": int(sid), "turn_axis": turn.axis.tolist(),
                                          "turn_angle_deg": float(np.degrees(turn.angle or 0.0)),
                                          "turn_residual": float(turn.residual)}
        held.warnings.append(f"fitted as a slide along sibling part {sid}'s direction: its own best fit, a "
                             f"{np.degrees(turn.angle or 0.0):.1f} deg turn, "
                             f"explained the points only {turn.residual / held.residual:.2f} x better "
                             f"(axis uncertainty {sigma:.1f} deg)")
        replaced[pid] = held
    return replaced

