"""Mask-to-point label transfer through the pixel grid.

Row-major pixel index ``k`` of an ``H x W`` image is pixel ``(k // W, k % W)``; a pointmap stores
its points in that order, so the label of point ``k`` is ``mask.reshape(-1)[k]``.
"""
from __future__ import annotations

import cv2
import numpy as np

from ..types import Frame, LabelledCloud, Pointmap

SEGMENT_STRIDE = 1 << 16  # segment id = frame_index * SEGMENT_STRIDE + mask id (masks are <= uint16)

# Points of frames with a depth confidence map (``conf/NNN.npy``) whose confidence is below this
# are left out of the labelled clouds (smeared depth edges, hole rims, strongly warped regions);
# frames without a map lose nothing. 0 = off, the default, because dropping hurt on average
# (experiment EXP-011: 7 rendered realistic objects, posed and unposed):
# at 0.15 all three prismatic joints of the posed scenes (and the unposed dishwasher) turned
# revolute (~85-90 deg off): the dropped points are edges and grazing side walls, unevenly in the
# two states, and they carry the slide direction; unposed registrations did improve (median axis
# 3.1 -> 2.3 deg). At 0.05 a posed door, the unposed dishwasher and an unposed storage drawer
# failed instead. Pass ``min_confidence`` to use it.
DEPTH_CONFIDENCE_MIN = 0.0

# A mask segment that the boundary rule would nearly erase is a thin structure (a wire rack, a
# rod): a strip w pixels wide keeps (w - 2) / w of its pixels, so under this share it is less than
# ~2.5 px wide and every pixel of it touches another label. Under smeared depth its neighbours sit
# at similar depths, so the rule would drop the whole part: such a segment keeps its boundary
# pixels (their depth is the only evidence of the part). Measured on the 16 realistic renders: an
# oven's wire racks keep 3-14 % (all 18 rack segments), the widest sliver of a solid part 28 % (a
# laptop base seen past its lid, whose hinge-side pixels must stay dropped: keeping them turned
# the lid's axis 45 deg); at 0.5 that sliver counted as thin.
THIN_SEGMENT_KEEP_SHARE = 0.2


def mask_boundary(mask: np.ndarray, depth: np.ndarray | None = None, relative_jump: float = 0.05) -> np.ndarray:
    """(H, W) bool: pixels next to a 4-neighbour with another label.

    With ``depth`` ((H, W) metres), only label changes between pixels at similar depth count
    (|d - d_n| <= relative_jump * d): there the depth cannot tell which side a pixel belongs to.
    Across a depth edge the depth decides, so thin structures (wires, handles) keep their labels.
    O(H W).
    """
    boundary = np.zeros(mask.shape, dtype=bool)
    for axis in (0, 1):
        a = [slice(None), slice(None)]
        b = [slice(None), slice(None)]
        a[axis], b[axis] = slice(1, None), slice(None, -1)
        differs = mask[tuple(a)] != mask[tuple(b)]
        if depth is not None:
            near, far = depth[tuple(a)], depth[tuple(b)]
            differs &= np.abs(near - far) <= relative_jump * np.maximum(near, far)
        boundary[tuple(a)] |= differs
        boundary[tuple(b)] |= differs
    return boundary


def without_ambiguous_boundaries(mask: np.ndarray, depth: np.ndarray | None, valid: np.ndarray,
                                 keep_share: float = THIN_SEGMENT_KEEP_SHARE) -> np.ndarray:
    """(H, W) mask with its ambiguous boundary pixels (:func:`mask_boundary`) set to 0, except in
    thin segments: an id whose valid pixels would fall below ``keep_share`` of their count keeps
    them all, but only its front layer (:func:`seen_through` pixels set to 0). mask (H, W) int;
    depth (H, W) metres or None; valid (H, W) bool. O(H W (1 + thin ids))."""
    boundary = mask_boundary(mask, depth)
    ids = np.asarray(mask, dtype=np.int64)
    bins = int(ids.max()) + 1 if ids.size else 1
    total = np.bincount(ids[valid], minlength=bins)
    kept = np.bincount(ids[valid & ~boundary], minlength=bins)
    thin = (kept < keep_share * total) & (total > 0)
    thin[0] = False
    cleaned = np.where(boundary & ~thin[ids], 0, mask)
    if depth is not None and thin.any():
        cleaned = np.where(seen_through(ids, depth, valid, np.flatnonzero(thin)), 0, cleaned)
    return cleaned


# A mask of a see-through part (a wire rack, a grille) also covers what is seen between its wires.
# Pixels of a thin segment this far (relative) behind the nearest depth of the same segment within
# SEE_THROUGH_WINDOW px belong to the layer behind it. Measured on a smeared, ragged-masked oven
# rack: the wire pixels lie a median 2-3.5 % behind that front, the pixels seen through 6-8 %.
SEE_THROUGH_GAP = 0.045
SEE_THROUGH_WINDOW = 7


