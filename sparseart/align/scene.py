"""The align stage: per-view pointmaps of both states -> one frame, and how far to trust it.

``align_scene`` takes what the lift stage produced and decides what the scene needs:

* frame "world" (posed) or "model" (a reconstructor's joint frame): nothing to register
  (alignment "cameras" / "model"; a "model" alignment is polished on the static part later). A
  posed end view taken from a start view's camera gets its depth matched to that view's on the
  static scene when the two differ by a smooth ratio (a reconstructor run per state, a drifting
  sensor: :mod:`sparseart.align.depth_ratio`; report entry ``"depth_ratio"``);
* frame "views" (unposed RGB-D): an end view whose camera did not move between the states gets
  its depth matched to its start twin's first (:func:`~sparseart.align.still.still_pairs`, the
  same smooth ratio); then every view of both states registered at once
  (:func:`~sparseart.align.graph.register_scene`: all pairs matched, components of views merged by
  pooled robust fits, poses solved jointly, per-view depth scale, checked state alignment);
* frame "states" (per-state reconstructions): only the states are aligned, by a similarity
  (:func:`~sparseart.align.states.align_states`).

A state alignment by features is polished on the labelled static part after labelling
(:mod:`sparseart.align.static`, alignment "features"); when it fails or is not trusted, a view
whose camera did not move between the states aligns them exactly (:mod:`sparseart.align.still`,
alignment "still", no polish), else the states stay apart (alignment "none") and the pipeline
registers them through the labeler's static part. A view left out of one state is placed through
its same-camera twin in the other once the states are aligned.

``AlignedScene.registration`` reports how each view and the states were registered (see
:func:`registration_report`); the pipeline copies it into ``Articulation.registration``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from sparseart.align.depth_ratio import SAME_POSE_DEG, SAME_POSE_SHARE, DepthRatio, match_end_depth, same_camera
from sparseart.align.features import THRESHOLD_FRACTION
from sparseart.align.graph import SceneRegistration, register_scene
from sparseart.align.ransac import AlignmentError
from sparseart.align.states import align_states
from sparseart.align.still import place_through_twins, still_camera, still_pairs, view_depth
from sparseart.geometry.clouds import scene_size, transform_pointmap, valid_points
from sparseart.geometry.icp import icp_polish
from sparseart.geometry.transforms import rotation_angle
from sparseart.lift.scene_lift import LiftedScene
from sparseart.types import Pointmap, Scene, SceneError

STATES = ("start", "end")
SHARED_PROBE_POINTS = 20000   # points per state (strided) that the posed states' shared-surface check reads
SHARED_RADIUS_SIZE = 0.5      # an end point within this share of the start cloud's size of a start point is near it
MIN_SHARED_SHARE = 0.02       # posed states with less than this share of the end points near the start state:
                              # the cameras or the depth units disagree (the object is seen in both)
# A whole-scene ICP that moves a feature alignment of the states by more than this says the
# alignment was off (:func:`_polish_states`); smaller corrections are left to the static polish.
STATE_POLISH_MIN_DEG = 2.0
# The state polish first probes on an even subsample of at most STATE_PROBE_POINTS points per state
# (0.6-4.5 s on realistic scenes, where the full ICP took 24-37 s); only a probe that moves the
# states by more than STATE_PROBE_MIN_DEG runs the full-resolution ICP from the probe's answer.
# Measured on 32 realistic renders: probes 0.0-1.26 deg, their full ICPs < 0.2 deg; the desk's
# probe 4.31 deg, its full ICP 4.31.
STATE_PROBE_POINTS = 20000
STATE_PROBE_MIN_DEG = 1.5


@dataclass
class AlignedScene:
    """Every view's pointmap in the result frame.

    pointmaps: {"start": [...], "end": [...]}, one per frame of the scene; a view that could not be
        registered keeps its place with no valid point (so it adds nothing to the clouds).
    alignment: "cameras" | "model" | "features" | "still" | "none" (module docstring).
    frame: (kind "world" | "camera", what defines it, units "metres" | "relative").
    motion_hints: (4, 4) start->end rigid motions in the result frame that state alignment found
        among the matches the static transform did not explain (candidate moving parts).
    seconds: wall seconds of "register_views" (matching, merging, joint solve, polish) and
        "align_states" (state checks, motion candidates) when they ran.
    registration: the report of :func:`registration_report` (per view and for the states).
    poses: {"start": [...], "end": [...]} (4, 4) camera -> result frame per view (None: not
        registered) for unposed scenes; empty otherwise.
    scene: the scene with the end views' depth matched to the start views'
        (:mod:`sparseart.align.depth_ratio`: posed scenes, and unposed views whose camera did not
        move) when that changed it; None otherwise.
    """

    pointmaps: dict[str, list[Pointmap]]
    alignment: str
    frame: tuple[str, str, str]
    motion_hints: list[np.ndarray] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)
    registration: dict = field(default_factory=dict)
    poses: dict[str, list[np.ndarray | None]] = field(default_factory=dict)
    scene: Scene | None = None


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
    if lifted.frame in ("world", "model"):
        how = "cameras" if lifted.frame == "world" else "model"
        frame = (("world", "cameras.json world frame", "metres") if lifted.frame == "world"
                 else ("camera", reference, lifted.units))
        report = _given_report(scene, how)
        if lifted.frame == "world":
            return _posed(scene, lifted, frame, report)
        return AlignedScene(lifted.pointmaps, how, frame, warnings=list(lifted.warnings), registration=report)
    frame = ("camera", reference, lifted.units)
    warnings = list(lifted.warnings)
    if lifted.frame == "views":
        began = time.perf_counter()
        scene, lifted, corrected = _match_still_end_depth(scene, lifted, warnings)
        registration = register_scene({s: scene.frames(s) for s in STATES}, lifted.pointmaps,
                                      relative=lifted.units != "metres", seed=seed, matcher=matcher)
        frame = ("camera", "OpenCV frame of start/rgb/" + scene.start[registration.reference].rgb_path.name,
                 lifted.units)
        total = time.perf_counter() - began
        checks = registration.seconds.get("check", 0.0)
        seconds = {"register_views": total - checks, "align_states": checks}
        warnings.extend(registration.warnings)
        pointmaps = {state: [transform_pointmap(p, pose) if pose is not None else _emptied(p)
                             for p, pose in zip(lifted.pointmaps[state], registration.poses[state])]
                     for state in STATES}
        report = registration_report(registration)
        diagnostics = {k: report["states"].get(k) for k in ("matches", "inliers", "rmse")}
        diagnostics["candidates"] = [int(c.support) for c in registration.candidates]
        alignment = "features" if registration.aligned else "none"
        end_to_start = np.eye(4) if registration.aligned else None
        if registration.aligned:
            began = time.perf_counter()
            _polish_states(pointmaps, registration.poses, report, warnings)
            seconds["align_states"] += time.perf_counter() - began
        if end_to_start is None:
            began = time.perf_counter()
            end_to_start = _align_through_still_camera(scene, lifted, registration.poses, pointmaps, report, warnings)
            seconds["align_states"] += time.perf_counter() - began
            alignment = "none" if end_to_start is None else "still"
        if end_to_start is not None:
            began = time.perf_counter()
            _place_through_twins(scene, lifted, registration.poses, pointmaps, report, warnings, end_to_start)
            seconds["register_views"] += time.perf_counter() - began
        if corrected:
            report["depth_ratio"] = [r.report() for r in corrected]
        return AlignedScene(pointmaps, alignment, frame, [c.transform for c in registration.candidates], seconds,
                            warnings, diagnostics, report, registration.poses,
                            scene=scene if any(r.applied for r in corrected) else None)
    # "states": per-state reconstructions, each already in one frame; only the states are aligned.
    pointmaps = dict(lifted.pointmaps)
    began = time.perf_counter()
    with_scale = lifted.units != "metres"
    try:
        alignment = align_states(scene.start, pointmaps["start"], scene.end, pointmaps["end"],
                                 with_scale=with_scale, seed=seed, matcher=matcher)
    except AlignmentError as error:
        seconds = {"align_states": time.perf_counter() - began}
        if with_scale:
            raise
        warnings.append(f"feature alignment of the states failed ({error}); registering them through "
                        f"the static part instead")
        report = _given_report(scene, "model")
        report["states"] = {"method": "none", "trusted": False, "reason": str(error)}
        return AlignedScene(pointmaps, "none", frame, seconds=seconds, warnings=warnings, registration=report)
    seconds = {"align_states": time.perf_counter() - began}
    warnings.extend(alignment.warnings)
    to_start = alignment.transform.matrix()
    pointmaps["end"] = [transform_pointmap(p, to_start) for p in pointmaps["end"]]
    diagnostics = {"matches": int(len(alignment.inliers)), "static_inliers": int(alignment.inliers.sum()),
                   "scale": float(alignment.transform.scale), "rmse": float(alignment.rmse),
                   "candidates": [int(c.support) for c in alignment.candidates]}
    report = _given_report(scene, "model")
    report["states"] = {"method": "features", "trusted": True, "matches": int(len(alignment.inliers)),
                        "inliers": int(alignment.inliers.sum()), "rmse": float(alignment.rmse),
                        "scale": float(alignment.transform.scale)}
    return AlignedScene(pointmaps, "features", frame, [c.transform for c in alignment.candidates],
                        seconds, warnings, diagnostics, report)


def _align_through_still_camera(scene: Scene, lifted: LiftedScene, poses: dict[str, list],
                                pointmaps: dict[str, list], report: dict, warnings: list[str]) -> np.ndarray | None:
    """States the features left apart, aligned through a view whose camera did not move
    (:func:`~sparseart.align.still.still_camera`): the end pointmaps moved into the start frame,
    the report's states entry and the warnings updated in place. Returns the (4, 4) end -> start
    transform, or None (nothing changed) when no view pair is one camera position."""
    still = still_camera(scene.start, scene.end, lifted.pointmaps["start"], lifted.pointmaps["end"],
                         poses["start"], poses["end"])
    if still is None:
        return None
    pointmaps["end"] = [transform_pointmap(p, still.transform) for p in pointmaps["end"]]
    report["states"] = {"method": "still camera", "trusted": True, "view": still.view,
                        "agreeing_pixels": round(still.share, 4), "scale": round(still.scale, 5),
                        "features": report["states"]}
    warnings[:] = [w for w in warnings if not w.startswith("feature alignment of the states failed")]
    warnings.append(f"{scene.end[still.view].image}: the camera did not move between the states ({still.share:.0%} "
                    f"of its pixels agree with {scene.start[still.view].image} in depth and colour); the states "
                    f"are aligned through it")
    return still.transform


def _place_through_twins(scene: Scene, lifted: LiftedScene, poses: dict[str, list], pointmaps: dict[str, list],
                         report: dict, warnings: list[str], end_to_start: np.ndarray) -> None:
    """Views left out of one state that their same-camera twin in the other state places
    (:func:`~sparseart.align.still.place_through_twins`): pose, pointmap (in its state's frame),
    report entry and warning updated in place."""
    placed = place_through_twins(scene.start, scene.end, lifted.pointmaps["start"], lifted.pointmaps["end"],
                                 poses["start"], poses["end"], end_to_start, zoom=lifted.units != "metres")
    for (state, k), (pose, share) in placed.items():
        poses[state][k] = pose
        to_frame = pose if state == "start" else end_to_start @ pose
        pointmaps[state][k] = transform_pointmap(lifted.pointmaps[state][k], to_frame)
        frame = scene.frames(state)[k]
        twin = scene.frames("end" if state == "start" else "start")[k]
        entry = next(v for v in report["views"] if v["image"] == frame.image)
        entry.update(registered=True, how="still camera", twin=twin.image, agreeing_pixels=round(share, 4))
        entry.pop("reason", None)
        warnings[:] = [w for w in warnings if not w.startswith(f"{frame.image}: view could not be registered")]
        warnings.append(f"{frame.image}: placed through {twin.image}, taken from the same place ({share:.0%} of "
                        f"the pixels agree in depth and colour)")


def _match_still_end_depth(scene: Scene, lifted: LiftedScene,
                           warnings: list[str]) -> tuple[Scene, LiftedScene, list[DepthRatio]]:
    """Unposed RGB-D: every end view whose camera did not move between the states
    (:func:`~sparseart.align.still.still_pairs`) gets its depth matched to its start twin's on the
    static scene (:func:`~sparseart.align.depth_ratio.match_end_depth`), before registration.

    Why: a reconstructor run once per state (or a drifting sensor) warps each state's depth on
    its own; where nothing moved, the two depths of one camera should agree, and the smooth ratio
    between them is that warp. Removing it before the views are registered lets the static scene
    agree between the states, so the part's apparent motion carries less of the warp. Measured on
    the realistic renders (16 objects, seeds 0-3, 3 still views per state, each warped ~2 % per
    state): 69 -> 71 of 84 joints within 10 deg, median axis error 2.36 -> 2.16 deg
    (experiment EXP-046). Returns the scene and lifted views with the
    corrected end views (unchanged when none was corrected) and one DepthRatio per still pair;
    the warnings gain one line per corrected view. O(V H W log(H W)) for the still test plus the
    ratio fits."""
    pairs = still_pairs(scene.start, scene.end, lifted.pointmaps["start"], lifted.pointmaps["end"])
    if not pairs:
        return scene, lifted, []
    frames, maps, ratios = match_end_depth(scene.start, scene.end, lifted.pointmaps["start"], lifted.pointmaps["end"],
                                           pairs=pairs)
    applied = [r for r in ratios if r.applied]
    warnings.extend(_ratio_warning(r) for r in applied)
    if not applied:
        return scene, lifted, ratios
    return (replace(scene, end=frames), replace(lifted, pointmaps={"start": lifted.pointmaps["start"], "end": maps}),
            ratios)


def _ratio_warning(ratio: DepthRatio) -> str:
    """The line a corrected end view adds to the warnings."""
    return (f"{ratio.end_image}: depth differs from {ratio.start_image} (same camera) by a smooth ratio (up to "
            f"{ratio.largest:.1%} on the static scene); matched to it there")


def _posed(scene: Scene, lifted: LiftedScene, frame: tuple[str, str, str], report: dict) -> AlignedScene:
    """Posed views stay where their cameras put them; an end view seen from a start view's camera
    gets its depth matched to that view's on the static scene
    (:func:`~sparseart.align.depth_ratio.match_end_depth`)."""
    warnings = list(lifted.warnings)
    began = time.perf_counter()
    placed = place_still_end_views(scene, lifted, warnings)
    if placed is not None:
        scene, lifted = placed
        report["cameras"] = "end views placed by the start views whose pictures they repeat"
    check_shared_surface(scene, lifted.pointmaps)
    frames, maps, ratios = match_end_depth(scene.start, scene.end, lifted.pointmaps["start"], lifted.pointmaps["end"])
    seconds = {"match_depth": time.perf_counter() - began}
    report["depth_ratio"] = [r.report() for r in ratios]
    applied = [r for r in ratios if r.applied]
    if not applied:
        return AlignedScene(lifted.pointmaps, "cameras", frame, seconds=seconds, warnings=warnings, registration=report,
                            scene=scene if placed is not None else None)
    warnings.extend(_ratio_warning(r) for r in applied)
    pointmaps = {"start": lifted.pointmaps["start"], "end": maps}
    return AlignedScene(pointmaps, "cameras", frame, seconds=seconds, warnings=warnings, registration=report,
                        scene=replace(scene, end=frames))


def place_still_end_views(scene: Scene, lifted: LiftedScene,
                          warnings: list[str]) -> tuple[Scene, LiftedScene] | None:
    """Posed views whose pictures say the camera did not move while cameras.json says it did:
    each such end view placed by its start twin. Returns the scene and lifted views with every
    still end view k (its camera and points) mapped by start pose_k x end pose_k^-1, or None when
    nothing is placed (no same-index view pair of one camera posed apart -- then at no cost -- or
    none of those pairs still: the camera did move).

    A still pair (:func:`~sparseart.align.still.still_pairs`: the images' shift at most a pixel,
    at least 30 % of the pixels agreeing in depth and colour) cannot come from cameras posed
    apart beyond the depth-matching tolerance (``SAME_POSE_DEG``, ``SAME_POSE_SHARE`` of the
    depth): the recorded pose is wrong -- a robot's head camera whose pose drifted between the
    states, or noise in the poses of a camera on a tripod. Views whose pictures differ (a door
    fills them) take the still views' correction when two or more still views agree on it
    (:func:`_common_placement`: the drift is the state's); otherwise they keep their poses and
    the warning says so. Measured on the real laptop capture with its end pose shifted 30 cm: two lids
    (one flagged unstable, confidence 0.44) in 65 s before, the true lid (0.4 deg, confidence
    0.93) in 10 s when placed; given world-to-camera for the end view: an internal error before,
    the true lid now. O(V H W log(H W)) for the still test of the posed-apart pairs."""
    apart, medians = [], {}
    for k in range(min(len(scene.start), len(scene.end))):
        start, end = scene.start[k], scene.end[k]
        depth = view_depth(start, lifted.pointmaps["start"][k])
        median = float(np.median(depth[depth > 0])) if depth is not None and np.any(depth > 0) else 0.0
        medians[k] = median
        if (start.camera is not None and end.camera is not None and start.camera.cam_to_world is not None
                and end.camera.cam_to_world is not None and median > 0 and not same_camera(start, end, median)):
            apart.append(k)
    if not apart:
        return None
    still = still_pairs(scene.start, scene.end, lifted.pointmaps["start"], lifted.pointmaps["end"])
    placed = [k for k in apart if still.get(k) == k]
    if not placed:
        return None
    placements = {k: scene.start[k].camera.cam_to_world @ np.linalg.inv(scene.end[k].camera.cam_to_world)
                  for k in placed}
    scene_point = np.median(valid_points(lifted.pointmaps["start"][placed[0]]), axis=0)
    common = _common_placement([placements[k] for k in placed], scene_point, SAME_POSE_SHARE * medians[placed[0]])
    others = [k for k in apart if k not in placements]
    if common is not None:     # the drift is the state's: the views whose pictures differ carry it too
        placements.update({k: common for k in others})
    end_frames, end_maps = list(scene.end), list(lifted.pointmaps["end"])
    notes = []
    for k, placement in sorted(placements.items()):
        end_pose = scene.end[k].camera.cam_to_world
        end_frames[k] = replace(end_frames[k], camera=replace(end_frames[k].camera, cam_to_world=placement @ end_pose))
        end_maps[k] = transform_pointmap(end_maps[k], placement)
        if k in placed:
            notes.append(f"end/rgb/{scene.end[k].rgb_path.name} ({np.linalg.norm(placement[:3, 3]):.3g} m, "
                         f"{np.degrees(rotation_angle(placement[:3, :3])):.2f} deg)")
    message = (f"cameras.json: {', '.join(notes)} repeat the pictures of their start views (the camera did not "
               f"move) but their cam_to_world lies apart from the start's: placed by the start poses")
    if others:
        names = ", ".join(f"end/rgb/{scene.end[k].rgb_path.name}" for k in others)
        message += (f"; {names} moved alike (the still views agree on one correction)" if common is not None
                    else f"; {names} kept their poses (their pictures differ; they may carry the same error)")
    warnings.append(message)
    return (replace(scene, end=end_frames),
            replace(lifted, pointmaps={"start": lifted.pointmaps["start"], "end": end_maps}))


def _common_placement(placements: list[np.ndarray], point: np.ndarray, tolerance: float) -> np.ndarray | None:
    """The first of two or more (4, 4) placements that agree -- turns within ``SAME_POSE_DEG`` of
    each other, and moving ``point`` (3,), a point of the scene, to within ``tolerance`` (scene
    units) of each other -- or None: one still view cannot tell a drift of the state's from its
    own. O(P)."""
    if len(placements) < 2:
        return None
    first = placements[0]
    where = first[:3, :3] @ point + first[:3, 3]
    for other in placements[1:]:
        if np.degrees(rotation_angle(other[:3, :3] @ first[:3, :3].T)) > SAME_POSE_DEG:
            return None
        if np.linalg.norm(other[:3, :3] @ point + other[:3, 3] - where) > tolerance:
            return None
    return first


def check_shared_surface(scene: Scene, pointmaps: dict[str, list[Pointmap]]) -> float:
    """The share of the end state's points (posed views, one world frame) that lie near the start
    state: within ``SHARED_RADIUS_SIZE`` x the start cloud's size (:func:`~sparseart.geometry.
    clouds.scene_size`, its median distance from its centroid) of a start point, on at most
    ``SHARED_PROBE_POINTS`` strided points per state. Returns it; raises SceneError, naming
    cameras.json and the end views, when it is below ``MIN_SHARED_SHARE``.

    Why: the object is seen in both states, so posed views whose states lie apart carry a wrong
    pose or depth unit -- a world-to-camera matrix given as cam_to_world for one state, or one
    state's depth in other units. Both had ended in an internal error of the labeler ("no usable
    segments"). The radius is a share of the object, not of the point spacing: on a clean posed
    laptop render whose lid fills the views, 1.7 % of the end points lie within 5 spacings of a
    start point, but 17 % within 0.2 x its size. Measured shares: clean posed renders (laptop,
    stapler, box, faucet, door) 0.36-1.00, a robot-shaped render 0.97, the real laptop capture
    0.98, its end camera shifted 30 cm 0.82 (not caught here); its end pose inverted, its end
    depth x10 or at the uint16 limit 0.00. O(P log P)."""
    clouds = []
    for state in STATES:
        points = np.concatenate([valid_points(p) for p in pointmaps[state]] or [np.zeros((0, 3))])
        clouds.append(points[:: max(1, len(points) // SHARED_PROBE_POINTS)])
    start, end = clouds
    if len(start) == 0 or len(end) == 0:
        return 0.0
    from scipy.spatial import cKDTree

    radius = SHARED_RADIUS_SIZE * max(scene_size(start), 1e-12)
    share = float(np.mean(cKDTree(start).query(end, distance_upper_bound=radius)[0] <= radius))
    if share < MIN_SHARED_SHARE:
        images = ", ".join(f"end/rgb/{frame.rgb_path.name}" for frame in scene.end)
        raise SceneError(f"{scene.root / 'cameras.json'}: the end views ({images}) lie apart from the start views "
                         f"({share:.1%} of their points near the start state's): check their cam_to_world (camera "
                         f"to world, not world to camera) and the depth units (depth_scale)")
    return share


def _polish_states(pointmaps: dict[str, list], poses: dict[str, list], report: dict, warnings: list[str]) -> None:
    """A feature alignment of the states that a whole-scene ICP moves by more than
    ``STATE_POLISH_MIN_DEG`` was off: the end pointmaps and poses take the ICP's correction (in
    place) before any labelling, with a warning and ``report["states"]["polish_deg"]``.

    Why: on weak texture the states' matches can be few and partly on moved parts (a desk whose
    drawers carry the handles: 38 inliers, trusted, 4.3 deg off). Then no segment stays put and a
    labeler without masks takes the whole desk for moving parts. The static scene is most of
    both clouds, so a trimmed point-to-plane ICP of the end cloud onto the start cloud
    (:func:`~sparseart.geometry.icp.icp_polish`, distance ``THRESHOLD_FRACTION`` of the scene size,
    kept only when it raises the overlap) lays it back (4.31 -> 0.01 deg). Below the threshold
    the features decide: on 32 realistic renders the ICP's corrections were 0.05-0.67 deg and
    left the end camera's error as it was (0.02-0.41 deg before, 0.01-0.66 after), and the
    labelled static part is polished later anyway (:mod:`sparseart.align.static`).
    O((N + M) log(N + M)) for the states' N + M points."""
    clouds = {state: [valid_points(p) for p in pointmaps[state]] for state in STATES}
    if not all(any(len(c) for c in clouds[state]) for state in STATES):
        return
    start, end = (np.concatenate([c for c in clouds[state] if len(c)]) for state in STATES)
    distance = THRESHOLD_FRACTION * scene_size(start)
    coarse = icp_polish(end, start, np.eye(4), distance, max_points=STATE_PROBE_POINTS)
    if coarse is None or np.degrees(rotation_angle(coarse[:3, :3])) <= STATE_PROBE_MIN_DEG:
        return
    correction = icp_polish(end, start, coarse, distance)
    if correction is None:
        return
    correction = np.asarray(correction, dtype=np.float64)
    angle = float(np.degrees(rotation_angle(correction[:3, :3])))
    if angle <= STATE_POLISH_MIN_DEG:
        return
    pointmaps["end"] = [transform_pointmap(p, correction) for p in pointmaps["end"]]
    poses["end"] = [None if pose is None else correction @ pose for pose in poses["end"]]
    report.setdefault("states", {})["polish_deg"] = angle
    warnings.append(f"the feature alignment of the states was {angle:.1f} deg off the static scene's geometry "
                    f"(weak texture?); corrected by ICP of the whole scene before labelling")


def _emptied(pointmap: Pointmap) -> Pointmap:
    """The pointmap of a view that could not be registered: same grid, no valid point."""
    return replace(pointmap, points=np.full_like(pointmap.points, np.nan), valid=np.zeros_like(pointmap.valid),
                   confidence=np.zeros_like(pointmap.confidence),
                   depth=None if pointmap.depth is None else np.zeros_like(pointmap.depth))


def _given_report(scene: Scene, how: str) -> dict:
    """Registration report of views placed by their cameras ("cameras") or a reconstructor ("model")."""
    views = [{"image": f.image, "registered": True, "how": how,
              "inliers": None, "residual": None, "scale": 1.0} for f in scene.all_frames]
    return {"views": views, "states": {"method": how, "trusted": True}}


def registration_report(registration: SceneRegistration) -> dict:
    """The JSON-ready registration report of an unposed scene.

    views: one entry per image: "image" (state/rgb/NAME), "registered", "how" ("reference" = the
        frame's own camera, "features", "geometry", "unregistered"), "inliers" (matches to the other
        registered views that agree with the poses), "residual" (their RMS distance, scene units),
        "scale" (estimated depth scale of the view, 1 = as given), "reason" (why a view was left out).
    states: "method" ("features", "still camera" -- set by :func:`align_scene` when a view's camera
        did not move: "view", "agreeing_pixels", "scale", the failed feature report under
        "features" -- or "none" when the states were left apart: failed or not
        trusted), "trusted", "matches" / "inliers" (cross-state matches / those on the static part),
        "rmse" (of the inliers), "second_motion" (support of the strongest moving part),
        "seen_through" (share of end points where the start cameras see empty space), "reason".
    noise: the depth-relative inlier threshold used (fraction of the distance from the camera);
    depth_noise: the per-pixel depth noise relative to distance (median view; ICP polish only below 0.2 %);
    seconds: wall seconds per step (match, merge, solve, geometry, polish, check).
    """
    views = []
    for view in registration.views:
        entry = {"image": view.name, "registered": view.how != "unregistered", "how": view.how,
                 "inliers": int(view.inliers), "residual": view.residual, "scale": round(float(view.scale), 5)}
        if view.reason:
            entry["reason"] = view.reason
        views.append(entry)
    states = {k: v for k, v in registration.states.items() if k not in ("untrusted",)}
    noise = registration.depth_noise
    return {"views": views, "states": states, "noise": round(float(registration.rho), 5),
            "depth_noise": round(float(noise), 6) if np.isfinite(noise) else None,
            "seconds": {k: round(v, 3) for k, v in registration.seconds.items()}}
