"""Segmenters: one frame -> (H, W) int64 label image, 0 = background, ids local to the image.

    segmenter = make_segmenter("builtin")        # or "given", or "sam:ENCODER.onnx,DECODER.onnx"
    segment_scene(scene, segmenter)               # sets frame.mask of every frame

Label transfer (sparseart.lift.labels) then works unchanged. Heavy modules (cv2, onnxruntime) are
imported when a segmenter runs or loads.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..types import Scene
from .base import MAX_LABEL, Segmenter, relabel_consecutive, segmentation_quality

__all__ = ["Segmenter", "make_segmenter", "segment_scene", "segmentation_quality", "SEGMENTER_SPECS"]

SEGMENTER_SPECS = ("given", "builtin", "sam:ENCODER.onnx,DECODER.onnx")


def make_segmenter(spec: str, **options: Any) -> Segmenter:
    """A segmenter from a spec string.

    spec:
        "given"   the scene's own mask images (start/mask, end/mask);
        "builtin" the rule-based segmenter (no model; sparseart.segment.rules);
        "sam:ENCODER.onnx,DECODER.onnx" a SAM/MobileSAM ONNX pair (sparseart.segment.onnx_sam).
    options: fields of RuleOptions ("builtin") or SamOptions ("sam:..."), e.g. points_per_side=16.

    Raises ValueError with one line naming the spec/option/file that is wrong.
    """
    if not isinstance(spec, str):
        raise ValueError(f"segmenter spec must be a string, got {type(spec).__name__}")
    kind, _, argument = spec.strip().partition(":")
    kind = kind.lower()
    if kind == "given":
        if options or argument:
            raise ValueError(f"segmenter 'given' takes no arguments or options, got {spec!r} {options or ''}")
        from .given import GivenMasks

        return GivenMasks()
    if kind == "builtin":
        from dataclasses import fields

        from .rules import RuleOptions, RuleSegmenter

        if argument:
            raise ValueError(f"segmenter 'builtin' takes no ':' argument, got {spec!r}")
        _check_options(options, {f.name for f in fields(RuleOptions)}, "builtin")
        return RuleSegmenter(RuleOptions(**options))
    if kind == "sam":
        from dataclasses import fields

        from .onnx_sam import SamOptions, SamSegmenter

        paths = [p.strip() for p in argument.split(",")]
        if len(paths) != 2 or not all(paths):
            raise ValueError(f"segmenter spec {spec!r}: expected 'sam:ENCODER.onnx,DECODER.onnx'")
        _check_options(options, {f.name for f in fields(SamOptions)}, "sam")
        return SamSegmenter(paths[0], paths[1], SamOptions(**options))
    raise ValueError(f"unknown segmenter spec {spec!r}; use one of {', '.join(SEGMENTER_SPECS)}")


def _check_options(options: dict, known: set[str], kind: str) -> None:
    unknown = sorted(set(options) - known)
    if unknown:
        raise ValueError(f"segmenter '{kind}': unknown option(s) {unknown}; known: {sorted(known)}")


def segment_scene(scene: Scene, segmenter: Segmenter) -> None:
    """Set ``frame.mask`` of every frame of both states to ``segmenter.segment(frame)``.

    All frames are segmented before any mask is replaced, so an error leaves the scene unchanged.
    Each result must be an (H, W) non-negative integer image; ids are renumbered 1..S. A frame with
    no segment at all adds a warning to ``scene.warnings`` (its points get no segment). With the
    "given" segmenter the masks read from the scene are kept as they are.
    """
    if getattr(segmenter, "name", None) == "given":
        for frame in scene.all_frames:
            segmenter.segment(frame)  # raises when a frame has no mask
        return
    results = []
    for frame in scene.all_frames:
        labels = np.asarray(segmenter.segment(frame))
        if labels.shape != frame.shape:
            raise ValueError(f"{frame.rgb_path}: segmenter '{segmenter.name}' returned shape {labels.shape}, "
                             f"expected {frame.shape}")
        if labels.dtype.kind not in "iu":
            raise ValueError(f"{frame.rgb_path}: segmenter '{segmenter.name}' returned {labels.dtype} labels, "
                             f"expected integers")
        if labels.size and labels.min() < 0:
            raise ValueError(f"{frame.rgb_path}: segmenter '{segmenter.name}' returned negative labels")
        labels = relabel_consecutive(labels)
        if labels.max(initial=0) > MAX_LABEL:
            raise ValueError(f"{frame.rgb_path}: more than {MAX_LABEL} segments")
        results.append(labels)
    for frame, labels in zip(scene.all_frames, results):
        frame.mask = labels
        if not labels.any():
            scene.warnings.append(f"{frame.rgb_path}: segmenter '{segmenter.name}' found no segment")
