"""The fit of one joint model to one part: one-to-one matching alternated with parameter updates,
then the robust solve of ``L_align + alpha * L_CD`` and its covariance -> ``ModelFit``.

All arrays are normalised float64 (``part.PartData``). Stages of ``fit_model`` and their cost
(n = matching sample per side, ``FitConfig.max_match_points``; c = Chamfer sample,
``max_chamfer_points``; p <= 5 parameters; measured CPU at n = c = 1500 in brackets):

1. ``alternate``: one-to-one matching (``one_to_one_pairs``: sparse assignment, ~O(E sqrt(n)) for
   E ~ 3-50 n pairs within reach [2-8 ms, up to ~70 ms far from convergence]) alternated with a
   pairs-only robust solve (``robust_solve``, O(n p^2) per evaluation [~3 ms per solve]); stops
   when the motion moves the part by less than the stop distance (``stop_distance``: a fraction
   of the displacement the stated uncertainty allows) or after ``match_iterations``; the last
   assignment is kept when it converged (it cannot change any more);
2. the final solve of the true objective with the Chamfer term (``Problem.solve_chamfer``):
   neighbours re-queried at every evaluated point (O(c log c) [~1 ms]), frozen inside the finite
   differences; Aitken extrapolation of the ICP-like linear convergence; stops when the
   estimated remaining motion (``RemainingBelow``) is below the stop distance [10-25
   evaluations];
3. ``covariance``: central-difference Jacobian with the neighbours frozen, O((n + c) p^2) [~2 ms].

Why sparse matching: the costs are squared distances clipped at tau^2, so only pairs closer than
tau carry information; the dense O(n^2) cost matrix and O(n^3) assignment of the same problem
(``scipy.optimize.linear_sum_assignment``) cost ~0.1 s CPU at n = 1500 against 2-8 ms for the
sparse one (same optimum up to the integer cost quantum; ``tests/test_fit_optimise.py``). Why a
hand-written solver: for p <= 5 parameters ``scipy.optimize.least_squares``'s trust-region
bookkeeping cost more than the residuals (~5x the time of ``robust_solve`` here).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import min_weight_full_bipartite_matching
from scipy.spatial import cKDTree

from sparseart.joints.config import UNCERTAINTY_FLOOR, FitConfig
from sparseart.joints.models import Model
from sparseart.joints.part import MIN_POINTS, PartData, Sample

QUANTUM_BITS = 20  # matching costs are integers in units of tau^2 / 2^QUANTUM_BITS


def one_to_one_pairs(moved: np.ndarray, sample: Sample, tau_factor: float = 3.0,
                     moved_normals: np.ndarray | None = None, normal_cos: float = 0.0
                     ) -> tuple[np.ndarray, np.ndarray, float]:
    """One-to-one pairs (rows into ``moved``, cols into ``sample.end``) and the clip distance tau.

    moved (n, 3): the sample's start points under the current motion; moved_normals (n, 3) their
    rotated normals. Minimises sum(min(|a - b|^2, tau^2)) over assignments (tau = tau_factor x the
    median nearest distance, kept within [sample.floor, sample.ceiling]); pairs at the clip --
    farther than tau or with normals more than arccos(normal_cos) apart -- are dropped, so a
    point whose partner is hidden stays unmatched. Solved as a minimum-weight full matching of
    the sparse graph of the E pairs within tau, padded with one "unmatched" node per point
    (cost tau^2) and a mirrored copy of the E edges so every point may stay unmatched; a full
    matching of that graph is an assignment of the clipped problem with the same total cost.
    O(n log m) neighbour queries + O(E) graph + the sparse assignment (LAPJVsp, ~O(E sqrt(n))
    in practice; E ~ 10-60 n here).
    """
    end, end_tree = sample.end, sample.end_tree
    nearest, _ = end_tree.query(moved)
    tau = min(max(tau_factor * float(np.median(nearest)), sample.floor), max(sample.ceiling, sample.floor))
    tau2 = tau * tau
    n, m = len(moved), len(end)
    found = cKDTree(moved).sparse_distance_matrix(end_tree, tau, output_type="ndarray")
    rows, cols, cost = found["i"].astype(np.int64), found["j"].astype(np.int64), found["v"] ** 2
    keep = cost < tau2
    if moved_normals is not None:
        keep &= np.abs(np.einsum("ij,ij->i", moved_normals[rows], sample.end_normals[cols])) >= normal_cos
    rows, cols, cost = rows[keep], cols[keep], cost[keep]
    if rows.size == 0:
        return rows, cols, tau
    # Nodes: left = n points + m "end unmatched" dummies, right = m points + n "start unmatched"
    # dummies. Every full matching has n + m edges, so the constant tau^2 added to every edge
    # (zero-cost edges could be read as absent) does not change the optimum. Costs are integers
    # (units of tau^2 / 2^QUANTUM_BITS): with float costs of near-equal size LAPJVsp can cycle
    # forever (seen on a wire rack: 1.6k edges, weights 1e-3 apart by 1e-9); exact integer sums
    # cannot. The rounding moves a total by at most n tau^2 2^-QUANTUM_BITS.
    left = np.concatenate([rows, np.arange(n), n + cols, n + np.arange(m)])
    right = np.concatenate([cols, m + np.arange(n), m + rows, np.arange(m)])
    units = float(2 ** QUANTUM_BITS)
    weight = np.concatenate([np.round(cost / tau2 * units), np.full(n, units), np.zeros(rows.size), np.zeros(m)]) + units
    graph = csr_matrix((weight, (left, right)), shape=(n + m, n + m))
    _, partner = min_weight_full_bipartite_matching(graph)
    partner = partner[:n]
    matched = np.flatnonzero(partner < m)
    return matched, partner[matched], tau


def pair_weights(kind: str, start: np.ndarray, end: np.ndarray, beta: float) -> np.ndarray:
    """Distance-proportional weights ``w = K (d~ + beta) / sum(d~ + beta)`` (revolute: points far
    from the axis pin it down) or ones (prismatic), mean 1, shape (K,). O(K)."""
    count = start.shape[0]
    if kind != "revolute" or count == 0:
        return np.ones(count)
    displacement = np.linalg.norm(end - start, axis=1)
    span = displacement.max() - displacement.min()
    normalised = (displacement - displacement.min()) / span if span > 1e-12 else np.zeros(count)
    return count * (normalised + beta) / np.sum(normalised + beta)


def confidence_pair_weights(weights: np.ndarray, sample: Sample, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``weights`` (K,) of the pairs (rows into ``sample.start``, cols into ``sample.end``) times
    sqrt(c_start c_end), the geometric mean of the two points' depth confidences, rescaled to the
    mean of ``weights`` (so the balance with the Chamfer term is kept): a pair with a smeared or
    warped point counts less. ``weights`` itself (the same array) when the sample carries no
    confidences, so a fit without them is unchanged to the bit. O(K)."""
    if sample.start_confidence is None or sample.end_confidence is None or len(rows) == 0:
        return weights
    scaled = weights * np.sqrt(sample.start_confidence[rows] * sample.end_confidence[cols])
    total = float(np.sum(scaled))
    if not total > 1e-12 * max(float(np.sum(weights)), 1e-300):
        return weights   # every pair has confidence 0: nothing to prefer
    return scaled * (float(np.sum(weights)) / total)


