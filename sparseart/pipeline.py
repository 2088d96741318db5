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
from .lift.labels import build_labelled_cloud
from .lift.rgbd import pointmap_from_depth
from .types import (JOINT_TYPES, Articulation, JointEstimate, LabelledCloud, PartLabels, PartResult,
                    Scene, SceneError, StageRecord)

MIN_PART_POINTS = 20


@dataclass
class RunOptions:
    """Options of :func:`run`.

    joint_type: "auto" (classify) or a type applied to every movable part.
    reject_flying_pixels: drop depth-edge pixels when lifting.
    use_masks: transfer the scene's masks onto the points (False: the labeler sees no segments).
    seed: random seed for every sub-sampling step (results are deterministic for a seed).
    refine: run the SPLART refinement (needs torch and the scene's images); refine_options: its
        :class:`~sparseart.refine.RefineOptions`.
    """

    joint_type: str = "auto"
    reject_flying_pixels: bool = True
    use_masks: bool = True
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
        scenes, else the OpenCV frame of ``start/rgb/000.png``), stage timings and warnings.

    Raises:
        SceneError: bad input, one line naming the file.
    """
    options = _options(options, overrides)
    clock = StageClock()
    if not isinstance(scene, Scene):
        from .scene import load_scene

        with clock.stage("read", "scene folder"):
            scene = load_scene(scene)
    warnings = list(scene.warnings)
    posed = scene.posed
    with clock.stage("lift", "depth + K given: unprojecting RGB-D (no reconstructor)"):
        clouds = _lift_rgbd(scene, posed, options, warnings)
    clock.skip("reconstruct", "depth given: the ONNX reconstructor is not needed")
    start, end = clouds
    if not options.use_masks:
        for cloud in (start, end):
            cloud.segment[:] = -1
            cloud.segment_source.clear()
    frame_kind = "world" if posed else "camera"
    reference = ("cameras.json world frame" if posed
                 else "OpenCV frame of start/rgb/" + scene.start[0].rgb_path.name)
    return _label_and_fit(start, end, labeler, options, clock, warnings, scene=scene, aligned=posed,
                          frame=(frame_kind, reference, "metres"))


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
    return _label_and_fit(start, end, labeler, options, clock, [], scene=None, aligned=aligned, frame=frame)


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
                   aligned: bool, frame: tuple[str, str, str]) -> Articulation:
    if labeler is None:
        from .labelers.rules import RuleBasedLabeler

        labeler = RuleBasedLabeler()
    if aligned:
        clock.skip("align", "cameras given for every image: both states are in one frame")
        with clock.stage("label", f"part labeler: {labeler.name}"):
            labels = labeler.label(start, end, scene, aligned=True)
    else:
        with clock.stage("align", "unposed: end state registered to start through the static part"):
            first = labeler.label(start, end, scene, aligned=False)
            end = _align_on_static(start, end, first, warnings)
        with clock.stage("label", f"part labeler: {labeler.name} (after alignment)"):
            labels = labeler.label(start, end, scene, aligned=True)
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


def _lift_rgbd(scene: Scene, posed: bool, options: RunOptions,
               warnings: list[str]) -> tuple[LabelledCloud, LabelledCloud]:
    clouds = []
    for state in ("start", "end"):
        frames = scene.frames(state)
        if not posed and len(frames) > 1:
            warnings.append(f"unposed scene: only {state}/rgb/{frames[0].rgb_path.name} is used; the "
                            f"other {len(frames) - 1} view(s) need cam_to_world to be placed")
            frames = frames[:1]
        pointmaps = [pointmap_from_depth(f, f.camera.cam_to_world if posed else np.eye(4),
                                         options.reject_flying_pixels) for f in frames]
        cloud = build_labelled_cloud(state, frames, pointmaps)
        if len(cloud) < MIN_PART_POINTS:
            raise SceneError(f"{scene.root / state}: only {len(cloud)} valid depth points after "
                             f"removing invalid and flying pixels")
        clouds.append(cloud)
    return clouds[0], clouds[1]


def _transformed(cloud: LabelledCloud, transform: np.ndarray) -> LabelledCloud:
    """The same cloud with its points moved by a (4, 4) transform (other arrays shared)."""
    return replace(cloud, points=cloud.points @ transform[:3, :3].T + transform[:3, 3])


def _align_on_static(start: LabelledCloud, end: LabelledCloud, labels: PartLabels,
                     warnings: list[str]) -> LabelledCloud:
    """Bring the end cloud into the start frame through the static part (part 0).

    The labeler's static start->end motion (identity for a still camera) seeds a robust ICP of the
    end static points onto the start static points; the end cloud is moved by its inverse.
    """
    from .joints.register import register_rigid

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
    mirror_seed = _mirror_seed(min(candidates, key=lambda c: c.residual), part_start)
    if mirror_seed is not None and joint_type != "prismatic":
        try:
            candidates.append(fit_joint(part_start, part_end, joint_type="revolute",
                                        initial_transform=mirror_seed, **colours))
        except ValueError:
            pass
    return _choose_fit(candidates, part_start, static_points)


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
