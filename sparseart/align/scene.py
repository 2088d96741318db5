"""The align stage: per-view pointmaps of both states -> one frame, and how far to trust it.

``align_scene`` takes what the lift stage produced and decides what the scene needs:

* frame "world" (posed) or "model" (a reconstructor's joint frame): nothing to register
  (alignment "cameras" / "model"; a "model" alignment is polished on the static part later);
* frame "views" (unposed RGB-D): each state's views registered to its first view
  (:func:`~sparseart.align.views.register_views`, rigid, metric depth), then the end state to the
  start state (:func:`~sparseart.align.states.align_states`);
* frame "states" (per-state reconstructions): only the states are aligned, by a similarity.

A state alignment by features is polished on the labelled static part after labelling
(:mod:`sparseart.align.static`, alignment "features"); when it fails the states stay apart
(alignment "none") and the pipeline registers them through the labeler's static part.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from sparseart.align.ransac import AlignmentError
from sparseart.align.states import align_states
from sparseart.align.views import register_views
from sparseart.geometry.clouds import transform_pointmap
from sparseart.lift.scene_lift import LiftedScene
from sparseart.types import Pointmap, Scene

STATES = ("start", "end")


@dataclass
class AlignedScene:
    """Every kept view's pointmap in the result frame.

    pointmaps: {"start": [...], "end": [...]}; a view that could not be registered is dropped (the
        lists are then shorter than the scene's frames: the first len(...) frames are kept).
    alignment: "cameras" | "model" | "features" | "none" (module docstring).
    frame: (kind "world" | "camera", what defines it, units "metres" | "relative").
    motion_hints: (4, 4) start->end rigid motions in the result frame that state alignment found
        among the matches the static transform did not explain (candidate moving parts).
    seconds: wall seconds of "register_views" and "align_states" when they ran.
    """

    pointmaps: dict[str, list[Pointmap]]
    alignment: str
    frame: tuple[str, str, str]
    motion_hints: list[np.ndarray] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)


def align_scene(scene: Scene, lifted: LiftedScene, *, seed: int = 0, matcher=None) -> AlignedScene:
    """Bring the lifted views of both states into one frame (see the module docstring).

    Args:
        scene: the loaded scene (its frames name the images in warnings).
        lifted: the lift stage's output.
        seed: random seed of every RANSAC and ICP step.
        matcher: a pair matcher (``match(frame_a, pointmap_a, frame_b, pointmap_b) -> FeatureMatches``,
            see :func:`sparseart.align.matchers.open_matcher`) used instead of SIFT; None = SIFT.

    Raises:
        AlignmentError: per-state reconstructions whose states cannot be aligned (no fallback
            exists for relative scale).
    """
    reference = "OpenCV frame of start/rgb/" + scene.start[0].rgb_path.name
    if lifted.frame == "world":
        return AlignedScene(lifted.pointmaps, "cameras", ("world", "cameras.json world frame", "metres"),
                            warnings=list(lifted.warnings))
    frame = ("camera", reference, lifted.units)
    if lifted.frame == "model":
        return AlignedScene(lifted.pointmaps, "model", frame, warnings=list(lifted.warnings))
    warnings = list(lifted.warnings)
    seconds: dict[str, float] = {}
    pointmaps = dict(lifted.pointmaps)
    if lifted.frame == "views":
        began = time.perf_counter()
        pointmaps = {state: _register_state(scene, state, pointmaps[state], seed, matcher, warnings)
                     for state in STATES}
        seconds["register_views"] = time.perf_counter() - began
    began = time.perf_counter()
    with_scale = lifted.units != "metres"
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
        return AlignedScene(pointmaps, "none", frame, seconds=seconds, warnings=warnings)
    seconds["align_states"] = time.perf_counter() - began
    warnings.extend(alignment.warnings)
    to_start = alignment.transform.matrix()
    pointmaps["end"] = [transform_pointmap(p, to_start) for p in pointmaps["end"]]
    diagnostics = {"matches": int(len(alignment.inliers)), "static_inliers": int(alignment.inliers.sum()),
                   "scale": float(alignment.transform.scale), "rmse": float(alignment.rmse),
                   "candidates": [int(c.support) for c in alignment.candidates]}
    return AlignedScene(pointmaps, "features", frame, [c.transform for c in alignment.candidates],
                        seconds, warnings, diagnostics)


def _register_state(scene: Scene, state: str, own: list[Pointmap], seed: int, matcher,
                    warnings: list[str]) -> list[Pointmap]:
    """One state's views (each in its own camera frame) -> the frame of its first view; a state
    whose views cannot be registered keeps its first view only, with a warning."""
    frames = scene.frames(state)
    if len(frames) < 2:
        return own
    try:
        transforms, view_warnings = register_views(frames, own, with_scale=False, seed=seed, matcher=matcher)
    except AlignmentError as error:
        warnings.append(f"{state}: views could not be registered ({error}); only "
                        f"{state}/rgb/{frames[0].rgb_path.name} is used")
        return own[:1]
    warnings.extend(view_warnings)
    return [transform_pointmap(p, t) for p, t in zip(own, transforms)]
