"""SIFT features lifted to 3D through pointmaps, and the point-cloud checks of :mod:`sparseart.align.ransac`.

Keypoints come from OpenCV SIFT (RootSIFT descriptors), restricted to pixels with a valid 3D point
(within ``LIFT_RADIUS_PX``: silhouette corners sit on the background side of the edge) and to the
caller's masks. Matches pass Lowe's ratio test and a mutual (cross) check; each match is lifted to
3D through the pointmaps of both images (nearest valid pixel within ``LIFT_RADIUS_PX``).

Cloud helpers used by the view registration: scene size and spread, the ICP polish, and the
geometric fallback for views without feature matches, verified by a free-space check.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sparseart.types import Frame, Pointmap, SceneError

# Lower than OpenCV's 0.04: rendered and indoor scenes are texture-poor; the ratio and mutual
# checks, and RANSAC after them, remove what the extra low-contrast keypoints get wrong.
SIFT_CONTRAST_THRESHOLD = 0.01
# A keypoint may sit up to this many pixels from the nearest valid pointmap pixel.
LIFT_RADIUS_PX = 2.0
THRESHOLD_FRACTION = 0.02        # RANSAC inlier threshold / ICP distance, fraction of the scene size
PLANAR_FRACTION = 0.02           # RMS spread along the 3rd principal axis / scene size: planar
GEOMETRY_MIN_OVERLAP = 0.5       # geometric fallback: accepted overlap fraction
MAX_FREE_SPACE_VIOLATION = 0.05  # geometric fallback: accepted share of points in seen-through space


class AlignmentError(SceneError):
    """Alignment failed. ``str(error)`` is one line naming the image file(s) and the problem."""


@dataclass
class FeatureMatches:
    """Matches between image(s) a and image(s) b, lifted to 3D through their pointmaps.

    points_a, points_b: (K, 3) float64, each in its pointmap's frame.
    pixels_a, pixels_b: (K, 2) float64 keypoint positions (x, y) in their image.
    n_keypoints: keypoints detected in a and in b (summed over views when pooled).
    n_ratio_passed: matches that passed the ratio and mutual checks, before dropping those
        without a valid 3D point.
    view_a, view_b: (K,) int64 view index of each match (0 for a single pair; pooled matches of
        :func:`sparseart.align.ransac.align_states` say which start / end view each came from).
    """

    points_a: np.ndarray
    points_b: np.ndarray
    pixels_a: np.ndarray
    pixels_b: np.ndarray
    n_keypoints: tuple[int, int]
    n_ratio_passed: int
    view_a: np.ndarray | None = None
    view_b: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.points_a.shape[0])

    @staticmethod
    def concatenate(parts: list["FeatureMatches"], views_a: list[int], views_b: list[int],
                    n_keypoints: tuple[int, int]) -> "FeatureMatches":
        """Pool the matches of several image pairs (pair p came from views_a[p], views_b[p])."""
        def cat(name: str, width: int) -> np.ndarray:
            arrays = [getattr(p, name) for p in parts]
            return np.concatenate(arrays) if arrays else np.zeros((0, width))
        sizes = [len(p) for p in parts]
        return FeatureMatches(cat("points_a", 3), cat("points_b", 3), cat("pixels_a", 2),
                              cat("pixels_b", 2), n_keypoints, int(sum(p.n_ratio_passed for p in parts)),
                              np.repeat(np.asarray(views_a, np.int64), sizes),
                              np.repeat(np.asarray(views_b, np.int64), sizes))


@dataclass
class ViewFeatures:
    """SIFT keypoints of one view with their lifted 3D points.

    pixels: (M, 2) float64 (x, y); descriptors: (M, 128) float32 RootSIFT; points: (M, 3) float64
    in the pointmap's frame (NaN when no valid pixel lies within ``LIFT_RADIUS_PX``).
    """

    name: str
    pixels: np.ndarray
    descriptors: np.ndarray
    points: np.ndarray


def _valid_image(pointmap: Pointmap, mask: np.ndarray | None) -> np.ndarray:
    valid = pointmap.valid.reshape(pointmap.height, pointmap.width).copy()
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != valid.shape:
            raise AlignmentError(f"mask shape {mask.shape} does not match the pointmap's "
                                 f"{valid.shape}")
        valid &= mask != 0
    return valid


def view_features(frame: Frame, pointmap: Pointmap, mask: np.ndarray | None = None,
                  max_features: int = 4000) -> ViewFeatures:
    """Detect SIFT keypoints on valid (and masked) pixels and lift them. O(H W)."""
    import cv2

    name = str(frame.rgb_path)
    height, width = pointmap.height, pointmap.width
    if frame.rgb.shape[:2] != (height, width):
        raise AlignmentError(f"{name}: image size {frame.rgb.shape[1]}x{frame.rgb.shape[0]} does not "
                             f"match its pointmap ({width}x{height})")
    valid = _valid_image(pointmap, mask)
    empty = ViewFeatures(name, np.zeros((0, 2)), np.zeros((0, 128), np.float32), np.zeros((0, 3)))
    if not valid.any():
        return empty
    radius = int(np.ceil(LIFT_RADIUS_PX))
    detect_mask = cv2.dilate(valid.astype(np.uint8) * 255, np.ones((2 * radius + 1,) * 2, np.uint8))
    rgb = np.ascontiguousarray(frame.rgb[..., :3]).astype(np.uint8)
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb
    sift = cv2.SIFT_create(nfeatures=int(max_features), contrastThreshold=SIFT_CONTRAST_THRESHOLD)
    keypoints, descriptors = sift.detectAndCompute(gray, detect_mask)
    if descriptors is None or len(keypoints) == 0:
        return empty
    pixels = np.array([kp.pt for kp in keypoints], dtype=np.float64)
    # RootSIFT: L1-normalise, square root -> Hellinger kernel under L2 distance.
    descriptors = descriptors.astype(np.float32)
    descriptors /= np.maximum(descriptors.sum(axis=1, keepdims=True), 1e-12)
    descriptors = np.sqrt(descriptors)
    return ViewFeatures(name, pixels, descriptors, lift_pixels(pointmap, pixels, valid))


def lift_pixels(pointmap: Pointmap, pixels: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """3D points (K, 3) float64 (pointmap's frame) of (K, 2) x, y pixel positions: the point of the
    nearest valid pixel within ``LIFT_RADIUS_PX``, NaN where none is that close (or the pixel lies
    outside the image). valid: (H, W) bool, default the pointmap's. O(H W) distance transform."""
    from scipy.ndimage import distance_transform_edt

    height, width = pointmap.height, pointmap.width
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    valid = _valid_image(pointmap, None) if valid is None else valid
    points = np.full((len(pixels), 3), np.nan)
    if len(pixels) == 0 or not valid.any():
        return points
    # Nearest valid pixel of every pixel (exact Euclidean distance transform, O(H W)).
    distance, (rows, cols) = distance_transform_edt(~valid, return_indices=True)
    x, y = np.nan_to_num(pixels[:, 0], nan=-1.0), np.nan_to_num(pixels[:, 1], nan=-1.0)
    inside = (x >= -0.5) & (x <= width - 0.5) & (y >= -0.5) & (y <= height - 0.5)
    r = np.rint(y.clip(0, height - 1)).astype(int)
    c = np.rint(x.clip(0, width - 1)).astype(int)
    near = inside & (distance[r, c] <= LIFT_RADIUS_PX)
    index = rows[r, c] * width + cols[r, c]
    points[near] = pointmap.points[index[near]]
    return points


def match_view_features(a: ViewFeatures, b: ViewFeatures, ratio: float = 0.75) -> FeatureMatches:
    """Ratio test (a -> b) + mutual check (b -> a), then drop matches without 3D points.

    Brute force L2: O(M_a M_b) descriptor distances.
    """
    import cv2

    n_keypoints = (int(a.pixels.shape[0]), int(b.pixels.shape[0]))
    empty = FeatureMatches(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 2)),
                           n_keypoints, 0, np.zeros(0, np.int64), np.zeros(0, np.int64))
    if min(n_keypoints) < 2:
        return empty
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    forward = matcher.knnMatch(a.descriptors, b.descriptors, k=2)
    backward = matcher.match(b.descriptors, a.descriptors)
    best_back = np.full(n_keypoints[1], -1, np.int64)
    for m in backward:
        best_back[m.queryIdx] = m.trainIdx
    ia, ib = [], []
    for pair in forward:
        if len(pair) < 2:
            continue
        best, second = pair
        if best.distance < ratio * second.distance and best_back[best.trainIdx] == best.queryIdx:
            ia.append(best.queryIdx)
            ib.append(best.trainIdx)
    ia_arr, ib_arr = np.asarray(ia, np.int64), np.asarray(ib, np.int64)
    n_passed = int(ia_arr.size)
    lifted = np.isfinite(a.points[ia_arr]).all(axis=1) & np.isfinite(b.points[ib_arr]).all(axis=1)
    ia_arr, ib_arr = ia_arr[lifted], ib_arr[lifted]
    k = int(ia_arr.size)
    return FeatureMatches(a.points[ia_arr], b.points[ib_arr], a.pixels[ia_arr], b.pixels[ib_arr],
                          n_keypoints, n_passed, np.zeros(k, np.int64), np.zeros(k, np.int64))


