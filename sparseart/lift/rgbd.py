"""RGB-D lifting: depth + K (+ cam_to_world) -> per-pixel pointmap in the scene frame."""
from __future__ import annotations

import numpy as np

from ..types import Frame, Pointmap

# A pixel whose depth differs from a 4-neighbour by more than this fraction of its own depth
# lies on a depth edge; such "flying pixels" interpolate foreground and background and are dropped.
# At 320 px and a 60 deg field of view this keeps surfaces up to ~85 deg from the viewing ray.
DEFAULT_EDGE_RELATIVE_JUMP = 0.05


MIN_CONSISTENT_NEIGHBOURS = 3


def consistent_neighbour_count(depth: np.ndarray, relative_jump: float = DEFAULT_EDGE_RELATIVE_JUMP) -> np.ndarray:
    """(H, W) int: how many of a pixel's 8 neighbours are valid and within ``relative_jump`` of
    its depth (relative to its own depth). O(H W)."""
    padded = np.pad(depth, 1, mode="constant")
    height, width = depth.shape
    count = np.zeros(depth.shape, dtype=np.int64)
    tolerance = relative_jump * depth
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            if dy == 1 and dx == 1:
                continue
            neighbour = padded[dy:dy + height, dx:dx + width]
            count += (neighbour > 0) & (np.abs(neighbour - depth) <= tolerance)
    return count


def flying_pixel_mask(depth: np.ndarray, relative_jump: float = DEFAULT_EDGE_RELATIVE_JUMP) -> np.ndarray:
    """Pixels not supported by a locally consistent surface ("flying pixels").

    A valid pixel is flagged when fewer than 3 of its 8 neighbours lie within ``relative_jump``
    of its depth: isolated pixels and 1-pixel lines of depths interpolated between a foreground
    and a background. Pixels on the edge of a surface (5 consistent neighbours) and structures at
    least 2 pixels wide (a rack's wires, a handle) are kept.

    Args:
        depth: (H, W) float64 metres, 0 = invalid.

    Returns:
        (H, W) bool, True where the pixel is a flying pixel. O(H W).
    """
    return (depth > 0) & (consistent_neighbour_count(depth, relative_jump) < MIN_CONSISTENT_NEIGHBOURS)


def pixel_rays(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H*W, 3) float64 camera-frame directions with z = 1 for every pixel centre, row-major."""
    rows, cols = np.mgrid[0:height, 0:width]
    u = cols.reshape(-1).astype(np.float64)
    v = rows.reshape(-1).astype(np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    skew = K[0, 1]
    y = (v - cy) / fy
    x = (u - cx - skew * y) / fx
    return np.stack([x, y, np.ones_like(x)], axis=1)


def pointmap_from_depth(frame: Frame, cam_to_world: np.ndarray | None = None,
                        reject_flying_pixels: bool = True,
                        relative_jump: float = DEFAULT_EDGE_RELATIVE_JUMP) -> Pointmap:
    """Unproject one RGB-D frame.

    Args:
        frame: a frame with depth (H, W) float64 metres and a camera with K.
        cam_to_world: (4, 4) float64 transform to the scene frame; defaults to the frame's own
            ``camera.cam_to_world``, or identity (the camera frame) when that is None.
        reject_flying_pixels: drop pixels on depth discontinuities (see :func:`flying_pixel_mask`).

    Returns:
        Pointmap with (H*W, 3) float64 points in the scene frame (NaN where invalid) and
        confidence (H*W,) float64: the frame's ``depth_confidence`` (``conf/NNN.npy``) at valid
        pixels, or 1 there when the scene gives none; 0 at invalid pixels. O(H W).
    """
    if frame.depth is None or frame.camera is None:
        raise ValueError(f"{frame.rgb_path}: RGB-D lifting needs depth and K")
    depth = frame.depth
    height, width = depth.shape
    if cam_to_world is None:
        cam_to_world = frame.camera.cam_to_world if frame.camera.cam_to_world is not None else np.eye(4)
    valid = (depth > 0) & np.isfinite(depth)
    if reject_flying_pixels:
        valid &= ~flying_pixel_mask(depth, relative_jump)
    flat_depth = depth.reshape(-1)
    camera_points = pixel_rays(frame.camera.K, height, width) * flat_depth[:, None]
    points = camera_points @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]
    valid_flat = valid.reshape(-1)
    points[~valid_flat] = np.nan
    confidence = valid_flat.astype(np.float64)
    if frame.depth_confidence is not None:
        confidence *= np.asarray(frame.depth_confidence, dtype=np.float64).reshape(-1)
    return Pointmap(state=frame.state, frame_index=frame.index, height=height, width=width,
                    points=points, valid=valid_flat, confidence=confidence)
