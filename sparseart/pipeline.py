"""The pipeline: scene folder -> lift -> label transfer -> align -> part labels -> joint fits.

Each stage is a plain function over dataclasses; :func:`run` decides which stages a scene needs and
records every stage's wall time and, when skipped, why.
"""
from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Iterator

import numpy as np

from .labelers.base import PartLabeler
from sparseart.bench.metrics import axis_angle_error_deg
from .lift.labels import build_labelled_cloud
from .lift.rgbd import pointmap_from_depth
from .types import (JOINT_TYPES, Articulation, JointEstimate, LabelledCloud, PartLabels, PartResult,
                    Scene, SceneError, StageRecord)

MIN_PART_POINTS = 20
# What segmenter="auto" uses when the scene has no masks: the motion split ("none"). Measured on
# the 16 shared objects without masks, the built-in image segmenter's over-segmentation (ids that
# disagree across images) gives the rule labeler spurious and missed parts far more often.
AUTO_SEGMENTER_WITHOUT_MASKS = "none"


@dataclass
class RunOptions:
    """Options of :func:`run`.

    joint_type: "auto" (classify) or a type applied to every movable part.
    reject_flying_pixels: drop depth-edge pixels when lifting.
    use_masks: transfer masks onto the points (False: the labeler sees no segments and splits
        the points by motion).
    segmenter: "auto" (the scene's masks when every image has one, else none: a motion split),
        "given", "builtin", "sam:ENCODER.onnx,DECODER.onnx" (see :func:`sparseart.segment.make_segmenter`)
        or "none" (same as ``use_masks=False``).
    model: an ONNX reconstructor (.onnx) for RGB-only scenes (see models/README.md);
        onnx_options: its :class:`~sparseart.lift.onnx_model.OnnxLiftOptions`.
    matcher: an ONNX LightGlue pipeline export (.onnx) matching the images of unposed scenes
        instead of SIFT (see :mod:`sparseart.align.lightglue`); matcher_options: its
        :class:`~sparseart.align.lightglue.LightGlueOptions`.
    seed: random seed for every sub-sampling step (results are deterministic for a seed).
    refine: run the SPLART refinement (needs torch and the scene's images); refine_options: its
        :class:`~sparseart.refine.RefineOptions`.
    """

    joint_type: str = "auto"
    reject_flying_pixels: bool = True
    use_masks: bool = True
    segmenter: str = "auto"
    model: str | Path | None = None
    onnx_options: object | None = None  # sparseart.lift.onnx_model.OnnxLiftOptions; None = its defaults
    matcher: str | Path | None = None
    matcher_options: object | None = None  # sparseart.align.lightglue.LightGlueOptions; None = defaults
    seed: int = 0
    refine: bool = False
    refine_options: object | None = None  # sparseart.refine.RefineOptions (torch); None = its defaults


class StageClock:
    """Collects :class:`StageRecord` entries."""

    def __init__(self) -> None:
        self.records: list[StageRecord] = []

    @contextmanager
    def stage(self, name: str, why: str) -> Iterator[None]:
        began = time.perf_counter()
        try:
            yield
        finally:
            self.records.append(StageRecord(name, True, time.perf_counter() - began, why))

    def skip(self, name: str, why: str) -> None:
        self.records.append(StageRecord(name, False, 0.0, why))


