"""The classic baseline: segment the moving points, register each moving part between the two
states with open3d's ICP, read the screw axis off the transform.

Registration per part (open3d 0.20):

1. voxel down-sampling (voxel = part bounding-box diagonal / ``PeerOptions.voxel_divisions``),
   normals by hybrid KD-tree search, FPFH features;
2. global registration by RANSAC on FPFH matches (``registration_ransac_based_on_feature_matching``)
   and the identity, each refined by point-to-plane ICP with a Tukey robust kernel
   (``TransformationEstimationPointToPlane(TukeyLoss(k))``, k = 2 voxels); the refined transform
   with the higher fitness (then lower RMSE) wins;
3. the start->end transform is decomposed by ``sparseart.geometry.transforms.screw_from_transform``; the
   type follows ArtGS's ``cal_art_type`` rule: rotation above ``revolute_min_deg`` (10 deg) ->
   revolute (axis, pivot, angle), else prismatic (translation direction and length).

Segmentation: two routes, both ground-truth free.

* ``"labels"`` (default, used by ``sparseart bench``): the part labels the sparseart labeler put on
  the same lifted clouds. The peer then differs from sparseart only in the joint estimation
  (ICP + screw read-out vs sparseart's joint fitter), so the comparison isolates that stage and
  multi-part objects keep their part correspondence.
* ``"motion"``: the textbook route without any labeler -- end points farther than a threshold
  from every start point (and vice versa) are "moving"; DBSCAN splits them into parts; start and
  end clusters are paired by the Hungarian algorithm on centroid distance. It needs the states in
  one frame (posed scenes, or clouds already aligned).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from sparseart.geometry.transforms import screw_from_transform, transform_from_prismatic, transform_from_revolute
from sparseart.types import Articulation, JointEstimate, LabelledCloud, PartLabels, PartResult, PartSpec, StageRecord

MIN_PART_POINTS = 20


@dataclass
class PeerOptions:
    """Knobs of the ICP peer.

    segmentation: "labels" (the labeler's parts) or "motion" (threshold + DBSCAN, see module doc).
    voxel_divisions: voxel size = part bbox diagonal / this. revolute_min_deg: ArtGS's type rule.
    tukey_k_voxels: Tukey kernel width in voxels. icp_distance_voxels: ICP correspondence radius in
    voxels. ransac_iterations / ransac_confidence: global registration budget.
    motion_threshold: "motion" route -- a point moved when its nearest neighbour in the other state
    is farther than this fraction of the object's bbox diagonal. dbscan_eps: fraction of the
    diagonal; dbscan_min_points: DBSCAN core size.
    """

    segmentation: str = "labels"
    voxel_divisions: float = 40.0
    revolute_min_deg: float = 10.0
    tukey_k_voxels: float = 2.0
    icp_distance_voxels: float = 3.0
    ransac_iterations: int = 20000
    ransac_confidence: float = 0.999
    motion_threshold: float = 0.02
    dbscan_eps: float = 0.03
    dbscan_min_points: int = 10
    seed: int = 0
    warnings: list[str] = field(default_factory=list)


def _cloud(points: np.ndarray, voxel: float):
    from sparseart.geometry.o3d import open3d

    o3d = open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    cloud = cloud.voxel_down_sample(voxel)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
    return cloud


def register_part_icp(start_points: np.ndarray, end_points: np.ndarray,
                      options: PeerOptions | None = None) -> tuple[np.ndarray, dict]:
    """Start->end rigid motion of one part by FPFH + RANSAC and robust point-to-plane ICP.

    start_points (N, 3), end_points (M, 3): float64, one frame, any units (N, M >= 20).
    Returns the (4, 4) float64 transform and diagnostics {"fitness", "rmse", "init"}.
    Cost: O((N + M) log(N + M)) for down-sampling, normals and FPFH, plus the RANSAC budget.
    Raises ValueError for too few points.
    """
    from sparseart.geometry.o3d import open3d

    o3d = open3d()
    reg = o3d.pipelines.registration
    options = options or PeerOptions()
    start_points = np.asarray(start_points, dtype=np.float64)
    end_points = np.asarray(end_points, dtype=np.float64)
    if len(start_points) < MIN_PART_POINTS or len(end_points) < MIN_PART_POINTS:
        raise ValueError(f"icp peer: a part needs at least {MIN_PART_POINTS} points per state, got "
                         f"{len(start_points)} and {len(end_points)}")
    both = np.concatenate([start_points, end_points])
    diagonal = float(np.linalg.norm(both.max(0) - both.min(0)))
    if not diagonal > 0:
        raise ValueError("icp peer: the part's points coincide")
    voxel = diagonal / options.voxel_divisions
    source, target = _cloud(start_points, voxel), _cloud(end_points, voxel)
    feature_param = o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100)
    source_fpfh = reg.compute_fpfh_feature(source, feature_param)
    target_fpfh = reg.compute_fpfh_feature(target, feature_param)
    o3d.utility.random.seed(options.seed)
    distance = 1.5 * voxel
    ransac = reg.registration_ransac_based_on_feature_matching(
        source, target, source_fpfh, target_fpfh, True, distance,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(options.ransac_iterations, options.ransac_confidence))
    estimation = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=options.tukey_k_voxels * voxel))
    criteria = reg.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=60)
    best, best_init = None, ""
    for init_name, init in (("fpfh+ransac", np.asarray(ransac.transformation)), ("identity", np.eye(4))):
        refined = reg.registration_icp(source, target, options.icp_distance_voxels * voxel, init,
                                       estimation, criteria)
        if best is None or (refined.fitness, -refined.inlier_rmse) > (best.fitness, -best.inlier_rmse):
            best, best_init = refined, init_name
    transform = np.asarray(best.transformation, dtype=np.float64).copy()
    return transform, {"fitness": float(best.fitness), "rmse": float(best.inlier_rmse), "init": best_init,
                       "voxel": voxel}


def joint_from_transform(transform: np.ndarray, start_points: np.ndarray, fitness: float, rmse: float,
                         revolute_min_deg: float = 10.0) -> JointEstimate:
    """Read a joint off a start->end (4, 4) transform (screw decomposition).

    Revolute when the rotation exceeds ``revolute_min_deg`` degrees: axis and angle of the screw,
    origin = the point of the screw axis nearest the part centre. Otherwise prismatic: axis =
    translation of the part centre normalised, distance = its length, origin = the part centre.
    ``uncertainty`` is NaN-free but uninformative (the peer has no error model): all zeros.
    """
    centre = np.asarray(start_points, dtype=np.float64).mean(axis=0)
    screw = screw_from_transform(transform[:3, :3], transform[:3, 3], reference=centre)
    confidence = float(np.clip(fitness, 0.0, 1.0))
    if screw.axis_defined and math.degrees(abs(screw.angle)) > revolute_min_deg:
        axis, angle = screw.axis, float(screw.angle)
        if angle < 0:
            axis, angle = -axis, -angle
        return JointEstimate(type="revolute", axis=axis, origin=screw.pivot, angle=angle, distance=None,
                             transform=transform_from_revolute(axis, screw.pivot, angle),
                             uncertainty={"axis_deg": 0.0, "origin": 0.0, "angle": 0.0}, residual=rmse,
                             confidence=confidence, slide=float(screw.slide))
    shift = transform[:3, :3] @ centre + transform[:3, 3] - centre
    distance = float(np.linalg.norm(shift))
    axis = shift / distance if distance > 0 else np.array([0.0, 0.0, 1.0])
    return JointEstimate(type="prismatic", axis=axis, origin=centre, angle=None, distance=distance,
                         transform=transform_from_prismatic(axis, distance),
                         uncertainty={"axis_deg": 0.0, "origin": 0.0, "distance": 0.0}, residual=rmse,
                         confidence=confidence, slide=distance)


def motion_labels(start: LabelledCloud, end: LabelledCloud, options: PeerOptions) -> PartLabels:
    """The "motion" segmentation route: static = points with a close partner in the other state,
    moving points clustered by DBSCAN, start/end clusters paired by Hungarian on centroid distance.
    Both clouds must be in one frame. O((N + M) log(N + M)) plus DBSCAN."""
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial import cKDTree

    from sparseart.geometry.o3d import open3d

    o3d = open3d()
    both = np.concatenate([start.points, end.points])
    diagonal = float(np.linalg.norm(both.max(0) - both.min(0)))
    threshold = options.motion_threshold * diagonal
    start_moved = cKDTree(end.points).query(start.points, k=1)[0] > threshold
    end_moved = cKDTree(start.points).query(end.points, k=1)[0] > threshold

    def clusters(points: np.ndarray) -> np.ndarray:
        if len(points) == 0:
            return np.zeros(0, dtype=np.int64)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        return np.asarray(cloud.cluster_dbscan(options.dbscan_eps * diagonal, options.dbscan_min_points),
                          dtype=np.int64)

    start_ids, end_ids = clusters(start.points[start_moved]), clusters(end.points[end_moved])
    start_part = np.where(start_moved, -1, 0).astype(np.int64)
    end_part = np.where(end_moved, -1, 0).astype(np.int64)
    start_keys = [k for k in np.unique(start_ids) if k >= 0 and np.sum(start_ids == k) >= MIN_PART_POINTS]
    end_keys = [k for k in np.unique(end_ids) if k >= 0 and np.sum(end_ids == k) >= MIN_PART_POINTS]
    parts = [PartSpec(0, "static")]
    if start_keys and end_keys:
        start_centres = np.array([start.points[start_moved][start_ids == k].mean(0) for k in start_keys])
        end_centres = np.array([end.points[end_moved][end_ids == k].mean(0) for k in end_keys])
        rows, cols = linear_sum_assignment(np.linalg.norm(start_centres[:, None] - end_centres[None], axis=2))
        start_index, end_index = np.flatnonzero(start_moved), np.flatnonzero(end_moved)
        for part_id, (r, c) in enumerate(zip(rows, cols), start=1):
            start_part[start_index[start_ids == start_keys[r]]] = part_id
            end_part[end_index[end_ids == end_keys[c]]] = part_id
            parts.append(PartSpec(part_id, "movable", parent=0))
    return PartLabels(parts=parts, start_part=start_part, end_part=end_part)


def icp_peer(start: LabelledCloud, end: LabelledCloud, labels: PartLabels | None = None,
             options: PeerOptions | None = None, frame: tuple[str, str, str] = ("world", "given clouds", "metres"),
             stages: list[StageRecord] | None = None) -> Articulation:
    """Run the peer on two clouds in one frame.

    labels: the parts to register ("labels" route; required then); ignored for "motion".
    stages: records of the work shared with sparseart (lift, align, label) to report beside the
    peer's own "peer_register" stage. Returns an :class:`Articulation` like ``sparseart.run``, so
    ``sparseart.evaluate.evaluate`` scores it unchanged. Parts that fail get a warning, no joint.
    """
    options = options or PeerOptions()
    records = [s for s in (stages or []) if s.name != "fit" and s.name.split(".")[0] != "refine"]
    warnings: list[str] = []
    began = time.perf_counter()
    if options.segmentation == "motion":
        labels = motion_labels(start, end, options)
    elif options.segmentation != "labels":
        raise ValueError(f"icp peer: segmentation must be 'labels' or 'motion', got {options.segmentation!r}")
    elif labels is None:
        raise ValueError("icp peer: segmentation 'labels' needs the labeler's PartLabels")
    segment_seconds = time.perf_counter() - began
    if options.segmentation == "motion":
        records.append(StageRecord("peer_segment", True, segment_seconds, "moved points + DBSCAN"))
    began = time.perf_counter()
    parts = []
    for spec in labels.parts:
        start_mask, end_mask = labels.start_part == spec.id, labels.end_part == spec.id
        result = PartResult(spec=spec, n_points=int(start_mask.sum() + end_mask.sum()))
        parts.append(result)
        if spec.role != "movable":
            continue
        try:
            transform, info = register_part_icp(start.points[start_mask], end.points[end_mask], options)
        except ValueError as error:
            warnings.append(f"part {spec.id}: {error}")
            continue
        result.joint = joint_from_transform(transform, start.points[start_mask], info["fitness"], info["rmse"],
                                            options.revolute_min_deg)
        result.joint.diagnostics.update(info)
    records.append(StageRecord("peer_register", True, time.perf_counter() - began,
                               "open3d FPFH+RANSAC, point-to-plane ICP (Tukey), screw read-out"))
    return Articulation(frame_kind=frame[0], frame_reference=frame[1], units=frame[2], parts=parts,
                        stages=records, warnings=warnings, start_cloud=start, end_cloud=end, labels=labels)


def icp_peer_from_result(result: Articulation, options: PeerOptions | None = None) -> Articulation:
    """The peer on the clouds (already lifted and, if unposed, aligned) and labels of a sparseart
    result; the shared stages' times are carried over so the totals are comparable."""
    if result.start_cloud is None or result.end_cloud is None:
        raise ValueError("icp peer: the sparseart result carries no clouds")
    return icp_peer(result.start_cloud, result.end_cloud, result.labels, options,
                    frame=(result.frame_kind, result.frame_reference, result.units), stages=result.stages)


__all__ = ["PeerOptions", "icp_peer", "icp_peer_from_result", "joint_from_transform", "motion_labels",
           "register_part_icp"]