def match_features(frame_a: Frame, pointmap_a: Pointmap, frame_b: Frame, pointmap_b: Pointmap, *,
                   ratio: float = 0.75, max_features: int = 4000, mask_a: np.ndarray | None = None,
                   mask_b: np.ndarray | None = None) -> FeatureMatches:
    """SIFT matches between two images, lifted to 3D through their pointmaps.

    Args:
        frame_a, frame_b: frames with rgb (H, W, 3) uint8.
        pointmap_a, pointmap_b: their pointmaps (any frame; points are returned in it).
        ratio: Lowe's ratio-test threshold.
        max_features: at most this many keypoints per image (strongest first).
        mask_a, mask_b: optional (H, W) arrays; keypoints only where nonzero.

    Returns:
        FeatureMatches (possibly empty). O(H W + M_a M_b).
    """
    fa = view_features(frame_a, pointmap_a, mask_a, max_features)
    fb = view_features(frame_b, pointmap_b, mask_b, max_features)
    return match_view_features(fa, fb, ratio)


# ----------------------------------------------------------------------------- cloud helpers
def scene_size(points: np.ndarray, max_points: int = 20000) -> float:
    """Median distance of the finite points to their centroid (the scale of RANSAC thresholds)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    if points.shape[0] == 0:
        return 0.0
    if points.shape[0] > max_points:
        points = points[np.linspace(0, points.shape[0] - 1, max_points).astype(int)]
    return float(np.median(np.linalg.norm(points - points.mean(axis=0), axis=1)))


def spread(points: np.ndarray) -> np.ndarray:
    """(3,) RMS extent of the points along their principal axes, largest first. O(N)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if points.shape[0] < 2:
        return np.zeros(3)
    singular = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return np.pad(singular, (0, 3 - singular.size)) / np.sqrt(points.shape[0])


