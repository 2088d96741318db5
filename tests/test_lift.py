"""RGB-D lifting and mask-to-point label transfer."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sparseart.lift.labels import SEGMENT_STRIDE, build_labelled_cloud, mask_boundary, without_ambiguous_boundaries
from sparseart.lift.rgbd import flying_pixel_mask, pointmap_from_depth
from sparseart.types import Camera, Frame


def _frame(depth: np.ndarray, K: np.ndarray, cam_to_world=None, mask=None, index=0) -> Frame:
    h, w = depth.shape
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 0] = np.arange(w, dtype=np.uint8)[None, :]
    rgb[..., 1] = np.arange(h, dtype=np.uint8)[:, None]
    return Frame(state="start", index=index, rgb_path=Path(f"rgb/{index:03d}.png"), rgb=rgb, depth=depth,
                 mask=mask, camera=Camera(K=K, width=w, height=h, cam_to_world=cam_to_world))


K = np.array([[50.0, 0, 16.5], [0, 60.0, 11.0], [0, 0, 1]])


def test_unprojection_matches_pinhole_and_pose() -> None:
    rng = np.random.default_rng(0)
    depth = 1.0 + 0.001 * rng.random((24, 32))  # smooth enough: no flying pixels
    rotation = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], float)
    cam_to_world = np.eye(4)
    cam_to_world[:3, :3], cam_to_world[:3, 3] = rotation, [1.0, 2.0, 3.0]
    pointmap = pointmap_from_depth(_frame(depth, K, cam_to_world), reject_flying_pixels=False)
    k = 5 * 32 + 7  # row 5, column 7
    camera_point = np.array([(7 - 16.5) / 50.0, (5 - 11.0) / 60.0, 1.0]) * depth[5, 7]
    np.testing.assert_allclose(pointmap.points[k], rotation @ camera_point + [1, 2, 3], atol=1e-12)
    # projecting back with K gives the pixel
    back = np.linalg.solve(rotation, pointmap.points[k] - [1, 2, 3])
    pixel = K @ (back / back[2])
    np.testing.assert_allclose(pixel[:2], [7, 5], atol=1e-9)
    assert pointmap.points.dtype == np.float64 and pointmap.valid.all()


def test_invalid_and_flying_pixels() -> None:
    depth = np.ones((10, 12))
    depth[:, 6:] = 2.0  # a clean depth edge between columns 5 and 6: both sides are kept
    depth[0, 0] = 0.0
    depth[5, 3] = 1.5  # an isolated flying pixel
    depth[2:8, 9] = 1.4  # a 1-pixel line interpolated between surfaces
    depth[2:8, 1:3] = 0.7  # a 2-pixel-wide structure (a wire, a handle) in front: kept
    flags = flying_pixel_mask(depth)
    assert not flags[4, 5] and not flags[4, 6] and not flags[4, 10]
    assert flags[5, 3] and flags[4, 9]
    assert not flags[4, 1] and not flags[4, 2]
    pointmap = pointmap_from_depth(_frame(depth, K))
    assert not pointmap.valid[0] and np.isnan(pointmap.points[0]).all()
    assert not pointmap.valid[5 * 12 + 3] and pointmap.valid[4 * 12 + 5]


def test_label_transfer_row_major() -> None:
    depth = np.ones((12, 16))
    mask = np.zeros((12, 16), np.int64)
    mask[1:11, 1:8] = 3
    mask[1:11, 8:15] = 9
    frame = _frame(depth, K, np.eye(4), mask=mask, index=1)
    pointmap = pointmap_from_depth(frame, reject_flying_pixels=False)
    cloud = build_labelled_cloud("start", [frame], [pointmap], drop_mask_boundaries=False)
    rows, cols = cloud.pixel_index // 16, cloud.pixel_index % 16
    np.testing.assert_array_equal(cloud.colors[:, 0] * 255, cols)
    np.testing.assert_array_equal(cloud.colors[:, 1] * 255, rows)
    expected = np.where(mask[rows, cols] > 0, SEGMENT_STRIDE + mask[rows, cols], -1)
    np.testing.assert_array_equal(cloud.segment, expected)
    assert cloud.segment_source[SEGMENT_STRIDE + 9] == (1, 9)
    cleaned = build_labelled_cloud("start", [frame], [pointmap], drop_mask_boundaries=True)
    boundary = mask_boundary(mask, depth)[rows, cols]
    assert np.all(cleaned.segment[boundary] == -1)
    assert np.all(cleaned.segment[~boundary] == expected[~boundary])


def test_thin_segment_keeps_its_boundary_pixels() -> None:
    """A 2-px wire in front of a body at a smeared (similar) depth: every wire pixel touches the
    body's label, so the boundary rule alone would erase the wire; it keeps its points, while the
    body (a solid segment) still loses its ambiguous rim."""
    depth = np.ones((20, 20))
    mask = np.ones((20, 20), np.int64)
    mask[3:17, 9:11] = 2                      # the wire
    depth[3:17, 9:11] = 0.98                  # smeared: within the 5 % similarity band
    frame = _frame(depth, K, np.eye(4), mask=mask)
    pointmap = pointmap_from_depth(frame, reject_flying_pixels=False)
    cloud = build_labelled_cloud("start", [frame], [pointmap], drop_mask_boundaries=True)
    rows, cols = cloud.pixel_index // 20, cloud.pixel_index % 20
    wire = mask[rows, cols] == 2
    assert np.all(cloud.segment[wire] == 2)               # all 28 wire points keep their id
    rim = (mask[rows, cols] == 1) & ((cols == 8) | (cols == 11)) & (rows >= 3) & (rows < 17)
    assert rim.any() and np.all(cloud.segment[rim] == -1)  # the body's pixels next to it do not
    assert np.all(without_ambiguous_boundaries(mask, depth, np.ones_like(depth, bool), keep_share=0.0)[3:17, 9:11] == 0)


def test_see_through_mask_keeps_only_its_front_layer() -> None:
    """A rack's (ragged) mask also covers the oven wall seen beside its wires, and smeared depth
    puts the wires close to that wall: the thin segment keeps its pixels, but those well behind
    the segment's own nearest depth lose the id; the wires keep it. A solid segment with the same
    depth step (a drawer front with a recess) is left alone."""
    depth = np.full((24, 24), 1.25)
    mask = np.ones((24, 24), np.int64)
    wires = np.zeros((24, 24), bool)
    wires[4:20, 4:20:5] = True                # 1-px vertical wires, smeared towards the wall
    depth[wires] = 1.19                       # 4.8 % in front: within the similar-depth band
    for column in range(4, 20, 5):
        mask[4:20, column - 1:column + 2] = 2  # the mask: each wire and a pixel either side
    # 29 % of this short rack survives the boundary rule: thin at a share of 0.5
    kept = without_ambiguous_boundaries(mask, depth, np.ones_like(depth, bool), keep_share=0.5)
    assert np.all(kept[wires] == 2)
    assert np.all(kept[(mask == 2) & ~wires] == 0)
    solid = np.ones((24, 24), np.int64)
    solid[4:20, 4:20] = 2
    recessed = np.where(solid == 2, 1.0, 1.25)
    recessed[10:14, 10:14] = 1.1              # a recess inside a solid segment: not see-through
    kept = without_ambiguous_boundaries(solid, recessed, np.ones_like(recessed, bool))
    assert np.all(kept[10:14, 10:14] == 2)


def test_segments_of_two_frames_never_collide() -> None:
    depth = np.ones((4, 4))
    mask = np.ones((4, 4), np.int64)
    frames = [_frame(depth, K, np.eye(4), mask=mask, index=i) for i in range(2)]
    pointmaps = [pointmap_from_depth(f, reject_flying_pixels=False) for f in frames]
    cloud = build_labelled_cloud("start", frames, pointmaps, drop_mask_boundaries=False)
    assert len(np.unique(cloud.segment)) == 2


def test_mask_boundary_ignores_depth_edges() -> None:
    mask = np.zeros((6, 6), np.int64)
    mask[:, 3:] = 2
    mask[:, :3] = 1
    flat = np.ones((6, 6))
    stepped = flat.copy()
    stepped[:, 3:] = 2.0
    assert mask_boundary(mask, flat)[:, 2:4].all()
    assert not mask_boundary(mask, stepped).any()
