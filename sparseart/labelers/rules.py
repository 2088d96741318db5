"""The default part labeler: rigid-motion consistency, no model needed.

Steps (both clouds in one frame):

0. Both states are voxel-downsampled to a resolution set by the scene's extent
   (``voxel_divisions`` voxels across it); every decision below is made on these work clouds and
   carried back to every point (per segment with masks, per voxel without).
1. Segments: mask segments when the scene has masks (a mask that merges two parts or splits one
   in one image is put right by the state's other images when the ids name parts across images:
   :mod:`.mask_repair`); otherwise one motion-based split (points of
   one state farther than a radius from the other state's cloud are "moving", clustered into
   connected pieces; the rest is static). With the other state's depth views, a far point whose
   place those views could not see (something nearer covers it) is unseen, not moved: it has no
   vote and only joins a part whose motion carries it onto moved points (:mod:`.motion_layers`).
2. Within a state, segments from different images that cover the same surface are merged (mask ids
   need not agree across images).
3. Across states, start and end groups are paired as one assignment problem
   (:mod:`.correspondence`): each plausible pair is registered coarse-to-fine and costed by
   appearance over what the other state's views could see (:mod:`sparseart.geometry.free_space`), displacement
   relative to the object, whether one joint anchored on the static body can make the motion, and
   mask-id agreement; the Hungarian algorithm pairs them, and a runner-up pairing within a small
   cost is reported as an ambiguity (warning, lower confidence, runner-up in the diagnostics).
   A pair whose best motion is the identity is static.
4. Without masks, one moved piece can hold several parts: the moved points are split into the
   rigid motions that explain both states together (:mod:`.motion_layers`).
5. Moving pairs whose motions agree are merged into one part. Each part gets its start->end motion
   as evidence and a joint-type prior read off the rotation angle. When the world frame is known
   (posed scenes) a part that moved is kept even if no static segment is seen in both states.
6. Whole-object consistency: every part's start points moved by its motion (the static part
   staying put) are checked against the end views; the share the end views contradict is
   reported per part.

``PartLabels.diagnostics`` (when the type has the field; set as an attribute otherwise) holds the
pairing cost, the runner-up and its cost, per-part confidence and consistency, and the voxel size.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from sparseart.geometry.clouds import median_spacing, normals_with_variation, radius_components
from sparseart.geometry.sampling import random_subset
from ..types import LabelledCloud, PartLabels, PartSpec, Scene
from .base import TooLittleToLabel
from ..geometry.free_space import CONSISTENT, HIDDEN, VIOLATION, StateViews, state_views
from .correspondence import (AMBIGUITY_MARGIN, Group, PairContext, apply, assign, distinct_by_masks,
                             mask_agreement, motion_size, named_mask_ids, pair_score, prefer_small_turns, score_pairs)
from .mask_repair import repair_merged_masks, split_mask_ids

STATIC_ANGLE_DEG = 1.0          # a matched pair moving less than this and ...
STATIC_SHIFT_RADII = 1.5        # ... less than this many inlier radii is static
REVOLUTE_PRIOR_DEG = 10.0       # rotation above this: revolute prior
PRISMATIC_PRIOR_DEG = 2.0       # rotation below this: prismatic prior (in between: no prior)
DISTINCT_MOTION_DEG = 5.0       # registered motions further apart than this are real alternatives
ADJACENT_RADII = 3.0           # groups closer than this many inlier radii touch (may be one part)
STILL_EXPLAINS_SHARE = 0.8  # identity score / best score above which a pair is taken as not moved
POSE_ERROR_DEG = 5.0            # posed, no static pair: a largest pair moving less is the base (pose error)
POSE_ERROR_DIAMETERS = 0.05
POLISH_POINTS = 1000            # points per state in a part's final registration (work clouds)
FULL_POLISH_POINTS = 2000       # points per state in the refinement on the full clouds
REFINE_SHARE_SLACK = 0.01       # ... and kept unless it fits the part worse by more than this share
FULL_POLISH_MIN_POINTS = 500    # parts with fewer points per state keep their work-cloud motion
UNSEEN = -2                     # motion split: far from the other state but hidden in its views (no vote)
VIOLATION_WARN_SHARE = 0.3      # a part whose predicted end points the end views contradict this much

_Group = Group  # the group type (kept under its old name for callers)


@dataclass
class RuleLabelerConfig:
    """Tuning of the rule-based labeler. Radii are multiples of the measured point spacing.

    voxel_divisions: the work clouds' voxel is the scene's extent (bounding-box diagonal of both
    states) over this; 0 = no downsampling. The voxel never goes below the clouds' own spacing.
    """

    inlier_radius_spacings: float = 3.0
    min_segment_points: int = 30
    min_segment_share: float = 0.002
    merge_overlap: float = 0.2
    match_min_score: float = 0.3
    same_motion_overlap: float = 0.6
    max_points_per_segment: int = 1500
    pair_registration_points: int = 500
    motion_radius_spacings: float = 4.0
    motion_piece_min_share: float = 0.01  # without masks, moved pieces smaller than this share are noise
    motion_floor_moved_share: float = 0.1  # ... and a motion's floor is at most this share of the moved points
    voxel_divisions: float = 250.0
    seed: int = 0


class RuleBasedLabeler:
    """Static vs movable by rigid-motion consistency; see the module docstring."""

    name = "rules"

    def __init__(self, config: RuleLabelerConfig | None = None) -> None:
        self.config = config or RuleLabelerConfig()

    # ------------------------------------------------------------------ public

    def label(self, start: LabelledCloud, end: LabelledCloud, scene: Scene | None = None,
              aligned: bool = True, motion_hints: list[np.ndarray] | None = None,
              posed: bool | None = None) -> PartLabels:
        """Label parts (:meth:`_label_pass`). Without masks, when the pass finds no part that
        moved, a second pass splits the points again with replaced surfaces counted as moved
        (:func:`_replaced_surfaces`) and is kept when it finds a part.

        scene: the scene whose frames the clouds came from; its depth images and intrinsics give
            the free-space evidence (none without it).
        motion_hints: (4, 4) start->end rigid motions (scene frame) that another stage found, e.g.
            the feature alignment's candidate moving parts; each is tried as one more hypothesis
            for every pair of segment groups.
        posed: the clouds are in a known world frame (cameras given); None = ``scene.posed`` when a
            scene is given and ``aligned``. A part that moved is then kept even when no static
            segment is seen in both states.

        Why the second pass only then: "nothing moved" is the strongest claim the labeler makes,
        and the nearest-point test behind it is blind to a part whose old place the other state
        fills with a different surface -- a drawer pulled towards a robot's head camera leaves its
        front's place to its own side walls, its interior and the arm that pulled it, all within
        the motion radius. Measured on the robot-shaped renders (16 objects, seeds 0-3, one view,
        no masks): the replaced-surface split on every scene gave 46 -> 46 and 41 -> 45 of 84
        joints, with as many new misses as new hits, and a clean twin-drawer desk lost 2 of 4
        drawers (drawer boxes passing the carcass's opening edges); only after "no part moved" it
        gave 46 -> 49 and 41 -> 43 with no joint lost, and every other setting unchanged
        (experiment EXP-037). Costs one pass more (~0.9 s on a
        robot view), in those scenes only.
        """
        labels = self._label_pass(start, end, scene, aligned, motion_hints, posed, replaced=False)
        if has_masks(start, end) or any(p.role == "movable" for p in labels.parts):
            return labels
        again = self._label_pass(start, end, scene, aligned, motion_hints, posed, replaced=True)
        if not any(p.role == "movable" for p in again.parts):
            return labels
        again.warnings.insert(1, "no part moved by the nearest-point test; found by surfaces that the other "
                                 "state shows replaced by a differently facing surface (a drawer's front by "
                                 "its own sides or a hand)")
        return again

    def _label_pass(self, start: LabelledCloud, end: LabelledCloud, scene: Scene | None, aligned: bool,
                    motion_hints: list[np.ndarray] | None, posed: bool | None, replaced: bool) -> PartLabels:
        """One labelling (arguments as :meth:`label`); ``replaced``: the split without masks also
        counts replaced surfaces as moved (:func:`_replaced_surfaces`). About O(N log N) for the
        downsampling and KD-trees, plus O(G_s G_e (R_c + S (log M + V))) for the pair search
        (:mod:`.correspondence`) with G groups per state, a coarse registration R_c, S samples,
        V views."""
        if len(start) < 10 or len(end) < 10:
            raise TooLittleToLabel("too few valid points to label parts (need at least 10 per state)",
                                   "start" if len(start) < 10 else "end")
        config = self.config
        if posed is None:
            posed = bool(aligned and scene is not None and scene.posed)
        rng = np.random.default_rng(config.seed)
        warnings: list[str] = []
        masked = has_masks(start, end)
        original_start, original_end, split_ids = start, end, frozenset()
        if masked:   # merged / split masks put right by the state's other views (module doc, step 1)
            ids, repair_rng = named_mask_ids(start, end), np.random.default_rng(config.seed + 7)
            start, start_notes = repair_merged_masks(start, ids, repair_rng)
            end, end_notes = repair_merged_masks(end, ids, repair_rng)
            split_ids = split_mask_ids(original_start, start) | split_mask_ids(original_end, end)
            warnings.extend(start_notes + end_notes)
        voxel = _voxel_size(start, end, config, rng)
        work_start, start_map = _downsample(start, voxel)
        work_end, end_map = _downsample(end, voxel)
        spacing = max(median_spacing(work_start.points, sample=4000, rng=rng),
                      median_spacing(work_end.points, sample=4000, rng=rng))
        radius = config.inlier_radius_spacings * spacing
        if masked:
            start_segments, end_segments = work_start.segment, work_end.segment
        else:
            start_segments, end_segments = _motion_split(work_start, work_end, config, spacing, start, end, rng,
                                                         scene if aligned else None, replaced)
            warnings.append("no masks: parts come from a motion-based split (points that moved)")
            config = replace(config, min_segment_share=max(config.min_segment_share,
                                                           config.motion_piece_min_share))
        named = named_mask_ids(work_start, work_end) - split_ids if masked else frozenset()
        start_groups = _merge_across_frames(work_start, start_segments, radius, config, rng, named)
        end_groups = _merge_across_frames(work_end, end_segments, radius, config, rng, named)
        if not start_groups or not end_groups:
            raise TooLittleToLabel("no usable segment: too few valid points, or masks empty after filtering",
                                   "start" if not start_groups else "end")
        margin = 2.0 * radius
        views = (state_views(work_start, scene, margin), state_views(work_end, scene, margin))
        diameter = max(float(np.linalg.norm(np.ptp(work_start.points, axis=0))), 1e-12)
        context = PairContext(work_start, work_end, start_groups, end_groups, radius, diameter, views[0], views[1],
                              config.max_points_per_segment, config.pair_registration_points, config.seed)
        context.prepare()
        mask_ids = mask_agreement(work_start, work_end, start_groups, end_groups, named, split_ids) if masked else None
        candidates = score_pairs(context, config.match_min_score, list(motion_hints or []), mask_ids)
        moving = {key for key, c in candidates.items() if not _is_static(c.transform, c.i, work_start, start_groups, radius)}
        assignment = assign(candidates, len(start_groups), len(end_groups), diameter, config.match_min_score, moving)
        pairs = [(i, j, candidates[(i, j)].transform, candidates[(i, j)].score) for i, j in assignment.pairs]
        extras = _extras(context, candidates, assignment.pairs, start_groups, end_groups, config, warnings)
        layers = None
        if not masked:
            layers = _layers_without_masks(work_start, work_end, start_segments, end_segments, candidates,
                                           assignment.pairs, radius, config, warnings, context, posed)
            unseen = bool(np.any(start_segments == UNSEEN) or np.any(end_segments == UNSEEN))
            if len(layers) < 2 and not (layers and unseen):
                # One motion: the pieces' own pairing labels more of the points -- unless some
                # moved points were unseen (no piece holds them; only a motion can claim them).
                layers = None
        labels = _assign_parts(work_start, work_end, start_segments, end_segments, start_groups, end_groups, pairs,
                               extras, radius, config, warnings, motion_split=not masked,
                               identity_scores={k: c.identity for k, c in candidates.items()},
                               posed=posed, diameter=diameter, layers=layers, views=views, aligned=aligned)
        part_of_pair = _part_of_pairs(labels, pairs, start_groups)
        diagnostics = _pairing_diagnostics(assignment, candidates, part_of_pair, warnings, voxel,
                                           swaps_only=not masked)
        labels = _to_full(labels, start, end, start_map, end_map, masked)
        _refine_on_full(labels, start, end, config)
        diagnostics["consistency"] = _object_consistency(labels, work_start, work_end, start_map, views[1], warnings)
        diagnostics["voxel"] = voxel
        diagnostics["work_points"] = [len(work_start), len(work_end)]
        diagnostics["motion_split"] = not masked
        labels.warnings = warnings
        _attach(labels, diagnostics)
        return labels


# ---------------------------------------------------------------------- helpers


def has_masks(start: LabelledCloud, end: LabelledCloud) -> bool:
    """Whether the labeler reads parts from the clouds' mask segments: both states have segmented
    points. Otherwise it splits the points by motion. O(N)."""
    return bool(np.any(start.segment >= 0) and np.any(end.segment >= 0))


def _median_spacing(points: np.ndarray, rng: np.random.Generator, sample: int = 4000) -> float:
    """Median nearest-neighbour distance of a cloud, from a random sample. O(N log N)."""
    return median_spacing(points, sample=sample, rng=rng)


def _voxel_size(start: LabelledCloud, end: LabelledCloud, config: RuleLabelerConfig,
                rng: np.random.Generator) -> float:
    """The work clouds' voxel: the extent of both states (1st-99th percentile box diagonal) over
    ``voxel_divisions``, never below the clouds' own spacing (no point is then merged with a
    neighbour it would not touch anyway); 0 when downsampling is off. O(N log N) on a sample."""
    if config.voxel_divisions <= 0:
        return 0.0
    points = np.concatenate([start.points, end.points])
    low, high = np.percentile(points, [1, 99], axis=0)
    extent = float(np.linalg.norm(high - low))
    sample = points[random_subset(len(points), 20000, rng)]
    spacing = median_spacing(sample, sample=4000, rng=rng) * np.sqrt(len(sample) / max(len(points), 1))
    voxel = extent / config.voxel_divisions
    return voxel if voxel > spacing else 0.0


def _downsample(cloud: LabelledCloud, voxel: float) -> tuple[LabelledCloud, np.ndarray]:
    """One point per (voxel, segment): the first in the cloud's order (deterministic).

    Returns the work cloud and (N,) int64, for every point of ``cloud``, the index of its work
    point. O(N log N)."""
    if voxel <= 0 or len(cloud) == 0:
        return cloud, np.arange(len(cloud))
    keys = np.floor((cloud.points - cloud.points.min(axis=0)) / voxel).astype(np.int64)
    table = np.concatenate([keys, cloud.segment[:, None] - cloud.segment.min()], axis=1)
    sizes = table.max(axis=0) + 1
    if float(np.prod(sizes.astype(np.float64))) < 2.0 ** 62:
        # One int64 per (voxel, segment): a 1-D unique is much faster than rows (same groups).
        code = np.zeros(len(table), dtype=np.int64)
        for column, size in zip(table.T, sizes):
            code = code * size + column
        _, first, inverse = np.unique(code, return_index=True, return_inverse=True)
    else:
        _, first, inverse = np.unique(table, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return cloud.subset(first[order]), rank[inverse.reshape(-1)].astype(np.int64)


def _motion_split(start: LabelledCloud, end: LabelledCloud, config: RuleLabelerConfig, spacing: float,
                  full_start: LabelledCloud, full_end: LabelledCloud,
                  rng: np.random.Generator, scene: Scene | None = None,
                  replaced: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Pseudo-segments without masks: 0 = stayed put, 1..k = connected pieces of moved points,
    ``UNSEEN`` = no vote (see below).

    A work point is "far" when it is farther than ``motion_radius_spacings`` x the FULL clouds'
    spacing from every point of the other state's full cloud (the work clouds' coarser spacing
    would hide small motions: a toaster's lever pressed a few millimetres). Far is not yet moved:
    with the other state's depth views (``scene``, states in one frame), a far point that those
    views could not see -- something nearer covers its place (the base under a lid that closed
    over it, the table under an arm) -- has no evidence of moving and gets ``UNSEEN``; only a far
    point whose place the other state's views saw through (or saw a surface at) is moved. Unseen
    points are neither static nor moved: the motion layers may still claim them when a part's
    motion carries them onto moved points that were seen (a lid whose own end pose hides its start
    pose), otherwise they stay unassigned. Pieces link moved work points within 3 work spacings.
    ``replaced``: a near point whose surface the other state replaced by a differently facing one
    counts as far too (:func:`_replaced_surfaces`).
    O(N log N) plus O(N V) for V views (plus O(N k log N) for the normals when ``replaced``)."""
    full_spacing = max(median_spacing(full_start.points, sample=4000, rng=rng),
                       median_spacing(full_end.points, sample=4000, rng=rng))
    radius = config.motion_radius_spacings * full_spacing
    views = ((state_views(end, scene, radius), state_views(start, scene, radius)) if scene is not None
             else (StateViews([], radius), StateViews([], radius)))
    trees = (cKDTree(full_start.points), cKDTree(full_end.points))
    surfaces = ([normals_with_variation(full.points, REPLACED_NEIGHBOURS) for full in (full_start, full_end)]
                if replaced else None)
    result = []
    for side, (cloud, other_views) in enumerate(((start, views[0]), (end, views[1]))):
        distance, nearest = trees[1 - side].query(cloud.points, k=1, distance_upper_bound=radius)
        if surfaces is not None:
            near = np.flatnonzero(distance <= radius)
            own = trees[side].query(cloud.points[near], k=1)[1]
            (own_normals, own_variation), (other_normals, other_variation) = surfaces[side], surfaces[1 - side]
            swapped = _replaced_surfaces(own_normals[own], own_variation[own], other_normals[nearest[near]],
                                         other_variation[nearest[near]])
            distance[near[swapped]] = np.inf
        segments = np.zeros(len(cloud), dtype=np.int64)
        far = np.flatnonzero(distance > radius)
        if other_views and len(far):
            unseen = other_views.classify(cloud.points[far]) == HIDDEN
            segments[far[unseen]] = UNSEEN
            far = far[~unseen]
        if len(far):
            labels = radius_components(cloud.points[far], 3.0 * spacing)
            segments[far] = labels + 1
        result.append(segments)
    return result[0], result[1]


