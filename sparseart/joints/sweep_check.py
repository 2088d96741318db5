"""Does a fitted turn drive its part into the static body? A door turned the wrong way about the
right hinge, a lid flipped about its far edge: the end pose can fit the points (the part lands on
what it revealed, or on its own mirror image) while the first steps of the turn push the part
through the cabinet or the base. No real joint does that, so such a fit is said and trusted less.

The check steps the part's points of each state a little along the turn (start points forward,
end points back; :func:`~sparseart.geometry.sweep.blocked_step_share`) and counts those that run
into the static part as seen in EITHER state: the static body is the same in both, and the surface
a closed door hides (its frame, the oven's inside) is seen only once the door has opened.
Measured on the robot-shaped renders (posed, one view per state, no masks, seeds 0-3;
experiment EXP-068): right turns push at most 9 % of their points
into the static body, the drop-down oven doors turned inwards 22-24 %.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from sparseart.geometry.sweep import blocked_step_share
from sparseart.types import JointEstimate

SWEEP_RADIUS_SPACINGS = 2.0   # a stepped point within this many point spacings of the static part meets it
SWEEP_SAMPLE = 400            # points of the part stepped per state
BLOCKED_TURN_SHARE = 0.1      # a turn that pushes more than this share of the part into the static part ...
BLOCKED_TRUST = 0.5           # ... is trusted this much (the confidence is multiplied by it)


def blocked_turn_share(joint: JointEstimate, part_start: np.ndarray, part_end: np.ndarray,
                       static: cKDTree, spacing: float) -> float:
    """In [0, 1]: the larger, over the two states, of the share of the part's points that the
    first steps of the fitted turn push into the static part (``static``: a KD-tree of its points
    in both states, scene frame) where they did not already touch it. part_start / part_end: (N, 3)
    / (M, 3) float64, scene frame; spacing: the clouds' median point spacing (scene units).
    0 for slides. O(S log N) for S = ``SWEEP_SAMPLE`` points per state."""
    if joint.type != "revolute" or static.n < 10:
        return 0.0
    radius = SWEEP_RADIUS_SPACINGS * spacing

    def near_static(points: np.ndarray) -> np.ndarray:
        return static.query(points, k=1, distance_upper_bound=radius)[0] < radius

    shares = []
    for points, direction in ((part_start, 1.0), (part_end, -1.0)):
        sample = points[:: max(1, len(points) // SWEEP_SAMPLE)]
        shares.append(blocked_step_share(joint.transform, direction, sample, radius, near_static, surface=static)
                      if len(sample) else 0.0)
    return float(max(shares))


def check_turn(joint: JointEstimate, part_start: np.ndarray, part_end: np.ndarray, static: cKDTree,
               spacing: float) -> None:
    """Record the blocked share in ``joint.diagnostics["blocked_share"]``; above
    ``BLOCKED_TURN_SHARE`` multiply the confidence by ``BLOCKED_TRUST`` and add a warning."""
    if joint.type != "revolute":
        return
    share = blocked_turn_share(joint, part_start, part_end, static, spacing)
    joint.diagnostics["blocked_share"] = share
    if share > BLOCKED_TURN_SHARE:
        joint.confidence *= BLOCKED_TRUST
        joint.warnings.append(f"its turn pushes {share:.0%} of its points into the static part within its first "
                              f"steps (seen in either state): the turn's direction or size may be wrong; "
                              f"confidence x{BLOCKED_TRUST:g}")
