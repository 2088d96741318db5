"""The end depth matched to the start depth of the same camera (sparseart.align.depth_ratio): a
smooth relative warp is found and removed, motion and per-pixel noise are not mistaken for one,
and the rendered robot-shaped scene (one posed view per state, depth warped per state) gets it
in the pipeline. Fast: synthetic depth maps and one 160 x 120 render."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from sparseart.align.depth_ratio import MIN_CORRECTION, fit_log_ratio, match_end_depth
from sparseart.types import Camera, Frame, Pointmap

H, W = 120, 160
K = np.array([[150.0, 0.0, 79.5], [0.0, 150.0, 59.5], [0.0, 0.0, 1.0]])


def _room(rng: np.random.Generator) -> np.ndarray:
    """(H, W) depth of a static scene: a slanted wall and a box in front of it, metres."""
    v, u = np.mgrid[0:H, 0:W] / np.array([H, W])[:, None, None]
    depth = 2.5 + 0.6 * v - 0.3 * u
    depth[30:70, 40:90] = 1.6 + 0.2 * u[30:70, 40:90]
    return depth


def _warp(amplitude: float = 0.015, scale: float = 1.008) -> np.ndarray:
    """A smooth multiplicative warp that is not in the fit's basis (a sine and a Gaussian bump)."""
    v, u = np.mgrid[0:H, 0:W] / np.array([H, W])[:, None, None]
    return scale * (1.0 + amplitude * np.sin(2.2 * u + 0.7) * np.cos(1.3 * v)
                    + 0.5 * amplitude * np.exp(-((u - 0.3) ** 2 + (v - 0.6) ** 2) / 0.1))


