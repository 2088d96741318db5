"""Learned 2D matchers from ONNX weights behind one small interface, and their lift to 3D.

Interface: a :class:`PixelMatcher` has ``match(image_a, image_b, *, key_a=None, key_b=None) ->
PixelMatches``; images are (H, W, 3) uint8 RGB arrays, matches are pixel positions in the ORIGINAL
images. Pixel convention (the same as :func:`sparseart.align.features.lift_pixels` and OpenCV):
(x, y) = (column, row), the centre of pixel (c, r) is (c, r), so an image spans [-0.5, W - 0.5] x
[-0.5, H - 0.5]; a position p on a model grid of W' columns maps to (p + 0.5) W / W' - 0.5.

Implementations:

* :class:`XFeatExtractor`: XFeat (Potje et al., CVPR 2024) keypoints + 64-d descriptors from an
  ONNX export of its backbone (``xfeat.onnx``, any size; or a fixed-size export such as
  ``xfeat_320x224.onnx``). The keypoint post-processing is not in the graph; it follows the
  reference ``XFeat.detectAndCompute`` (verlab/accelerated_features, modules/xfeat.py): softmax
  over the 65 logit channels, drop the "no keypoint" channel, unfold each cell's 64 channels into
  an 8 x 8 block (full-resolution heatmap), 5 x 5 non-maximum suppression, heat > 0.05, score =
  heat x reliability (bilinear), top-k; descriptors L2-normalised per cell, sampled bicubically
  (as the reference) at the keypoints and L2-normalised again. Features of an image are cached
  (keyed by the caller's key or a hash of the pixels) so an image in many pairs is run once.
* :class:`LighterGlueMatcher`: XFeat + LighterGlue (``lighterglue_L3.onnx``, noahzhy/
  xfeat_lightglue_onnx): keypoints normalised (k - size/2) / (max(W, H)/2) with the size of the
  original image, mutual-argmax matches of the log-assignment, scores in [0, 1] >= ``min_score``.
* :class:`XFeatMNNMatcher`: XFeat descriptors matched by mutual nearest neighbours (cosine
  similarity > ``min_similarity``, 0.82 as the reference ``XFeat.match``); no matcher network.
* :class:`LightGluePipelineMatcher`: the end-to-end LightGlue-ONNX export of
  :class:`sparseart.align.lightglue.LightGlueMatcher` behind the same interface.

:func:`open_matcher` builds one from a spec string or a ``sparseart-matcher/1`` JSON file;
:func:`lifted_matches` / :class:`LiftedMatcher` lift pixel matches through pointmaps into the
:class:`~sparseart.align.features.FeatureMatches` that the registration consumes.

Cost (measured on this project's shared 2-core CPU, 2 onnxruntime threads, 640 x 480 network
input): XFeat O(H W), 130-180 ms per image (about 30 ms of it numpy post-processing), once per image
thanks to the cache; LighterGlue O((N + M)^2 d) attention per layer, ~0.35 s per pair at 1024 +
1024 keypoints and ~0.8-1.1 s at 2048 + 2048; MNN O(N M 64), ~0.1 s at 2048 + 2048. The fixed
320 x 224 export runs in ~20-50 ms per image.
"""
from __future__ import annotations

import hashlib
import json
import math
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Hashable, Protocol, runtime_checkable

import numpy as np

from sparseart._onnx import describe_io, open_session, run_error, tensors
from sparseart.align.features import FeatureMatches, lift_pixels
from sparseart.types import Frame, Pointmap, SceneError

SCHEMA = "sparseart-matcher/1"
KINDS = ("xfeat+lighterglue", "xfeat", "lightglue-pipeline")
DEFAULT_MAX_KEYPOINTS = 2048     # XFeat top-k per image
DEFAULT_MAX_SIDE = 640           # long side of the XFeat input for dynamic-size exports
DETECTION_THRESHOLD = 0.05       # XFeat heatmap threshold (reference default)
NMS_SIZE = 5                     # XFeat non-maximum suppression window (pixels of the model grid)
# LighterGlue match-score threshold: the reference min_conf. Measured on 18 rendered view pairs
# (6 PartNet objects, 640 x 480, GT poses): 0.05 / 0.1 / 0.2 / 0.3 registered 8 / 7 / 6 / 5 pairs
# correctly, with 66 / 75 / 86 / 91 % of the lifted matches within 2 % of the object diagonal.
DEFAULT_MIN_SCORE = 0.1
DEFAULT_MIN_SIMILARITY = 0.82    # MNN cosine-similarity threshold (reference XFeat.match)
SIZE_MULTIPLE = 32               # XFeat input sizes are rounded to this (reference preprocess_tensor)
CELL = 8                         # XFeat output stride
DESCRIPTOR_DIM = 64
DEFAULT_CACHE_SIZE = 64          # images whose features an extractor keeps
MNN_CHUNK = 1024                 # rows of the similarity matrix computed at once (memory O(chunk M))


class MatcherError(SceneError):
    """Bad matcher spec, contract or model. ``str(error)`` is one line naming the file or field."""


# ----------------------------------------------------------------------------- interface


