"""Entry points of the refinement: :func:`refine_part` (one movable part) and
:func:`refine_parts` (what the pipeline calls; replaces each part's JointEstimate).

Per movable part k the Gaussians come from the points labelled static (0), k or unassigned (-1)
of both states; pixels of other movable parts are left out of every loss. The stages run in
order (each switchable, each timed): build, fit_states, cross_static (Chamfer then rendering),
cross_mobile (Chamfer restarts then rendering), mobility_correction, then the acceptance guard.

Acceptance guard. The refined joint replaces the seed only when, with the Gaussians as they were
before the joint was touched (after cross-static), its cross-mobile rendering loss over all
training views is lower than the seed's by at least ``accept_margin`` (relative) AND its
geometric residual on the labelled part points (trimmed RMS nearest-neighbour distance, both
directions) is at most ``geometric_tolerance`` times the seed's. A refined joint that leaves the
seed's stated 1-sigma region (largest of axis angle / sigma_axis, pivot offset / sigma_origin,
state change / sigma_state = m > 1) must in addition not raise the geometric residual at all.
Measured: on the bench the stapler's pivot moved 3.8 sigma for a 0.7 % rendering gain at +5 %
geometric residual and came out 20x worse in position (rejected now); seeds perturbed by 5 deg
are 10+ sigma from their refined joints, which fit the points better, and stay accepted. (Scaling
the rendering margin with m instead rejected 4 of those 6 recoveries.) Otherwise the seed is
kept and a warning says why; ``joint.diagnostics["refine"]`` always holds both joints and all
numbers.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..clock import StageClock
from ..types import JointEstimate, LabelledCloud, PartLabels, PartResult, Scene
from . import stages
from .gaussians import gaussians_from_points, initial_mobility
from .joint import JointParams


@dataclass
class RefineOptions:
    """Defaults chosen for < 2 min per movable part on 2 CPU cores: measured 55-95 s per joint on
    5 PartNet objects (320x240 images, 4 views, 2500 Gaussians per state, crops rendered at 96 px;
    experiment EXP-002). Objects with k movable parts take k times that.

    long_side: rendering resolution (px of the longer image side). max_gaussians: per state.
    *_iters: optimisation steps of each stage (one view per state per step). joint_restarts:
    randomised restarts of the joint Chamfer besides the seed. holdout_views: last views of each
    state kept out of fitting for PSNR (0 = use all). per_state / cross_static / cross_mobile /
    mobility_correction: switch stages. accept_margin / geometric_tolerance: acceptance guard.
    object_budget_seconds: wall-time budget for all parts of one object (None = no budget). With
    several movable parts each part gets an equal share; the iteration counts of a part are scaled
    down (never up) by share / expected cost, the cost being re-estimated from the parts already
    refined (``EXPECTED_PART_SECONDS`` before the first), and a warning says so.
    """

    long_side: int = 96
    max_gaussians: int = 2500
    per_state_iters: int = 60
    static_chamfer_iters: int = 60
    cross_static_iters: int = 30
    joint_restarts: int = 4
    joint_chamfer_iters: int = 40
    cross_mobile_iters: int = 80
    holdout_views: int = 0
    per_state: bool = True
    cross_static: bool = True
    cross_mobile: bool = True
    mobility_correction: bool = True
    depth_weight: float = 1.0
    ssim_weight: float = 0.2
    mobility_reg: float = 0.01
    accept_margin: float = 0.005
    geometric_tolerance: float = 1.25
    threads: int = 2
    seed: int = 0
    object_budget_seconds: float | None = 100.0

    def validate(self) -> "RefineOptions":
        for name in ("long_side", "max_gaussians", "threads"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"refine option {name} must be >= 1, got {getattr(self, name)!r}")
        for name in ("per_state_iters", "static_chamfer_iters", "cross_static_iters", "joint_restarts",
                     "joint_chamfer_iters", "cross_mobile_iters", "holdout_views"):
            if int(getattr(self, name)) < 0:
                raise ValueError(f"refine option {name} must be >= 0, got {getattr(self, name)!r}")
        if self.object_budget_seconds is not None and not self.object_budget_seconds > 0:
            raise ValueError(f"refine option object_budget_seconds must be > 0 or None, got {self.object_budget_seconds!r}")
        if self.long_side < 16:
            raise ValueError(f"refine option long_side must be >= 16 px, got {self.long_side}")
        return self


class _PartClock:
    """Prefixes every stage's reason with the part it refines."""

    def __init__(self, clock, part_id: int) -> None:
        self.clock, self.prefix = clock, f"part {part_id}: "

    def stage(self, name: str, why: str):
        return self.clock.stage(name, why if why.startswith(self.prefix) else self.prefix + why)

    def skip(self, name: str, why: str) -> None:
        self.clock.skip(name, self.prefix + why)


