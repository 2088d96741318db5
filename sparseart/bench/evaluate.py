"""Scoring a result against a rendered scene's ``gt.json`` (metrics of design section 4).

Predicted movable parts are matched to ground-truth parts with the Hungarian algorithm on part
Chamfer distance between their start-state points (never on joint type); an unmatched
ground-truth joint scores 90 degrees and the object's size as position error.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from sparseart.bench import metrics
from sparseart.geometry.sampling import random_subset
from sparseart.types import Articulation, LabelledCloud, Scene

CHAMFER_SAMPLE = 3000


def load_gt(path: str | Path) -> dict[str, Any]:
    """Read a gt.json written by ``sparseart render``."""
    return json.loads(Path(path).read_text())


def true_groups(cloud: LabelledCloud, scene: Scene, gt: dict[str, Any]) -> np.ndarray:
    """(N,) int64 ground-truth part group (unscrambled mask id) of every point, 0 = unknown.

    Reads the true masks through each point's frame and pixel index, so it works even when the run
    itself ignored the masks: ``gt_mask/{state}/NNN.png`` when gt.json names them (realistic
    renders, whose written masks are frayed, merged and split), else the scene's written masks
    mapped back through gt.json's ``mask_maps`` (scrambled ids).
    """
    import cv2

    groups = np.zeros(len(cloud), dtype=np.int64)
    true_masks = gt.get("gt_masks")
    maps = None if true_masks else gt.get("mask_maps", {}).get(cloud.state)
    for frame in scene.frames(cloud.state):
        if true_masks:
            path = scene.root / "gt_mask" / cloud.state / f"{frame.rgb_path.stem}.png"
            mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if mask is None:
                continue
        elif frame.mask is None:
            continue
        else:
            mask = frame.mask
        here = cloud.frame_index == frame.index
        written = mask.reshape(-1)[cloud.pixel_index[here]].astype(np.int64)
        if maps:
            table = {int(k): int(v) for k, v in maps[frame.index].items()}
            lookup = np.vectorize(lambda w: table.get(int(w), 0), otypes=[np.int64])
            written = lookup(written) if len(written) else written
        groups[here] = written
    return groups


def _result_to_gt_frame(result: Articulation, gt: dict[str, Any], scene: Scene | None = None) -> np.ndarray:
    """(4, 4) rigid map from the result's frame to gt.json's world frame.

    Posed results are already in the world frame (identity). Unposed results are in the OpenCV
    frame of a start camera (design section 2): the first, or the start image the result's frame
    reference names when that one could not be registered (``scene`` gives the images' order);
    its true cam_to_world from gt.json maps them to the world. Relative-scale results are not
    rescaled here; their prismatic distances and positions are only comparable after a scale is
    known.
    """
    if result.frame_kind != "camera":
        return np.eye(4)
    cameras = gt.get("cameras", {}).get("start")
    if not cameras:
        raise ValueError("gt.json has no true start cameras to bring a camera-frame result into the world frame")
    names = [frame.rgb_path.name for frame in scene.start] if scene is not None else []
    index = next((k for k, name in enumerate(names) if result.frame_reference.endswith("start/rgb/" + name)), 0)
    return np.asarray(cameras[index], dtype=np.float64)


def _subsample(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return points[random_subset(len(points), CHAMFER_SAMPLE, rng)]


def _finite(value: Any) -> float | None:
    return None if value is None or not np.isfinite(value) else float(value)


def _stated_sigmas(joint: Any) -> dict[str, float | None]:
    """The joint's stated 1-sigma in the units of the errors beside it: ``axis_sigma_deg``,
    ``origin_sigma`` (the hinge line's position, scene units; revolute only: a slide's origin is
    only where its part starts) and ``state_sigma`` (degrees for a revolute angle, scene units for
    a slide). None where the joint states none."""
    uncertainty = joint.uncertainty or {}
    revolute = joint.type == "revolute"
    state = uncertainty.get("angle") if revolute else uncertainty.get("distance")
    return {"axis_sigma_deg": _finite(uncertainty.get("axis_deg")),
            "origin_sigma": _finite(uncertainty.get("origin")) if revolute else None,
            "state_sigma": None if _finite(state) is None else float(np.degrees(state) if revolute else state)}


def _confidence_terms(joint: Any) -> dict[str, float | None]:
    """What the joint's confidence was made of (:func:`sparseart.joints.reliability.confidence`), so a
    bench can study it without rerunning: ``covered_fraction``, ``residual_excess`` (the residual
    beyond the part's noise floor, in part radii), ``residual_floor`` (the floor, in part
    radii) and ``blocked_share`` (the share of a turning part its first steps push into the static
    part, :mod:`sparseart.joints.sweep_check`). None where the joint does not report them (the ICP
    peer, slides)."""
    from sparseart.joints.reliability import residual_excess

    diagnostics = getattr(joint, "diagnostics", None) or {}
    radius = _finite(diagnostics.get("part_radius"))
    floor = _finite(diagnostics.get("residual_floor"))
    residual = _finite(getattr(joint, "residual", None))
    relative = radius is not None and radius > 0 and floor is not None and residual is not None
    return {"covered_fraction": _finite(diagnostics.get("covered_fraction")),
            "residual_excess": residual_excess(residual, floor) / radius if relative else None,
            "residual_floor": floor / radius if relative else None,
            "blocked_share": _finite(diagnostics.get("blocked_share"))}


def evaluate(result: Articulation, scene: Scene, gt: dict[str, Any]) -> list[dict[str, Any]]:
    """Per ground-truth joint: the metrics.joint_errors dict plus "name" and "part" (matched
    predicted part id or None). Units: degrees for angles, scene units for positions."""
    rng = np.random.default_rng(0)
    cloud = result.start_cloud
    labels = result.labels
    if cloud is None or labels is None:
        raise ValueError("the result carries no clouds/labels to match parts with")
    groups = true_groups(cloud, scene, gt)
    gt_joints = gt["joints"]
    predicted = [(p, j) for p, j in result.joints]
    gt_points = [_subsample(cloud.points[groups == g["mask_id"]], rng) for g in gt_joints]
    cost = np.full((len(predicted), len(gt_joints)), np.inf)
    for i, (part, _) in enumerate(predicted):
        part_points = _subsample(cloud.points[labels.start_part == part.spec.id], rng)
        for k, points in enumerate(gt_points):
            if len(part_points) and len(points):
                cost[i, k] = metrics.chamfer_distance(part_points, points)
    matches, unmatched = metrics.match_parts(cost) if len(predicted) else ([], list(range(len(gt_joints))))
    scale = float(gt.get("scale", 1.0))
    to_world = _result_to_gt_frame(result, gt, scene)
    rows: list[dict[str, Any]] = [{} for _ in gt_joints]
    for i, k in matches:
        part, joint = predicted[i]
        pred = {"type": joint.type, "axis": to_world[:3, :3] @ joint.axis,
                "origin": to_world[:3, :3] @ joint.origin + to_world[:3, 3],
                "angle": joint.angle, "distance": joint.distance}
        rows[k] = {**metrics.joint_errors(pred, gt_joints[k]), "part": part.spec.id,
                   **_stated_sigmas(joint), "confidence": float(joint.confidence),
                   **_confidence_terms(joint)}
    for k in unmatched:
        rows[k] = {**metrics.unmatched_joint_errors(gt_joints[k], position_max=scale), "part": None}
    for row, g in zip(rows, gt_joints):
        row["name"] = g.get("name")
    return rows
