"""Fit a revolute or prismatic joint to one part's points in two states.

Pipeline of ``fit_joint`` (all maths in float64 on coordinates centred at the joint centroid of
both sets and divided by their RMS radius; results converted back at the end):

1. clean both sets (``clean.clean_part_points``), normalise scale;
2. initial rigid motion (given, or ``register.register_rigid``) -> screw decomposition -> revolute
   init (axis, pivot, angle) and prismatic init (centroid shift);
3. alternate Hungarian matching (``scipy.optimize.linear_sum_assignment``, O(n^3) on a random
   subsample of at most ``FitConfig.max_match_points`` per side; costs are clipped at a robust
   distance so points without a partner -- partial views -- stay unmatched) with joint-parameter
   updates, until the assignment is stable;
4. revolute pairs get distance-proportional weights ``w = N (d~ + beta) / sum(d~ + beta)``;
5. minimise ``L_align + alpha * L_CD`` (weighted pair residuals + symmetric Chamfer residuals
   via cKDTree) over the joint's own parameters with ``scipy.optimize.least_squares`` (soft_l1);
6. covariance ``s^2 (J^T J)^+`` at the optimum, inflated by an effective-sample factor (this one
   drives the type test and stays as it was);
7. type selection (``select.select_joint_type``) for ``joint_type="auto"``;
8. stated uncertainty (``JointEstimate.uncertainty``) = the Jacobian covariance of 6 + a spatial
   block jackknife of the linearised fit + the spread of warm-started refits on re-matched
   half-samples of the chosen model + a calibrated systematic floor (``UNCERTAINTY_FLOOR``), added
   as variances (see ``sparseart.joints.uncertainty``); the parts are kept in
   ``diagnostics["uncertainty_jacobian" | "uncertainty_resample" | "uncertainty_half" |
   "uncertainty_floor"]``. None of it changes the point estimates (own random generators).
   Why: on rendered objects the errors are dominated by systematic effects (partial views, label
   errors, correspondence bias) that a residual-based sigma cannot see; the Jacobian sigma alone
   covered 39 % / 50 % / 72 % of the axis errors at 1 / 2 / 3 sigma on the 16 PartNet objects,
   the stated sigma covers 75 % / 90 % / 90 % (benchmarks/results/uncertainty_calibration_v2.txt);
9. reliability warnings with the module constants below (shared with ``sparseart.bench.stability``).
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np
from scipy.optimize import least_squares, linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from sparseart.joints.clean import clean_part_points, estimate_normals
from sparseart.geometry.icp import register_rigid
from sparseart.geometry.transforms import (apply_transform, make_transform, perturb_axis, screw_from_transform,
                                    tangent_basis, transform_from_prismatic, transform_from_revolute, unit)
from sparseart.joints.select import select_joint_type
from sparseart.joints.uncertainty import (block_jackknife_covariance, inlier_fraction, scatter_fraction,
                                          spatial_blocks)
from sparseart.geometry.sampling import random_subset
from sparseart.types import JointEstimate

MIN_POINTS = 5
# Warning thresholds; sparseart/stability.py imports these to mark "unreliable" rows the same way.
ILL_CONDITIONED = 1e6        # Jacobian condition number above which the fit is called ill-conditioned
# Outliers: more than MAX_SCATTER_FRACTION of the cleaned points off any surface
# (uncertainty.scatter_fraction) AND fewer than MIN_INLIER_FRACTION of the start points landing on
# the end cloud under the fit (uncertainty.inlier_fraction). Either alone also fires on good fits
# (thin shells scatter; partial overlap leaves points unmatched: 0.23-0.38 seen on PartNet renders).
MAX_SCATTER_FRACTION = 0.4
MIN_INLIER_FRACTION = 0.5
MAX_AXIS_SIGMA_DEG = 5.0     # stated axis 1-sigma above this: "uncertainty large" (2 sigma = the 10 deg success bar)
MAX_RELATIVE_SIGMA = 0.25    # stated angle / distance 1-sigma above this fraction of the estimate: "uncertainty large"
# Calibrated floor (benchmarks/uncertainty_calibration.py): systematic errors (partial views, label
# errors, correspondence bias) tilt the axis by about this fraction of the angle the pair residual
# subtends over the part radius; added in quadrature to the statistical sigma.
UNCERTAINTY_FLOOR = 0.2


@dataclass
class FitConfig:
    """Knobs of ``fit_joint``; defaults suit parts of 1e2..1e5 points.

    max_match_points: subsample per side for Hungarian matching (cost O(n^3)).
    max_chamfer_points: subsample per side for the Chamfer term.
    chamfer_weight: alpha in ``L_align + alpha * L_CD``. beta: weight floor for revolute pairs.
    match_iterations: max matching / update alternations.
    correlation_factor: variance inflation of the covariance -- "residuals per independent
        residual": dense surface residuals are correlated, subsampled Chamfer/Hungarian pairs share
        points, and partial views leave a small bias. Calibrated on synthetic partial views with
        3 mm noise (tests/test_joints.py::test_uncertainty_coverage): about 90 % of true errors
        fall within 3 sigma. bic_correlation_factor: the same idea for the BIC sample count.
    angle_z, min_angle_deg: significance test of the rotation in auto mode.
    far_pivot_factor: warn when the pivot is farther than this x the part radius (for a prismatic
        answer: when the rigid motion turns by more than small_angle_deg and the revolute fit's
        pivot is that far -- small angle x large radius ~ translation).
    small_angle_deg: warn below this rotation. few_points: warn below this count.
    uncertainty_resamples: spatial blocks of the linearised block jackknife (< 2: off).
    half_samples: warm-started refits on re-matched random half-samples (at most
        half_sample_points per side) of the chosen model (< 2: off); about 5-15 % of the fit time.
    uncertainty_floor: add the calibrated systematic floor (``UNCERTAINTY_FLOOR``) to the stated sigma.
    """

    max_match_points: int = 1500
    max_chamfer_points: int = 1500
    chamfer_weight: float = 0.5
    beta: float = 0.1
    match_iterations: int = 6
    correlation_factor: float = 25.0
    bic_correlation_factor: float = 4.0
    angle_z: float = 4.0
    min_angle_deg: float = 0.1
    far_pivot_factor: float = 5.0
    small_angle_deg: float = 1.0
    few_points: int = 50
    uncertainty_resamples: int = 6
    half_samples: int = 4
    half_sample_points: int = 600
    uncertainty_floor: bool = True
    robust_loss: str = "soft_l1"
    pair_tau_factor: float = 3.0
    normal_gate_deg: float = 45.0
    clean: bool = True
    seed: int = 0


class _Revolute:
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
        axis, pivot, angle = self.unpack(x)
        rotation = Rotation.from_rotvec(axis * angle).as_matrix()
        return rotation, pivot - rotation @ pivot

    def recentred(self, x: np.ndarray) -> "_Revolute":
        axis, pivot, angle = self.unpack(x)
        return _Revolute(axis, pivot, angle, self.reference)


class _Prismatic:
    """Prismatic parameters around a reference state: x = [u1, u2, distance]."""

    kind = "prismatic"

    def __init__(self, axis: np.ndarray, distance: float):
        self.axis = unit(axis)
        self.basis = tangent_basis(self.axis)
        self.x0 = np.array([0.0, 0.0, float(distance)])

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, float]:
        return perturb_axis(self.axis, self.basis, x[:2]), float(x[2])

    def motion(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        axis, distance = self.unpack(x)
        return np.eye(3), distance * axis

    def recentred(self, x: np.ndarray) -> "_Prismatic":
        axis, distance = self.unpack(x)
        return _Prismatic(axis, distance)


def _hungarian_pairs(moved: np.ndarray, end: np.ndarray, end_tree: cKDTree, floor: float, ceiling: float,
                     tau_factor: float = 3.0, moved_normals: np.ndarray | None = None,
                     end_normals: np.ndarray | None = None, normal_cos: float = 0.0):
    """One-to-one pairs between moved start (n, 3) and end (m, 3) points.

    Costs are squared distances clipped at tau^2 (tau = 3 x median NN distance, kept within
    [floor, ceiling]), so a point whose partner is hidden costs the same whatever it is paired
    with and is rejected afterwards; pairs whose normals differ by more than arccos(normal_cos) cost
    tau^2 too. O(n m) memory; linear_sum_assignment is O(n^3) worst case
    but fast when few costs fall below the clip (about 0.03 s for n = m = 1500 near the optimum).
    """
    nearest, _ = end_tree.query(moved)
    tau = min(max(tau_factor * float(np.median(nearest)), floor), max(ceiling, floor))
    cost = cdist(moved, end, "sqeuclidean")
    if moved_normals is not None:
        cost[np.abs(moved_normals @ end_normals.T) < normal_cos] = np.inf
    rows, cols = linear_sum_assignment(np.minimum(cost, tau * tau))
    keep = cost[rows, cols] < tau * tau
    return rows[keep], cols[keep], tau


def _pair_weights(kind: str, start: np.ndarray, end: np.ndarray, beta: float) -> np.ndarray:
    """Distance-proportional weights (revolute) or ones (prismatic), mean 1, shape (K,)."""
    count = start.shape[0]
    if kind != "revolute" or count == 0:
        return np.ones(count)
    displacement = np.linalg.norm(end - start, axis=1)
    span = displacement.max() - displacement.min()
    normalised = (displacement - displacement.min()) / span if span > 1e-12 else np.zeros(count)
    return count * (normalised + beta) / np.sum(normalised + beta)


class _Problem:
    """Residual vector of L_align + alpha L_CD for one model; all arrays normalised float64."""

    def __init__(self, model, pair_start, pair_end, weights, chamfer_start=None, chamfer_end=None, alpha=0.5,
                 loss="soft_l1", chamfer_normals=None, normal_cos=0.0):
        self.model, self.loss, self.normal_cos = model, loss, normal_cos
        self.chamfer_normals = chamfer_normals  # (start normals, end normals) or None
        self.pair_start, self.pair_end = pair_start, pair_end
        self.sqrt_weights = np.sqrt(weights)[:, None]
        self.chamfer = chamfer_start is not None and alpha > 0
        if self.chamfer:
            self.chamfer_start, self.chamfer_end = chamfer_start, chamfer_end
            self.start_tree, self.end_tree = cKDTree(chamfer_start), cKDTree(chamfer_end)
            count = max(len(pair_start), 1)
            self.start_factor = np.sqrt(alpha * count / len(chamfer_start))
            self.end_factor = np.sqrt(alpha * count / len(chamfer_end))

    def residuals(self, x: np.ndarray, frozen: tuple | None = None) -> np.ndarray:
        """(3K [+ 3 n_s + 3 n_e],) residual components; O(K + n log n).

        frozen: (forward index, backward index, forward mask, backward mask) from ``matches`` to
        keep the Chamfer nearest neighbours fixed (smooth residuals for the Jacobian).
        """
        rotation, translation = self.model.motion(x)
        align = self.sqrt_weights * (self.pair_start @ rotation.T + translation - self.pair_end)
        if not self.chamfer:
            return align.ravel()
        moved = self.chamfer_start @ rotation.T + translation
        back = (self.chamfer_end - translation) @ rotation
        forward, backward, forward_ok, backward_ok = frozen if frozen is not None else self.matches(x)
        forward_residual = self.start_factor * (moved - self.chamfer_end[forward]) * forward_ok[:, None]
        backward_residual = self.end_factor * (back - self.chamfer_start[backward]) * backward_ok[:, None]
        return np.concatenate([align.ravel(), forward_residual.ravel(), backward_residual.ravel()])

    def matches(self, x: np.ndarray) -> tuple:
        """Chamfer nearest neighbours at ``x`` and the normal-agreement masks (hidden partners = 0)."""
        rotation, translation = self.model.motion(x)
        _, forward = self.end_tree.query(self.chamfer_start @ rotation.T + translation)
        _, backward = self.start_tree.query((self.chamfer_end - translation) @ rotation)
        forward_ok = np.ones(len(forward))
        backward_ok = np.ones(len(backward))
        if self.chamfer_normals is not None:
            start_normals, end_normals = self.chamfer_normals
            forward_ok = np.abs(np.einsum("ij,ij->i", start_normals @ rotation.T, end_normals[forward])) >= self.normal_cos
            backward_ok = np.abs(np.einsum("ij,ij->i", start_normals[backward] @ rotation.T, end_normals)) >= self.normal_cos
        return forward, backward, forward_ok.astype(float), backward_ok.astype(float)

    def solve(self, x0: np.ndarray, f_scale: float, max_nfev: int, freeze: bool = False):
        """Robust least squares from ``x0``; ``freeze``: Chamfer neighbours fixed at ``x0`` (cheap
        residuals, for short warm-started refits)."""
        function = self.residuals
        if freeze and self.chamfer:
            frozen = self.matches(x0)
            function = lambda x: self.residuals(x, frozen)  # noqa: E731
        return least_squares(function, x0, loss=self.loss, f_scale=f_scale, x_scale="jac",
                             max_nfev=max_nfev, method="trf")


def _covariance(problem: _Problem, x: np.ndarray, f_scale: float,
                factor: float) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """cov = factor * s^2 (J_w^T J_w)^+ with soft_l1 IRLS weights; returns (cov, condition number,
    J_w (R, p), r_w (R,)) -- the robust-weighted Jacobian and residual rows, reused by the block
    jackknife (``uncertainty.block_jackknife_covariance``).

    J by central differences (2p residual evaluations) with the Chamfer neighbours frozen at ``x``
    (otherwise a neighbour switch inside the step fakes a huge derivative); s^2 from the align
    residuals.
    """
    frozen = problem.matches(x) if problem.chamfer else None
    residual = problem.residuals(x, frozen)
    step = 1e-6
    columns = []
    for index in range(x.size):
        delta = np.zeros_like(x)
        delta[index] = step
        columns.append((problem.residuals(x + delta, frozen) - problem.residuals(x - delta, frozen)) / (2 * step))
    jacobian = np.stack(columns, axis=1)
    z = (residual / f_scale) ** 2
    rho_prime = {"soft_l1": 1.0 / np.sqrt(1.0 + z), "cauchy": 1.0 / (1.0 + z), "arctan": 1.0 / (1.0 + z * z),
                 "huber": np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1.0)))}.get(problem.loss, np.ones_like(z))
    robust = np.sqrt(rho_prime)
    weighted_jacobian = jacobian * robust[:, None]
    align_count = 3 * len(problem.pair_start)
    align = residual[:align_count] * robust[:align_count]
    variance = float(align @ align) / max(align_count - x.size, 1)
    singular = np.linalg.svd(weighted_jacobian, compute_uv=False)
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else float("inf")
    normal = weighted_jacobian.T @ weighted_jacobian
    return factor * variance * np.linalg.pinv(normal, rcond=1e-12), condition, weighted_jacobian, residual * robust


def _fit_model(model, start, end, start_normals, end_normals, config: FitConfig,
               rng: np.random.Generator) -> dict:
    """Hungarian/update alternation then the full robust solve for one model (normalised units)."""
    pick_start = random_subset(len(start), config.max_match_points, rng)
    pick_end = random_subset(len(end), config.max_match_points, rng)
    match_start, match_end = start[pick_start], end[pick_end]
    match_start_normals, match_end_normals = start_normals[pick_start], end_normals[pick_end]
    pick_start = random_subset(len(start), config.max_chamfer_points, rng)
    pick_end = random_subset(len(end), config.max_chamfer_points, rng)
    chamfer_start, chamfer_end = start[pick_start], end[pick_end]
    chamfer_normals = (start_normals[pick_start], end_normals[pick_end])
    normal_cos = float(np.cos(np.radians(config.normal_gate_deg)))
    end_tree = cKDTree(match_end)
    spacing = float(np.median(end_tree.query(match_end, k=2)[0][:, 1])) if len(match_end) > 1 else 0.0
    floor, ceiling = max(2.0 * spacing, 1e-9), 8.0 * spacing

    def pairs(rotation, translation):
        moved = match_start @ rotation.T + translation
        rows, cols, tau = _hungarian_pairs(moved, match_end, end_tree, floor, ceiling, config.pair_tau_factor,
                                           match_start_normals @ rotation.T, match_end_normals, normal_cos)
        if len(rows) < MIN_POINTS:
            rows = cols = np.arange(min(len(match_start), len(match_end)))
        return moved, rows, cols, tau

    x = model.x0
    for _ in range(config.match_iterations):
        rotation, translation = model.motion(x)
        before, rows, cols, tau = pairs(rotation, translation)
        weights = _pair_weights(model.kind, match_start[rows], match_end[cols], config.beta)
        problem = _Problem(model, match_start[rows], match_end[cols], weights, loss=config.robust_loss)
        result = problem.solve(x, f_scale=max(tau / 3.0, 1e-9), max_nfev=30)
        model = model.recentred(result.x)
        x = model.x0
        rotation, translation = model.motion(x)
        change = float(np.max(np.linalg.norm(match_start @ rotation.T + translation - before, axis=1)))
        if change < 0.05 * max(spacing, 1e-9):  # assignment cannot change any more
            break
    rotation, translation = model.motion(x)
    moved, rows, cols, tau = pairs(rotation, translation)
    weights = _pair_weights(model.kind, match_start[rows], match_end[cols], config.beta)
    problem = _Problem(model, match_start[rows], match_end[cols], weights, chamfer_start, chamfer_end,
                       config.chamfer_weight, config.robust_loss,
                       chamfer_normals if config.normal_gate_deg < 90 else None, normal_cos)
    pair_distance = np.linalg.norm(moved[rows] - match_end[cols], axis=1)
    f_scale = max(1.4826 * float(np.median(pair_distance)) / np.sqrt(3.0), tau / 6.0, 1e-9)
    result = problem.solve(x, f_scale=f_scale, max_nfev=50)
    x = result.x
    covariance, condition, weighted_jacobian, weighted_residual = _covariance(problem, x, f_scale,
                                                                             config.correlation_factor)
    rotation, translation = model.motion(x)
    began = time.perf_counter()
    resample_covariance, blocks_used = _resample_covariance(problem, rotation, translation, weighted_jacobian,
                                                            weighted_residual, config)
    resample_seconds = time.perf_counter() - began
    pair_residual = np.linalg.norm(match_start[rows] @ rotation.T + translation - match_end[cols], axis=1)
    # Truncated symmetric Chamfer RSS on the common chamfer subsamples (comparable across models).
    # Point-to-plane distances of the Chamfer neighbours: free of the sampling-spacing floor of
    # point-to-point distances, so small real rotations stand out against a translation.
    moved_chamfer = chamfer_start @ rotation.T + translation
    _, forward_index = cKDTree(chamfer_end).query(moved_chamfer)
    _, backward_index = cKDTree(moved_chamfer).query(chamfer_end)
    forward = np.abs(np.einsum("ij,ij->i", moved_chamfer - chamfer_end[forward_index], chamfer_normals[1][forward_index]))
    backward = np.abs(np.einsum("ij,ij->i", chamfer_end - moved_chamfer[backward_index],
                                chamfer_normals[0][backward_index] @ rotation.T))

    def half_sample_covariance(count: int, max_points: int, max_nfev: int = 8) -> np.ndarray:
        """Spread of ``count`` refits on random subsets (half, at most ``max_points`` per side) of
        both states' matching and Chamfer points, each re-matched (Hungarian) at the converged
        motion and solved warm-started from it with the Chamfer neighbours frozen (at most
        ``max_nfev`` evaluations). A subset holding a fraction f of the points deviates from the
        full-data solution with about (1/f - 1) x the variance of the full-data estimate (delete-d
        jackknife), so the covariance is f/(1-f) x the mean outer product of the deviations.
        Own random generator: the fit itself is unchanged. Cost per refit: O(m^3) Hungarian on m
        points plus a small solve."""
        centred = model.recentred(x)
        half_rng = np.random.default_rng(config.seed + 7919)
        size = max(min(len(match_start), len(match_end)) // 2, MIN_POINTS)
        size = min(size, max_points)
        fraction = size / max(min(len(match_start), len(match_end)), 1)
        if fraction >= 1.0:
            return np.zeros((x.size, x.size))
        chamfer_size = max(min(min(len(chamfer_start), len(chamfer_end)) // 2, max_points), MIN_POINTS)
        deviations = []
        for _ in range(count):
            half_start = half_rng.permutation(len(match_start))[:size]
            half_end = half_rng.permutation(len(match_end))[:size]
            start_h, end_h = match_start[half_start], match_end[half_end]
            moved_h = start_h @ rotation.T + translation
            rows_h, cols_h, _ = _hungarian_pairs(moved_h, end_h, cKDTree(end_h), floor, ceiling,
                                                 config.pair_tau_factor, match_start_normals[half_start] @ rotation.T,
                                                 match_end_normals[half_end], normal_cos)
            if len(rows_h) < MIN_POINTS:
                continue
            chamfer_s = half_rng.permutation(len(chamfer_start))[:chamfer_size]
            chamfer_e = half_rng.permutation(len(chamfer_end))[:chamfer_size]
            half_problem = _Problem(centred, start_h[rows_h], end_h[cols_h],
                                    _pair_weights(model.kind, start_h[rows_h], end_h[cols_h], config.beta),
                                    chamfer_start[chamfer_s], chamfer_end[chamfer_e], config.chamfer_weight,
                                    config.robust_loss,
                                    (chamfer_normals[0][chamfer_s], chamfer_normals[1][chamfer_e])
                                    if config.normal_gate_deg < 90 else None, normal_cos)
            refit = half_problem.solve(centred.x0, f_scale=f_scale, max_nfev=max_nfev, freeze=True)
            deviations.append(refit.x - centred.x0)
        if len(deviations) < 2:
            return np.zeros((x.size, x.size))
        deviations = np.array(deviations)
        return fraction / (1.0 - fraction) * deviations.T @ deviations / len(deviations)

    return {"model": model, "x": x, "covariance": covariance, "condition": condition,
            "resample_covariance": resample_covariance, "resample_blocks": blocks_used,
            "resample_seconds": resample_seconds,
            "half_sample_covariance": half_sample_covariance,
            "rotation": rotation, "translation": translation, "pair_residual": pair_residual,
            "tau": tau, "chamfer": np.concatenate([forward, backward]),
            "match_fraction": len(rows) / max(min(len(match_start), len(match_end)), 1),
            "pairs": len(rows), "pair_start": match_start[rows], "pair_end": match_end[cols]}


def _resample_covariance(problem: _Problem, rotation: np.ndarray, translation: np.ndarray, jacobian: np.ndarray,
                         residual: np.ndarray, config: FitConfig) -> tuple[np.ndarray, int]:
    """Spatial block-jackknife covariance of the converged fit (see ``uncertainty``); zeros when
    ``config.uncertainty_resamples`` < 2. Every residual row is assigned to the block of its point
    in the start frame (end-state Chamfer points mapped back by the fitted motion). Uses its own
    random generator, so the fit's subsamples and estimates do not change."""
    p = jacobian.shape[1]
    if config.uncertainty_resamples < 2:
        return np.zeros((p, p)), 0
    locations = [problem.pair_start]
    if problem.chamfer:
        locations += [problem.chamfer_start, (problem.chamfer_end - translation) @ rotation]
    points = np.concatenate(locations)
    rng = np.random.default_rng(config.seed + 104729)
    blocks = spatial_blocks(points, config.uncertainty_resamples, rng)
    return block_jackknife_covariance(jacobian, residual, np.repeat(blocks, 3))


