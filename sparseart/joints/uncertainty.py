"""Honest 1-sigma joint uncertainty: a spatial block jackknife on top of the Jacobian covariance.

Why: the Jacobian covariance ``s^2 (J^T J)^+`` assumes independent residuals. Surface points of one
pixel grid are not independent, and the errors that dominate on real scenes are *systematic* and
spatially coherent (a region seen in one state only, a strip of static points labelled as moving,
correspondences biased on one face). They leave residual patterns that pull the estimate, but a
residual variance cannot see the pull. A *block* resampling can: split the part into ``K`` spatial
blocks (farthest-point centres, every residual assigned to the block of its point), re-estimate
without each block and take the spread of the ``K`` estimates (delete-a-group jackknife; Kunsch
1989, Busing et al. 1999). A block that holds a systematic error moves the estimate when dropped,
so its effect enters the variance; correlations shorter than a block are absorbed too.

The re-estimates are one Gauss-Newton step from the converged solution on the robust
(IRLS-weighted) Jacobian that the fitter already has (``_covariance``), i.e. the linearised
refit without the block -- exact for the linearised problem, and the same as the
cluster-robust "sandwich" covariance to first order. Chamfer neighbours stay frozen.

Cost: O(R p^2 + K p^3) for R residual rows and p <= 5 parameters plus an O(R K) block
assignment -- no extra residual evaluations (milliseconds).

How ``fit_joint`` states its sigma (variances added): Jacobian covariance (unchanged, also used by
the type test) + this block jackknife + the spread of re-matched half-sample refits
(``fit._fit_model.half_sample_covariance``: sees the correspondence noise of independent samples)
+ a calibrated floor ``fit.UNCERTAINTY_FLOOR`` x (pair residual / part radius). Measured on the 16
PartNet objects (``benchmarks/results/uncertainty_calibration.txt``): the two resampling terms are
small next to the true errors (axis 0.02-0.25 deg and 0.03-0.23 deg against errors up to 2.7 deg),
i.e. most of the real error is a bias shared by every subset, which no resampling can see; the
floor carries most of the correction. ``inlier_fraction`` below feeds the outlier warning.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def spatial_blocks(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Block index (n,) int of every point: nearest of ``count`` farthest-point-sampled centres.

    points (n, 3) float64. O(n count). Fewer than ``count`` distinct points -> fewer blocks.
    """
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=int)
    centres = [int(rng.integers(n))]
    distance = np.linalg.norm(points - points[centres[0]], axis=1)
    for _ in range(1, count):
        index = int(np.argmax(distance))
        if distance[index] <= 0:
            break
        centres.append(index)
        distance = np.minimum(distance, np.linalg.norm(points - points[index], axis=1))
    gaps = np.linalg.norm(points[:, None, :] - points[centres][None, :, :], axis=2)
    return np.argmin(gaps, axis=1)


def block_jackknife_covariance(jacobian: np.ndarray, residual: np.ndarray, blocks: np.ndarray,
                               rcond: float = 1e-12) -> tuple[np.ndarray, int]:
    """Delete-a-block jackknife covariance of one Gauss-Newton step, (p, p) float64, and the
    number of blocks used.

    jacobian (R, p), residual (R,): robust-weighted rows at the converged solution. blocks (R,)
    int: the spatial block of every row. For each block b the linearised estimate without it is
    ``d_b = -(H - H_b)^+ (g - g_b)`` with ``H = J^T J``, ``g = J^T r``; the covariance is
    ``(K-1)/K sum_b (d_b - d)(d_b - d)^T`` with ``d = -H^+ g`` the full-data step (so a solution
    that is not exactly converged adds nothing). Fewer than 2 blocks -> zeros.
    """
    p = jacobian.shape[1]
    labels = np.unique(blocks)
    if len(labels) < 2:
        return np.zeros((p, p)), len(labels)
    hessian = jacobian.T @ jacobian
    gradient = jacobian.T @ residual
    full = -np.linalg.pinv(hessian, rcond=rcond) @ gradient
    steps = []
    for label in labels:
        rows = blocks == label
        block_jacobian = jacobian[rows]
        reduced = hessian - block_jacobian.T @ block_jacobian
        steps.append(-np.linalg.pinv(reduced, rcond=rcond) @ (gradient - block_jacobian.T @ residual[rows]))
    deviation = np.array(steps) - full
    count = len(labels)
    return (count - 1) / count * deviation.T @ deviation, count


def inlier_fraction(start: np.ndarray, end: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                    spacing_quantile: float = 0.1, tolerance: float = 4.0) -> float:
    """Fraction of start points (n, 3) that land on the end cloud (m, 3) under the fitted motion.

    "On" = an end point within ``tolerance`` x the surface spacing, the ``spacing_quantile``
    quantile of the start cloud's nearest-neighbour distances (a low quantile: scattered outliers
    are sparse and must not set the scale). Surface points seen in both states count, points of a
    region seen in one state only and scattered outliers do not. O((n + m) log m).
    """
    if len(start) < 2 or len(end) < 1:
        return 0.0
    own = cKDTree(start).query(start, k=2)[0][:, 1]
    radius = tolerance * max(float(np.quantile(own, spacing_quantile)), 1e-12)
    distance = cKDTree(end).query(start @ rotation.T + translation)[0]
    return float(np.mean(distance <= radius))


def scatter_fraction(points: np.ndarray, rng: np.random.Generator, neighbours: int = 10,
                     max_points: int = 4000, threshold: float = 0.1) -> float:
    """Fraction of points (n, 3) not lying on a surface or curve: the smallest eigenvalue of their
    ``neighbours``-NN covariance exceeds ``threshold`` x the eigenvalue sum ("surface variation";
    ~0 on a sampled surface or wire, ~0.2-0.3 for points scattered in a volume). Estimated on at
    most ``max_points`` random points (neighbours from the whole cloud). O(n log n)."""
    if len(points) <= neighbours:
        return 0.0
    pick = rng.choice(len(points), min(max_points, len(points)), replace=False)
    _, index = cKDTree(points).query(points[pick], k=neighbours + 1)
    local = points[index] - points[index].mean(axis=1, keepdims=True)
    eigen = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", local, local))
    variation = eigen[:, 0] / np.maximum(eigen.sum(axis=1), 1e-300)
    return float(np.mean(variation > threshold))
