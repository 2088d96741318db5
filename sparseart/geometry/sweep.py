"""Physics of a rigid motion's first steps: does a part, moved a little along its motion, run into
another surface? A turn that drives a door into its cabinet, a slide that pushes a drawer through
its neighbour, is not the motion the part made, however well its end pose fits.

Each step is a share of the screw-interpolated motion (:class:`Screw`): ``STEP_FRACTIONS`` of it,
but at least ``MIN_STEP_RADII`` radii for the median point and at most half of it. A stepped point
is blocked when it lands within the radius of an obstacle it was not already touching, moving into
that surface rather than along it (:func:`moves_into_surface`). Used by the labeler's pairing and
motion ratings (obstacles: the other points of the same state) and by the fitter's check of a fitted
turn (obstacles: the static part seen in either state, :func:`~sparseart.joints.candidates.fit_parts`).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from sparseart.geometry.clouds import pca_normals
from sparseart.geometry.transforms import apply_transform

STEP_FRACTIONS = (0.15, 0.3)  # steps along the motion (share of the whole motion) ...
MIN_STEP_RADII = 3.0        # ... but at least this many radii for the median point
# A step meeting a surface blocks when |normal . step direction| >= this (15 deg off the surface).
# 30 deg (0.5) also let a real laptop lid's mirrored flip (84 deg about the wrong edge) sweep the
# base uncharged: it was chosen beside the true 96 deg turn and the confidence fell 0.68 -> 0.40.
INTO_SURFACE_SINE = 0.26
NORMAL_NEIGHBOURS = 8       # points of the surface whose smallest principal axis is its normal


class Screw:
    """Screw interpolation of a rigid motion: x -> p + R(s angle)(x - p) + s slide axis for a
    share s of the motion (closed form; a pure translation for tiny angles). O(1) per step."""

    def __init__(self, transform: np.ndarray, direction: float = 1.0) -> None:
        rotvec = Rotation.from_matrix(transform[:3, :3]).as_rotvec()
        angle = float(np.linalg.norm(rotvec))
        translation = transform[:3, 3]
        self.direction = direction
        if angle < 1e-6:
            self.axis, self.angle, self.pivot = np.zeros(3), 0.0, np.zeros(3)
            self.slide_vector = translation.copy()
            return
        axis = rotvec / angle
        slide = float(translation @ axis)
        perpendicular = translation - slide * axis
        pivot, *_ = np.linalg.lstsq(np.eye(3) - transform[:3, :3], perpendicular, rcond=1e-6)
        self.axis, self.angle, self.pivot = axis, angle, pivot
        self.slide_vector = slide * axis

    def at(self, share: float) -> np.ndarray:
        """(4, 4) motion for ``share`` of the whole (negative: of the inverse)."""
        s = share * self.direction
        transform = np.eye(4)
        rotation = Rotation.from_rotvec(self.axis * self.angle * s).as_matrix() if self.angle else np.eye(3)
        transform[:3, :3] = rotation
        transform[:3, 3] = self.pivot - rotation @ self.pivot + s * self.slide_vector
        return transform


def blocked_step_share(transform: np.ndarray, direction: float, points: np.ndarray, radius: float,
                       near_surface, surface: cKDTree | None = None) -> float:
    """The largest share of ``points`` that a small step of the motion pushes onto a surface they
    were not already touching (``near_surface(points) -> (n,) bool``: within ``radius`` of another
    surface). Steps are ``STEP_FRACTIONS`` of the screw-interpolated motion (``direction`` -1: of
    its inverse), at least ``MIN_STEP_RADII`` radii for the median point, at most half of it; 0 for
    motions whose median travel is under two such steps. With ``surface`` (a KD-tree of the points
    the obstacles belong to), a step that lands on a surface counts only when it moves into it
    (:func:`moves_into_surface`): a sash sliding past its neighbour at a gap under ``radius`` is not
    blocked. O(len(STEP_FRACTIONS)) calls of near_surface.
    """
    screw = Screw(transform, direction)
    travel = float(np.median(np.linalg.norm(apply_transform(screw.at(1.0), points) - points, axis=1)))
    if travel < 2.0 * MIN_STEP_RADII * radius:
        return 0.0
    touching = near_surface(points)
    least = MIN_STEP_RADII * radius / travel
    worst = 0.0
    for fraction in STEP_FRACTIONS:
        step = min(max(fraction, least), 0.5)
        stepped = apply_transform(screw.at(step), points)
        blocked = near_surface(stepped) & ~touching
        if surface is not None and blocked.any():
            blocked[blocked] = moves_into_surface(surface, stepped[blocked], stepped[blocked] - points[blocked])
        worst = max(worst, float(np.mean(blocked)))
    return worst


def moves_into_surface(surface: cKDTree, points: np.ndarray, displacement: np.ndarray) -> np.ndarray:
    """(n,) bool: does each step (``displacement``, (n, 3), ending at ``points``) run into the local
    surface of ``surface``'s points there rather than along it? The surface normal is the smallest
    principal axis of the ``NORMAL_NEIGHBOURS`` nearest points; into means
    |normal . direction| >= ``INTO_SURFACE_SINE``. O(n k log N)."""
    k = min(NORMAL_NEIGHBOURS, surface.n)
    if k < 3 or len(points) == 0:
        return np.ones(len(points), dtype=bool)
    normals = pca_normals(surface.data, points, k, tree=surface)
    length = np.linalg.norm(displacement, axis=1)
    direction = displacement / np.maximum(length, 1e-12)[:, None]
    return np.abs(np.einsum("ni,ni->n", normals, direction)) >= INTO_SURFACE_SINE