REPLACED_NEIGHBOURS = 60        # points (full cloud) behind each normal of the replaced-surface test
REPLACED_MIN_DEG = 45.0         # a near point's surface and the other state's there differ by more: replaced
REPLACED_MAX_VARIATION = 0.15   # ... when both are planar enough for their normals to mean something


def _replaced_surfaces(own_normals: np.ndarray, own_variation: np.ndarray, other_normals: np.ndarray,
                       other_variation: np.ndarray) -> np.ndarray:
    """(P,) bool: which of P near points (each within the motion radius of the other state's
    cloud) lie on a surface the other state replaced by a differently facing one: its normal and
    the other state's normal at its nearest point ((P, 3) each, PCA of ``REPLACED_NEIGHBOURS``
    points of each state's full cloud) differ by more than ``REPLACED_MIN_DEG`` and both
    neighbourhoods are planar (surface variations (P,) <= ``REPLACED_MAX_VARIATION``).

    Why: a drawer pulled out towards the camera leaves its front's place to its own side walls and
    interior (and the arm), so the front is "near" the other state everywhere and was called
    static; its normal is not found there. Measured on robot-shaped renders with noisy depth
    (nightstand, the drawer's start front): normal gaps > 45 deg on 82 % of it against 3 % of the
    static carcass and background; the background's wrongly gapped points are noise-dominated
    (surface variation median 0.20 against 0.10 on the drawer), which the planarity test drops.
    O(P)."""
    facing = np.abs(np.einsum("ij,ij->i", own_normals, other_normals))
    planar = (own_variation <= REPLACED_MAX_VARIATION) & (other_variation <= REPLACED_MAX_VARIATION)
    return (facing < np.cos(np.radians(REPLACED_MIN_DEG))) & planar


