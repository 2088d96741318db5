"""The default part labeler: rigid-motion consistency, no model needed.

Steps (both clouds in one frame):

1. Segments: mask segments when the scene has masks; otherwise one motion-based split (points of
   one state farther than a radius from the other state's cloud are "moving", clustered into
   connected pieces; the rest is static).
2. Within a state, segments from different images that cover the same surface are merged (mask ids
   need not agree across images).
3. Across states, every start group is registered rigidly to every end group; Hungarian matching on
   the registration cost pairs them. A pair whose best motion is the identity is static.
4. Moving pairs whose motions agree (one pair's motion carries another pair's start points onto its
   end points) are merged into one part. Each part gets its start->end motion as evidence and a
   joint-type prior read off the rotation angle.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from sparseart.geometry.sampling import random_subset
from ..types import LabelledCloud, PartLabels, PartSpec, Scene

STATIC_ANGLE_DEG = 1.0          # a matched pair moving less than this and ...
STATIC_SHIFT_RADII = 1.5        # ... less than this many inlier radii is static
REVOLUTE_PRIOR_DEG = 10.0       # rotation above this: revolute prior
PRISMATIC_PRIOR_DEG = 2.0       # rotation below this: prismatic prior (in between: no prior)
DISTINCT_MOTION_DEG = 5.0       # registered motions further apart than this are real alternatives
IDENTITY_TRUSTED_SCORE = 0.6   # identity overlap above which "stayed put" is preferred on near-ties
ADJACENT_RADII = 3.0           # groups closer than this many inlier radii touch (may be one part)
TRAVEL_PENALTY = 0.25  # score units per object diameter a pairing moves its points (tie-breaker)
IDENTITY_PREFERENCE = 0.05      # a motion must beat "stayed put" by this overlap share to be taken


@dataclass
class RuleLabelerConfig:
    """Tuning of the rule-based labeler. Radii are multiples of the measured point spacing."""

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
    seed: int = 0


@dataclass
class _Group:
    """Merged segments of one state: the segment ids and (sub-sampled) point indices."""

    segments: list[int]
    indices: np.ndarray
    part: int = -1
    extra: dict = field(default_factory=dict)


class RuleBasedLabeler:
    """Static vs movable by rigid-motion consistency; see the module docstring."""

    name = "rules"

    def __init__(self, config: RuleLabelerConfig | None = None) -> None:
        self.config = config or RuleLabelerConfig()

    # ------------------------------------------------------------------ public

    def label(self, start: LabelledCloud, end: LabelledCloud, scene: Scene | None = None,
              aligned: bool = True, motion_hints: list[np.ndarray] | None = None) -> PartLabels:
        """Label parts. O(G_s G_e (R + H S log M)) with G groups per state, R one registration of
        <= ``max_points_per_segment`` points, H motion hints scored on S samples, plus O(N log N)
        KD-tree work.

        motion_hints: (4, 4) start->end rigid motions (scene frame) that another stage found, e.g.
            the feature alignment's candidate moving parts; each is tried as one more hypothesis
            for every pair of segment groups (a hint that explains a pair better than the pair's own
            registration is polished by ICP and kept).
        """
        if len(start) < 10 or len(end) < 10:
            raise ValueError("too few valid points to label parts (need at least 10 per state)")
        config = self.config
        rng = np.random.default_rng(config.seed)
        spacing = max(_median_spacing(start.points, rng), _median_spacing(end.points, rng))
        radius = config.inlier_radius_spacings * spacing
        warnings: list[str] = []
        has_masks = bool(np.any(start.segment >= 0) and np.any(end.segment >= 0))
        if has_masks:
            start_segments, end_segments = start.segment, end.segment
        else:
            start_segments, end_segments = _motion_split(start, end, config.motion_radius_spacings * spacing,
                                                         spacing)
            warnings.append("no masks: parts come from a motion-based split (points that moved)")
            config = replace(config, min_segment_share=max(config.min_segment_share,
                                                           config.motion_piece_min_share))
        start_groups = _merge_across_frames(start, start_segments, radius, config, rng)
        end_groups = _merge_across_frames(end, end_segments, radius, config, rng)
        if not start_groups or not end_groups:
            raise ValueError("no usable segments in one of the states (masks empty after filtering)")
        identity_scores: dict[tuple[int, int], float] = {}
        pairs, extras = _match_groups(start, end, start_groups, end_groups, radius, config, warnings,
                                      motion_hints or [], identity_scores)
        return _assign_parts(start, end, start_segments, end_segments, start_groups, end_groups, pairs,
                             extras, radius, config, warnings, motion_split=not has_masks,
                             identity_scores=identity_scores)


# ---------------------------------------------------------------------- helpers


def _median_spacing(points: np.ndarray, rng: np.random.Generator, sample: int = 4000) -> float:
    """Median nearest-neighbour distance of a cloud, from a random sample. O(N log N)."""
    tree = cKDTree(points)
    query = points[rng.choice(len(points), size=min(sample, len(points)), replace=False)]
    distances, _ = tree.query(query, k=2)
    spacing = float(np.median(distances[:, 1]))
    return spacing if spacing > 0 else float(np.ptp(points, axis=0).max() * 1e-3 + 1e-12)


def _motion_split(start: LabelledCloud, end: LabelledCloud, radius: float,
                  spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Pseudo-segments without masks: 0 = stayed put, 1..k = connected pieces of moved points."""
    result = []
    for cloud, other in ((start, end), (end, start)):
        distance, _ = cKDTree(other.points).query(cloud.points, k=1)
        segments = np.zeros(len(cloud), dtype=np.int64)
        moved = np.flatnonzero(distance > radius)
        if len(moved):
            labels = _connected_pieces(cloud.points[moved], 3.0 * spacing)
            segments[moved] = labels + 1
        result.append(segments)
    return result[0], result[1]