class Problem:
    """Residual vector of ``L_align + alpha L_CD`` for one model: weighted pair residuals and the
    symmetric Chamfer residuals of a fixed Chamfer sample, whose nearest neighbours are frozen
    per solve (``matches``) so every residual evaluation is O((K + c) p) matrix algebra."""

    def __init__(self, model: Model, pair_start: np.ndarray, pair_end: np.ndarray, weights: np.ndarray,
                 chamfer: Sample | None = None, alpha: float = 0.5, loss: str = "soft_l1",
                 gate_normals: bool = False, normal_cos: float = 0.0):
        self.model, self.loss, self.normal_cos, self.gate_normals = model, loss, normal_cos, gate_normals
        self.alpha = alpha
        self.pair_start, self.pair_end = pair_start, pair_end
        self.sqrt_weights = np.sqrt(weights)[:, None]
        self.chamfer = chamfer if chamfer is not None and alpha > 0 else None
        if self.chamfer is not None:
            self.start_tree = cKDTree(chamfer.start)
            count = max(len(pair_start), 1)
            self.start_factor = np.sqrt(alpha * count / len(chamfer.start))
            self.end_factor = np.sqrt(alpha * count / len(chamfer.end))

    @property
    def align_rows(self) -> int:
        return 3 * len(self.pair_start)

    def residuals(self, x: np.ndarray, frozen: tuple | None = None) -> np.ndarray:
        """(3K [+ 3 c_s + 3 c_e],) residual components at ``x``; ``frozen`` from ``matches``
        (required with a Chamfer term). O((K + c) p)."""
        rotation, translation = self.model.motion(x)
        align = self.sqrt_weights * (self.pair_start @ rotation.T + translation - self.pair_end)
        if self.chamfer is None:
            return align.ravel()
        chamfer = self.chamfer
        forward, backward, forward_ok, backward_ok = frozen
        moved = chamfer.start @ rotation.T + translation
        back = (chamfer.end - translation) @ rotation
        forward_residual = self.start_factor * (moved - chamfer.end[forward]) * forward_ok[:, None]
        backward_residual = self.end_factor * (back - chamfer.start[backward]) * backward_ok[:, None]
        return np.concatenate([align.ravel(), forward_residual.ravel(), backward_residual.ravel()])

    def matches(self, x: np.ndarray) -> tuple | None:
        """Chamfer nearest neighbours at ``x`` and the normal-agreement masks (hidden partners
        = 0); None without a Chamfer term. O(c log c)."""
        if self.chamfer is None:
            return None
        chamfer = self.chamfer
        rotation, translation = self.model.motion(x)
        _, forward = chamfer.end_tree.query(chamfer.start @ rotation.T + translation)
        _, backward = self.start_tree.query((chamfer.end - translation) @ rotation)
        forward_ok = np.ones(len(forward))
        backward_ok = np.ones(len(backward))
        if self.gate_normals:
            turned = chamfer.start_normals @ rotation.T
            forward_ok = np.abs(np.einsum("ij,ij->i", turned, chamfer.end_normals[forward])) >= self.normal_cos
            backward_ok = np.abs(np.einsum("ij,ij->i", turned[backward], chamfer.end_normals)) >= self.normal_cos
        forward_ok, backward_ok = forward_ok.astype(float), backward_ok.astype(float)
        if chamfer.start_confidence is not None and chamfer.end_confidence is not None:
            # Depth confidences (``FitConfig.confidence_weights``): residual factor sqrt(w) with
            # w = sqrt(c_a c_b) / mean, the pair weights' rule for the nearest neighbours. Without
            # it the unweighted Chamfer term keeps pulling towards low-confidence points (a door
            # with a third of its points warped 4 cm at confidence 0.01: pair weights alone took
            # the axis error from 4.3 to 3.6 deg, with the Chamfer term weighted too to 2.0-2.9).
            forward_w = np.sqrt(chamfer.start_confidence * chamfer.end_confidence[forward])
            backward_w = np.sqrt(chamfer.end_confidence * chamfer.start_confidence[backward])
            forward_ok *= np.sqrt(forward_w / max(float(forward_w.mean()), 1e-12))
            backward_ok *= np.sqrt(backward_w / max(float(backward_w.mean()), 1e-12))
        return forward, backward, forward_ok, backward_ok

    def solve(self, x0: np.ndarray, f_scale: float, max_nfev: int, frozen: tuple | None = None) -> Solution:
        """Robust (``loss``) least squares from ``x0`` with the Chamfer neighbours ``frozen``
        (``matches(x0)`` when None): ``robust_solve``, O(max_nfev (K + c) p^2)."""
        if self.chamfer is not None and frozen is None:
            frozen = self.matches(x0)
        return robust_solve(lambda x: self.residuals(x, frozen), x0, f_scale, self.loss, max_nfev)

    def solve_chamfer(self, x0: np.ndarray, f_scale: float, max_nfev: int, small_step=None) -> Solution:
        """Robust least squares of the true objective: the Chamfer neighbours are re-queried at
        every evaluated x and frozen only inside the finite differences (a neighbour switch
        within a step would fake a huge derivative). O(max_nfev (c log c + (K + c) p^2))."""
        last = {}  # the neighbours of the last evaluated x: the linearisation at an accepted x reuses them

        def function(x):
            last["x"], last["frozen"] = x, self.matches(x)
            return self.residuals(x, last["frozen"])

        def linearise(x):
            frozen = last["frozen"] if last.get("x") is x else self.matches(x)
            return lambda y: self.residuals(y, frozen)

        return robust_solve(function, x0, f_scale, self.loss, max_nfev, linearise=linearise, small_step=small_step,
                            extrapolate=True)


