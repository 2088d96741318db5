"""The fit's numerical kernels: sparse one-to-one matching, the robust solver, the stop rule."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares, linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from sparseart.joints.optimise import (
    QUANTUM_BITS,
    RemainingBelow,
    one_to_one_pairs,
    robust_solve,
)
from sparseart.joints.part import Sample


def _sample(start: np.ndarray, end: np.ndarray, spacing: float, rng: np.random.Generator) -> Sample:
    normals = lambda count: rng.normal(size=(count, 3)) / np.sqrt(3.0)
    start_normals, end_normals = normals(len(start)), normals(len(end))
    start_normals /= np.linalg.norm(start_normals, axis=1, keepdims=True)
    end_normals /= np.linalg.norm(end_normals, axis=1, keepdims=True)
    return Sample(start, end, start_normals, end_normals, cKDTree(end), spacing)


def _dense_clipped(moved, sample, tau, moved_normals=None, normal_cos=0.0):
    """The reference: dense cost matrix clipped at tau^2, Hungarian, pairs at the clip dropped."""
    cost = cdist(moved, sample.end, "sqeuclidean")
    if moved_normals is not None:
        cost[np.abs(moved_normals @ sample.end_normals.T) < normal_cos] = np.inf
    rows, cols = linear_sum_assignment(np.minimum(cost, tau * tau))
    keep = cost[rows, cols] < tau * tau
    return rows[keep], cols[keep], cost


@pytest.mark.parametrize("seed,offset,gate", [(0, 0.0, False), (1, 0.02, False), (2, 0.05, True), (3, 0.1, True)])
def test_sparse_matching_reaches_the_dense_optimum(seed, offset, gate):
    """Same clipped total cost as the dense Hungarian assignment (ties may pick other pairs)."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(-1, 1, (300, 3)) * [1, 1, 0.05]
    end = np.concatenate([start[:250] + rng.normal(0, 0.01, (250, 3)), rng.uniform(-1, 1, (40, 3))])
    moved = start + offset
    spacing = float(np.median(cKDTree(end).query(end, k=2)[0][:, 1]))
    sample = _sample(start, end, spacing, rng)
    moved_normals = sample.start_normals if gate else None
    normal_cos = 0.5 if gate else 0.0
    rows, cols, tau = one_to_one_pairs(moved, sample, 3.0, moved_normals, normal_cos)
    dense_rows, dense_cols, cost = _dense_clipped(moved, sample, tau, moved_normals, normal_cos)
    assert len(set(rows)) == len(rows) and len(set(cols)) == len(cols)
    assert np.all(cost[rows, cols] < tau * tau)
    total = lambda r, c: float(np.sum(cost[r, c]) + (min(len(moved), len(end)) - len(r)) * tau * tau)
    quantum = len(moved) * tau * tau * 2.0 ** -QUANTUM_BITS  # integer costs (see one_to_one_pairs)
    assert total(rows, cols) == pytest.approx(total(dense_rows, dense_cols), abs=quantum)


def test_sparse_matching_of_an_aliased_wire_rack_terminates():
    """Wires slid by about one period: many near-equal costs (float LAPJVsp cycled forever here)."""
    rng = np.random.default_rng(0)
    wires = [np.c_[rng.uniform(-0.2, 0.2, 120), np.full(120, y), np.zeros(120)] for y in np.linspace(-0.1, 0.1, 5)]
    start = np.vstack(wires)
    end = np.vstack([w + [0.0, rng.normal(0, 1e-4), 0.0] for w in wires])[rng.permutation(len(start))]
    spacing = float(np.median(cKDTree(end).query(end, k=2)[0][:, 1]))
    sample = _sample(start, end, spacing, rng)
    rows, _, _ = one_to_one_pairs(start + [0.0, 0.05, 0.0], sample, 3.0)
    assert len(rows) == len(set(rows)) and len(rows) > 0


def test_sparse_matching_with_nothing_in_reach():
    rng = np.random.default_rng(4)
    start = rng.uniform(-1, 1, (50, 3))
    sample = _sample(start, start + 100.0, 0.01, rng)
    rows, cols, tau = one_to_one_pairs(start, sample)
    assert rows.size == 0 and cols.size == 0 and tau == pytest.approx(0.08)


@pytest.mark.parametrize("loss", ["linear", "soft_l1", "cauchy", "huber"])
def test_robust_solve_matches_scipy(loss):
    """A small nonlinear robust problem (exponential fit with outliers): same optimum as
    scipy.optimize.least_squares with the same loss and scale."""
    rng = np.random.default_rng(5)
    t = np.linspace(0, 3, 80)
    y = 2.0 * np.exp(-1.3 * t) + 0.5 + rng.normal(0, 0.02, t.size)
    y[::13] += 1.0  # outliers
    function = lambda x: x[0] * np.exp(-x[1] * t) + x[2] - y
    x0 = np.array([1.0, 1.0, 0.0])
    ours = robust_solve(function, x0, f_scale=0.05, loss=loss, max_nfev=400, rtol=1e-14)
    reference = least_squares(function, x0, loss=loss, f_scale=0.05, xtol=1e-14, ftol=1e-14, gtol=1e-14)
    assert np.allclose(ours.x, reference.x, atol=1e-5)


def test_robust_solve_extrapolation_reaches_the_fixed_point_faster():
    """A contraction x -> 0.2 x + 0.8 target, solved through a frozen linearisation that only
    sees a fifth of the way (the ICP-like slow convergence of frozen Chamfer neighbours): the
    Aitken extrapolation reaches the fixed point in fewer evaluations."""
    target = np.array([1.0, -2.0])

    def linearise(x):
        anchor = x + 0.2 * (target - x)  # each frozen problem's minimum is a fifth of the way on
        return lambda y: y - anchor

    function = lambda x: linearise(x)(x)
    plain = robust_solve(function, np.zeros(2), 1.0, "linear", 200, rtol=1e-12, linearise=linearise)
    fast = robust_solve(function, np.zeros(2), 1.0, "linear", 200, rtol=1e-12, linearise=linearise, extrapolate=True)
    assert np.allclose(plain.x, target, atol=1e-4) and np.allclose(fast.x, target, atol=1e-4)
    assert fast.nfev < plain.nfev


def test_remaining_below():
    stop = RemainingBelow(1.0)
    assert not stop(5.0)           # one step alone says nothing about the rest ...
    assert not stop(4.0)           # ... slow shrinking (rate 0.8): 16 still to go
    assert stop(0.5)               # rate 0.125: 0.07 to go
    assert RemainingBelow(1.0)(0.05)  # a first step under stop / 10
    growing = RemainingBelow(1.0)
    assert not growing(2.0) and not growing(3.0)
