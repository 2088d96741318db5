"""The two joint models as local parameterisations around a reference motion, and their
initial values from a rigid start -> end motion (screw decomposition).

Revolute x = [u1, u2, q1, q2, angle]: the axis tilted by (u1, u2) in its tangent plane, the pivot
moved by (q1, q2) in the same plane, the angle. Prismatic x = [u1, u2, distance]. ``x0`` is the
reference (zero tilt and offset); ``recentred(x)`` returns a model whose reference is ``x``, so
every solve starts at small parameters (no gimbal or wrap-around). All in normalised units.
"""
from __future__ import annotations

import numpy as np

from sparseart.geometry.transforms import (
    apply_transform,
    perturb_axis,
    screw_from_transform,
    tangent_basis,
    unit,
)


class Revolute:
    """Revolute parameters around a reference state: x = [u1, u2, q1, q2, angle]."""

    kind = "revolute"

    def __init__(self, axis: np.ndarray, pivot: np.ndarray, angle: float, reference: np.ndarray):
        self.axis = unit(axis)
        self.basis = tangent_basis(self.axis)
        self.reference = reference
        self.pivot = pivot + ((reference - pivot) @ self.axis) * self.axis
        self.x0 = np.array([0.0, 0.0, 0.0, 0.0, float(angle)])

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        return perturb_axis(self.axis, self.basis, x[:2]), self.pivot + self.basis @ x[2:4], float(x[4])

    def motion(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(3, 3) rotation and (3,) translation of the start -> end motion at ``x``. O(1); called
        once per residual evaluation, so written without the generic helpers' overhead."""
        direction = self.axis + self.basis @ x[:2]
        axis = direction / np.sqrt(direction @ direction)
        pivot = self.pivot + self.basis @ x[2:4]
        rotation = _rodrigues(axis, float(x[4]))
        return rotation, pivot - rotation @ pivot

    def recentred(self, x: np.ndarray) -> Revolute:
        axis, pivot, angle = self.unpack(x)
        return Revolute(axis, pivot, angle, self.reference)


class Prismatic:
    """Prismatic parameters around a reference state: x = [u1, u2, distance]. ``fixed``: the
    axis is held (a slide along a known direction): u1, u2 have no effect, so the solvers leave
    them at 0 and the Jacobian covariance gives the axis no variance."""

    kind = "prismatic"

    def __init__(self, axis: np.ndarray, distance: float, fixed: bool = False):
        self.axis = unit(axis)
        self.basis = tangent_basis(self.axis)
        self.fixed = fixed
        self.x0 = np.array([0.0, 0.0, float(distance)])

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, float]:
        return (self.axis.copy() if self.fixed else perturb_axis(self.axis, self.basis, x[:2])), float(x[2])

    def motion(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.fixed:
            return np.eye(3), float(x[2]) * self.axis
        direction = self.axis + self.basis @ x[:2]
        return np.eye(3), float(x[2]) * direction / np.sqrt(direction @ direction)

    def recentred(self, x: np.ndarray) -> Prismatic:
        axis, distance = self.unpack(x)
        return Prismatic(axis, distance, self.fixed)


Model = Revolute | Prismatic


def _rodrigues(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` (rad) about the unit ``axis`` (Rodrigues' formula)."""
    x, y, z = axis
    cross = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle) * cross + (1.0 - np.cos(angle)) * (cross @ cross)


def initial_models(transform: np.ndarray, start: np.ndarray,
                   slide_axis: np.ndarray | None = None) -> tuple[Revolute, Prismatic, dict]:
    """Revolute and prismatic initial models from a normalised (4, 4) start->end rigid motion,
    and {"screw_angle_deg", "screw_note"}. start (N, 3): normalised start points.
    slide_axis: (3,) a direction the prismatic model is held to (its distance starts at the
    motion's shift along it). O(N)."""
    reference = start.mean(axis=0)
    screw = screw_from_transform(transform[:3, :3], transform[:3, 3], reference=reference)
    shift = apply_transform(transform, reference[None])[0] - reference
    shift_norm = float(np.linalg.norm(shift))
    if screw.axis_defined and abs(screw.angle) > 1e-4:
        revolute = Revolute(screw.axis, screw.pivot, screw.angle, reference)
    else:  # (near) pure translation: mimic it by a small rotation about a far pivot
        _, _, vt = np.linalg.svd(start - reference, full_matrices=False)
        direction = shift / shift_norm if shift_norm > 1e-12 else vt[0]
        axis = np.cross(direction, vt[2])
        axis = unit(axis) if np.linalg.norm(axis) > 1e-6 else tangent_basis(direction)[:, 0]
        lever = 10.0
        revolute = Revolute(axis, reference - lever * np.cross(direction, axis), shift_norm / lever, reference)
    if slide_axis is not None:
        prismatic = Prismatic(slide_axis, float(shift @ unit(slide_axis)), fixed=True)
    else:
        prismatic = Prismatic(shift / shift_norm if shift_norm > 1e-12 else np.array([1.0, 0.0, 0.0]), shift_norm)
    return revolute, prismatic, {"screw_angle_deg": float(np.degrees(screw.angle)), "screw_note": screw.note}