@dataclass
class PartRefinement:
    """Result of refining one part. joint: the accepted JointEstimate (seed or refined);
    accepted: whether the refined joint replaced the seed; params: the accepted joint as torch
    parameters; sets / views: the final Gaussians and the views (for outputs)."""

    part_id: int
    joint: JointEstimate
    accepted: bool
    params: JointParams
    sets: dict
    views: dict
    diagnostics: dict
    warnings: list[str] = field(default_factory=list)


def _subsample(mask: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    from sparseart.geometry.sampling import random_subset

    index = np.flatnonzero(mask)
    return index[random_subset(len(index), count, rng)]


def _trimmed_residual(a: np.ndarray, b: np.ndarray, transform: np.ndarray, keep: float = 0.8) -> float:
    """Trimmed RMS nearest-neighbour distance, both directions, of a moved by ``transform`` vs b."""
    from sparseart.geometry.transforms import apply_transform

    inverse = np.linalg.inv(transform)
    d1 = np.sort(stages._nearest_distance(apply_transform(transform, a), b))
    d2 = np.sort(stages._nearest_distance(apply_transform(inverse, b), a))
    d = np.concatenate([d1[:max(1, int(keep * len(d1)))], d2[:max(1, int(keep * len(d2)))]])
    return float(np.sqrt(np.mean(d ** 2)))


def _transform(values: dict) -> np.ndarray:
    from sparseart.geometry.transforms import transform_from_prismatic, transform_from_revolute

    if values["type"] == "revolute":
        return transform_from_revolute(values["axis"], values["origin"], values["angle"])
    return transform_from_prismatic(values["axis"], values["distance"])


def _render_loss_all(problem: stages.Problem, joint: JointParams) -> float:
    import torch

    saved, problem.joint = problem.joint, joint
    total, count = 0.0, 0
    with torch.no_grad():
        for state in stages.STATES:
            for view in stages._training(problem, state):
                drawn = stages.components(state, problem.sets, joint, "cross_mobile")
                total += float(stages.view_loss(view, drawn, problem))
                count += 1
    problem.joint = saved
    return total / max(count, 1)


def _as_jsonable(values: dict) -> dict:
    return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in values.items()}


