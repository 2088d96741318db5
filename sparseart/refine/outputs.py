"""Outputs of the refinement: PSNR, renders of novel articulation states, a turntable strip, the
3DGS PLY files and refine.json, written beside articulation.json (each file atomically).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sparseart.io.scene import write_bytes_atomic, write_json_atomic
from ..types import Articulation
from .compose import components, novel_state_components, render_components
from .losses import psnr
from .ply import write_gaussians_ply
from .render import Camera

TURNTABLE_FRAMES = 8
TURNTABLE_SWEEP_DEG = 60.0   # the strip sweeps +-60 deg around the first view: the scene is only
                             # seen from the front, its back holds no observed Gaussians


def psnr_report(outcome) -> dict:
    """Mean PSNR (dB) of the cross-mobile renderings (the accepted joint) over the training views
    and, when any view was held out, over the held-out views: {"train": float, "heldout": float|None,
    "heldout_views": int}."""
    import torch

    scores = {"train": [], "heldout": []}
    with torch.no_grad():
        for state, views in outcome.views.items():
            for view in views:
                drawn = components(state, outcome.sets, outcome.params, "cross_mobile")
                image = render_components(drawn, view.camera, view.background)["rgb"].double().numpy()
                scores["heldout" if view.held_out else "train"].append(psnr(image, view.rgb.double().numpy()))

    def mean(values):
        finite = [v for v in values if math.isfinite(v)]
        return float(np.mean(finite)) if finite else None

    return {"train": mean(scores["train"]), "heldout": mean(scores["heldout"]),
            "heldout_views": len(scores["heldout"])}


def _to_png(image: np.ndarray) -> bytes:
    import cv2

    ok, encoded = cv2.imencode(".png", (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1])
    if not ok:
        raise ValueError("could not encode a PNG")
    return encoded.tobytes()


def render_state(outcome, fraction: float, camera: Camera | None = None) -> np.ndarray:
    """(H, W, 3) float64 RGB of the articulation state at ``fraction`` (0 = start, 1 = end, any
    value extrapolates along the joint) seen from ``camera`` (default: the first start view)."""
    import torch

    view = outcome.views["start"][0] if outcome.views.get("start") else next(iter(outcome.views.values()))[0]
    with torch.no_grad():
        drawn = novel_state_components(outcome.sets, outcome.params, float(fraction))
        return render_components(drawn, camera or view.camera, view.background)["rgb"].double().numpy()


def turntable_cameras(camera: Camera, centre: np.ndarray, up: np.ndarray,
                      frames: int = TURNTABLE_FRAMES) -> list[Camera]:
    """``frames`` cameras orbiting ``centre`` (3,) about the line through it along ``up`` (3,),
    from -TURNTABLE_SWEEP_DEG to +TURNTABLE_SWEEP_DEG around ``camera``'s position, each looking at the centre (principal point at the image
    centre, ``camera``'s focal length and size)."""
    from scipy.spatial.transform import Rotation

    up = np.asarray(up, np.float64) / max(np.linalg.norm(up), 1e-12)
    eye = np.linalg.inv(camera.world_to_cam)[:3, 3]
    K = np.asarray(camera.K, np.float64).copy()
    K[0, 2], K[1, 2] = (camera.width - 1) / 2, (camera.height - 1) / 2
    cameras = []
    for turn in np.radians(np.linspace(-TURNTABLE_SWEEP_DEG, TURNTABLE_SWEEP_DEG, frames)):
        position = centre + Rotation.from_rotvec(up * turn).apply(eye - centre)
        forward = (centre - position) / max(np.linalg.norm(centre - position), 1e-12)
        right = np.cross(forward, up)
        if np.linalg.norm(right) < 1e-9:       # looking straight along up: any perpendicular works
            right = np.cross(forward, np.eye(3)[int(np.argmin(np.abs(forward)))])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        cam_to_world = np.eye(4)
        cam_to_world[:3, :3] = np.stack([right, down, forward], axis=1)
        cam_to_world[:3, 3] = position
        cameras.append(Camera(K, np.linalg.inv(cam_to_world), camera.width, camera.height))
    return cameras


def turntable_strip(outcome, fractions: tuple[float, ...] = (0.0, 1.0), frames: int = TURNTABLE_FRAMES) -> np.ndarray:
    """(rows * H, frames * W, 3) image: one row per articulation state, ``frames`` views swept
    around the object (about the mean up direction of the start cameras, through the Gaussians' median)."""
    views = outcome.views["start"]
    up = np.mean([-np.linalg.inv(v.camera.world_to_cam)[:3, 1] for v in views], axis=0)
    centre = np.median(outcome.sets["start"].means.detach().double().numpy(), axis=0)
    cameras = turntable_cameras(views[0].camera, centre, up, frames)
    return np.concatenate([np.concatenate([render_state(outcome, f, c) for c in cameras], axis=1)
                           for f in fractions], axis=0)


def write_refine_outputs(result: Articulation, out_dir: str | Path,
                         render_states: tuple[float, ...] = (0.0, 0.5, 1.0)) -> list[Path]:
    """For every refined part: ``splats_part{id}_{start,end}.ply`` (3DGS + mobility),
    ``render_part{id}_state{s}.png`` per state in ``render_states``, ``turntable_part{id}.png``;
    plus ``refine.json`` with every part's before/after values. Returns the written paths."""
    out_dir = Path(out_dir)
    written: list[Path] = []
    summary = {}
    for part, joint in result.joints:
        outcome = part.refinement
        if outcome is None:
            continue
        pid = part.spec.id
        summary[str(pid)] = joint.diagnostics.get("refine", {})
        for state, gaussians in outcome.sets.items():
            written.append(write_gaussians_ply(out_dir / f"splats_part{pid}_{state}.ply", gaussians.to_numpy()))
        for fraction in render_states:
            path = out_dir / f"render_part{pid}_state{fraction:g}.png"
            write_bytes_atomic(path, _to_png(render_state(outcome, fraction)))
            written.append(path)
        path = out_dir / f"turntable_part{pid}.png"
        write_bytes_atomic(path, _to_png(turntable_strip(outcome)))
        written.append(path)
    if summary:
        path = out_dir / "refine.json"
        write_json_atomic(path, summary)
        written.append(path)
    return written