def _moved(depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The end state: a door-sized region 25 % nearer (opened towards the camera). Returns
    (depth, moved mask)."""
    moved = np.zeros(depth.shape, dtype=bool)
    moved[20:90, 95:140] = True
    return np.where(moved, depth * 0.75, depth), moved


def test_smooth_relative_warp_is_removed_and_the_motion_kept():
    rng = np.random.default_rng(0)
    start = _room(rng) * (1.0 + 0.003 * rng.standard_normal((H, W)))
    end, moved = _moved(_room(rng))
    end = end * _warp() * (1.0 + 0.003 * rng.standard_normal((H, W)))
    field, numbers = fit_log_ratio(start, end)
    assert field is not None
    static = ~moved
    before = np.median(np.abs(np.log(end / start)[static]))
    after = np.median(np.abs((np.log(end / start) - field)[static]))
    assert before > 0.008 and after < 0.3 * before, (before, after)
    assert numbers["largest"] > MIN_CORRECTION and 0.6 < numbers["inliers"] < 0.95
    # the moving region is not explained away: it still differs by ~25 %
    assert np.median(np.abs((np.log(end / start) - field)[moved])) > 0.2


def test_noise_or_exact_agreement_fits_no_ratio():
    rng = np.random.default_rng(1)
    start = _room(rng)
    end, _ = _moved(start.copy())
    _, exact = fit_log_ratio(start, end)
    assert exact["largest"] < MIN_CORRECTION
    noisy_start = start * (1.0 + 0.008 * rng.standard_normal((H, W)))
    noisy_end = end * (1.0 + 0.008 * rng.standard_normal((H, W)))
    _, noisy = fit_log_ratio(noisy_start, noisy_end)
    assert noisy["largest"] < MIN_CORRECTION, noisy


def _frame(state: str, depth: np.ndarray, pose: np.ndarray) -> Frame:
    return Frame(state, 0, Path(f"{state}/rgb/000.png"), np.zeros((H, W, 3), np.uint8), depth=depth,
                 camera=Camera(K, W, H, pose))


def _pointmap(frame: Frame) -> Pointmap:
    v, u = np.mgrid[0:H, 0:W]
    z = frame.depth
    camera = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1).reshape(-1, 3)
    pose = frame.camera.cam_to_world
    valid = z.reshape(-1) > 0
    points = np.where(valid[:, None], camera @ pose[:3, :3].T + pose[:3, 3], np.nan)
    return Pointmap(frame.state, 0, H, W, points, valid, np.ones(H * W))


def test_match_end_depth_corrects_depth_and_points_of_the_same_camera_only():
    rng = np.random.default_rng(2)
    pose = np.eye(4)
    pose[:3, 3] = [0.4, -0.2, 0.1]
    start = _frame("start", _room(rng), pose)
    end_depth, moved = _moved(_room(rng))
    end = _frame("end", end_depth * _warp(), pose)
    frames, maps, report = match_end_depth([start], [end], [_pointmap(start)], [_pointmap(end)])
    assert len(report) == 1 and report[0].applied and report[0].end_image == "end/rgb/000.png"
    static = ~moved
    assert np.median(np.abs(np.log(frames[0].depth / start.depth)[static])) < 0.002
    # the points moved along their rays: the same as lifting the corrected depth
    assert np.allclose(maps[0].points, _pointmap(frames[0]).points, atol=1e-9, equal_nan=True)
    # another camera (0.5 deg apart) is not paired, nothing changes
    turned = pose.copy()
    turned[:3, :3] = cv2.Rodrigues(np.array([0.0, np.radians(0.5), 0.0]))[0]
    other = _frame("end", end.depth, turned)
    frames, maps, report = match_end_depth([start], [other], [_pointmap(start)], [_pointmap(other)])
    assert report == [] and frames[0] is other


def test_a_large_moving_part_is_not_taken_for_a_warp():
    """Object-only view: the lid covers most of the pixels and moves; the static body agrees
    exactly. The ratio starts at the mode (the body), so nothing is corrected."""
    rng = np.random.default_rng(3)
    start = np.zeros((H, W))
    start[10:110, 10:150] = _room(rng)[10:110, 10:150]
    end = start.copy()
    lid = np.zeros((H, W), dtype=bool)
    lid[10:80, 10:150] = True
    v = np.mgrid[0:H, 0:W][0] / H
    end[lid] *= 0.9 + 0.1 * v[lid]          # a turning lid: its depth change grows across it
    pose = np.eye(4)
    frames, maps, report = match_end_depth([_frame("start", start, pose)], [_frame("end", end, pose)],
                                           [_pointmap(_frame("start", start, pose))],
                                           [_pointmap(_frame("end", end, pose))])
    assert len(report) == 1 and not report[0].applied, report


@pytest.fixture(scope="module")
def warped_robot_scene(tmp_path_factory):
    pytest.importorskip("open3d")
    from sparseart.datasets.partnet import render_articulated_scene
    from sparseart.datasets.realism import Realism
    from sparseart.datasets.synth import build_cabinet

    root = tmp_path_factory.mktemp("ratio") / "cabinet"
    render_articulated_scene(build_cabinet(0), root, {"door_hinge": 0.0, "drawer_slide": 0.0},
                             {"door_hinge": 0.9, "drawer_slide": 0.2}, views=1, seed=0, width=W, height=H,
                             realism=Realism(background=1, depth_warp=1, depth_scale=1))
    return root


def test_pipeline_matches_a_per_state_warp_of_a_robot_view(warped_robot_scene):
    """Rendered: one posed view per state from one camera, depth warped and scaled per state. The
    align stage matches the end depth on the static scene (report, warning) and the static body
    then agrees between the states better than before."""
    import json

    import sparseart
    from sparseart.io.scene import load_scene
    from sparseart.lift.scene_lift import lift_scene

    scene = load_scene(warped_robot_scene)
    lifted = lift_scene(scene)
    frames, _, report = match_end_depth(scene.start, scene.end, lifted.pointmaps["start"], lifted.pointmaps["end"])
    assert report and report[0].applied
    gt = json.loads((warped_robot_scene / "gt.json").read_text())
    static_id = gt["static_mask_id"]
    masks = [cv2.imread(str(warped_robot_scene / s / "mask" / "000.png"), cv2.IMREAD_UNCHANGED) for s in ("start", "end")]
    body = (masks[0] == static_id) & (masks[1] == static_id) & (scene.start[0].depth > 0) & (scene.end[0].depth > 0)
    before = np.median(np.abs(np.log(scene.end[0].depth / scene.start[0].depth)[body]))
    after = np.median(np.abs(np.log(frames[0].depth / scene.start[0].depth)[body]))
    assert after < 0.6 * before, (before, after)
    result = sparseart.run(warped_robot_scene, use_masks=False)
    entry = result.registration["depth_ratio"][0]
    assert entry["applied"] and entry["end"] == "end/rgb/000.png"
    assert any("same camera" in w for w in result.warnings)


def _unposed(state: str, depth: np.ndarray, rgb: np.ndarray) -> tuple[Frame, Pointmap]:
    """A view without a pose (unposed RGB-D): its pointmap in its own camera frame."""
    frame = Frame(state, 0, Path(f"{state}/rgb/000.png"), rgb, depth=depth, camera=Camera(K, W, H))
    v, u = np.mgrid[0:H, 0:W]
    points = np.stack([(u - K[0, 2]) / K[0, 0] * depth, (v - K[1, 2]) / K[1, 1] * depth, depth], axis=-1)
    return frame, Pointmap(state, 0, H, W, points.reshape(-1, 3), depth.reshape(-1) > 0, np.ones(H * W))


def test_an_unposed_view_whose_camera_did_not_move_gets_its_depth_matched():
    """Unposed: the still test pairs end view 0 with start view 0 (same picture, depth within
    the still tolerance), and the end depth and points (about the camera's own origin) are matched
    to the start's on the static scene; a camera moved between the states is not paired."""
    from sparseart.align.still import still_pairs

    rng = np.random.default_rng(4)
    texture = cv2.resize(rng.integers(0, 255, (H // 8, W // 8, 3), dtype=np.uint8), (W, H),
                         interpolation=cv2.INTER_NEAREST)
    start, start_map = _unposed("start", _room(rng), texture)
    end_depth, moved = _moved(_room(rng))
    end, end_map = _unposed("end", end_depth * _warp(amplitude=0.008), texture)
    pairs = still_pairs([start], [end], [start_map], [end_map])
    assert pairs == {0: 0}
    frames, maps, report = match_end_depth([start], [end], [start_map], [end_map], pairs=pairs)
    assert len(report) == 1 and report[0].applied
    assert np.median(np.abs(np.log(frames[0].depth / start.depth)[~moved])) < 0.002
    assert np.allclose(maps[0].points, _unposed("end", frames[0].depth, texture)[1].points, atol=1e-9)
    shifted, shifted_map = _unposed("end", end.depth, np.roll(texture, 12, axis=1))    # the camera moved
    assert still_pairs([start], [shifted], [start_map], [shifted_map]) == {}