def refine_part(start: LabelledCloud, end: LabelledCloud, labels: PartLabels, part_id: int,
                seed: JointEstimate, scene: Scene, options: RefineOptions | None = None,
                clock=None, object_centre: np.ndarray | None = None) -> PartRefinement:
    """Refine the joint of movable part ``part_id`` from its fitted ``seed``.

    start, end: the pipeline's clouds ((N, 3) float64 points, scene frame); labels: their part
    labels; scene: the loaded scene (images, depth, cameras). clock: an object with
    ``stage(name, why)`` / ``skip(name, why)`` (the pipeline's StageClock) or None.
    Returns a :class:`PartRefinement`; raises ValueError on unusable input (no views, too few
    points).
    """
    import torch

    options = (options or RefineOptions()).validate()
    clock = _PartClock(clock or StageClock(), part_id)
    rng = np.random.default_rng(options.seed)
    modelled = {0, part_id}
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(int(options.threads))
    began = time.perf_counter()
    try:
        with clock.stage("refine.build", f"Gaussians from the labelled points, views at "
                                         f"{options.long_side} px"):
            views, sets = {}, {}
            for cloud, part in ((start, labels.start_part), (end, labels.end_part)):
                views[cloud.state] = _state_views(scene, cloud, part, modelled, options)
                held = {v.index for v in views[cloud.state] if v.held_out}
                usable = np.isin(part, [0, part_id, -1]) & ~np.isin(cloud.frame_index, list(held))
                pick = _subsample(usable, options.max_gaussians, rng)
                if len(pick) < 20:
                    raise ValueError(f"part {part_id}: only {len(pick)} points of the {cloud.state} state to build "
                                     f"Gaussians from")
                sets[cloud.state] = gaussians_from_points(
                    cloud.state, cloud.points[pick], cloud.colors[pick], initial_mobility(part[pick], part_id))
            all_points = np.concatenate([start.points, end.points])
            diameter = float(np.linalg.norm(all_points.max(0) - all_points.min(0)))
            spacing = float(np.median(np.exp(np.concatenate(
                [g.log_scales[:, 0].double().numpy() for g in sets.values()]))))
            problem = stages.Problem(sets=sets, views=views, joint=JointParams.from_estimate(seed), diameter=diameter,
                                     spacing=max(spacing, 1e-9), options=options, rng=rng)
        _run(clock, options.per_state and options.per_state_iters > 0, "refine.fit_states",
             "per-state fit: L1 + D-SSIM + depth", stages.fit_states, problem)
        _run(clock, options.cross_static, "refine.cross_static",
             "mobility by cross-static weighted Chamfer, then cross-static rendering",
             lambda p: (stages.cross_static_chamfer(p), stages.cross_static_render(p)), problem)
        snapshot = {k: g.clone() for k, g in problem.sets.items()}
        seed_params = problem.joint.clone()
        _run(clock, options.cross_mobile, "refine.cross_mobile",
             f"joint by cross-mobile Chamfer ({options.joint_restarts} restarts), then cross-mobile rendering",
             lambda p: (stages.cross_mobile_chamfer(p), stages.cross_mobile_render(p)), problem)
        _run(clock, options.mobility_correction and options.cross_mobile, "refine.mobility_correction",
             "mobility of Gaussians moved out of sight, by geometric consistency", stages.correct_mobility, problem)
        with clock.stage("refine.accept", "acceptance guard: refined joint vs seed"):
            outcome = _accept(start, end, labels, part_id, seed, seed_params, problem, snapshot, options,
                              object_centre)
        from .outputs import psnr_report

        outcome.diagnostics["psnr"] = psnr_report(outcome)
    finally:
        torch.set_num_threads(previous_threads)
    outcome.diagnostics["seconds"] = time.perf_counter() - began
    outcome.diagnostics["losses"] = {k: v for k, v in problem.log.items() if k != "cross_mobile_chamfer"}
    outcome.diagnostics["chamfer_restart_losses"] = problem.log.get("cross_mobile_chamfer", {}).get("final_losses")
    return outcome


def _state_views(scene: Scene, cloud: LabelledCloud, part: np.ndarray, modelled: set[int],
                 options: RefineOptions) -> list:
    """The training/held-out views of ``cloud.state`` (see :func:`.views.build_views`)."""
    from .views import build_views

    return build_views(scene, cloud, part, modelled, options.long_side, options.holdout_views)


def _run(clock, enabled: bool, name: str, why: str, function, problem) -> None:
    if not enabled:
        clock.skip(name, "switched off in the refine options")
        return
    with clock.stage(name, why):
        function(problem)


def sigma_moves(before: dict, after: dict, uncertainty: dict[str, float]) -> dict[str, float]:
    """How far the refined joint ``after`` lies from the seed ``before``, in the seed's stated
    sigmas: {"axis": angle / sigma_axis_deg, "origin": offset of the seed pivot from the refined
    axis line / sigma_origin (revolute), "angle" | "distance": state change / its sigma}.
    Both dicts: type, axis (3,), origin (3,), angle (rad) | distance (scene units). Axes of
    opposite sign are compared as one line (the state's sign follows). Components without a
    positive sigma are left out. O(1)."""
    from ..geometry.transforms import axis_angle_deg

    axis_b = np.asarray(before["axis"], np.float64)
    axis_a = np.asarray(after["axis"], np.float64)
    axis_b, axis_a = axis_b / np.linalg.norm(axis_b), axis_a / np.linalg.norm(axis_a)
    sign = 1.0 if float(axis_a @ axis_b) >= 0 else -1.0
    moves: dict[str, float] = {}

    def add(name: str, amount: float, sigma_key: str) -> None:
        sigma = float(uncertainty.get(sigma_key, 0.0) or 0.0)
        if sigma > 0 and np.isfinite(sigma):
            moves[name] = float(amount) / sigma

    add("axis", axis_angle_deg(axis_a, axis_b), "axis_deg")
    if before["type"] == "revolute":
        offset = np.asarray(before["origin"], np.float64) - np.asarray(after["origin"], np.float64)
        add("origin", np.linalg.norm(offset - (offset @ axis_a) * axis_a), "origin")
        if before.get("angle") is not None and after.get("angle") is not None:
            add("angle", abs(sign * float(after["angle"]) - float(before["angle"])), "angle")
    elif before.get("distance") is not None and after.get("distance") is not None:
        add("distance", abs(sign * float(after["distance"]) - float(before["distance"])), "distance")
    return moves