def seen_through(ids: np.ndarray, depth: np.ndarray, valid: np.ndarray, which: np.ndarray) -> np.ndarray:
    """(H, W) bool: valid pixels of the ids ``which`` more than ``SEE_THROUGH_GAP`` (relative)
    behind the nearest valid pixel of the same id within a ``SEE_THROUGH_WINDOW`` square.
    ids (H, W) int64; depth (H, W) metres; valid (H, W) bool. O(H W x len(which))."""
    behind = np.zeros(ids.shape, dtype=bool)
    kernel = np.ones((SEE_THROUGH_WINDOW, SEE_THROUGH_WINDOW), np.uint8)
    for value in which:
        own = valid & (ids == value) & (depth > 0)
        front = cv2.erode(np.where(own, depth, np.inf).astype(np.float32), kernel).astype(np.float64)
        behind |= own & (depth > (1.0 + SEE_THROUGH_GAP) * front)
    return behind


def segment_id(frame_index: int, mask_id: int) -> int:
    """State-wide segment id of mask ``mask_id`` in frame ``frame_index``."""
    return int(frame_index) * SEGMENT_STRIDE + int(mask_id)


def build_labelled_cloud(state: str, frames: list[Frame], pointmaps: list[Pointmap],
                         drop_mask_boundaries: bool = True, drop_background: bool = False,
                         min_confidence: float | None = None) -> LabelledCloud:
    """Concatenate the valid points of a state's frames and copy mask labels onto them.

    Args:
        state: "start" or "end".
        frames: the state's frames (rgb (H, W, 3) uint8, optional mask (H, W) int64).
        pointmaps: one per frame, same order; points (H*W, 3) float64 in the scene frame.
        drop_mask_boundaries: label pixels on a mask boundary -1 (their depth may belong to either
            side), keeping the points themselves.
        drop_background: leave out the points of mask-0 pixels (user masks: 0 = not the object,
            e.g. a table, a wall, a hand); boundary pixels are kept. Frames without masks keep all.
        min_confidence: in frames with a depth confidence map (``frame.depth_confidence``), leave
            out the points whose pointmap confidence is below this (default
            ``DEPTH_CONFIDENCE_MIN`` = 0: keep all); frames without a map keep every valid point.

    Returns:
        LabelledCloud with (N, 3) float64 points and their pointmap confidence (N,) float64;
        ``segment`` is -1 for background (mask 0), boundaries and frames without masks.
        O(total pixels).
    """
    threshold = DEPTH_CONFIDENCE_MIN if min_confidence is None else float(min_confidence)
    parts: dict[str, list[np.ndarray]] = {k: [] for k in
                                          ("points", "colors", "segment", "frame", "pixel", "conf")}
    sources: dict[int, tuple[int, int]] = {}
    for frame, pointmap in zip(frames, pointmaps):
        if (pointmap.height, pointmap.width) != frame.shape:
            raise ValueError(f"{frame.rgb_path}: pointmap grid {pointmap.height}x{pointmap.width} "
                             f"does not match the image {frame.shape[0]}x{frame.shape[1]}")
        pixel = np.flatnonzero(pointmap.valid)
        if frame.depth_confidence is not None and threshold > 0:
            pixel = pixel[pointmap.confidence[pixel] >= threshold]
        if drop_background and frame.mask is not None:
            pixel = pixel[_object_or_boundary(frame.mask, frame.depth if frame.depth is not None else pointmap.depth)
                          .reshape(-1)[pixel]]
        labels = np.full(pixel.shape, -1, dtype=np.int64)
        if frame.mask is not None:
            mask = frame.mask
            if drop_mask_boundaries:
                depth = frame.depth if frame.depth is not None else pointmap.depth
                mask = without_ambiguous_boundaries(mask, depth, pointmap.valid.reshape(mask.shape))
            mask_ids = mask.reshape(-1)[pixel]
            foreground = mask_ids > 0
            labels[foreground] = frame.index * SEGMENT_STRIDE + mask_ids[foreground]
            for mask_id in np.unique(mask_ids[foreground]):
                sources[segment_id(frame.index, mask_id)] = (frame.index, int(mask_id))
        parts["points"].append(pointmap.points[pixel])
        parts["colors"].append(frame.rgb.reshape(-1, 3)[pixel].astype(np.float64) / 255.0)
        parts["segment"].append(labels)
        parts["frame"].append(np.full(pixel.shape, frame.index, dtype=np.int64))
        parts["pixel"].append(pixel.astype(np.int64))
        parts["conf"].append(pointmap.confidence[pixel])
    return LabelledCloud(
        state=state,
        points=np.concatenate(parts["points"]).astype(np.float64),
        colors=np.concatenate(parts["colors"]),
        segment=np.concatenate(parts["segment"]),
        frame_index=np.concatenate(parts["frame"]),
        pixel_index=np.concatenate(parts["pixel"]),
        confidence=np.concatenate(parts["conf"]),
        segment_source=sources,
    )


def _object_or_boundary(mask: np.ndarray, depth: np.ndarray | None) -> np.ndarray:
    """(H, W) bool: pixels of a mask id > 0, or on a mask boundary whose depth may belong to the
    object. O(H W)."""
    return (mask > 0) | mask_boundary(mask, depth)