def _initial_models(transform: np.ndarray, start: np.ndarray) -> tuple[_Revolute, _Prismatic, dict]:
    """Revolute and prismatic initial models from a normalised (4, 4) start->end rigid motion."""
    reference = start.mean(axis=0)
    screw = screw_from_transform(transform[:3, :3], transform[:3, 3], reference=reference)
    shift = apply_transform(transform, reference[None])[0] - reference
    shift_norm = float(np.linalg.norm(shift))
    if screw.axis_defined and abs(screw.angle) > 1e-4:
        revolute = _Revolute(screw.axis, screw.pivot, screw.angle, reference)
    else:  # (near) pure translation: mimic it by a small rotation about a far pivot
        _, _, vt = np.linalg.svd(start - reference, full_matrices=False)
        direction = shift / shift_norm if shift_norm > 1e-12 else vt[0]
        axis = np.cross(direction, vt[2])
        axis = unit(axis) if np.linalg.norm(axis) > 1e-6 else tangent_basis(direction)[:, 0]
        lever = 10.0
        revolute = _Revolute(axis, reference - lever * np.cross(direction, axis), shift_norm / lever, reference)
    prismatic = _Prismatic(shift / shift_norm if shift_norm > 1e-12 else np.array([1.0, 0.0, 0.0]), shift_norm)
    return revolute, prismatic, {"screw_angle_deg": float(np.degrees(screw.angle)), "screw_note": screw.note}