def _accept(start, end, labels, part_id, seed, seed_params, problem, snapshot, options, object_centre):
    part_start = start.points[labels.start_part == part_id]
    part_end = end.points[labels.end_part == part_id]
    reference = object_centre if seed.type == "revolute" else seed.origin
    before = {"type": seed.type, "axis": np.asarray(seed.axis, np.float64), "origin": np.asarray(seed.origin),
              "angle": seed.angle, "distance": seed.distance}
    after = problem.joint.values(reference)
    final_sets = problem.sets
    problem.sets = snapshot
    render_before = _render_loss_all(problem, seed_params)
    render_after = _render_loss_all(problem, problem.joint)
    problem.sets = final_sets
    geometric_before = _trimmed_residual(part_start, part_end, _transform(before))
    geometric_after = _trimmed_residual(part_start, part_end, _transform(after))
    finite = all(np.all(np.isfinite(v)) for v in after.values() if isinstance(v, (np.ndarray, float)))
    moves = sigma_moves(before, after, seed.uncertainty) if finite else {}
    reach = max(moves.values(), default=0.0)
    tolerance = options.geometric_tolerance if reach <= 1.0 else 1.0
    better_render = render_after < (1.0 - options.accept_margin) * render_before
    geometry_ok = geometric_after <= tolerance * geometric_before + 1e-12
    accepted = bool(options.cross_mobile and finite and better_render and geometry_ok)
    if not options.cross_mobile:
        why = "cross-mobile stage off: the seed joint is kept"
    elif accepted:
        why = "refined joint accepted: lower rendering loss and comparable geometric residual"
    else:
        why = ("kept the seed joint: the refined joint " +
               ("is not finite" if not finite else
                f"does not lower the rendering loss by {options.accept_margin:.1%} "
                f"({render_after:.5f} vs {render_before:.5f}; it moves {reach:.1f} sigma from the seed)"
                if not better_render else
                f"raises the geometric residual {geometric_after:.5f} vs {geometric_before:.5f} "
                f"(> x{tolerance:g}; it moves {reach:.1f} sigma from the seed)"))
    chosen = after if accepted else before
    joint = JointEstimate(
        type=seed.type, axis=np.asarray(chosen["axis"], np.float64), origin=np.asarray(chosen["origin"], np.float64),
        angle=chosen["angle"], distance=chosen["distance"], transform=_transform(chosen) if accepted else seed.transform,
        uncertainty=dict(seed.uncertainty), residual=seed.residual, confidence=seed.confidence,
        slide=0.0 if accepted else seed.slide, warnings=list(seed.warnings), diagnostics=dict(seed.diagnostics))
    diagnostics = {"accepted": accepted, "why": why, "before": _as_jsonable(before), "after": _as_jsonable(after),
                   "render_loss": {"seed": render_before, "refined": render_after},
                   "geometric_residual": {"seed": geometric_before, "refined": geometric_after},
                   "sigma_moves": moves,
                   "uncertainty": "carried over from the seed fit"}
    warnings = [] if accepted or not options.cross_mobile else [f"refine: {why}"]
    params = problem.joint if accepted else seed_params
    return PartRefinement(part_id=part_id, joint=joint, accepted=accepted, params=params, sets=problem.sets,
                          views=problem.views, diagnostics=diagnostics, warnings=warnings)


EXPECTED_PART_SECONDS = 70.0  # measured default cost of one part on 2 cores (refine_partnet_v4*.txt)
ITERATION_FIELDS = ("per_state_iters", "static_chamfer_iters", "cross_static_iters", "joint_chamfer_iters",
                    "cross_mobile_iters")


