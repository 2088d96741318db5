"""The static-part step of alignment, after labelling: the end cloud moved onto the start cloud by a
robust ICP of the labelled static part (part 0).

``polish_on_static`` refines an alignment that features or a reconstructor already gave (ICP from
identity); ``align_on_static`` registers states that were never aligned, seeded by the labeler's
static motion. Both return the moved end cloud (labels unchanged) and append warnings.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from sparseart.geometry.icp import register_rigid
from sparseart.geometry.transforms import apply_transform, rotation_angle
from sparseart.types import LabelledCloud, PartLabels

MIN_STATIC_POINTS = 20
POLISH_WARN_DEG = 3.0       # an ICP polish larger than this means the feature alignment was off
MIN_STATIC_AGREEMENT = 0.5  # share of static points that must agree after the ICP


def polish_on_static(start: LabelledCloud, end: LabelledCloud, labels: PartLabels, warnings: list[str],
                     seed: int = 0) -> LabelledCloud:
    """Refine a feature/model alignment: robust ICP of the end static points onto the start static
    points from identity; the end cloud moves by the result. O(I N log N) for I ICP iterations
    over N static points."""
    pair = _static_points(start, end, labels)
    if pair is None:
        warnings.append("static part too small to polish the alignment of the states")
        return end
    registration = register_rigid(pair[1], pair[0], init=np.eye(4), seed=seed)
    angle = float(np.degrees(rotation_angle(registration.transform[:3, :3])))
    if registration.inlier_fraction < MIN_STATIC_AGREEMENT:
        warnings.append(f"alignment polish is weak: {registration.inlier_fraction:.0%} of the static points "
                        f"agree; kept the feature alignment")
        return end
    if angle > POLISH_WARN_DEG:
        warnings.append(f"the static part needed a {angle:.1f} deg correction after feature alignment")
    return moved(end, registration.transform)


def align_on_static(start: LabelledCloud, end: LabelledCloud, labels: PartLabels, warnings: list[str],
                    seed: int = 0) -> LabelledCloud:
    """Bring the end cloud into the start frame through the static part (part 0): the labeler's
    static start->end motion (identity for a still camera) seeds a robust ICP of the end static
    points onto the start static points; the end cloud is moved by the result."""
    pair = _static_points(start, end, labels)
    if pair is None:
        warnings.append("static part too small to align the unposed states; they are used as they are")
        return end
    initial = np.linalg.inv(labels.initial_motion.get(0, np.eye(4)))
    registration = register_rigid(pair[1], pair[0], init=initial, seed=seed)
    if registration.inlier_fraction < MIN_STATIC_AGREEMENT:
        warnings.append(f"unposed alignment is weak: {registration.inlier_fraction:.0%} of the static points "
                        f"agree after registration")
    return moved(end, registration.transform)


def moved(cloud: LabelledCloud, transform: np.ndarray) -> LabelledCloud:
    """The same cloud with its points moved by a (4, 4) transform (other arrays shared). O(N)."""
    return replace(cloud, points=apply_transform(transform, cloud.points))


def _static_points(start: LabelledCloud, end: LabelledCloud,
                   labels: PartLabels) -> tuple[np.ndarray, np.ndarray] | None:
    start_static = start.points[labels.start_part == 0]
    end_static = end.points[labels.end_part == 0]
    if len(start_static) < MIN_STATIC_POINTS or len(end_static) < MIN_STATIC_POINTS:
        return None
    return start_static, end_static