_RHO = {"linear": lambda z: z, "soft_l1": lambda z: 2.0 * (np.sqrt(1.0 + z) - 1.0), "cauchy": np.log1p,
        "arctan": np.arctan, "huber": lambda z: np.where(z <= 1.0, z, 2.0 * np.sqrt(np.maximum(z, 1.0)) - 1.0)}
_RHO_PRIME = {"linear": np.ones_like, "soft_l1": lambda z: 1.0 / np.sqrt(1.0 + z), "cauchy": lambda z: 1.0 / (1.0 + z),
              "arctan": lambda z: 1.0 / (1.0 + z * z),
              "huber": lambda z: np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1.0)))}


@dataclass
class Solution:
    """Outcome of ``robust_solve``: x (p,), cost (robust, f_scale^2 units), nfev residual evaluations."""

    x: np.ndarray
    cost: float
    nfev: int


def robust_solve(function, x0: np.ndarray, f_scale: float, loss: str = "soft_l1", max_nfev: int = 50,
                 rtol: float = 1e-10, linearise=None, small_step=None, extrapolate: bool = False) -> Solution:
    """Minimise ``sum(rho((r_i / f_scale)^2))`` over x for residuals r = function(x) (R,):
    Levenberg-Marquardt on the IRLS normal equations (weights rho'), forward-difference
    Jacobian, the loss applied per residual component (as ``scipy.optimize.least_squares``
    does, which this replaces: for p <= 5 parameters its trust-region bookkeeping cost more than
    the residuals). ``linearise(x)``: a smooth stand-in for ``function`` near x, equal to it at x,
    for the finite differences (the Chamfer term with its neighbours frozen at x); default
    ``function``. Stops when an accepted step lowers the cost by less than ``rtol`` of it, when
    ``small_step(x_before, x_after)`` says the step no longer matters, when no step lowers the
    cost, or after ``max_nfev`` evaluations (finite differences included). ``extrapolate``: when
    two accepted steps point the same way and shrink by a ratio r (the linear convergence of a
    frozen linearisation, ICP-like), also try the rest of their geometric series, r / (1 - r)
    times the last step (Aitken), kept when it lowers the cost.
    O(iterations x (p + 1) x (residual evaluation + R p))."""
    rho, rho_prime = _RHO[loss], _RHO_PRIME[loss]
    scale2 = f_scale * f_scale
    x = np.array(x0, dtype=np.float64)
    residual = function(x)
    cost = float(np.sum(rho(residual * residual / scale2)))
    nfev, damping, p = 1, 1e-3, x.size
    previous_delta = None
    while nfev + p + 1 <= max_nfev:
        local = function if linearise is None else linearise(x)
        columns = np.empty((residual.size, p))
        for index in range(p):
            step = 1.4901161193847656e-08 * max(1.0, abs(x[index]))
            shifted = x.copy()
            shifted[index] += step
            columns[:, index] = (local(shifted) - residual) / step
        nfev += p
        weights = rho_prime(residual * residual / scale2)
        weighted = columns * weights[:, None]
        normal = weighted.T @ columns
        gradient = weighted.T @ residual
        diagonal = np.maximum(np.diag(normal), 1e-12 * max(float(np.max(np.diag(normal))), 1e-300))
        accepted = False
        while nfev < max_nfev:
            try:
                delta = -np.linalg.solve(normal + damping * np.diag(diagonal), gradient)
            except np.linalg.LinAlgError:
                damping *= 10.0
                continue
            trial = x + delta
            trial_residual = function(trial)
            nfev += 1
            trial_cost = float(np.sum(rho(trial_residual * trial_residual / scale2)))
            if np.isfinite(trial_cost) and trial_cost < cost:
                accepted = True
                decrease = cost - trial_cost
                tiny = small_step is not None and small_step(x, trial)
                x, residual, cost = trial, trial_residual, trial_cost
                damping = max(damping / 3.0, 1e-9)
                if extrapolate and not tiny and previous_delta is not None and nfev < max_nfev:
                    size, previous_size = np.linalg.norm(delta), np.linalg.norm(previous_delta)
                    rate = size / max(previous_size, 1e-300)
                    if rate < 0.95 and delta @ previous_delta > 0.9 * size * previous_size:
                        jump = x + min(rate / (1.0 - rate), 10.0) * delta
                        jump_residual = function(jump)
                        nfev += 1
                        jump_cost = float(np.sum(rho(jump_residual * jump_residual / scale2)))
                        if np.isfinite(jump_cost) and jump_cost < cost:
                            decrease += cost - jump_cost
                            x, residual, cost = jump, jump_residual, jump_cost
                            delta = None
                previous_delta = delta
                break
            damping *= 4.0
            if damping > 1e8:
                break
        if not accepted or tiny or decrease <= rtol * max(cost, 1e-300):
            break
    return Solution(x, cost, nfev)


