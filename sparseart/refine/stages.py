"""The refinement stages (SPLART): per-state fit, cross-static mobility, cross-mobile articulation
and mobility correction. Each is a plain function over a :class:`Problem`; :mod:`.api` runs them
in order, times each one and lets each be switched off.

Cost per optimisation step: one rendering per state (the training views are cycled), i.e.
O(N_drawn * footprint_tiles * 256) each (see :mod:`.render`), plus a KD-tree matching
O(N log N) for the Chamfer steps. N_drawn is N (own), 2N (cross-static) or 3N (cross-mobile)
for N Gaussians per state.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .compose import components, render_components
from .gaussians import GaussianSet
from .joint import JointParams
from .losses import depth_loss, photometric_loss, weighted_chamfer
from .views import View

STATES = ("start", "end")
CHAMFER_CAP_SPACINGS = 10.0     # Chamfer distances are capped at this many Gaussian spacings
STATIC_MARGIN_SPACINGS = 2.0    # small-mobility regulariser of the cross-static Chamfer, in spacings
NEIGHBOURS_FOR_CORRECTION = 8


@dataclass
class Problem:
    """Everything the stages share. sets: state -> GaussianSet; views: state -> training views;
    joint: the current joint; diameter: object size (frame units); spacing: median Gaussian
    spacing (frame units); options: RefineOptions; rng: numpy Generator; log: loss traces."""

    sets: dict[str, GaussianSet]
    views: dict[str, list[View]]
    joint: JointParams
    diameter: float
    spacing: float
    options: object
    rng: np.random.Generator
    log: dict = field(default_factory=dict)


def _adam(groups: list[tuple[list, float]]):
    import torch

    for tensors, _ in groups:
        for t in tensors:
            t.requires_grad_(True)
    return torch.optim.Adam([{"params": tensors, "lr": lr} for tensors, lr in groups if tensors], eps=1e-15)


def _step(optimiser, loss) -> float:
    """Backward + Adam step; non-finite gradients (singular maths) are zeroed, never applied."""
    import torch

    optimiser.zero_grad(set_to_none=True)
    if not torch.isfinite(loss):
        return float("nan")
    loss.backward()
    for group in optimiser.param_groups:
        for p in group["params"]:
            if p.grad is not None:
                torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
    optimiser.step()
    return float(loss.detach())


def _freeze(problem: Problem) -> None:
    for gaussians in problem.sets.values():
        gaussians.requires_grad_(())
    for t in (problem.joint.axis, problem.joint.pivot, problem.joint.amount):
        t.requires_grad_(False)


def view_loss(view: View, drawn: tuple, problem: Problem):
    """Photometric (L1 + D-SSIM) + depth/silhouette loss of one view for the drawn components."""
    options = problem.options
    out = render_components(drawn, view.camera, view.background)
    loss = photometric_loss(out["rgb"], view.rgb, view.weight, options.ssim_weight)
    if view.depth is not None and options.depth_weight > 0:
        loss = loss + options.depth_weight * depth_loss(out["depth"], out["alpha"], view.depth, view.weight,
                                                        0.1 * problem.diameter)
    return loss


def _training(problem: Problem, state: str) -> list[View]:
    return [v for v in problem.views.get(state, []) if not v.held_out]


def _render_step(problem: Problem, step: int, mode: str, states=STATES):
    """Sum over states of one training view's loss (views cycled by step)."""
    total = None
    for state in states:
        train = _training(problem, state)
        if not train or state not in problem.sets:
            continue
        loss = view_loss(train[step % len(train)], components(state, problem.sets, problem.joint, mode), problem)
        total = loss if total is None else total + loss
    return total


def _mobility_mean(problem: Problem):
    import torch

    return torch.cat([g.mobility() for g in problem.sets.values()]).mean()