def run(scene: Scene | str | Path, labeler: PartLabeler | None = None,
        options: RunOptions | None = None, **overrides) -> Articulation:
    """Recover the articulation of the object in a scene.

    Args:
        scene: a scene folder (design section 2) or an already loaded :class:`Scene`.
        labeler: the part labeler; default :class:`~sparseart.labelers.RuleBasedLabeler`.
        options: :class:`RunOptions`; keyword ``overrides`` replace single fields
            (e.g. ``run(path, joint_type="revolute")``).

    Returns:
        :class:`Articulation` with per-part joints in the scene frame (world frame for posed
        RGB-D scenes, else the OpenCV frame of ``start/rgb/000.png``), stage timings and warnings.

    Raises:
        SceneError: bad input, one line naming the file (a missing or unusable model, a view that
            cannot be registered, too few valid points).
    """
    from .lift.scene_lift import lift_scene

    options = _options(options, overrides)
    clock = StageClock()
    if not isinstance(scene, Scene):
        from sparseart.io.scene import load_scene

        with clock.stage("read", "scene folder"):
            scene = load_scene(scene, require_depth=options.model is None)
    _segment(scene, options, clock)
    with clock.stage("lift", _lift_reason(scene, options)):
        lifted = lift_scene(scene, reject_flying_pixels=options.reject_flying_pixels, model=options.model,
                            onnx_options=options.onnx_options, seed=options.seed,
                            matcher=options.matcher, matcher_options=options.matcher_options)
    for name, seconds in lifted.seconds.items():
        clock.records.append(StageRecord(f"lift.{name}", True, seconds, _SUBSTAGE_WHY.get(name, name)))
    if options.model is None:
        clock.skip("reconstruct", "depth given: the ONNX reconstructor is not needed")
    warnings = [*scene.warnings, *lifted.warnings]
    start, end = lifted.start, lifted.end
    if _segmenter_spec(scene, options) == "none":
        for cloud in (start, end):
            cloud.segment[:] = -1
            cloud.segment_source.clear()
    return _label_and_fit(start, end, labeler, options, clock, warnings, scene=scene,
                          alignment=lifted.alignment, frame=lifted.frame, motion_hints=lifted.motion_hints)


_SUBSTAGE_WHY = {"load_model": "ONNX reconstructor: session created",
                 "reconstruct": "ONNX reconstructor: forward pass(es) and decoding",
                 "register_views": "unposed: views of each state registered to its first view",
                 "align_states": "unposed: end state aligned to the start state by feature matches"}


def _lift_reason(scene: Scene, options: RunOptions) -> str:
    if options.model is not None:
        return f"RGB only: ONNX reconstructor {Path(options.model).name}"
    if scene.posed:
        return "depth + K + cam_to_world given: unprojecting RGB-D into the world frame (no reconstructor)"
    return "depth + K given, no cam_to_world: unprojecting per camera, registering views and states"


def _segmenter_spec(scene: Scene, options: RunOptions) -> str:
    """The segmenter a scene gets: "auto" = the scene's masks when every image has one, else
    ``AUTO_SEGMENTER_WITHOUT_MASKS``; ``use_masks=False`` = "none" (the labeler splits by motion)."""
    if not options.use_masks:
        return "none"
    if options.segmenter == "auto":
        return "given" if scene.has_masks else AUTO_SEGMENTER_WITHOUT_MASKS
    return options.segmenter


def _segment(scene: Scene, options: RunOptions, clock: StageClock) -> None:
    spec = _segmenter_spec(scene, options)
    if spec == "none":
        clock.skip("segment", "masks not used: parts come from a motion split")
        return
    if spec == "given":
        if not scene.has_masks:
            missing = next(f for f in scene.all_frames if f.mask is None)
            raise SceneError(f"{missing.rgb_path}: segmenter 'given' needs a mask for every image "
                             f"({missing.state}/mask/{missing.rgb_path.stem}.png is missing)")
        clock.skip("segment", "masks given in the scene folder")
        return
    from .segment import make_segmenter, segment_scene

    try:
        segmenter = make_segmenter(spec)
    except ValueError as error:
        raise SceneError(f"--segmenter: {error}") from None
    with clock.stage("segment", f"segmenter {spec.split(':')[0]}: a mask per image"):
        try:
            segment_scene(scene, segmenter)
        except SceneError:
            raise
        except ValueError as error:
            raise SceneError(str(error)) from None


def run_clouds(start: LabelledCloud, end: LabelledCloud, labeler: PartLabeler | None = None,
               options: RunOptions | None = None, aligned: bool = True, units: str = "metres",
               **overrides) -> Articulation:
    """Recover the articulation from already lifted clouds (e.g. a robot's own point clouds).

    Args:
        start, end: :class:`LabelledCloud` of each state; (N, 3) float64 points. With
            ``aligned=True`` both are in one frame (the result's frame); otherwise the end cloud is
            registered to the start cloud through the static part first.
        labeler, options, overrides: as in :func:`run`.
    """
    options = _options(options, overrides)
    clock = StageClock()
    clock.skip("lift", "clouds given")
    frame = ("world" if aligned else "camera", "frame of the given start cloud", units)
    return _label_and_fit(start, end, labeler, options, clock, [], scene=None,
                          alignment="cameras" if aligned else "none", frame=frame)


