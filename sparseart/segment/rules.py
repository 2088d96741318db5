"""Built-in rule-based segmenter: superpixels split at depth/normal edges, merged across weak boundaries.

No model, no download. Per image:

1. Features per pixel: CIE Lab colour; with depth + K also the surface normal (from the
   back-projected depth map, one-sided differences that avoid depth jumps) and log depth.
2. Over-segmentation: SLIC superpixels (``cv2.ximgproc.createSuperpixelSLIC``, SLICO) on the
   stacked, weighted features, each then split into the connected pieces left after cutting the
   pixel graph at *geometric* edges (slope-aware depth jumps, normal creases). Pixels without
   depth are background (0) and never join a segment.
3. A region adjacency graph with additive statistics: for every two touching regions the length
   of their shared boundary and how much of it is a *hard* edge (geometric or a strong colour
   step); per region the area, mean colour, mean normal and centroid. Merging, cheapest first:
   (a) across boundaries with few hard-edge pixels between regions of similar colour and normal
   that lie on one plane (the offset of their centroids along the mean normal is small: a sliding
   sash in front of its frame stays apart); (b) regions below ``min_area`` into their cheapest
   neighbour; (c) while more than ``max_segments`` remain, the globally cheapest pair.

Every segment should lie on ONE rigid part (over-segmentation is fine: the labeler merges
segments that move together). Without depth: colour and colour edges only, and no background.

Complexity: O(H W) for features, edges and splitting (SLIC is O(H W) per iteration) and
O(E log E) heap operations for merging a graph with E adjacencies (a few thousand). Measured
0.1-0.25 s for a 320x240 image on one contended core (benchmarks/segment_quality.py).
"""
from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np

from ..types import Frame
from .base import check_rgb, relabel_consecutive

BACKGROUND_OFFSET = 1.0e4  # feature-space distance that keeps background apart from the object