def fit_states(problem: Problem) -> None:
    """Stage 1: fit each state's Gaussians to its own views (every Gaussian parameter but
    mobility), photometric L1 + D-SSIM plus depth/silhouette. O(iters * render)."""
    d = problem.diameter
    groups = []
    for g in problem.sets.values():
        groups += [([g.means], 5e-4 * d), ([g.log_scales], 0.01), ([g.quats], 0.005),
                   ([g.opacity_logits], 0.05), ([g.f_dc], 0.02)]
    optimiser = _adam(groups)
    trace = []
    for step in range(problem.options.per_state_iters):
        loss = _render_step(problem, step, "own")
        if loss is None:
            break
        trace.append(_step(optimiser, loss))
    _freeze(problem)
    problem.log["fit_states"] = trace


def _nearest_distance(points: np.ndarray, others: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    if len(others) == 0:
        return np.full(len(points), np.inf)
    return cKDTree(others).query(points, k=1)[0]


def cross_static_chamfer(problem: Problem) -> None:
    """Stage 2a: mobility from the weighted Chamfer between the two states' static components.

    Loss = sum_i w_i min(d_i, cap) / sum_i w_i over both directions, w = (1 - m) o, plus a
    regulariser ``STATIC_MARGIN_SPACINGS * mean(m)`` (distances in units of the Gaussian
    spacing) preferring small mobility: a Gaussian turns mobile when its nearest Gaussian of
    the other state is more than about the margin beyond the average. Centres are fixed here, so
    the matching is computed once. O(N log N + iters N)."""
    import torch

    if len(problem.sets) < 2:
        return
    start, end = problem.sets["start"], problem.sets["end"]
    xs, xe = start.means.detach().double().numpy(), end.means.detach().double().numpy()
    cap = CHAMFER_CAP_SPACINGS
    ds = torch.as_tensor(np.minimum(_nearest_distance(xs, xe) / problem.spacing, cap), dtype=start.means.dtype)
    de = torch.as_tensor(np.minimum(_nearest_distance(xe, xs) / problem.spacing, cap), dtype=start.means.dtype)
    optimiser = _adam([([start.mobility_logits, end.mobility_logits], 0.05)])
    trace = []
    for _ in range(problem.options.static_chamfer_iters):
        ws, we = start.static_opacities(), end.static_opacities()
        loss = (ws * ds).sum() / ws.sum().clamp_min(1e-12) + (we * de).sum() / we.sum().clamp_min(1e-12) \
            + STATIC_MARGIN_SPACINGS * _mobility_mean(problem)
        trace.append(_step(optimiser, loss))
    _freeze(problem)
    problem.log["cross_static_chamfer"] = trace


def cross_static_render(problem: Problem) -> None:
    """Stage 2b: each state rendered with the other state's static components added; optimises
    mobility (and colour/opacity at a low rate) with the photometric loss and the small-mobility
    regulariser. O(iters * render of 2N)."""
    if len(problem.sets) < 2:
        return
    groups = []
    for g in problem.sets.values():
        groups += [([g.mobility_logits], 0.05), ([g.f_dc], 0.005), ([g.opacity_logits], 0.01)]
    optimiser = _adam(groups)
    trace = []
    for step in range(problem.options.cross_static_iters):
        loss = _render_step(problem, step, "cross_static")
        if loss is None:
            break
        trace.append(_step(optimiser, loss + problem.options.mobility_reg * _mobility_mean(problem)))
    _freeze(problem)
    problem.log["cross_static_render"] = trace


def joint_chamfer_loss(problem: Problem, joint: JointParams):
    """Cross-mobile + mobile-only weighted Chamfer of a joint (frame units / spacing).

    mobile-only: start's mobile centres moved start -> end vs end's mobile centres (weights m o,
    both directions); cross-mobile: each state's moved mobile centres vs all Gaussians of the
    other state (one direction each)."""
    start, end = problem.sets["start"], problem.sets["end"]
    cap = CHAMFER_CAP_SPACINGS * problem.spacing
    r_f, t_f = joint.motion(1.0)
    r_b, t_b = joint.motion(1.0, inverse=True)
    moved_start = start.means @ r_f.T + t_f
    moved_end = end.means @ r_b.T + t_b
    ws, we = start.mobile_opacities().detach(), end.mobile_opacities().detach()
    mobile_s = start.mobility().detach() > 0.5
    mobile_e = end.mobility().detach() > 0.5
    mobile_only = weighted_chamfer(moved_start[mobile_s], end.means.detach()[mobile_e], ws[mobile_s],
                                   we[mobile_e], cap)
    cross = weighted_chamfer(moved_start, end.means.detach(), ws, None, cap, both=False) \
        + weighted_chamfer(moved_end, start.means.detach(), we, None, cap, both=False)
    return (mobile_only + cross) / problem.spacing


def _joint_groups(joint: JointParams, diameter: float, scale: float) -> list:
    groups = [([joint.axis], 0.01 * scale), ([joint.amount], (0.01 if joint.type == "revolute" else 0.005 * diameter)
                                            * scale)]
    if joint.type == "revolute":
        groups.append(([joint.pivot], 0.005 * diameter * scale))
    return groups


def _perturbed(joint: JointParams, rng: np.random.Generator, diameter: float) -> JointParams:
    """A copy of the joint with its axis tilted up to 5 deg, pivot moved up to 3 % of the object
    size and angle changed up to 5 deg (distance up to 5 % of the object size)."""
    import torch

    out = joint.clone()
    axis = out.unit_axis().double().numpy()
    tilt = rng.normal(size=3)
    tilt -= tilt.dot(axis) * axis
    tilt /= max(np.linalg.norm(tilt), 1e-12)
    angle = np.radians(rng.uniform(0, 5))
    out.axis = torch.as_tensor(np.cos(angle) * axis + np.sin(angle) * tilt, dtype=out.axis.dtype)
    out.pivot = out.pivot + torch.as_tensor(rng.uniform(-0.03, 0.03, 3) * diameter, dtype=out.pivot.dtype)
    delta = np.radians(rng.uniform(-5, 5)) if joint.type == "revolute" else rng.uniform(-0.05, 0.05) * diameter
    out.amount = out.amount + float(delta)
    return out


def cross_mobile_chamfer(problem: Problem) -> None:
    """Stage 3a: joint by cross-mobile + mobile-only weighted Chamfer from the seed and
    ``joint_restarts`` randomised perturbations of it; the lowest final loss wins.
    O(restarts * iters * N log N)."""
    import torch

    if len(problem.sets) < 2:
        return
    candidates = [problem.joint.clone()] + [_perturbed(problem.joint, problem.rng, problem.diameter)
                                            for _ in range(problem.options.joint_restarts)]
    results = []
    for candidate in candidates:
        optimiser = _adam(_joint_groups(candidate, problem.diameter, 1.0))
        trace = [_step(optimiser, joint_chamfer_loss(problem, candidate))
                 for _ in range(problem.options.joint_chamfer_iters)]
        with torch.no_grad():
            final = float(joint_chamfer_loss(problem, candidate))
        for t in candidate.tensors():
            t.requires_grad_(False)
        results.append((final, candidate, trace))
    best = min(results, key=lambda r: r[0] if np.isfinite(r[0]) else np.inf)
    problem.joint = best[1]
    problem.log["cross_mobile_chamfer"] = {"final_losses": [r[0] for r in results], "trace": best[2]}
    problem.log["joint_after_chamfer"] = {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                                          for k, v in problem.joint.values().items()}


def cross_mobile_render(problem: Problem) -> None:
    """Stage 3b: joint + mobility + Gaussians optimised by cross-mobile rendering (each state drawn
    with the other state's static components and its mobile components moved by the joint).
    O(iters * render of 3N)."""
    if len(problem.sets) < 2:
        return
    d = problem.diameter
    groups = _joint_groups(problem.joint, d, 0.2)
    for g in problem.sets.values():
        groups += [([g.mobility_logits], 0.05), ([g.means], 2e-4 * d), ([g.f_dc], 0.005),
                   ([g.opacity_logits], 0.01), ([g.log_scales], 0.005)]
    optimiser = _adam(groups)
    trace = []
    for step in range(problem.options.cross_mobile_iters):
        loss = _render_step(problem, step, "cross_mobile")
        if loss is None:
            break
        trace.append(_step(optimiser, loss + problem.options.mobility_reg * _mobility_mean(problem)))
    _freeze(problem)
    problem.log["cross_mobile_render"] = trace


def in_sight(points: np.ndarray, views: list[View], tolerance: float) -> np.ndarray:
    """(N,) bool: the point projects into some view with valid depth and is not behind the
    observed surface by more than ``tolerance`` (frame units). Views without depth never see."""
    seen = np.zeros(len(points), dtype=bool)
    for view in views:
        if view.depth is None:
            continue
        cam = view.camera.world_to_cam[:3, :3] @ points.T + view.camera.world_to_cam[:3, 3:4]
        z = cam[2]
        front = z > 1e-6
        uv = (view.camera.K @ cam)[:2] / np.where(front, z, 1.0)
        col, row = np.round(uv[0]).astype(np.int64), np.round(uv[1]).astype(np.int64)
        inside = front & (col >= 0) & (col < view.camera.width) & (row >= 0) & (row < view.camera.height)
        observed = np.zeros(len(points))
        depth = view.depth.double().numpy()
        observed[inside] = depth[row[inside], col[inside]]
        seen |= inside & (observed > 0) & (z <= observed + tolerance)
    return seen


def correct_mobility(problem: Problem) -> dict:
    """Stage 3c: mobility of Gaussians that moved out of sight, by geometric consistency.

    A Gaussian whose static position and whose moved position both fall outside every view of
    the other state (or behind its observed surface) got no photometric evidence about its
    mobility; it takes the mean mobility of its ``NEIGHBOURS_FOR_CORRECTION`` nearest in-sight
    Gaussians of the same state (parts are rigid and contiguous), when those lie within 3
    spacings. A Gaussian in sight whose geometry is decisive (exactly one of its two positions
    within 1 spacing of a Gaussian of the other state, the other beyond 3) is set to that
    answer (mobility 0.05 or 0.95). Returns counts. O(N log N + N * views)."""
    import torch
    from scipy.spatial import cKDTree

    from .gaussians import logit

    counts = {}
    if len(problem.sets) < 2:
        return counts
    for state, other in (("start", "end"), ("end", "start")):
        g, h = problem.sets[state], problem.sets[other]
        x = g.means.detach().double().numpy()
        rotation, translation = problem.joint.motion(1.0, inverse=(state == "end"))
        y = x @ rotation.detach().double().numpy().T + translation.detach().double().numpy()
        other_views = [v for v in problem.views.get(other, []) if not v.held_out]
        tol = 2.0 * problem.spacing
        visible = in_sight(x, other_views, tol) | in_sight(y, other_views, tol)
        mobility = g.mobility().detach().double().numpy().copy()
        others = h.means.detach().double().numpy()
        d_static, d_mobile = _nearest_distance(x, others), _nearest_distance(y, others)
        near, far = problem.spacing, 3.0 * problem.spacing
        to_static = visible & (d_static < near) & (d_mobile > far)
        to_mobile = visible & (d_mobile < near) & (d_static > far)
        mobility[to_static], mobility[to_mobile] = 0.05, 0.95
        hidden = np.flatnonzero(~visible)
        propagated = 0
        if len(hidden) and visible.sum() >= NEIGHBOURS_FOR_CORRECTION:
            dist, idx = cKDTree(x[visible]).query(x[hidden], k=NEIGHBOURS_FOR_CORRECTION)
            ok = dist.max(axis=1) <= 3.0 * problem.spacing
            mobility[hidden[ok]] = mobility[visible][idx[ok]].mean(axis=1)
            propagated = int(ok.sum())
        g.mobility_logits = torch.as_tensor(logit(mobility), dtype=g.mobility_logits.dtype)
        counts[state] = {"out_of_sight": int(len(hidden)), "propagated": propagated,
                         "set_static": int(to_static.sum()), "set_mobile": int(to_mobile.sum())}
    problem.log["mobility_correction"] = counts
    return counts
