"""A camera that did not move between the states aligns them (``sparseart.align.still``): the
pixel test tells a still camera from a moved one, and an unposed textureless cabinet without masks,
whose states neither features nor geometry can align, gets its drawers through it."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import REPO_ROOT

from sparseart.align.still import (STILL_MAX_SHIFT_PX, STILL_MIN_SHARE, image_shift, pixel_agreement,
                                   place_through_twins, still_camera, still_pairs, still_tiles)
from sparseart.lift.rgbd import pointmap_from_depth
from sparseart.types import Camera, Frame

TWINS_DIR = REPO_ROOT.parent / "shared" / "data" / "partnet-twins"
requires_twins = pytest.mark.skipif(not TWINS_DIR.is_dir(), reason=f"twin objects not found at {TWINS_DIR}")

K = np.array([[60.0, 0.0, 40.0], [0.0, 60.0, 30.0], [0.0, 0.0, 1.0]])


def _frame(state: str, depth: np.ndarray, rgb: np.ndarray, index: int = 0) -> Frame:
    camera = Camera(K=K, width=depth.shape[1], height=depth.shape[0])
    return Frame(state=state, index=index, rgb_path=Path(f"{state}/rgb/{index:03d}.png"), rgb=rgb, depth=depth,
                 camera=camera)


def _room(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(depth (60, 80) metres, rgb (60, 80, 3) uint8): a wall at 3 m, a box at 1.5 m, texture."""
    rng = np.random.default_rng(seed)
    depth = np.full((60, 80), 3.0)
    depth[20:45, 25:55] = 1.5
    rgb = rng.integers(0, 255, size=(60, 80, 3), dtype=np.uint8)
    return depth, rgb


def _with_maps(frames):
    return [pointmap_from_depth(f) for f in frames]


def test_a_still_camera_agrees_pixel_by_pixel_and_gives_its_depth_scale():
    depth, rgb = _room()
    moved_depth, moved_rgb = depth.copy(), rgb.copy()
    moved_depth[20:45, 25:35] = 1.2           # a door in front of the box opened towards the camera
    moved_rgb[20:45, 25:35] = 30
    start = _frame("start", depth, rgb)
    end = _frame("end", moved_depth / 1.01, moved_rgb)    # the sensor's scale drifted by 1 %
    share, scale = pixel_agreement(start, end, *_with_maps([start, end]))
    assert scale == pytest.approx(1.01, rel=1e-6)
    assert share == pytest.approx(1.0 - 250 / 4800, abs=1e-6)

    # the same room seen from 6 pixels to the side: a camera that moved
    shifted = _frame("end", np.roll(depth, 6, axis=1), np.roll(rgb, 6, axis=1))
    assert pixel_agreement(start, shifted, *_with_maps([start, shifted]))[0] < STILL_MIN_SHARE


def test_the_image_shift_reads_how_far_the_picture_moved():
    _, rgb = _room()
    assert image_shift(rgb, rgb) < 0.1
    moved = np.roll(np.roll(rgb, 3, axis=0), 4, axis=1)
    assert image_shift(rgb, moved) == pytest.approx(5.0, abs=0.5) and image_shift(rgb, moved) > STILL_MAX_SHIFT_PX


def test_a_still_camera_whose_view_a_moved_door_fills_is_told_by_its_tiles():
    """A textured door over 55 % of the picture moved 12 px: the whole picture's shift follows
    the door, the tiles of the room beside it lie still, so the pair is one camera; the room seen
    from 5 px to the side is not, tiles or not."""
    depth, rgb = _room()
    door = np.random.default_rng(1).integers(0, 255, size=(60, 100, 3), dtype=np.uint8)
    closed, opened = rgb.copy(), rgb.copy()
    closed[:, :44], opened[:, :44] = door[:, :44], door[:, 12:56]
    assert image_shift(closed, opened) > STILL_MAX_SHIFT_PX
    assert still_tiles(closed, opened)
    start, end = _frame("start", depth, closed), _frame("end", depth, opened)
    share, _ = pixel_agreement(start, end, *_with_maps([start, end]))
    assert share == pytest.approx(36 / 80, abs=0.02)      # the room beside the door agrees
    # one camera, but its depth is not matched between the states on the margins the door leaves
    start_map, end_map = _with_maps([start, end])
    assert still_pairs([start], [end], [start_map], [end_map]) == {}
    assert still_pairs([start], [start], [start_map], [start_map]) == {0: 0}
    assert not still_tiles(rgb, np.roll(rgb, 5, axis=1))


