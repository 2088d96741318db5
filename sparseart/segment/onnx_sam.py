"""SAM-family ONNX adapter: automatic masks from a grid of point prompts, painted into one label image.

Supported layout (SAM / MobileSAM exports: facebookresearch/segment-anything
``scripts/export_onnx_model.py`` and samexporter; see ../shared/research/onnx-models.md section 3):

* encoder: one input, either ``[1, 3, S, S]`` (image resized so its long side is S, normalised with
  the ImageNet mean/std in 0-255 units, zero-padded bottom/right; S from the model, else 1024) or
  ``[H', W', 3]`` (samexporter ``--use-preprocess``: 0-255 RGB resized to long side S, normalisation
  inside); output ``image_embeddings``.
* decoder: inputs ``image_embeddings, point_coords [B, N, 2], point_labels [B, N], mask_input
  [B, 1, 256, 256], has_mask_input [B], orig_im_size [2]``; outputs ``masks [B, M, H, W]`` (logits
  at the original size, threshold 0) and ``iou_predictions [B, M]``. When the decoder's batch axis
  is dynamic, ``points_per_batch`` prompts go in one call; otherwise one call per prompt.

SAM2 (``image_embed, high_res_feats_0, ...``) and EfficientSAM (``batched_point_coords``) decoders
are detected by their input names and refused with a message saying so.

Automatic mask generation (after ``SamAutomaticMaskGenerator``): an ``n x n`` grid of single
foreground points (``points_per_side``; on depth frames only points with valid depth), every
multimask output kept when its predicted IoU >= ``pred_iou_thresh`` and its stability score
(area(logits > +offset) / area(logits > -offset)) >= ``stability_thresh`` and its area >=
``min_area_pixels``; box NMS (IoU > ``nms_iou``, by predicted IoU, applied after every decoder
batch to the masks kept so far, so memory stays at distinct masks x H x W); kept masks are painted largest
first, so smaller masks (parts, handles) lie on top of the larger ones containing them. Pixels no
mask covers, and pixels without depth, are 0.

CPU cost: one encoder pass per image plus ceil(n^2 / points_per_batch) decoder calls (n^2 with a
fixed-batch decoder); decoder time is ~40-90 ms per call for MobileSAM/EfficientSAM-class models,
so ``points_per_side=16`` (256 prompts) costs ~10-20 s per image unbatched and 32 about four times
that. Mask post-processing is O(n^2 M H W).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..types import Frame
from .base import check_rgb, relabel_consecutive

SAM1_DECODER_INPUTS = ("image_embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input",
                       "orig_im_size")
PIXEL_MEAN = np.array([123.675, 116.28, 103.53])
PIXEL_STD = np.array([58.395, 57.12, 57.375])
DEFAULT_LONG_SIDE = 1024


@dataclass(frozen=True)
class SamOptions:
    """Automatic-mask-generation settings (defaults of SamAutomaticMaskGenerator except the grid,
    16 instead of 32 for CPU time). ``threads``: onnxruntime intra-op threads (0 = its default)."""

    points_per_side: int = 16
    points_per_batch: int = 64
    pred_iou_thresh: float = 0.88
    stability_thresh: float = 0.95
    stability_offset: float = 1.0
    nms_iou: float = 0.7
    min_area_pixels: int = 16
    threads: int = 0

    def __post_init__(self) -> None:
        if int(self.points_per_side) < 1 or int(self.points_per_batch) < 1:
            raise ValueError("SamOptions: points_per_side and points_per_batch must be >= 1")
        for name in ("pred_iou_thresh", "stability_thresh", "nms_iou"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"SamOptions.{name} must be in [0, 1], got {getattr(self, name)!r}")
        if self.stability_offset < 0:
            raise ValueError(f"SamOptions.stability_offset must be >= 0, got {self.stability_offset!r}")


def _session(path: Path, role: str, threads: int):
    """The SAM encoder or decoder session (:func:`sparseart._onnx.open_session`; SceneError, a
    ValueError, naming the file)."""
    from sparseart._onnx import open_session

    return open_session(path, what=f"SAM {role}", threads=threads, providers=["CPUExecutionProvider"])


def _describe(io) -> str:
    return ", ".join(f"{x.name} {list(x.shape)}" for x in io)


def grid_points(height: int, width: int, points_per_side: int) -> np.ndarray:
    """(n*n, 2) float64 pixel coordinates (x, y) at ((i + 0.5) / n * W, (j + 0.5) / n * H)."""
    steps = (np.arange(points_per_side) + 0.5) / points_per_side
    xs, ys = np.meshgrid(steps * width, steps * height)
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def stability_scores(logits: np.ndarray, offset: float) -> np.ndarray:
    """(K,) area(logits > +offset) / area(logits > -offset) for (K, H, W) logits (1 when both are 0)."""
    flat = logits.reshape(logits.shape[0], int(np.prod(logits.shape[1:])))
    high = np.count_nonzero(flat > offset, axis=1)
    low = np.count_nonzero(flat > -offset, axis=1)
    return np.where(low > 0, high / np.maximum(low, 1), 1.0)


def paint_masks(masks: np.ndarray) -> np.ndarray:
    """(K, H, W) bool masks -> (H, W) int64 labels: largest painted first, smaller on top, 0 where
    no mask covers; ids renumbered 1..S over what stays visible. O(K H W)."""
    if masks.shape[0] == 0:
        return np.zeros(masks.shape[1:], dtype=np.int64)
    order = np.argsort(-masks.reshape(masks.shape[0], int(np.prod(masks.shape[1:]))).sum(axis=1), kind="stable")
    labels = np.zeros(masks.shape[1:], dtype=np.int64)
    for rank, k in enumerate(order, start=1):
        labels[masks[k]] = rank
    return relabel_consecutive(labels)


def box_nms(masks: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Indices of masks kept by NMS on their bounding boxes (cv2.dnn.NMSBoxes), best score first."""
    import cv2

    boxes = []
    for mask in masks:
        rows, cols = np.any(mask, axis=1), np.any(mask, axis=0)
        y0, y1 = np.flatnonzero(rows)[[0, -1]]
        x0, x1 = np.flatnonzero(cols)[[0, -1]]
        boxes.append([int(x0), int(y0), int(x1 - x0 + 1), int(y1 - y0 + 1)])
    keep = cv2.dnn.NMSBoxes(boxes, scores.astype(float).tolist(), 0.0, float(iou_threshold))
    return np.asarray(keep, dtype=np.int64).reshape(-1)


