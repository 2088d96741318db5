"""The lift stage: a scene -> per-view pointmaps of both states. It never aligns anything.

Three routes, chosen by what the scene holds:

* **posed RGB-D** (depth + cam_to_world for every image): every view unprojected into the world
  frame of cameras.json (frame "world": the states already share a frame);
* **unposed RGB-D** (depth + K, no cam_to_world): each view unprojected in its OWN camera frame
  (frame "views"); :func:`sparseart.align.align_scene` brings them together;
* **RGB only** (``model`` given): an ONNX reconstructor lifts every image
  (:func:`sparseart.lift.onnx_model.lift_scene_with_model`); "joint" mode gives both states in the
  frame of the first start camera (frame "model"), "per_state" mode one frame and scale per state
  (frame "states": each state's pointmaps share its first view's frame).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from sparseart.lift.rgbd import pointmap_from_depth
from sparseart.types import Pointmap, Scene, SceneError

FRAMES = ("world", "views", "model", "states")


@dataclass
class LiftedScene:
    """Every view's pointmap and the frame they are in.

    pointmaps: {"start": [...], "end": [...]}, one :class:`Pointmap` per frame of the scene
        ((H*W, 3) float64 points).
    frame: "world" | "views" | "model" | "states" (module docstring).
    units: "metres" or "relative" (a relative-scale reconstructor).
    seconds: wall seconds of the sub-steps ("load_model", "reconstruct").
    """

    pointmaps: dict[str, list[Pointmap]]
    frame: str
    units: str = "metres"
    seconds: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)


def lift_scene(scene: Scene, *, reject_flying_pixels: bool = True, model: str | Path | None = None,
               onnx_options=None) -> LiftedScene:
    """Lift a loaded scene (masks already set on the frames) into per-view pointmaps.

    Args:
        scene: a loaded :class:`Scene` (``load_scene(path, require_depth=model is None)``).
        reject_flying_pixels: drop depth-edge pixels (RGB-D and depth-unprojecting models).
        model: an ONNX reconstructor (.onnx path); required when the scene has no depth.
        onnx_options: :class:`~sparseart.lift.onnx_model.OnnxLiftOptions` (None: defaults).

    Raises:
        SceneError (incl. ModelError): one line naming the file.
    """
    if model is not None:
        return _lift_with_model(scene, model, onnx_options, reject_flying_pixels)
    if not scene.has_depth:
        missing = next(f for f in scene.all_frames if f.depth is None)
        raise SceneError(f"{missing.rgb_path}: no depth image and no reconstructor given "
                         f"(add {missing.state}/depth/ or run with --model MODEL.onnx)")
    posed = scene.posed
    pointmaps = {state: [pointmap_from_depth(f, f.camera.cam_to_world if posed else np.eye(4), reject_flying_pixels)
                         for f in scene.frames(state)] for state in ("start", "end")}
    return LiftedScene(pointmaps, "world" if posed else "views")


def _with_depth(pointmap: Pointmap, camera) -> Pointmap:
    """The pointmap with its (H, W) depth along the camera's optical axis (for depth-aware mask
    boundaries), computed from the points and the camera's cam_to_world; unchanged without a camera."""
    if camera is None or camera.cam_to_world is None:
        return pointmap
    c2w = camera.cam_to_world
    in_camera = (pointmap.points - c2w[:3, 3]) @ c2w[:3, :3]
    depth = np.where(pointmap.valid, np.nan_to_num(in_camera[:, 2], nan=0.0), 0.0)
    return replace(pointmap, depth=depth.reshape(pointmap.height, pointmap.width))


def _lift_with_model(scene: Scene, model: str | Path, onnx_options, reject_flying_pixels: bool) -> LiftedScene:
    from sparseart.lift.onnx_model import OnnxLiftOptions, lift_scene_with_model

    options = onnx_options or OnnxLiftOptions(reject_flying_pixels=reject_flying_pixels)
    lift = lift_scene_with_model(scene, model, options)
    seconds = {"load_model": lift.seconds.get("load", 0.0), "reconstruct": lift.seconds.get("reconstruct", 0.0)}
    warnings = list(lift.warnings)
    if scene.posed:
        warnings.append("--model: the reconstructor's cameras are used; cameras.json poses are not, so the "
                        "result is in the frame of the first start camera")
    pointmaps = {state: [_with_depth(p, c) for p, c in zip(lift.pointmaps(state), lift.cameras(state))]
                 for state in ("start", "end")}
    return LiftedScene(pointmaps, "model" if lift.frame == "joint" else "states",
                       "metres" if lift.scale == "metric" else "relative", seconds, warnings,
                       {"contract": lift.contract, "mode": lift.frame})
