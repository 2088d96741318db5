"""Global-then-local rigid registration of two (possibly partial) views of one rigid part.

Used by the joint fitter (initial motion, putative matches) and by the part labeler (does a
segment move rigidly between the states?). Hypotheses: identity, centroid shift, centroid + PCA
frame alignment with the 4 proper sign flips, and open3d FPFH + RANSAC (only when the
cheap hypotheses leave the inlier fraction below ``fpfh_below``); each is refined by
open3d point-to-plane ICP with a Tukey robust kernel (coarse then fine). The best hypothesis has
the highest symmetric inlier fraction; among near-ties the smallest rotation wins (real joints
rarely exceed 180 deg and symmetric parts such as drawer fronts create flip ambiguities).

Reproducible: subsamples come from ``numpy.random.default_rng(seed)``, open3d's RANSAC from its
seeded generator held by one call at a time (:func:`sparseart.geometry.o3d.seeded`: the
generator is process-wide), and every open3d registration call runs on one thread
(:func:`sparseart.geometry.o3d.serial`), so its parallel sums cannot change the last bits from run
to run: the same input gives the same transform, bit for bit. The hypotheses are refined side
by side in threads (:func:`sparseart.parallel.in_parallel`): each refinement is a pure function
of its inputs, so the results do not depend on the schedule.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from sparseart.geometry.clouds import median_spacing
from sparseart.geometry.o3d import open3d, seeded, serial
from sparseart.geometry.sampling import random_subset
from sparseart.geometry.transforms import apply_transform, make_transform, rotation_angle
from sparseart.parallel import in_parallel


@dataclass
class RigidRegistration:
    """Result of ``register_rigid``.

    transform: (4, 4) float64 source -> target rigid transform, in the input frame and units.
    rmse: RMS nearest-neighbour distance of inlier source points after alignment (input units).
    inlier_fraction: in [0, 1]; mean of the source->target and target->source fractions of points
        with a neighbour closer than the inlier distance (partial views give < 1).
    correspondences: (K, 2) int64 rows (source index, target index) of inlier nearest neighbours
        over the full input clouds.
    diagnostics: hypotheses tried, their scores, the inlier distance.
    """

    transform: np.ndarray
    rmse: float
    inlier_fraction: float
    correspondences: np.ndarray
    diagnostics: dict = field(default_factory=dict)


def _pca_frame(points: np.ndarray) -> np.ndarray:
    centred = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    frame = vt.T
    if np.linalg.det(frame) < 0:
        frame[:, 2] *= -1
    return frame


def _hypotheses(source: np.ndarray, target: np.ndarray) -> list[tuple[str, np.ndarray]]:
    source_centre, target_centre = source.mean(axis=0), target.mean(axis=0)
    hypotheses = [("identity", np.eye(4)),
                  ("centroid", make_transform(np.eye(3), target_centre - source_centre))]
    if source.shape[0] >= 4 and target.shape[0] >= 4:
        source_frame, target_frame = _pca_frame(source), _pca_frame(target)
        for flip in ([1, 1, 1], [-1, -1, 1], [-1, 1, -1], [1, -1, -1]):
            rotation = target_frame @ np.diag(flip) @ source_frame.T
            hypotheses.append((f"pca{flip}", make_transform(rotation, target_centre - rotation @ source_centre)))
    return hypotheses


def _o3d_cloud(points: np.ndarray, radius: float | None = None):
    """open3d cloud of (N, 3) float64 points, with normals from a hybrid search of ``radius`` (30
    neighbours at most; per point, so reproducible) when one is given. O(N log N)."""
    o3d = open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if radius is not None:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
    return cloud


def _fpfh_hypothesis(source_cloud, target_cloud, voxel: float, seed: int) -> np.ndarray | None:
    """open3d FPFH + RANSAC on one thread with a seeded generator, one call at a time
    (:func:`~sparseart.geometry.o3d.seeded`: reproducible from threads too); None when it fails.
    Roughly O(N log N) for features + RANSAC."""
    with seeded(seed) as o3d:
        reg = o3d.pipelines.registration
        try:
            param = o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100)
            source_feature = reg.compute_fpfh_feature(source_cloud, param)
            target_feature = reg.compute_fpfh_feature(target_cloud, param)
            result = reg.registration_ransac_based_on_feature_matching(
                source_cloud, target_cloud, source_feature, target_feature, True, 1.5 * voxel,
                reg.TransformationEstimationPointToPoint(False), 3,
                [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                 reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
                reg.RANSACConvergenceCriteria(5000, 0.999))
            transform = np.array(result.transformation, dtype=np.float64)
            matched = len(result.correspondence_set)
        except RuntimeError:
            return None
    return transform if np.all(np.isfinite(transform)) and matched >= 3 else None


def tukey_icp(source_cloud, target_cloud, init: np.ndarray, distances: tuple[float, ...], *,
              tolerance: float = 1e-7, iterations: int = 40, strict: bool = True) -> np.ndarray | None:
    """THE coarse-to-fine ICP of the project: point-to-plane with a Tukey kernel (open3d) at each of
    ``distances`` in turn (point-to-point when the target has no normals).

    source_cloud / target_cloud: open3d point clouds (one frame, one unit); init: (4, 4) float64.
    A non-finite step returns None with ``strict`` and is skipped otherwise. Runs open3d on one
    thread (:func:`sparseart.geometry.o3d.serial`): the same input gives the same transform, bit for
    bit. O(I N log M) for I iterations over N source and M target points.
    """
    reg = open3d().pipelines.registration
    transform = init
    for distance in distances:
        if target_cloud.has_normals():
            estimation = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=distance))
        else:
            estimation = reg.TransformationEstimationPointToPoint(False)
        with serial():
            result = reg.registration_icp(source_cloud, target_cloud, distance, transform, estimation,
                                          reg.ICPConvergenceCriteria(tolerance, tolerance, iterations))
        candidate = np.asarray(result.transformation, dtype=np.float64)
        if np.all(np.isfinite(candidate)):
            transform = candidate
        elif strict:
            return None
    return transform


def _score(source: np.ndarray, target: np.ndarray, target_tree: cKDTree, transform: np.ndarray,
           inlier_distance: float) -> tuple[float, float]:
    """(inlier_fraction, rmse) of a transform; O((N + M) log(N + M)). Only inlier distances are
    read, so the searches stop at ``inlier_distance``."""
    moved = apply_transform(transform, source)
    forward, _ = target_tree.query(moved, distance_upper_bound=inlier_distance)
    backward, _ = cKDTree(moved).query(target, distance_upper_bound=inlier_distance)
    inlier = forward < inlier_distance
    fraction = 0.5 * (inlier.mean() + (backward < inlier_distance).mean())
    rmse = float(np.sqrt(np.mean(forward[inlier] ** 2))) if inlier.any() else float("inf")
    return float(fraction), rmse


def _refine(name, start, source_cloud, target_cloud, schedule, source_sub, target_sub, target_tree,
            inlier_distance) -> dict:
    refined = tukey_icp(source_cloud, target_cloud, start, schedule, strict=False)
    fraction, rmse = _score(source_sub, target_sub, target_tree, refined, inlier_distance)
    return {"name": name, "transform": refined, "inlier_fraction": fraction, "rmse": rmse,
            "angle_deg": float(np.degrees(rotation_angle(refined[:3, :3])))}


def register_rigid(
    source: np.ndarray,
    target: np.ndarray,
    source_colors: np.ndarray | None = None,
    target_colors: np.ndarray | None = None,
    init: np.ndarray | None = None,
    max_points: int = 2000,
    inlier_factor: float = 3.0,
    use_fpfh: bool = True,
    fpfh_below: float = 0.7,
    tie_tolerance: float = 0.03,
    seed: int = 0,
    hypotheses: Sequence[np.ndarray] | None = None,
    agreement: Callable[[np.ndarray], float] | None = None,
) -> RigidRegistration:
    """Rigidly align ``source`` (N, 3) onto ``target`` (M, 3), both float64 in one frame.

    Both clouds may be partial views of the same rigid part. ``init``: optional (4, 4) source ->
    target guess; when given only it is refined, otherwise all hypotheses are tried (module doc).
    Colours (N, 3)/(M, 3) in [0, 1], when both are given, drive a final open3d coloured-ICP polish
    (kept only if it does not lower the inlier fraction). ``hypotheses``: (4, 4) source -> target
    starting guesses in input units, tried in place of the built-in ones (``init`` still wins).
    ``agreement``: a weight in [0, 1] of a (4, 4) source -> target transform in input units (for
    instance the share of labelled points whose mask ids agree); hypotheses are then ranked by
    inlier fraction x agreement instead of the inlier fraction alone. Work happens on random subsamples of at
    most ``max_points`` per cloud, in coordinates normalised by the joint RMS radius; the
    inlier distance is ``inlier_factor`` x the median point spacing. Cost about
    O(H * max_points log max_points) for H hypotheses plus O((N + M) log(N + M)) for the final
    correspondences. Raises ValueError for fewer than 3 finite points per cloud.
    """
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    for name, cloud in (("source", source), ("target", target)):
        if cloud.ndim != 2 or cloud.shape[1] != 3 or cloud.shape[0] < 3 or not np.all(np.isfinite(cloud)):
            raise ValueError(f"register_rigid: {name} must be finite (N >= 3, 3), got shape {cloud.shape}")
    rng = np.random.default_rng(seed)
    centre = np.concatenate([source, target]).mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((np.concatenate([source, target]) - centre) ** 2, axis=1))))
    if not scale > 0:
        raise ValueError("register_rigid: all points coincide")
    normalise = make_transform(np.eye(3) / scale, -centre / scale)
    denormalise = np.linalg.inv(normalise)
    source_n, target_n = (source - centre) / scale, (target - centre) / scale
    source_sub = source_n[random_subset(source_n.shape[0], max_points, rng)]
    target_sub = target_n[random_subset(target_n.shape[0], max_points, rng)]
    resolution = max(median_spacing(source_sub), median_spacing(target_sub))
    inlier_distance = inlier_factor * resolution
    target_tree = cKDTree(target_sub)
    source_cloud = _o3d_cloud(source_sub)
    target_cloud = _o3d_cloud(target_sub, radius=4.0 * resolution)
    coarse = max(0.3, 10.0 * resolution)
    schedule = (coarse, max(3.0 * inlier_distance, coarse / 4.0), inlier_distance)
    def scored(result: dict) -> dict:
        weight = 1.0 if agreement is None else float(agreement(denormalise @ result["transform"] @ normalise))
        result["score"] = result["inlier_fraction"] * weight
        return result

    if init is not None:
        starts = [("init", normalise @ np.asarray(init, dtype=np.float64) @ denormalise)]
    elif hypotheses is not None:
        starts = [(f"given{k}", normalise @ np.asarray(h, dtype=np.float64) @ denormalise)
                  for k, h in enumerate(hypotheses)]
    else:
        starts = _hypotheses(source_sub, target_sub)
    if len(starts) > 1:  # screen the hypotheses cheaply on a coarser subsample, refine the best 2
        coarse_pick = random_subset(source_sub.shape[0], max(max_points // 3, 50), rng)
        coarse_cloud = _o3d_cloud(source_sub[coarse_pick])
        screened = in_parallel(lambda item: scored(_refine(item[0], item[1], coarse_cloud, target_cloud, schedule[:2],
                                                           source_sub[coarse_pick], target_sub, target_tree,
                                                           schedule[1])), starts)
        screened.sort(key=lambda r: (-round(r["score"], 2), r["angle_deg"]))
        starts = [(r["name"], r["transform"]) for r in screened[:2]]
    results = in_parallel(lambda item: scored(_refine(item[0], item[1], source_cloud, target_cloud, schedule[1:],
                                                      source_sub, target_sub, target_tree, inlier_distance)), starts)
    if init is None and use_fpfh and max(r["inlier_fraction"] for r in results) < fpfh_below \
            and min(len(source_sub), len(target_sub)) >= 30:
        # The cheap hypotheses did not explain the data: try features (about 0.2-1 s).
        source_cloud.estimate_normals(open3d().geometry.KDTreeSearchParamHybrid(radius=4.0 * resolution, max_nn=30))
        fpfh = _fpfh_hypothesis(source_cloud, target_cloud, 2.0 * resolution, seed)
        if fpfh is not None:
            results.append(scored(_refine("fpfh", fpfh, source_cloud, target_cloud, schedule, source_sub,
                                          target_sub, target_tree, inlier_distance)))
    best_score = max(r["score"] for r in results)
    best_rmse = min(r["rmse"] for r in results if r["score"] >= best_score - tie_tolerance)
    ties = [r for r in results if r["score"] >= best_score - tie_tolerance
            and r["rmse"] <= 1.5 * best_rmse + 1e-12]
    chosen = min(ties, key=lambda r: r["angle_deg"])
    transform = chosen["transform"]
    if source_colors is not None and target_colors is not None:
        transform = _colored_polish(source_n, target_n, source_colors, target_colors, transform,
                                    inlier_distance, resolution, target_tree, source_sub, target_sub, rng,
                                    max_points, chosen["inlier_fraction"])
    # Full-resolution correspondences: only inliers are kept, so the search stops at the inlier
    # distance (without the bound, a far hypothesis walks the whole tree for every point: 39 % of
    # the time of the geometric view fallback on a realistic toaster; same rows either way).
    moved_full = apply_transform(transform, source_n)
    full_distance, full_index = cKDTree(target_n).query(moved_full, distance_upper_bound=inlier_distance)
    inlier_full = full_distance < inlier_distance
    fraction, rmse = _score(source_sub, target_sub, target_tree, transform, inlier_distance)
    correspondences = np.stack([np.flatnonzero(inlier_full), full_index[inlier_full]], axis=1).astype(np.int64)
    diagnostics = {
        "hypotheses": [{k: v for k, v in r.items() if k != "transform"} for r in results],
        "chosen": chosen["name"],
        "inlier_distance": inlier_distance * scale,
        "scale": scale,
    }
    return RigidRegistration(denormalise @ transform @ normalise, rmse * scale, fraction, correspondences,
                             diagnostics)


def _colored_polish(source_n, target_n, source_colors, target_colors, transform, inlier_distance,
                    resolution, target_tree, source_sub, target_sub, rng, max_points, fraction):
    """open3d coloured ICP (one thread, reproducible) on subsamples; returns the better of the
    polished and given transform. O(I N log N) for I <= 30 iterations over N <= max_points."""
    o3d = open3d()
    reg = o3d.pipelines.registration
    try:
        pick_s = random_subset(source_n.shape[0], max_points, rng)
        pick_t = random_subset(target_n.shape[0], max_points, rng)
        source_cloud = _o3d_cloud(source_n[pick_s], radius=4.0 * resolution)
        target_cloud = _o3d_cloud(target_n[pick_t], radius=4.0 * resolution)
        source_cloud.colors = o3d.utility.Vector3dVector(np.asarray(source_colors, np.float64)[pick_s])
        target_cloud.colors = o3d.utility.Vector3dVector(np.asarray(target_colors, np.float64)[pick_t])
        with serial():
            result = reg.registration_colored_icp(source_cloud, target_cloud, inlier_distance, transform,
                                                  reg.TransformationEstimationForColoredICP(),
                                                  reg.ICPConvergenceCriteria(1e-7, 1e-7, 30))
        polished = np.asarray(result.transformation, dtype=np.float64)
    except RuntimeError:
        return transform
    if not np.all(np.isfinite(polished)):
        return transform
    new_fraction, _ = _score(source_sub, target_sub, target_tree, polished, inlier_distance)
    return polished if new_fraction >= fraction else transform


def icp_polish(source: np.ndarray, target: np.ndarray, init: np.ndarray, distance: float, *,
               max_points: int | None = None) -> np.ndarray | None:
    """Polish a registration of ``source`` onto ``target`` ((N, 3), (M, 3) float64, one frame and
    unit) with :func:`tukey_icp` at 4, 2 and 1 times ``distance`` (voxel 1/60 of 50 x distance).

    max_points: when given, the voxel grows (x 1.5 per step) until each downsampled cloud holds at
    most this many points -- a spatially even subsample that bounds the cost on wide scenes (a
    room around the object keeps 130k of 225k points at the default voxel).

    Returns the polished (4, 4) source -> target, or None when it does not raise the share of points
    within ``distance / 2`` (or the clouds are too small or the result is not finite). Reproducible:
    the ICP runs on one thread and the fitness is an exact count. O(N log N).
    """
    o3d = open3d()
    reg = o3d.pipelines.registration
    voxel = distance / (60.0 * 0.02)
    source_cloud, target_cloud = _o3d_cloud(source), _o3d_cloud(target)
    src = source_cloud.voxel_down_sample(voxel)
    tgt = target_cloud.voxel_down_sample(voxel)
    while max_points is not None and max(len(src.points), len(tgt.points)) > max_points:
        voxel *= 1.5
        src = source_cloud.voxel_down_sample(voxel)
        tgt = target_cloud.voxel_down_sample(voxel)
    if len(src.points) < 30 or len(tgt.points) < 30:
        return None
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=30))
    transform = tukey_icp(src, tgt, init, (4 * distance, 2 * distance, distance), tolerance=1e-8, iterations=50)
    if transform is None:
        return None
    before = reg.evaluate_registration(src, tgt, distance / 2, init)
    after = reg.evaluate_registration(src, tgt, distance / 2, transform)
    return transform if after.fitness >= before.fitness else None
