"""Fit a revolute or prismatic joint to one part's points in two states: ``fit_joint``.

Steps (all maths in float64 on coordinates centred at the centroid of both sets and divided by
their RMS radius; results converted back at the end), each in its own module:

1. ``part.prepare_part`` (once per part, cached): at most ``max_work_points`` per state, cleaning,
   normalisation, ONE fixed matching / Chamfer / screening subsample with normals and trees;
2. ``seeds.initial_motion``: the given start -> end motion (or ``register_rigid``) -> screw
   decomposition -> revolute init (axis, pivot, angle) and prismatic init (centroid shift)
   (``models.initial_models``);
3. ``optimise.fit_model`` per joint type: matching/update alternation on the matching sample
   (sparse one-to-one matching with costs clipped at a robust distance, so points without a
   partner -- partial views -- stay unmatched; distance-proportional revolute weights), then
   ``L_align + alpha * L_CD`` (soft_l1) with the Chamfer neighbours re-queried at every step;
   covariance ``s^2 (J^T J)^+`` inflated by an effective-sample factor (drives the type test).
   Every loop stops when the motion still to come is below a fraction of the displacement the
   stated uncertainty allows (``FitConfig.stop_fraction``);
4. ``select.choose_type`` for ``joint_type="auto"`` (BIC on the shared Chamfer sample + angle
   significance);
5. stated uncertainty (``JointEstimate.uncertainty``) = the Jacobian covariance of 3 + a spatial
   block jackknife on the optimum's own rows + re-matched half-sample refits warm-started at the
   optimum (one step each) + a calibrated systematic floor (``UNCERTAINTY_FLOOR``), added as
   variances (see
   ``sparseart.joints.uncertainty``); the parts are kept in ``diagnostics["uncertainty_jacobian" |
   "uncertainty_resample" | "uncertainty_half" | "uncertainty_floor"]``. None of it changes the
   point estimates (own random generators). Why: on rendered objects the errors are dominated by
   systematic effects (partial views, label errors, correspondence bias) that a residual-based
   sigma cannot see; the Jacobian sigma alone covered 39 % / 50 % / 72 % of the axis errors at
   1 / 2 / 3 sigma on the 16 PartNet objects, the stated sigma covers 75 % / 90 % / 90 %
   (experiment EXP-009);
6. ``reliability``: warnings with codes and the confidence (read on the residual beyond the part's
   sampling and noise floor, ``noise_floor.residual_floor``).

Cost of one call (W working points per state, n matching / c Chamfer sample per side, p <= 5;
experiment EXP-010 has the measured curve): step 1 O(W log W) once per part (~0.1 s CPU
at 20k points), then per joint type a few sparse matchings (~O(E sqrt(n)), 2-8 ms at n = 1500)
and solves O((n + c) p^2) per evaluation (~25-60 ms CPU per type); step 5 O(R p^2) for R residual
rows plus ``half_samples`` matchings of <= 600 points (~20-30 ms). ``diagnostics["seconds"]`` and
``["cpu_seconds"]`` hold the sub-step times; ``collect_seconds()`` sums them over every call in a
block (profiling).
"""
from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass

import numpy as np

from sparseart.geometry.transforms import (
    apply_transform,
    make_transform,
    transform_from_prismatic,
    transform_from_revolute,
)
from sparseart.joints.cache import LRUCache
from sparseart.joints.config import BUDGETS, UNCERTAINTY_FLOOR, FitConfig
from sparseart.joints.models import initial_models
from sparseart.joints.noise_floor import residual_floor
from sparseart.joints.optimise import ModelFit, fit_model
from sparseart.joints.part import MIN_POINTS, PartData, fingerprint, prepare_part
from sparseart.joints.reliability import (
    ILL_CONDITIONED,
    MAX_AXIS_SIGMA_DEG,
    MAX_RELATIVE_SIGMA,
    MAX_SCATTER_FRACTION,
    MIN_INLIER_FRACTION,
    FitWarning,
    confidence,
    covered_fraction,
    prismatic_warnings,
    reliability_warnings,
    revolute_warnings,
    shape_warnings,
)
from sparseart.joints.seeds import initial_motion
from sparseart.joints.select import choose_type, type_test_angle_sigma
from sparseart.joints.uncertainty import (
    add_frame_sigma,
    floor_covariance,
    frame_turn,
    half_sample_covariance,
    prismatic_sigma,
    resample_covariance,
    revolute_sigma,
)
from sparseart.types import JointEstimate

