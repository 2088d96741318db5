"""Image preprocessing for ONNX reconstructors, with the exact pixel mapping model grid <-> image.

Pixel convention (OpenCV, the one every sparseart module uses): pixel (row i, column j) has its
centre at the integer coordinate (u, v) = (j, i). ``cv2.resize`` aligns pixel *areas*, so an axis
resized from n to n' pixels maps image coordinate u to ``(u + 0.5) * n'/n - 0.5``. Padding adds,
cropping subtracts an integer offset. Every preprocessed frame therefore carries a
:class:`PixelMap` with, per axis, ``grid = scale * (image + 0.5) - 0.5 + offset``, which is exact
for the resize, pad and crop done here. Model outputs are brought back to the original pixel grid
with :meth:`PixelMap.sample_nearest` (nearest model pixel of each image pixel centre) and
intrinsics with :meth:`PixelMap.K_to_image`.

Resize rules (``resize`` of the contract):

* ``pad``: isotropic scale so the image fits the grid (its long side = ``long_side`` for models
  with a free size), then centred padding with ``pad_value`` up to the fixed grid or to the next
  multiple of ``multiple_of`` (VGGT's "pad" mode, without its anisotropic rounding of the short
  side; the image is never distorted, so K keeps square pixels).
* ``crop``: isotropic scale so the image covers the grid (free size: long side = ``long_side``),
  then a centred crop to the fixed grid or down to a multiple of ``multiple_of``. Cropped-away
  pixels have no model output (invalid).
* ``stretch``: anisotropic scale to the grid (free size: each side rounded to a multiple).

When the scale is exactly 1 the image is not resampled at all.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

INTERPOLATIONS = ("nearest", "linear", "cubic", "area")
RESIZE_RULES = ("pad", "crop", "stretch")


@dataclass(frozen=True)
class PixelMap:
    """Affine map between an original image (W x H) and the model grid (grid_width x grid_height).

    Per axis: ``grid = scale * (image + 0.5) - 0.5 + offset`` in pixel-centre coordinates
    (u = column, v = row). offset > 0 is padding before the image, < 0 a crop.
    """

    width: int
    height: int
    grid_width: int
    grid_height: int
    scale_x: float
    scale_y: float
    offset_x: float
    offset_y: float

    def to_grid(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image pixel coordinates -> grid coordinates (float64, any shape)."""
        return (self.scale_x * (np.asarray(u, np.float64) + 0.5) - 0.5 + self.offset_x,
                self.scale_y * (np.asarray(v, np.float64) + 0.5) - 0.5 + self.offset_y)

    def to_image(self, u_grid: np.ndarray, v_grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Grid coordinates -> image pixel coordinates (float64, any shape)."""
        return ((np.asarray(u_grid, np.float64) - self.offset_x + 0.5) / self.scale_x - 0.5,
                (np.asarray(v_grid, np.float64) - self.offset_y + 0.5) / self.scale_y - 0.5)

    def K_to_image(self, K_grid: np.ndarray) -> np.ndarray:
        """(3, 3) intrinsics in grid pixels -> (3, 3) float64 intrinsics of the original image."""
        K_grid = np.asarray(K_grid, np.float64)
        K = np.eye(3)
        K[0, 0], K[0, 1], K[1, 1] = (K_grid[0, 0] / self.scale_x, K_grid[0, 1] / self.scale_x,
                                     K_grid[1, 1] / self.scale_y)
        K[0, 2], K[1, 2] = self.to_image(K_grid[0, 2], K_grid[1, 2])
        return K

    def K_to_grid(self, K: np.ndarray) -> np.ndarray:
        """(3, 3) intrinsics of the original image -> (3, 3) float64 intrinsics in grid pixels."""
        K = np.asarray(K, np.float64)
        K_grid = np.eye(3)
        K_grid[0, 0], K_grid[0, 1], K_grid[1, 1] = K[0, 0] * self.scale_x, K[0, 1] * self.scale_x, K[1, 1] * self.scale_y
        K_grid[0, 2], K_grid[1, 2] = self.to_grid(K[0, 2], K[1, 2])
        return K_grid

    def nearest_grid_index(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For every image pixel (row-major, H*W): (grid row, grid column, inside) of the grid
        pixel whose centre is nearest to the image pixel's centre; ``inside`` is False where that
        lies outside the grid (cropped away). O(H W)."""
        rows, cols = np.mgrid[0:self.height, 0:self.width]
        u_grid, v_grid = self.to_grid(cols.reshape(-1), rows.reshape(-1))
        col_grid = np.floor(u_grid + 0.5).astype(np.int64)
        row_grid = np.floor(v_grid + 0.5).astype(np.int64)
        inside = (col_grid >= 0) & (col_grid < self.grid_width) & (row_grid >= 0) & (row_grid < self.grid_height)
        return np.clip(row_grid, 0, self.grid_height - 1), np.clip(col_grid, 0, self.grid_width - 1), inside

    def sample_nearest(self, grid_values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Resample a (grid_height, grid_width, ...) array onto the image grid.

        Returns ((H*W, ...) values in row-major image order, (H*W,) bool inside). Nearest
        neighbour, so depth edges stay sharp (no interpolated "flying" depths). O(H W).
        """
        if grid_values.shape[:2] != (self.grid_height, self.grid_width):
            raise ValueError(f"model output grid {grid_values.shape[:2]} does not match the input grid "
                             f"{(self.grid_height, self.grid_width)}")
        row, col, inside = self.nearest_grid_index()
        return grid_values[row, col], inside


@dataclass(frozen=True)
class SizeRule:
    """How an image is brought to the model grid (see the module docstring).

    height, width: fixed grid in pixels, or None for a free size (then ``long_side`` and
    ``multiple_of`` decide; long_side None keeps the original scale).
    """

    height: int | None = None
    width: int | None = None
    long_side: int | None = 518
    multiple_of: int = 14
    resize: str = "pad"
    interpolation: str = "cubic"


def _round_multiple(value: int, multiple: int, how: str) -> int:
    """``value`` rounded up / down / to the nearest multiple of ``multiple`` (at least one multiple)."""
    steps = {"up": math.ceil, "down": math.floor, "nearest": round}[how](value / multiple)
    return max(multiple, int(steps) * multiple)


def plan_mapping(width: int, height: int, rule: SizeRule,
                 grid: tuple[int, int] | None = None) -> PixelMap:
    """The :class:`PixelMap` of one image under ``rule``.

    Args:
        width, height: original image size in pixels.
        rule: the contract's size rule.
        grid: (grid_width, grid_height) to use instead of the rule's (e.g. the grid chosen for the
            first frame of a batch, so all frames share one tensor shape).
    """
    if width < 1 or height < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if grid is None and rule.width is not None and rule.height is not None:
        grid = (int(rule.width), int(rule.height))
    if grid is not None:
        grid_w, grid_h = grid
        if rule.resize == "stretch":
            new_w, new_h = grid_w, grid_h
        else:
            fit = min if rule.resize == "pad" else max
            scale = fit(grid_w / width, grid_h / height)
            new_w, new_h = max(1, round(width * scale)), max(1, round(height * scale))
            if rule.resize == "pad":
                new_w, new_h = min(new_w, grid_w), min(new_h, grid_h)
            else:
                new_w, new_h = max(new_w, grid_w), max(new_h, grid_h)
    else:
        scale = 1.0 if rule.long_side is None else rule.long_side / max(width, height)
        new_w, new_h = max(1, round(width * scale)), max(1, round(height * scale))
        m = rule.multiple_of
        if rule.resize == "pad":
            grid_w, grid_h = _round_multiple(new_w, m, "up"), _round_multiple(new_h, m, "up")
        elif rule.resize == "crop":
            grid_w, grid_h = _round_multiple(new_w, m, "down"), _round_multiple(new_h, m, "down")
            new_w, new_h = max(new_w, grid_w), max(new_h, grid_h)
        else:
            grid_w, grid_h = _round_multiple(new_w, m, "nearest"), _round_multiple(new_h, m, "nearest")
            new_w, new_h = grid_w, grid_h
    # centred: padding (grid - new) // 2 before the image, crops (new - grid) // 2 removed before it
    offset_x = (grid_w - new_w) // 2 if grid_w >= new_w else -((new_w - grid_w) // 2)
    offset_y = (grid_h - new_h) // 2 if grid_h >= new_h else -((new_h - grid_h) // 2)
    return PixelMap(width=width, height=height, grid_width=int(grid_w), grid_height=int(grid_h),
                    scale_x=new_w / width, scale_y=new_h / height, offset_x=float(offset_x),
                    offset_y=float(offset_y))


def _cv2_interpolation(name: str) -> int:
    import cv2

    return {"nearest": cv2.INTER_NEAREST, "linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC,
            "area": cv2.INTER_AREA}[name]


def warp_to_grid(image: np.ndarray, mapping: PixelMap, interpolation: str,
                 pad_value: tuple[float, float, float]) -> np.ndarray:
    """Resize, pad and crop one (H, W, 3) float32 image onto the (grid_h, grid_w, 3) model grid.

    Pixels outside the image get ``pad_value``. O(grid pixels).
    """
    import cv2

    new_w = round(mapping.width * mapping.scale_x)
    new_h = round(mapping.height * mapping.scale_y)
    if (new_w, new_h) != (mapping.width, mapping.height):
        image = cv2.resize(image, (new_w, new_h), interpolation=_cv2_interpolation(interpolation))
    canvas = np.empty((mapping.grid_height, mapping.grid_width, 3), np.float32)
    canvas[:] = np.asarray(pad_value, np.float32)
    ox, oy = int(mapping.offset_x), int(mapping.offset_y)
    src_x0, src_y0 = max(0, -ox), max(0, -oy)
    dst_x0, dst_y0 = max(0, ox), max(0, oy)
    w = min(new_w - src_x0, mapping.grid_width - dst_x0)
    h = min(new_h - src_y0, mapping.grid_height - dst_y0)
    canvas[dst_y0:dst_y0 + h, dst_x0:dst_x0 + w] = image[src_y0:src_y0 + h, src_x0:src_x0 + w]
    return canvas


def prepare_frames(images: list[np.ndarray], rule: SizeRule, value_range: tuple[float, float],
                   mean: tuple[float, float, float], std: tuple[float, float, float],
                   pad_value: tuple[float, float, float]) -> tuple[np.ndarray, list[PixelMap]]:
    """Bring 8-bit RGB images onto one model grid.

    Args:
        images: list of (H_i, W_i, 3) uint8 RGB (sizes may differ; all frames share the grid of
            the first one).
        rule: size rule; value_range: (lo, hi) the 0-255 range is mapped to; mean, std: per-channel
            normalisation the host applies after that (identity when the model normalises inside);
            pad_value: in ``value_range`` units, before normalisation.

    Returns:
        ((S, 3, grid_h, grid_w) float32 normalised tensor, one :class:`PixelMap` per image).
        O(S grid pixels).
    """
    if not images:
        raise ValueError("no images to preprocess")
    lo, hi = value_range
    first = plan_mapping(images[0].shape[1], images[0].shape[0], rule)
    maps, planes = [], []
    for image in images:
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"expected (H, W, 3) uint8 RGB images, got {image.dtype} {image.shape}")
        mapping = (first if not maps else
                   plan_mapping(image.shape[1], image.shape[0], rule, (first.grid_width, first.grid_height)))
        scaled = image.astype(np.float32) * np.float32((hi - lo) / 255.0) + np.float32(lo)
        warped = warp_to_grid(scaled, mapping, rule.interpolation, pad_value)
        warped = np.clip(warped, min(lo, hi), max(lo, hi))  # cubic resampling overshoots
        warped = (warped - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
        planes.append(np.transpose(warped, (2, 0, 1)))
        maps.append(mapping)
    return np.ascontiguousarray(np.stack(planes).astype(np.float32)), maps
