"""The shift of a joint's whole frame that the alignment measured, in its stated sigma.

A reconstructor's or sensor's depth is off mostly along the camera rays (a per-view scale, a
smooth warp of ~2 %): whole surfaces -- the part, the body, the hinge line placed from them --
move by ~2 % of their distance from the camera and turn little. The joint fit cannot see it (the
points it lays onto each other moved alike), and the static part's misfit
(:func:`~sparseart.joints.uncertainty.frame_misfit`, nearest-point distances) does not see a shift
along a surface. What does: the RMS distance of the features matched across the states
(:func:`registration_shift`), and, for states in one frame from posed cameras, how far the depth-ratio
step found the two states' depths apart (:func:`depth_ratio_shift`). :func:`add_alignment_shift`
reads whichever the alignment report holds and widens every joint's origin (and, for feature-aligned
states, a slide's length) in quadrature; the axis and a revolute angle keep their sigma.
Measured: experiment EXP-059 (benchmarks/EXPERIMENTS.md).
"""
from __future__ import annotations

import numpy as np

from sparseart.types import JointEstimate, LabelledCloud, PartLabels, PartResult, Scene

# Share of the states' feature registration residual (RMS, scene units) by which a joint's frame is
# shifted, 1 sigma. Measured on the realistic renders (16 objects, seeds 0-1: 22 hinges and 16
# slides within 10 deg; the seeds 2-3 and realistic-1view held out): the hinge lines lay 0.002-0.045
# off, 0.03-1.05 x the residual (0.044-0.087: ~2 % of the distance from the camera), where the frame
# misfit of the static points had stated 0.004-0.028 -- smallest exactly where the polish had slid
# the states along a flat valley of the static surfaces.
REGISTRATION_SHIFT_SHARE = 0.35

# Share of "how far the two states' depths disagree" (the depth-ratio step's 95th percentile of
# |z_end / z_start - 1| over the static scene, same camera) x the distance from the camera that a
# hinge line placed from that depth moves, 1 sigma. Measured on robot-1view (one posed view per
# state, reconstructor-grade depth; seeds 0-1, 20 hinges within 10 deg; seeds 2-3 and
# robot-sensor-1view held out): hinges 0.1-4.4 x largest x distance off (largest 1.2-2.3 %, camera
# 2.5-3.7 away), at a stated sigma that covered 40 % / 60 %.
DEPTH_RATIO_SHIFT_SHARE = 1.0


def add_frame_shift(joint: JointEstimate, shift: float, keys: tuple[str, ...] = ("origin", "distance")) -> None:
    """Widen a joint's stated sigma (in place) by a shift of its whole frame (module doc): ``shift``
    (scene units, 1 sigma) joins each of ``keys`` the joint states ("origin": the hinge line or a
    slide's origin; "distance": a slide's length) in quadrature; the axis and a revolute angle are
    left alone. Records ``joint.diagnostics["frame_shift"]`` (scene units). No-op for a shift <= 0
    or non-finite. O(1)."""
    if not (np.isfinite(shift) and shift > 0):
        return
    for key in keys:
        if key in joint.uncertainty:
            joint.uncertainty[key] = float(np.hypot(float(joint.uncertainty[key]), shift))
    joint.diagnostics["frame_shift"] = float(shift)


def registration_shift(rmse: float) -> float:
    """The frame shift (scene units) that a feature registration of the states with inlier RMS
    ``rmse`` (scene units: 3D distance of the features matched across the states) shows:
    ``REGISTRATION_SHIFT_SHARE`` x rmse. The static misfit (:func:`frame_misfit`) reads
    nearest-point distances, which a shift along a surface does not raise; matched features see
    every component. O(1)."""
    return REGISTRATION_SHIFT_SHARE * float(rmse)


def depth_ratio_shift(largest: float, distance: float) -> float:
    """The frame shift (scene units) of surfaces ``distance`` (scene units) from the camera whose
    depth the two states disagree on by ``largest`` (the depth-ratio step's 95th percentile of
    |ratio - 1| over the static scene): ``DEPTH_RATIO_SHIFT_SHARE`` x largest x distance. The ratio
    step lays the end depth onto the start's, so the joint no longer sees the disagreement; what it
    measured is how far each state's own depth may be off. O(1)."""
    return DEPTH_RATIO_SHIFT_SHARE * float(largest) * float(distance)


def add_alignment_shift(parts: list[PartResult], registration: dict | None, start: LabelledCloud,
                        labels: PartLabels, scene: Scene | None) -> None:
    """Every joint's sigma widened by the shift of its frame that the alignment measured
    (:func:`add_frame_shift`): states aligned by features carry
    their registration residual's share on the hinge line and the slide
    (:func:`registration_shift`); states in one frame from posed
    cameras whose depth the ratio step compared carry the disagreement it found, times the part's
    distance from its camera, on the origin (:func:`depth_ratio_shift`;
    a depth error moves both states alike there, so a slide's length keeps its sigma). Nothing
    for clouds without a scene, nor for states never compared. O(N) for the part distances."""
    report = registration or {}
    states = report.get("states", {})
    if states.get("method") == "features" and states.get("trusted", False) and states.get("rmse") is not None:
        for part in parts:
            if part.joint is not None:
                add_frame_shift(part.joint, registration_shift(float(states["rmse"])))
        return
    ratios = [float(r["largest"]) for r in report.get("depth_ratio", []) if r.get("largest") is not None]
    centres = _camera_centres(scene)
    if not ratios or centres is None:
        return
    largest = float(np.median(ratios))
    for part in parts:
        if part.joint is None:
            continue
        own = labels.start_part == part.spec.id
        if not own.any():
            continue
        distance = float(np.median(np.linalg.norm(start.points[own] - centres[start.frame_index[own]], axis=1)))
        add_frame_shift(part.joint, depth_ratio_shift(largest, distance), keys=("origin",))


def _camera_centres(scene: Scene | None) -> np.ndarray | None:
    """(F, 3) float64 scene-frame centres of the start cameras, or None unless every start frame is
    posed. O(F)."""
    if scene is None or not scene.start:
        return None
    poses = [frame.camera.cam_to_world if frame.camera is not None else None for frame in scene.start]
    if any(pose is None for pose in poses):
        return None
    return np.array([np.asarray(pose, dtype=np.float64)[:3, 3] for pose in poses])