def _clean(points: np.ndarray, colors: np.ndarray | None, name: str, config: FitConfig,
           warnings: list[str]) -> tuple[np.ndarray, np.ndarray | None]:
    """Finite, cleaned points (and their colours) of one state; ValueError when too few."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"fit_joint: {name} must have shape (N, 3), got {points.shape}")
    if colors is not None:
        colors = np.asarray(colors, dtype=np.float64)
        if colors.shape != points.shape:
            raise ValueError(f"fit_joint: colours of {name} have shape {colors.shape}, expected {points.shape}")
    keep = np.all(np.isfinite(points), axis=1)
    finite = points[keep]
    if colors is not None:
        colors = colors[keep]
    if finite.shape[0] < MIN_POINTS:
        raise ValueError(f"fit_joint: {name} has {finite.shape[0]} finite points; at least {MIN_POINTS} needed")
    if config.clean:
        mask = clean_part_points(finite)
        if np.count_nonzero(mask) >= MIN_POINTS:
            if np.count_nonzero(mask) < 0.7 * finite.shape[0]:
                warnings.append(f"{name}: cleaning removed {finite.shape[0] - np.count_nonzero(mask)} "
                                f"of {finite.shape[0]} points")
            finite = finite[mask]
            colors = None if colors is None else colors[mask]
    if finite.shape[0] < config.few_points:
        warnings.append(f"{name}: only {finite.shape[0]} points; estimate is fragile")
    return finite, colors


def fit_joint(
    start_points: np.ndarray,
    end_points: np.ndarray,
    joint_type: str = "auto",
    initial_transform: np.ndarray | None = None,
    start_colors: np.ndarray | None = None,
    end_colors: np.ndarray | None = None,
    config: FitConfig | None = None,
) -> JointEstimate:
    """Fit the joint that moves a part from ``start_points`` to ``end_points``.

    start_points (N, 3), end_points (M, 3): float64 points of the same rigid part in the two
    states, in one frame (any units; partial views allowed; correspondence not needed).
    joint_type: "auto" | "revolute" | "prismatic". initial_transform: optional (4, 4) start -> end
    rigid guess in the same frame (e.g. from the labeler). Colours (N, 3)/(M, 3) in [0, 1] help
    the initial registration only.
    Returns a ``JointEstimate`` in the input frame and units: angle >= 0 radians (axis oriented
    accordingly) or distance >= 0; uncertainty 1-sigma including systematic effects (step 8 of
    the module docstring); warnings for unreliable estimates (step 9); diagnostics hold both
    models' BIC scores, Jacobian condition numbers, the parts of the uncertainty, the inlier
    fraction and timings-relevant sizes.
    Cost: O(N log N) cleaning + registration, then per matching iteration O(n^3) Hungarian on
    n = min(FitConfig.max_match_points, N, M) points per side (n = 1500: ~0.1 s) plus a small
    least-squares solve; about 1 s for 5k points per side in auto mode on one core. The
    uncertainty step adds FitConfig.half_samples Hungarian matchings on <= 600 points and short
    frozen-neighbour solves, O(R p^2) for the jackknife and O(N log N) for the inlier fraction:
    +5-15 % (``diagnostics["uncertainty_seconds"]``).
    Raises ValueError for fewer than 5 finite points per state, coincident points or a bad type.
    """
    config = config or FitConfig()
    if joint_type not in ("auto", "revolute", "prismatic"):
        raise ValueError(f"fit_joint: joint_type must be auto, revolute or prismatic, got {joint_type!r}")
    warnings: list[str] = []
    start, start_colors = _clean(start_points, start_colors, "start_points", config, warnings)
    end, end_colors = _clean(end_points, end_colors, "end_points", config, warnings)
    everything = np.concatenate([start, end])
    centre = everything.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((everything - centre) ** 2, axis=1))))
    if not np.isfinite(scale) or scale <= 1e-12 * max(1.0, float(np.abs(centre).max())):
        raise ValueError("fit_joint: all points coincide; no motion can be estimated")
    start_n, end_n = (start - centre) / scale, (end - centre) / scale
    rng = np.random.default_rng(config.seed)
    normalise = make_transform(np.eye(3) / scale, -centre / scale)
    denormalise = make_transform(np.eye(3) * scale, centre)
    diagnostics: dict = {"scale": scale, "n_start": len(start), "n_end": len(end), "config": asdict(config)}
    if initial_transform is not None:
        initial = normalise @ np.asarray(initial_transform, dtype=np.float64) @ denormalise
        diagnostics["initial"] = "given"
    else:
        registration = register_rigid(start_n, end_n, start_colors, end_colors, seed=config.seed)
        initial = registration.transform
        diagnostics["initial"] = f"register_rigid ({registration.diagnostics['chosen']})"
        diagnostics["registration_inlier_fraction"] = registration.inlier_fraction
    revolute_init, prismatic_init, screw_info = _initial_models(initial, start_n)
    start_normals, end_normals = estimate_normals(start_n), estimate_normals(end_n)
    diagnostics.update(screw_info)
    fits = {}
    if joint_type in ("auto", "revolute"):
        fits["revolute"] = _fit_model(revolute_init, start_n, end_n, start_normals, end_normals, config, rng)
    if joint_type in ("auto", "prismatic"):
        fits["prismatic"] = _fit_model(prismatic_init, start_n, end_n, start_normals, end_normals, config, rng)
    if joint_type == "auto":
        chosen = _choose(fits, config, diagnostics)
    else:
        chosen = joint_type
    for kind, fit in fits.items():
        diagnostics[f"{kind}_condition"] = fit["condition"]
    if "revolute" in fits:
        diagnostics["revolute_pivot_factor"] = _pivot_factor(fits["revolute"], start_n)
        diagnostics["revolute_angle_deg"] = float(np.degrees(abs(fits["revolute"]["x"][4])))
    began = time.perf_counter()
    scatter_rng = np.random.default_rng(config.seed + 3571)
    diagnostics["scatter_fraction"] = max(scatter_fraction(start_n, scatter_rng), scatter_fraction(end_n, scatter_rng))
    diagnostics["inlier_fraction"] = inlier_fraction(start_n, end_n, fits[chosen]["rotation"],
                                                     fits[chosen]["translation"])
    if config.half_samples >= 2:
        fits[chosen]["half_covariance"] = fits[chosen]["half_sample_covariance"](config.half_samples,
                                                                                 config.half_sample_points)
    diagnostics["uncertainty_seconds"] = (time.perf_counter() - began
                                          + sum(fit["resample_seconds"] for fit in fits.values()))
    return _estimate(chosen, fits[chosen], start_n, scale, centre, config, warnings, diagnostics)


def _pivot_factor(fit: dict, start_n: np.ndarray) -> float:
    """Distance of a revolute fit's axis line from the part centre, in part radii (RMS)."""
    axis, pivot, _ = fit["model"].unpack(fit["x"])
    reference = start_n.mean(axis=0)
    offset = pivot - reference
    radius = float(np.sqrt(np.mean(np.sum((start_n - reference) ** 2, axis=1))))
    return float(np.linalg.norm(offset - (offset @ axis) * axis)) / max(radius, 1e-12)