__all__ = [
    "BUDGETS",
    "ILL_CONDITIONED",
    "MAX_AXIS_SIGMA_DEG",
    "MAX_RELATIVE_SIGMA",
    "MAX_SCATTER_FRACTION",
    "MIN_INLIER_FRACTION",
    "MIN_POINTS",
    "UNCERTAINTY_FLOOR",
    "FitConfig",
    "collect_seconds",
    "fit_joint",
]

SUB_STEPS = ("prepare", "seeds", "optimise", "select", "uncertainty", "reliability")
_sinks: list[dict] = []


@contextmanager
def collect_seconds() -> Iterator[dict]:
    """Within the block, every ``fit_joint`` call adds its sub-step wall seconds (``SUB_STEPS``),
    CPU seconds ("cpu." + step) and a "calls" count to the yielded dict."""
    sink: dict = defaultdict(float)
    _sinks.append(sink)
    try:
        yield sink
    finally:
        _sinks.remove(sink)


class _Clock:
    """Wall and CPU seconds per sub-step (the machine may be shared: CPU is the steadier measure)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self.last, self.last_cpu = time.perf_counter(), time.process_time()

    def lap(self, name: str) -> None:
        now, now_cpu = time.perf_counter(), time.process_time()
        self.seconds[name] = self.seconds.get(name, 0.0) + now - self.last
        self.cpu[name] = self.cpu.get(name, 0.0) + now_cpu - self.last_cpu
        self.last, self.last_cpu = now, now_cpu


@dataclass
class _Fitted:
    """Everything of one fit before its stated uncertainty: the chosen type, the model fits and
    their diagnostics. Remembered per (part, seed, type, config) -- a pure function of them."""

    chosen: str
    fits: dict[str, ModelFit]
    diagnostics: dict


FITTED_CACHE_SIZE = 16
_fitted: LRUCache[_Fitted] = LRUCache(FITTED_CACHE_SIZE)


def fit_joint(
    start_points: np.ndarray,
    end_points: np.ndarray,
    joint_type: str = "auto",
    initial_transform: np.ndarray | None = None,
    start_colors: np.ndarray | None = None,
    end_colors: np.ndarray | None = None,
    config: FitConfig | None = None,
    uncertainty: bool = True,
    start_confidence: np.ndarray | None = None,
    end_confidence: np.ndarray | None = None,
    frame_error: tuple[float, float] | None = None,
    slide_axis: np.ndarray | None = None,
) -> JointEstimate:
    """Fit the joint that moves a part from ``start_points`` to ``end_points``.

    start_points (N, 3), end_points (M, 3): float64 points of the same rigid part in the two
    states, in one frame (any units; partial views allowed; correspondence not needed).
    joint_type: "auto" | "revolute" | "prismatic". initial_transform: optional (4, 4) start -> end
    rigid guess in the same frame (e.g. from the labeler). Colours (N, 3)/(M, 3) in [0, 1] help
    the initial registration only. config: ``FitConfig`` (``FitConfig.for_budget(name)``).
    uncertainty: False skips the resampling terms of the stated sigma (jackknife, half-samples:
    ~20 % of a call) -- for candidate fits a search may discard; the sigma is then the Jacobian
    + floor part only and ``diagnostics["uncertainty_complete"]`` is False.
    start_confidence (N,) / end_confidence (M,): optional per-point depth confidences in [0, 1];
    matched pairs are weighted by sqrt(c_start c_end) (``FitConfig.confidence_weights``,
    ``part.prepare_part``); None or all ones fits exactly as without them. Calling again with the
    same arrays, seed, type and config and ``uncertainty=True`` reuses the remembered model fits
    and pays only the uncertainty step.
    frame_error: optional (misfit, static radius), input units, of
    ``uncertainty.frame_misfit``: how far the static part's two states disagree. The frame's
    turn (misfit / radius, rad) joins the angle sigma of the type test (a slide in a warped frame
    shows a rotation of that size) and the stated uncertainty (``uncertainty.add_frame_sigma``;
    the part before it in ``diagnostics["uncertainty_before_frame"]``), so the reliability
    warnings and the confidence see it. None or a zero misfit: the states agree.
    slide_axis: (3,) direction, input frame: a prismatic fit held to it (only the distance is
    fitted; requires ``joint_type="prismatic"``). The axis then has no Jacobian or resampling
    variance -- what the caller knows of the direction's own error must be added to the stated
    sigma by the caller.
    Returns a ``JointEstimate`` in the input frame and units: angle >= 0 radians (axis oriented
    accordingly) or distance >= 0; uncertainty 1-sigma including systematic effects (step 5 of
    the module docstring); warnings for unreliable estimates (step 6, codes in
    ``diagnostics["warning_codes"]``); diagnostics hold both models' BIC scores, Jacobian
    condition numbers, the parts of the uncertainty, the inlier fraction, sizes and
    ``diagnostics["seconds"]`` / ``["cpu_seconds"]`` per sub-step.
    Cost: see the module docstring; repeated calls on the same arrays and config share step 1.
    Raises ValueError for fewer than 5 finite points per state, coincident points or a bad type.
    """
    config = config or FitConfig()
    if joint_type not in ("auto", "revolute", "prismatic"):
        raise ValueError(f"fit_joint: joint_type must be auto, revolute or prismatic, got {joint_type!r}")
    if slide_axis is not None:
        slide_axis = np.asarray(slide_axis, dtype=np.float64).reshape(-1)
        if joint_type != "prismatic" or slide_axis.shape != (3,) or not np.all(np.isfinite(slide_axis)) \
                or np.linalg.norm(slide_axis) < 1e-12:
            raise ValueError("fit_joint: slide_axis must be a finite non-zero (3,) direction, with joint_type "
                             "'prismatic'")
        slide_axis = slide_axis / np.linalg.norm(slide_axis)
    clock = _Clock()
    part = prepare_part(start_points, end_points, config, start_confidence=start_confidence,
                        end_confidence=end_confidence)
    _check_colours(start_colors, part.input_counts[0], "start_points")
    _check_colours(end_colors, part.input_counts[1], "end_points")
    clock.lap("prepare")
    key = None
    if part.key is not None:
        seed_key = (fingerprint(np.asarray(initial_transform, dtype=np.float64)) if initial_transform is not None
                    else tuple(None if c is None else fingerprint(np.asarray(c)) for c in (start_colors, end_colors)))
        key = (part.key, seed_key, joint_type, frame_error,
               None if slide_axis is None else fingerprint(slide_axis))
    fitted = _fitted.get(key) if key is not None else None
    if fitted is None:
        fitted = _fit_models(part, joint_type, initial_transform, start_colors, end_colors, config, clock,
                             turn=frame_turn(*frame_error) if frame_error is not None else 0.0,
                             slide_axis=slide_axis)
        if key is not None:
            _fitted.put(key, fitted)
    diagnostics: dict = {"scale": part.scale, "n_start": len(part.start), "n_end": len(part.end),
                         "n_start_input": part.input_counts[0], "n_end_input": part.input_counts[1],
                         "config": asdict(config), **fitted.diagnostics}
    fit = fitted.fits[fitted.chosen]
    covariances = _uncertainty(fit, part, config, diagnostics, resample=uncertainty)
    clock.lap("uncertainty")
    estimate = _estimate(fit, part, covariances, config, diagnostics, frame_error)
    clock.lap("reliability")
    estimate.diagnostics["uncertainty_complete"] = bool(uncertainty)
    estimate.diagnostics["seconds"] = dict(clock.seconds)
    estimate.diagnostics["cpu_seconds"] = dict(clock.cpu)
    estimate.diagnostics["uncertainty_seconds"] = clock.seconds["uncertainty"]
    for sink in _sinks:
        for name, seconds in clock.seconds.items():
            sink[name] += seconds
            sink[f"cpu.{name}"] += clock.cpu[name]
        sink["calls"] += 1
    return estimate


def _fit_models(part: PartData, joint_type: str, initial_transform: np.ndarray | None,
                start_colors: np.ndarray | None, end_colors: np.ndarray | None, config: FitConfig,
                clock: _Clock, turn: float = 0.0, slide_axis: np.ndarray | None = None) -> _Fitted:
    """Steps 2-4 of the module docstring: seed -> model fit(s) -> type choice (the rotation judged
    against the static frame's turn ``turn``, rad); ``slide_axis``: the prismatic model held to
    that direction (normalisation only shifts and scales, so it is the same direction there)."""
    diagnostics: dict = {} if slide_axis is None else {"slide_axis_held": True}
    initial, seed_info = initial_motion(part, initial_transform, start_colors, end_colors, config)
    revolute_init, prismatic_init, screw_info = initial_models(initial, part.start, slide_axis)
    diagnostics.update(seed_info)
    diagnostics.update(screw_info)
    clock.lap("seeds")
    fits: dict[str, ModelFit] = {}
    if joint_type in ("auto", "revolute"):
        fits["revolute"] = fit_model(revolute_init, part, config)
    if joint_type in ("auto", "prismatic"):
        fits["prismatic"] = fit_model(prismatic_init, part, config)
    clock.lap("optimise")
    if "revolute" in fits:
        revolute = fits["revolute"]
        sigma = type_test_angle_sigma(revolute, turn)
        diagnostics["revolute_pivot_factor"] = _pivot_factor(revolute, part)
        diagnostics["revolute_angle_deg"] = float(np.degrees(abs(revolute.x[4])))
        diagnostics["revolute_angle_z"] = float(abs(revolute.x[4]) / sigma) if sigma > 0 else float("inf")
    if joint_type == "auto":
        decision, type_info = choose_type(fits["revolute"], fits["prismatic"], config, turn,
                                          pivot_factor=diagnostics["revolute_pivot_factor"])
        chosen = decision.joint_type
        diagnostics.update(type_info)
    else:
        chosen = joint_type
    for kind, fit in fits.items():
        diagnostics[f"{kind}_condition"] = fit.condition
        diagnostics[f"{kind}_iterations"] = dict(fit.iterations)
    clock.lap("select")
    return _Fitted(chosen, fits, diagnostics)


def _check_colours(colors: np.ndarray | None, count: int, name: str) -> None:
    if colors is not None and np.shape(colors) != (count, 3):
        raise ValueError(f"fit_joint: colours of {name} have shape {np.shape(colors)}, expected {(count, 3)}")


def _uncertainty(fit: ModelFit, part: PartData, config: FitConfig, diagnostics: dict,
                 resample: bool = True) -> dict[str, np.ndarray]:
    """The stated covariance's parts of the chosen fit (normalised units) and the inlier
    fraction: O(R p^2) algebra on the optimum's rows, ``half_samples`` sparse matchings of
    <= ``half_sample_points`` points, O(c log W) queries. ``resample`` False: the jackknife and
    half-sample parts are zeros."""
    diagnostics["scatter_fraction"] = part.scatter
    moved = part.chamfer.start @ fit.rotation.T + fit.translation
    distance = part.end_tree.query(moved)[0]
    diagnostics["inlier_fraction"] = float(np.mean(distance <= part.inlier_radius))
    zeros = np.zeros_like(fit.covariance)
    blocks, jackknife, half = 0, zeros, zeros
    if resample:
        jackknife, blocks = resample_covariance(fit, config.uncertainty_resamples,
                                                np.random.default_rng(config.seed + 104729))
        half = half_sample_covariance(fit, part.match, config.half_samples, config.half_sample_points,
                                      np.random.default_rng(config.seed + 7919), config.normal_gate_deg,
                                      config.pair_tau_factor, config.beta)
    diagnostics["resample_blocks"] = blocks
    floor = floor_covariance(fit.kind, fit.rms_residual, part.part_radius)
    return {"jacobian": fit.covariance, "resample": jackknife, "half": half, "floor": floor}


def _pivot_factor(fit: ModelFit, part: PartData) -> float:
    """Distance of a revolute fit's axis line from the part centre, in part radii (RMS)."""
    axis, pivot, _ = fit.model.unpack(fit.x)
    offset = pivot - part.reference
    return float(np.linalg.norm(offset - (offset @ axis) * axis)) / max(part.part_radius, 1e-12)


def _estimate(fit: ModelFit, part: PartData, covariances: dict[str, np.ndarray], config: FitConfig,
              diagnostics: dict, frame_error: tuple[float, float] | None = None) -> JointEstimate:
    """Convert a normalised fit into a JointEstimate in input units, with warnings; the static
    frame's error (``frame_error``, input units) joins the stated sigma before the warnings."""
    kind, model, x = fit.kind, fit.model, fit.x
    scale, centre, reference, part_radius = part.scale, part.centre, part.reference, part.part_radius
    residual = fit.rms_residual
    noise = residual / np.sqrt(max(fit.pairs, 1))
    stated = (covariances["jacobian"] + covariances["resample"] + covariances["half"]
              + (covariances["floor"] if config.uncertainty_floor else 0.0))
    warnings: list[FitWarning] = [*part.warnings, *shape_warnings(part.principal_variances, fit.condition)]
    if kind == "revolute":
        axis, pivot, angle = model.unpack(x)
        pivot = pivot + ((reference - pivot) @ axis) * axis
        if angle < 0:
            axis, angle = -axis, -angle
        transform_n = transform_from_revolute(axis, pivot, angle)
        slide_n = float(np.mean((fit.pair_end - apply_transform(transform_n, fit.pair_start)) @ axis))
        uncertainty = revolute_sigma(stated, scale)
        sigma_parts = {f"uncertainty_{name}": revolute_sigma(covariances[name], scale)
                       for name in ("jacobian", "resample", "half", "floor")}
        warnings += revolute_warnings(angle, float(np.linalg.norm(pivot - reference)), part_radius, slide_n,
                                      max(3.0 * noise, 0.02 * part_radius), slide_n * scale, config.small_angle_deg,
                                      config.far_pivot_factor)
        origin = pivot * scale + centre
        estimate_angle, estimate_distance, slide = float(angle), None, slide_n * scale
    else:
        axis, distance = model.unpack(x)
        if distance < 0:
            axis, distance = -axis, -distance
        transform_n = transform_from_prismatic(axis, distance)
        origin_sigma = noise * scale
        uncertainty = prismatic_sigma(stated, scale, origin_sigma)
        sigma_parts = {f"uncertainty_{name}": prismatic_sigma(covariances[name], scale,
                                                              origin_sigma if name == "jacobian" else 0.0)
                       for name in ("jacobian", "resample", "half", "floor")}
        jacobian_distance_sigma = sigma_parts["uncertainty_jacobian"]["distance"] / scale
        warnings += prismatic_warnings(distance, max(jacobian_distance_sigma, noise), distance * scale)
        origin = reference * scale + centre
        estimate_angle, estimate_distance, slide = None, float(distance * scale), float(distance * scale)
    if frame_error is not None and frame_error[0] > 0:
        diagnostics["uncertainty_before_frame"] = dict(uncertainty)
        diagnostics["frame_misfit"] = {"misfit": float(frame_error[0]), "static_radius": float(frame_error[1])}
        uncertainty = add_frame_sigma(uncertainty, frame_error[0], frame_error[1], part_radius * scale,
                                      estimate_distance)
    warnings += reliability_warnings(kind, uncertainty, estimate_angle, estimate_distance,
                                     diagnostics.get("scatter_fraction", 0.0), diagnostics.get("inlier_fraction", 1.0),
                                     float(diagnostics.get("screw_angle_deg", 0.0)),
                                     diagnostics.get("revolute_pivot_factor", 0.0), config.small_angle_deg,
                                     config.far_pivot_factor)
    rotation = transform_n[:3, :3]
    transform = make_transform(rotation, scale * transform_n[:3, 3] + centre - rotation @ centre)
    floor = residual_floor(part, config)
    covered = covered_fraction(part.match.start, part.match.end, part.match.end_tree, fit.rotation, fit.translation,
                               fit.tau)
    unmoved = covered_fraction(part.match.start, part.match.end, part.match.end_tree, np.eye(3), np.zeros(3), fit.tau)
    diagnostics.update({"pairs": fit.pairs, "match_fraction": fit.match_fraction, "covered_fraction": covered,
                        "covered_unmoved": unmoved, "match_points": [len(part.match.start), len(part.match.end)],
                        "condition": fit.condition,
                        "residual_floor": floor * scale,
                        "part_radius": part_radius * scale, "warning_codes": [w.code.value for w in warnings],
                        **sigma_parts})
    return JointEstimate(type=kind, axis=axis.copy(), origin=origin, angle=estimate_angle, distance=estimate_distance,
                         transform=transform, uncertainty=uncertainty, residual=residual * scale,
                         confidence=confidence(covered, residual, part_radius, warnings, floor),
                         slide=slide,
                         warnings=[w.message for w in warnings], diagnostics=diagnostics)