def _merge_across_frames(cloud: LabelledCloud, segments: np.ndarray, radius: float,
                         config: RuleLabelerConfig, rng: np.random.Generator,
                         named_ids: frozenset[int] = frozenset()) -> list[Group]:
    """Union segments of different frames that cover the same surface. O(S^2 P log P).

    A segment takes part with ``min_segment_points`` points; the share floor
    (``min_segment_share`` of the cloud) applies to the merged group, so a small part seen in
    several views counts with all of them (a toaster lever half hidden by a hand: 62 + 68 points
    in two views, each below the 83-point floor, together above it).

    named_ids: mask ids that name parts across images (:func:`~.correspondence.named_mask_ids`).
    Segments of two different named ids never join, however much they overlap: measured on a
    realistic oven, two touching wire racks merged into one group and were paired as one part.
    Segments of one named id still join only by overlap: forcing them together also joined a
    laptop base's two end views that per-view registration error kept apart (lid 1.3 -> 87 deg).
    Segments of other ids (a split mask's new id) join by overlap as before."""
    ids, counts = np.unique(segments[segments >= 0], return_counts=True)
    name = {int(s): cloud.segment_source[int(s)][1] for s in ids
            if int(s) in cloud.segment_source and cloud.segment_source[int(s)][1] in named_ids}
    kept = [int(i) for i, c in zip(ids, counts) if c >= config.min_segment_points]
    members = {s: np.flatnonzero(segments == s) for s in kept}
    samples = {s: idx[random_subset(len(idx), config.max_points_per_segment, rng)]
               for s, idx in members.items()}
    trees = {s: cKDTree(cloud.points[samples[s]]) for s in kept}
    frame_of = {s: int(cloud.frame_index[members[s][0]]) for s in kept}
    parent = {s: s for s in kept}
    root_name = {s: name.get(s) for s in kept}

    def find(s: int) -> int:
        while parent[s] != s:
            parent[s] = parent[parent[s]]
            s = parent[s]
        return s

    def union(a: int, b: int) -> None:
        ra, rb = find(a), find(b)
        if ra == rb or (root_name[ra] is not None and root_name[rb] is not None and root_name[ra] != root_name[rb]):
            return
        parent[ra] = rb
        root_name[rb] = root_name[rb] if root_name[rb] is not None else root_name[ra]

    for i, a in enumerate(kept):
        for b in kept[i + 1:]:
            if frame_of[a] == frame_of[b] or find(a) == find(b):
                continue
            overlap_ab = _overlap(cloud.points[samples[a]], trees[b], radius)
            overlap_ba = _overlap(cloud.points[samples[b]], trees[a], radius)
            if max(overlap_ab, overlap_ba) >= config.merge_overlap:
                union(a, b)
    groups: dict[int, list[int]] = {}
    for s in kept:
        groups.setdefault(find(s), []).append(s)
    result = []
    minimum = max(config.min_segment_points, config.min_segment_share * len(cloud))
    for segs in groups.values():
        indices = np.concatenate([members[s] for s in segs])
        if len(indices) >= minimum:
            result.append(Group(segments=sorted(segs), indices=np.sort(indices)))
    result.sort(key=lambda g: (-len(g.indices), g.segments[0]))
    return result