def _connected_pieces(points: np.ndarray, link_radius: float) -> np.ndarray:
    """Connected components of the radius graph (label per point, 0..k-1). O(N log N)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pairs = cKDTree(points).query_pairs(link_radius, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points),) * 2)
    _, labels = connected_components(graph, directed=False)
    return labels.astype(np.int64)


def _merge_across_frames(cloud: LabelledCloud, segments: np.ndarray, radius: float,
                         config: RuleLabelerConfig, rng: np.random.Generator) -> list[_Group]:
    """Union segments of different frames that cover the same surface. O(S^2 P log P)."""
    ids, counts = np.unique(segments[segments >= 0], return_counts=True)
    minimum = max(config.min_segment_points, config.min_segment_share * len(cloud))
    kept = [int(i) for i, c in zip(ids, counts) if c >= minimum]
    members = {s: np.flatnonzero(segments == s) for s in kept}
    samples = {s: idx[random_subset(len(idx), config.max_points_per_segment, rng)]
               for s, idx in members.items()}
    trees = {s: cKDTree(cloud.points[samples[s]]) for s in kept}
    frame_of = {s: int(cloud.frame_index[members[s][0]]) for s in kept}
    parent = {s: s for s in kept}

    def find(s: int) -> int:
        while parent[s] != s:
            parent[s] = parent[parent[s]]
            s = parent[s]
        return s

    for i, a in enumerate(kept):
        for b in kept[i + 1:]:
            if frame_of[a] == frame_of[b]:
                continue
            overlap_ab = np.mean(trees[b].query(cloud.points[samples[a]], k=1)[0] < radius)
            overlap_ba = np.mean(trees[a].query(cloud.points[samples[b]], k=1)[0] < radius)
            if max(overlap_ab, overlap_ba) >= config.merge_overlap:
                parent[find(a)] = find(b)
    groups: dict[int, list[int]] = {}
    for s in kept:
        groups.setdefault(find(s), []).append(s)
    result = []
    for segs in groups.values():
        indices = np.concatenate([members[s] for s in segs])
        result.append(_Group(segments=sorted(segs), indices=indices))
    result.sort(key=lambda g: -len(g.indices))
    return result


def _group_sample(group: _Group, limit: int, rng: np.random.Generator) -> np.ndarray:
    """Indices (into the state's cloud) of at most ``limit`` random points of a group."""
    return group.indices[random_subset(len(group.indices), limit, rng)]


def _overlap(moved: np.ndarray, target_tree: cKDTree, radius: float) -> float:
    return float(np.mean(target_tree.query(moved, k=1)[0] < radius))


def _apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ transform[:3, :3].T + transform[:3, 3]


def _match_groups(start: LabelledCloud, end: LabelledCloud, start_groups: list[_Group],
                  end_groups: list[_Group], radius: float, config: RuleLabelerConfig,
                  warnings: list[str], motion_hints: list[np.ndarray] = (),
                  identity_scores: dict[tuple[int, int], float] | None = None,
                  ) -> tuple[list[tuple[int, int, np.ndarray, float]], list[tuple[str, int, int]]]:
    """Register every start group to every end group and pair them by Hungarian matching.
    ``identity_scores`` (if given) receives the "stayed put" score of every scored (i, j).

    Returns the pairs (start group, end group, start->end transform (4, 4), score in [0, 1]) and
    the extras (state, group, partner group in the other state) for groups left over.
    """
    from sparseart.geometry.icp import register_rigid

    rng = np.random.default_rng(config.seed + 1)
    start_samples = [_group_sample(g, config.max_points_per_segment, rng) for g in start_groups]
    end_samples = [_group_sample(g, config.max_points_per_segment, rng) for g in end_groups]
    # Overlaps are measured against every point of a group (a sub-sample would be too sparse for
    # the inlier radius); the backward direction maps end samples back into the start tree.
    start_trees = [cKDTree(start.points[g.indices]) for g in start_groups]
    end_trees = [cKDTree(end.points[g.indices]) for g in end_groups]
    scores = np.zeros((len(start_groups), len(end_groups)))
    travel = np.zeros_like(scores)
    diameter = max(float(np.linalg.norm(np.ptp(start.points, axis=0))), 1e-12)
    transforms: dict[tuple[int, int], np.ndarray] = {}
    for i, s_idx in enumerate(start_samples):
        source = start.points[s_idx]
        for j, e_idx in enumerate(end_samples):
            size_ratio = len(start_groups[i].indices) / max(len(end_groups[j].indices), 1)
            if size_ratio > 20 or size_ratio < 0.05:
                continue
            target = end.points[e_idx]
            # "Stayed put" is judged first and preferred on a near-tie: a registration on few points
            # can slide a surface along itself and call a static segment moving.
            trees = (start_trees[i], end_trees[j])
            colours = (start.colors[s_idx], end.colors[end_groups[j].indices])
            best_score, best_transform = _pair_score(np.eye(4), source, target, trees, colours, radius), np.eye(4)
            if identity_scores is not None:
                identity_scores[(i, j)] = best_score
            registration = register_rigid(source, target, max_points=config.pair_registration_points,
                                          use_fpfh=False, seed=config.seed)
            score = _pair_score(registration.transform, source, target, trees, colours, radius)
            transform = registration.transform
            if motion_hints:
                hint_scores = [_pair_score(h, source, target, trees, colours, radius) for h in motion_hints]
                best_hint = int(np.argmax(hint_scores))
                if hint_scores[best_hint] > score:
                    polished = register_rigid(source, target, init=motion_hints[best_hint],
                                              max_points=config.pair_registration_points, seed=config.seed)
                    polished_score = _pair_score(polished.transform, source, target, trees, colours, radius)
                    score, transform = max((hint_scores[best_hint], motion_hints[best_hint]),
                                           (polished_score, polished.transform), key=lambda st: st[0])
            # The preference protects well-seen static surfaces; a weak identity overlap (a part
            # mostly hidden in one state, whose visible edge happens to land on itself) earns none.
            preference = IDENTITY_PREFERENCE if best_score >= IDENTITY_TRUSTED_SCORE else 0.0
            if score > best_score + preference:
                best_score, best_transform = score, transform
            scores[i, j] = best_score
            transforms[(i, j)] = best_transform
            travel[i, j] = float(np.median(np.linalg.norm(_apply(best_transform, source) - source, axis=1)))
    # Identical sibling parts (an oven's racks) register onto each other as well as onto
    # themselves; the pairing that moves the parts less is the articulated one.
    rows, cols = linear_sum_assignment(-scores + TRAVEL_PENALTY * travel / diameter)
    chosen = {(int(i), int(j)) for i, j in zip(rows, cols) if scores[i, j] >= config.match_min_score}
    pairs = [(i, j, transforms[(i, j)], float(scores[i, j])) for i, j in sorted(chosen)]
    # Groups left over by the one-to-one matching (a surface seen in two views that did not merge,
    # an over-segmented or fragmented part) follow the part of their best-scoring partner.
    extras: list[tuple[str, int, int]] = []
    for i in range(len(start_groups)):
        if all(p[0] != i for p in chosen) and scores[i].max() >= config.match_min_score:
            extras.append(("start", i, int(np.argmax(scores[i]))))
    for j in range(len(end_groups)):
        if all(p[1] != j for p in chosen) and scores[:, j].max() >= config.match_min_score:
            extras.append(("end", j, int(np.argmax(scores[:, j]))))
    attached = {(state, k) for state, k, _ in extras}
    unmatched = ([f"start group of {len(g.indices)} points" for k, g in enumerate(start_groups)
                  if k not in {p[0] for p in pairs} and ("start", k) not in attached] +
                 [f"end group of {len(g.indices)} points" for k, g in enumerate(end_groups)
                  if k not in {p[1] for p in pairs} and ("end", k) not in attached])
    if unmatched:
        warnings.append("seen in one state only (occluded, moved out of view, or not rigid): "
                        + ", ".join(unmatched) + "; left unassigned")
    return pairs, extras


def _pair_score(transform: np.ndarray, source: np.ndarray, target: np.ndarray,
                trees: tuple[cKDTree, cKDTree], colours: tuple[np.ndarray, np.ndarray], radius: float) -> float:
    """Symmetric overlap of a start group moved by ``transform`` and an end group, times colour
    agreement; in [0, 1].

    source / target: (S, 3) samples of the start / end group; trees: KD-trees over ALL points of
    the start / end group; colours: (S, 3) colours of the source samples and (M, 3) colours of all
    end-group points (the end tree's order). O(S log M).
    """
    start_tree, end_tree = trees
    moved = _apply(transform, source)
    distance, nearest = end_tree.query(moved, k=1)
    forward = float(np.mean(distance < radius))
    inverse = np.linalg.inv(transform)
    backward = _overlap(_apply(inverse, target), start_tree, radius)
    close = distance < radius
    if np.any(close):
        difference = np.abs(colours[0][close] - colours[1][nearest[close]]).mean()
        colour = 1.0 - 0.5 * min(1.0, difference / 0.25)
    else:
        colour = 0.5
    return 0.5 * (forward + backward) * colour


def _motion_size(transform: np.ndarray) -> tuple[float, float]:
    angle = float(np.degrees(np.linalg.norm(Rotation.from_matrix(transform[:3, :3]).as_rotvec())))
    return angle, float(np.linalg.norm(transform[:3, 3]))


STILL_EXPLAINS_SHARE = 0.8  # identity score / best score above which a pair is taken as not moved


def _fallback_base(moving_pairs: list[tuple[int, int, np.ndarray, float]], start_groups: list[_Group],
                   identity_scores: dict[tuple[int, int], float]) -> tuple[int, int, np.ndarray, float]:
    """The static base when no pair passed the static test: the pair that staying put explains
    best relative to its own motion (identity score / pair score >= ``STILL_EXPLAINS_SHARE``; the
    largest such one), else the largest pair (design: the largest consistent set)."""
    def share(pair) -> float:
        return identity_scores.get((pair[0], pair[1]), 0.0) / max(pair[3], 1e-12)

    still = [p for p in moving_pairs if share(p) >= STILL_EXPLAINS_SHARE]
    candidates = still or moving_pairs
    return max(candidates, key=lambda p: len(start_groups[p[0]].indices))


def _assign_parts(start: LabelledCloud, end: LabelledCloud, start_segments: np.ndarray,
                  end_segments: np.ndarray, start_groups: list[_Group], end_groups: list[_Group],
                  pairs: list[tuple[int, int, np.ndarray, float]], extras: list[tuple[str, int, int]],
                  radius: float, config: RuleLabelerConfig, warnings: list[str],
                  motion_split: bool, identity_scores: dict[tuple[int, int], float] | None = None) -> PartLabels:
    """Static pairs -> part 0; moving pairs merged by shared motion -> parts 1..k."""
    rng = np.random.default_rng(config.seed + 2)
    static_pairs, moving_pairs = [], []
    for pair in pairs:
        i, _, transform, _ = pair
        angle, _ = _motion_size(transform)
        centroid = start.points[start_groups[i].indices].mean(axis=0)
        displacement = float(np.linalg.norm(_apply(transform, centroid[None])[0] - centroid))
        static = angle < STATIC_ANGLE_DEG and displacement < STATIC_SHIFT_RADII * radius
        (static_pairs if static else moving_pairs).append(pair)
    if not static_pairs and moving_pairs:
        base = _fallback_base(moving_pairs, start_groups, identity_scores or {})
        moving_pairs.remove(base)
        if (identity_scores or {}).get((base[0], base[1]), 0.0) >= STILL_EXPLAINS_SHARE * base[3]:
            # Noisy depth lowers every overlap; a pair that staying put explains nearly as well as
            # its registered motion did not move (measured: a laptop base at 1 % depth noise,
            # identity 0.33 vs a spurious 80 deg registration 0.38).
            static_pairs.append((base[0], base[1], np.eye(4), base[3]))
            warnings.append("no segment stayed put clearly (noisy depth?); the one that staying put explains "
                            f"nearly as well as any motion (>= {STILL_EXPLAINS_SHARE:.0%}) is taken as the static base")
        else:
            static_pairs.append(base)
            warnings.append("no segment stayed put between the states; the largest one is taken as the "
                            "static base (are the two states in one frame?)")
    # Merge moving pairs that share a motion (over-segmented parts).
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
    ordered = sorted(clusters.values(),
                     key=lambda ks: -sum(len(start_groups[moving_pairs[k][0]].indices) for k in ks))
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
                                                 end_part_indices(members), moving_pairs[best][2], config)
        motions[part_id] = transform
        if alternatives:
            alternative_motions[part_id] = alternatives
        angle, _ = _motion_size(transform)
        if angle >= REVOLUTE_PRIOR_DEG:
            priors[part_id] = "revolute"
        elif angle <= PRISMATIC_PRIOR_DEG:
            priors[part_id] = "prismatic"
        else:
            warnings.append(f"part {part_id}: rotation of {angle:.1f} deg is between "
                            f"{PRISMATIC_PRIOR_DEG} and {REVOLUTE_PRIOR_DEG} deg: joint type is left to the fit")
        parts.append(PartSpec(id=part_id, role="movable", parent=0))
    start_group_part = {i: start_map[start_groups[i].segments[0]] for i, _, _, _ in pairs}
    end_group_part = {j: end_map[end_groups[j].segments[0]] for _, j, _, _ in pairs}
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