def motion_change(model: Model, x_a: np.ndarray, x_b: np.ndarray, points: np.ndarray) -> float:
    """Largest displacement between the motions at ``x_a`` and ``x_b`` over ``points`` (n, 3); O(n)."""
    rotation_a, translation_a = model.motion(x_a)
    rotation_b, translation_b = model.motion(x_b)
    return float(np.max(np.linalg.norm(points @ (rotation_a - rotation_b).T + (translation_a - translation_b),
                                       axis=1)))


def stop_distance(rms_residual: float, spacing: float, config: FitConfig) -> float:
    """Motion change below which iterating cannot move the answer by a stated sigma: stop_fraction
    x the displacement of the calibrated floor sigma (``UNCERTAINTY_FLOOR`` x the RMS pair
    residual), at least ``min_stop_spacing`` x the sample's point spacing."""
    return max(config.stop_fraction * UNCERTAINTY_FLOOR * rms_residual, config.min_stop_spacing * spacing, 1e-12)


class RemainingBelow:
    """Early stop of a slowly converging iteration: True once the distance still to go, estimated
    from the last two steps as a geometric series (``step x r / (1 - r)``, r = step / previous
    step), falls below ``stop``; a first step is judged alone only when under ``stop / 10``.
    Steps are motion changes (``motion_change``). O(1) per call."""

    def __init__(self, stop: float):
        self.stop, self.previous = stop, None

    def __call__(self, step: float) -> bool:
        previous, self.previous = self.previous, step
        if step < 0.1 * self.stop:
            return True
        if previous is None or step >= previous:
            return False
        rate = step / previous
        return step * rate / (1.0 - rate) < self.stop