@dataclass(frozen=True)
class RuleOptions:
    """Tuning of :class:`RuleSegmenter` (defaults chosen on rendered PartNet scenes, see
    benchmarks/segment_quality.py).

    slic_size: superpixel side in pixels; slic_iterations: SLIC iterations.
    colour_unit: Lab distance worth one feature unit in SLIC; normal_weight: feature units per
        unit of normal difference; log_depth_weight: feature units per unit of log depth.
    depth_jump: relative depth step |d1 - d2| / min(d1, d2) that is always a jump.
    jump_pixels: change of the depth step between neighbouring pairs, in pixel footprints
        (depth / focal), that makes a jump on a smooth surface.
    crease_deg: normal angle between neighbours (degrees) that is a crease.
    colour_edge: Lab distance between neighbours (after a 3x3 blur) that is a hard edge.
    merge_colour: largest Lab distance between region means that may merge.
    merge_normal_deg: largest angle between region mean normals that may merge.
    merge_hard_fraction: largest fraction of hard-edge pixels on a shared boundary that may merge.
    merge_plane_pixels: largest offset of two regions' centroids along their mean normal, in pixel
        footprints, that may merge.
    min_area: regions smaller than this fraction of the image join a neighbour.
    max_segments: most segments per image.
    """

    slic_size: int = 8
    slic_iterations: int = 5
    colour_unit: float = 8.0
    normal_weight: float = 4.0
    log_depth_weight: float = 100.0
    depth_jump: float = 0.05
    jump_pixels: float = 1.5
    crease_deg: float = 35.0
    colour_edge: float = 18.0
    merge_colour: float = 8.0
    merge_normal_deg: float = 10.0
    merge_hard_fraction: float = 0.05
    merge_plane_pixels: float = 1.0
    min_area: float = 0.0015
    max_segments: int = 60

    def __post_init__(self) -> None:
        for name in ("colour_unit", "normal_weight", "log_depth_weight", "depth_jump", "jump_pixels",
                     "crease_deg", "colour_edge", "merge_colour", "merge_normal_deg", "merge_plane_pixels"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
                raise ValueError(f"RuleOptions.{name} must be a positive number, got {value!r}")
        if not 0.0 <= self.merge_hard_fraction <= 1.0:
            raise ValueError(f"RuleOptions.merge_hard_fraction must be in [0, 1], got {self.merge_hard_fraction!r}")
        if not 0.0 <= self.min_area < 1.0:
            raise ValueError(f"RuleOptions.min_area must be in [0, 1), got {self.min_area!r}")
        for name in ("slic_size", "slic_iterations", "max_segments"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"RuleOptions.{name} must be >= 1, got {getattr(self, name)!r}")


class RuleSegmenter:
    """Segments a frame without any model (see the module docstring). ``segment(frame)`` returns
    (H, W) int64 labels, 0 = background (depth 0 when the frame has depth; none otherwise)."""

    name = "builtin"

    def __init__(self, options: RuleOptions | None = None) -> None:
        self.options = options or RuleOptions()

    def segment(self, frame: Frame) -> np.ndarray:
        rgb = check_rgb(frame)
        depth, K = _depth_and_K(frame)
        return segment_image(rgb, depth, K, self.options)


def _depth_and_K(frame: Frame) -> tuple[np.ndarray | None, np.ndarray | None]:
    if frame.depth is None:
        return None, None
    depth = np.asarray(frame.depth, dtype=np.float64)
    if depth.shape != frame.shape:
        raise ValueError(f"{frame.rgb_path}: depth {depth.shape[1]}x{depth.shape[0]} does not match the "
                         f"image {frame.shape[1]}x{frame.shape[0]}")
    if frame.camera is None:
        raise ValueError(f"{frame.rgb_path}: depth without a camera K; cannot compute normals")
    return depth, np.asarray(frame.camera.K, dtype=np.float64)


def segment_image(rgb: np.ndarray, depth: np.ndarray | None = None, K: np.ndarray | None = None,
                  options: RuleOptions | None = None) -> np.ndarray:
    """Segment one image.

    Args:
        rgb: (H, W, 3) uint8.
        depth: (H, W) float metres, 0 / non-finite = invalid (background), or None.
        K: (3, 3) float64 intrinsics in pixels; required with depth.
        options: tuning, see :class:`RuleOptions`.

    Returns:
        (H, W) int64 labels 1..S (S <= max_segments), 0 = background (invalid depth).
    """
    import cv2

    options = options or RuleOptions()
    height, width = rgb.shape[:2]
    lab = cv2.cvtColor(cv2.GaussianBlur(rgb, (3, 3), 0).astype(np.float32) / 255.0, cv2.COLOR_RGB2Lab)
    lab = lab.astype(np.float64)
    features = [lab / options.colour_unit]
    points = normals = None
    focal = 1.0
    if depth is not None:
        if K is None:
            raise ValueError("segment_image: depth given without K")
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
        valid = depth > 0
        if not valid.any():
            return np.zeros((height, width), dtype=np.int64)
        points, normals = depth_normals(depth, K)
        focal = float(np.sqrt(K[0, 0] * K[1, 1]))
        features += [normals * options.normal_weight,
                     (np.log(np.where(valid, depth, 1.0)) * options.log_depth_weight)[..., None],
                     (~valid)[..., None] * BACKGROUND_OFFSET]
    else:
        valid = np.ones((height, width), dtype=bool)
    stacked = np.ascontiguousarray(np.concatenate(features, axis=2), dtype=np.float32)
    size = max(2, min(int(options.slic_size), min(height, width) // 2))
    slic = cv2.ximgproc.createSuperpixelSLIC(stacked, cv2.ximgproc.SLICO, size)
    slic.iterate(int(options.slic_iterations))
    geometric, hard = _hard_edges(lab, depth, normals, focal, options)
    regions = _split_regions(slic.getLabels().astype(np.int64), valid, geometric)
    merged = _merge_regions(regions, valid, lab, normals, points, hard, focal, options) + 1
    merged[~valid] = 0
    return relabel_consecutive(merged)


def depth_normals(depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(points, normals) of a depth map: (H, W, 3) float64 camera-frame points (metres) and unit
    normals facing the camera.

    depth: (H, W) metres, 0 = invalid; K: (3, 3). Tangents use the one-sided difference with the
    smaller depth change, so pixels next to a depth jump keep their own surface's normal. Invalid
    pixels get normal (0, 0, 0). O(H W).
    """
    height, width = depth.shape
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    x = (u - K[0, 2]) / K[0, 0] * depth
    y = (v - K[1, 2]) / K[1, 1] * depth
    points = np.stack([x, y, depth], axis=2)
    valid = depth > 0

    def tangent(axis: int) -> np.ndarray:
        forward = np.zeros_like(points)
        backward = np.zeros_like(points)
        ok_f = np.zeros(valid.shape, dtype=bool)
        ok_b = np.zeros(valid.shape, dtype=bool)
        lo = [slice(None), slice(None)]
        hi = [slice(None), slice(None)]
        lo[axis], hi[axis] = slice(None, -1), slice(1, None)
        lo, hi = tuple(lo), tuple(hi)
        step = points[hi] - points[lo]
        both = valid[hi] & valid[lo]
        forward[lo], ok_f[lo] = step, both
        backward[hi], ok_b[hi] = step, both
        use_forward = ok_f & (~ok_b | (np.abs(forward[..., 2]) <= np.abs(backward[..., 2])))
        return np.where(use_forward[..., None], forward, backward)

    normal = np.cross(tangent(1), tangent(0))
    norm = np.linalg.norm(normal, axis=2, keepdims=True)
    normal = np.divide(normal, norm, out=np.zeros_like(normal), where=norm > 1e-12)
    facing = np.sum(normal * points, axis=2) > 0  # flip so normals point towards the camera
    normal[facing] *= -1.0
    normal[~valid] = 0.0
    return points, normal


def _neighbour_pairs(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Row-major indices (a, b) of all horizontal and vertical 4-neighbour pixel pairs."""
    height, width = shape
    index = np.arange(height * width).reshape(height, width)
    a = np.concatenate([index[:, :-1].ravel(), index[:-1, :].ravel()])
    b = np.concatenate([index[:, 1:].ravel(), index[1:, :].ravel()])
    return a, b


def depth_jumps(depth: np.ndarray, focal: float, jump_pixels: float, jump_relative: float) -> np.ndarray:
    """(P,) bool over the pairs of :func:`_neighbour_pairs`: a depth discontinuity between the two
    pixels.

    Slope-aware: on a smooth surface the depth step between neighbours changes slowly along a row
    (exactly linearly in inverse depth on a plane), so a pair is a jump when its step differs from
    the steps on both sides by more than ``jump_pixels`` pixel footprints (d / focal), or when the
    step exceeds ``jump_relative`` of the depth outright. Pairs with an invalid pixel are False.
    O(H W).
    """
    flags = []
    for transpose in (False, True):  # horizontal pairs, then vertical pairs (same order as pairs)
        d = depth.T if transpose else depth
        step = np.diff(d, axis=1)
        near = np.minimum(d[:, 1:], d[:, :-1])
        before = np.full_like(step, np.inf)
        after = np.full_like(step, np.inf)
        before[:, 1:] = np.abs(step[:, 1:] - step[:, :-1])
        after[:, :-1] = np.abs(step[:, :-1] - step[:, 1:])
        jump = (np.minimum(before, after) > jump_pixels * near / focal) | (np.abs(step) > jump_relative * near)
        jump &= near > 0
        flags.append((jump.T if transpose else jump).ravel())
    return np.concatenate(flags)


def _hard_edges(lab: np.ndarray, depth: np.ndarray | None, normals: np.ndarray | None,
                focal: float, options: RuleOptions) -> tuple[np.ndarray, np.ndarray]:
    """Over the neighbour pairs of :func:`_neighbour_pairs`: (geometric, hard), bool (P,) each.
    geometric = depth jump or normal crease; hard = geometric or a strong colour step. O(H W)."""
    a, b = _neighbour_pairs(lab.shape[:2])
    lab_flat = lab.reshape(-1, 3)
    colour = np.linalg.norm(lab_flat[a] - lab_flat[b], axis=1) > options.colour_edge
    if depth is None or normals is None:
        return np.zeros_like(colour), colour
    geometric = depth_jumps(depth, focal, options.jump_pixels, options.depth_jump)
    n = normals.reshape(-1, 3)
    geometric |= np.sum(n[a] * n[b], axis=1) < np.cos(np.radians(options.crease_deg))
    valid = depth.reshape(-1) > 0
    geometric &= valid[a] & valid[b]
    return geometric, geometric | colour


def _split_regions(regions: np.ndarray, valid: np.ndarray, cut: np.ndarray) -> np.ndarray:
    """Connected components of the 4-neighbour pixel graph restricted to pairs in one region,
    both valid and not ``cut`` (P,). Returns (H, W) int64 ids. O(H W)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    a, b = _neighbour_pairs(regions.shape)
    flat, ok = regions.reshape(-1), valid.reshape(-1)
    keep = (flat[a] == flat[b]) & ~cut & (ok[a] == ok[b])
    n = flat.size
    graph = coo_matrix((np.ones(int(keep.sum()), dtype=np.int8), (a[keep], b[keep])), shape=(n, n))
    _, component = connected_components(graph, directed=False)
    return component.reshape(regions.shape).astype(np.int64)


class _Regions:
    """Region adjacency graph with additive statistics and union-find, for greedy merging.

    Per region: area (valid pixels), sums of Lab, normal and 3D point. Per touching pair:
    [boundary length, hard-edge pairs on it].
    """

    def __init__(self, regions: np.ndarray, valid: np.ndarray, lab: np.ndarray, normals: np.ndarray | None,
                 points: np.ndarray | None, hard: np.ndarray, focal: float, options: RuleOptions) -> None:
        ids, inverse = np.unique(regions.reshape(-1), return_inverse=True)
        self.count, self.label, self.focal, self.options = ids.size, inverse.reshape(regions.shape), focal, options
        weights = valid.reshape(-1).astype(np.float64)

        def sums(values: np.ndarray) -> np.ndarray:
            flat = values.reshape(-1, 3)
            return np.stack([np.bincount(inverse, weights=flat[:, c] * weights, minlength=self.count)
                             for c in range(3)], axis=1)

        columns = [np.bincount(inverse, weights=weights, minlength=self.count), sums(lab)]
        self.has_geometry = normals is not None and points is not None
        if self.has_geometry:
            columns += [sums(normals), sums(points)]
        # per region [area, L, a, b(, nx, ny, nz, x, y, z)] sums as Python floats: the merge loop
        # touches single regions, where plain floats are ~10x faster than numpy scalars
        self.stats: list[list[float]] = np.column_stack(columns).tolist()
        self.parent = np.arange(self.count)
        a, b = _neighbour_pairs(regions.shape)
        la, lb = inverse[a], inverse[b]
        keep = (la != lb) & (weights[a] > 0) & (weights[b] > 0)
        key = np.minimum(la[keep], lb[keep]) * self.count + np.maximum(la[keep], lb[keep])
        keys, key_inverse = np.unique(key, return_inverse=True)
        length = np.bincount(key_inverse)
        hard_count = np.bincount(key_inverse, weights=hard[keep].astype(np.float64))
        self.adjacent: list[dict[int, list[float]]] = [dict() for _ in range(self.count)]
        for k, n_len, n_hard in zip(keys.tolist(), length.tolist(), hard_count.tolist()):
            i, j = divmod(k, self.count)
            self.adjacent[i][j] = self.adjacent[j][i] = [float(n_len), n_hard]

    def area(self, i: int) -> float:
        return self.stats[i][0]

    def cost(self, i: int, j: int) -> tuple[float, bool]:
        """(cost, allowed): normalised dissimilarity of touching regions i and j, and whether every
        merge threshold allows joining them."""
        o = self.options
        length, hard = self.adjacent[i][j]
        hard_fraction = hard / max(length, 1.0)
        si, sj = self.stats[i], self.stats[j]
        area_i, area_j = max(si[0], 1.0), max(sj[0], 1.0)
        colour = math.sqrt(sum((si[c] / area_i - sj[c] / area_j) ** 2 for c in (1, 2, 3)))
        cost = hard_fraction / max(o.merge_hard_fraction, 1e-3) + colour / o.merge_colour
        allowed = hard_fraction <= o.merge_hard_fraction and colour <= o.merge_colour
        if self.has_geometry:
            ni, nj = si[4:7], sj[4:7]
            norm_i, norm_j = math.hypot(*ni), math.hypot(*nj)
            angle, offset = 180.0, 1e6
            if norm_i > 0 and norm_j > 0:
                cosine = sum(x * y for x, y in zip(ni, nj)) / (norm_i * norm_j)
                angle = math.degrees(math.acos(min(1.0, max(-1.0, cosine))))
                mean = [x / norm_i + y / norm_j for x, y in zip(ni, nj)]
                norm_mean = max(math.hypot(*mean), 1e-12)
                delta = [x / area_i - y / area_j for x, y in zip(si[7:10], sj[7:10])]
                footprint = max(0.5 * (si[9] / area_i + sj[9] / area_j) / self.focal, 1e-12)
                offset = min(abs(sum(m * d for m, d in zip(mean, delta))) / norm_mean / footprint, 1e6)
            cost += angle / o.merge_normal_deg + offset / o.merge_plane_pixels
            allowed = allowed and angle <= o.merge_normal_deg and offset <= o.merge_plane_pixels
        return cost, allowed

    def merge(self, keep: int, gone: int) -> None:
        self.parent[gone] = keep
        self.stats[keep] = [x + y for x, y in zip(self.stats[keep], self.stats[gone])]
        for neighbour, (length, hard) in self.adjacent[gone].items():
            del self.adjacent[neighbour][gone]
            if neighbour != keep:
                entry = self.adjacent[keep].setdefault(neighbour, [0.0, 0.0])
                entry[0] += length
                entry[1] += hard
                self.adjacent[neighbour][keep] = entry
        self.adjacent[gone] = {}

    def alive(self, i: int) -> bool:
        return self.parent[i] == i

    def final_labels(self) -> np.ndarray:
        root = self.parent.copy()
        while not np.array_equal(root[root], root):
            root = root[root]
        return root[self.label]


def _merge_regions(regions: np.ndarray, valid: np.ndarray, lab: np.ndarray, normals: np.ndarray | None,
                   points: np.ndarray | None, hard: np.ndarray, focal: float,
                   options: RuleOptions) -> np.ndarray:
    """Greedy merging, phases (a)-(c) of the module docstring. Returns (H, W) int64 region ids.
    O(E log E) heap operations for E adjacencies."""
    graph = _Regions(regions, valid, lab, normals, points, hard, focal, options)
    n_alive = sum(1 for row in graph.stats if row[0] > 0)

    def join(i: int, j: int) -> int:
        nonlocal n_alive
        keep, gone = (i, j) if graph.area(i) >= graph.area(j) else (j, i)
        graph.merge(keep, gone)
        n_alive -= 1
        return keep

    def pair_heap(only_allowed: bool) -> list[tuple[float, int, int]]:
        heap = []
        for i in range(graph.count):
            if graph.alive(i):
                for j in graph.adjacent[i]:
                    if i < j:
                        cost, allowed = graph.cost(i, j)
                        if allowed or not only_allowed:
                            heap.append((cost, i, j))
        heapq.heapify(heap)
        return heap

    def cheapest_pairs(only_allowed: bool, stop_at: int) -> None:
        heap = pair_heap(only_allowed)
        while heap and n_alive > stop_at:
            cost, i, j = heapq.heappop(heap)
            if not (graph.alive(i) and graph.alive(j) and j in graph.adjacent[i]):
                continue
            current, allowed = graph.cost(i, j)
            if (only_allowed and not allowed) or current > cost + 1e-9:
                if current > cost + 1e-9 and (allowed or not only_allowed):
                    heapq.heappush(heap, (current, i, j))  # stale: statistics changed since queued
                continue
            keep = join(i, j)
            for neighbour in graph.adjacent[keep]:
                cost, allowed = graph.cost(keep, neighbour)
                if allowed or not only_allowed:
                    heapq.heappush(heap, (cost, min(keep, neighbour), max(keep, neighbour)))

    cheapest_pairs(only_allowed=True, stop_at=1)                                     # (a)
    min_area = options.min_area * valid.size
    by_area = [(row[0], i) for i, row in enumerate(graph.stats) if row[0] > 0]
    heapq.heapify(by_area)
    while by_area:                                                                   # (b)
        area, i = heapq.heappop(by_area)
        if area >= min_area:
            break
        if not graph.alive(i) or area != graph.area(i) or not graph.adjacent[i]:
            continue  # stale entry, or isolated by background: nothing to join
        target = min(graph.adjacent[i], key=lambda j: graph.cost(i, j)[0])
        keep = join(i, target)
        heapq.heappush(by_area, (graph.area(keep), keep))
    if n_alive > options.max_segments:                                               # (c)
        cheapest_pairs(only_allowed=False, stop_at=options.max_segments)
    return graph.final_labels()