def _options(options: RunOptions | None, overrides: dict) -> RunOptions:
    options = options or RunOptions()
    for key, value in overrides.items():
        if not hasattr(options, key):
            raise TypeError(f"unknown option {key!r}")
        setattr(options, key, value)
    if options.joint_type not in ("auto", *JOINT_TYPES):
        raise ValueError(f"joint_type must be auto, revolute or prismatic, got {options.joint_type!r}")
    return options


def _label_and_fit(start: LabelledCloud, end: LabelledCloud, labeler: PartLabeler | None,
                   options: RunOptions, clock: StageClock, warnings: list[str], scene: Scene | None,
                   alignment: str, frame: tuple[str, str, str],
                   motion_hints: list[np.ndarray] | None = None) -> Articulation:
    """Label the parts, finish aligning the states, fit the joints, refine when asked.

    alignment: "cameras" (already in one frame), "features" / "model" (roughly aligned: polished
    by ICP on the labelled static part), "none" (labelled unaligned first, then registered on the
    static part and labelled again).
    """
    if labeler is None:
        from .labelers.rules import RuleBasedLabeler

        labeler = RuleBasedLabeler()
    hints = {"motion_hints": motion_hints} if motion_hints and _accepts_hints(labeler) else {}
    if alignment == "cameras":
        clock.skip("align", "cameras given for every image: both states are in one frame")
        with clock.stage("label", f"part labeler: {labeler.name}"):
            labels = labeler.label(start, end, scene, aligned=True)
    elif alignment == "none":
        with clock.stage("align", "unposed: end state registered to start through the static part"):
            first = labeler.label(start, end, scene, aligned=False)
            end = _align_on_static(start, end, first, warnings)
        with clock.stage("label", f"part labeler: {labeler.name} (after alignment)"):
            labels = labeler.label(start, end, scene, aligned=True, **hints)
    else:
        with clock.stage("label", f"part labeler: {labeler.name} (states aligned by {alignment})"):
            labels = labeler.label(start, end, scene, aligned=True, **hints)
        with clock.stage("align", "static part: ICP polish of the " + alignment + " alignment"):
            end = _polish_on_static(start, end, labels, warnings)
    warnings.extend(labels.warnings)
    known_type = options.joint_type != "auto" or all(p.joint_type for p in labels.movable)
    with clock.stage("fit", "joint type given: classification skipped" if known_type
                     else "fitting revolute and prismatic, choosing by penalised residual"):
        parts = _fit_parts(start, end, labels, options, warnings)
    if options.refine:
        from .refine.api import refine_parts

        refine_parts(start, end, labels, parts, scene, options.refine_options, clock, warnings)
    else:
        clock.skip("refine", "refinement not requested (--refine)")
    return Articulation(frame_kind=frame[0], frame_reference=frame[1], units=frame[2],
                        parts=parts, stages=clock.records, warnings=warnings,
                        start_cloud=start, end_cloud=end, labels=labels)


def _accepts_hints(labeler: PartLabeler) -> bool:
    import inspect

    try:
        return "motion_hints" in inspect.signature(labeler.label).parameters
    except (TypeError, ValueError):
        return False


POLISH_WARN_DEG = 3.0  # an ICP polish larger than this means the feature alignment was off


def _polish_on_static(start: LabelledCloud, end: LabelledCloud, labels: PartLabels,
                      warnings: list[str]) -> LabelledCloud:
    """Refine a feature/model alignment: robust ICP of the end static points onto the start static
    points from identity; the end cloud moves by the result (per-point labels are unchanged).
    O(I N log N) for I ICP iterations over N static points."""
    from sparseart.geometry.icp import register_rigid
    from sparseart.geometry.transforms import rotation_angle

    start_static = start.points[labels.start_part == 0]
    end_static = end.points[labels.end_part == 0]
    if len(start_static) < MIN_PART_POINTS or len(end_static) < MIN_PART_POINTS:
        warnings.append("static part too small to polish the alignment of the states")
        return end
    registration = register_rigid(end_static, start_static, init=np.eye(4))
    angle = float(np.degrees(rotation_angle(registration.transform[:3, :3])))
    if registration.inlier_fraction < 0.5:
        warnings.append(f"alignment polish is weak: {registration.inlier_fraction:.0%} of the static points "
                        f"agree; kept the feature alignment")
        return end
    if angle > POLISH_WARN_DEG:
        warnings.append(f"the static part needed a {angle:.1f} deg correction after feature alignment")
    return _transformed(end, registration.transform)


