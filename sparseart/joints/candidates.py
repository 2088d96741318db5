"""The search over candidate joint fits of one part: the fitter (:func:`~sparseart.joints.fit.fit_joint`)
run from every seed motion (the labeler's, its tied alternatives, the mirror of a slab's best fit,
slides along the static part's principal axes), then one fit chosen and its axis uncertainty
widened when a rival slide explains the data about as well.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from sparseart.geometry.clouds import median_spacing, rms_radius, slab_axes
from sparseart.geometry.free_space import StateViews
from sparseart.geometry.planes import best_by_truncated_chamfer, hinge_turns, ransac_plane
from sparseart.geometry.sampling import random_subset
from sparseart.geometry.transforms import axis_angle_deg
from sparseart.joints.body_axes import along_body_axes, static_body_axes
from sparseart.joints.clean import estimate_normals
from sparseart.joints.fit import FitConfig, fit_joint
from sparseart.joints.free_space_check import MotionCost, check_free_space, scene_views
from sparseart.joints.reliability import HALF_TURN_DEG, MAX_AXIS_SIGMA_DEG, measurable_motion
from sparseart.joints.siblings import slides_like_siblings
from sparseart.joints.sweep_check import check_turn
from sparseart.joints.uncertainty import frame_misfit, joint_gap, raise_sigma
from sparseart.types import JointEstimate, LabelledCloud, PartLabels, PartResult, Scene

MIN_PART_POINTS = 20
SPACING_SAMPLE = 5000   # start points whose nearest neighbours give its spacing (the turn check's radius)


def fit_parts(start: LabelledCloud, end: LabelledCloud, labels: PartLabels, *, joint_type: str = "auto",
              config: FitConfig | None = None, warnings: list[str], scene: Scene | None = None) -> list[PartResult]:
    """Fit every movable part's joint (:func:`fit_part`); parts with too few points get a warning
    and no joint. Then the parts are read together: a turn that a look-alike sibling's slide
    explains about as well becomes a slide along it
    (:func:`~sparseart.joints.siblings.slides_like_siblings`; only parts whose type was not given).
    Revolute origins are moved to the axis point nearest the object's median point, and a turn
    whose first steps push its part into the static part (seen in either state) is said and
    trusted less (:func:`~sparseart.joints.sweep_check.check_turn`); with the ``scene``'s depth
    images, a turn that puts its part where the cameras saw empty space gets the hinge line and
    angle the views contradict least (:func:`~sparseart.joints.free_space_check.check_free_space`).
    A joint's confidence is multiplied by the labeler's trust in its part's pairing
    (``labels.confidence``; ``diagnostics["pairing_confidence"]`` when below 1).
    A fitted motion that no motion explains as well (the states agree within the depth noise:
    :func:`~sparseart.joints.reliability.measurable_motion`) is no joint, with a warning -- unless
    the cameras saw the part move (:func:`_seen_moving`).
    The stated uncertainty gains the static frame's own error (:func:`~sparseart.joints.uncertainty.
    frame_misfit`: how far the static part's two states disagree beyond their sampling).
    Returns one :class:`PartResult` per part of ``labels``; appends warnings prefixed by the part."""
    object_centre = np.median(start.points, axis=0)
    static_mask = labels.start_part == 0
    static_points = start.points[static_mask] if static_mask.sum() >= MIN_PART_POINTS else None
    # What a hinge can be attached to: every start point on no movable part (the static part and
    # the unassigned points, e.g. a base the closed lid hides in the other state).
    movable = [p.id for p in labels.parts if p.role == "movable"]
    support_mask = ~np.isin(labels.start_part, movable)
    support_points = start.points[support_mask] if support_mask.sum() >= MIN_PART_POINTS else None
    body_axes = static_body_axes(static_points)
    # how far the static part's two states disagree beyond sampling: the joint's frame error
    frame_error = frame_misfit(start.points[static_mask], end.points[labels.end_part == 0],
                               seed=(config or FitConfig()).seed)
    # both states' views for the physical test of a motion (None without depth images)
    free_space = scene_views(start, end, scene, static_mask) if labels.movable else None
    results = []
    inputs: dict[int, tuple[tuple[np.ndarray, np.ndarray], dict]] = {}   # part id -> points, fit options
    free_type: set[int] = set()
    for spec in labels.parts:
        start_mask = labels.start_part == spec.id
        end_mask = labels.end_part == spec.id
        n_points = int(start_mask.sum() + end_mask.sum())
        result = PartResult(spec=spec, n_points=n_points)
        results.append(result)
        if spec.role != "movable":
            continue
        if start_mask.sum() < MIN_PART_POINTS or end_mask.sum() < MIN_PART_POINTS:
            warnings.append(f"part {spec.id}: too few points ({int(start_mask.sum())} at start, "
                            f"{int(end_mask.sum())} at end) to fit a joint")
            continue
        part_type = joint_type if joint_type != "auto" else (spec.joint_type or "auto")
        seeds = [labels.initial_motion.get(spec.id), *labels.alternative_motions.get(spec.id, [])]
        part_points = (start.points[start_mask], end.points[end_mask])
        fit_options = dict(start_colors=start.colors[start_mask], end_colors=end.colors[end_mask], config=config,
                           start_confidence=start.confidence[start_mask],
                           end_confidence=end.confidence[end_mask], frame_error=frame_error)
        try:
            joint = fit_part(*part_points, joint_type=part_type, seeds=seeds, static_points=static_points,
                             support_points=support_points, type_prior=labels.type_prior.get(spec.id),
                             body_axes=body_axes, free_space=free_space,
                             views=(start.frame_index[start_mask], end.frame_index[end_mask]), **fit_options)
        except ValueError as error:
            warnings.append(f"part {spec.id}: joint fit failed: {error}")
            continue
        result.joint = joint
        if part_type == "auto":    # a type the labeler or the user gave stays
            free_type.add(spec.id)
        else:
            joint.diagnostics.update(type_choice=part_type, type_reason="given by the user (joint_type)"
                                     if joint_type != "auto" else "given by the part labeler")
        inputs[spec.id] = (part_points, fit_options)
    fitted = {r.spec.id: r for r in results if r.joint is not None}
    turned_to_slides = slides_like_siblings({pid: r.joint for pid, r in fitted.items()},
                                            {pid: inputs[pid][0] for pid in fitted},
                                            {pid: inputs[pid][1] for pid in fitted}, free_type, body_axes)
    for pid, joint in turned_to_slides.items():
        fitted[pid].joint = joint
    unmeasured = []
    for pid, result in fitted.items():   # the cameras' test only for motions the overlap does not measure
        reason = _unmeasured_reason(result.joint)
        if reason is not None and not _seen_moving(result.joint, inputs[pid][0], free_space):
            warnings.append(f"part {pid}: {reason}")
            unmeasured.append(pid)
    for pid in unmeasured:
        fitted.pop(pid).joint = None
    if unmeasured and not fitted:
        warnings.append("no part moved measurably between the two states: they agree within the depth noise")
    turns = any(r.joint.type == "revolute" for r in fitted.values())
    static_both = _static_tree(start, end, labels) if turns else None
    for pid, result in fitted.items():
        joint = result.joint
        if joint.type == "revolute":
            joint.origin = point_on_line_nearest(joint.origin, joint.axis, object_centre)
            if free_space is not None:
                check_free_space(joint, *inputs[pid][0], free_space)
            if static_both is not None:
                check_turn(joint, *inputs[pid][0], *static_both)
        pairing = float(labels.confidence.get(pid, 1.0))
        if pairing < 1.0:   # look-alike parts that could pair the other way round (the labeler warned)
            joint.diagnostics["pairing_confidence"] = pairing
            joint.confidence *= pairing
        warnings.extend(f"part {pid}: {w}" for w in joint.warnings)
    return results


def _seen_moving(joint: JointEstimate, points: tuple[np.ndarray, np.ndarray],
                 free_space: tuple[StateViews, StateViews] | None) -> bool:
    """Did the cameras see the part move: does standing still put clearly more of it (by
    ``VIOLATION_SLACK``) where the other state's views saw empty space than the fitted motion?
    Then the motion is measured whatever the overlap says (a handle whose round cap lands on itself
    either way, its lever alone showing the turn). False without views. O(V S)."""
    if free_space is None:
        return False
    cost = MotionCost(*points, free_space)
    return cost.violation(np.eye(4)) > cost.violation(joint.transform) + VIOLATION_SLACK


def _unmeasured_reason(joint: JointEstimate) -> str | None:
    """None when the part's fitted motion is a measurement (:func:`~sparseart.joints.reliability.
    measurable_motion`: it lays more of the part onto the other state than no motion, beyond
    sampling), else the warning that says why not (the caller drops the joint unless the cameras
    saw it move). A joint without the fit's coverage diagnostics counts as measured."""
    covered, unmoved = joint.diagnostics.get("covered_fraction"), joint.diagnostics.get("covered_unmoved")
    counts = joint.diagnostics.get("match_points")
    if covered is None or unmoved is None or counts is None or measurable_motion(covered, unmoved, *counts):
        return None
    amount = (f"{np.degrees(joint.angle):.3g} deg turn" if joint.type == "revolute"
              else f"{joint.distance:.3g} slide")
    return (f"no measurable motion, no joint: its two states agree without any motion "
            f"({100 * unmoved:.0f} % of its points on the other state) as well as under the fitted "
            f"{amount} ({100 * covered:.0f} %), i.e. within the depth noise")


def _static_tree(start: LabelledCloud, end: LabelledCloud, labels: PartLabels) -> tuple[cKDTree, float] | None:
    """A KD-tree of the static part's points of both states (scene frame) and the start cloud's
    median point spacing (one state's own sampling: the two states' static points can coincide, a
    still camera's pixels), for :func:`~sparseart.joints.sweep_check.check_turn`; None with too few
    static points. O(N log N)."""
    static = np.concatenate([start.points[labels.start_part == 0], end.points[labels.end_part == 0]])
    if len(static) < MIN_PART_POINTS:
        return None
    spacing = median_spacing(start.points, sample=SPACING_SAMPLE, rng=np.random.default_rng(0))
    return cKDTree(static), spacing


def fit_part(part_start: np.ndarray, part_end: np.ndarray, start_colors: np.ndarray, end_colors: np.ndarray,
             joint_type: str, seeds: list[np.ndarray | None], static_points: np.ndarray | None,
             config: FitConfig | None = None, support_points: np.ndarray | None = None,
             start_confidence: np.ndarray | None = None, end_confidence: np.ndarray | None = None,
             frame_error: tuple[float, float] | None = None, type_prior: str | None = None,
             views: tuple[np.ndarray | None, np.ndarray | None] = (None, None),
             body_axes: np.ndarray | None = None,
             free_space: tuple[StateViews, StateViews] | None = None) -> JointEstimate:
    """Fit one part's joint from every seed motion (the labeler's, its tied alternatives, and for
    a slab the mirror of the best fit) and keep the one :func:`choose_fit` prefers.

    part_start / part_end: (N, 3) / (M, 3) float64 points of the part, scene frame.
    frame_error: (misfit, static radius) of :func:`~sparseart.joints.uncertainty.frame_misfit`
    (scene units), passed to every :func:`fit_joint`. type_prior: the labeler's reading of the
    motion (``PartLabels.type_prior``); "prismatic" (it turned by < 2 deg) skips the hinge seed,
    a revolute hypothesis from the part's planes that a slide never needs (and that under noise
    fitted a slide as a 9.5 deg flap; ~0.14 s per part). views: the view index of each start /
    end point (:func:`along_front_normal` reads the face per view). body_axes: (3, 3) columns, the
    static body's Manhattan frame (:func:`~sparseart.joints.body_axes.static_body_axes`; None: no
    body-axis re-fits, :func:`body_axis_fits`). free_space: both states' views
    (:func:`~sparseart.joints.free_space_check.scene_views`; None: no depth images), with which
    :func:`choose_fit` drops the comparable turns the cameras contradict.
    Raises ValueError (from the fitter) when no seed gives a fit.
    """
    colours = dict(start_colors=start_colors, end_colors=end_colors, config=config,
                   start_confidence=start_confidence, end_confidence=end_confidence, frame_error=frame_error)
    calls: dict[int, tuple[str, np.ndarray | None, int]] = {}  # id(candidate) -> joint type, seed, own warnings

    def attempt(kind: str, seed: np.ndarray | None) -> JointEstimate:
        """One candidate fit without the resampling part of its sigma (paid once, for the chosen)."""
        estimate = fit_joint(part_start, part_end, joint_type=kind, initial_transform=seed, uncertainty=False,
                             **colours)
        calls[id(estimate)] = (kind, seed, len(estimate.warnings))
        return estimate

    candidates, errors = [], []
    for seed in seeds:
        try:
            candidates.append(attempt(joint_type, seed))
        except ValueError as error:
            errors.append(error)
    hinge = (hinge_seed(part_start, part_end, config.seed if config else 0)
             if joint_type != "prismatic" and type_prior != "prismatic" else None)
    if hinge is not None:
        try:
            candidates.append(attempt("revolute", hinge))
        except ValueError as error:
            errors.append(error)
    if not candidates:
        raise errors[0]
    face_slide = (face_slide_seed(part_start, part_end, config.seed if config else 0, *views)
                  if joint_type != "revolute" and all(c.type == "revolute" for c in candidates) else None)
    if face_slide is not None:
        try:
            candidates.append(attempt("prismatic", face_slide))
        except ValueError as error:
            errors.append(error)
    if joint_type != "revolute" and not any(c.type == "prismatic" for c in candidates):
        detached = []
        for slide_seed in detached_slide_seeds(candidates, part_start, part_end, static_points):
            try:
                detached.append(attempt("prismatic", slide_seed))
            except ValueError as error:
                errors.append(error)
        # a slide far worse than the turns explains nothing they do not (a door's points away from its hinge)
        turns = min(c.residual for c in candidates)
        candidates.extend(f for f in detached if f.residual <= COMPARABLE_RESIDUAL_RATIO * turns)
    best = min(candidates, key=lambda c: c.residual)
    mirrored = mirror_seed(best, part_start)
    if mirrored is not None and joint_type != "prismatic":
        try:   # any type: the mirror of a half-turn of a symmetric slab is a slide
            candidates.append(attempt(joint_type, mirrored))
        except ValueError:
            pass
    slide_fits = []
    for slide_seed in static_axis_seeds(best, static_points):
        try:
            seeded = attempt("prismatic", slide_seed)
        except ValueError:
            continue
        slide_fits.append(seeded)
        if seeded.residual < STATIC_AXIS_MIN_GAIN * best.residual:
            seeded.warnings.append("slide re-fitted from the static part's axis: the first fit was a local "
                                   "minimum (repeated structure?)")
            candidates.append(seeded)
    candidates.extend(body_axis_fits(best, body_axes, lambda seed: attempt("prismatic", seed)))
    violation = MotionCost(part_start, part_end, free_space).violation if free_space is not None else None
    chosen = choose_fit(without_half_turns(plausible_fits(candidates, config or FitConfig(), part_start)), part_start,
                        support_points if support_points is not None else static_points, violation)
    # The chosen fit again with its full sigma: fit_joint remembers the model fits of these
    # arrays, seed and type, so only the uncertainty step runs (the point estimate is the same).
    kind, seed, own = calls[id(chosen)]
    complete = fit_joint(part_start, part_end, joint_type=kind, initial_transform=seed, **colours)
    complete.warnings.extend(chosen.warnings[own:])     # what the choice among candidates added
    explain_type(complete, candidates)
    widen_for_rival_slides(complete, [c for c in candidates + slide_fits if c is not chosen])
    widen_for_tied_hinges(complete, chosen.diagnostics.get("tied_hinge"))
    return along_front_normal(complete, part_start, part_end, colours, config.seed if config else 0, *views)


def explain_type(joint: JointEstimate, candidates: list[JointEstimate]) -> None:
    """Give ``joint`` a ``type_reason`` (and ``type_choice``) when its own fit did not run the type
    test (a seed fitted as one type only): the test's reading of the best candidate that chose the
    same type, else the residuals of the best candidates of each type. In place. O(C)."""
    if joint.diagnostics.get("type_choice") == joint.type:
        return
    tested = sorted((c for c in candidates if c.diagnostics.get("type_choice") == joint.type),
                    key=lambda c: c.residual)
    if tested:
        joint.diagnostics.update({k: tested[0].diagnostics[k] for k in
                                  ("bic_revolute", "bic_prismatic", "type_reason", "type_choice", "angle_significant")
                                  if k in tested[0].diagnostics})
        return
    others = [c.residual for c in candidates if c.type != joint.type]
    other = "prismatic" if joint.type == "revolute" else "revolute"
    joint.diagnostics["type_reason"] = (
        f"the {joint.type} candidates fit best (residual {joint.residual:.3g}"
        + (f", the best {other} {min(others):.3g})" if others else f"; no {other} candidate)"))
    joint.diagnostics["type_choice"] = joint.type


RIVAL_SLIDE_RESIDUAL_RATIO = 1.1  # another slide fitting this close to the chosen one is a rival ...


RIVAL_SLIDE_MIN_DEG = 10.0        # ... when its axis is at least this far off


def widen_for_rival_slides(chosen: JointEstimate, fits: list[JointEstimate]) -> None:
    """A prismatic fit whose data a slide >= ``RIVAL_SLIDE_MIN_DEG`` away explains about as well
    (residual within ``RIVAL_SLIDE_RESIDUAL_RATIO``) is ambiguous, whatever its local curvature
    says: its axis sigma is raised to the angle between them, with a warning. Measured: an
    oven rack whose chosen slide was 18 deg off had a rival 18 deg away at +5 % residual and a
    local sigma of 0.7 deg. Modifies ``chosen`` in place. O(F)."""
    if chosen.type != "prismatic":
        return
    rivals = [f for f in fits if f is not chosen and f.type == "prismatic"
              and f.residual <= RIVAL_SLIDE_RESIDUAL_RATIO * chosen.residual]
    if not rivals:
        return
    angles = [axis_angle_deg(f.axis, chosen.axis) for f in rivals]
    widest = max(angles)
    if widest < RIVAL_SLIDE_MIN_DEG:
        return
    rival = rivals[int(np.argmax(angles))]
    chosen.uncertainty["axis_deg"] = max(float(chosen.uncertainty.get("axis_deg", 0.0)), widest)
    chosen.warnings.append(f"another slide direction {widest:.1f} deg away fits almost as well (residual "
                           f"{100.0 * (rival.residual / chosen.residual - 1.0):+.0f} %): the axis is "
                           f"ambiguous (repeated structure?); axis uncertainty raised to {widest:.1f} deg")


STATIC_AXIS_SEED_MIN_DEG = 2.0  # a static principal axis this close to the fitted slide adds nothing


# A static-axis-seeded slide replaces the first fit only when its residual is this much lower: on
# flat faces (drawer fronts) in-plane tilts of +-6 deg change the residual by < 2 % (noise), while
# the aliased rack minima were 15-22 % worse than the seeded ones (oven_7179_multi, 2026-11-23).
STATIC_AXIS_MIN_GAIN = 0.9


def static_axis_seeds(joint: JointEstimate, static_points: np.ndarray | None) -> list[np.ndarray]:
    """Extra (4, 4) start->end seeds for a prismatic fit: the same slide length along each
    principal axis of the static part (sign towards the fitted slide).

    Why: a part with repeated structure (a wire rack, a grille) matches itself after a sideways
    shift by one period, so the slide fit has local minima tilted in the part's plane (measured:
    oven racks 16-18 deg off). Slides in furniture mostly follow the body's own axes, so these
    seeds start the fit in the right basin; a seeded fit is kept only when its residual is
    ``STATIC_AXIS_MIN_GAIN`` times the first fit's or lower.
    static_points (S, 3) float64, scene frame. O(S) for the 3x3 scatter; empty unless the fit is
    prismatic and the static part has >= 10 points.
    """
    if joint.type != "prismatic" or not joint.distance:
        return []
    return body_axis_slides(principal_axes(static_points), joint.axis * float(joint.distance),
                            abs(float(joint.distance)), skip_near=joint.axis)


def body_axis_fits(joint: JointEstimate, body_axes: np.ndarray | None,
                   attempt: Callable[[np.ndarray], JointEstimate]) -> list[JointEstimate]:
    """Slide fits started from the static body's axes, for a slide that runs along none of them.

    Drawers, racks and trays slide along their carcass' axes. A slide that runs along none of the
    axes of ``body_axes`` ((3, 3) columns, :func:`~sparseart.joints.body_axes.static_body_axes`;
    none within ``BODY_AXIS_WINDOW_DEG``, :func:`~sparseart.joints.body_axes.along_body_axes`) is
    fitted again from a slide of the same length along each axis (``attempt``: seed (4, 4) ->
    prismatic fit); a re-fit that stays in its axis' basin (ends nearer that axis than the first
    fit) and fits at least as well (residual <= the first fit's) is returned, to be chosen among
    the candidates. Why: a wire rack matches itself after a shift
    along its wires by any length, so under depth noise its free fit settles on a slide tilted in
    its plane (realistic oven, seed 2: 38 deg off, residual 0.0448; from the body's axis 8 deg
    off, 0.0432, ending 10.4 deg from that axis and 31 deg from the first fit). Fits within the
    window of an axis (every drawer whose front the face rule holds) are left alone, so a body
    frame read a few degrees off does not tilt them. Empty when the fit is not a slide or there is
    no frame. Up to 3 fits."""
    if joint.type != "prismatic" or not joint.distance or body_axes is None:
        return []
    if along_body_axes(joint.axis, body_axes):
        return []
    found = []
    for seed in body_axis_slides(body_axes, joint.axis * float(joint.distance), abs(float(joint.distance))):
        axis = seed[:3, 3] / np.linalg.norm(seed[:3, 3])
        try:
            fit = attempt(seed)
        except ValueError:
            continue
        if fit.residual <= joint.residual and axis_angle_deg(fit.axis, axis) < axis_angle_deg(fit.axis, joint.axis):
            fit.warnings.append(f"slide re-fitted from the static body's axis: the free fit ran "
                                f"{axis_angle_deg(joint.axis, axis):.0f} deg off it (off every body axis) "
                                f"and fitted no better")
            found.append(fit)
    return found


def principal_axes(points: np.ndarray | None) -> np.ndarray | None:
    """(3, 3) columns: the principal axes of ``points`` ((S, 3) float64); None with fewer than 10.
    O(S) for the 3x3 scatter."""
    if points is None or len(points) < 10:
        return None
    centred = points - points.mean(axis=0)
    return np.linalg.eigh(centred.T @ centred)[1]


def body_axis_slides(axes: np.ndarray | None, direction: np.ndarray, length: float,
                     skip_near: np.ndarray | None = None) -> list[np.ndarray]:
    """(4, 4) translations by ``length`` along each axis (column) of ``axes`` ((3, 3), e.g.
    :func:`principal_axes` of the static part or
    :func:`~sparseart.joints.body_axes.static_body_axes`), each pointing with ``direction`` (3,);
    axes within ``STATIC_AXIS_SEED_MIN_DEG`` of ``skip_near`` are left out. Empty without axes.
    O(1)."""
    if axes is None:
        return []
    seeds = []
    for axis in np.asarray(axes).T:
        axis = axis if float(axis @ direction) >= 0 else -axis
        if skip_near is not None and axis_angle_deg(axis, skip_near) < STATIC_AXIS_SEED_MIN_DEG:
            continue
        seed = np.eye(4)
        seed[:3, 3] = axis * length
        seeds.append(seed)
    return seeds


FRONT_MIN_SHARE = 0.6           # the part's dominant plane holds at least this share of its points in each state
FRONT_STATES_AGREE_DEG = 5.0    # ... and its normals in both states and in every view agree within this (a slide
                                # keeps it)
FRONT_VIEW_MIN_POINTS = 100     # a view's own face normal is read when it holds this many of the part's points
FRONT_OTHER_MIN_SHARE = 0.2     # in the state where the face does not dominate (an open drawer shows its box), the
                                # face's slab must still hold this share of the points (facing_plane)
FRONT_FACING_DEG = 20.0         # points whose own normal is within this of the face's place and fit its plane
FRONT_CROSSING_DEG = 60.0       # slab points whose normal is farther than this lie on a wall crossing it (the box's)
FRONT_FACING_NEIGHBOURS = 30    # neighbours of those normals' PCA (noisy depth: 12 left 8 % of a drawer's open
                                # state within 18 deg of its front's normal, 30 left 17 %)
FRONT_FACING_POINTS = 5000      # at most this many points read (random)
FRONT_FLAT_RATIO = 0.2          # a face's points spread at least this much across (second / first singular value)
FRONT_MIN_TILT_DEG = 2.0        # a free slide this close to the face normal is kept (they agree to the plane fit)
FRONT_MAX_RESIDUAL_RATIO = 1.2  # the held slide replaces the free one only when its residual is within this ratio
FRONT_MAX_TILT_DEG = 30.0       # a free slide farther from the face normal than this slides within the face
                                # (or along an oblique face: a toaster lever's, 35-37 deg, clean renders)
# A free slide whose own stated axis sigma exceeds MAX_AXIS_SIGMA_DEG (a rival slide fits as well)
# does not fix its direction: its face normal is then taken up to this tilt, beyond
# FRONT_MAX_TILT_DEG with the faces read within this looser agreement (within FRONT_MAX_TILT_DEG a
# face read this loosely is held under LOOSE_FACE_RESIDUAL_RATIO, for any slide).
UNSURE_MAX_TILT_DEG = 60.0
UNSURE_STATES_AGREE_DEG = 10.0
# Within the usual tilt window a face whose normals were read FRONT_STATES_AGREE_DEG to
# UNSURE_STATES_AGREE_DEG apart is held when its slide fits within this ratio of the free slide's
# residual (the data cannot tell the two apart; a rival slide counts alike at RIVAL_SLIDE_RESIDUAL_RATIO).
LOOSE_FACE_RESIDUAL_RATIO = 1.1


def front_normal(part_start: np.ndarray, part_end: np.ndarray, direction: np.ndarray, seed: int = 0,
                 start_views: np.ndarray | None = None, end_views: np.ndarray | None = None,
                 agree_deg: float = FRONT_STATES_AGREE_DEG) -> tuple[np.ndarray, float] | None:
    """The normal of a part's face, when both states show it alike: (unit normal (3,) oriented
    along ``direction``, the widest angle in degrees between the normals read), or None.

    The face is each state's dominant plane (:func:`~sparseart.geometry.planes.ransac_plane`,
    inlier distance ``HINGE_PLANE_SPACINGS`` point spacings); it must hold ``FRONT_MIN_SHARE`` of
    the state's points. ``start_views`` / ``end_views`` ((N,) / (M,) view index of each point):
    every view holding ``FRONT_VIEW_MIN_POINTS`` of them whose own points are that planar also
    reads the normal. When the face dominates one state only (a drawer shows its front alone
    when closed, its box when open: measured on a realistic desk drawer, front 98 % of the closed
    state's points, 24 % of the open one's, whose dominant plane is the box's bottom), the other
    state's face is read from its points facing like it (:func:`facing_plane`), fused: its views
    see too little of the face (10.8 deg off in one view of that drawer). All the normals read (a
    slide leaves the face's normal unchanged) must agree within ``agree_deg``; the
    answer is the two states' mean. Why the views:
    fused from views whose depth each carries its own smooth warp, a face is tilted by the fusion
    (measured on a realistic render of a desk drawer: its true points read 3.5 and 7.8 deg in two
    start views, 11.5 deg fused, while the fit's slide was 3.2 deg off). part_start (N, 3),
    part_end (M, 3) float64, one frame; unit-free. O((N + M) log(N + M) + V R S) for V planes of
    R RANSAC rounds over S points.
    """
    if len(part_start) < 30 or len(part_end) < 30:
        return None
    rng = np.random.default_rng(seed)

    def face(points: np.ndarray) -> np.ndarray | None:
        spacing = median_spacing(points, sample=2000, rng=rng)
        plane = ransac_plane(points, HINGE_PLANE_SPACINGS * spacing, rng)
        if plane is None:
            return None
        normal, centre = plane
        planar = np.mean(np.abs((points - centre) @ normal) < HINGE_PLANE_SPACINGS * spacing) >= FRONT_MIN_SHARE
        return normal if planar else None

    states = [face(part_start), face(part_end)]
    if states[0] is None and states[1] is None:
        return None
    weak = next((k for k in (0, 1) if states[k] is None), None)
    if weak is not None:
        states[weak] = facing_plane((part_start, part_end)[weak], states[1 - weak], rng)
        if states[weak] is None:
            return None
    read = list(states)
    for k, (points, views) in enumerate(((part_start, start_views), (part_end, end_views))):
        seen_by = np.unique(views) if views is not None and k != weak else []
        if len(seen_by) < 2:
            continue
        for view in seen_by:
            own = points[views == view]
            normal = face(own) if len(own) >= FRONT_VIEW_MIN_POINTS else None
            if normal is not None:
                read.append(normal)
    read = [n if float(n @ states[0]) >= 0 else -n for n in read]    # one orientation before comparing
    disagreement = max(axis_angle_deg(a, b) for k, a in enumerate(read) for b in read[k + 1:])
    if disagreement > agree_deg:
        return None
    mean = read[0] + read[1]
    mean /= np.linalg.norm(mean)
    return (mean if float(mean @ direction) >= 0 else -mean), float(disagreement)


def face_slide_seed(part_start: np.ndarray, part_end: np.ndarray, seed: int = 0,
                    start_views: np.ndarray | None = None,
                    end_views: np.ndarray | None = None) -> np.ndarray | None:
    """A slide seed for a part all of whose fits turn, when its face kept its normal: a (4, 4)
    translation along the face normal of :func:`front_normal` by the shift of the face along it
    (:func:`face_offset` of each state); None when the part has no such face (a turned face
    changes its normal by the turn).

    Why: a drawer seen front-only when closed and box-first when open can be registered with a
    turn laying its front onto its box's bottom (measured on a realistic desk drawer: every seed
    motion of one run turned by 85-97 deg, the fits followed, residual 0.028; a slide fits it at
    0.021). A face that keeps its normal did not turn; the slide is fitted beside the turns and the
    residual decides. O(:func:`front_normal`)."""
    shift = part_end.mean(axis=0) - part_start.mean(axis=0)
    if not np.any(shift):
        return None
    front = front_normal(part_start, part_end, shift, seed, start_views, end_views)
    if front is None:
        return None
    rng = np.random.default_rng(seed)
    slide = np.eye(4)
    slide[:3, 3] = front[0] * (face_offset(part_end, front[0], rng) - face_offset(part_start, front[0], rng))
    return slide


def face_offset(points: np.ndarray, normal: np.ndarray, rng: np.random.Generator,
                distance: float | None = None) -> float:
    """Where along ``normal`` the points (N, 3) hold their densest slab 2 x ``distance`` thick: the
    median height of its points (default distance ``HINGE_PLANE_SPACINGS`` point spacings). A face
    across the normal is such a slab; walls along it (a drawer's box) spread out. O(N log N)."""
    if distance is None:
        distance = HINGE_PLANE_SPACINGS * median_spacing(points, sample=2000, rng=rng)
    heights = np.sort(points @ normal)
    ends = np.searchsorted(heights, heights + 2.0 * distance)
    first = int(np.argmax(ends - np.arange(len(heights))))
    return float(np.median(heights[first:ends[first]]))


def facing_plane(points: np.ndarray, normal: np.ndarray, rng: np.random.Generator) -> np.ndarray | None:
    """The unit normal of the plane of ``points`` (N, 3) that faces like ``normal`` (3,), or None.

    The points whose own normals (PCA of ``FRONT_FACING_NEIGHBOURS`` neighbours; at most
    ``FRONT_FACING_POINTS`` points, random) lie within ``FRONT_FACING_DEG`` of
    ``normal`` vote for the plane's offset along it (the densest slab ``HINGE_PLANE_SPACINGS``
    point spacings thick); the plane is then fitted to that slab's facing points (least squares),
    and kept when its normal is still within ``FRONT_FACING_DEG`` of ``normal``, its points
    spread in two directions (not a strip, whose plane the fit cannot fix) and the slab's points
    not on a wall crossing it (normals within ``FRONT_CROSSING_DEG``: noisy depth tilts a face's
    own normals well beyond ``FRONT_FACING_DEG``) are ``FRONT_OTHER_MIN_SHARE`` of all the
    points. Unit-free. O(S log S) for S = min(N, ``FRONT_FACING_POINTS``)."""
    if len(points) < 30:
        return None
    points = points[random_subset(len(points), FRONT_FACING_POINTS, rng)]
    alignment = np.abs(estimate_normals(points, FRONT_FACING_NEIGHBOURS) @ normal)
    facing = alignment >= np.cos(np.radians(FRONT_FACING_DEG))
    if np.count_nonzero(facing) < 10:
        return None
    distance = HINGE_PLANE_SPACINGS * median_spacing(points, sample=2000, rng=rng)
    offset = face_offset(points[facing], normal, rng, distance)
    slab = np.abs(points @ normal - offset) < distance
    members = points[slab & facing]
    on_face = slab & (alignment >= np.cos(np.radians(FRONT_CROSSING_DEG)))    # not a wall crossing the slab
    if len(members) < 10 or np.mean(on_face) < FRONT_OTHER_MIN_SHARE:
        return None
    spread = np.linalg.svd(members - members.mean(axis=0), full_matrices=False)[1:]
    found = spread[1][2]
    if spread[0][1] < FRONT_FLAT_RATIO * spread[0][0] or axis_angle_deg(found, normal) > FRONT_FACING_DEG:
        return None
    return found


def along_front_normal(joint: JointEstimate, part_start: np.ndarray, part_end: np.ndarray, fit_options: dict,
                       seed: int = 0, start_views: np.ndarray | None = None,
                       end_views: np.ndarray | None = None) -> JointEstimate:
    """A prismatic fit that slides mostly out of the part's face (within ``FRONT_MAX_TILT_DEG``
    of its normal, :func:`front_normal`) re-fitted as a slide along that normal, the distance
    alone fitted (``fit_joint(slide_axis=...)``); other fits, and fits within
    ``FRONT_MIN_TILT_DEG`` of the normal, are returned unchanged.

    Why: a face slid along its normal lays onto itself under any extra shift within its plane,
    so only the face's outline fixes that component -- and on real input the outline is what a
    hand, a depth edge smeared into the carcass or a strip of the carcass labelled with the part
    makes up. Measured on robot-shaped renders of a nightstand drawer (one view per state, a
    hand on it, no masks, 8 runs): free slides 6-30 deg off the true axis, the face normal 0.5-4
    deg (the drawer slides along its front's normal, as drawers, trays and pull-outs do); a
    sliding window or a wire rack slides within its face, 64-90 deg from the normal, and keeps
    its fit, as does a part whose face is oblique to its slide beyond ``FRONT_MAX_TILT_DEG`` (a
    toaster lever's, 35-37 deg; an oblique face within it would be pulled onto its normal).
    The held fit is kept only when its RMS residual is within ``FRONT_MAX_RESIDUAL_RATIO`` of the
    free fit's: where the data can tell the two apart, they decide (measured on robot-shaped
    renders: the drawers and a dishwasher rack the face normal put right held at 0.98-1.13 x the
    free residual; a table drawer whose labelled points carry a strip of carcass, so that the
    face read 11-13 deg off in both states, at 1.86 x -- it went 6.3 -> 12.0 deg without this test).
    A free slide whose own axis sigma is above ``MAX_AXIS_SIGMA_DEG`` (a rival slide direction
    fits as well: :func:`widen_for_rival_slides`) does not fix its direction, so the face is read
    up to ``UNSURE_STATES_AGREE_DEG`` of disagreement and taken up to ``UNSURE_MAX_TILT_DEG``
    (measured on a realistic storage drawer: free slide 35 deg off with a rival 14.6 deg away at
    +1 %, the face 33.9 deg from it with its normals 6.7 deg apart; held 6.5 deg off). Within
    the usual ``FRONT_MAX_TILT_DEG`` a face read up to ``UNSURE_STATES_AGREE_DEG`` apart is held
    too, but beyond ``FRONT_STATES_AGREE_DEG`` only when its slide fits within
    ``LOOSE_FACE_RESIDUAL_RATIO`` of the free slide's residual and the free slide tilts from it by
    more than the normals' spread: the data then cannot tell the two apart, and the drawer's
    physics can (measured on realistic renders of a table drawer: faces read 5.0 and 5.8 deg
    apart, 6.4 and 2.5 deg off, 14.5 and 10.9 deg from free slides 11.5 and 10.2 deg off, held at
    1.085 and 1.029 x). A free slide within the spread is kept: a clean desk drawer's, 0.8 deg
    off, 2.7 deg from a face read 7.2 deg apart and 1.9 deg off (2026-11-27,
    experiment EXP-050).
    The held fit's axis sigma gains the normals' disagreement (half the widest angle between
    them, in quadrature), and ``diagnostics["free_slide"]`` keeps the free fit's axis and tilt.
    ``fit_options``: the keyword arguments of the free fit (colours, config, confidences, frame
    error); ``start_views`` / ``end_views``: each point's view (:func:`front_normal`).
    O(one prismatic fit + :func:`front_normal`)."""
    if joint.type != "prismatic" or not joint.distance:
        return joint
    unsure = float(joint.uncertainty.get("axis_deg", 0.0)) > MAX_AXIS_SIGMA_DEG
    front = front_normal(part_start, part_end, joint.axis, seed, start_views, end_views, UNSURE_STATES_AGREE_DEG)
    if front is None:
        return joint
    normal, disagreement = front
    tilt = axis_angle_deg(normal, joint.axis)
    if tilt < FRONT_MIN_TILT_DEG or tilt > (UNSURE_MAX_TILT_DEG if unsure else FRONT_MAX_TILT_DEG):
        return joint
    # a face read looser than FRONT_STATES_AGREE_DEG is held only when the free slide lies outside
    # the reading's own spread and the data cannot tell the two apart (LOOSE_FACE_RESIDUAL_RATIO),
    # except beyond the usual tilt window, which is open to unsure slides only
    loose = disagreement > FRONT_STATES_AGREE_DEG and tilt <= FRONT_MAX_TILT_DEG
    if loose and tilt <= disagreement:
        return joint
    ratio = LOOSE_FACE_RESIDUAL_RATIO if loose else FRONT_MAX_RESIDUAL_RATIO
    seed_motion = np.eye(4)
    seed_motion[:3, 3] = normal * float(joint.distance) * float(np.cos(np.radians(tilt)))
    held_fit = dict(joint_type="prismatic", initial_transform=seed_motion, slide_axis=normal, **fit_options)
    try:    # without the resampling part of its sigma first: it is paid only for a held fit that is kept
        held = fit_joint(part_start, part_end, uncertainty=False, **held_fit)
    except ValueError:
        return joint
    if held.residual > ratio * joint.residual:
        return joint            # the data tell the free slide from the face's normal: keep the data's answer
    # the same fit again with its full sigma (fit_joint remembers the model fit: same point estimate)
    held = fit_joint(part_start, part_end, **held_fit)
    sigma = float(np.hypot(held.uncertainty.get("axis_deg", 0.0), disagreement / 2.0))
    held.uncertainty["axis_deg"] = sigma
    held.diagnostics["free_slide"] = {"axis": joint.axis.tolist(), "tilt_deg": float(tilt),
                                      "face_states_deg": float(disagreement), "residual": float(joint.residual),
                                      "covered_fraction": joint.diagnostics.get("covered_fraction")}
    held.warnings.append(f"slide taken along the part's face normal: the free fit tilted {tilt:.1f} deg within "
                         f"the face, which only its outline fixes (axis uncertainty {sigma:.1f} deg)")
    return held


HINGE_PLANE_SPACINGS = 4.0      # RANSAC plane inlier distance of the hinge seed, in point spacings
HINGE_MIN_TURN_DEG = 5.0        # planes closer to parallel than this: no hinge seed (a slide)
HINGE_LOSS_CLIP_SPACINGS = 3.0  # truncation of the Chamfer loss that ranks the hinge seeds


def hinge_seed(part_start: np.ndarray, part_end: np.ndarray, seed: int = 0) -> np.ndarray | None:
    """A closed-form revolute seed for a slab (door, lid): the line where the part's start and end
    planes meet, turned by theta or pi - theta (theta between the plane normals), either sign; the
    one of these four motions with the lowest truncated Chamfer loss, as a (4, 4) start->end map
    (:mod:`~sparseart.geometry.planes`).

    Why: a thin slab has several near-equal minima (the true turn, its mirror about the slab's
    mid-line, a flip about the perpendicular axis), and a fit started from a labeler's motion of
    polluted points can settle in the wrong one (measured on a real laptop capture: 174 deg found,
    96 deg true). The plane intersection pins the hinge line without any fit.
    None for parts that are not slabs, or whose planes are within ``HINGE_MIN_TURN_DEG`` of
    parallel. part_start (N, 3), part_end (M, 3) float64, one frame; unit-free (thresholds in
    point spacings). O((N + M) log(N + M) + R S) for R RANSAC rounds over S <= 5000 points.
    """
    if slab_axes(part_start) is None or len(part_end) < 10:
        return None
    rng = np.random.default_rng(seed)
    spacing = max(median_spacing(part_start, sample=2000, rng=rng), median_spacing(part_end, sample=2000, rng=rng))
    planes = [ransac_plane(points, HINGE_PLANE_SPACINGS * spacing, rng) for points in (part_start, part_end)]
    if any(plane is None for plane in planes):
        return None
    turns = hinge_turns(planes[0], planes[1], HINGE_MIN_TURN_DEG)
    if not turns:
        return None
    start_sample = part_start[rng.choice(len(part_start), min(3000, len(part_start)), replace=False)]
    end_sample = part_end[rng.choice(len(part_end), min(3000, len(part_end)), replace=False)]
    return best_by_truncated_chamfer(turns, start_sample, end_sample, HINGE_LOSS_CLIP_SPACINGS * spacing)


COMPARABLE_RESIDUAL_RATIO = 1.5  # fits within this residual ratio of the best explain the data alike


def mirror_seed(joint: JointEstimate, start_points: np.ndarray) -> np.ndarray | None:
    """A slab (door, lid) turned by theta about its hinge also maps onto its end pose by a turn of
    theta - 180 deg about its own mid-line; so does any part symmetric under a half-turn about
    the fitted axis (a drawer box) when the fit turns by ~180 deg (> ``HALF_TURN_DEG``: the twin
    is then a small turn or a slide). For a revolute fit of a slab-like part, or one turning that
    far, the (4, 4) start->end motion of that mirror solution (to seed a second fit); None otherwise."""
    if joint.type != "revolute":
        return None
    centre = start_points.mean(axis=0)
    if slab_axes(start_points) is None and np.degrees(abs(joint.angle or 0.0)) <= HALF_TURN_DEG:
        return None
    flip = np.eye(4)
    flip[:3, :3] = Rotation.from_rotvec(np.pi * joint.axis).as_matrix()
    flip[:3, 3] = centre - flip[:3, :3] @ centre
    return joint.transform @ flip


def plausible_fits(candidates: list[JointEstimate], config: FitConfig,
                   start_points: np.ndarray | None = None) -> list[JointEstimate]:
    """The candidates without the revolute fits that are slides in disguise, when a slide is among
    them. The hinge and mirror seeds are fitted as revolute only (no type test), and a revolute
    model with its two extra parameters always fits a little better; under smooth depth warps it
    then beats a correct slide with a small "flap" rotation about a pivot far outside the part
    (measured on a realistic drawer: 9.5 deg about a pivot 5.8 part radii away, residual 14 %
    below the slide's, axis 90 deg off). A revolute candidate is dropped when its angle is not
    significant against the type test's sigma (``revolute_angle_z`` < ``config.angle_z``; the
    static frame's turn included) or its pivot lies farther than ``config.far_pivot_factor`` part
    radii -- what the type test of :func:`fit_joint` would have said -- or, given the part's
    start points ((N, 3) float64, the candidates' frame), when its axis line passes farther than
    ``DETACHED_HINGE_RADII`` part radii (RMS, about the centroid) from every one of them: a
    hinge joins the part to its parent, so it touches the part (measured on the 16 realistic
    objects, seed 0: the 24 hinge fits within 0.2 radii, their mirrors within 0.35; the hinge
    seed's flaps of a realistic drawer front and a storage drawer, 12.6-13.3 deg at 5-7 % below
    the slide's residual, 2.0 and 2.9 radii away). Tried and left out (2026-11-27): keeping a
    detached turn whose residual is below 1 / 1.5 of the best slide's -- it turned three
    robot-view sliding windows from slides into turns (one success lost). O(C N)."""
    if not any(c.type == "prismatic" for c in candidates):
        return candidates
    radius = None if start_points is None else rms_radius(start_points)
    kept = [c for c in candidates if c.type != "revolute"
            or (c.diagnostics.get("revolute_angle_z", np.inf) >= config.angle_z
                and c.diagnostics.get("revolute_pivot_factor", 0.0) <= config.far_pivot_factor
                and (radius is None or hinge_reach(c, start_points, radius) <= DETACHED_HINGE_RADII))]
    return kept


DETACHED_HINGE_RADII = 1.0   # a revolute axis this many part radii clear of the part is not its hinge
# ... and offers slide seeds this far clear in both states (an oven door labelled without masks in
# one robot view lay 1.1-1.2 radii clear of its true hinge; the realistic racks the seeds put right
# 2.6 radii)
DETACHED_SEED_RADII = 1.5


def detached_slide_seeds(candidates: list[JointEstimate], part_start: np.ndarray, part_end: np.ndarray,
                         static_points: np.ndarray | None) -> list[np.ndarray]:
    """(4, 4) start->end slide seeds for a part whose every fit is a hinge that does not touch it.

    A hinge joins a part to its parent, so its axis passes through or along the part; when every
    candidate's axis passes more than ``DETACHED_SEED_RADII`` part radii clear of the part's points
    in both states (:func:`hinge_reach`), the turns are a slide's motion in disguise (a thin part's few
    points registered with a turn). :func:`fit_part` keeps the slides fitted from them only when
    one fits within ``COMPARABLE_RESIDUAL_RATIO`` of the best turn (an oven door seen without
    masks from one robot view, its points 1.2 radii clear of its hinge, turned 18 deg at 0.54 x
    the slides' residual and was right; measured slides on the realistic racks 1.16 x). The
    seeds: the shift of the part's centroid, and that shift's
    length along each principal axis of the static part (:func:`body_axis_slides`: slides follow
    the body's axes). Empty when some candidate touches the part or there is no shift.
    part_start (N, 3), part_end (M, 3), static_points (S, 3) float64, one frame. O(C N + S)."""
    if not candidates or any(c.type != "revolute" for c in candidates):
        return []
    # the distance to a hinge line is the same in both states (the turn keeps it): clear in both
    radii = (rms_radius(part_start), rms_radius(part_end))
    if min(hinge_reach(c, points, radius) for c in candidates
           for points, radius in zip((part_start, part_end), radii)) <= DETACHED_SEED_RADII:
        return []
    shift = part_end.mean(axis=0) - part_start.mean(axis=0)
    length = float(np.linalg.norm(shift))
    if not length > 0:
        return []
    seed = np.eye(4)
    seed[:3, 3] = shift
    return [seed, *body_axis_slides(principal_axes(static_points), shift, length)]


def hinge_reach(candidate: JointEstimate, points: np.ndarray, radius: float) -> float:
    """Distance from the candidate's axis line to the nearest of ``points`` ((N, 3) float64, the
    candidate's frame), in units of ``radius`` (the points' :func:`~sparseart.geometry.clouds.rms_radius`; unit-free). O(N)."""
    offsets = points - candidate.origin
    across = offsets - np.outer(offsets @ candidate.axis, candidate.axis)
    return float(np.sqrt(np.min(np.sum(across ** 2, axis=1))) / max(radius, 1e-12))


def without_half_turns(candidates: list[JointEstimate]) -> list[JointEstimate]:
    """The candidates without the revolute fits that turn by more than ``HALF_TURN_DEG``, when
    one of the others explains the data nearly alike (residual within ``HALF_TURN_RESIDUAL_RATIO``
    of the best). A symmetric part (a drawer front, a lid) maps onto itself under a half-turn, so a
    slide or a small turn has a twin turning by ~180 deg that fits as well; real joints of
    furniture and appliances turn by less (the 21 rendered joints: 37-75 deg, the real laptop 96
    deg). Measured: an unposed twin-drawer cabinet's drawer fitted as a 180 deg turn (axis 90 deg
    off) beside its slide. The half-turns go also when the best fit turns less: otherwise
    :func:`choose_fit`'s tie-break among comparable hinges may still pick one (a door opened by
    28 deg and its mirror turn of 155 deg about the door's mid-line, which lies nearer the oven's
    front than the hinge: measured on a realistic oven, 155 deg chosen over the 25 deg fit of
    lower residual). Unchanged when nothing smaller is comparable. O(C)."""
    best = min(candidates, key=lambda c: c.residual)
    smaller = [c for c in candidates if not _half_turn(c)]
    if len(smaller) == len(candidates) or not smaller:
        return candidates
    if min(c.residual for c in smaller) > HALF_TURN_RESIDUAL_RATIO * best.residual:
        return candidates
    return smaller


# A turn of less than HALF_TURN_DEG replaces a half-turn fitting up to this many times better: the
# corpus's true turns are all below 100 deg, and a symmetric part's flip (a bucket's U-shaped wire
# handle turned over about its bisector) lays the part on itself better than its true turn seen
# from one side (measured: a bucket handle's 180 deg flip at 0.40 of the residual of its 90 deg turn).
HALF_TURN_RESIDUAL_RATIO = 3.0


def _half_turn(candidate: JointEstimate) -> bool:
    return candidate.type == "revolute" and np.degrees(abs(candidate.angle or 0.0)) > HALF_TURN_DEG


def choose_fit(candidates: list[JointEstimate], start_points: np.ndarray,
               static_points: np.ndarray | None,
               violation: Callable[[np.ndarray], float] | None = None) -> JointEstimate:
    """Among fits from different seeds, keep those whose residual is within
    ``COMPARABLE_RESIDUAL_RATIO`` of the best. If the best is revolute and several comparable
    revolute fits remain, the one whose axis lies nearest the static part wins (a hinge is
    attached to its parent); otherwise the lowest residual. Measured against a tighter window
    (1.25 x; 2026-11-27, experiment EXP-043): the attachment was
    right where the residual was not on three robot-shaped microwave doors (a rival 30-34 % worse,
    or the 36.7 deg turn at 1.33 x its 143.9 deg mirror) and wrong on one realistic stapler (a
    rival 35 % worse, 25.6 deg off). When even the nearest hinge lies farther than
    ``UNATTACHED_GAP_RADII`` part radii from the static points (its surroundings unseen), the
    attachment tells nothing among the hinges about as near (within ``TIED_GAP_RATIO``): the
    lowest residual among them wins. Before the type and the attachment, with ``violation`` (a
    motion's share of the part the cameras saw through,
    :class:`~sparseart.joints.free_space_check.MotionCost`) each comparable fit contradicted by more
    than ``VIOLATION_SLACK`` beyond another is dropped -- of either type, except that a turn is
    judged only against turns the same way (angles within ``MIRROR_TURN_GAP``). Measured: a
    suitcase lid whose nearest-attached rival, 27 deg off, put 32 % of it in seen-through space,
    the lowest-residual turn 8 %; a faucet handle whose cap stays on itself, where standing still
    (a 3.5 mm slide) fitted 2 % better than the 73 deg turn and left the lever in seen-through space.
    O(C (25 log S + V S')) for C candidates."""
    best = min(candidates, key=lambda c: c.residual)
    comparable = [c for c in candidates if c.residual <= COMPARABLE_RESIDUAL_RATIO * best.residual]
    if violation is not None and len(comparable) > 1:
        # the physical test first: of motions that fit alike, those the cameras contradict clearly
        # more than another are not the motion -- a slide (or standing still) that leaves a turned
        # lever where the other state saw empty space, a hinge line beside the true one. A slab's
        # mirror (turning the other way about its mid-line) is not judged against the hinge: a
        # hinge line fitted beside the true one is contradicted until check_free_space moves it,
        # the mirror is not
        shares = {id(c): violation(c.transform) for c in comparable}

        def witnesses(c: JointEstimate, o: JointEstimate) -> bool:
            return c.type != "revolute" or o.type != "revolute" or joint_gap(c, o).get("angle", 0.0) <= MIRROR_TURN_GAP

        comparable = [c for c in comparable
                      if not any(shares[id(o)] + VIOLATION_SLACK < shares[id(c)] and witnesses(c, o) for o in comparable)]
        best = min(comparable, key=lambda c: c.residual)
    comparable = [c for c in comparable if c.type == "revolute"]
    if best.type != "revolute" or len(comparable) < 2:
        return best
    if static_points is None:
        return best
    static_tree = cKDTree(static_points)

    def axis_gap(candidate: JointEstimate) -> float:
        """Median distance from the axis line (sampled across the part) to the static points."""
        offsets = (start_points - candidate.origin) @ candidate.axis
        samples = candidate.origin + np.linspace(offsets.min(), offsets.max(), 25)[:, None] * candidate.axis
        return float(np.median(static_tree.query(samples, k=1)[0]))

    gaps = {id(c): axis_gap(c) for c in comparable}
    chosen = min(comparable, key=lambda c: gaps[id(c)])
    unattached = gaps[id(chosen)] > UNATTACHED_GAP_RADII * rms_radius(start_points)
    if unattached:
        # even the nearest hinge is far from the static points seen: the attachment cannot tell the
        # hinges about as near apart, the residual does
        chosen = min((c for c in comparable if gaps[id(c)] <= TIED_GAP_RATIO * gaps[id(chosen)]),
                     key=lambda c: c.residual)
    if chosen is not best:
        chosen.warnings.append(
            "several motions fit alike (symmetric part): no hinge axis lies on the static part seen; chose "
            "the best-fitting axis among those about as near it" if unattached else
            "several motions fit alike (symmetric part): chose the axis nearest the static part")
    tied = [c for c in comparable if c is not chosen and c.residual <= RIVAL_SLIDE_RESIDUAL_RATIO * chosen.residual
            and gaps[id(c)] <= TIED_GAP_RATIO * gaps[id(chosen)]]
    if tied:
        chosen.diagnostics["tied_hinge"] = tied_spread(chosen, tied)
    return chosen


def tied_spread(chosen: JointEstimate, rivals: list[JointEstimate]) -> dict[str, float]:
    """The widest :func:`~sparseart.joints.uncertainty.joint_gap` of the revolute ``rivals`` from
    ``chosen``, per key ("axis_deg" deg, "origin" input units, "angle" rad), over the rivals that
    turn the same way: a rival whose angle read along the chosen axis differs by more than 90 deg
    is the slab's mirror (a lid turned about its far edge the other way, 0.57 away on a clean
    laptop), a discrete alternative that no sigma describes; it widens the axis alone, as before.
    O(len(rivals))."""
    spread = {"axis_deg": 0.0, "origin": 0.0, "angle": 0.0}
    for rival in rivals:
        gap = joint_gap(chosen, rival)
        if gap.get("angle", 0.0) > MIRROR_TURN_GAP:
            gap = {"axis_deg": gap["axis_deg"]}
        for key, value in gap.items():
            spread[key] = max(spread.get(key, 0.0), value)
    return spread


MIRROR_TURN_GAP = np.pi / 2   # rad: a tied rival this far off in angle turns the other way (the slab's mirror)


VIOLATION_SLACK = 0.1   # comparable turns the cameras contradict by more than this beyond the least one drop out
TIED_GAP_RATIO = 1.25   # a rival hinge axis this close to the static part (x the chosen one's distance) is a tie
# The nearest hinge lies farther than this many part radii (RMS) from the static points: nothing it could
# be attached to is seen, and the residual breaks the tie (measured: a realistic oven's second door,
# 0.93 radii, the nearest 12 deg off at a 4 % higher residual; attached hinges 0.04 radii (a washing
# machine's door, robot view, the nearest right and a rival 3.5 % lower 4.9 deg off) and 0.38 (a box lid)).
UNATTACHED_GAP_RADII = 0.5


def widen_for_tied_hinges(chosen: JointEstimate, tied: dict[str, float] | None) -> None:
    """A revolute fit chosen over rivals that fit as well (residual within
    ``RIVAL_SLIDE_RESIDUAL_RATIO``) and whose axes lie about as near the static part (within
    ``TIED_GAP_RATIO`` of the chosen axis's distance) was picked by a tie-break the data cannot
    confirm: each of its sigma (axis, hinge line, angle) is raised to the widest gap to such a
    rival (``tied``: :func:`tied_spread`), with a warning when the axis sigma grows.
    Measured on the realistic renders (16 objects): the faucet lever, a rod-like part whose roll
    the points barely fix, had two such rivals 7.3 and 9.1 deg away and a local sigma of 2.7 deg
    (error 36 deg); the rivals the attachment rule does tell apart lie 1.6-21 x farther from the
    static part (laptop, oven and washing machine doors) and keep their sigma. A lid turned by 90
    deg, flat, fixes its hinge line only through its edges: a clean laptop's rivals lay 0.025 and
    0.05 from the chosen line at +4 and +9 % residual, the chosen one 0.016 off at a local sigma of
    0.003. In place. O(1)."""
    if not tied or chosen.type != "revolute":
        return
    widened_axis = tied["axis_deg"] > float(chosen.uncertainty.get("axis_deg", 0.0))
    raise_sigma(chosen, tied)
    if widened_axis:
        chosen.warnings.append(f"a rival hinge axis {tied['axis_deg']:.1f} deg away fits as well and lies as near "
                               f"the static part: the axis is ambiguous (a rod-like or symmetric part?); axis "
                               f"uncertainty raised to {tied['axis_deg']:.1f} deg")


def point_on_line_nearest(origin: np.ndarray, axis: np.ndarray, point: np.ndarray) -> np.ndarray:
    """The point of the line ``origin + s * axis`` nearest ``point``; all (3,) float64."""
    axis = axis / np.linalg.norm(axis)
    return origin + float(np.dot(point - origin, axis)) * axis

