"""Unit tests of the labeler's free-space consistency, pair costs and assignment (issue 18)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sparseart.geometry.free_space import CONSISTENT, HIDDEN, VIOLATION, state_views, visible_fraction
from sparseart.geometry.sweep import Screw
from sparseart.labelers.correspondence import (Assignment, Group, PairCandidate, assign,
                                               distinct_by_masks, mask_agreement, prefer_small_turns)
from sparseart.labelers.rules import _downsample
from sparseart.geometry.planes import manhattan_frame
from sparseart.types import Camera, Frame, LabelledCloud, Scene

K = np.array([[100.0, 0.0, 39.5], [0.0, 100.0, 29.5], [0.0, 0.0, 1.0]])


def _wall_scene(depth_m: float = 2.0, cam_to_world: np.ndarray | None = None) -> tuple[Scene, LabelledCloud]:
    """One 80x60 view of a wall ``depth_m`` in front of the camera, with its cloud in the world frame."""
    cam_to_world = np.eye(4) if cam_to_world is None else cam_to_world
    depth = np.full((60, 80), depth_m)
    depth[:, :10] = 0.0                          # nothing seen on the left edge (background)
    frame = Frame(state="end", index=0, rgb_path=Path("end/rgb/000.png"), rgb=np.zeros((60, 80, 3), np.uint8),
                  depth=depth, camera=Camera(K=K, width=80, height=60, cam_to_world=cam_to_world))
    v, u = np.nonzero(depth > 0)
    z = depth[v, u]
    camera_points = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    world = camera_points @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]
    n = len(world)
    cloud = LabelledCloud(state="end", points=world, colors=np.zeros((n, 3)), segment=np.full(n, -1),
                          frame_index=np.zeros(n, np.int64), pixel_index=(v * 80 + u).astype(np.int64),
                          confidence=np.ones(n))
    scene = Scene(root=Path("."), start=[], end=[frame])
    return scene, cloud


@pytest.mark.parametrize("moved", [False, True])
def test_views_tell_seen_surface_free_space_and_hidden(moved):
    """A point on the wall is consistent, one in front of it (seen through) a violation, one behind
    it hidden; the camera is recovered from the cloud, wherever the world frame puts it."""
    pose = np.eye(4)
    if moved:
        angle = np.radians(30.0)
        pose[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
        pose[:3, 3] = [0.3, -0.2, 1.0]
    scene, cloud = _wall_scene(cam_to_world=pose)
    views = state_views(cloud, scene, margin=0.05)
    assert len(views.views) == 1
    camera_points = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0], [0.0, 0.0, 3.0], [-0.365, 0.0, 1.0], [50.0, 0, 1.0]])
    world = camera_points @ pose[:3, :3].T + pose[:3, 3]
    labels = views.classify(world)
    assert labels.tolist() == [CONSISTENT, VIOLATION, HIDDEN, VIOLATION, HIDDEN]


def test_no_scene_means_no_views_and_plain_overlap():
    _, cloud = _wall_scene()
    views = state_views(cloud, None, margin=0.05)
    assert not views
    hits = np.array([True, False, False, False])
    # Hidden points do not count, but the denominator is at least 40 % of the points.
    assert visible_fraction(np.array([HIDDEN] * 4), hits) == pytest.approx(1 / 1.6)
    assert visible_fraction(np.array([CONSISTENT, VIOLATION, VIOLATION, VIOLATION]), hits) == pytest.approx(0.25)


def _cloud(segment_source: dict[int, tuple[int, int]]) -> LabelledCloud:
    return LabelledCloud(state="start", points=np.zeros((0, 3)), colors=np.zeros((0, 3)),
                         segment=np.zeros(0, np.int64), frame_index=np.zeros(0, np.int64),
                         pixel_index=np.zeros(0, np.int64), confidence=np.zeros(0), segment_source=segment_source)


def test_mask_ids_used_only_when_they_agree_across_images():
    start = _cloud({1: (0, 1), 65537: (1, 1), 2: (0, 2), 65538: (1, 2), 3: (0, 3)})
    end = _cloud({1: (0, 1), 2: (0, 3), 3: (0, 2)})
    start_groups = [Group([1, 65537], np.arange(3)), Group([2, 65538], np.arange(3)), Group([3], np.arange(3))]
    end_groups = [Group([1], np.arange(3)), Group([2], np.arange(3)), Group([3], np.arange(3))]
    agreement = mask_agreement(start, end, start_groups, end_groups)
    assert agreement.tolist() == [[1, -1, -1], [-1, -1, 1], [-1, 1, -1]]
    # One merged mask (a group with two ids): that group has no say, the others keep theirs, and
    # the ids both states agree on mark distinct parts.
    merged = _cloud({1: (0, 1), 65537: (1, 7), 2: (0, 2), 65538: (1, 2), 3: (0, 3)})
    agreement = mask_agreement(merged, end, start_groups, end_groups)
    assert agreement.tolist() == [[0, 0, 0], [-1, -1, 1], [-1, 1, -1]]
    assert distinct_by_masks(start_groups[1], start_groups[2]) and not distinct_by_masks(start_groups[0], start_groups[1])
    # Scrambled ids: most groups carry several ids -> no agreement at all.
    scrambled = _cloud({1: (0, 1), 65537: (1, 7), 2: (0, 2), 65538: (1, 5), 3: (0, 3)})
    assert mask_agreement(scrambled, end, start_groups, end_groups) is None


def _candidate(i: int, j: int, score: float, moved: bool = True) -> PairCandidate:
    transform = np.eye(4)
    if moved:
        transform[0, 3] = 0.3
    return PairCandidate(i, j, transform, score, identity=0.0, travel=0.3 if moved else 0.0)


def test_assignment_keeps_a_runner_up_and_its_cost_margin():
    """Two twins that pair either way at nearly equal cost: the runner-up swaps them and the
    margin is small; a clear winner leaves a large margin."""
    candidates = {(0, 0): _candidate(0, 0, 0.99, moved=False),
                  (1, 1): _candidate(1, 1, 0.90), (2, 2): _candidate(2, 2, 0.90),
                  (1, 2): _candidate(1, 2, 0.89), (2, 1): _candidate(2, 1, 0.89)}
    moving = {(1, 1), (2, 2), (1, 2), (2, 1)}
    result = assign(candidates, 3, 3, diameter=1.0, match_min_score=0.3, moving=moving)
    assert isinstance(result, Assignment)
    assert result.pairs == [(0, 0), (1, 1), (2, 2)]
    assert sorted(result.runner_up) == [(0, 0), (1, 2), (2, 1)]
    assert result.margin == pytest.approx(0.02, abs=1e-9)
    candidates[(1, 2)].physics = candidates[(2, 1)].physics = 0.3    # the swap pushes into a neighbour
    clear = assign(candidates, 3, 3, diameter=1.0, match_min_score=0.3, moving=moving)
    assert clear.pairs == [(0, 0), (1, 1), (2, 2)] and clear.margin > 0.5


def test_small_turn_wins_a_tie():
    flip = np.eye(4)
    flip[:3, :3] = np.diag([1.0, -1.0, -1.0])
    turn = np.eye(4)
    turn[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    assert prefer_small_turns([(0.71, flip), (0.68, turn)])[1] is turn
    assert prefer_small_turns([(0.90, flip), (0.68, turn)])[1] is flip
    assert prefer_small_turns([]) == (-1.0, None)


def test_screw_interpolation_reaches_the_motion_and_its_inverse():
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec([0.2, -0.5, 0.9]).as_matrix()
    transform[:3, 3] = [0.3, -0.1, 0.4]
    np.testing.assert_allclose(Screw(transform).at(1.0), transform, atol=1e-9)
    np.testing.assert_allclose(Screw(transform, -1.0).at(1.0), np.linalg.inv(transform), atol=1e-9)
    half = Screw(transform).at(0.5)
    np.testing.assert_allclose(half @ half, transform, atol=1e-9)
    slide = np.eye(4)
    slide[:3, 3] = rng.normal(size=3)
    np.testing.assert_allclose(Screw(slide).at(0.25)[:3, 3], 0.25 * slide[:3, 3])


def test_manhattan_frame_finds_a_turned_box():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    faces = []
    for axis in range(3):
        for side in (-0.5, 0.5):
            face = rng.uniform(-0.5, 0.5, size=(1500, 3)) * [1.0, 0.6, 0.8]
            face[:, axis] = side * [1.0, 0.6, 0.8][axis]
            faces.append(face)
    rotation = Rotation.from_rotvec([0.3, 0.5, -0.2]).as_matrix()
    box = np.concatenate(faces) @ rotation.T
    frame = manhattan_frame(box)
    np.testing.assert_allclose(np.abs(frame.T @ rotation).max(axis=1), 1.0, atol=0.02)


def test_downsample_keeps_segments_and_maps_every_point():
    rng = np.random.default_rng(2)
    n = 5000
    points = rng.uniform(0, 1, size=(n, 3))
    segment = (points[:, 0] > 0.5).astype(np.int64)
    cloud = LabelledCloud(state="start", points=points, colors=np.zeros((n, 3)), segment=segment,
                          frame_index=np.zeros(n, np.int64), pixel_index=np.arange(n), confidence=np.ones(n))
    work, mapping = _downsample(cloud, 0.1)
    assert len(work) < n and mapping.shape == (n,)
    assert np.all(work.segment[mapping] == segment)
    assert np.all(np.abs(work.points[mapping] - points) <= 0.1 * np.sqrt(3) + 1e-12)
    same, identity = _downsample(cloud, 0.0)
    assert same is cloud and np.array_equal(identity, np.arange(n))


def test_a_small_part_seen_in_two_views_counts_with_both():
    """The share floor applies to the merged group: a lever of 60 + 70 points in two views of a
    cloud whose floor is 100 points (0.2 % of 50k) forms one group; one 60-point view alone does not."""
    from sparseart.labelers.rules import RuleLabelerConfig, _merge_across_frames

    rng = np.random.default_rng(0)
    body = rng.uniform(-1, 1, size=(49870, 3))
    lever = rng.uniform(-0.02, 0.02, size=(130, 3)) + [2.0, 0.0, 0.0]
    points = np.concatenate([body, lever])
    segment = np.concatenate([np.ones(49870, np.int64), np.full(60, 2), np.full(70, 65538)])
    frame = np.concatenate([np.zeros(49870, np.int64), np.zeros(60, np.int64), np.ones(70, np.int64)])
    cloud = LabelledCloud(state="end", points=points, colors=np.zeros_like(points), segment=segment,
                          frame_index=frame, pixel_index=np.arange(len(points)), confidence=np.ones(len(points)),
                          segment_source={1: (0, 1), 2: (0, 2), 65538: (1, 2)})
    groups = _merge_across_frames(cloud, segment, 0.01, RuleLabelerConfig(), np.random.default_rng(0))
    assert sorted(g.segments for g in groups) == [[1], [2, 65538]]
    alone = segment.copy()
    alone[-70:] = -1
    groups = _merge_across_frames(cloud, alone, 0.01, RuleLabelerConfig(), np.random.default_rng(0))
    assert [g.segments for g in groups] == [[1]]


def _two_view_cloud(state: str, parts: list[tuple[np.ndarray, int, int]]) -> LabelledCloud:
    """A cloud of (points, frame, mask id) pieces; segment id = frame * 65536 + mask id."""
    points = np.concatenate([p for p, _, _ in parts])
    segment = np.concatenate([np.full(len(p), f * 65536 + i, np.int64) for p, f, i in parts])
    frame = np.concatenate([np.full(len(p), f, np.int64) for p, f, _ in parts])
    return LabelledCloud(state=state, points=points, colors=np.zeros_like(points), segment=segment,
                         frame_index=frame, pixel_index=np.arange(len(points)), confidence=np.ones(len(points)),
                         segment_source={f * 65536 + i: (f, i) for _, f, i in parts})


def test_named_mask_ids_keep_touching_parts_apart_and_unpaired():
    """Masks whose ids agree across images name parts. A ragged mask of one rack that bleeds over
    its touching neighbour in another view merges the two racks by overlap when the ids are not
    trusted; with named ids they stay two groups. A rack too small to form a group in one state
    still owns its id: no other rack's group may pair with it. Ids drawn per image name nothing."""
    from sparseart.labelers.correspondence import named_mask_ids, pair_cost
    from sparseart.labelers.rules import RuleLabelerConfig, _merge_across_frames

    rng = np.random.default_rng(0)

    def slab(x0: float, n: int = 400) -> np.ndarray:
        return np.column_stack([rng.uniform(x0, x0 + 1.0, n), rng.uniform(0, 1, n), np.zeros(n)])

    start = _two_view_cloud("start", [(slab(-2.0), 0, 1), (slab(-2.0), 1, 1), (slab(0.0), 0, 2),
                                      (slab(0.6), 1, 3), (slab(3.0, 10), 0, 4)])
    end = _two_view_cloud("end", [(slab(-2.0), 0, 1), (slab(0.0), 0, 2), (slab(1.0), 1, 3), (slab(3.0), 0, 4)])
    named = named_mask_ids(start, end)
    assert named == {1, 2, 3, 4}
    config, radius = RuleLabelerConfig(), 0.05
    merged = _merge_across_frames(start, start.segment, radius, config, np.random.default_rng(0))
    assert [2, 65539] in [g.segments for g in merged]
    start_groups = _merge_across_frames(start, start.segment, radius, config, np.random.default_rng(0), named)
    assert sorted(g.segments for g in start_groups) == [[1, 65537], [2], [65539]]
    end_groups = _merge_across_frames(end, end.segment, radius, config, np.random.default_rng(0), named)
    mask_agreement(start, end, start_groups, end_groups, named)
    rack_3 = next(g for g in start_groups if g.segments == [65539])
    rack_4_end = next(g for g in end_groups if g.segments == [4])
    assert rack_4_end.mask_ids == {4}       # id 4 has no start group (10 points), yet it is named
    assert distinct_by_masks(rack_3, rack_4_end)
    conflict = PairCandidate(0, 0, np.eye(4), score=0.9, identity=0.1, named_conflict=True)
    assert pair_cost(conflict, 1.0, 0.3) >= 1e3
    # Ids drawn per image (scrambled): nothing is named.
    scrambled = _two_view_cloud("end", [(slab(-2.0), 0, 17), (slab(0.0), 0, 404), (slab(1.0), 1, 3)])
    assert named_mask_ids(start, scrambled) == frozenset()
    # A per-image segmenter numbers its segments 1..k in every image: the ids repeat in both
    # states but mark different places in different images -> nothing is named.
    numbered = _two_view_cloud("start", [(slab(-2.0), 0, 1), (slab(0.0), 0, 2), (slab(3.0), 0, 3),
                                         (slab(3.0), 1, 1), (slab(-2.0), 1, 2), (slab(0.0), 1, 3)])
    assert named_mask_ids(numbered, end) == frozenset()