def _transformed(cloud: LabelledCloud, transform: np.ndarray) -> LabelledCloud:
    """The same cloud with its points moved by a (4, 4) transform (other arrays shared)."""
    return replace(cloud, points=cloud.points @ transform[:3, :3].T + transform[:3, 3])


def _align_on_static(start: LabelledCloud, end: LabelledCloud, labels: PartLabels,
                     warnings: list[str]) -> LabelledCloud:
    """Bring the end cloud into the start frame through the static part (part 0).

    The labeler's static start->end motion (identity for a still camera) seeds a robust ICP of the
    end static points onto the start static points; the end cloud is moved by its inverse.
    """
    from sparseart.geometry.icp import register_rigid

    start_static = start.points[labels.start_part == 0]
    end_static = end.points[labels.end_part == 0]
    if len(start_static) < MIN_PART_POINTS or len(end_static) < MIN_PART_POINTS:
        warnings.append("static part too small to align the unposed states; they are used as they are")
        return end
    seed = np.linalg.inv(labels.initial_motion.get(0, np.eye(4)))
    registration = register_rigid(end_static, start_static, init=seed)
    if registration.inlier_fraction < 0.5:
        warnings.append(f"unposed alignment is weak: {registration.inlier_fraction:.0%} of the static points "
                        f"agree after registration")
    return _transformed(end, registration.transform)


def _fit_parts(start: LabelledCloud, end: LabelledCloud, labels: PartLabels, options: RunOptions,
               warnings: list[str]) -> list[PartResult]:
    object_centre = np.median(start.points, axis=0)
    static_mask = labels.start_part == 0
    static_points = start.points[static_mask] if static_mask.sum() >= MIN_PART_POINTS else None
    results = []
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
        joint_type = options.joint_type if options.joint_type != "auto" else (spec.joint_type or "auto")
        seeds = [labels.initial_motion.get(spec.id), *labels.alternative_motions.get(spec.id, [])]
        try:
            joint = _fit_part(start.points[start_mask], end.points[end_mask], start.colors[start_mask],
                              end.colors[end_mask], joint_type, seeds, static_points)
        except ValueError as error:
            warnings.append(f"part {spec.id}: joint fit failed: {error}")
            continue
        if joint.type == "revolute":
            joint.origin = _point_on_line_nearest(joint.origin, joint.axis, object_centre)
        warnings.extend(f"part {spec.id}: {w}" for w in joint.warnings)
        result.joint = joint
    return results


def _fit_part(part_start: np.ndarray, part_end: np.ndarray, start_colors: np.ndarray, end_colors: np.ndarray,
              joint_type: str, seeds: list[np.ndarray | None], static_points: np.ndarray | None) -> JointEstimate:
    """Fit one part's joint from every seed motion (the labeler's, its tied alternatives, and for
    a slab the mirror of the best fit) and keep the one :func:`_choose_fit` prefers.

    part_start / part_end: (N, 3) / (M, 3) float64 points of the part, scene frame.
    Raises ValueError (from the fitter) when no seed gives a fit.
    """
    from .joints.fit import fit_joint

    colours = dict(start_colors=start_colors, end_colors=end_colors)
    candidates, errors = [], []
    for seed in seeds:
        try:
            candidates.append(fit_joint(part_start, part_end, joint_type=joint_type, initial_transform=seed,
                                        **colours))
        except ValueError as error:
            errors.append(error)
    if not candidates:
        raise errors[0]
    best = min(candidates, key=lambda c: c.residual)
    mirror_seed = _mirror_seed(best, part_start)
    if mirror_seed is not None and joint_type != "prismatic":
        try:
            candidates.append(fit_joint(part_start, part_end, joint_type="revolute",
                                        initial_transform=mirror_seed, **colours))
        except ValueError:
            pass
    slide_fits = []
    for slide_seed in _static_axis_seeds(best, static_points):
        try:
            seeded = fit_joint(part_start, part_end, joint_type="prismatic", initial_transform=slide_seed, **colours)
        except ValueError:
            continue
        slide_fits.append(seeded)
        if seeded.residual < STATIC_AXIS_MIN_GAIN * best.residual:
            seeded.warnings.append("slide re-fitted from the static part's axis: the first fit was a local "
                                   "minimum (repeated structure?)")
            candidates.append(seeded)
    chosen = _choose_fit(candidates, part_start, static_points)
    _widen_for_rival_slides(chosen, candidates + slide_fits)
    return chosen