def _choose(fits: dict, config: FitConfig, diagnostics: dict) -> str:
    revolute, prismatic = fits["revolute"], fits["prismatic"]
    tau = min(revolute["tau"], prismatic["tau"])
    rss = {kind: float(np.sum(np.minimum(fit["chamfer"], tau) ** 2)) for kind, fit in fits.items()}
    count = revolute["chamfer"].size / config.bic_correlation_factor
    angle = float(revolute["x"][4])
    angle_sigma = float(np.sqrt(max(revolute["covariance"][4, 4], 0.0)))
    decision = select_joint_type(rss["revolute"], rss["prismatic"], count, angle, angle_sigma,
                                 z=config.angle_z, min_angle=np.radians(config.min_angle_deg))
    diagnostics.update({"bic_revolute": decision.bic_revolute, "bic_prismatic": decision.bic_prismatic,
                        "type_reason": decision.reason, "angle_significant": decision.angle_significant,
                        "revolute_angle_z": abs(angle) / angle_sigma if angle_sigma > 0 else float("inf")})
    return decision.joint_type


def _reliability_warnings(kind: str, uncertainty: dict, angle: float | None, distance_n: float | None, scale: float,
                          config: FitConfig, warnings: list[str], diagnostics: dict) -> None:
    """Append the warnings of an estimate that is unreliable whatever its stated sigma: outliers
    (many points scatter off any surface and few land on the other state), a prismatic answer to a motion
    that turns by more than ``small_angle_deg`` about a far pivot (small angle x large radius ~
    translation), a stated uncertainty large against the estimate."""
    scattered, inliers = diagnostics.get("scatter_fraction", 0.0), diagnostics.get("inlier_fraction", 1.0)
    if scattered > MAX_SCATTER_FRACTION and inliers < MIN_INLIER_FRACTION:
        warnings.append(f"many outliers: {100 * scattered:.0f} % of the points scatter off any surface "
                        f"(> {100 * MAX_SCATTER_FRACTION:.0f} %) and only {100 * inliers:.0f} % land on the other "
                        f"state under the fitted motion (< {100 * MIN_INLIER_FRACTION:.0f} %); estimate unreliable")
    turn = abs(float(diagnostics.get("screw_angle_deg", 0.0)))
    pivot_factor = diagnostics.get("revolute_pivot_factor", 0.0)
    if kind == "prismatic" and turn > config.small_angle_deg and pivot_factor > config.far_pivot_factor:
        warnings.append(f"the rigid motion turns by {turn:.3g} deg, which a rotation about a pivot "
                        f"{pivot_factor:.3g} x the part radius away explains as well as a slide: "
                        "revolute vs prismatic ambiguous")
    large = []
    if uncertainty["axis_deg"] > MAX_AXIS_SIGMA_DEG:
        large.append(f"axis +-{uncertainty['axis_deg']:.3g} deg > {MAX_AXIS_SIGMA_DEG:g} deg")
    if angle is not None and uncertainty["angle"] > MAX_RELATIVE_SIGMA * abs(angle):
        large.append(f"angle +-{np.degrees(uncertainty['angle']):.3g} deg of {np.degrees(angle):.3g} deg")
    if distance_n is not None and uncertainty["distance"] > MAX_RELATIVE_SIGMA * abs(distance_n) * scale:
        large.append(f"distance +-{uncertainty['distance']:.3g} of {abs(distance_n) * scale:.3g}")
    if large:
        warnings.append("uncertainty large relative to the estimate: " + ", ".join(large))