def _group_sample(group: Group, limit: int, rng: np.random.Generator) -> np.ndarray:
    """Indices (into the state's cloud) of at most ``limit`` random points of a group."""
    return group.indices[random_subset(len(group.indices), limit, rng)]


def _overlap(moved: np.ndarray, target_tree: cKDTree, radius: float) -> float:
    """Share of ``moved`` (N, 3) within ``radius`` of the tree's points; the search stops at the
    radius (only hits count). O(N log M)."""
    return float(np.mean(target_tree.query(moved, k=1, distance_upper_bound=radius)[0] < radius))


def _apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return apply(transform, points)


def _motion_size(transform: np.ndarray) -> tuple[float, float]:
    return motion_size(transform)


def _is_static(transform: np.ndarray, i: int, start: LabelledCloud, start_groups: list[Group],
               radius: float) -> bool:
    angle, _ = motion_size(transform)
    centroid = start.points[start_groups[i].indices].mean(axis=0)
    displacement = float(np.linalg.norm(apply(transform, centroid[None])[0] - centroid))
    return angle < STATIC_ANGLE_DEG and displacement < STATIC_SHIFT_RADII * radius


def _extras(context: PairContext, candidates: dict, chosen: list[tuple[int, int]], start_groups: list[Group],
            end_groups: list[Group], config: RuleLabelerConfig, warnings: list[str]) -> list[tuple[str, int, int]]:
    """Groups left over by the one-to-one pairing (a surface seen in two views that did not merge,
    an over-segmented or fragmented part) follow the part of their best-scoring partner, when that
    partner's own pairing motion carries them onto it too (one rigid part, one motion; a look-alike
    part that moved differently stays out)."""
    scores = np.zeros((len(start_groups), len(end_groups)))
    for (i, j), candidate in candidates.items():
        scores[i, j] = candidate.score
    paired_start = {i: j for i, j in chosen}
    paired_end = {j: i for i, j in chosen}
    extras: list[tuple[str, int, int]] = []
    for i in range(len(start_groups)):
        if i in paired_start or scores[i].max() < config.match_min_score:
            continue
        j = int(np.argmax(scores[i]))
        partner = paired_end.get(j)
        motion = candidates[(partner, j)].transform if partner is not None else candidates[(i, j)].transform
        if pair_score(context, i, j, motion) >= config.match_min_score:
            extras.append(("start", i, j))
    for j in range(len(end_groups)):
        if j in paired_end or scores[:, j].max() < config.match_min_score:
            continue
        i = int(np.argmax(scores[:, j]))
        partner = paired_start.get(i)
        motion = candidates[(i, partner)].transform if partner is not None else candidates[(i, j)].transform
        if pair_score(context, i, j, motion) >= config.match_min_score:
            extras.append(("end", j, i))
    attached = {(state, k) for state, k, _ in extras}
    unmatched = ([f"start group of {len(g.indices)} points" for k, g in enumerate(start_groups)
                  if k not in paired_start and ("start", k) not in attached] +
                 [f"end group of {len(g.indices)} points" for k, g in enumerate(end_groups)
                  if k not in paired_end and ("end", k) not in attached])
    if unmatched:
        warnings.append("seen in one state only (occluded, moved out of view, or not rigid): "
                        + ", ".join(unmatched) + "; left unassigned")
    return extras


def _fallback_base(moving_pairs: list[tuple[int, int, np.ndarray, float]], start_groups: list[Group],
                   identity_scores: dict[tuple[int, int], float],
                   aligned_start: LabelledCloud | None = None) -> tuple[int, int, np.ndarray, float]:
    """The static base when no pair passed the static test: the pair that staying put explains
    best relative to its own motion (identity score / pair score >= ``STILL_EXPLAINS_SHARE``; the
    largest such one), else the largest pair (design: the largest consistent set) -- or, when the
    states were already aligned on a static part without a known world frame (``aligned_start``
    given: the second labelling of an unposed scene), the pair that moved least (median travel of
    its points): the alignment brought the base near identity even when a flat base slid along
    itself, while the largest group may be the part that turned."""
    def share(pair) -> float:
        return identity_scores.get((pair[0], pair[1]), 0.0) / max(pair[3], 1e-12)

    still = [p for p in moving_pairs if share(p) >= STILL_EXPLAINS_SHARE]
    if still or aligned_start is None:
        return max(still or moving_pairs, key=lambda p: len(start_groups[p[0]].indices))

    return min(moving_pairs, key=lambda pair: _travel(pair, aligned_start, start_groups))