RIVAL_SLIDE_RESIDUAL_RATIO = 1.1  # another slide fitting this close to the chosen one is a rival ...
RIVAL_SLIDE_MIN_DEG = 10.0        # ... when its axis is at least this far off


def _widen_for_rival_slides(chosen: JointEstimate, fits: list[JointEstimate]) -> None:
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
    angles = [axis_angle_error_deg(f.axis, chosen.axis) for f in rivals]
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


def _static_axis_seeds(joint: JointEstimate, static_points: np.ndarray | None) -> list[np.ndarray]:
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
    if joint.type != "prismatic" or static_points is None or len(static_points) < 10 or not joint.distance:
        return []
    centred = static_points - static_points.mean(axis=0)
    _, axes = np.linalg.eigh(centred.T @ centred)
    slide = joint.axis * float(joint.distance)
    seeds = []
    for axis in axes.T:
        axis = axis if float(axis @ slide) >= 0 else -axis
        if axis_angle_error_deg(axis, joint.axis) < STATIC_AXIS_SEED_MIN_DEG:
            continue
        seed = np.eye(4)
        seed[:3, 3] = axis * abs(float(joint.distance))
        seeds.append(seed)
    return seeds


COMPARABLE_RESIDUAL_RATIO = 1.5  # fits within this residual ratio of the best explain the data alike
SLAB_THICKNESS_RATIO = 0.3       # smallest/middle extent below this: a slab (door, lid)


def _mirror_seed(joint: JointEstimate, start_points: np.ndarray) -> np.ndarray | None:
    """A slab (door, lid) turned by theta about its hinge also maps onto its end pose by a turn of
    theta - 180 deg about its own mid-line. For a revolute fit of a slab-like part, the (4, 4)
    start->end motion of that mirror solution (to seed a second fit); None otherwise."""
    from scipy.spatial.transform import Rotation

    if joint.type != "revolute":
        return None
    centre = start_points.mean(axis=0)
    centred = start_points - centre
    extents = np.sqrt(np.linalg.eigvalsh(centred.T @ centred / len(centred)))
    if extents[0] > SLAB_THICKNESS_RATIO * extents[1]:
        return None
    flip = np.eye(4)
    flip[:3, :3] = Rotation.from_rotvec(np.pi * joint.axis).as_matrix()
    flip[:3, 3] = centre - flip[:3, :3] @ centre
    return joint.transform @ flip


def _choose_fit(candidates: list[JointEstimate], start_points: np.ndarray,
                static_points: np.ndarray | None) -> JointEstimate:
    """Among fits from different seeds, keep those whose residual is within
    ``COMPARABLE_RESIDUAL_RATIO`` of the best. If the best is revolute and several comparable
    revolute fits remain, the one whose axis lies nearest the static part wins (a hinge is
    attached to its parent); otherwise the lowest residual. O(C (25 log S)) for C candidates."""
    from scipy.spatial import cKDTree

    best = min(candidates, key=lambda c: c.residual)
    comparable = [c for c in candidates if c.residual <= COMPARABLE_RESIDUAL_RATIO * best.residual
                  and c.type == "revolute"]
    if best.type != "revolute" or len(comparable) < 2 or static_points is None:
        return best
    static_tree = cKDTree(static_points)

    def axis_gap(candidate: JointEstimate) -> float:
        """Median distance from the axis line (sampled across the part) to the static points."""
        offsets = (start_points - candidate.origin) @ candidate.axis
        samples = candidate.origin + np.linspace(offsets.min(), offsets.max(), 25)[:, None] * candidate.axis
        return float(np.median(static_tree.query(samples, k=1)[0]))

    chosen = min(comparable, key=axis_gap)
    if chosen is not best:
        chosen.warnings.append("several motions fit alike (symmetric part): chose the axis nearest the static part")
    return chosen


def _point_on_line_nearest(origin: np.ndarray, axis: np.ndarray, point: np.ndarray) -> np.ndarray:
    """The point of the line ``origin + s * axis`` nearest ``point``; all (3,) float64."""
    axis = axis / np.linalg.norm(axis)
    return origin + float(np.dot(point - origin, axis)) * axis