@dataclass
class PixelMatches:
    """Matches between two images.

    pixels_a, pixels_b: (K, 2) float64 (x, y) positions in the ORIGINAL images a and b (pixel
        centres at integers, see the module docstring).
    scores: (K,) float64 in [0, 1], higher = more confident (LighterGlue / LightGlue match
        probability, or the cosine similarity for MNN).
    n_keypoints: keypoints detected in a and in b.
    """

    pixels_a: np.ndarray
    pixels_b: np.ndarray
    scores: np.ndarray
    n_keypoints: tuple[int, int] = (0, 0)

    def __len__(self) -> int:
        return int(self.pixels_a.shape[0])

    @staticmethod
    def empty(n_keypoints: tuple[int, int] = (0, 0)) -> "PixelMatches":
        return PixelMatches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), n_keypoints)


@runtime_checkable
class PixelMatcher(Protocol):
    """Anything that matches two (H, W, 3) uint8 RGB images. ``key_a`` / ``key_b`` optionally name
    the images for feature caches (a key must always denote the same pixels); None = hash them."""

    def match(self, image_a: np.ndarray, image_b: np.ndarray, *, key_a: Hashable | None = None,
              key_b: Hashable | None = None) -> PixelMatches: ...


@dataclass
class XFeatFeatures:
    """XFeat features of one image.

    keypoints: (N, 2) float64 (x, y) in the original image, strongest first.
    descriptors: (N, 64) float32, unit length.
    scores: (N,) float64 detection scores (heat x reliability) in (0, 1].
    image_size: (W, H) of the original image.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    scores: np.ndarray
    image_size: tuple[int, int]

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


def image_key(image: np.ndarray) -> tuple:
    """A cache key of an image's pixels: (shape, dtype, 128-bit BLAKE2b of the bytes). O(H W),
    about 1 ms for 640 x 480 x 3."""
    array = np.ascontiguousarray(image)
    return array.shape, str(array.dtype), hashlib.blake2b(array.data, digest_size=16).hexdigest()


def _rgb(image: np.ndarray, name: str) -> np.ndarray:
    """(H, W, 3) uint8 view of an RGB image (an alpha channel is dropped, grey is repeated)."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (3, 4)) \
            or min(image.shape[:2]) < 1:
        raise MatcherError(f"{name}: expected an (H, W, 3) uint8 RGB image, got shape {image.shape} "
                           f"dtype {image.dtype}")
    if image.ndim == 2:
        return np.repeat(image[..., None], 3, axis=2)
    return image[..., :3]


def _to_original(pixels: np.ndarray, grid_size: tuple[int, int], original_size: tuple[int, int]) -> np.ndarray:
    """(K, 2) x, y on a model grid of (H', W') -> the original (H, W) image (half-pixel centres)."""
    sy = original_size[0] / grid_size[0]
    sx = original_size[1] / grid_size[1]
    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    return np.column_stack([(pixels[:, 0] + 0.5) * sx - 0.5, (pixels[:, 1] + 0.5) * sy - 0.5])


# ----------------------------------------------------------------------------- XFeat post-processing


def keypoint_heatmap(logits: np.ndarray) -> np.ndarray:
    """(65, h, w) keypoint logits -> (8h, 8w) float32 heatmap: softmax over the 65 channels, drop
    the last ("no keypoint"), channel 8 r + c of a cell -> pixel (8 y + r, 8 x + c). O(h w 65)."""
    logits = np.asarray(logits, np.float32)
    channels, h, w = logits.shape
    exp = np.exp(logits - logits.max(axis=0, keepdims=True))
    probs = exp[:CELL * CELL] / exp.sum(axis=0, keepdims=True)
    return np.ascontiguousarray(probs.reshape(CELL, CELL, h, w).transpose(2, 0, 3, 1).reshape(h * CELL, w * CELL))


def nms_keypoints(heat: np.ndarray, threshold: float = DETECTION_THRESHOLD, size: int = NMS_SIZE) -> np.ndarray:
    """(N, 2) int64 (x, y) of the pixels that equal the maximum of their size x size window and
    exceed ``threshold`` (ties all kept, as torch max-pool NMS), row-major order. O(H W size)."""
    import cv2

    local_max = cv2.dilate(heat, np.ones((size, size), np.uint8), borderType=cv2.BORDER_CONSTANT,
                           borderValue=0.0)
    rows, cols = np.nonzero((heat == local_max) & (heat > threshold))
    return np.column_stack([cols, rows]).astype(np.int64)


def _cubic_weights(t: np.ndarray) -> list[np.ndarray]:
    """Cubic-convolution weights (A = -0.75, as torch bicubic) of the taps at -1, 0, 1, 2."""
    a = -0.75

    def near(x):   # |x| <= 1
        return ((a + 2) * x - (a + 3)) * x * x + 1

    def far(x):    # 1 < |x| < 2
        return ((a * x - 5 * a) * x + 8 * a) * x - 4 * a

    return [far(t + 1), near(t), near(1 - t), far(2 - t)]


