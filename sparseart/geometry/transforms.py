"""Stable rigid-motion maps: Kabsch, robust Kabsch, screw decomposition and joint transforms.

All the rotation math of the joint fitter lives here, written once and tested at the singular
points (angle ~ 0, where the screw axis is undefined, and angle ~ pi, where the sign of the
rotation-vector axis is ambiguous).

Conventions: points are ``(N, 3)`` float64 rows; a rigid transform ``(R, t)`` maps a point ``x``
to ``R @ x + t``; a ``(4, 4)`` homogeneous transform holds ``R`` in the top-left block and ``t``
in the last column. Angles are radians, right-handed about the axis. Motion semantics match
design section 3: revolute ``x -> origin + R(axis, angle) (x - origin)``, prismatic
``x -> x + distance * axis``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np
from scipy.spatial.transform import Rotation

#: Below this rotation angle (radians) the screw axis is treated as undefined.
AXIS_UNDEFINED_ANGLE = 1e-9


def _as_points(array: np.ndarray, name: str) -> np.ndarray:
    points = np.asarray(array, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {points.shape}")
    return points


def unit(vector: np.ndarray) -> np.ndarray:
    """``vector / |vector|`` as float64; raises ValueError for a zero or non-finite vector."""
    vector = np.asarray(vector, dtype=np.float64).reshape(3)
    norm = float(np.linalg.norm(vector))
    if not np.isfinite(norm) or norm < 1e-300:
        raise ValueError(f"cannot normalise vector {vector}")
    return vector / norm


def tangent_basis(axis: np.ndarray) -> np.ndarray:
    """Two unit vectors spanning the plane orthogonal to ``axis``: (3, 2) float64 columns.

    Deterministic and smooth away from the chosen helper direction (the world basis vector least
    aligned with ``axis``), so it can parameterise small axis perturbations.
    """
    axis = unit(axis)
    helper = np.zeros(3)
    helper[int(np.argmin(np.abs(axis)))] = 1.0
    first = unit(np.cross(axis, helper))
    second = np.cross(axis, first)
    return np.stack([first, second], axis=1)


def perturb_axis(axis: np.ndarray, basis: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Unit axis ``normalise(axis + basis @ params)``; ``params`` (2,) are tangent coordinates.

    For small params the angular deviation from ``axis`` is ``|params|`` radians.
    """
    return unit(np.asarray(axis, dtype=np.float64) + basis @ np.asarray(params, dtype=np.float64))


def rotation_angle(rotation: np.ndarray) -> float:
    """Geodesic angle of a (3, 3) rotation in [0, pi] radians (via the rotation vector, stable)."""
    return float(np.linalg.norm(Rotation.from_matrix(np.asarray(rotation, dtype=np.float64)).as_rotvec()))


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) float64 homogeneous transform from ``R`` (3, 3) and ``t`` (3,)."""
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = np.asarray(translation, dtype=np.float64).reshape(3)
    return transform


def apply_transform(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``R @ x + t`` for every row of ``points`` (N, 3) -> (N, 3) float64. O(N)."""
    return points @ transform[:3, :3].T + transform[:3, 3]