def _floor_covariance(kind: str, residual: float, part_radius: float) -> np.ndarray:
    """Diagonal covariance of the calibrated systematic floor (normalised units): axis tangents
    and angle (rad) UNCERTAINTY_FLOOR x residual / part radius, pivot and distance
    UNCERTAINTY_FLOOR x residual. Residual = RMS pair residual of the fit."""
    if not np.isfinite(residual):
        residual = 0.0
    angular = (UNCERTAINTY_FLOOR * residual / max(part_radius, 1e-12)) ** 2
    linear = (UNCERTAINTY_FLOOR * residual) ** 2
    if kind == "revolute":  # axis (2) split evenly, pivot (2) split evenly, angle
        return np.diag([angular / 2, angular / 2, linear / 2, linear / 2, angular])
    return np.diag([angular / 2, angular / 2, linear])


def _axis_sigma_deg(covariance: np.ndarray) -> float:
    """1-sigma axis direction error (deg) from the two tangent variances."""
    return float(np.degrees(np.sqrt(max(covariance[0, 0] + covariance[1, 1], 0.0))))


def _revolute_sigma(covariance: np.ndarray, scale: float) -> dict[str, float]:
    return {"axis_deg": _axis_sigma_deg(covariance),
            "origin": float(np.sqrt(max(covariance[2, 2] + covariance[3, 3], 0.0))) * scale,
            "angle": float(np.sqrt(max(covariance[4, 4], 0.0)))}


