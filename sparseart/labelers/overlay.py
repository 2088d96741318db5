"""Numbered mask overlays for a VLM, drawn with OpenCV and encoded as PNG data URLs.

Every region of a label image is tinted (by default with well-separated hues by the region's rank
in the image; with ``color_by="id"`` with a colour that depends only on the id, so part 2 has the
same colour in every image), outlined, and marked with its id at the pixel deepest inside
it (maximum of the distance transform), in white on a dark outline so it reads on any background.
"""
from __future__ import annotations

import base64

import cv2
import numpy as np

GOLDEN_RATIO = 0.618033988749895


def id_color(region_id: int) -> tuple[int, int, int]:
    """A saturated RGB colour (uint8 triple) determined by ``region_id`` alone; consecutive ids get
    well-separated hues (golden-ratio steps)."""
    hue = int(180 * ((region_id * GOLDEN_RATIO) % 1.0))
    hsv = np.array([[[hue, 220, 255]]], dtype=np.uint8)
    r, g, b = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0]
    return int(r), int(g), int(b)


def numbered_overlay(rgb: np.ndarray, labels: np.ndarray, ids: list[int] | None = None,
                     alpha: float = 0.45, min_side: int = 384, color_by: str = "rank") -> np.ndarray:
    """Draw the regions of ``labels`` on ``rgb`` with their ids written inside.

    Args:
        rgb: (H, W, 3) uint8 RGB image.
        labels: (H, W) integer label image; 0 is never drawn.
        ids: the ids to draw (default: every non-zero id present); ids absent from ``labels``
            are skipped.
        alpha: tint opacity in [0, 1].
        min_side: images whose shorter side is smaller are upscaled by an integer factor first
            (nearest neighbour for labels) so the numbers stay legible.
        color_by: "rank" (k-th drawn id gets ``id_color(k)``: distinct hues for arbitrary ids) or
            "id" (``id_color(id)``: the same id has the same colour in every image).

    Returns:
        (H*s, W*s, 3) uint8 RGB, s >= 1 the upscale factor. O(H W * number of ids).

    Raises:
        ValueError: shapes or dtypes that do not fit.
    """
    rgb = np.asarray(rgb)
    labels = np.asarray(labels)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"overlay: rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if labels.shape != rgb.shape[:2] or not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"overlay: labels must be an integer (H, W) = {rgb.shape[:2]} image, got "
                         f"{labels.shape} {labels.dtype}")
    if color_by not in ("rank", "id"):
        raise ValueError(f"overlay: color_by must be 'rank' or 'id', got {color_by!r}")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"overlay: alpha must be in [0, 1], got {alpha}")
    scale = max(1, int(np.ceil(min_side / max(1, min(rgb.shape[:2])))))
    if scale > 1:
        size = (rgb.shape[1] * scale, rgb.shape[0] * scale)
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_LINEAR)
        labels = cv2.resize(labels.astype(np.int32), size, interpolation=cv2.INTER_NEAREST)
    present = set(np.unique(labels).tolist()) - {0}
    drawn = sorted(present if ids is None else present & {int(i) for i in ids})
    canvas = rgb.astype(np.float64)
    regions, colors = {}, {}
    for rank, region_id in enumerate(drawn):
        region = labels == region_id
        regions[region_id] = region
        colors[region_id] = id_color(region_id if color_by == "id" else rank)
        canvas[region] = (1.0 - alpha) * canvas[region] + alpha * np.array(colors[region_id], np.float64)
    out = np.clip(np.round(canvas), 0, 255).astype(np.uint8)
    font_scale = max(0.4, min(out.shape[:2]) / 600.0)
    thickness = max(1, int(round(font_scale * 2)))
    for region_id, region in regions.items():
        region_u8 = region.astype(np.uint8)
        contours, _ = cv2.findContours(region_u8, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(out, contours, -1, colors[region_id], thickness)
        depth = cv2.distanceTransform(np.pad(region_u8, 1), cv2.DIST_L2, 3)[1:-1, 1:-1]
        row, col = np.unravel_index(int(np.argmax(depth)), depth.shape)
        text = str(region_id)
        (width, height), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, font_scale, thickness)
        x = int(np.clip(col - width // 2, 0, max(0, out.shape[1] - width)))
        y = int(np.clip(row + height // 2, height, out.shape[0] - 1))
        cv2.putText(out, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, font_scale, (0, 0, 0), thickness + 2,
                    cv2.LINE_AA)
        cv2.putText(out, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, font_scale, (255, 255, 255), thickness,
                    cv2.LINE_AA)
    return out


def png_data_url(rgb: np.ndarray) -> str:
    """``data:image/png;base64,...`` of a (H, W, 3) uint8 RGB image (lossless). O(H W)."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"png_data_url: expected (H, W, 3) uint8 RGB, got {rgb.shape} {rgb.dtype}")
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(rgb[:, :, ::-1]))
    if not ok:
        raise ValueError("png_data_url: OpenCV could not encode the image as PNG")
    return "data:image/png;base64," + base64.b64encode(encoded.tobytes()).decode("ascii")