def _travel(pair: tuple[int, int, np.ndarray, float], start: LabelledCloud, start_groups: list[Group]) -> float:
    """Median distance the pair's start-group points move under its (4, 4) motion (scene units).
    Unlike the motion's translation it does not depend on where the frame's origin lies. O(N)."""
    points = start.points[start_groups[pair[0]].indices]
    return float(np.median(np.linalg.norm(apply(pair[2], points) - points, axis=1)))


def _layers_without_masks(start: LabelledCloud, end: LabelledCloud, start_segments: np.ndarray,
                          end_segments: np.ndarray, candidates: dict, chosen: list[tuple[int, int]], radius: float,
                          config: RuleLabelerConfig, warnings: list[str], context: PairContext, posed: bool = False):
    """Motion layers of the moved points (pseudo-segments > 0), starting from the motions of the
    assigned pairs that moved (:mod:`.motion_layers`).

    The layers' point floor (a part's least support: candidate votes, price, layer size) is the
    piece floor (``min_segment_share`` of the cloud) but at most ``motion_floor_moved_share`` of
    the moved points (mean of the two states). A floor tied to the whole cloud grows with the room around the
    object, not with the object: one robot view of a nightstand on a table, walls and floor in
    the picture, has ~52k work points, so the floor was 522 points while the drawer pulled out
    gathered 317 slide votes; a washing machine's lid raised 67 deg had fewer than 543 points on
    its plane. Measured on the robot-shaped settings (16 objects, seeds 0-3): 38 -> 43 of 84
    joints within 10 deg (one view, reconstructor depth) and 35 -> 38 (sensor depth); the clean
    maskless settings, where the object fills the views, keep the cloud floor (no change).
    ``posed``: the states' frame is known (the small-part search trusts free space more there)."""
    from .motion_layers import motion_layers

    start_moved = np.flatnonzero((start_segments > 0) | (start_segments == UNSEEN))
    end_moved = np.flatnonzero((end_segments > 0) | (end_segments == UNSEEN))
    moving = [p for p in chosen if not _is_static(candidates[p].transform, p[0], start, context.start_groups, radius)]
    others = sorted((c for key, c in candidates.items() if key not in moving and c.how != "identity"
                     and c.score >= config.match_min_score), key=lambda c: (-c.score, c.i, c.j))
    motions = [candidates[p].transform for p in moving] + [c.transform for c in others]
    min_points = int(max(config.min_segment_points,
                         min(config.min_segment_share * (len(start) + len(end)) / 2,
                             config.motion_floor_moved_share * (len(start_moved) + len(end_moved)) / 2)))
    pieces = ([g.indices for g in context.start_groups if start_segments[g.indices[0]] > 0],
              [g.indices for g in context.end_groups if end_segments[g.indices[0]] > 0])
    unseen = (start_segments[start_moved] == UNSEEN, end_segments[end_moved] == UNSEEN)
    layers, notes = motion_layers(context, start_moved, end_moved, motions, min_points, pieces, unseen, posed)
    warnings.extend(notes)
    return layers


def _assign_parts(start: LabelledCloud, end: LabelledCloud, start_segments: np.ndarray,
                  end_segments: np.ndarray, start_groups: list[Group], end_groups: list[Group],
                  pairs: list[tuple[int, int, np.ndarray, float]], extras: list[tuple[str, int, int]],
                  radius: float, config: RuleLabelerConfig, warnings: list[str],
                  motion_split: bool, identity_scores: dict[tuple[int, int], float] | None = None,
                  posed: bool = False, diameter: float = 1.0, layers=None,
                  views: tuple[StateViews, StateViews] | None = None, aligned: bool = False) -> PartLabels:
    """Static pairs -> part 0; moving pairs merged by shared motion -> parts 1..k (or, without
    masks, one part per motion layer)."""
    rng = np.random.default_rng(config.seed + 2)
    static_pairs, moving_pairs = [], []
    for pair in pairs:
        (static_pairs if _is_static(pair[2], pair[0], start, start_groups, radius) else moving_pairs).append(pair)
    if not static_pairs and moving_pairs:
        least = aligned and not posed
        base = _fallback_base(moving_pairs, start_groups, identity_scores or {}, start if least else None)
        angle = motion_size(base[2])[0]
        # how far the base's own points travel, not the motion's translation (a 4.2 deg error of a
        # feature alignment about a camera 2.6 m away shifted a desk's origin by 0.19, its points
        # by a median 0.04)
        shift = _travel(base, start, start_groups)
        if (identity_scores or {}).get((base[0], base[1]), 0.0) >= STILL_EXPLAINS_SHARE * base[3]:
            # Noisy depth lowers every overlap; a pair that staying put explains nearly as well as
            # its registered motion did not move (measured: a laptop base at 1 % depth noise,
            # identity 0.33 vs a spurious 80 deg registration 0.38).
            moving_pairs.remove(base)
            static_pairs.append((base[0], base[1], np.eye(4), base[3]))
            warnings.append("no segment stayed put clearly (noisy depth?); the one that staying put explains "
                            f"nearly as well as any motion (>= {STILL_EXPLAINS_SHARE:.0%}) is taken as the static base")
        elif posed and not (angle < POSE_ERROR_DEG and shift < POSE_ERROR_DIAMETERS * diameter):
            warnings.append("no segment is seen in both states staying put; the cameras (or the trusted feature "
                            "alignment of the states) give the frame, "
                            "so every part that moved is kept (the static base is unseen)")
        else:
            moving_pairs.remove(base)
            static_pairs.append(base)
            warnings.append("no segment stayed put between the states; the " + ("one that moved least" if least else
                            "largest one") + " is taken as the static base (are the two states in one frame?)")
    start_map: dict[int, int] = {}
    end_map: dict[int, int] = {}
    for i, j, _, _ in static_pairs:
        for s in start_groups[i].segments:
            start_map[s] = 0
        for s in end_groups[j].segments:
            end_map[s] = 0
    parts = [PartSpec(id=0, role="static")]
    motions, priors, alternative_motions = {}, {}, {}
    if static_pairs:
        motions[0] = max(static_pairs, key=lambda p: len(start_groups[p[0]].indices))[2]
    if layers is not None:
        return _parts_from_layers(start, end, start_segments, end_segments, layers, parts, motions, config,
                                  warnings, radius, views)
    clusters = _motion_clusters(start, end, start_groups, end_groups, moving_pairs, radius, config, rng)
    ordered = sorted(clusters, key=lambda ks: -sum(len(start_groups[moving_pairs[k][0]].indices) for k in ks))

    def start_part_indices(members: list[int]) -> np.ndarray:
        return np.unique(np.concatenate([start_groups[moving_pairs[k][0]].indices for k in members]))

    def end_part_indices(members: list[int]) -> np.ndarray:
        return np.unique(np.concatenate([end_groups[moving_pairs[k][1]].indices for k in members]))

    for part_id, members in enumerate(ordered, start=1):
        best = max(members, key=lambda k: moving_pairs[k][3] * len(start_groups[moving_pairs[k][0]].indices))
        for k in members:
            i, j, _, _ = moving_pairs[k]
            for s in start_groups[i].segments:
                start_map[s] = part_id
            for s in end_groups[j].segments:
                end_map[s] = part_id
        transform, alternatives = _polish_motion(start, end, start_part_indices(members),
                                                 end_part_indices(members), moving_pairs[best][2], config,
                                                 radius, views)
        _add_part(parts, motions, priors, alternative_motions, part_id, transform, alternatives, warnings)
    start_group_part = {i: start_map[start_groups[i].segments[0]] for i, _, _, _ in static_pairs + moving_pairs}
    end_group_part = {j: end_map[end_groups[j].segments[0]] for _, j, _, _ in static_pairs + moving_pairs}
    for state, group, partner in extras:
        if state == "start" and partner in end_group_part:
            for s in start_groups[group].segments:
                start_map[s] = end_group_part[partner]
        elif state == "end" and partner in start_group_part:
            for s in end_groups[group].segments:
                end_map[s] = start_group_part[partner]
    if len(parts) == 1:
        warnings.append("no part moved between the two states")
    start_part = _points_to_parts(start_segments, start_map)
    end_part = _points_to_parts(end_segments, end_map)
    if motion_split:
        # Pseudo-segment 0 is "stayed put" in both states.
        start_part[start_segments == 0] = 0
        end_part[end_segments == 0] = 0
        start_map, end_map = {}, {}
    return PartLabels(parts=parts, start_part=start_part, end_part=end_part,
                      start_segment_to_part=start_map, end_segment_to_part=end_map,
                      initial_motion=motions, type_prior=priors, alternative_motions=alternative_motions,
                      warnings=warnings)