class SamSegmenter:
    """Automatic SAM segmentation of a frame (see module docstring). Loading checks both models."""

    name = "sam"

    def __init__(self, encoder: str | Path, decoder: str | Path, options: SamOptions | None = None) -> None:
        self.options = options or SamOptions()
        self.encoder_path, self.decoder_path = Path(encoder), Path(decoder)
        self.encoder = _session(self.encoder_path, "encoder", self.options.threads)
        self.decoder = _session(self.decoder_path, "decoder", self.options.threads)
        self._check_layout()

    def _check_layout(self) -> None:
        dec_inputs = {x.name: x for x in self.decoder.get_inputs()}
        names = set(dec_inputs)
        if "image_embed" in names or "high_res_feats_0" in names:
            raise ValueError(f"{self.decoder_path}: a SAM2 decoder ({_describe(self.decoder.get_inputs())}); "
                             f"only the SAM/MobileSAM layout ({', '.join(SAM1_DECODER_INPUTS)}) is supported")
        if "batched_point_coords" in names:
            raise ValueError(f"{self.decoder_path}: an EfficientSAM decoder ({_describe(self.decoder.get_inputs())}); "
                             f"only the SAM/MobileSAM layout ({', '.join(SAM1_DECODER_INPUTS)}) is supported")
        missing = [n for n in SAM1_DECODER_INPUTS if n not in names]
        if missing:
            raise ValueError(f"{self.decoder_path}: decoder lacks inputs {missing}; it has "
                             f"{_describe(self.decoder.get_inputs())} (expected {', '.join(SAM1_DECODER_INPUTS)})")
        outputs = {x.name for x in self.decoder.get_outputs()}
        if not {"masks", "iou_predictions"} <= outputs:
            raise ValueError(f"{self.decoder_path}: decoder outputs {_describe(self.decoder.get_outputs())}; "
                             f"expected 'masks' and 'iou_predictions'")
        enc_inputs = self.encoder.get_inputs()
        if len(enc_inputs) != 1 or len(enc_inputs[0].shape) not in (3, 4):
            raise ValueError(f"{self.encoder_path}: encoder must have one image input [1,3,S,S] or [H,W,3]; "
                             f"it has {_describe(enc_inputs)}")
        enc_outputs = {x.name: x for x in self.encoder.get_outputs()}
        if "image_embeddings" not in enc_outputs:
            raise ValueError(f"{self.encoder_path}: encoder outputs {_describe(self.encoder.get_outputs())} do "
                             f"not include 'image_embeddings' that decoder {self.decoder_path.name} needs")
        produced, expected = enc_outputs["image_embeddings"].shape, dec_inputs["image_embeddings"].shape
        if len(produced) != len(expected) or any(isinstance(p, int) and isinstance(e, int) and p != e
                                                 for p, e in zip(produced, expected)):
            raise ValueError(f"encoder {self.encoder_path.name} makes image_embeddings {list(produced)} but decoder "
                             f"{self.decoder_path.name} takes {list(expected)}: mismatched encoder/decoder pair")
        self.encoder_input = enc_inputs[0]
        shape = self.encoder_input.shape
        side = shape[2] if len(shape) == 4 else None
        self.long_side = int(side) if isinstance(side, int) else DEFAULT_LONG_SIDE
        mask_shape = dec_inputs["mask_input"].shape
        self.mask_input_shape = tuple(d if isinstance(d, int) else 256 for d in mask_shape[-2:])
        batch = dec_inputs["point_coords"].shape[0]
        self.batched = not (isinstance(batch, int) and batch == 1)

    def embed(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> the encoder's image_embeddings. One encoder pass."""
        import cv2

        height, width = rgb.shape[:2]
        scale = self.long_side / max(height, width)
        new_h, new_w = int(height * scale + 0.5), int(width * scale + 0.5)
        resized = cv2.resize(rgb, (new_w, new_h), interpolation=cv2.INTER_LINEAR) if (new_h, new_w) != (
            height, width) else rgb
        if len(self.encoder_input.shape) == 3:
            tensor = resized.astype(np.float32)
        else:
            normalised = (resized.astype(np.float64) - PIXEL_MEAN) / PIXEL_STD
            padded = np.zeros((self.long_side, self.long_side, 3), dtype=np.float32)
            padded[:new_h, :new_w] = normalised
            tensor = padded.transpose(2, 0, 1)[None]
        try:
            return self.encoder.run(["image_embeddings"], {self.encoder_input.name: tensor})[0]
        except Exception as error:
            raise ValueError(f"{self.encoder_path}: encoder failed on a {width}x{height} image "
                             f"({str(error).strip().splitlines()[0]})") from None

    def _decode(self, embedding: np.ndarray, points: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """points (B, 2) original pixels -> (B, M, H, W) logits, (B, M) predicted IoU."""
        count = points.shape[0]
        scale = self.long_side / max(height, width)
        coords = np.zeros((count, 2, 2), dtype=np.float32)  # prompt point + SAM's padding point
        coords[:, 0] = points * scale
        labels = np.tile(np.array([[1.0, -1.0]], dtype=np.float32), (count, 1))
        feeds = {"image_embeddings": embedding, "point_coords": coords, "point_labels": labels,
                 "mask_input": np.zeros((count, 1, *self.mask_input_shape), dtype=np.float32),
                 "has_mask_input": np.zeros(count, dtype=np.float32),
                 "orig_im_size": np.array([height, width], dtype=np.float32)}
        try:
            masks, iou = self.decoder.run(["masks", "iou_predictions"], feeds)
        except Exception as error:
            raise ValueError(f"{self.decoder_path}: decoder failed with {count} prompts "
                             f"({str(error).strip().splitlines()[0]})") from None
        if masks.ndim != 4 or masks.shape[0] != count or masks.shape[2:] != (height, width):
            raise ValueError(f"{self.decoder_path}: decoder returned masks {list(masks.shape)}, expected "
                             f"[{count}, M, {height}, {width}]")
        return masks, np.asarray(iou).reshape(count, -1)

    def segment(self, frame: Frame) -> np.ndarray:
        rgb = check_rgb(frame)
        height, width = rgb.shape[:2]
        o = self.options
        points = grid_points(height, width, int(o.points_per_side))
        valid = None
        if frame.depth is not None:
            valid = np.asarray(frame.depth) > 0
            ix = np.clip(points[:, 0].astype(int), 0, width - 1)
            iy = np.clip(points[:, 1].astype(int), 0, height - 1)
            points = points[valid[iy, ix]]
        embedding = self.embed(rgb)
        batch = int(o.points_per_batch) if self.batched else 1
        kept_masks = np.zeros((0, height, width), dtype=bool)
        kept_scores = np.zeros(0)
        for start in range(0, points.shape[0], batch):
            logits, iou = self._decode(embedding, points[start:start + batch], height, width)
            logits = logits.reshape(-1, height, width)
            iou = iou.reshape(-1)
            good = iou >= o.pred_iou_thresh
            logits, iou = logits[good], iou[good]
            good = stability_scores(logits, o.stability_offset) >= o.stability_thresh
            masks = logits[good] > 0.0
            if valid is not None:
                masks &= valid
            big = masks.reshape(masks.shape[0], height * width).sum(axis=1) >= max(1, o.min_area_pixels)
            if big.any():
                # NMS after every batch keeps memory at (distinct masks) x H x W
                kept_masks = np.concatenate([kept_masks, masks[big]])
                kept_scores = np.concatenate([kept_scores, iou[good][big]])
                keep = box_nms(kept_masks, kept_scores, o.nms_iou)
                kept_masks, kept_scores = kept_masks[keep], kept_scores[keep]
        return paint_masks(kept_masks)
