"""The segmenter protocol, label-image checks and a quality measure against true part masks.

A segmenter turns one :class:`~sparseart.types.Frame` into an ``(H, W)`` int64 label image:
0 = background (no segment), ids 1..S are segments local to that image. Label transfer
(:mod:`sparseart.lift.labels`) then copies the ids onto the frame's points unchanged, so a
segmenter only has to keep every segment on ONE rigid part; over-segmentation is fine (the
labeler merges segments that move together), a segment crossing a part boundary is not.
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from ..types import Frame

MAX_LABEL = (1 << 16) - 1  # label transfer packs mask ids into 16 bits (lift.labels.SEGMENT_STRIDE)
# Part masks with more effective segments than this in one image (:func:`effective_segments`)
# tile the object rather than name its parts: the rendered part masks of the 65-object corpus
# show at most 3.1 per image (6 ids; realistic renders with split and merged masks included), so
# 12 leaves room for objects with four times as many visible parts of similar size. Checkerboards
# measured: 16-pixel blocks give 16-24 on a 160x120 cabinet and 56-60 on a 320x240 door, 32-pixel
# blocks 16 on the door; the built-in over-segmenting segmenter gives 4-18 (it is not judged:
# pipeline._without_fragmented_masks).
MAX_EFFECTIVE_SEGMENTS = 12.0


@runtime_checkable
class Segmenter(Protocol):
    """Anything with a ``name`` and ``segment(frame) -> (H, W) int64 labels, 0 = background``."""

    name: str

    def segment(self, frame: Frame) -> np.ndarray:
        ...


def check_rgb(frame: Frame) -> np.ndarray:
    """The frame's image as (H, W, 3) uint8, or ValueError naming the file and the problem."""
    rgb = np.asarray(frame.rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"{frame.rgb_path}: segmenter needs an (H, W, 3) RGB image, got shape {rgb.shape}")
    if rgb.dtype != np.uint8:
        raise ValueError(f"{frame.rgb_path}: segmenter needs an 8-bit RGB image, got {rgb.dtype}")
    if rgb.shape[0] < 2 or rgb.shape[1] < 2:
        raise ValueError(f"{frame.rgb_path}: image {rgb.shape[1]}x{rgb.shape[0]} is too small to segment")
    return rgb


def effective_segments(labels: np.ndarray, valid: np.ndarray | None = None) -> float:
    """How many segments a label image (H, W) really has: the inverse Simpson index (sum a)^2 /
    sum a^2 of the segments' pixel counts a over the labelled pixels (ids > 0, and ``valid``, e.g.
    pixels with depth, when given). k segments of equal size give k; a few large parts with many
    specks stay near the number of parts, so over-segmentation that merely frays the borders is
    not counted as fragmentation. Resolution-free (a shared scale of every count cancels); 0 when
    nothing is labelled. O(H W log S)."""
    labels = np.asarray(labels)
    keep = labels > 0 if valid is None else (labels > 0) & np.asarray(valid, dtype=bool)
    _, counts = np.unique(labels[keep], return_counts=True)
    if counts.size == 0:
        return 0.0
    areas = counts.astype(np.float64)
    return float(areas.sum() ** 2 / np.sum(areas ** 2))


def fragmented_frames(frames: list[Frame]) -> list[tuple[Frame, float]]:
    """(frame, its effective segments) of the frames whose masks cut the object into far more
    pieces than parts could be: more than ``MAX_EFFECTIVE_SEGMENTS`` :func:`effective_segments`
    over the pixels with depth (all labelled pixels when the frame has no depth). Such ids do not follow parts (the labeler would pair
    hundreds of blocks that tile the image across the states); the caller ignores the masks and
    splits the parts by motion. Frames without a mask are never fragmented. O(H W log S) each."""
    found = []
    for frame in frames:
        if frame.mask is None:
            continue
        valid = None if frame.depth is None else np.asarray(frame.depth) > 0
        pieces = effective_segments(frame.mask, valid)
        if pieces > MAX_EFFECTIVE_SEGMENTS:
            found.append((frame, pieces))
    return found


def relabel_consecutive(labels: np.ndarray) -> np.ndarray:
    """(H, W) int64 with the positive ids renumbered 1..S in order of first appearance
    (row-major), 0 kept as background. O(H W log S)."""
    labels = np.asarray(labels, dtype=np.int64)
    flat = labels.reshape(-1)
    ids, first = np.unique(flat[flat > 0], return_index=True)
    result = np.zeros_like(flat)
    if ids.size:
        order = np.argsort(first)
        new_id = np.empty(ids.size, dtype=np.int64)
        new_id[order] = np.arange(1, ids.size + 1)
        positive = flat > 0
        result[positive] = new_id[np.searchsorted(ids, flat[positive])]
    if ids.size > MAX_LABEL:
        raise ValueError(f"segmenter produced {ids.size} segments; at most {MAX_LABEL} fit a mask image")
    return result.reshape(labels.shape)


def segmentation_quality(labels: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """How well a label image respects the true parts.

    Args:
        labels: (H, W) int predicted segments, 0 = background.
        truth: (H, W) int true part ids, 0 = background (e.g. a rendered PartNet mask).

    Returns a dict:
        segments: number of predicted segments (ids > 0).
        purity: fraction of object pixels (truth > 0) inside a segment whose majority true part
            (over its object pixels) is their own part; 1 = no segment mixes parts.
        coverage: fraction of object pixels that got a segment (label > 0).
        leakage: fraction of true part-boundary pixel pairs (4-neighbours, both on the object,
            different true parts) whose two pixels share one segment; 0 = every part boundary is a
            segment boundary.
        background_in_segments: fraction of segmented pixels (label > 0) that are true background.
    O(H W log S).
    """
    labels = np.asarray(labels, dtype=np.int64)
    truth = np.asarray(truth, dtype=np.int64)
    if labels.shape != truth.shape:
        raise ValueError(f"labels {labels.shape} and truth {truth.shape} differ in shape")
    on_object = truth > 0
    segmented = labels > 0
    scored = on_object & segmented
    purity = 1.0
    if scored.any():
        seg, part = labels[scored], truth[scored]
        pair, count = np.unique(np.stack([seg, part], 1), axis=0, return_counts=True)
        order = np.lexsort((-count, pair[:, 0]))  # per segment, largest count first
        pair, count = pair[order], count[order]
        first = np.r_[True, pair[1:, 0] != pair[:-1, 0]]
        purity = float(count[first].sum() / scored.sum())
    pairs = total = 0
    for axis in (0, 1):
        a = [slice(None), slice(None)]
        b = [slice(None), slice(None)]
        a[axis], b[axis] = slice(1, None), slice(None, -1)
        ta, tb, la, lb = truth[tuple(a)], truth[tuple(b)], labels[tuple(a)], labels[tuple(b)]
        boundary = (ta > 0) & (tb > 0) & (ta != tb)
        total += int(boundary.sum())
        pairs += int((boundary & (la == lb) & (la > 0)).sum())
    return {
        "segments": float(np.unique(labels[segmented]).size),
        "purity": purity,
        "coverage": float(scored.sum() / max(on_object.sum(), 1)),
        "leakage": float(pairs / total) if total else 0.0,
        "background_in_segments": float((segmented & ~on_object).sum() / max(segmented.sum(), 1)),
    }
