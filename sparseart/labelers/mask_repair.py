"""Merged and split masks repaired by the state's other views.

A segmenter now and then gives two touching parts one id in one image (a stapler's arm and its
base) or cuts one part into two ids (a door and a strip of it). When the ids name parts across
images (:func:`~.correspondence.named_mask_ids`), the state's other views say which part a point
is: the nearest point of another frame carries its own id. A frame segment a good share of whose
covered points the other views give to one other named id (at least two other views, and more than
half of those that cover the point, give it that id) hands those points over: they become a
segment of that id in the same frame (a merge undone; a split piece re-joined). Frayed borders
hand over too few points to pass the share and are left alone.

Measured on the realistic renders (merge and split probability 0.1 per image): a stapler whose
start view merged the arm into the base put 2958 arm points into the static part, the states'
alignment then turned by 87 deg and the arm's axis came out 65 deg off; a door whose third view in
both states split a strip off under an id of its own fitted that strip as a second part.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from sparseart.geometry.clouds import median_spacing
from ..types import LabelledCloud

CLAIM_SHARE = 0.25           # of a segment's covered points, the share another id must claim
MIN_CLAIMED_POINTS = 30      # ... and at least this many points
MIN_CLAIMED_SHARE = 0.01     # ... and this share of the state's named points (a frayed border is less)
CLAIM_RADIUS_SPACINGS = 6.0  # another frame's point this near covers a point (views warp by ~1-2 %)
NO_CLAIM = -1                # fewer than two other frames agree on the point's id
SPLIT_VOTE = -2              # no id has a majority of the frames covering it


def repair_merged_masks(cloud: LabelledCloud, named_ids: frozenset[int],
                        rng: np.random.Generator) -> tuple[LabelledCloud, list[str]]:
    """The cloud with the points another named id claims moved into new segments of that id.

    cloud: one state, all frames in one frame of reference. named_ids: mask ids that name parts
    across images; only their points vote and only they are handed over (a per-image segmenter's
    ids name nothing across images: no repair). Returns the cloud (a copy when anything changed;
    same point order) and one line per repaired segment. O(N log N) for the per-frame KD-trees.
    """
    if len(named_ids) < 2 or len(cloud) == 0:
        return cloud, []
    mask_id = cloud.mask_ids()
    named = np.isin(mask_id, list(named_ids))
    frames = np.unique(cloud.frame_index[named])
    if len(frames) < 2:
        return cloud, []
    radius = CLAIM_RADIUS_SPACINGS * median_spacing(cloud.points[named], sample=4000, rng=rng)
    claimed = _claims(cloud, mask_id, named, frames, radius)
    floor = max(MIN_CLAIMED_POINTS, MIN_CLAIMED_SHARE * int(named.sum()))
    segment = cloud.segment.copy()
    source = dict(cloud.segment_source)
    next_segment = int(segment.max()) + 1
    notes = []
    for seg in np.unique(segment[named]).tolist():
        members = np.flatnonzero(segment == seg)
        own = source[seg][1]
        votes = claimed[members]
        covered = votes != NO_CLAIM
        if covered.sum() < MIN_CLAIMED_POINTS:
            continue
        ids, counts = np.unique(votes[(votes >= 0) & (votes != own)], return_counts=True)
        for other, count in zip(ids.tolist(), counts.tolist()):
            if count < floor or count < CLAIM_SHARE * covered.sum():
                continue
            segment[members[votes == other]] = next_segment
            source[next_segment] = (source[seg][0], other)
            notes.append(f"{cloud.state} image {source[seg][0]}: {count} points of mask id {own} are id "
                         f"{other} in the other images (merged or split mask); handed over")
            next_segment += 1
    if not notes:
        return cloud, []
    return replace(cloud, segment=segment, segment_source=source), notes


SPLIT_ID_SHARE = 0.5         # an id that lost more than this share of its points in a state to other ids is a split


def split_mask_ids(before: LabelledCloud, after: LabelledCloud) -> frozenset[int]:
    """The mask ids that :func:`repair_merged_masks` found to be split pieces of other parts: ids
    that occur in one image of this state only and more than ``SPLIT_ID_SHARE`` of whose points
    (``before``, same point order as ``after``) the repair handed over to other ids. Such an id
    names no part of its own, even when a split in the other state happens to reuse it (a
    segmenter numbering a new piece max id + 1): it must not keep its piece apart from the part it
    was cut from (:func:`~.correspondence.distinct_by_masks`). A merge hands over the swallowed
    part's points under an id the other images use too (measured on a realistic oven: a rack's id
    swallowed a door in one image, 1279 of its 1500 points there; the rack keeps its id), so it
    keeps its name. O(K N) for K mask ids (a handful)."""
    old, new = before.mask_ids(), after.mask_ids()
    found = []
    for mask_id in np.unique(old[old > 0]).tolist():
        members = old == mask_id
        if (len(np.unique(before.frame_index[members])) == 1
                and np.count_nonzero(new[members] != mask_id) > SPLIT_ID_SHARE * np.count_nonzero(members)):
            found.append(int(mask_id))
    return frozenset(found)


def _claims(cloud: LabelledCloud, mask_id: np.ndarray, named: np.ndarray, frames: np.ndarray,
            radius: float) -> np.ndarray:
    """(N,) int64: for each named point, the id that most of the other frames covering it give it,
    when at least two give it and they are more than half of those covering it (one frame with a
    merged or split mask then cannot outvote the rest); ``SPLIT_VOTE`` when no id has that
    majority, ``NO_CLAIM`` when fewer than two frames agree on any. O(F^2 N + F N log N) for F
    frames."""
    votes = np.full((len(frames), len(cloud)), -1, dtype=np.int64)
    for k, frame in enumerate(frames):     # frame k's vote on every named point of the other frames
        members = np.flatnonzero(named & (cloud.frame_index == frame))
        query = np.flatnonzero(named & (cloud.frame_index != frame))
        distance, index = cKDTree(cloud.points[members]).query(cloud.points[query], k=1, distance_upper_bound=radius)
        hit = distance < radius
        votes[k, query[hit]] = mask_id[members[index[hit]]]
    covering = (votes >= 0).sum(axis=0)
    agreeing = np.stack([np.where(row >= 0, (votes == row).sum(axis=0), 0) for row in votes])
    best = agreeing.argmax(axis=0)
    count = agreeing[best, np.arange(len(cloud))]
    claimed = np.where(2 * count > covering, votes[best, np.arange(len(cloud))], SPLIT_VOTE)
    claimed[count < 2] = NO_CLAIM
    return claimed
