"""How far a correct 3D match may be off: inlier thresholds that grow with depth.

Matches are lifted through depth, and depth errors are multiplicative: a reconstructor's smooth
warp (~2 %) and per-view scale (~1 %), or a sensor's noise, move a point along its ray by a share
of its distance from the camera. A threshold fixed in scene units is then too tight far away (the
wall behind the object) and too loose near. Measured on the realistic renders of the 16 shared
objects (XFeat + LighterGlue matches, ground-truth poses): correct matches sit at a median 1.2 %
and a 90th percentile 3-3.5 % of their distance from the camera; on clean renders below 0.3 %.

A match's threshold is ``max(floor, rho * distance)``: ``floor`` is
``THRESHOLD_FRACTION * scene size`` (the clean-depth threshold the alignment always used),
``distance`` the larger distance of its two points from their cameras and ``rho`` the noise level,
estimated from the data (:func:`estimate_rho`): a robust fit starts loose (``RHO_MAX``), the
residuals of its inliers give ``rho = NOISE_SIGMAS x`` their robust sigma relative to distance
(from the lower quartile),
clipped to [0, ``RHO_MAX``], so clean depth keeps the tight floor and noisy depth gets room.
"""
from __future__ import annotations

import numpy as np

from sparseart.align.features import THRESHOLD_FRACTION

RHO_MAX = 0.05          # loosest threshold: 5 % of the distance from the camera
NOISE_SIGMAS = 3.0      # rho = this many robust sigmas of the relative residuals
QUARTILE_TO_SIGMA = 1.0 / 0.3187   # |x| of a zero-mean normal: lower quartile = 0.3187 sigma
# Depth this rough (per-pixel noise / distance, median view, :func:`depth_roughness`; raycasts ~1e-4,
# the realistic renders 5e-3) is treated as a sensor's or reconstructor's: ICP over it trades one
# surface's warp against another's. The view graph then skips its ICP polish (the poses got 1-2 deg
# worse) and the static polish of the states keeps only its constrained turn (:mod:`sparseart.align.static`).
MAX_CLEAN_ROUGHNESS = 0.002


def floor_threshold(size: float) -> float:
    """The depth-independent floor of every threshold: ``THRESHOLD_FRACTION`` of the scene size."""
    return THRESHOLD_FRACTION * float(size)


def thresholds(distance: np.ndarray, size: float, rho: float) -> np.ndarray:
    """(K,) per-match inlier thresholds ``max(floor, rho * distance)`` in scene units."""
    return np.maximum(floor_threshold(size), float(rho) * np.asarray(distance, dtype=np.float64))


def estimate_rho(residuals: np.ndarray, distance: np.ndarray, inliers: np.ndarray) -> float:
    """Noise level from a fit's inlier residuals: ``NOISE_SIGMAS`` robust sigmas of residual /
    distance, the sigma read off the lower quartile (``QUARTILE_TO_SIGMA``; the loose inlier set
    still holds wrong matches that a median would count as noise), clipped to [0, ``RHO_MAX``];
    ``RHO_MAX`` when fewer than 6 inliers. O(K)."""
    inliers = np.asarray(inliers, bool)
    if inliers.sum() < 6:
        return RHO_MAX
    relative = np.asarray(residuals, np.float64)[inliers] / np.maximum(np.asarray(distance, np.float64)[inliers], 1e-12)
    return float(np.clip(NOISE_SIGMAS * QUARTILE_TO_SIGMA * np.percentile(relative, 25), 0.0, RHO_MAX))


def depth_roughness(pointmap) -> float:
    """Per-pixel depth noise of a view, relative to distance: the median of |r(i-1) + r(i+1) -
    2 r(i)| / r(i) along rows and columns of the distance image r (both neighbours valid, no jump
    above 5 %, so depth edges do not count), divided by sqrt(6) (the second difference of white
    noise). A raycast gives ~1e-4, a sensor or reconstructor 0.3-1 %. Smooth warps do not show.
    NaN when fewer than 100 pixels qualify. O(H W)."""
    h, w = pointmap.height, pointmap.width
    points = np.asarray(pointmap.points, np.float64).reshape(h, w, 3)
    valid = np.asarray(pointmap.valid, bool).reshape(h, w) & np.isfinite(points).all(axis=2)
    r = np.where(valid, np.linalg.norm(np.nan_to_num(points), axis=2), np.nan)
    values = []
    for axis in (0, 1):
        lo, mid, hi = (np.take(r, np.arange(k, r.shape[axis] - 2 + k), axis=axis) for k in range(3))
        with np.errstate(invalid="ignore", divide="ignore"):
            smooth = (np.abs(lo - mid) < 0.05 * mid) & (np.abs(hi - mid) < 0.05 * mid)
            second = np.abs(lo + hi - 2.0 * mid) / mid
        values.append(second[smooth & np.isfinite(second)])
    values = np.concatenate(values)
    if values.size < 100:
        return float("nan")
    return float(np.median(values) / np.sqrt(6.0))