def budget_ratio(budget: float | None, elapsed: float, parts_left: int, full_cost: float) -> float:
    """Fraction in (0, 1] of the default iterations the next part may use so that the
    ``parts_left`` parts share what is left of ``budget`` seconds, each costing ``full_cost``
    seconds at full iterations. 1 without a budget; at least 0.05."""
    if budget is None or parts_left <= 0 or full_cost <= 0:
        return 1.0
    share = max(budget - elapsed, 0.0) / parts_left
    return float(min(1.0, max(0.05, share / full_cost)))


def with_iterations(options: RefineOptions, cross_mobile_iters: int) -> RefineOptions:
    """A copy of ``options`` whose ``cross_mobile_iters`` is the given count and every other
    ``*_iters`` count scaled by the same ratio (``--refine-iters``; 0 switches every stage off)."""
    from dataclasses import replace

    ratio = cross_mobile_iters / options.cross_mobile_iters if options.cross_mobile_iters else 0.0
    scaled = {name: int(round(getattr(options, name) * ratio)) for name in ITERATION_FIELDS}
    return replace(options, **{**scaled, "cross_mobile_iters": int(cross_mobile_iters)})


def scaled_iterations(options: RefineOptions, ratio: float) -> RefineOptions:
    """A copy of ``options`` with every ``*_iters`` count scaled by ``ratio`` (at least 1 where it was > 0)."""
    from dataclasses import replace

    if ratio >= 1.0:
        return options
    return replace(options, **{name: max(1, int(round(getattr(options, name) * ratio))) if getattr(options, name) > 0
                               else 0 for name in ITERATION_FIELDS})


def refine_parts(start: LabelledCloud, end: LabelledCloud, labels: PartLabels, parts: list[PartResult],
                 scene: Scene | None, options: RefineOptions | None, clock, warnings: list[str]) -> list[PartRefinement]:
    """Pipeline hook: refine every movable part that has a joint, in place.

    Each refined part's ``joint`` is replaced by the accepted JointEstimate (same fields);
    ``joint.diagnostics["refine"]`` holds before/after values, losses and seconds, and
    ``PartResult.refinement`` the :class:`PartRefinement` (Gaussians, views) for the
    outputs (not serialised). Failures of one part become a warning; the seed joint stays.
    """
    if scene is None:
        clock.skip("refine", "no scene images (clouds given): nothing to render against")
        return []
    try:
        import torch  # noqa: F401
    except ImportError:
        clock.skip("refine", "torch is not installed (pip install torch): refinement skipped")
        warnings.append("refinement requested but torch is not installed; the fitted joints are kept")
        return []
    if options is not None and not isinstance(options, RefineOptions):
        raise ValueError(f"refine_options must be a sparseart.refine.RefineOptions, got {type(options).__name__}")
    options = (options or RefineOptions()).validate()   # bad options are an error, not a per-part warning
    object_centre = np.median(start.points, axis=0)
    done = []
    movable = [part for part in parts if part.joint is not None and part.spec.role == "movable"]
    began, full_cost = time.perf_counter(), EXPECTED_PART_SECONDS
    for k, part in enumerate(movable):
        ratio = budget_ratio(options.object_budget_seconds, time.perf_counter() - began, len(movable) - k, full_cost)
        part_options = scaled_iterations(options, ratio)
        if ratio < 1.0:
            warnings.append(f"part {part.spec.id}: refinement iterations scaled to {ratio:.0%} to keep the object "
                            f"within {options.object_budget_seconds:.0f} s ({len(movable)} movable parts)")
        part_began = time.perf_counter()
        try:
            outcome = refine_part(start, end, labels, part.spec.id, part.joint, scene, part_options, clock,
                                  object_centre)
            full_cost = (time.perf_counter() - part_began) / max(ratio, 0.05)
        except (ValueError, np.linalg.LinAlgError) as error:
            warnings.append(f"part {part.spec.id}: refinement failed, seed joint kept: {error}")
            continue
        outcome.joint.diagnostics["refine"] = outcome.diagnostics
        part.refinement = outcome
        warnings.extend(f"part {part.spec.id}: {w}" for w in outcome.warnings)
        part.joint = outcome.joint
        done.append(outcome)
    return done
