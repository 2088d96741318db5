"""A labeler that returns what it is told: the sanctioned test double."""
from __future__ import annotations

import numpy as np

from ..types import LabelledCloud, PartLabels, PartSpec, Scene
from .base import labels_from_segment_maps


class MockLabeler:
    """Maps mask ids to parts as configured.

    Args:
        mask_to_part: mask id (as written in the mask images) -> part id; applied in every image
            of both states. Part 0 is static, every other listed part is movable.
        joint_types: optional part id -> "revolute" | "prismatic" given to the fitter.
        per_image: optional {(state, frame_index): {mask id: part id}} overriding ``mask_to_part``
            for images whose ids disagree.
    """

    name = "mock"

    def __init__(self, mask_to_part: dict[int, int], joint_types: dict[int, str] | None = None,
                 per_image: dict[tuple[str, int], dict[int, int]] | None = None) -> None:
        self.mask_to_part = dict(mask_to_part)
        self.joint_types = dict(joint_types or {})
        self.per_image = dict(per_image or {})

    def _segment_map(self, cloud: LabelledCloud) -> dict[int, int]:
        mapping = {}
        for segment, (frame_index, mask_id) in cloud.segment_source.items():
            table = self.per_image.get((cloud.state, frame_index), self.mask_to_part)
            if mask_id in table:
                mapping[segment] = table[mask_id]
        return mapping

    def label(self, start: LabelledCloud, end: LabelledCloud, scene: Scene | None = None,
              aligned: bool = True, motion_hints: list[np.ndarray] | None = None,
              posed: bool | None = None) -> PartLabels:
        part_ids = sorted(set(self.mask_to_part.values()) |
                          {p for table in self.per_image.values() for p in table.values()})
        parts = [PartSpec(id=p, role="static" if p == 0 else "movable",
                          joint_type=self.joint_types.get(p), parent=None if p == 0 else 0)
                 for p in part_ids]
        return labels_from_segment_maps(parts, start, end, self._segment_map(start), self._segment_map(end))
