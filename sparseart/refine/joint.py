"""The joint as differentiable torch parameters, with the fitter's parameterisation and motion
semantics (design section 3): revolute ``x -> pivot + R(axis, angle) (x - pivot)``, prismatic
``x -> x + distance * axis``. The axis is a free 3-vector normalised when used (its length is a
gauge), the pivot a free point (its position along the axis is a gauge, removed at the end).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..types import JointEstimate


@dataclass
class JointParams:
    """type: "revolute" | "prismatic"; axis (3,), pivot (3,), amount () torch tensors
    (amount = angle in radians or distance in frame units, start -> end)."""

    type: str
    axis: object
    pivot: object
    amount: object

    @classmethod
    def from_estimate(cls, joint: JointEstimate, dtype=None) -> "JointParams":
        import torch

        dtype = dtype or torch.float32
        amount = joint.angle if joint.type == "revolute" else joint.distance
        if amount is None or not np.isfinite(amount):
            raise ValueError(f"the {joint.type} seed joint has no finite angle/distance")
        return cls.from_values(joint.type, joint.axis, joint.origin, float(amount), dtype)

    @classmethod
    def from_values(cls, joint_type: str, axis, pivot, amount: float, dtype=None) -> "JointParams":
        import torch

        dtype = dtype or torch.float32
        axis = np.asarray(axis, dtype=np.float64)
        axis = axis / max(np.linalg.norm(axis), 1e-12)
        return cls(joint_type, torch.tensor(axis, dtype=dtype), torch.tensor(np.asarray(pivot, np.float64),
                                                                            dtype=dtype),
                   torch.tensor(float(amount), dtype=dtype))

    def tensors(self) -> list:
        return [self.axis, self.pivot, self.amount] if self.type == "revolute" else [self.axis, self.amount]

    def unit_axis(self):
        return self.axis / self.axis.norm().clamp_min(1e-12)

    def motion(self, fraction: float = 1.0, inverse: bool = False):
        """(R (3, 3), t (3,)) of ``x -> R x + t`` for ``fraction`` of the start -> end motion
        (fraction 1 = the joint's full motion; ``inverse`` gives the end -> start motion)."""
        import torch

        axis = self.unit_axis()
        amount = self.amount * fraction * (-1.0 if inverse else 1.0)
        eye = torch.eye(3, dtype=axis.dtype)
        if self.type == "prismatic":
            return eye, amount * axis
        zero = torch.zeros((), dtype=axis.dtype)
        skew = torch.stack([torch.stack([zero, -axis[2], axis[1]]),
                            torch.stack([axis[2], zero, -axis[0]]),
                            torch.stack([-axis[1], axis[0], zero])])
        rotation = eye + torch.sin(amount) * skew + (1.0 - torch.cos(amount)) * (skew @ skew)
        return rotation, self.pivot - rotation @ self.pivot

    def values(self, reference: np.ndarray | None = None) -> dict:
        """float64 values: {"type", "axis" unit (3,), "origin" (3,), "angle"|"distance"}; a
        revolute origin is moved along the axis to the point nearest ``reference``; a prismatic
        origin is ``reference`` (the part centre at start)."""
        axis = self.axis.detach().double().numpy()
        axis = axis / max(np.linalg.norm(axis), 1e-12)
        amount = float(self.amount.detach())
        if self.type == "prismatic":
            origin = np.zeros(3) if reference is None else np.asarray(reference, np.float64)
            return {"type": "prismatic", "axis": axis, "origin": origin, "angle": None, "distance": amount}
        origin = self.pivot.detach().double().numpy()
        if reference is not None:
            origin = origin + float(np.dot(np.asarray(reference, np.float64) - origin, axis)) * axis
        return {"type": "revolute", "axis": axis, "origin": origin, "angle": amount, "distance": None}

    def clone(self) -> "JointParams":
        return JointParams(self.type, self.axis.detach().clone(), self.pivot.detach().clone(),
                           self.amount.detach().clone())


def move_gaussians(means, quats, rotation, translation):
    """Move Gaussians rigidly: centres ``R x + t`` (N, 3) and orientations ``q_R * q`` (N, 4)."""
    from .gaussians import quaternion_multiply

    q_rotation = matrix_to_quaternion(rotation)
    return means @ rotation.T + translation, quaternion_multiply(q_rotation.expand_as(quats), quats)


def matrix_to_quaternion(rotation):
    """(3, 3) rotation -> (4,) unit quaternion (w, x, y, z), differentiable; stable for every
    angle (branch on the largest diagonal term, Shepperd's method)."""
    import torch

    m = rotation
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = torch.stack([trace, m[0, 0], m[1, 1], m[2, 2]])
    k = int(torch.argmax(candidates.detach()))
    if k == 0:
        s = torch.sqrt((1.0 + trace).clamp_min(1e-12)) * 2
        q = torch.stack([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    elif k == 1:
        s = torch.sqrt((1.0 + m[0, 0] - m[1, 1] - m[2, 2]).clamp_min(1e-12)) * 2
        q = torch.stack([(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s])
    elif k == 2:
        s = torch.sqrt((1.0 + m[1, 1] - m[0, 0] - m[2, 2]).clamp_min(1e-12)) * 2
        q = torch.stack([(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s])
    else:
        s = torch.sqrt((1.0 + m[2, 2] - m[0, 0] - m[1, 1]).clamp_min(1e-12)) * 2
        q = torch.stack([(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s])
    return q / q.norm()
