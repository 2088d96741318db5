"""Geometric fallback for view registration: metric clouds registered without features.

Used when features leave a view unreached (weak texture): PCA/FPFH hypotheses + coloured ICP
(:func:`sparseart.geometry.icp.register_rigid`), accepted only with enough overlap and when
neither view sees through the other's surfaces (free-space check).
"""
from __future__ import annotations

import numpy as np

from sparseart.align.features import PLANAR_FRACTION, THRESHOLD_FRACTION
from sparseart.geometry.clouds import spread
from sparseart.geometry.icp import register_rigid
from sparseart.geometry.transforms import apply_transform
from sparseart.types import Frame, Pointmap

GEOMETRY_MIN_OVERLAP = 0.5       # geometric fallback: accepted overlap fraction

MAX_FREE_SPACE_VIOLATION = 0.05  # geometric fallback: accepted share of points in seen-through space


def _free_space_violation(points: np.ndarray, frame: Frame, pointmap: Pointmap, size: float) -> float:
    """Fraction of ``points`` (in ``frame``'s camera frame) that land in front of the surface the
    camera saw (or on certain background): a wrong registration puts surfaces where this view saw
    through. O(N + H W)."""
    import cv2

    h, w = pointmap.height, pointmap.width
    valid = pointmap.valid.reshape(h, w)
    # Nearest seen surface over a 5x5 window: grazing surfaces change depth quickly per pixel.
    depth = np.where(valid, np.nan_to_num(pointmap.points[:, 2].reshape(h, w)), np.inf)
    depth = cv2.erode(depth.astype(np.float32), np.ones((5, 5), np.uint8)).astype(np.float64)
    background = cv2.dilate(valid.astype(np.uint8), np.ones((7, 7), np.uint8)) == 0
    points = points[points[:, 2] > 1e-9]
    uv = points @ frame.camera.K.T
    col, row = np.rint(uv[:, 0] / uv[:, 2]).astype(int), np.rint(uv[:, 1] / uv[:, 2]).astype(int)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    if inside.sum() < 30:
        return 0.0
    row, col, z = row[inside], col[inside], points[inside, 2]
    seen = depth[row, col]
    bad = background[row, col] | (np.isfinite(seen) & (z < seen - 2 * THRESHOLD_FRACTION * size))
    return float(bad.mean())


def geometry_edge(j: int, i: int, frames: list[Frame], pointmaps: list[Pointmap], clouds: list[np.ndarray],
                   size: float, seed: int) -> tuple[np.ndarray, float, float] | None:
    """Geometric fallback view j -> view i for metric clouds in their camera frames
    (:func:`sparseart.geometry.icp.register_rigid`: PCA/FPFH hypotheses + coloured ICP).

    None for planar clouds (they slide), small overlap, or when either view sees through the other
    one's surfaces (free-space check, which rejects the turned-around fits of symmetric objects).
    Returns ((4, 4) j -> i, overlap fraction, edge weight in [0, 1)). O(N log N + H W)."""
    if min(spread(clouds[i])[2], spread(clouds[j])[2]) < PLANAR_FRACTION * size:
        return None
    colors = [frames[k].rgb.reshape(-1, 3)[pointmaps[k].valid & np.isfinite(pointmaps[k].points).all(axis=1)]
              / 255.0 for k in (j, i)]
    result = register_rigid(clouds[j], clouds[i], colors[0], colors[1], seed=seed)
    if result.inlier_fraction < GEOMETRY_MIN_OVERLAP:
        return None
    forward = np.asarray(result.transform, dtype=np.float64)
    backward = np.linalg.inv(forward)
    violation = max(
        _free_space_violation(apply_transform(forward, clouds[j]), frames[i], pointmaps[i], size),
        _free_space_violation(apply_transform(backward, clouds[i]), frames[j], pointmaps[j], size))
    if violation > MAX_FREE_SPACE_VIOLATION:
        return None
    return forward, result.inlier_fraction, 0.999 * result.inlier_fraction * (1.0 - violation)
