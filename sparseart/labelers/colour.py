"""Colour without brightness: what a surface keeps when it turns under fixed lights.

Shading scales a surface's RGB by how it faces the lights; a part that turns (or a symmetric cap
turning onto itself) changes its shading point by point, while its hue stays. Comparisons of a
part's appearance across the states therefore use chromaticity, not RGB.
"""
from __future__ import annotations

import numpy as np


def rg_chromaticity(colors: np.ndarray) -> np.ndarray:
    """(N, 2) rg chromaticity r / (r + g + b), g / (r + g + b) in [0, 1] of (N, 3) RGB in [0, 1]."""
    rgb = np.clip(np.asarray(colors, dtype=np.float64), 0.0, 1.0)
    return rgb[:, :2] / np.maximum(rgb.sum(axis=1, keepdims=True), 1e-6)


def chroma(colors: np.ndarray) -> np.ndarray:
    """(N, 4) colour without brightness of (N, 3) RGB colours in [0, 1]: CIELAB a*, b* (in
    [-128, 127]) and :func:`rg_chromaticity` (in [0, 1])."""
    import cv2

    rgb = np.clip(np.asarray(colors, dtype=np.float64), 0.0, 1.0)
    ab = cv2.cvtColor(np.ascontiguousarray(rgb, dtype=np.float32)[None], cv2.COLOR_RGB2LAB)[0, :, 1:]
    return np.concatenate([ab.astype(np.float64), rg_chromaticity(rgb)], axis=1)
