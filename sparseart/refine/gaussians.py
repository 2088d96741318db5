"""3D Gaussians with a per-Gaussian mobility, built from a labelled point cloud.

Parameterisation (the stable one of 3DGS): centres (N, 3) in the scene frame (frame units),
quaternions (N, 4) (w, x, y, z; normalised when used), log-scales (N, 3), opacity logits (N,),
SH degree-0 colour coefficients ``f_dc`` (N, 3) with colour ``0.5 + SH_C0 * f_dc`` and a
mobility logit (N,) with mobility ``m = sigmoid(logit)`` in [0, 1]. A Gaussian's opacity
``o = sigmoid(opacity_logit)`` is split into a static component ``(1 - m) o`` and a mobile
component ``m o``; the two always sum to ``o``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SH_C0 = 0.28209479177387814
INITIAL_OPACITY = 0.8
NEIGHBOURS_FOR_SCALE = 3


def logit(p: np.ndarray | float) -> np.ndarray:
    """log(p / (1 - p)) with p clipped to [1e-6, 1 - 1e-6] (no inf)."""
    p = np.clip(np.asarray(p, dtype=np.float64), 1e-6, 1 - 1e-6)
    return np.log(p / (1.0 - p))


def rgb_to_dc(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) RGB in [0, 1] -> SH degree-0 coefficients."""
    return (np.asarray(rgb, dtype=np.float64) - 0.5) / SH_C0


@dataclass
class GaussianSet:
    """The Gaussians of one articulation state (torch tensors, all leaf parameters).

    means (N, 3), quats (N, 4), log_scales (N, 3), opacity_logits (N,), f_dc (N, 3),
    mobility_logits (N,). ``state`` is "start" or "end".
    """

    state: str
    means: object
    quats: object
    log_scales: object
    opacity_logits: object
    f_dc: object
    mobility_logits: object

    def __len__(self) -> int:
        return int(self.means.shape[0])

    # ---- activations
    def opacities(self):
        """(N,) o = sigmoid(opacity_logit)."""
        return self.opacity_logits.sigmoid()

    def mobility(self):
        """(N,) m = sigmoid(mobility_logit) in [0, 1]."""
        return self.mobility_logits.sigmoid()

    def static_opacities(self):
        """(N,) (1 - m) o: the static component's opacity."""
        return (1.0 - self.mobility()) * self.opacities()

    def mobile_opacities(self):
        """(N,) m o: the mobile component's opacity."""
        return self.mobility() * self.opacities()

    def colors(self):
        """(N, 3) RGB = 0.5 + SH_C0 f_dc, clamped to [0, 1] (as 3DGS clamps at 0)."""
        return (0.5 + SH_C0 * self.f_dc).clamp(0.0, 1.0)

    # ---- bookkeeping
    def tensors(self) -> dict:
        return {"means": self.means, "quats": self.quats, "log_scales": self.log_scales,
                "opacity_logits": self.opacity_logits, "f_dc": self.f_dc,
                "mobility_logits": self.mobility_logits}

    def requires_grad_(self, names: tuple[str, ...]) -> "GaussianSet":
        """Make the named tensors trainable and freeze the others."""
        for name, tensor in self.tensors().items():
            tensor.requires_grad_(name in names)
        return self

    def to_numpy(self) -> dict[str, np.ndarray]:
        """float64 copies of every raw parameter and of the activated opacity/mobility/colour."""
        out = {k: v.detach().double().numpy().copy() for k, v in self.tensors().items()}
        out["opacity"] = 1.0 / (1.0 + np.exp(-out["opacity_logits"]))
        out["mobility"] = 1.0 / (1.0 + np.exp(-out["mobility_logits"]))
        out["colors"] = np.clip(0.5 + SH_C0 * out["f_dc"], 0.0, 1.0)
        return out

    @classmethod
    def from_numpy(cls, state: str, arrays: dict[str, np.ndarray], dtype=None) -> "GaussianSet":
        """Leaf tensors (no grad yet) from float arrays named as in :meth:`tensors`."""
        import torch

        dtype = dtype or torch.float32
        tensors = {k: torch.as_tensor(np.asarray(arrays[k], dtype=np.float64), dtype=dtype).clone()
                   for k in ("means", "quats", "log_scales", "opacity_logits", "f_dc", "mobility_logits")}
        return cls(state=state, **tensors)

    def clone(self) -> "GaussianSet":
        return GaussianSet(self.state, *(t.detach().clone() for t in self.tensors().values()))


def neighbour_spacing(points: np.ndarray, k: int = NEIGHBOURS_FOR_SCALE) -> np.ndarray:
    """(N,) mean distance of each point to its k nearest neighbours (frame units); points that
    coincide with all neighbours get the median spacing. O(N log N) with a KD-tree."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    if len(points) < 2:
        return np.full(len(points), 1e-3)
    k = min(k, len(points) - 1)
    distances, _ = cKDTree(points).query(points, k=k + 1)
    spacing = distances[:, 1:].mean(axis=1)
    positive = spacing[spacing > 0]
    fallback = float(np.median(positive)) if len(positive) else 1e-3
    return np.where(spacing > 0, spacing, fallback)


def gaussians_from_points(state: str, points: np.ndarray, colors: np.ndarray, mobility: np.ndarray,
                          dtype=None) -> GaussianSet:
    """One isotropic Gaussian per point.

    points: (N, 3) float64 scene frame; colors: (N, 3) RGB in [0, 1]; mobility: (N,) initial
    mobility in [0, 1]. The scale is the mean spacing to the 3 nearest neighbours, the opacity
    ``INITIAL_OPACITY``, the rotation the identity. O(N log N).
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"need a non-empty (N, 3) point array to build Gaussians, got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points for the Gaussians contain NaN or inf")
    count = len(points)
    spacing = neighbour_spacing(points)
    arrays = {
        "means": points,
        "quats": np.tile([1.0, 0.0, 0.0, 0.0], (count, 1)),
        "log_scales": np.repeat(np.log(spacing)[:, None], 3, axis=1),
        "opacity_logits": np.full(count, float(logit(INITIAL_OPACITY))),
        "f_dc": rgb_to_dc(np.clip(colors, 0.0, 1.0)),
        "mobility_logits": logit(mobility),
    }
    return GaussianSet.from_numpy(state, arrays, dtype)


def initial_mobility(part_of_point: np.ndarray, movable_id: int, static_value: float = 0.05,
                     movable_value: float = 0.95, unsure_value: float = 0.5) -> np.ndarray:
    """(N,) initial mobility from the labeler's part ids: part 0 (static) -> low, ``movable_id``
    -> high, anything else (-1 = unassigned) -> 0.5."""
    part_of_point = np.asarray(part_of_point)
    return np.where(part_of_point == 0, static_value,
                    np.where(part_of_point == movable_id, movable_value, unsure_value))


def quaternion_multiply(left, right):
    """Hamilton product of (…, 4) quaternions (w, x, y, z): the rotation ``left`` after ``right``."""
    import torch

    w1, x1, y1, z1 = left.unbind(-1)
    w2, x2, y2, z2 = right.unbind(-1)
    return torch.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], dim=-1)
