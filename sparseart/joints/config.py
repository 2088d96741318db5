"""``FitConfig``: every knob of the joint fit, and the named budgets ``fast | default | best``.

The budget trades accuracy for time in documented steps (``FitConfig.for_budget(name)``,
``BUDGETS``); ``RunOptions.budget`` selects one, ``RunOptions.seed`` becomes ``FitConfig.seed``.
Every random choice of ``sparseart.joints`` (sub-samples, spatial blocks, half-samples) is drawn
from ``FitConfig.seed``: a fit is a pure function of its inputs and its config.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace

# Calibrated floor (benchmarks/uncertainty_calibration.py): systematic errors (partial views, label
# errors, correspondence bias) tilt the axis by about this fraction of the angle the pair residual
# subtends over the part radius; added in quadrature to the statistical sigma
# (``uncertainty.floor_covariance``), and the unit of the fit's stopping rule.
UNCERTAINTY_FLOOR = 0.2


@dataclass
class FitConfig:
    """Knobs of ``fit_joint``; defaults suit parts of 1e2..1e6 points.

    Work sizes (the cost model, see ``sparseart.joints.fit``):
    max_work_points: at most this many points per state are kept (random subset) before cleaning
        and normals; beyond it the fit costs O(N) (the subset draw). The default leaves every part
        of the shared PartNet scenes at 320x240 whole (the largest have 30-60k points; a 30k cap
        moved their axes by 0.1-0.2 deg and the median from 0.28 to 0.35 deg: sampling noise,
        but the bench's numbers are measured without it).
    max_match_points: subsample per side for one-to-one (Hungarian) matching.
    max_chamfer_points: subsample per side for the Chamfer term.
    screen_points: screening sample per side (a subset of the matching sample) on which
        ``seeds.screen_seeds`` scores seed motions before any full fit. (It is not a coarse stage
        of the fit itself: a fit warm-started from a 400-point alternation settles elsewhere along
        weakly observed directions -- a flat door's in-plane tilt moved 1-8 deg.)
    Objective: chamfer_weight = alpha in ``L_align + alpha * L_CD``; beta = weight floor of revolute
        pairs; robust_loss (scipy name) and pair_tau_factor (matching clip = this x the median
        nearest distance); normal_gate_deg: pairs whose normals differ more cost the clip.
    Stopping: match_iterations = max matching / update alternations; they stop early when the
        motion moves the part by less than stop_fraction x the part's stated-uncertainty
        displacement (``UNCERTAINTY_FLOOR`` x the RMS pair residual: what the floor sigma moves a
        point at one part radius), floored at min_stop_spacing x the point spacing.
        chamfer_evaluations: residual evaluations of the final solve (finite differences included).
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
    half_samples: re-matched refits on random halves (at most half_sample_points per side),
        warm-started at the optimum, one step each (< 2: off); ~5 ms each.
    uncertainty_floor: add the calibrated systematic floor (``UNCERTAINTY_FLOOR``) to the stated sigma.
    clean: outlier / fragment removal (``clean.clean_part_points``) before fitting.
    confidence_weights: when the points come with a confidence (``fit_joint(start_confidence=,
        end_confidence=)``; the pipeline passes the labelled clouds' confidence, i.e. a scene's
        ``conf/`` maps), weight each matched pair's residual, and each Chamfer nearest-neighbour
        residual, by sqrt(c_start c_end) on top of the distance-proportional weights
        (``optimise.confidence_pair_weights``). Off by default: on 7 rendered realistic objects
        it did not help (posed median axis error 3.64 -> 3.70 deg, mean position 27 -> 29 mm;
        unposed median 3.10 -> 2.95 deg, no type change; experiment EXP-011)
        -- there the errors come from labels, partial views and per-view warps / scales, which the
        confidence does not single out. False, or no / all-one confidences, fits exactly as without.
    seed: every random choice of the fit.
    """

    max_work_points: int = 60000
    max_match_points: int = 1500
    max_chamfer_points: int = 1500
    screen_points: int = 400
    chamfer_weight: float = 0.5
    beta: float = 0.1
    match_iterations: int = 6
    chamfer_evaluations: int = 50
    stop_fraction: float = 0.25
    min_stop_spacing: float = 0.02
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
    confidence_weights: bool = False
    seed: int = 0

    @classmethod
    def for_budget(cls, name: str, **overrides) -> FitConfig:
        """The preset of a named budget (``BUDGETS``), with single fields replaced by ``overrides``.
        Raises ValueError for an unknown name or field."""
        if name not in BUDGETS:
            raise ValueError(f"budget must be one of {', '.join(BUDGETS)}, got {name!r}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise ValueError(f"FitConfig has no field(s) {', '.join(unknown)}")
        return replace(cls(**BUDGETS[name]), **overrides)


#: Named budgets, each a set of FitConfig fields (the rest keep their defaults), measured on the 16
#: shared PartNet objects (posed, 3 views, 320x240; experiment EXP-010):
#: fast -- matching and Chamfer samples of 800 points per side, 20k working points per state, no
#: half-sample refits: ~40 % less fit CPU than default; same success and type accuracy, median
#: axis error 0.47 deg instead of 0.28.
#: default -- the settings the bench accuracy (success >= 95 %, median axis <= 0.4 deg, type
#: 100 %) is measured with.
#: best -- 2500 points per side, 200k working points, 8 alternations, a tighter stop (0.1 of the
#: stated uncertainty), 80 Chamfer evaluations, 8 half-samples: ~1.7x the default's fit CPU. On the
#: rendered objects the errors are systematic (partial views, labels), so it is not measurably
#: more accurate there (median axis 0.31 vs 0.28 deg, within the run-to-run spread); it is for
#: dense real captures where 1500 points under-sample a part.
BUDGETS: dict[str, dict] = {
    "fast": {"max_work_points": 20000, "max_match_points": 800, "max_chamfer_points": 800, "half_samples": 0},
    "default": {},
    "best": {"max_work_points": 200000, "max_match_points": 2500, "max_chamfer_points": 2500, "screen_points": 500,
             "match_iterations": 8, "chamfer_evaluations": 80, "stop_fraction": 0.1, "half_samples": 8},
}