def _pairs(model: Model, x: np.ndarray, sample: Sample, config: FitConfig, normal_cos: float):
    rotation, translation = model.motion(x)
    moved = sample.start @ rotation.T + translation
    rows, cols, tau = one_to_one_pairs(moved, sample, config.pair_tau_factor, sample.start_normals @ rotation.T,
                                       normal_cos)
    if len(rows) < MIN_POINTS:
        rows = cols = np.arange(sample.size)
    return moved, rows, cols, tau


@dataclass
class Alternation:
    """Outcome of ``alternate``: the recentred model, the iteration count, whether it converged
    (stopped on a small change), and its last one-to-one pairs (rows / cols into the sample) and
    clip distance tau."""

    model: Model
    iterations: int
    converged: bool
    rows: np.ndarray
    cols: np.ndarray
    tau: float


def alternate(model: Model, sample: Sample, config: FitConfig) -> Alternation:
    """Matching / update alternation on one sample from ``model.x0``: match one-to-one at the
    current motion, solve the pairs-only robust problem (<= 30 evaluations), recentre; stop after
    ``match_iterations`` or when the motion changed by less than ``stop_distance`` (then the
    assignment cannot change any more and its pairs hold at the answer too).
    O(iterations x (matching + 30 n p))."""
    normal_cos = float(np.cos(np.radians(config.normal_gate_deg)))
    iterations, converged = 0, False
    rows = cols = np.zeros(0, dtype=np.int64)
    tau = 0.0
    for iterations in range(1, config.match_iterations + 1):
        x = model.x0
        _, rows, cols, tau = _pairs(model, x, sample, config, normal_cos)
        pair_start, pair_end = sample.start[rows], sample.end[cols]
        weights = confidence_pair_weights(pair_weights(model.kind, pair_start, pair_end, config.beta), sample, rows, cols)
        problem = Problem(model, pair_start, pair_end, weights, loss=config.robust_loss)
        result = problem.solve(x, f_scale=max(tau / 3.0, 1e-9), max_nfev=30)
        change = motion_change(model, x, result.x, sample.start)
        rotation, translation = model.motion(result.x)
        rms = float(np.sqrt(np.mean(np.sum((pair_start @ rotation.T + translation - pair_end) ** 2, axis=1))))
        model = model.recentred(result.x)
        if change < stop_distance(rms, sample.spacing, config):
            converged = True
            break
    return Alternation(model, iterations, converged, rows, cols, tau)


