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