def valid_points(pointmap: Pointmap) -> np.ndarray:
    return pointmap.points[pointmap.valid & np.isfinite(pointmap.points).all(axis=1)]


def icp_polish(source: np.ndarray, target: np.ndarray, init: np.ndarray, size: float) -> np.ndarray | None:
    """Point-to-plane ICP (Tukey kernel, coarse to fine) of camera-frame ``source`` onto ``target``.

    Returns the polished (4, 4) or None when it does not improve the overlap. O(N log N)."""
    from sparseart.geometry.o3d import open3d
    o3d = open3d()
    reg = o3d.pipelines.registration
    voxel = size / 60.0
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source)).voxel_down_sample(voxel)
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target)).voxel_down_sample(voxel)
    if len(src.points) < 30 or len(tgt.points) < 30:
        return None
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=30))
    transform = init
    for distance in (4 * THRESHOLD_FRACTION * size, 2 * THRESHOLD_FRACTION * size,
                     THRESHOLD_FRACTION * size):
        estimation = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=distance))
        result = reg.registration_icp(src, tgt, distance, transform, estimation,
                                      reg.ICPConvergenceCriteria(1e-8, 1e-8, 50))
        candidate = np.asarray(result.transformation, dtype=np.float64)
        if not np.all(np.isfinite(candidate)):
            return None
        transform = candidate
    check = THRESHOLD_FRACTION * size / 2
    before = reg.evaluate_registration(src, tgt, check, init)
    after = reg.evaluate_registration(src, tgt, check, transform)
    return transform if after.fitness >= before.fitness else None


