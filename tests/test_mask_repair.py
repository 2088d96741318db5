"""Merged and split masks put right by the state's other views (sparseart.labelers.mask_repair)."""
from __future__ import annotations

import numpy as np

from sparseart.labelers.mask_repair import repair_merged_masks, split_mask_ids
from sparseart.types import LabelledCloud


def _state(ids_per_frame: list[np.ndarray], points: np.ndarray, scale: float = 1.0) -> LabelledCloud:
    """One state whose frames all see ``points`` ((P, 3), two touching plates) with mask ids
    ``ids_per_frame[f]`` ((P,) per frame); each frame's ids become segments of their own."""
    rng = np.random.default_rng(0)
    clouds, segments, frames, source = [], [], [], {}
    for frame, ids in enumerate(ids_per_frame):
        clouds.append(points + rng.normal(0, 0.002, points.shape))   # each view a little off
        seg = np.full(len(ids), -1, dtype=np.int64)
        for mask_id in np.unique(ids):
            segment = len(source)
            source[segment] = (frame, int(mask_id))
            seg[ids == mask_id] = segment
        segments.append(seg)
        frames.append(np.full(len(ids), frame, dtype=np.int64))
    count = sum(len(c) for c in clouds)
    return LabelledCloud(state="start", points=np.concatenate(clouds) * scale, colors=np.zeros((count, 3)),
                         segment=np.concatenate(segments), frame_index=np.concatenate(frames),
                         pixel_index=np.arange(count), confidence=np.ones(count), segment_source=source)


def _plates(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A base (id 1, x < 0) and an arm (id 2, x >= 0): 2000 points on the unit square."""
    points = np.column_stack([rng.uniform(-0.5, 0.5, 2000), rng.uniform(-0.5, 0.5, 2000), np.zeros(2000)])
    return points, np.where(points[:, 0] < 0, 1, 2)


def test_a_merged_mask_hands_the_other_part_back_and_a_split_piece_rejoins():
    rng = np.random.default_rng(1)
    points, truth = _plates(rng)
    merged = np.ones_like(truth)                                  # frame 2: arm merged into the base
    split = np.where((truth == 2) & (points[:, 1] > 0.2), 3, truth)   # frame 1: a strip of the arm as id 3
    cloud = _state([truth, split, merged, truth], points)
    repaired, notes = repair_merged_masks(cloud, frozenset({1, 2, 3}), np.random.default_rng(0))
    ids = repaired.mask_ids()
    frame = repaired.frame_index
    assert len(notes) == 2
    # the merged frame's arm points are id 2 again, its base points stay id 1
    assert np.mean(ids[frame == 2] == truth) > 0.97
    # the split strip rejoins the arm
    assert np.mean(ids[frame == 1] == truth) > 0.97
    # the good frames are not touched: one faulty frame cannot outvote the rest
    assert np.array_equal(ids[frame == 0], truth) and np.array_equal(ids[frame == 3], truth)
    # same point order, nothing else changed
    assert np.array_equal(repaired.points, cloud.points)


def test_frayed_borders_and_two_views_are_left_alone_and_the_repair_is_unit_free():
    rng = np.random.default_rng(2)
    points, truth = _plates(rng)
    frayed = np.where(np.abs(points[:, 0]) < 0.01, 3 - truth, truth)   # a 1 % strip along the border
    cloud = _state([truth, frayed, truth], points)
    assert repair_merged_masks(cloud, frozenset({1, 2}), np.random.default_rng(0)) == (cloud, [])
    two_views = _state([truth, np.ones_like(truth)], points)         # who is right? nobody can say
    assert repair_merged_masks(two_views, frozenset({1, 2}), np.random.default_rng(0)) == (two_views, [])
    merged = _state([truth, truth, np.ones_like(truth)], points, scale=1000.0)   # millimetres
    repaired, notes = repair_merged_masks(merged, frozenset({1, 2}), np.random.default_rng(0))
    assert len(notes) == 1 and np.mean(repaired.mask_ids()[repaired.frame_index == 2] == truth) > 0.97
    # ids that name nothing across images (a per-image segmenter): no repair
    assert repair_merged_masks(merged, frozenset(), np.random.default_rng(0)) == (merged, [])


def test_a_split_id_is_told_from_an_id_that_swallowed_another_part():
    rng = np.random.default_rng(3)
    points, truth = _plates(rng)
    # frame 1 cuts a strip off the arm under a new id 3, seen in that image only
    split = np.where((truth == 2) & (points[:, 1] > 0.2), 3, truth)
    cloud = _state([truth, split, truth, truth], points)
    repaired, _ = repair_merged_masks(cloud, frozenset({1, 2, 3}), np.random.default_rng(0))
    assert split_mask_ids(cloud, repaired) == frozenset({3})
    # a small part's id (2, a narrow strip) swallows the base in frame 2: most of its points there
    # are handed over, but every image uses the id, so it keeps naming its part
    small = np.where(points[:, 0] > 0.4, 2, 1)
    swallowed = np.full_like(small, 2)
    cloud = _state([small, small, swallowed, small], points)
    repaired, notes = repair_merged_masks(cloud, frozenset({1, 2}), np.random.default_rng(0))
    assert notes and np.count_nonzero(repaired.mask_ids() != cloud.mask_ids()) > 0.5 * np.count_nonzero(
        cloud.mask_ids() == 2)
    assert split_mask_ids(cloud, repaired) == frozenset()
    assert split_mask_ids(cloud, cloud) == frozenset()   # nothing handed over, nothing split