@dataclass
class ModelFit:
    """One joint model fitted to one part (normalised units) -- what type selection, the stated
    uncertainty and the ``JointEstimate`` read.

    model, x: the model and its optimum (``model.motion(x)`` = rotation, translation).
    problem, frozen: the final residual problem and its Chamfer neighbours at ``x`` (reused by the
    jackknife and the half-samples, no re-matching). covariance: Jacobian covariance (p, p),
    inflated by ``correlation_factor`` (drives the type test); condition: its condition number;
    jacobian / residual: robust-weighted rows at ``x`` (R, p) / (R,). f_scale, tau: robust scale
    and matching clip. pair_start / pair_end (K, 3): the matched pairs; pair_residual (K,): their
    distances under the fit. chamfer_distances (c_s + c_e,): point-to-plane distances of the
    Chamfer sample (type selection). match_fraction: pairs / sample size. iterations:
    {"alternations", "chamfer_evaluations"}.
    """

    model: Model
    x: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    problem: Problem
    frozen: tuple | None
    covariance: np.ndarray
    condition: float
    jacobian: np.ndarray
    residual: np.ndarray
    f_scale: float
    tau: float
    pair_start: np.ndarray
    pair_end: np.ndarray
    pair_residual: np.ndarray
    chamfer_distances: np.ndarray
    match_fraction: float
    iterations: dict = field(default_factory=dict)

    @property
    def kind(self) -> str:
        return self.model.kind

    @property
    def pairs(self) -> int:
        return len(self.pair_start)

    @property
    def rms_residual(self) -> float:
        """RMS pair residual (normalised units); inf without pairs."""
        return float(np.sqrt(np.mean(self.pair_residual ** 2))) if self.pairs else float("inf")