def _polish_motion(start: LabelledCloud, end: LabelledCloud, start_indices: np.ndarray,
                   end_indices: np.ndarray, transform: np.ndarray,
                   config: RuleLabelerConfig) -> tuple[np.ndarray, list[np.ndarray]]:
    """A part's start->end motion on all of its points (with colour), and tied alternatives.

    The pair matching registered sub-samples of single groups with cheap hypotheses only; a
    symmetric part (a round door, a box lid) can come out turned the wrong way there. So the full
    global registration (all hypotheses, FPFH fallback) runs on the whole part too, beside the
    pair's motion refined from its own start. The higher inlier fraction is the primary motion;
    the other, when it differs by more than ``DISTINCT_MOTION_DEG``, is returned as an alternative:
    registration inlier fractions do not separate a symmetric part's turns reliably, so the joint
    fit decides (by residual, then by where a hinge can be).
    """
    from sparseart.geometry.icp import register_rigid
    from sparseart.geometry.transforms import rotation_angle

    source, target = start.points[start_indices], end.points[end_indices]
    colours = dict(source_colors=start.colors[start_indices], target_colors=end.colors[end_indices])
    candidates = [register_rigid(source, target, init=transform, seed=config.seed, **colours),
                  register_rigid(source, target, seed=config.seed, **colours)]
    candidates.sort(key=lambda c: -c.inlier_fraction)
    chosen = candidates[0].transform
    alternatives = [c.transform for c in candidates[1:]
                    if np.degrees(rotation_angle(c.transform[:3, :3] @ chosen[:3, :3].T)) > DISTINCT_MOTION_DEG]
    return chosen, alternatives


def _points_to_parts(segments: np.ndarray, mapping: dict[int, int]) -> np.ndarray:
    result = np.full(len(segments), -1, dtype=np.int64)
    for segment, part in mapping.items():
        result[segments == segment] = part
    return result


def _same_motion(start: LabelledCloud, end: LabelledCloud, start_groups: list[_Group],
                 end_groups: list[_Group], pair_a: tuple, pair_b: tuple, radius: float,
                 config: RuleLabelerConfig, rng: np.random.Generator) -> bool:
    """Do two moving pairs belong to one part? They must touch (in either state: pieces of one
    part are adjacent, identical sibling parts such as an oven's racks are not) and either pair's
    motion must carry the other pair's start points onto its end points. O(S log N) per test."""
    (ia, ja, _, _), (ib, jb, _, _) = pair_a, pair_b
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
