"""Synthetic two-state clouds of box-shaped parts, seen from one side (partial views)."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from sparseart.types import JointEstimate, LabelledCloud


def box_surface(size, centre, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) points uniformly on the surface of an axis-aligned box and their outward normals."""
    size = np.asarray(size, float)
    areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]] * 2)
    faces = rng.choice(6, size=n, p=areas / areas.sum())
    local = (rng.random((n, 3)) - 0.5) * size
    normals = np.zeros((n, 3))
    for face in range(6):
        axis, sign = face % 3, (1 if face < 3 else -1)
        sel = faces == face
        local[sel, axis] = sign * size[axis] / 2
        normals[sel, axis] = sign
    return local + np.asarray(centre, float), normals


def visible(points: np.ndarray, normals: np.ndarray, viewpoint) -> np.ndarray:
    return np.einsum("ij,ij->i", normals, np.asarray(viewpoint) - points) > 0


def make_clouds(kind: str = "revolute", amount: float = np.radians(40), noise: float = 0.001,
                seed: int = 0, n: int = 6000, viewpoint=(2.0, -3.0, 2.5)):
    """Body (mask 1) + one moving panel (mask 2) in two states.

    Returns (start, end, truth) with truth {"type", "axis", "origin", "angle"|"distance"}.
    """
    rng = np.random.default_rng(seed)
    body, body_n = box_surface([1.0, 0.6, 1.2], [0, 0.3, 0.6], n, rng)
    if kind == "revolute":
        panel, panel_n = box_surface([0.9, 0.04, 1.1], [0.45, -0.02, 0.6], n // 2, rng)
        axis, origin = np.array([0, 0, 1.0]), np.array([0.0, 0.0, 0.6])
        rotation = Rotation.from_rotvec(axis * amount).as_matrix()
        move = lambda p: (p - origin) @ rotation.T + origin  # noqa: E731
        turn = lambda v: v @ rotation.T  # noqa: E731
        truth = {"type": "revolute", "axis": axis, "origin": origin, "angle": amount}
    else:
        panel, panel_n = box_surface([0.8, 0.5, 0.3], [0.0, 0.27, 0.3], n // 2, rng)
        axis = np.array([0, -1.0, 0])
        move = lambda p: p + amount * axis  # noqa: E731
        turn = lambda v: v  # noqa: E731
        truth = {"type": "prismatic", "axis": axis, "origin": panel.mean(0), "distance": amount}
    clouds = []
    for state, panel_points, panel_normals in (("start", panel, panel_n), ("end", move(panel), turn(panel_n))):
        points = np.concatenate([body, panel_points])
        normals = np.concatenate([body_n, panel_normals])
        segment = np.concatenate([np.full(len(body), 1), np.full(len(panel), 2)]).astype(np.int64)
        keep = visible(points, normals, viewpoint)
        points = points[keep] + rng.normal(0, noise, (keep.sum(), 3))
        segment = segment[keep]
        colors = np.where(segment[:, None] == 1, [0.6, 0.6, 0.6], [0.8, 0.3, 0.2])
        clouds.append(LabelledCloud(state=state, points=points, colors=colors, segment=segment,
                                    frame_index=np.zeros(len(points), np.int64),
                                    pixel_index=np.arange(len(points), dtype=np.int64),
                                    confidence=np.ones(len(points)), segment_source={1: (0, 1), 2: (0, 2)}))
    return clouds[0], clouds[1], truth


def labelled_cloud(state: str, points: np.ndarray) -> LabelledCloud:
    """A grey LabelledCloud of (N, 3) points: no mask ids, part 0, full confidence."""
    n = len(points)
    return LabelledCloud(state, points, np.full((n, 3), 0.5), np.full(n, -1), np.zeros(n, np.int64),
                         np.arange(n), np.ones(n))


def joint_estimate(kind: str, axis, origin, amount: float, transform: np.ndarray,
                   axis_sigma_deg: float = 0.1) -> JointEstimate:
    """A JointEstimate of ``kind`` turning ``amount`` rad / sliding ``amount`` units, confidence 0.9."""
    uncertainty = {"axis_deg": axis_sigma_deg, "origin": 0.001,
                   ("angle" if kind == "revolute" else "distance"): 0.01}
    return JointEstimate(type=kind, axis=np.asarray(axis, float), origin=np.asarray(origin, float),
                         angle=amount if kind == "revolute" else None,
                         distance=amount if kind == "prismatic" else None, transform=transform,
                         uncertainty=uncertainty, residual=0.001, confidence=0.9)