def sample_map(maps: np.ndarray, u: np.ndarray, v: np.ndarray, mode: str = "bilinear") -> np.ndarray:
    """Sample (C, h, w) maps at (N,) continuous cell positions u (column), v (row), cell centres at
    integers, zeros outside (torch ``grid_sample(..., padding_mode="zeros")``). mode: "bilinear" or
    "bicubic". Returns (N, C) float32. O(N C taps)."""
    maps = np.asarray(maps, np.float32)
    channels, h, w = maps.shape
    pad = 2
    padded = np.pad(maps, ((0, 0), (pad, pad), (pad, pad))).transpose(1, 2, 0)   # (h+4, w+4, C)
    x0, y0 = np.floor(u), np.floor(v)
    tx, ty = (u - x0).astype(np.float32), (v - y0).astype(np.float32)
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    if mode == "bilinear":
        offsets, wx, wy = (0, 1), [1 - tx, tx], [1 - ty, ty]
    elif mode == "bicubic":
        offsets, wx, wy = (-1, 0, 1, 2), _cubic_weights(tx), _cubic_weights(ty)
    else:
        raise ValueError(f"sample_map: mode must be bilinear or bicubic, got {mode!r}")
    out = np.zeros((u.shape[0], channels), np.float32)
    for j, dy in enumerate(offsets):
        rows = np.clip(y0 + dy + pad, 0, h + 2 * pad - 1)   # clipped taps land in the zero border
        for i, dx in enumerate(offsets):
            cols = np.clip(x0 + dx + pad, 0, w + 2 * pad - 1)
            out += (wx[i] * wy[j])[:, None] * padded[rows, cols]
    return out


def _unit(vectors: np.ndarray, axis: int) -> np.ndarray:
    return vectors / np.maximum(np.linalg.norm(vectors, axis=axis, keepdims=True), 1e-12)


def xfeat_features(descriptors: np.ndarray, logits: np.ndarray, reliability: np.ndarray, *,
                   top_k: int = DEFAULT_MAX_KEYPOINTS, threshold: float = DETECTION_THRESHOLD,
                   descriptor_sampling: str = "bicubic") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """XFeat keypoints from the three network outputs of one image (reference detectAndCompute).

    Args:
        descriptors: (64, h, w); logits: (65, h, w); reliability: (1, h, w) or (h, w) in [0, 1].
    Returns:
        keypoints (N, 2) int64 (x, y) on the (8h, 8w) model-input grid, strongest first;
        scores (N,) float64 > 0; descriptors (N, 64) float32 unit length. N <= top_k.

    Sampling positions follow the reference exactly: a grid pixel x is sampled at cell coordinate
    x w / (W - 1) - 0.5 (its ``InterpolateSparse2d`` normalises by W - 1 with align_corners=False).
    Cost O(h w 65 + 64 h w + N 64 16).
    """
    heat = keypoint_heatmap(logits)
    height, width = heat.shape
    h, w = descriptors.shape[1:]
    points = nms_keypoints(heat, threshold)
    if points.shape[0] == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0), np.zeros((0, descriptors.shape[0]), np.float32)
    u = points[:, 0] * (w / max(width - 1, 1)) - 0.5
    v = points[:, 1] * (h / max(height - 1, 1)) - 0.5
    reliability = np.asarray(reliability, np.float32).reshape(1, h, w)
    scores = heat[points[:, 1], points[:, 0]].astype(np.float64) * sample_map(reliability, u, v)[:, 0]
    order = np.argsort(-scores, kind="stable")[:int(top_k)]
    order = order[scores[order] > 0]
    points, scores, u, v = points[order], scores[order], u[order], v[order]
    unit_map = _unit(np.asarray(descriptors, np.float32), axis=0)
    sampled = _unit(sample_map(unit_map, u, v, descriptor_sampling), axis=1)
    return points, scores, sampled.astype(np.float32)


# ----------------------------------------------------------------------------- XFeat extractor