def _add_part(parts: list[PartSpec], motions: dict, priors: dict, alternative_motions: dict, part_id: int,
              transform: np.ndarray, alternatives: list[np.ndarray], warnings: list[str]) -> None:
    motions[part_id] = transform
    if alternatives:
        alternative_motions[part_id] = alternatives
    angle, _ = motion_size(transform)
    if angle >= REVOLUTE_PRIOR_DEG:
        priors[part_id] = "revolute"
    elif angle <= PRISMATIC_PRIOR_DEG:
        priors[part_id] = "prismatic"
    else:
        warnings.append(f"part {part_id}: rotation of {angle:.1f} deg is between "
                        f"{PRISMATIC_PRIOR_DEG} and {REVOLUTE_PRIOR_DEG} deg: joint type is left to the fit")
    parts.append(PartSpec(id=part_id, role="movable", parent=0))


def _parts_from_layers(start: LabelledCloud, end: LabelledCloud, start_segments: np.ndarray,
                       end_segments: np.ndarray, layers, parts: list[PartSpec], motions: dict,
                       config: RuleLabelerConfig, warnings: list[str], radius: float,
                       views: tuple[StateViews, StateViews] | None) -> PartLabels:
    """Without masks: pseudo-segment 0 is static, every motion layer is one movable part."""
    start_part = np.where(start_segments == 0, 0, -1).astype(np.int64)
    end_part = np.where(end_segments == 0, 0, -1).astype(np.int64)
    priors, alternative_motions, confidence = {}, {}, {}
    for part_id, layer in enumerate(layers, start=1):
        start_part[layer.start] = part_id
        end_part[layer.end] = part_id
        transform, alternatives = _polish_motion(start, end, layer.start, layer.end, layer.transform, config,
                                                 radius, views)
        _add_part(parts, motions, priors, alternative_motions, part_id, transform, alternatives, warnings)
        for doubt in layer.doubts:
            confidence[part_id] = min(confidence.get(part_id, 1.0), doubt.trust)
            warnings.append(f"part {part_id}: {doubt.why}: confidence x{doubt.trust:.2g}")
    if len(parts) == 1:
        warnings.append("no part moved between the two states")
    return PartLabels(parts=parts, start_part=start_part, end_part=end_part, initial_motion=motions,
                      type_prior=priors, alternative_motions=alternative_motions, confidence=confidence,
                      warnings=warnings)


