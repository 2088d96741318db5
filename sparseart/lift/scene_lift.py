"""The lift stage of the pipeline: a scene -> the labelled clouds of both states, in one frame when possible.

Three routes, chosen by what the scene holds:

* **posed RGB-D** (depth + cam_to_world for every image): every view unprojected into the world
  frame of cameras.json; the states are aligned by construction.
* **unposed RGB-D** (depth + K, no cam_to_world): each view unprojected in its own camera frame;
  the views of a state are registered to its first view (:func:`sparseart.align.ransac.register_views`,
  rigid, metric depth) and the end state is brought into the frame of ``start/rgb/000`` by
  :func:`sparseart.align.ransac.align_states` (SIFT matches lifted to 3D, RANSAC + Umeyama).
* **RGB only** (``model`` given): an ONNX reconstructor lifts every image
  (:func:`sparseart.lift.onnx_model.lift_scene_with_model`). In "joint" mode both states come out
  in the frame of the first start camera; in "per_state" mode each state has its own frame and
  scale, and :func:`~sparseart.align.ransac.align_states` fits a similarity between them.

The result says how the states were brought together (``alignment``): "cameras" (posed),
"features" (feature alignment, to be polished on the static part after labelling), "model" (the
reconstructor's joint frame, polished likewise) or "none" (feature alignment failed; the pipeline
registers the states through the labeler's static part instead).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..types import LabelledCloud, Pointmap, Scene, SceneError
from .labels import build_labelled_cloud
from .rgbd import pointmap_from_depth

MIN_STATE_POINTS = 20


@dataclass
class LiftedScene:
    """Both states' clouds and how they were put in one frame.

    start, end: :class:`LabelledCloud`, (N, 3) float64 points in the result frame.
    alignment: "cameras" | "features" | "model" | "none" (module docstring).
    frame: (kind "world" | "camera", what defines it, units "metres" | "relative").
    motion_hints: (4, 4) start->end rigid motions in the result frame that feature alignment found
        among the matches the static similarity did not explain (candidate moving parts).
    seconds: wall seconds of the sub-steps ("reconstruct", "register_views", "align_states").
    """

    start: LabelledCloud
    end: LabelledCloud
    alignment: str
    frame: tuple[str, str, str]
    motion_hints: list[np.ndarray] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)


def lift_scene(scene: Scene, *, reject_flying_pixels: bool = True, model: str | Path | None = None,
               onnx_options=None, seed: int = 0, matcher: str | Path | None = None,
               matcher_options=None) -> LiftedScene:
    """Lift a loaded scene into two labelled clouds (masks already set on the frames).

    Args:
        scene: a loaded :class:`Scene` (``load_scene(path, require_depth=model is None)``).
        reject_flying_pixels: drop depth-edge pixels (RGB-D and depth-unprojecting models).
        model: an ONNX reconstructor (.onnx path); required when the scene has no depth.
        onnx_options: :class:`~sparseart.lift.onnx_model.OnnxLiftOptions` (None: defaults).
        seed: random seed of the RANSAC steps.
        matcher: an ONNX LightGlue pipeline export used instead of SIFT to register views and align
            the states (opened only when the scene needs alignment); matcher_options: its
            :class:`~sparseart.align.lightglue.LightGlueOptions`.

    Raises:
        SceneError (incl. ModelError, AlignmentError for a view that cannot be registered): one
        line naming the file.
    """
    needs_matcher = matcher is not None and (model is not None or not scene.posed)
    pair_matcher = _open_matcher(matcher, matcher_options) if needs_matcher else None
    if model is not None:
        lifted = _lift_with_model(scene, model, onnx_options, reject_flying_pixels, seed, pair_matcher)
    elif not scene.has_depth:
        missing = next(f for f in scene.all_frames if f.depth is None)
        raise SceneError(f"{missing.rgb_path}: no depth image and no reconstructor given "
                         f"(add {missing.state}/depth/ or run with --model MODEL.onnx)")
    elif scene.posed:
        lifted = _lift_posed_rgbd(scene, reject_flying_pixels)
    else:
        lifted = _lift_unposed_rgbd(scene, reject_flying_pixels, seed, pair_matcher)
    if matcher is not None and not needs_matcher:
        lifted.warnings.append("--matcher not used: every image has a camera pose, so nothing is aligned")
    for cloud, state in ((lifted.start, "start"), (lifted.end, "end")):
        if len(cloud) < MIN_STATE_POINTS:
            raise SceneError(f"{scene.root / state}: only {len(cloud)} valid 3D points after removing "
                             f"invalid, low-confidence and flying pixels")
    return lifted


def _open_matcher(matcher: str | Path, matcher_options):
    """A :class:`~sparseart.align.lightglue.LightGlueMatcher` (ModelError for a bad model)."""
    from sparseart.align.lightglue import LightGlueMatcher

    return LightGlueMatcher(matcher, matcher_options)


def _clouds(scene: Scene, pointmaps: dict[str, list[Pointmap]]) -> tuple[LabelledCloud, LabelledCloud]:
    """Labelled clouds of the frames that have a pointmap (the first len(pointmaps) of each state)."""
    return tuple(build_labelled_cloud(state, scene.frames(state)[:len(pointmaps[state])], pointmaps[state])
                 for state in ("start", "end"))


def _lift_posed_rgbd(scene: Scene, reject_flying_pixels: bool) -> LiftedScene:
    pointmaps = {state: [pointmap_from_depth(f, f.camera.cam_to_world, reject_flying_pixels)
                         for f in scene.frames(state)] for state in ("start", "end")}
    start, end = _clouds(scene, pointmaps)
    return LiftedScene(start, end, "cameras", ("world", "cameras.json world frame", "metres"))


def _camera_reference(scene: Scene) -> str:
    return "OpenCV frame of start/rgb/" + scene.start[0].rgb_path.name


def _lift_unposed_rgbd(scene: Scene, reject_flying_pixels: bool, seed: int, matcher=None) -> LiftedScene:
    """Camera-frame unprojection, views registered within each state, then the states aligned."""
    from sparseart.align.ransac import AlignmentError, register_views, transform_pointmap

    seconds: dict[str, float] = {}
    warnings: list[str] = []
    pointmaps: dict[str, list[Pointmap]] = {}
    began = time.perf_counter()
    for state in ("start", "end"):
        frames = scene.frames(state)
        own = [pointmap_from_depth(f, np.eye(4), reject_flying_pixels) for f in frames]
        if len(frames) > 1:
            try:
                transforms, view_warnings = register_views(frames, own, with_scale=False, seed=seed,
                                                           matcher=matcher)
            except AlignmentError as error:
                warnings.append(f"{state}: views could not be registered ({error}); only "
                                f"{state}/rgb/{frames[0].rgb_path.name} is used")
                own = own[:1]
            else:
                warnings.extend(view_warnings)
                own = [transform_pointmap(p, t) for p, t in zip(own, transforms)]
        pointmaps[state] = own
    seconds["register_views"] = time.perf_counter() - began
    return _align_states(scene, pointmaps, with_scale=False, units="metres", seed=seed,
                         seconds=seconds, warnings=warnings, matcher=matcher)


def _align_states(scene: Scene, pointmaps: dict[str, list[Pointmap]], *, with_scale: bool, units: str,
                  seed: int, seconds: dict[str, float], warnings: list[str], matcher=None) -> LiftedScene:
    """End pointmaps (end view-0 frame) -> start view-0 frame by feature alignment; on failure
    (too few matches, degenerate) keep them as they are and say so (alignment "none")."""
    from sparseart.align.ransac import AlignmentError, align_states, transform_pointmap

    frame = ("camera", _camera_reference(scene), units)
    began = time.perf_counter()
    try:
        alignment = align_states(scene.start[:len(pointmaps["start"])], pointmaps["start"],
                                 scene.end[:len(pointmaps["end"])], pointmaps["end"],
                                 with_scale=with_scale, seed=seed, matcher=matcher)
    except AlignmentError as error:
        seconds["align_states"] = time.perf_counter() - began
        if with_scale:
            raise
        warnings.append(f"feature alignment of the states failed ({error}); registering them through "
                        f"the static part instead")
        start, end = _clouds(scene, pointmaps)
        return LiftedScene(start, end, "none", frame, seconds=seconds, warnings=warnings)
    seconds["align_states"] = time.perf_counter() - began
    warnings.extend(alignment.warnings)
    to_start = alignment.transform.matrix()
    pointmaps = {"start": pointmaps["start"],
                 "end": [transform_pointmap(p, to_start) for p in pointmaps["end"]]}
    start, end = _clouds(scene, pointmaps)
    diagnostics = {"matches": int(len(alignment.inliers)), "static_inliers": int(alignment.inliers.sum()),
                   "scale": float(alignment.transform.scale), "rmse": float(alignment.rmse),
                   "candidates": [int(c.support) for c in alignment.candidates]}
    return LiftedScene(start, end, "features", frame, motion_hints=[c.transform for c in alignment.candidates],
                       seconds=seconds, warnings=warnings, diagnostics=diagnostics)


def _with_depth(pointmap: Pointmap, camera) -> Pointmap:
    """The pointmap with its (H, W) depth along the camera's optical axis (for depth-aware mask
    boundaries), computed from the points and the camera's cam_to_world; unchanged without a camera."""
    if camera is None or camera.cam_to_world is None:
        return pointmap
    c2w = camera.cam_to_world
    in_camera = (pointmap.points - c2w[:3, 3]) @ c2w[:3, :3]
    depth = np.where(pointmap.valid, np.nan_to_num(in_camera[:, 2], nan=0.0), 0.0)
    return replace(pointmap, depth=depth.reshape(pointmap.height, pointmap.width))


