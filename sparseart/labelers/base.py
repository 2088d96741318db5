"""The part-labeler protocol every labeler (rule-based, VLM, mock) implements."""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from ..types import LabelledCloud, PartLabels, PartSpec, Scene


class TooLittleToLabel(ValueError):
    """A state holds too few usable points to label parts (``state``: "start" | "end"); the
    pipeline reports it as bad input naming that state's depth images."""

    def __init__(self, message: str, state: str) -> None:
        super().__init__(message)
        self.state = state


@runtime_checkable
class PartLabeler(Protocol):
    """Decides the parts of an object from its labelled clouds in the two states.

    ``label`` receives both states' clouds in one frame when the scene is posed (in each state's
    own reference frame otherwise, with ``aligned=False``) and, optionally, the scene (images,
    masks). It returns :class:`PartLabels`: the parts (part 0 = static base), the part of every
    point of each state (-1 = unassigned), the segment -> part maps it decided, optionally a joint
    type per movable part (``PartSpec.joint_type``; the fitter then skips classification) and
    optionally a start->end rigid transform per movable part as evidence. ``motion_hints`` are
    (4, 4) start->end rigid motions (scene frame) that alignment found among the matches the
    static part did not explain: candidate part motions a labeler may try (or ignore). ``posed``
    says the two clouds are in a known common frame (cameras given, or a trusted feature alignment
    of the states; None = the scene's cameras decide): a part that moved may then be kept even
    when no static segment is seen in both states.
    """

    name: str

    def label(self, start: LabelledCloud, end: LabelledCloud, scene: Scene | None = None,
              aligned: bool = True, motion_hints: list[np.ndarray] | None = None,
              posed: bool | None = None) -> PartLabels:
        ...


def labels_from_segment_maps(parts: list[PartSpec], start: LabelledCloud, end: LabelledCloud,
                             start_segment_to_part: dict[int, int],
                             end_segment_to_part: dict[int, int]) -> PartLabels:
    """Build per-point part arrays from segment -> part maps (unmapped segments get -1). O(N)."""

    def per_point(cloud: LabelledCloud, mapping: dict[int, int]) -> np.ndarray:
        result = np.full(len(cloud), -1, dtype=np.int64)
        if mapping:
            keys = np.fromiter(mapping.keys(), dtype=np.int64)
            values = np.fromiter(mapping.values(), dtype=np.int64)
            order = np.argsort(keys)
            keys, values = keys[order], values[order]
            slot = np.clip(np.searchsorted(keys, cloud.segment), 0, len(keys) - 1)
            hit = keys[slot] == cloud.segment
            result[hit] = values[slot[hit]]
        return result

    return PartLabels(parts=parts, start_part=per_point(start, start_segment_to_part),
                      end_part=per_point(end, end_segment_to_part),
                      start_segment_to_part=dict(start_segment_to_part),
                      end_segment_to_part=dict(end_segment_to_part))