def _motion_clusters(start: LabelledCloud, end: LabelledCloud, start_groups: list[Group], end_groups: list[Group],
                     moving_pairs: list, radius: float, config: RuleLabelerConfig,
                     rng: np.random.Generator) -> list[list[int]]:
    """Moving pairs merged when they share a motion (over-segmented parts): union-find."""
    parent = list(range(len(moving_pairs)))

    def find(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for a in range(len(moving_pairs)):
        for b in range(a + 1, len(moving_pairs)):
            if _same_motion(start, end, start_groups, end_groups, moving_pairs[a], moving_pairs[b],
                            radius, config, rng):
                parent[find(a)] = find(b)
    clusters: dict[int, list[int]] = {}
    for k in range(len(moving_pairs)):
        clusters.setdefault(find(k), []).append(k)
    return list(clusters.values())


def _polish_motion(start: LabelledCloud, end: LabelledCloud, start_indices: np.ndarray,
                   end_indices: np.ndarray, transform: np.ndarray, config: RuleLabelerConfig,
                   radius: float | None = None, views: tuple[StateViews, StateViews] | None = None,
                   ) -> tuple[np.ndarray, list[np.ndarray]]:
    """A part's start->end motion on all of its points (with colour), and tied alternatives.

    The pair matching registered sub-samples of single groups; a symmetric part (a round door, a
    box lid) can come out turned the wrong way there. So the full global registration (all
    hypotheses, FPFH fallback) runs on the whole part too, beside the pair's motion refined from
    its own start (coloured ICP, and with a radius the symmetric point-to-point ICP, which stays
    put on flat parts). With a radius the primary motion is the one that explains the part best
    over what the other state's views could see (:func:`~.correspondence.pair_score` on the part);
    without, the highest inlier fraction. Another motion that differs by more than
    ``DISTINCT_MOTION_DEG`` is returned as an alternative: registration scores do not separate a
    symmetric part's turns reliably, so the joint fit decides (by residual, then by where a hinge can be).
    """
    from sparseart.geometry.icp import register_rigid
    from sparseart.geometry.transforms import rotation_angle

    source, target = start.points[start_indices], end.points[end_indices]
    if len(source) < 3 or len(target) < 3:
        return transform, []
    colours = dict(source_colors=start.colors[start_indices], target_colors=end.colors[end_indices])
    candidates = [register_rigid(source, target, init=transform, max_points=POLISH_POINTS, seed=config.seed, **colours),
                  register_rigid(source, target, max_points=POLISH_POINTS, seed=config.seed, **colours)]
    motions = [c.transform for c in candidates]
    if radius is None:
        order = np.argsort([-c.inlier_fraction for c in candidates], kind="stable")
    else:
        from .correspondence import refine_icp

        rng = np.random.default_rng(config.seed + 4)
        s_pick = start_indices[random_subset(len(start_indices), config.max_points_per_segment, rng)]
        e_pick = end_indices[random_subset(len(end_indices), config.max_points_per_segment, rng)]
        motions.insert(0, refine_icp(start.points[s_pick], end.points[e_pick], transform, radius))
        context = PairContext(start, end, [Group([0], start_indices)], [Group([0], end_indices)], radius, 1.0,
                              *(views or (StateViews([], radius), StateViews([], radius))),
                              config.max_points_per_segment, config.pair_registration_points, config.seed)
        context.start_samples, context.end_samples = [s_pick], [e_pick]
        context.start_trees, context.end_trees = [cKDTree(source)], [cKDTree(target)]
        scores = [pair_score(context, 0, 0, m) for m in motions]
        _, first = prefer_small_turns(list(zip(scores, motions)))
        first_index = next(k for k, m in enumerate(motions) if m is first)
        order = [first_index] + [int(k) for k in np.argsort([-round(v, 3) for v in scores], kind="stable")
                                 if k != first_index]
    chosen = motions[order[0]]
    alternatives = []
    for k in order[1:]:
        m = motions[k]
        if np.degrees(rotation_angle(m[:3, :3] @ chosen[:3, :3].T)) > DISTINCT_MOTION_DEG and \
                all(np.degrees(rotation_angle(m[:3, :3] @ a[:3, :3].T)) > DISTINCT_MOTION_DEG for a in alternatives):
            alternatives.append(m)
    return chosen, alternatives


def _points_to_parts(segments: np.ndarray, mapping: dict[int, int]) -> np.ndarray:
    result = np.full(len(segments), -1, dtype=np.int64)
    if mapping:
        keys = np.fromiter(mapping.keys(), dtype=np.int64)
        values = np.fromiter(mapping.values(), dtype=np.int64)
        order = np.argsort(keys)
        keys, values = keys[order], values[order]
        slot = np.clip(np.searchsorted(keys, segments), 0, len(keys) - 1)
        hit = keys[slot] == segments
        result[hit] = values[slot[hit]]
    return result


def _same_motion(start: LabelledCloud, end: LabelledCloud, start_groups: list[Group],
                 end_groups: list[Group], pair_a: tuple, pair_b: tuple, radius: float,
                 config: RuleLabelerConfig, rng: np.random.Generator) -> bool:
    """Do two moving pairs belong to one part? They must touch (in either state: pieces of one
    part are adjacent, identical sibling parts such as an oven's racks are not) and either pair's
    motion must carry the other pair's start points onto its end points; never when the masks name
    them as different parts (:func:`~.correspondence.distinct_by_masks`). O(S log N) per test."""
    (ia, ja, _, _), (ib, jb, _, _) = pair_a, pair_b
    if distinct_by_masks(start_groups[ia], start_groups[ib]) or distinct_by_masks(end_groups[ja], end_groups[jb]):
        return False
    touching = False
    for cloud, groups, a, b in ((start, start_groups, ia, ib), (end, end_groups, ja, jb)):
        sample = cloud.points[_group_sample(groups[b], config.max_points_per_segment, rng)]
        gap = cKDTree(cloud.points[groups[a].indices]).query(sample, k=1)[0].min()
        touching = touching or gap < ADJACENT_RADII * radius
    if not touching:
        return False
    for (ia, ja, ta, _), (ib, jb, _, _) in ((pair_a, pair_b), (pair_b, pair_a)):
        source = start.points[_group_sample(start_groups[ib], config.max_points_per_segment, rng)]
        target_tree = cKDTree(end.points[end_groups[jb].indices])
        if _overlap(_apply(ta, source), target_tree, radius) >= config.same_motion_overlap:
            return True
    return False


def _part_of_pairs(labels: PartLabels, pairs: list, start_groups: list[Group]) -> dict[tuple[int, int], int]:
    """Part id of every chosen pair (by the part of its start group's points)."""
    result = {}
    for i, j, _, _ in pairs:
        values = labels.start_part[start_groups[i].indices]
        values = values[values >= 0]
        if len(values):
            result[(i, j)] = int(np.bincount(values).argmax())
    return result


def _pairing_diagnostics(assignment, candidates: dict, part_of_pair: dict[tuple[int, int], int],
                         warnings: list[str], voxel: float, swaps_only: bool = False) -> dict:
    """Pairing cost, runner-up and per-part confidence; a warning when the runner-up is within
    ``AMBIGUITY_MARGIN`` (the parts it would re-pair get confidence margin / AMBIGUITY_MARGIN,
    at least 0.3).

    swaps_only (no masks): only a runner-up that swaps look-alike parts counts, one that gives a
    start group an end group the best pairing gave to another start group. Without masks the
    pairing only proposes motions, and the motion layers weigh every proposal over all the moved
    points; a runner-up that pairs a part with an end piece nothing else took (the real laptop's
    lid with the arm that closed it, by a 128 deg turn) is already decided there, while a swap of
    twins stays ambiguous after it (their motions explain each other's points alike). Measured:
    the real laptop in a world turned 300 deg about the vertical read confidence 0.37 for a lid
    0.2 deg off (revealed_pieces/summary.txt)."""
    def describe(pair: tuple[int, int]) -> dict:
        c = candidates[pair]
        angle, shift = motion_size(c.transform)
        return {"start_group": c.i, "end_group": c.j, "score": round(c.score, 4), "physics": round(c.physics, 4),
                "slide": round(c.slide, 4),
                "mask": c.mask, "rotation_deg": round(angle, 3), "translation": round(shift, 6),
                "transform": np.round(c.transform, 9).tolist()}

    result = {"pairing": {"cost": round(assignment.cost, 6), "pairs": [describe(p) for p in assignment.pairs]},
              "confidence": {}, "runner_up": {}}
    confidence = {part: 1.0 for part in part_of_pair.values() if part > 0}
    if assignment.runner_up is not None:
        margin = assignment.margin
        result["pairing"]["runner_up"] = [describe(p) for p in assignment.runner_up]
        result["pairing"]["runner_up_cost"] = round(assignment.runner_up_cost, 6)
        result["pairing"]["margin"] = round(margin, 6)
        changed = [p for p in assignment.pairs if p not in assignment.runner_up]
        taken = {p[1]: p[0] for p in assignment.pairs}     # end group -> its start group in the best pairing
        swapped = {q[0] for q in assignment.runner_up if q not in assignment.pairs and taken.get(q[1], q[0]) != q[0]}
        affected = sorted({part_of_pair[p] for p in changed
                           if part_of_pair.get(p, 0) > 0 and (not swaps_only or p[0] in swapped)})
        for p in changed:
            part = part_of_pair.get(p, 0)
            if part <= 0:
                continue
            other = next((q for q in assignment.runner_up if q[0] == p[0]), None)
            if other is not None:
                result["runner_up"][part] = describe(other)
        if margin < AMBIGUITY_MARGIN and affected:
            level = max(0.3, margin / AMBIGUITY_MARGIN)
            for part in affected:
                confidence[part] = min(confidence.get(part, 1.0), level)
            warnings.append(f"ambiguous pairing of look-alike parts: part(s) {', '.join(map(str, affected))} could "
                            f"also pair the other way round (cost margin {margin:.3f} < {AMBIGUITY_MARGIN}); "
                            "confidence lowered, runner-up kept in the labeler diagnostics")
    result["confidence"] = confidence
    result["voxel"] = voxel
    return result


def _to_full(labels: PartLabels, start: LabelledCloud, end: LabelledCloud, start_map: np.ndarray,
             end_map: np.ndarray, has_masks: bool) -> PartLabels:
    """Carry work-cloud labels to every point: through the segment maps with masks, else through
    each point's voxel representative."""
    if has_masks and labels.start_segment_to_part:
        labels.start_part = _points_to_parts(start.segment, labels.start_segment_to_part)
        labels.end_part = _points_to_parts(end.segment, labels.end_segment_to_part)
    else:
        labels.start_part = labels.start_part[start_map]
        labels.end_part = labels.end_part[end_map]
    return labels


def _refine_on_full(labels: PartLabels, start: LabelledCloud, end: LabelledCloud,
                    config: RuleLabelerConfig) -> None:
    """Every movable part's motion (and its alternatives) refined on the part's points of the FULL
    clouds (ICP from the labeler's motion, with colour, up to ``FULL_POLISH_POINTS`` per state).

    The pair search and the part's final registration work on the voxel work clouds with at most
    ``POLISH_POINTS`` per state; the joint fit starts from this motion and is sensitive to it
    (measured: a dishwasher rack's seed 0.4 deg and 5 mm off gave a 1.3 deg axis, the refined one
    0.19 deg). The refinement is kept only when it stays in its basin (turns the motion by at most
    ``DISTINCT_MOTION_DEG``) and does not fit the part's points worse (:func:`_fit_share` drops by
    at most ``REFINE_SHARE_SLACK``); parts with fewer than ``FULL_POLISH_MIN_POINTS`` points in a
    state keep their motion (ICP on a few hundred points of a thin rack drifts along it). Results
    are rounded to 1e-10 (reproducible despite open3d's threaded sums). O(P log P) per part."""
    from sparseart.geometry.icp import register_rigid
    from sparseart.geometry.transforms import rotation_angle

    def refine(transform: np.ndarray, source: np.ndarray, target: np.ndarray, colours: dict) -> np.ndarray:
        try:
            result = register_rigid(source, target, init=transform, max_points=FULL_POLISH_POINTS,
                                    seed=config.seed, **colours).transform
        except ValueError:
            return transform
        turn = np.degrees(rotation_angle(result[:3, :3] @ transform[:3, :3].T))
        if not (np.all(np.isfinite(result)) and turn <= DISTINCT_MOTION_DEG):
            return transform
        before, after = _fit_share(transform, source, target), _fit_share(result, source, target)
        return result if after >= before - REFINE_SHARE_SLACK else transform

    for spec in labels.parts:
        if spec.role != "movable" or spec.id not in labels.initial_motion:
            continue
        s_rows = np.flatnonzero(labels.start_part == spec.id)
        e_rows = np.flatnonzero(labels.end_part == spec.id)
        if min(len(s_rows), len(e_rows)) < FULL_POLISH_MIN_POINTS:
            continue
        source, target = start.points[s_rows], end.points[e_rows]
        colours = dict(source_colors=start.colors[s_rows], target_colors=end.colors[e_rows])
        labels.initial_motion[spec.id] = refine(labels.initial_motion[spec.id], source, target, colours)
        if spec.id in labels.alternative_motions:
            labels.alternative_motions[spec.id] = [refine(m, source, target, colours)
                                                   for m in labels.alternative_motions[spec.id]]
    # open3d's threaded sums differ in the last bits from run to run: snap them off (1e-10 is far
    # below any registration's accuracy) so the labels stay reproducible.
    labels.initial_motion = {k: np.round(v, 10) for k, v in labels.initial_motion.items()}
    labels.alternative_motions = {k: [np.round(m, 10) for m in v] for k, v in labels.alternative_motions.items()}


def _fit_share(transform: np.ndarray, source: np.ndarray, target: np.ndarray) -> float:
    """How well a motion lays a part's start points onto its end points: the symmetric share
    within 1.5 x the part's own median spacing (tight: a grid bias of a fraction of a voxel shows).
    O((N + M) log(N + M))."""
    rng = np.random.default_rng(0)
    source = source[random_subset(len(source), 4000, rng)]
    target = target[random_subset(len(target), 4000, rng)]
    distance = 1.5 * max(median_spacing(source, sample=2000, rng=rng), median_spacing(target, sample=2000, rng=rng))
    moved = apply(transform, source)
    forward = cKDTree(target).query(moved, k=1, distance_upper_bound=distance)[0] < distance
    backward = cKDTree(moved).query(target, k=1, distance_upper_bound=distance)[0] < distance
    return float((forward.sum() + backward.sum()) / (len(forward) + len(backward)))


def _object_consistency(labels: PartLabels, work_start: LabelledCloud, work_end: LabelledCloud,
                        start_map: np.ndarray, end_views: StateViews, warnings: list[str]) -> dict:
    """Whole-object check: every part's start points moved by its motion (static: staying put)
    against the end views. Per part: the share the views confirm (a surface at the predicted
    depth) and the share they contradict (seen through), among the points they can judge."""
    if not end_views:
        return {}
    work_part = np.full(len(work_start), -1, dtype=np.int64)
    work_part[start_map] = labels.start_part
    result = {}
    for spec in labels.parts:
        rows = np.flatnonzero(work_part == spec.id)
        if len(rows) == 0:
            continue
        rows = rows[:: max(1, len(rows) // 2000)]
        transform = labels.initial_motion.get(spec.id, np.eye(4)) if spec.role == "movable" else np.eye(4)
        verdict = end_views.classify(apply(transform, work_start.points[rows]))
        judged = max(int(np.sum(verdict != 0)), 1)
        confirmed = float(np.sum(verdict == CONSISTENT) / judged)
        contradicted = float(np.sum(verdict == VIOLATION) / judged)
        result[spec.id] = {"confirmed": round(confirmed, 4), "contradicted": round(contradicted, 4),
                           "judged_share": round(judged / len(rows), 4)}
        if spec.role == "movable" and contradicted > VIOLATION_WARN_SHARE:
            warnings.append(f"part {spec.id}: its motion puts {contradicted:.0%} of its visible start points where "
                            "the end views see through (the pairing or the motion may be wrong)")
    return result


def _attach(labels: PartLabels, diagnostics: dict) -> None:
    """Store the diagnostics and the per-part pairing confidence on the labels (the lower of it
    and any trust the labels already state, e.g. a part laid only on revealed surfaces)."""
    labels.diagnostics = diagnostics
    confidence = dict(diagnostics.get("confidence", {}))
    for part, value in labels.confidence.items():
        confidence[part] = min(confidence.get(part, 1.0), value)
    labels.confidence = confidence