def test_the_states_are_aligned_through_the_still_view_and_a_left_out_view_through_its_twin():
    depth, rgb = _room()
    start = [_frame("start", depth, rgb, 0), _frame("start", depth, rgb, 1)]
    end = [_frame("end", depth / 1.02, rgb, 0), _frame("end", np.roll(depth, 9, axis=1), np.roll(rgb, 9, axis=1), 1)]
    maps = _with_maps(start), _with_maps(end)
    turn = np.eye(4)
    turn[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    turn[:3, 3] = [0.1, 0.2, 0.3]
    # the end state's frame is that of its view 1: end view 0 sits at ``turn`` in it
    still = still_camera(start, end, *maps, [np.eye(4), np.eye(4)], [turn, np.eye(4)])
    assert still is not None and still.view == 0 and still.scale == pytest.approx(1.02)
    expected = np.diag([1.02, 1.02, 1.02, 1.0]) @ np.linalg.inv(turn)
    np.testing.assert_allclose(still.transform, expected, atol=1e-12)
    # view 1's pair disagrees (that camera moved): no still camera without view 0's pose
    assert still_camera(start, end, *maps, [np.eye(4), np.eye(4)], [None, np.eye(4)]) is None

    # start view 0 left out: placed through end view 0 and the states' transform
    placed = place_through_twins(start, end, *maps, [None, np.eye(4)], [turn, np.eye(4)], still.transform)
    assert list(placed) == [("start", 0)]
    pose, share = placed[("start", 0)]
    assert share == pytest.approx(1.0)
    np.testing.assert_allclose(pose, np.eye(4), atol=1e-12)
    # metric depth keeps its scale: the twin's pose carried across, without the 1.02 zoom
    kept = place_through_twins(start, end, *maps, [None, np.eye(4)], [turn, np.eye(4)], still.transform, zoom=False)
    np.testing.assert_allclose(kept[("start", 0)][0], still.transform @ turn, atol=1e-12)


@requires_twins
def test_a_moved_camera_is_not_taken_for_a_still_one(tmp_path):
    """The same cabinet with fresh end cameras: no view pair passes the pixel test."""
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.io.scene import load_scene

    scene_dir = tmp_path / "moved"
    render_partnet_scene(TWINS_DIR / "drawer_32761_multi", scene_dir, views=3, seed=0, posed=False,
                         same_cameras=False)
    scene = load_scene(scene_dir)
    start_maps, end_maps = _with_maps(scene.start), _with_maps(scene.end)
    shares = [pixel_agreement(s, e, sm, em)[0] for s, e, sm, em in zip(scene.start, scene.end, start_maps, end_maps)]
    assert max(shares) < STILL_MIN_SHARE, shares
    identity = [np.eye(4)] * 3
    assert still_camera(scene.start, scene.end, start_maps, end_maps, identity, identity) is None


def _alignment_error(result, gt: dict, scene_dir: Path) -> tuple[float, float]:
    """(deg, share of the object) between the end-to-start transform the run used and the truth
    (the rendered cameras), read off the end cloud of the result and its end view 0 pixels."""
    from sparseart.geometry.transforms import rotation_angle

    cams = {state: [np.asarray(c, dtype=np.float64) for c in gt["cameras"][state]] for state in ("start", "end")}
    cloud = result.end_cloud
    view = cloud.frame_index == 0
    # end view 0 camera -> start frame (start view 0's camera), as the truth has it
    truth = np.linalg.inv(cams["start"][0]) @ cams["end"][0]
    ours = np.linalg.lstsq(np.c_[_camera_points(result, scene_dir, 0), np.ones(int(view.sum()))],
                           np.c_[cloud.points[view], np.ones(int(view.sum()))], rcond=None)[0].T
    turn = ours[:3, :3] / np.cbrt(np.linalg.det(ours[:3, :3]))
    return (float(np.degrees(rotation_angle(truth[:3, :3].T @ turn))),
            float(np.linalg.norm(truth[:3, 3] - ours[:3, 3]) / gt["scale"]))


def _camera_points(result, scene_dir: Path, index: int) -> np.ndarray:
    """End view ``index``'s points of the result's end cloud in that view's own camera frame."""
    from sparseart.io.scene import load_scene

    cloud = result.end_cloud
    rows = np.flatnonzero(cloud.frame_index == index)
    frame = load_scene(scene_dir).end[index]
    pointmap = pointmap_from_depth(frame, cam_to_world=np.eye(4))
    return pointmap.points[cloud.pixel_index[rows]]


@requires_twins
def test_an_unposed_textureless_desk_without_masks_is_aligned(tmp_path):
    """Four black drawers in a desk, unposed, no masks, each view's camera kept between the
    states. On renders whose coplanar duplicates flickered (before RENDERER_VERSION 2) SIFT found 3
    matches across the states and the still camera aligned them. On honest renders it finds 38,
    partly on the drawers' handles, and the states come out 4.3 deg off: no segment stays put, and
    the maskless labeler took the whole desk for moving parts (two drawers unmatched, two fitted as
    turns 85-89 deg off). A whole-scene ICP that moves the states by more than
    STATE_POLISH_MIN_DEG says the features were off; its correction is taken before labelling.
    The states are then aligned to < 0.1 deg and 0.3 % of the object, and all four drawers slide
    within 5 deg. (On one machine the two lower drawers, slid 0.245 and 0.218 object units, came
    out as one part until the geometric view edges were polished at full resolution: the views
    registered by geometry alone lay a few per cent of the scene apart, enough to blur the two
    drawers' motions into one.) (The still camera keeps its test: the cabinet below.)"""
    import sparseart
    from sparseart.bench.evaluate import evaluate
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.io.scene import load_scene

    scene_dir = tmp_path / "desk"
    gt = render_partnet_scene(TWINS_DIR / "drawer_32761_multi", scene_dir, views=3, seed=0, posed=False)
    result = sparseart.run(scene_dir, use_masks=False)
    assert any("feature alignment of the states was 4." in w for w in result.warnings)
    degrees, shift = _alignment_error(result, gt, scene_dir)
    assert degrees < 0.1 and shift < 0.003, (degrees, shift)
    rows = evaluate(result, load_scene(scene_dir), gt)
    assert len(rows) == 4
    for row in rows:
        assert row["type_correct"] and row["axis_deg"] < 5.0, row


@requires_twins
def test_an_unposed_textureless_cabinet_with_masks_is_aligned_through_its_reference_views(tmp_path):
    """Two black drawers, unposed, masks given, the cameras kept: the mask ids had found the
    states' registration from upright turns, leaving both drawers 3.2-3.4 deg off. The still
    camera of the two reference views aligns them exactly: both within 2 deg (0.6 and 1.4). (Its
    best-agreeing view pair goes through an end view registered 3.9 % of the object off, which
    put them 7-9 deg off: reference views are preferred.)"""
    import sparseart
    from sparseart.bench.evaluate import evaluate
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.io.scene import load_scene

    scene_dir = tmp_path / "cabinet"
    gt = render_partnet_scene(TWINS_DIR / "drawer_19179_multi", scene_dir, views=3, seed=0, posed=False)
    result = sparseart.run(scene_dir)
    assert result.registration["states"]["method"] == "still camera"
    rows = evaluate(result, load_scene(scene_dir), gt)
    assert len(rows) == 2
    for row in rows:
        assert row["type_correct"] and row["axis_deg"] < 2.0, row


@requires_twins
def test_an_unposed_textureless_cabinet_without_masks_keeps_its_twin_placed_views_at_scale(tmp_path):
    """The same cabinet without masks: two start views are left out and placed through their end
    twins. With both drawers pulled towards the camera, the two images' depth ratio reads 1.115 on
    the drawers where the metric depth is exact (the static quarter of the pixels: 1.000); placed
    at that zoom, one start view lay 30 point spacings off the others, the lower drawer's moved
    points fell on it and the drawer went unmatched. Metric depth keeps its scale: both drawers
    within 2 deg."""
    import sparseart
    from sparseart.bench.evaluate import evaluate
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.io.scene import load_scene

    scene_dir = tmp_path / "cabinet"
    gt = render_partnet_scene(TWINS_DIR / "drawer_19179_multi", scene_dir, views=3, seed=0, posed=False)
    result = sparseart.run(scene_dir, use_masks=False)
    assert any("placed through" in w for w in result.warnings)
    rows = evaluate(result, load_scene(scene_dir), gt)
    assert len(rows) == 2
    for row in rows:
        assert row["type_correct"] and row["axis_deg"] < 2.0, row



def _run_true_and_drifted(tmp_path, views: int):
    """The synthetic cabinet with ``views`` posed views per state, run with its true poses and
    again with every end pose drifted by (0.25, 0, -0.1) m: (truth, drifted) results."""
    import json

    import sparseart
    from sparseart.datasets.synth import render_synth_scene

    scene = tmp_path / "cabinet"
    render_synth_scene(scene, views=views, seed=0, width=160, height=120)
    truth = sparseart.run(scene)
    cameras = json.loads((scene / "cameras.json").read_text())
    for entry in cameras["end"]:
        entry["cam_to_world"][0][3] += 0.25
        entry["cam_to_world"][2][3] -= 0.1
    (scene / "cameras.json").write_text(json.dumps(cameras))
    return truth, sparseart.run(scene)


def _same_joints(truth, drifted) -> None:
    from sparseart.geometry.transforms import axis_angle_deg

    assert len(drifted.joints) == len(truth.joints) >= 1
    for (_, a), (_, b) in zip(truth.joints, drifted.joints):
        assert a.type == b.type and axis_angle_deg(a.axis, b.axis) < 1.0

def test_posed_end_views_that_repeat_their_start_pictures_are_placed_by_them(tmp_path):
    """A posed camera that did not move while cameras.json says it did (a robot head's drifted
    pose, one view per state): the end view repeats the start picture, so it is placed by the
    start pose (align.scene.place_still_end_views) and the joint is the one of the true poses;
    with poses that agree nothing is placed (no warning)."""
    truth, drifted = _run_true_and_drifted(tmp_path, views=1)
    assert not any("repeat the pictures" in w for w in truth.warnings)
    assert any("repeat the pictures" in w for w in drifted.warnings), drifted.warnings
    _same_joints(truth, drifted)


def test_a_drift_two_still_views_agree_on_moves_the_views_a_door_fills_too(tmp_path):
    """Four posed views per state, every end pose drifted alike; two end views repeat their start
    pictures (the others are filled by the moved door and drawer). The two still views agree on
    one correction, so the drift is the state's and every end view is placed: the joints are the
    true poses' (the drawer's slide came out 68 deg off, confidence 0.92, when the two other
    views kept the drifted poses)."""
    truth, drifted = _run_true_and_drifted(tmp_path, views=4)
    assert any("moved alike" in w for w in drifted.warnings), drifted.warnings
    assert len(truth.joints) == 2
    _same_joints(truth, drifted)