def _lift_with_model(scene: Scene, model: str | Path, onnx_options, reject_flying_pixels: bool,
                     seed: int, matcher=None) -> LiftedScene:
    from .onnx_model import OnnxLiftOptions, lift_scene_with_model

    options = onnx_options or OnnxLiftOptions(reject_flying_pixels=reject_flying_pixels)
    lift = lift_scene_with_model(scene, model, options)
    seconds = {"load_model": lift.seconds.get("load", 0.0), "reconstruct": lift.seconds.get("reconstruct", 0.0)}
    warnings = list(lift.warnings)
    units = "metres" if lift.scale == "metric" else "relative"
    if scene.posed:
        warnings.append("--model: the reconstructor's cameras are used; cameras.json poses are not, so the "
                        "result is in the frame of the first start camera")
    pointmaps = {state: [_with_depth(p, c) for p, c in zip(lift.pointmaps(state), lift.cameras(state))]
                 for state in ("start", "end")}
    if lift.frame == "joint":
        start, end = _clouds(scene, pointmaps)
        return LiftedScene(start, end, "model", ("camera", _camera_reference(scene), units),
                           seconds=seconds, warnings=warnings,
                           diagnostics={"contract": lift.contract, "mode": lift.frame})
    lifted = _align_states(scene, pointmaps, with_scale=lift.scale != "metric", units=units, seed=seed,
                           seconds=seconds, warnings=warnings, matcher=matcher)
    lifted.diagnostics.update(contract=lift.contract, mode=lift.frame)
    return lifted