def fit_model(model: Model, part: PartData, config: FitConfig) -> ModelFit:
    """Fit ``model`` (started at ``model.x0``) to ``part``: stages 1-3 of the module docstring.
    O(iterations x (matching + 30 n p^2) + evaluations x (c log c + (n + c) p^2)); ~25-60 ms CPU
    at n = c = 1500."""
    sample, chamfer = part.match, part.chamfer
    alternation = alternate(model, sample, config)
    model, iterations = alternation.model, {"alternations": alternation.iterations}
    normal_cos = float(np.cos(np.radians(config.normal_gate_deg)))
    x = model.x0
    if alternation.converged:
        rotation, translation = model.motion(x)
        moved, rows, cols, tau = (sample.start @ rotation.T + translation, alternation.rows, alternation.cols,
                                  alternation.tau)
    else:
        moved, rows, cols, tau = _pairs(model, x, sample, config, normal_cos)
    pair_start, pair_end = sample.start[rows], sample.end[cols]
    weights = confidence_pair_weights(pair_weights(model.kind, pair_start, pair_end, config.beta), sample, rows, cols)
    problem = Problem(model, pair_start, pair_end, weights,
                      chamfer, config.chamfer_weight, config.robust_loss, config.normal_gate_deg < 90, normal_cos)
    pair_distance = np.linalg.norm(moved[rows] - pair_end, axis=1)
    f_scale = max(1.4826 * float(np.median(pair_distance)) / np.sqrt(3.0), tau / 6.0, 1e-9)
    stop = stop_distance(float(np.sqrt(np.mean(pair_distance ** 2))) if len(pair_distance) else 0.0,
                         sample.spacing, config)
    remaining_below = RemainingBelow(stop)
    result = problem.solve_chamfer(x, f_scale, config.chamfer_evaluations,
                                   small_step=lambda a, b: remaining_below(motion_change(model, a, b, chamfer.start)))
    x = result.x
    iterations["chamfer_evaluations"] = result.nfev
    frozen = problem.matches(x)
    covariance_matrix, condition, jacobian, residual = covariance(problem, x, f_scale, config.correlation_factor,
                                                                  frozen)
    rotation, translation = model.motion(x)
    pair_residual = np.linalg.norm(pair_start @ rotation.T + translation - pair_end, axis=1)
    return ModelFit(model=model, x=x, rotation=rotation, translation=translation, problem=problem, frozen=frozen,
                    covariance=covariance_matrix, condition=condition, jacobian=jacobian, residual=residual,
                    f_scale=f_scale, tau=tau, pair_start=pair_start, pair_end=pair_end, pair_residual=pair_residual,
                    chamfer_distances=chamfer_plane_distances(chamfer, rotation, translation),
                    match_fraction=len(rows) / max(sample.size, 1), iterations=iterations)


def chamfer_plane_distances(chamfer: Sample, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Symmetric point-to-plane Chamfer distances (c_s + c_e,) of the Chamfer sample under a
    motion: free of the sampling-spacing floor of point-to-point distances, so small real
    rotations stand out against a translation (type selection). O(c log c)."""
    moved = chamfer.start @ rotation.T + translation
    _, forward_index = chamfer.end_tree.query(moved)
    _, backward_index = cKDTree(moved).query(chamfer.end)
    forward = np.abs(np.einsum("ij,ij->i", moved - chamfer.end[forward_index], chamfer.end_normals[forward_index]))
    backward = np.abs(np.einsum("ij,ij->i", chamfer.end - moved[backward_index],
                                chamfer.start_normals[backward_index] @ rotation.T))
    return np.concatenate([forward, backward])


def covariance(problem: Problem, x: np.ndarray, f_scale: float, factor: float,
               frozen: tuple | None = None) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """cov = factor * s^2 (J_w^T J_w)^+ with the robust loss's IRLS weights; returns (cov,
    condition number, J_w (R, p), r_w (R,)) -- the robust-weighted Jacobian and residual rows,
    reused by the block jackknife and the half-samples (``uncertainty``).

    J by central differences (2p residual evaluations) with the Chamfer neighbours frozen at ``x``
    (otherwise a neighbour switch inside the step fakes a huge derivative); s^2 from the align
    residuals. O(R p^2) for R residual rows.
    """
    if frozen is None:
        frozen = problem.matches(x)
    residual = problem.residuals(x, frozen)
    step = 1e-6
    columns = []
    for index in range(x.size):
        delta = np.zeros_like(x)
        delta[index] = step
        columns.append((problem.residuals(x + delta, frozen) - problem.residuals(x - delta, frozen)) / (2 * step))
    jacobian = np.stack(columns, axis=1)
    z = (residual / f_scale) ** 2
    rho_prime = _RHO_PRIME.get(problem.loss, np.ones_like)(z)
    robust = np.sqrt(rho_prime)
    weighted_jacobian = jacobian * robust[:, None]
    align_count = problem.align_rows
    align = residual[:align_count] * robust[:align_count]
    variance = float(align @ align) / max(align_count - x.size, 1)
    # parameters the model holds (identically zero columns: a slide along a given axis) do not
    # make the problem ill-conditioned
    active = np.any(weighted_jacobian != 0.0, axis=0)
    singular = np.linalg.svd(weighted_jacobian[:, active], compute_uv=False) if active.any() else np.zeros(1)
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else float("inf")
    normal = weighted_jacobian.T @ weighted_jacobian
    return factor * variance * np.linalg.pinv(normal, rcond=1e-12), condition, weighted_jacobian, residual * robust
