"""The pipeline, one straight line of stages:

    read -> segment -> lift -> align -> label transfer -> label -> (align on static) -> fit -> refine

Each stage is a function over plain dataclasses in its own package; :func:`run` decides which
stages a scene needs and records every stage's wall time and, when skipped, why.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sparseart.align.noise import MAX_CLEAN_ROUGHNESS
from sparseart.align.static import align_on_static, polish_on_static
from sparseart.clock import StageClock
from sparseart.io.validate import validate_clouds
from sparseart.joints.candidates import fit_parts
from sparseart.joints.frame_shift import add_alignment_shift
from sparseart.joints.fit import FitConfig
from sparseart.labelers.base import PartLabeler, TooLittleToLabel
from sparseart.labelers.rules import RuleBasedLabeler, RuleLabelerConfig, has_masks
from sparseart.lift.labels import build_labelled_cloud
from sparseart.types import JOINT_TYPES, Articulation, LabelledCloud, PartLabels, Scene, SceneError

if TYPE_CHECKING:   # heavy (onnxruntime / torch) option types, imported only by the stages using them
    from sparseart.lift.onnx_model import OnnxLiftOptions
    from sparseart.refine.api import RefineOptions

MIN_STATE_POINTS = 20
# What segmenter="auto" uses when the scene has no masks: the motion split ("none"). Measured on
# the 16 shared objects without masks, the built-in image segmenter's over-segmentation (ids that
# disagree across images) gives the rule labeler spurious and missed parts far more often.
AUTO_SEGMENTER_WITHOUT_MASKS = "none"


@dataclass
class RunOptions:
    """Options of :func:`run` and :func:`run_clouds`; every stage's configuration is reachable here.

    joint_type: "auto" (classify) or a type applied to every movable part.
    reject_flying_pixels: drop depth-edge pixels when lifting.
    use_masks: transfer masks onto the points (False: the labeler splits the points by motion).
    segmenter: "auto" (the scene's masks when every image has one, else none: a motion split),
        "given", "builtin", "sam:ENCODER.onnx,DECODER.onnx" (see :func:`sparseart.segment.make_segmenter`)
        or "none" (same as ``use_masks=False``).
    model: an ONNX reconstructor (.onnx) for RGB-only scenes (see models/README.md);
        onnx_options: its options.
    matcher: a learned matcher spec for unposed scenes instead of SIFT
        (:func:`sparseart.align.matchers.open_matcher`: ``xfeat:DET.onnx,MATCHER.onnx``,
        ``xfeat:DET.onnx``, a ``sparseart-matcher/1`` JSON or a LightGlue pipeline .onnx);
        matcher_min_score: its score threshold (None = the matcher's default); threads: onnxruntime
        threads of the reconstructor and the matcher (0 = its default).
    labeler_config: the default rule labeler's configuration (ignored when a labeler is passed).
    fit: the joint fitter's configuration.
    seed: random seed of every sampling step (RANSAC, ICP, labeler, fitter, refinement): results
        are deterministic for a seed; it overrides the seeds inside the stage configurations.
    refine: run the SPLART refinement (needs torch and the scene's images); refine_options: its options.
    second_opinion: without masks, label and fit again with another seed and mark the joints that
        change (:mod:`sparseart.joints.second_opinion`; about doubles the labelling time).
    """

    joint_type: str = "auto"
    reject_flying_pixels: bool = True
    use_masks: bool = True
    segmenter: str = "auto"
    model: str | Path | None = None
    onnx_options: OnnxLiftOptions | None = None
    matcher: str | Path | None = None
    matcher_min_score: float | None = None
    threads: int = 0
    labeler_config: RuleLabelerConfig | None = None
    fit: FitConfig | None = None
    seed: int = 0
    refine: bool = False
    refine_options: RefineOptions | None = None
    second_opinion: bool = True


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
    from sparseart.align.scene import align_scene
    from sparseart.lift.scene_lift import lift_scene

    options = _options(options, overrides)
    clock = StageClock()
    if not isinstance(scene, Scene):
        from sparseart.io.scene import load_scene

        with clock.stage("read", "scene folder"):
            scene = load_scene(scene, require_depth=options.model is None)
    scene = _segment(scene, options, clock)
    if _segmenter_spec(scene, options) != "none" and not scene.has_masks:   # fragmented masks dropped
        options = replace(options, use_masks=False)
    with clock.stage("lift", _lift_reason(scene, options)):
        lifted = lift_scene(scene, reject_flying_pixels=options.reject_flying_pixels, model=options.model,
                            onnx_options=options.onnx_options)
    for name, seconds in lifted.seconds.items():
        clock.add(f"lift.{name}", seconds, _SUBSTAGE_WHY[name])
    if options.model is None:
        clock.skip("reconstruct", "depth given: the ONNX reconstructor is not needed")
    matcher = _open_matcher(options) if lifted.frame in ("views", "states") and options.matcher else None
    if lifted.frame in ("views", "states"):
        with clock.stage("align", _align_reason(lifted.frame)):
            aligned = align_scene(scene, lifted, seed=options.seed, matcher=matcher)
    else:
        clock.skip("align", _align_reason(lifted.frame))
        aligned = align_scene(scene, lifted, seed=options.seed)
    for name, seconds in aligned.seconds.items():
        clock.add(f"align.{name}", seconds, _SUBSTAGE_WHY[name])
    scene = aligned.scene or scene
    warnings = [*scene.warnings, *aligned.warnings]
    if options.matcher is not None and matcher is None:
        warnings.append("--matcher not used: every image has a camera pose, so nothing is aligned")
    segmenter = _segmenter_spec(scene, options)
    start, end = (_labelled_cloud(scene, state, aligned.pointmaps[state], segmenter) for state in ("start", "end"))
    return _label_and_fit(start, end, labeler, options, clock, warnings, scene=scene,
                          alignment=aligned.alignment, frame=aligned.frame, motion_hints=aligned.motion_hints,
                          registration=aligned.registration)


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
    start, end = validate_clouds(start, end)
    options = _options(options, overrides)
    clock = StageClock()
    clock.skip("lift", "clouds given")
    frame = ("world" if aligned else "camera", "frame of the given start cloud", units)
    return _label_and_fit(start, end, labeler, options, clock, [], scene=None,
                          alignment="cameras" if aligned else "none", frame=frame)


_SUBSTAGE_WHY = {"load_model": "ONNX reconstructor: session created",
                 "reconstruct": "ONNX reconstructor: forward pass(es) and decoding",
                 "register_views": "unposed: views of each state registered to its first view",
                 "align_states": "unposed: end state aligned to the start state by feature matches",
                 "match_depth": "posed: end views checked against the start views (repeated pictures, a shared "
                                "surface), end depth matched to the start view with the same camera"}


def _label(labeler: PartLabeler, start: LabelledCloud, end: LabelledCloud, scene: Scene | None,
           **arguments) -> PartLabels:
    """``labeler.label``; a state with too little to label (:class:`~sparseart.labelers.base.
    TooLittleToLabel`: a depth map with few valid pixels, masks that leave nothing) is bad input:
    a SceneError naming that state's depth images (or its cloud when clouds were given)."""
    try:
        return labeler.label(start, end, scene, **arguments)
    except TooLittleToLabel as error:
        cloud = start if error.state == "start" else end
        if scene is None:
            raise SceneError(f"{error.state} cloud ({len(cloud)} points): {error}") from None
        frames = scene.frames(error.state)
        depths = ", ".join(f"{error.state}/depth/{f.depth_path.name}" if f.depth_path is not None
                           else f"{error.state}/rgb/{f.rgb_path.name}" for f in frames)
        raise SceneError(f"{scene.root / error.state} ({depths}): {len(cloud)} valid points in the "
                         f"{error.state} state against {len(start) + len(end) - len(cloud)} in the other: {error}; "
                         f"check the depth") from None


def _labelled_by_motion(labels: PartLabels) -> bool:
    """Did the labeler split the points by motion (no masks)?"""
    return bool(labels.diagnostics.get("motion_split", False))


class _SecondOpinion:
    """The second opinion without masks (:mod:`sparseart.joints.second_opinion`): the same clouds
    labelled and fitted again with seed + 1 (its warnings discarded), in a thread of its own
    beside the first labelling and fit, then compared with them (:meth:`apply`).

    Why a thread: it is a whole second labelling and fit, 48 % of the pipeline's time on the
    robot-1view bench (175 of 364 s over 64 scenes). Both runs spend their time in numpy, k-d
    trees and open3d, which release the GIL, and every open3d call is a pure function of its input
    (:func:`sparseart.geometry.o3d.serial`, ``seeded``), so the answer is the same bit for bit as
    one after the other; only the wall time changes. It starts before the first labelling when
    the end cloud is final there (no polish follows: cameras, a still camera, or registered on the
    static part), else right after the polish (beside the first fit)."""

    def __init__(self, start: LabelledCloud, end: LabelledCloud, scene: Scene | None, labeler: RuleBasedLabeler,
                 hints: list[np.ndarray], options: RunOptions, posed: bool | None) -> None:
        from concurrent.futures import ThreadPoolExecutor

        seed = options.seed + 1
        other = RuleBasedLabeler(replace(labeler.config, seed=seed))
        config = replace(options.fit or FitConfig(), seed=seed)

        def label_and_fit():
            labels = other.label(start, end, scene, aligned=True, motion_hints=hints, posed=posed)
            return labels, fit_parts(start, end, labels, joint_type=options.joint_type, config=config, warnings=[],
                                     scene=scene)

        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="second_opinion")
        self._future = self._pool.submit(label_and_fit)

    def apply(self, parts: list, labels: PartLabels, warnings: list[str]) -> None:
        """Wait for the second labelling and mark the joints whose counterpart differs."""
        from sparseart.joints.second_opinion import apply_second_opinion

        other_labels, other_parts = self.result()
        apply_second_opinion(parts, labels, other_parts, other_labels, warnings)

    def result(self) -> tuple[PartLabels, list]:
        """(labels, parts) of the second labelling (waits; raises what it raised)."""
        try:
            return self._future.result()
        finally:
            self._pool.shutdown(wait=True)


def _rough_depth(registration: dict | None) -> bool:
    """Whether the alignment stage measured the depth as rough (a sensor's or reconstructor's:
    ``depth_noise`` above :data:`~sparseart.align.noise.MAX_CLEAN_ROUGHNESS`). False when it was
    not measured (posed cameras, a reconstructor's joint frame)."""
    noise = (registration or {}).get("depth_noise")
    return noise is not None and float(noise) > MAX_CLEAN_ROUGHNESS


def _options(options: RunOptions | None, overrides: dict) -> RunOptions:
    options = replace(options) if options is not None else RunOptions()
    for key, value in overrides.items():
        if not hasattr(options, key):
            raise TypeError(f"unknown option {key!r}")
        setattr(options, key, value)
    if options.joint_type not in ("auto", *JOINT_TYPES):
        raise ValueError(f"joint_type must be auto, revolute or prismatic, got {options.joint_type!r}")
    return options


def _lift_reason(scene: Scene, options: RunOptions) -> str:
    if options.model is not None:
        return f"RGB only: ONNX reconstructor {Path(options.model).name}"
    if scene.posed:
        return "depth + K + cam_to_world given: unprojecting RGB-D into the world frame (no reconstructor)"
    return "depth + K given, no cam_to_world: unprojecting every view in its own camera frame"


def _align_reason(frame: str) -> str:
    return {"world": "cameras given for every image: both states are in one frame",
            "model": "the reconstructor's joint frame: polished on the static part after labelling",
            "views": "unposed: views registered within each state, then the end state to the start state",
            "states": "per-state reconstructions: end state aligned to the start state (similarity)"}[frame]


def _open_matcher(options: RunOptions):
    """The pair matcher of :func:`~sparseart.align.scene.align_scene` from ``options.matcher``."""
    from sparseart.align.matchers import LiftedMatcher, open_matcher

    return LiftedMatcher(open_matcher(options.matcher, threads=options.threads,
                                      min_score=options.matcher_min_score))


def _segmenter_spec(scene: Scene, options: RunOptions) -> str:
    """The segmenter a scene gets: "auto" = the scene's masks when every image has one, else
    ``AUTO_SEGMENTER_WITHOUT_MASKS``; ``use_masks=False`` = "none" (the labeler splits by motion)."""
    if not options.use_masks:
        return "none"
    if options.segmenter == "auto":
        return "given" if scene.has_masks else AUTO_SEGMENTER_WITHOUT_MASKS
    return options.segmenter


def _segment(scene: Scene, options: RunOptions, clock: StageClock) -> Scene:
    """The scene with a mask per image from the chosen segmenter (in place), or, when masks are
    not used, a copy without the folder's masks: no stage may lean on masks it was told to ignore
    (the registration's free-space checks read the object's outline from them)."""
    spec = _segmenter_spec(scene, options)
    if spec == "none":
        clock.skip("segment", "masks not used: parts come from a motion split")
        if not any(f.mask is not None for f in scene.all_frames):
            return scene
        return _without_masks(scene)
    if spec == "given":
        if not scene.has_masks:
            missing = next(f for f in scene.all_frames if f.mask is None)
            raise SceneError(f"{missing.rgb_path}: segmenter 'given' needs a mask for every image "
                             f"({missing.state}/mask/{missing.rgb_path.stem}.png is missing)")
        clock.skip("segment", "masks given in the scene folder")
        return _without_fragmented_masks(scene)
    from sparseart.segment import make_segmenter, segment_scene

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
    return scene


def _without_masks(scene: Scene) -> Scene:
    """A copy of the scene whose frames carry no mask (the arrays are shared, not copied)."""
    return replace(scene, start=[replace(f, mask=None, mask_path=None) for f in scene.start],
                   end=[replace(f, mask=None, mask_path=None) for f in scene.end])


def _without_fragmented_masks(scene: Scene) -> Scene:
    """The scene with its given masks unchanged, or -- when any image's masks cut the object into
    far more pieces than parts could be (:func:`sparseart.segment.base.fragmented_frames`) -- a
    copy without masks and a warning naming those images: the parts are then split by motion, as
    with ``use_masks=False`` (:func:`run` reads the missing masks so). Only the scene's own masks
    are judged: they claim to be part masks, while the built-in and SAM segmenters over-segment by
    design and their segments are merged by motion in the labeler."""
    from sparseart.segment.base import MAX_EFFECTIVE_SEGMENTS, fragmented_frames

    fragmented = fragmented_frames(scene.all_frames)
    if not fragmented:
        return scene
    named = ", ".join(f"{f.state}/mask/{f.mask_path.name if f.mask_path else f.rgb_path.stem + '.png'} "
                      f"({pieces:.0f})" for f, pieces in fragmented[:4])
    more = f" and {len(fragmented) - 4} more" if len(fragmented) > 4 else ""
    stripped = _without_masks(scene)
    stripped.warnings = [*scene.warnings,
                         f"masks not used: {named}{more} cut the object into more than "
                         f"{MAX_EFFECTIVE_SEGMENTS:.0f} pieces of similar size (effective segments), far "
                         f"more than parts; parts come from a motion split as with --no-masks"]
    return stripped


def _labelled_cloud(scene: Scene, state: str, pointmaps: list, segmenter: str) -> LabelledCloud:
    """Label transfer: the state's kept views (the first len(pointmaps) frames) -> one labelled cloud.
    With the user's masks ("given") mask-0 pixels are not the object (table, wall, a hand) and are
    left out; without masks ("none") the segments are cleared. SceneError when too few valid
    points remain."""
    cloud = build_labelled_cloud(state, scene.frames(state)[:len(pointmaps)], pointmaps,
                                 drop_background=segmenter == "given")
    if len(cloud) < MIN_STATE_POINTS:
        raise SceneError(f"{scene.root / state}: only {len(cloud)} valid 3D points after removing "
                         f"invalid, low-confidence and flying pixels")
    if segmenter == "none":
        cloud.segment[:] = -1
        cloud.segment_source.clear()
    return cloud


def _label_and_fit(start: LabelledCloud, end: LabelledCloud, labeler: PartLabeler | None,
                   options: RunOptions, clock: StageClock, warnings: list[str], scene: Scene | None,
                   alignment: str, frame: tuple[str, str, str],
                   motion_hints: list[np.ndarray] | None = None, registration: dict | None = None) -> Articulation:
    """Label the parts, finish aligning the states on the static part, fit the joints, refine.

    alignment: "cameras" (already in one frame), "still" (aligned exactly through a camera that
    did not move between the states: a known frame, no polish), "features" / "model" (roughly
    aligned: polished by ICP on the labelled static part), "none" (labelled unaligned first, then
    registered on the static part and labelled again).
    registration: the alignment stage's report (:func:`sparseart.align.scene.registration_report`).
    """
    seed = options.seed
    labeler = labeler or RuleBasedLabeler(replace(options.labeler_config or RuleLabelerConfig(), seed=seed))
    hints = list(motion_hints or [])
    if alignment == "none":
        with clock.stage("align.static", "unposed: end state registered to start through the static part"):
            first = _label(labeler, start, end, scene, aligned=False, motion_hints=[])
            end = align_on_static(start, end, first, warnings, seed=seed)
    # A trusted feature alignment of the states (static background and body matched) or a camera
    # that did not move gives a known frame as cameras do: a part that moved is kept even when no
    # static segment of the object is seen in both states (a laptop base hidden behind its open lid).
    known_frame = True if alignment in ("features", "still") else None
    polished = alignment in ("features", "model")
    wants_second = options.second_opinion and isinstance(labeler, RuleBasedLabeler)
    second = (_SecondOpinion(start, end, scene, labeler, hints, options, known_frame)
              if wants_second and not polished and not has_masks(start, end) else None)
    with clock.stage("label", f"part labeler: {labeler.name}"):
        labels = _label(labeler, start, end, scene, aligned=True, motion_hints=hints, posed=known_frame)
    if polished:
        with clock.stage("align.static", f"static part: ICP polish of the {alignment} alignment"):
            end, labels = polish_on_static(start, end, labels, warnings, seed=seed,
                                           rough_depth=_rough_depth(registration))
    if second is None and wants_second and _labelled_by_motion(labels):
        second = _SecondOpinion(start, end, scene, labeler, hints, options, known_frame)
    warnings.extend(labels.warnings)
    known_type = options.joint_type != "auto" or all(p.joint_type for p in labels.movable)
    with clock.stage("fit", "joint type given: classification skipped" if known_type
                     else "fitting revolute and prismatic, choosing by penalised residual"):
        parts = fit_parts(start, end, labels, joint_type=options.joint_type,
                          config=replace(options.fit or FitConfig(), seed=seed), warnings=warnings, scene=scene)
        add_alignment_shift(parts, registration, start, labels, scene)
    if second is not None and _labelled_by_motion(labels):
        with clock.stage("second_opinion", "no masks: labelled and fitted again with another seed, in a thread "
                         "beside the first (the seconds here: the wait after the first fit)"):
            second.apply(parts, labels, warnings)
    else:
        if second is not None:
            second.result()
        clock.skip("second_opinion", "labels from masks (or another labeler): no second labelling")
    if options.refine:
        from sparseart.refine.api import RefineOptions, refine_parts

        refine_options = replace(options.refine_options or RefineOptions(), seed=seed)
        refine_parts(start, end, labels, parts, scene, refine_options, clock, warnings)
    else:
        clock.skip("refine", "refinement not requested (--refine)")
    return Articulation(frame_kind=frame[0], frame_reference=frame[1], units=frame[2],
                        parts=parts, stages=clock.records, warnings=warnings,
                        start_cloud=start, end_cloud=end, labels=labels, registration=registration or {},
                        cameras=_cameras(scene))


def _cameras(scene: Scene | None) -> dict:
    """state -> each frame's camera by frame index (the clouds' ``frame_index``); {} without a scene."""
    if scene is None:
        return {}
    cameras: dict = {}
    for state in ("start", "end"):
        frames = scene.frames(state)
        cameras[state] = [None] * (max((f.index for f in frames), default=-1) + 1)
        for frame in frames:
            cameras[state][frame.index] = frame.camera
    return cameras
