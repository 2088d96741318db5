"""Learned feature matches from an ONNX LightGlue export (fabio-sim/LightGlue-ONNX), lifted to 3D.

The supported export is the current end-to-end pipeline (``lightglue-onnx export superpoint|disk|
aliked``): one input ``images [2, C, H, W]`` float in [0, 1] (C = 1 grey for SuperPoint, 3 RGB for
DISK / ALIKED), outputs ``keypoints [2, K, 2]`` (x, y pixels of the *model input* image),
``matches [M, 3]`` (batch index, index in image 0, index in image 1) and ``mscores [M]``
(``../shared/research/onnx-models.md`` section 4.1). The older split export (extractor + matcher
models) is refused with a message saying what to export instead.

Pixel mapping: both images are resized (OpenCV INTER_AREA, half-pixel centres) to the model's
fixed H x W, or -- for dynamic sizes -- to image a's size scaled so its long side is at most
``max_side`` and rounded to a multiple of 8; a keypoint (x, y) of the model grid is
((x + 0.5) sx - 0.5, (y + 0.5) sy - 0.5) in the original image, sx = W0 / W. Keypoints are then
lifted through the image's pointmap exactly as the SIFT ones are (nearest valid pixel within
``LIFT_RADIUS_PX``), so both matchers feed the same RANSAC + Umeyama alignment.

Cost: one forward pass per image pair (the network dominates: O(K^2) attention per layer), plus
O(H W) per image for the resize and the distance transform of the lift.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sparseart.align.features import FeatureMatches, lift_pixels
from sparseart.types import Frame, Pointmap

DEFAULT_MIN_SCORE = 0.1   # LightGlue-ONNX's own filter threshold
DEFAULT_MAX_SIDE = 1024   # long side of the model input for dynamic-size exports
SIZE_MULTIPLE = 8         # dynamic sizes are rounded to this (the extractors downsample by 8)
PIPELINE_OUTPUTS = ("keypoints", "matches", "mscores")
SPLIT_INPUTS = ("image", "kpts0", "kpts1", "desc0", "desc1", "image0", "image1")


@dataclass
class LightGlueOptions:
    """threads: onnxruntime intra-op threads (0 = its default); min_score: matches below it are
    dropped; max_side: long side of the model input when the export has a dynamic size;
    providers: execution providers (None = CUDA when available, then CPU)."""

    threads: int = 0
    min_score: float = DEFAULT_MIN_SCORE
    max_side: int = DEFAULT_MAX_SIDE
    providers: tuple[str, ...] | None = None


class LightGlueMatcher:
    """A pair matcher (``match(frame_a, pointmap_a, frame_b, pointmap_b) -> FeatureMatches``) backed
    by an ONNX LightGlue pipeline export. Construction opens and checks the model.

    Raises:
        ModelError: missing/unloadable file, or a model that is not a LightGlue pipeline export
            (the message lists the model's inputs and outputs).
    """

    def __init__(self, path: str | Path, options: LightGlueOptions | None = None) -> None:
        from sparseart.lift.contract import ModelError
        from sparseart.lift.onnx_model import OnnxLiftOptions, model_io, open_session

        self.path = Path(path)
        self.options = options or LightGlueOptions()
        if not 0.0 <= self.options.min_score <= 1.0:
            raise ModelError(f"{self.path}: matcher min_score must lie in [0, 1], got {self.options.min_score}")
        session_options = OnnxLiftOptions(threads=self.options.threads, providers=self.options.providers)
        self.session = open_session(self.path, session_options)
        io = model_io(self.session, self.path)
        input_names = [t.name for t in io.inputs]
        output_names = [t.name for t in io.outputs]
        if any(name in SPLIT_INPUTS for name in input_names):
            raise ModelError(f"{self.path}: this looks like a split LightGlue export (extractor or matcher "
                             f"alone); export the end-to-end pipeline instead (lightglue-onnx export "
                             f"superpoint|disk|aliked). {io.describe()}")
        if len(io.inputs) != 1 or not set(PIPELINE_OUTPUTS) <= set(output_names):
            raise ModelError(f"{self.path}: not a LightGlue pipeline export (expected one input "
                             f"images[2, C, H, W] and outputs {', '.join(PIPELINE_OUTPUTS)}). {io.describe()}")
        image = io.inputs[0]
        if len(image.shape) != 4 or image.shape[1] not in (1, 3) or image.shape[0] not in (None, 2):
            raise ModelError(f"{self.path}: input {image.describe()} is not images[2, 1|3, H, W]")
        self.input_name = image.name
        self.channels = int(image.shape[1])
        self.fixed_size = (image.shape[2], image.shape[3]) if None not in image.shape[2:] else None
        self.float16 = "float16" in image.type

    def model_size(self, height: int, width: int) -> tuple[int, int]:
        """(H, W) of the model input for an original image of height x width pixels."""
        if self.fixed_size is not None:
            return int(self.fixed_size[0]), int(self.fixed_size[1])
        scale = min(1.0, self.options.max_side / max(height, width))
        return (max(SIZE_MULTIPLE, int(round(height * scale / SIZE_MULTIPLE)) * SIZE_MULTIPLE),
                max(SIZE_MULTIPLE, int(round(width * scale / SIZE_MULTIPLE)) * SIZE_MULTIPLE))

    def _image(self, frame: Frame, size: tuple[int, int]) -> np.ndarray:
        """(C, H, W) float32 in [0, 1] of the frame resized to ``size`` (H, W)."""
        import cv2

        rgb = np.ascontiguousarray(frame.rgb[..., :3]).astype(np.uint8)
        if rgb.shape[:2] != size:
            rgb = cv2.resize(rgb, (size[1], size[0]), interpolation=cv2.INTER_AREA)
        image = rgb.astype(np.float32) / 255.0
        if self.channels == 1:   # LightGlue-ONNX's SuperPoint preprocessing weights
            return (image @ np.array([0.299, 0.587, 0.114], np.float32))[None]
        return image.transpose(2, 0, 1)

    def match(self, frame_a: Frame, pointmap_a: Pointmap, frame_b: Frame, pointmap_b: Pointmap) -> FeatureMatches:
        """Matches between two images, lifted to 3D through their pointmaps (each in its own frame)."""
        from sparseart.lift.contract import ModelError

        size = self.model_size(*frame_a.rgb.shape[:2])
        images = np.stack([self._image(frame_a, size), self._image(frame_b, size)])
        images = images.astype(np.float16 if self.float16 else np.float32)
        try:
            outputs = self.session.run(list(PIPELINE_OUTPUTS), {self.input_name: images})
        except Exception as error:  # onnxruntime raises private exception types
            first = next((line for line in str(error).splitlines() if line.strip()), type(error).__name__)
            raise ModelError(f"{self.path}: matcher failed on {frame_a.rgb_path.name} / "
                             f"{frame_b.rgb_path.name} ({first[:200]})") from None
        keypoints, matches, scores = (np.asarray(o) for o in outputs)
        if keypoints.ndim != 3 or keypoints.shape[0] != 2 or keypoints.shape[2] != 2 \
                or matches.ndim != 2 or matches.shape[1] != 3 or scores.shape != (matches.shape[0],):
            raise ModelError(f"{self.path}: outputs keypoints {keypoints.shape}, matches {matches.shape}, "
                             f"mscores {scores.shape} are not [2, K, 2], [M, 3], [M]")
        keypoints = keypoints.astype(np.float64)
        n_keypoints = (int(keypoints.shape[1]), int(keypoints.shape[1]))
        matches = matches.astype(np.int64)
        scores = scores.astype(np.float64)
        count = keypoints.shape[1]
        keep = ((matches[:, 0] == 0) & (matches[:, 1] >= 0) & (matches[:, 1] < count)
                & (matches[:, 2] >= 0) & (matches[:, 2] < count) & np.isfinite(scores)
                & (scores >= self.options.min_score))
        ia, ib = matches[keep, 1], matches[keep, 2]
        pixels_a = _to_original(keypoints[0, ia], size, frame_a.rgb.shape[:2])
        pixels_b = _to_original(keypoints[1, ib], size, frame_b.rgb.shape[:2])
        points_a = lift_pixels(pointmap_a, pixels_a)
        points_b = lift_pixels(pointmap_b, pixels_b)
        lifted = np.isfinite(points_a).all(axis=1) & np.isfinite(points_b).all(axis=1)
        k = int(lifted.sum())
        return FeatureMatches(points_a[lifted], points_b[lifted], pixels_a[lifted], pixels_b[lifted],
                              n_keypoints, int(keep.sum()), np.zeros(k, np.int64), np.zeros(k, np.int64))


def _to_original(pixels: np.ndarray, model_size: tuple[int, int], original_size: tuple[int, int]) -> np.ndarray:
    """(K, 2) x, y pixels of the model grid -> the original image (half-pixel centres)."""
    sy = original_size[0] / model_size[0]
    sx = original_size[1] / model_size[1]
    return np.column_stack([(pixels[:, 0] + 0.5) * sx - 0.5, (pixels[:, 1] + 0.5) * sy - 0.5])
