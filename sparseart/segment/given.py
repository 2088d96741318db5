"""User-given masks: the ``start/mask/*.png`` / ``end/mask/*.png`` images that scene.py reads into
``Frame.mask`` ((H, W) int64, 0 = background, ids local to each image)."""
from __future__ import annotations

import numpy as np

from ..types import Frame, SceneError


def given_mask(frame: Frame) -> np.ndarray:
    """The frame's own mask, (H, W) int64, 0 = background. SceneError when the scene has none."""
    if frame.mask is None:
        raise SceneError(f"{frame.rgb_path}: segmenter 'given' needs a mask image "
                         f"({frame.state}/mask/{frame.rgb_path.stem}.png); use 'builtin' or 'sam:...' instead")
    return np.asarray(frame.mask, dtype=np.int64)


class GivenMasks:
    """Segmenter that returns the masks read with the scene (``segment_scene`` leaves them as they are)."""

    name = "given"

    def segment(self, frame: Frame) -> np.ndarray:
        return given_mask(frame)