def _prismatic_sigma(covariance: np.ndarray, scale: float, origin_sigma: float) -> dict[str, float]:
    return {"axis_deg": _axis_sigma_deg(covariance), "origin": float(origin_sigma),
            "distance": float(np.sqrt(max(covariance[2, 2], 0.0))) * scale}


def _estimate(kind: str, fit: dict, start_n: np.ndarray, scale: float, centre: np.ndarray,
              config: FitConfig, warnings: list[str], diagnostics: dict) -> JointEstimate:
    """Convert a normalised fit into a JointEstimate in input units, with warnings."""
    model, x = fit["model"], fit["x"]
    reference = start_n.mean(axis=0)
    part_radius = float(np.sqrt(np.mean(np.sum((start_n - reference) ** 2, axis=1))))
    residual = float(np.sqrt(np.mean(fit["pair_residual"] ** 2))) if fit["pairs"] else float("inf")
    jacobian_covariance = fit["covariance"]
    half_covariance = fit.get("half_covariance", np.zeros_like(jacobian_covariance))
    floor_covariance = _floor_covariance(kind, residual, part_radius)
    covariance = (jacobian_covariance + fit["resample_covariance"] + half_covariance
                  + (floor_covariance if config.uncertainty_floor else 0.0))
    eigen = np.sort(np.linalg.eigvalsh(np.cov((start_n - reference).T)))[::-1]
    if eigen[1] < 1e-4 * eigen[0]:
        warnings.append("part is nearly collinear (thin rod): rotation about its own line is unobservable")
    elif eigen[2] < 1e-4 * eigen[0]:
        warnings.append("part is nearly planar: axis estimate relies on the in-plane shape")
    if fit["condition"] > ILL_CONDITIONED:
        warnings.append(f"ill-conditioned fit (Jacobian condition number {fit['condition']:.3g})")
    if kind == "revolute":
        axis, pivot, angle = model.unpack(x)
        pivot = pivot + ((reference - pivot) @ axis) * axis
        if angle < 0:
            axis, angle = -axis, -angle
        transform_n = transform_from_revolute(axis, pivot, angle)
        slide_n = float(np.mean((fit["pair_end"] - apply_transform(transform_n, fit["pair_start"])) @ axis))
        uncertainty = _revolute_sigma(covariance, scale)
        sigma_parts = {"uncertainty_jacobian": _revolute_sigma(jacobian_covariance, scale),
                       "uncertainty_resample": _revolute_sigma(fit["resample_covariance"], scale),
                       "uncertainty_half": _revolute_sigma(half_covariance, scale),
                       "uncertainty_floor": _revolute_sigma(floor_covariance, scale)}
        if np.degrees(angle) < config.small_angle_deg:
            warnings.append(f"rotation of {np.degrees(angle):.3g} deg < {config.small_angle_deg} deg: axis poorly defined")
        pivot_distance = float(np.linalg.norm(pivot - reference))
        if pivot_distance > config.far_pivot_factor * part_radius:
            warnings.append(f"pivot is {pivot_distance / part_radius:.3g} x the part radius away: "
                            "revolute vs prismatic ambiguous")
        if abs(slide_n) > max(3.0 * residual / np.sqrt(max(fit["pairs"], 1)), 0.02 * part_radius):
            warnings.append(f"motion slides {slide_n * scale:.3g} along the axis: not a pure rotation")
        origin = pivot * scale + centre
        estimate_angle, estimate_distance, slide = float(angle), None, slide_n * scale
    else:
        axis, distance = model.unpack(x)
        if distance < 0:
            axis, distance = -axis, -distance
        transform_n = transform_from_prismatic(axis, distance)
        origin_sigma = residual / np.sqrt(max(fit["pairs"], 1)) * scale
        uncertainty = _prismatic_sigma(covariance, scale, origin_sigma)
        sigma_parts = {"uncertainty_jacobian": _prismatic_sigma(jacobian_covariance, scale, origin_sigma),
                       "uncertainty_resample": _prismatic_sigma(fit["resample_covariance"], scale, 0.0),
                       "uncertainty_half": _prismatic_sigma(half_covariance, scale, 0.0),
                       "uncertainty_floor": _prismatic_sigma(floor_covariance, scale, 0.0)}
        jacobian_distance_sigma = sigma_parts["uncertainty_jacobian"]["distance"] / scale
        if distance < 3.0 * max(jacobian_distance_sigma, residual / np.sqrt(max(fit["pairs"], 1))):
            warnings.append(f"slide of {distance * scale:.3g} is tiny compared with the noise: axis poorly defined")
        origin = reference * scale + centre
        estimate_angle, estimate_distance, slide = None, float(distance * scale), float(distance * scale)
    _reliability_warnings(kind, uncertainty, estimate_angle, None if estimate_distance is None else distance,
                          scale, config, warnings, diagnostics)
    rotation = transform_n[:3, :3]
    transform = make_transform(rotation, scale * transform_n[:3, 3] + centre - rotation @ centre)
    relative = residual / max(part_radius, 1e-12)
    confidence = float(np.clip(fit["match_fraction"], 0, 1) / (1.0 + (relative / 0.1) ** 2))
    if any(word in w for w in warnings for word in ("poorly defined", "ambiguous", "ill-conditioned", "unreliable",
                                                     "uncertainty large")):
        confidence *= 0.5
    diagnostics.update({"pairs": fit["pairs"], "match_fraction": fit["match_fraction"],
                        "condition": fit["condition"], "part_radius": part_radius * scale,
                        "resample_blocks": fit["resample_blocks"], **sigma_parts})
    return JointEstimate(type=kind, axis=axis.copy(), origin=origin, angle=estimate_angle, distance=estimate_distance,
                         transform=transform, uncertainty=uncertainty, residual=residual * scale,
                         confidence=float(np.clip(confidence, 0.0, 1.0)), slide=slide, warnings=warnings,
                         diagnostics=diagnostics)