def kabsch(
    source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid motion ``(R, t)`` with ``target ~ R @ source + t``.

    source, target: (N, 3) float64 paired rows (N >= 3 for a unique answer).
    weights: (N,) non-negative, optional (uniform when None).
    Returns R (3, 3) proper rotation (reflection fixed via the SVD sign trick) and t (3,).
    Degenerate inputs (collinear / coincident points) still give a finite proper rotation.
    O(N).
    """
    source = _as_points(source, "source")
    target = _as_points(target, "target")
    if source.shape != target.shape or source.shape[0] == 0:
        raise ValueError(f"kabsch needs equal non-empty shapes, got {source.shape}, {target.shape}")
    if weights is None:
        weights = np.ones(source.shape[0])
    weights = np.clip(np.asarray(weights, dtype=np.float64).reshape(-1), 0.0, None)
    total = weights.sum()
    if not np.isfinite(total) or total <= 0:
        weights = np.ones(source.shape[0])
        total = float(source.shape[0])
    source_centre = weights @ source / total
    target_centre = weights @ target / total
    covariance = (source - source_centre).T @ ((target - target_centre) * weights[:, None])
    u, _, vt = np.linalg.svd(covariance)
    sign = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation = vt.T @ np.diag([1.0, 1.0, sign]) @ u.T
    return rotation, target_centre - rotation @ source_centre


def robust_kabsch(
    source: np.ndarray,
    target: np.ndarray,
    scale: float | None = None,
    iterations: int = 20,
    ransac_trials: int = 200,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rigid motion from putative matches with outliers: RANSAC over minimal triples + Tukey IRLS.

    source, target: (N, 3) float64 putative pairs. scale: inlier distance scale (frame units);
    estimated from the residuals (MAD) when None.
    Returns R (3, 3), t (3,), weights (N,) in [0, 1] (0 = outlier).
    Cost O(ransac_trials * N + iterations * N), fully vectorised over the trials.
    """
    source = _as_points(source, "source")
    target = _as_points(target, "target")
    count = source.shape[0]
    if count < 3:
        raise ValueError(f"robust_kabsch needs at least 3 pairs, got {count}")
    rng = np.random.default_rng(seed)
    best_rotation, best_translation = kabsch(source, target)
    if scale is None:
        residual = np.linalg.norm(apply_transform(make_transform(best_rotation, best_translation), source) - target, axis=1)
        scale = max(1.4826 * float(np.median(np.abs(residual - np.median(residual)))), 1e-12)
    best_inliers = -1
    for _ in range(ransac_trials):
        pick = rng.choice(count, 3, replace=False)
        rotation, translation = kabsch(source[pick], target[pick])
        residual = np.linalg.norm(source @ rotation.T + translation - target, axis=1)
        inliers = int(np.count_nonzero(residual < 3.0 * scale))
        if inliers > best_inliers:
            best_inliers, best_rotation, best_translation = inliers, rotation, translation
    rotation, translation = best_rotation, best_translation
    weights = np.ones(count)
    for _ in range(iterations):
        residual = np.linalg.norm(source @ rotation.T + translation - target, axis=1)
        cutoff = 4.685 * max(scale, 1e-12)
        weights = np.where(residual < cutoff, (1.0 - (residual / cutoff) ** 2) ** 2, 0.0)
        if np.count_nonzero(weights) < 3:
            weights = np.ones(count)
        new_rotation, new_translation = kabsch(source, target, weights)
        moved = np.abs(new_rotation - rotation).max() + np.abs(new_translation - translation).max()
        rotation, translation = new_rotation, new_translation
        if moved < 1e-12:
            break
    return rotation, translation, weights


@dataclass
class Screw:
    """Screw decomposition of a rigid motion; unpacks as ``axis, angle, pivot, slide``.

    axis: (3,) unit vector. angle: radians (in [0, pi] unless oriented by an axis hint).
    pivot: (3,) point on the screw axis nearest the reference point. slide: translation along
    the axis (frame units). axis_defined: False when angle ~ 0 (then axis is the translation
    direction, or +z for the identity, and pivot is the reference point). note: why, if anything
    is ill-defined.
    """

    axis: np.ndarray
    angle: float
    pivot: np.ndarray
    slide: float
    axis_defined: bool = True
    note: str = ""

    def __iter__(self) -> Iterator:
        return iter((self.axis, self.angle, self.pivot, self.slide))


def screw_from_transform(
    rotation: np.ndarray,
    translation: np.ndarray,
    reference: np.ndarray | None = None,
    axis_hint: np.ndarray | None = None,
) -> Screw:
    """Decompose ``x -> R x + t`` into a screw: rotation ``angle`` about the line through
    ``pivot`` along ``axis``, then ``slide`` along ``axis``.

    rotation: (3, 3); translation: (3,); reference: (3,) point (e.g. the part centre) -- the
    returned pivot is the point on the axis nearest it (origin when None).
    axis_hint: optional (3,) direction; the axis is flipped (and the angle negated) to agree with
    it. This resolves the sign ambiguity at angle ~ pi, where (a, pi) and (-a, pi) coincide.
    The pivot solves ``(I - R) p = t_perp`` by ``np.linalg.lstsq`` (never ``inv(I - R)``, which is
    singular along the axis) and is then projected on the plane through the reference.
    """
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64).reshape(3)
    reference = np.zeros(3) if reference is None else np.asarray(reference, dtype=np.float64).reshape(3)
    rotvec = Rotation.from_matrix(rotation).as_rotvec()
    angle = float(np.linalg.norm(rotvec))
    if angle < AXIS_UNDEFINED_ANGLE:
        norm = float(np.linalg.norm(translation))
        axis = translation / norm if norm > 0 else np.array([0.0, 0.0, 1.0])
        if axis_hint is not None and axis @ np.asarray(axis_hint) < 0:
            axis = -axis
        return Screw(axis, 0.0, reference.copy(), float(translation @ axis), False,
                     "rotation angle ~ 0: screw axis undefined (pure translation)")
    axis = rotvec / angle
    if axis_hint is not None and axis @ np.asarray(axis_hint, dtype=np.float64) < 0:
        axis, angle = -axis, -angle
        if angle <= -np.pi + 1e-12:  # (-a, -pi) is the same rotation as (-a, pi)
            angle = np.pi
    slide = float(translation @ axis)
    perpendicular = translation - slide * axis
    # Singular values of (I - R) are 0, 2 sin(angle/2), 2 sin(angle/2): cut the zero one.
    pivot, *_ = np.linalg.lstsq(np.eye(3) - rotation, perpendicular, rcond=1e-6)
    pivot = pivot - (pivot @ axis) * axis
    pivot = pivot + ((reference - pivot) @ axis) * axis
    note = ""
    if abs(angle) < 1e-6:
        note = "rotation angle < 1e-6 rad: pivot and axis poorly defined"
    elif np.pi - abs(angle) < 1e-6:
        note = "rotation angle ~ pi: axis sign chosen by convention"
    return Screw(axis, angle, pivot, slide, True, note)


def transform_from_revolute(axis: np.ndarray, origin: np.ndarray, angle: float) -> np.ndarray:
    """(4, 4) transform of ``x -> origin + R(axis, angle) (x - origin)``."""
    axis = unit(axis)
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    rotation = Rotation.from_rotvec(axis * float(angle)).as_matrix()
    return make_transform(rotation, origin - rotation @ origin)


def transform_from_prismatic(axis: np.ndarray, distance: float) -> np.ndarray:
    """(4, 4) transform of ``x -> x + distance * axis``."""
    return make_transform(np.eye(3), unit(axis) * float(distance))


def axis_angle_deg(axis_a: np.ndarray, axis_b: np.ndarray) -> float:
    """Angle in degrees, in [0, 90], between two lines of direction ``axis_a`` and ``axis_b`` ((3,),
    any non-zero length; the sign of a direction does not matter). atan2 of the cross and dot
    products: accurate at small angles, where arccos of the dot product loses half its digits."""
    a = np.asarray(axis_a, dtype=np.float64)
    b = np.asarray(axis_b, dtype=np.float64)
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), abs(float(a @ b)))))