def _free_space_violation(points: np.ndarray, frame: Frame, pointmap: Pointmap, size: float) -> float:
    """Fraction of ``points`` (in ``frame``'s camera frame) that land in front of the surface the
    camera saw (or on certain background): a wrong registration puts surfaces where this view saw
    through. O(N + H W)."""
    import cv2

    h, w = pointmap.height, pointmap.width
    valid = pointmap.valid.reshape(h, w)
    # Nearest seen surface over a 5x5 window: grazing surfaces change depth quickly per pixel.
    depth = np.where(valid, np.nan_to_num(pointmap.points[:, 2].reshape(h, w)), np.inf)
    depth = cv2.erode(depth.astype(np.float32), np.ones((5, 5), np.uint8)).astype(np.float64)
    background = cv2.dilate(valid.astype(np.uint8), np.ones((7, 7), np.uint8)) == 0
    points = points[points[:, 2] > 1e-9]
    uv = points @ frame.camera.K.T
    col, row = np.rint(uv[:, 0] / uv[:, 2]).astype(int), np.rint(uv[:, 1] / uv[:, 2]).astype(int)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    if inside.sum() < 30:
        return 0.0
    row, col, z = row[inside], col[inside], points[inside, 2]
    seen = depth[row, col]
    bad = background[row, col] | (np.isfinite(seen) & (z < seen - 2 * THRESHOLD_FRACTION * size))
    return float(bad.mean())


def geometry_edge(j: int, i: int, frames: list[Frame], pointmaps: list[Pointmap], clouds: list[np.ndarray],
                   size: float, seed: int) -> tuple[np.ndarray, float, float] | None:
    """Geometric fallback view j -> view i for metric clouds in their camera frames
    (:func:`sparseart.geometry.icp.register_rigid`: PCA/FPFH hypotheses + coloured ICP).

    None for planar clouds (they slide), small overlap, or when either view sees through the other
    one's surfaces (free-space check, which rejects the turned-around fits of symmetric objects).
    Returns ((4, 4) j -> i, overlap fraction, edge weight in [0, 1)). O(N log N + H W)."""
    from sparseart.geometry.icp import register_rigid

    if min(spread(clouds[i])[2], spread(clouds[j])[2]) < PLANAR_FRACTION * size:
        return None
    colors = [frames[k].rgb.reshape(-1, 3)[pointmaps[k].valid & np.isfinite(pointmaps[k].points).all(axis=1)]
              / 255.0 for k in (j, i)]
    result = register_rigid(clouds[j], clouds[i], colors[0], colors[1], seed=seed)
    if result.inlier_fraction < GEOMETRY_MIN_OVERLAP:
        return None
    forward = np.asarray(result.transform, dtype=np.float64)
    backward = np.linalg.inv(forward)
    violation = max(
        _free_space_violation(clouds[j] @ forward[:3, :3].T + forward[:3, 3], frames[i], pointmaps[i], size),
        _free_space_violation(clouds[i] @ backward[:3, :3].T + backward[:3, 3], frames[j], pointmaps[j], size))
    if violation > MAX_FREE_SPACE_VIOLATION:
        return None
    return forward, result.inlier_fraction, 0.999 * result.inlier_fraction * (1.0 - violation)