class XFeatExtractor:
    """XFeat keypoints and descriptors from an ONNX backbone export, with a per-image cache.

    The model must have one input [1|?, 3|1, H, W] (RGB in [0, 1]) and three outputs at 1/8
    resolution told apart by their channels: 64 = descriptors, 65 = keypoint logits, 1 =
    reliability. Dynamic-size exports get the image resized (INTER_AREA when shrinking, INTER_LINEAR
    when enlarging) so its long side is ``max_side`` -- smaller images are enlarged only when
    ``upscale`` (default: XFeat finds far more keypoints on a small object at 2x; on 320 x 240
    renders it took view-pair registration from 1-2 to 7 of 18 pairs) -- and both sides are
    multiples of 32. Fixed-size exports get it resized to their size (aspect not kept; the pixel
    mapping is per axis). Cost: see the module docstring (~130-180 ms per 640 x 480 image).

    Raises:
        MatcherError: unreadable file, or a model that is not an XFeat backbone (lists its I/O).
    """

    what = "XFeat detector"

    def __init__(self, path: str | Path, *, max_keypoints: int = DEFAULT_MAX_KEYPOINTS,
                 max_side: int = DEFAULT_MAX_SIDE, upscale: bool = True,
                 detection_threshold: float = DETECTION_THRESHOLD, threads: int = 0,
                 cache_size: int = DEFAULT_CACHE_SIZE, descriptor_sampling: str = "bicubic") -> None:
        self.path = Path(path)
        if int(max_keypoints) < 1:
            raise MatcherError(f"{self.path}: max_keypoints must be >= 1, got {max_keypoints}")
        if int(max_side) < SIZE_MULTIPLE:
            raise MatcherError(f"{self.path}: max_side must be >= {SIZE_MULTIPLE}, got {max_side}")
        if not 0.0 < detection_threshold < 1.0:
            raise MatcherError(f"{self.path}: detection_threshold must lie in (0, 1), got {detection_threshold}")
        if descriptor_sampling not in ("bicubic", "bilinear"):
            raise MatcherError(f"{self.path}: descriptor_sampling must be bicubic or bilinear, "
                               f"got {descriptor_sampling!r}")
        self.max_keypoints = int(max_keypoints)
        self.max_side = int(max_side)
        self.upscale = bool(upscale)
        self.detection_threshold = float(detection_threshold)
        self.descriptor_sampling = descriptor_sampling
        self.session = open_session(self.path, threads=threads, what=self.what, error_type=MatcherError)
        inputs, outputs = tensors(self.session)

        def wrong(why: str) -> MatcherError:
            return MatcherError(f"{self.path}: not an XFeat backbone export ({why}; expected input "
                                f"[1, 3, H, W] and outputs with 64, 65 and 1 channels at H/8 x W/8). "
                                f"{describe_io(self.session)}")

        if len(inputs) != 1 or len(inputs[0].shape) != 4:
            raise wrong(f"{len(inputs)} input(s)" if len(inputs) != 1 else f"input rank {len(inputs[0].shape)}")
        image = inputs[0]
        if image.shape[0] not in (None, 1) or image.shape[1] not in (None, 1, 3):
            raise wrong(f"input {image.describe()}")
        if "float" not in image.type or "16" in image.type:
            raise wrong(f"input type {image.type}")
        channels = {t.shape[1] if len(t.shape) == 4 else -1: t.name for t in outputs}
        if len(outputs) != 3 or set(channels) != {DESCRIPTOR_DIM, 65, 1}:
            raise wrong(f"output channels {[t.shape[1] if len(t.shape) == 4 else t.shape for t in outputs]}")
        self.input_name = image.name
        self.input_channels = 1 if image.shape[1] == 1 else 3
        self.output_names = [channels[DESCRIPTOR_DIM], channels[65], channels[1]]
        height, width = image.shape[2], image.shape[3]
        if (height is None) != (width is None):
            raise wrong(f"input {image.describe()} fixes only one of H, W")
        if height is not None and (height % CELL or width % CELL):
            raise wrong(f"fixed input size {width}x{height} is not a multiple of {CELL}")
        self.fixed_size = None if height is None else (int(height), int(width))
        self.cache_size = int(cache_size)
        self._cache: OrderedDict[Hashable, tuple[tuple[int, ...], XFeatFeatures]] = OrderedDict()
        self.runs = 0   # network passes so far (cache misses)

    @property
    def name(self) -> str:
        return f"xfeat({self.path.name})"

    def model_size(self, height: int, width: int) -> tuple[int, int]:
        """(H', W') of the network input for an original image of height x width pixels."""
        if self.fixed_size is not None:
            return self.fixed_size
        scale = self.max_side / max(height, width)
        scale = scale if self.upscale else min(1.0, scale)

        def side(n: int) -> int:
            return max(SIZE_MULTIPLE, int(math.floor(n * scale / SIZE_MULTIPLE + 0.5)) * SIZE_MULTIPLE)

        return side(height), side(width)

    def features(self, image: np.ndarray, key: Hashable | None = None) -> XFeatFeatures:
        """Cached :meth:`extract`. ``key`` names the image (e.g. its file path); it must always
        denote the same pixels. None = :func:`image_key` (a hash of the pixels, ~1 ms). The cache
        keeps the ``cache_size`` most recently used images (0.5 MB each at 2048 keypoints)."""
        image = _rgb(image, str(key) if key is not None else "image")
        key = image_key(image) if key is None else key
        hit = self._cache.get(key)
        if hit is not None and hit[0] == image.shape:
            self._cache.move_to_end(key)
            return hit[1]
        features = self.extract(image, name=str(key))
        if self.cache_size > 0:
            self._cache[key] = (image.shape, features)
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return features

    def extract(self, image: np.ndarray, name: str = "image") -> XFeatFeatures:
        """Keypoints and descriptors of one (H, W, 3) uint8 RGB image (no cache). O(H W) + network."""
        import cv2

        rgb = _rgb(image, name)
        height, width = rgb.shape[:2]
        size = self.model_size(height, width)
        if (height, width) != size:
            shrink = size[0] <= height and size[1] <= width
            rgb = cv2.resize(np.ascontiguousarray(rgb), (size[1], size[0]),
                             interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
        tensor = rgb.astype(np.float32) * np.float32(1.0 / 255.0)
        if self.input_channels == 1:
            tensor = tensor.mean(axis=2, keepdims=True)
        tensor = np.ascontiguousarray(tensor.transpose(2, 0, 1)[None])
        try:
            descriptors, logits, reliability = self.session.run(self.output_names, {self.input_name: tensor})
        except Exception as error:  # onnxruntime raises private exception types
            raise run_error(self.path, f"{self.what} on {name} ({size[1]}x{size[0]})", error, MatcherError) from None
        self.runs += 1
        h, w = size[0] // CELL, size[1] // CELL
        shapes = (descriptors.shape, logits.shape, reliability.shape)
        if shapes != ((1, DESCRIPTOR_DIM, h, w), (1, 65, h, w), (1, 1, h, w)):
            raise MatcherError(f"{self.path}: outputs {[list(s) for s in shapes]} for a {size[1]}x{size[0]} "
                               f"input are not [1, 64|65|1, {h}, {w}]")
        points, scores, desc = xfeat_features(descriptors[0], logits[0], reliability[0],
                                              top_k=self.max_keypoints, threshold=self.detection_threshold,
                                              descriptor_sampling=self.descriptor_sampling)
        return XFeatFeatures(_to_original(points, size, (height, width)), desc, scores, (width, height))


# ----------------------------------------------------------------------------- matchers


def mutual_nearest_neighbours(desc_a: np.ndarray, desc_b: np.ndarray, min_similarity: float = DEFAULT_MIN_SIMILARITY
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual nearest neighbours of unit descriptors under cosine similarity.

    Returns (ia, ib, similarity) for the pairs where b[ib] is a[ia]'s best match and vice versa
    (first index on ties, as argmax) and the similarity exceeds ``min_similarity``.
    O(N M D) time (one matrix product), O(MNN_CHUNK M) memory.
    """
    n, m = desc_a.shape[0], desc_b.shape[0]
    if n == 0 or m == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    a = np.asarray(desc_a, np.float32)
    b_t = np.ascontiguousarray(np.asarray(desc_b, np.float32).T)
    best_b, best_ab = np.empty(n, np.int64), np.empty(n, np.float32)
    col_best = np.full(m, -np.inf, np.float32)
    for start in range(0, n, MNN_CHUNK):
        sim = a[start:start + MNN_CHUNK] @ b_t
        arg = sim.argmax(axis=1)
        best_b[start:start + sim.shape[0]] = arg
        best_ab[start:start + sim.shape[0]] = sim[np.arange(sim.shape[0]), arg]
        np.maximum(col_best, sim.max(axis=0), out=col_best)   # max over rows: contiguous, unlike argmax
    # a's best b is mutual when a attains b's column maximum; the first such a per b (argmax order).
    candidates = np.nonzero(best_ab >= col_best[best_b])[0]
    _, first = np.unique(best_b[candidates], return_index=True)
    ia = candidates[np.sort(first)]
    ib, sim = best_b[ia], best_ab[ia].astype(np.float64)
    keep = sim > min_similarity
    return ia[keep], ib[keep], sim[keep]


class XFeatMNNMatcher:
    """XFeat + mutual nearest neighbours (cosine similarity > ``min_similarity``); scores = the
    similarity clipped to [0, 1]. Cost per pair: two cached extractions + O(N M 64)."""

    def __init__(self, extractor: XFeatExtractor, *, min_similarity: float = DEFAULT_MIN_SIMILARITY) -> None:
        if not -1.0 <= min_similarity < 1.0:
            raise MatcherError(f"{extractor.path}: min_similarity must lie in [-1, 1), got {min_similarity}")
        self.extractor = extractor
        self.min_similarity = float(min_similarity)

    @property
    def name(self) -> str:
        return f"xfeat-mnn({self.extractor.path.name})"

    def match_features(self, fa: XFeatFeatures, fb: XFeatFeatures) -> PixelMatches:
        ia, ib, sim = mutual_nearest_neighbours(fa.descriptors, fb.descriptors, self.min_similarity)
        return PixelMatches(fa.keypoints[ia], fb.keypoints[ib], np.clip(sim, 0.0, 1.0), (len(fa), len(fb)))

    def match(self, image_a: np.ndarray, image_b: np.ndarray, *, key_a: Hashable | None = None,
              key_b: Hashable | None = None) -> PixelMatches:
        return self.match_features(self.extractor.features(image_a, key_a), self.extractor.features(image_b, key_b))


class LighterGlueMatcher:
    """XFeat + LighterGlue (an ONNX export with inputs kpts0 [1, N, 2], kpts1 [1, M, 2], desc0
    [1, N, 64], desc1 [1, M, 64] and outputs matches [K, 2] int64, scores [K]).

    Keypoints are normalised as LightGlue does, (k - size/2) / (max(W, H)/2), in the original
    image's pixels and size (what the reference ``XFeat.match_lighterglue`` passes). Matches are
    the mutual argmaxes of the log-assignment (inside the graph); those with score < ``min_score``
    are dropped. Cost per pair: two cached extractions + the network, O((N + M)^2) attention per
    layer (~0.35 s at 1k + 1k, ~0.8-1.1 s at 2k + 2k keypoints on 2 threads).

    Raises:
        MatcherError: unreadable file or a model without that I/O (the message lists its I/O).
    """

    what = "LighterGlue matcher"

    def __init__(self, extractor: XFeatExtractor, path: str | Path, *, min_score: float = DEFAULT_MIN_SCORE,
                 threads: int = 0) -> None:
        self.path = Path(path)
        if not 0.0 <= min_score <= 1.0:
            raise MatcherError(f"{self.path}: min_score must lie in [0, 1], got {min_score}")
        self.extractor = extractor
        self.min_score = float(min_score)
        self.session = open_session(self.path, threads=threads, what=self.what, error_type=MatcherError)
        inputs, outputs = tensors(self.session)
        by_name = {t.name: t for t in inputs}
        expected = {"kpts0": 2, "kpts1": 2, "desc0": DESCRIPTOR_DIM, "desc1": DESCRIPTOR_DIM}
        problem = None
        if set(by_name) != set(expected):
            problem = f"inputs {sorted(by_name)}"
        else:
            for name, last in expected.items():
                shape = by_name[name].shape
                if len(shape) != 3 or shape[0] not in (None, 1) or shape[2] not in (None, last):
                    problem = f"input {by_name[name].describe()} is not [1, ?, {last}]"
        ranks = sorted(len(t.shape) for t in outputs)
        if problem is None and ranks != [1, 2]:
            problem = f"outputs of rank {ranks}"
        if problem is not None:
            raise MatcherError(f"{self.path}: not a LighterGlue matcher for XFeat ({problem}; expected inputs "
                               f"kpts0 [1, N, 2], kpts1 [1, M, 2], desc0 [1, N, 64], desc1 [1, M, 64] and "
                               f"outputs matches [K, 2], scores [K]). {describe_io(self.session)}")
        self.matches_name = next(t.name for t in outputs if len(t.shape) == 2)
        self.scores_name = next(t.name for t in outputs if len(t.shape) == 1)

    @property
    def name(self) -> str:
        return f"xfeat+lighterglue({self.extractor.path.name}, {self.path.name})"

    @staticmethod
    def normalise(keypoints: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
        """(N, 2) pixels of an image of (W, H) -> float32 (k - size/2) / (max(W, H)/2)."""
        size = np.asarray(image_size, np.float64)
        return ((keypoints - size / 2) / (size.max() / 2)).astype(np.float32)

    def match_features(self, fa: XFeatFeatures, fb: XFeatFeatures) -> PixelMatches:
        counts = (len(fa), len(fb))
        if min(counts) == 0:
            return PixelMatches.empty(counts)
        feed = {"kpts0": self.normalise(fa.keypoints, fa.image_size)[None],
                "kpts1": self.normalise(fb.keypoints, fb.image_size)[None],
                "desc0": np.ascontiguousarray(fa.descriptors, np.float32)[None],
                "desc1": np.ascontiguousarray(fb.descriptors, np.float32)[None]}
        try:
            matches, scores = self.session.run([self.matches_name, self.scores_name], feed)
        except Exception as error:  # onnxruntime raises private exception types
            raise run_error(self.path, f"{self.what} ({counts[0]} x {counts[1]} keypoints)", error,
                            MatcherError) from None
        matches = np.asarray(matches).astype(np.int64).reshape(-1, 2)
        scores = np.asarray(scores, np.float64).reshape(-1)
        if scores.shape[0] != matches.shape[0]:
            raise MatcherError(f"{self.path}: {matches.shape[0]} matches but {scores.shape[0]} scores")
        keep = ((matches[:, 0] >= 0) & (matches[:, 0] < counts[0]) & (matches[:, 1] >= 0)
                & (matches[:, 1] < counts[1]) & np.isfinite(scores) & (scores >= self.min_score))
        ia, ib = matches[keep, 0], matches[keep, 1]
        return PixelMatches(fa.keypoints[ia], fb.keypoints[ib], np.clip(scores[keep], 0.0, 1.0), counts)

    def match(self, image_a: np.ndarray, image_b: np.ndarray, *, key_a: Hashable | None = None,
              key_b: Hashable | None = None) -> PixelMatches:
        return self.match_features(self.extractor.features(image_a, key_a), self.extractor.features(image_b, key_b))


class LightGluePipelineMatcher:
    """The end-to-end LightGlue-ONNX export (:class:`sparseart.align.lightglue.LightGlueMatcher`:
    its checks, resizing and pixel mapping) as a :class:`PixelMatcher`. One network pass per pair
    (no per-image cache: the pipeline extracts and matches together)."""

    def __init__(self, path: str | Path, *, min_score: float | None = None, max_side: int | None = None,
                 threads: int = 0) -> None:
        from sparseart.align.lightglue import LightGlueMatcher, LightGlueOptions

        options = LightGlueOptions(threads=threads)
        if min_score is not None:
            options.min_score = float(min_score)
        if max_side is not None:
            options.max_side = int(max_side)
        self.pipeline = LightGlueMatcher(path, options)
        self.path = self.pipeline.path

    @property
    def name(self) -> str:
        return f"lightglue-pipeline({self.path.name})"

    def match(self, image_a: np.ndarray, image_b: np.ndarray, *, key_a: Hashable | None = None,
              key_b: Hashable | None = None) -> PixelMatches:
        from sparseart.align.lightglue import PIPELINE_OUTPUTS

        pipe = self.pipeline
        names = (str(key_a) if key_a is not None else "image a", str(key_b) if key_b is not None else "image b")
        frames = [Frame("start", 0, Path(n), _rgb(im, n)) for n, im in zip(names, (image_a, image_b))]
        size = pipe.model_size(*frames[0].rgb.shape[:2])
        images = np.stack([pipe._image(f, size) for f in frames]).astype(np.float16 if pipe.float16 else np.float32)
        try:
            keypoints, matches, scores = (np.asarray(o) for o in pipe.session.run(list(PIPELINE_OUTPUTS),
                                                                                   {pipe.input_name: images}))
        except Exception as error:  # onnxruntime raises private exception types
            raise run_error(self.path, f"LightGlue pipeline on {names[0]} / {names[1]}", error, MatcherError) from None
        if keypoints.ndim != 3 or keypoints.shape[0] != 2 or keypoints.shape[2] != 2 \
                or matches.ndim != 2 or matches.shape[1] != 3 or scores.shape != (matches.shape[0],):
            raise MatcherError(f"{self.path}: outputs keypoints {keypoints.shape}, matches {matches.shape}, "
                               f"mscores {scores.shape} are not [2, K, 2], [M, 3], [M]")
        count = keypoints.shape[1]
        matches, scores = matches.astype(np.int64), scores.astype(np.float64)
        keep = ((matches[:, 0] == 0) & (matches[:, 1] >= 0) & (matches[:, 1] < count) & (matches[:, 2] >= 0)
                & (matches[:, 2] < count) & np.isfinite(scores) & (scores >= pipe.options.min_score))
        keypoints = keypoints.astype(np.float64)
        pixels_a = _to_original(keypoints[0, matches[keep, 1]], size, frames[0].rgb.shape[:2])
        pixels_b = _to_original(keypoints[1, matches[keep, 2]], size, frames[1].rgb.shape[:2])
        return PixelMatches(pixels_a, pixels_b, np.clip(scores[keep], 0.0, 1.0), (count, count))


# ----------------------------------------------------------------------------- specs


_FIELDS = {   # field -> kinds it applies to
    "schema": KINDS, "kind": KINDS, "description": KINDS,
    "detector": ("xfeat+lighterglue", "xfeat"),
    "matcher": ("xfeat+lighterglue", "lightglue-pipeline"),
    "min_score": ("xfeat+lighterglue", "lightglue-pipeline"),
    "max_keypoints": ("xfeat+lighterglue", "xfeat"),
    "max_side": KINDS,
    "upscale": ("xfeat+lighterglue", "xfeat"),
    "detection_threshold": ("xfeat+lighterglue", "xfeat"),
    "min_similarity": ("xfeat",),
}


def _number(data: dict, field: str, where: str, low: float, high: float, integer: bool = False):
    value = data.get(field)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (integer and not isinstance(value, int)) \
            or not math.isfinite(value) or not low <= value <= high:
        kind = "an integer" if integer else "a number"
        raise MatcherError(f"{where}: field '{field}' must be {kind} in [{low:g}, {high:g}], got {value!r}")
    return value


def _from_contract(path: Path, threads: int) -> PixelMatcher:
    """A matcher from a ``sparseart-matcher/1`` JSON file (model paths relative to the file)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise MatcherError(f"{path}: matcher contract not found") from None
    except (OSError, UnicodeDecodeError) as error:
        raise MatcherError(f"{path}: cannot read the matcher contract ({error})") from None
    except json.JSONDecodeError as error:
        raise MatcherError(f"{path}: not valid JSON (line {error.lineno}: {error.msg})") from None
    if not isinstance(data, dict):
        raise MatcherError(f"{path}: a matcher contract must be a JSON object, got {type(data).__name__}")
    if data.get("schema") != SCHEMA:
        raise MatcherError(f"{path}: field 'schema' must be {SCHEMA!r}, got {data.get('schema')!r}")
    kind = data.get("kind")
    if kind not in KINDS:
        raise MatcherError(f"{path}: field 'kind' must be one of {', '.join(KINDS)}, got {kind!r}")
    unknown = sorted(set(data) - set(_FIELDS))
    if unknown:
        raise MatcherError(f"{path}: unknown field(s) {', '.join(unknown)} (allowed: {', '.join(_FIELDS)})")
    misplaced = sorted(f for f in data if kind not in _FIELDS[f])
    if misplaced:
        raise MatcherError(f"{path}: field(s) {', '.join(misplaced)} do not apply to kind {kind!r}")

    def model(field: str) -> Path:
        value = data.get(field)
        if not isinstance(value, str) or not value.strip():
            raise MatcherError(f"{path}: kind {kind!r} needs field '{field}' (a path to an .onnx file, "
                               f"relative to the contract), got {value!r}")
        resolved = Path(value) if Path(value).is_absolute() else (path.parent / value).resolve()
        if not resolved.is_file():
            raise MatcherError(f"{path}: field '{field}': model file {resolved} not found (paths are relative "
                               f"to the contract)")
        return resolved

    min_score = _number(data, "min_score", str(path), 0.0, 1.0)
    max_keypoints = _number(data, "max_keypoints", str(path), 1, 1 << 20, integer=True)
    max_side = _number(data, "max_side", str(path), SIZE_MULTIPLE, 1 << 16, integer=True)
    threshold = _number(data, "detection_threshold", str(path), 1e-6, 1 - 1e-6)
    min_similarity = _number(data, "min_similarity", str(path), -1.0, 0.999999)
    upscale = data.get("upscale", True)
    if not isinstance(upscale, bool):
        raise MatcherError(f"{path}: field 'upscale' must be true or false, got {upscale!r}")
    if kind == "lightglue-pipeline":
        return LightGluePipelineMatcher(model("matcher"), min_score=min_score, max_side=max_side, threads=threads)
    extractor = XFeatExtractor(model("detector"), threads=threads,
                               max_keypoints=DEFAULT_MAX_KEYPOINTS if max_keypoints is None else max_keypoints,
                               max_side=DEFAULT_MAX_SIDE if max_side is None else max_side, upscale=upscale,
                               detection_threshold=DETECTION_THRESHOLD if threshold is None else threshold)
    if kind == "xfeat":
        return XFeatMNNMatcher(extractor, min_similarity=DEFAULT_MIN_SIMILARITY if min_similarity is None
                               else min_similarity)
    return LighterGlueMatcher(extractor, model("matcher"), threads=threads,
                              min_score=DEFAULT_MIN_SCORE if min_score is None else min_score)


def open_matcher(spec: str | Path, *, threads: int = 0, min_score: float | None = None) -> PixelMatcher:
    """A :class:`PixelMatcher` from a spec.

    Specs:
        ``xfeat:DET.onnx,MATCHER.onnx``  XFeat + LighterGlue (default thresholds);
        ``xfeat:DET.onnx``               XFeat + mutual nearest neighbours;
        ``PATH.json``                    a ``sparseart-matcher/1`` contract: ``{"schema":
            "sparseart-matcher/1", "kind": "xfeat+lighterglue" | "xfeat" | "lightglue-pipeline",
            "detector": ..., "matcher": ..., "min_score", "max_keypoints", "max_side", "upscale",
            "detection_threshold", "min_similarity", "description"}`` (paths relative to the file;
            a field that does not apply to the kind is an error);
        ``PATH.onnx``                    an end-to-end LightGlue-ONNX pipeline export.
    threads: onnxruntime intra-op threads per session (0 = its default).
    min_score: overrides the match-score threshold of a LighterGlue or LightGlue-pipeline matcher
        (e.g. a command-line option; wins over the contract); an error for MNN matchers.

    Raises:
        MatcherError (a SceneError): one line naming the spec, file or field at fault.
    """
    matcher = _open_matcher(spec, threads)
    if min_score is not None:
        if not 0.0 <= min_score <= 1.0:
            raise MatcherError(f"matcher spec {str(spec)!r}: min_score must lie in [0, 1], got {min_score}")
        if isinstance(matcher, LighterGlueMatcher):
            matcher.min_score = float(min_score)
        elif isinstance(matcher, LightGluePipelineMatcher):
            matcher.pipeline.options.min_score = float(min_score)
        else:
            raise MatcherError(f"matcher spec {str(spec)!r}: min_score does not apply to {type(matcher).__name__} "
                               f"(mutual nearest neighbours use min_similarity, set in a JSON contract)")
    return matcher


def _open_matcher(spec: str | Path, threads: int) -> PixelMatcher:
    text = str(spec).strip()
    if not text:
        raise MatcherError("matcher spec is empty (expected xfeat:DET.onnx[,MATCHER.onnx], a LightGlue "
                           "pipeline .onnx or a sparseart-matcher/1 .json)")
    if text.lower().startswith("xfeat:"):
        parts = [p.strip() for p in text[len("xfeat:"):].split(",")]
        if not 1 <= len(parts) <= 2 or not all(parts):
            raise MatcherError(f"matcher spec {text!r}: expected xfeat:DET.onnx or xfeat:DET.onnx,MATCHER.onnx")
        extractor = XFeatExtractor(parts[0], threads=threads)
        if len(parts) == 1:
            return XFeatMNNMatcher(extractor)
        return LighterGlueMatcher(extractor, parts[1], threads=threads)
    path = Path(text)
    head = text.split(":", 1)[0]
    if ":" in text and not path.exists() and head.isalnum() and len(head) > 1:
        raise MatcherError(f"matcher spec {text!r}: unknown kind {head!r} (expected xfeat:DET.onnx[,MATCHER.onnx], "
                           f"a LightGlue pipeline .onnx or a sparseart-matcher/1 .json)")
    if path.suffix.lower() == ".json":
        return _from_contract(path, threads)
    if path.exists() and path.is_file() and path.suffix.lower() != ".onnx":
        raise MatcherError(f"{path}: a matcher must be an .onnx LightGlue pipeline export or a .json "
                           f"contract (got a {path.suffix or 'suffix-less'} file)")
    return LightGluePipelineMatcher(path, threads=threads)


# ----------------------------------------------------------------------------- lifting


def lifted_matches(matcher: PixelMatcher, frame_a: Frame, pointmap_a: Pointmap, frame_b: Frame,
                   pointmap_b: Pointmap, key_a: Hashable | None = None,
                   key_b: Hashable | None = None) -> FeatureMatches:
    """Pixel matches of two frames lifted to 3D through their pointmaps (each in its own frame),
    as :meth:`sparseart.align.lightglue.LightGlueMatcher.match` returns them.

    Each pixel takes the point of the nearest valid pointmap pixel within ``LIFT_RADIUS_PX``;
    matches without a point on either side are dropped. n_ratio_passed = matches before that drop;
    view_a / view_b are zeros (one pair). key_a / key_b: cache keys of the images (None = hash).
    O(matcher) + O(H W) per image for the lift's distance transform.
    """
    for frame, pointmap in ((frame_a, pointmap_a), (frame_b, pointmap_b)):
        if frame.rgb.shape[:2] != (pointmap.height, pointmap.width):
            raise MatcherError(f"{frame.rgb_path}: image size {frame.rgb.shape[1]}x{frame.rgb.shape[0]} does not "
                               f"match its pointmap ({pointmap.width}x{pointmap.height})")
    pixels = matcher.match(frame_a.rgb, frame_b.rgb, key_a=key_a, key_b=key_b)
    points_a = lift_pixels(pointmap_a, pixels.pixels_a)
    points_b = lift_pixels(pointmap_b, pixels.pixels_b)
    lifted = np.isfinite(points_a).all(axis=1) & np.isfinite(points_b).all(axis=1)
    k = int(lifted.sum())
    return FeatureMatches(points_a[lifted], points_b[lifted], pixels.pixels_a[lifted], pixels.pixels_b[lifted],
                          pixels.n_keypoints, len(pixels), np.zeros(k, np.int64), np.zeros(k, np.int64))


class LiftedMatcher:
    """The pair-matcher interface of :func:`sparseart.align.register_views` / ``align_states``
    (``match(frame_a, pointmap_a, frame_b, pointmap_b) -> FeatureMatches``) over any
    :class:`PixelMatcher`. Images are cache-keyed by a hash of their pixels, so each image's
    features are computed once however many pairs it is in."""

    def __init__(self, matcher: PixelMatcher) -> None:
        self.matcher = matcher

    def match(self, frame_a: Frame, pointmap_a: Pointmap, frame_b: Frame, pointmap_b: Pointmap) -> FeatureMatches:
        return lifted_matches(self.matcher, frame_a, pointmap_a, frame_b, pointmap_b)
