"""Tests of sparseart.align.ransac: Umeyama, RANSAC, SIFT matching, view registration, state alignment.

Synthetic scenes are textured rectangles ray-cast in numpy (exact depth, known poses and
motions); one PartNet object is rendered (module fixture) for the view registration on real data.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from sparseart.align import (AlignmentError, Similarity, align_states, match_features, ransac_similarity,
                             register_views, transform_pointmap, umeyama)
from sparseart.lift.rgbd import pointmap_from_depth
from sparseart.types import Camera, Frame, SceneError

from conftest import PARTNET_DIR, requires_partnet

PARTNET = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "partnet"
W, H = 320, 240
K = np.array([[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------- helpers
def rotation(axis, degrees: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    rvec = (np.radians(degrees) * axis).reshape(3, 1)
    return cv2.Rodrigues(rvec)[0]


def rigid(R: np.ndarray, t) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, t
    return out


def angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def look_at(eye, target=(0.0, 0.0, 2.6)) -> np.ndarray:
    """OpenCV camera at ``eye`` looking at ``target`` in a y-down world."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    return rigid(np.stack([x, np.cross(z, x), z], axis=1), eye)


def texture(seed: int, kind: str = "noise") -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == "flat":
        return np.full((256, 256, 3), 150, np.uint8)
    small = rng.integers(0, 256, (32, 32, 3)).astype(np.uint8)
    tex = cv2.resize(small, (256, 256), interpolation=cv2.INTER_CUBIC)
    if kind == "strip":  # texture only on a thin horizontal band
        flat = np.full_like(tex, 150)
        flat[124:132] = tex[124:132]
        tex = flat
    return tex


class Rect:
    """A textured rectangle: centre, unit in-plane axes u, v, half extents, texture, moving flag."""

    def __init__(self, centre, u, v, half_u, half_v, tex, moving=False):
        self.centre, self.u, self.v = (np.asarray(a, float) for a in (centre, u, v))
        self.half = (half_u, half_v)
        self.tex, self.moving = tex, moving

    def moved(self, motion: np.ndarray) -> "Rect":
        return Rect(motion[:3, :3] @ self.centre + motion[:3, 3], motion[:3, :3] @ self.u,
                    motion[:3, :3] @ self.v, *self.half, self.tex, self.moving)


def render(rects: list[Rect], c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast rectangles: (H, W, 3) uint8 RGB and (H, W) depth along the optical axis (0 = none)."""
    rows, cols = np.mgrid[0:H, 0:W].astype(float)
    rays_cam = np.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones_like(cols)], -1)
    rays = rays_cam @ c2w[:3, :3].T
    origin = c2w[:3, 3]
    depth = np.zeros((H, W))
    rgb = np.full((H, W, 3), 90, np.uint8)
    for rect in rects:
        normal = np.cross(rect.u, rect.v)
        denom = rays @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((rect.centre - origin) @ normal) / denom
        hit = origin + rays * t[..., None]
        a = (hit - rect.centre) @ rect.u / rect.half[0]
        b = (hit - rect.centre) @ rect.v / rect.half[1]
        inside = np.isfinite(t) & (t > 0) & (np.abs(a) <= 1) & (np.abs(b) <= 1)
        closer = inside & ((depth == 0) | (t < depth))
        mapx = ((a + 1) / 2 * 255).astype(np.float32)
        mapy = ((b + 1) / 2 * 255).astype(np.float32)
        colour = cv2.remap(rect.tex, np.nan_to_num(mapx), np.nan_to_num(mapy), cv2.INTER_LINEAR)
        rgb[closer] = colour[closer]
        depth[closer] = t[closer]
    return rgb, depth


def frame_of(rgb, depth, state: str, index: int) -> tuple[Frame, object]:
    frame = Frame(state=state, index=index, rgb_path=Path(f"{state}/rgb/{index:03d}.png"), rgb=rgb,
                  depth=depth, camera=Camera(K.copy(), W, H))
    return frame, pointmap_from_depth(frame, np.eye(4))


def room(kind: str = "noise", door: bool = True, door_half=(0.25, 0.4)) -> list[Rect]:
    """A corner of a room (back wall, floor, side wall) and a door panel in front of the wall."""
    rects = [Rect((0, 0, 3.2), (1, 0, 0), (0, 1, 0), 1.6, 1.2, texture(1, kind)),
             Rect((0, 1.2, 2.4), (1, 0, 0), (0, 0, 1), 1.6, 0.8, texture(2, kind)),
             Rect((-1.6, 0, 2.4), (0, 0, 1), (0, 1, 0), 0.8, 1.2, texture(3, kind))]
    if door:
        rects.append(Rect((0.2 + door_half[0], 0.1, 2.5), (1, 0, 0), (0, 1, 0), *door_half,
                          texture(4, kind), moving=True))
    return rects


DOOR_MOTION = rigid(rotation((0, 1, 0), 30.0), [0, 0, 0])
DOOR_MOTION[:3, 3] = np.array([0.2, 0, 2.5]) - DOOR_MOTION[:3, :3] @ np.array([0.2, 0, 2.5])  # hinge x=0.2
DRAWER_MOTION = rigid(np.eye(3), [0.0, 0.0, -0.3])


def two_states(rects: list[Rect], motion: np.ndarray, start_eye=(-0.3, -0.4, 0.0),
               end_eye=(0.4, -0.2, 0.2)):
    """One view per state: (start frame, pointmap, c2w), (end frame, pointmap, c2w)."""
    c2w_s, c2w_e = look_at(start_eye), look_at(end_eye)
    end_rects = [r.moved(motion) if r.moving else r for r in rects]
    fs, ps = frame_of(*render(rects, c2w_s), "start", 0)
    fe, pe = frame_of(*render(end_rects, c2w_e), "end", 0)
    return (fs, ps, c2w_s), (fe, pe, c2w_e)


# ----------------------------------------------------------------------------- geometry
def test_similarity_matrix_apply_inverse():
    sim = Similarity(2.5, rotation((1, 2, 3), 40), np.array([1.0, -2.0, 0.5]))
    pts = np.random.default_rng(0).normal(size=(20, 3))
    homogeneous = np.c_[pts, np.ones(20)] @ sim.matrix().T
    np.testing.assert_allclose(sim.apply(pts), homogeneous[:, :3], atol=1e-12)
    np.testing.assert_allclose(sim.inverse().apply(sim.apply(pts)), pts, atol=1e-12)
    back = Similarity.from_matrix(sim.matrix())
    assert back.scale == pytest.approx(2.5) and np.allclose(back.rotation, sim.rotation)


@pytest.mark.parametrize("scale", [1e-3, 0.37, 1.0, 1e3])
@pytest.mark.parametrize("with_scale", [True, False])
def test_umeyama_exact(scale, with_scale):
    rng = np.random.default_rng(1)
    source = rng.normal(size=(50, 3)) * scale
    true = Similarity(2.0 if with_scale else 1.0, rotation((0.3, -1, 0.2), 123), rng.normal(size=3) * scale)
    model = umeyama(source, true.apply(source), with_scale)
    assert model.scale == pytest.approx(true.scale, rel=1e-9)
    assert np.abs(model.rotation - true.rotation).max() < 1e-9
    np.testing.assert_allclose(model.translation, true.translation, atol=1e-9 * scale)
    assert np.linalg.det(model.rotation) == pytest.approx(1.0)


def test_umeyama_weights_ignore_zero_weight_outliers_and_fix_reflection():
    rng = np.random.default_rng(2)
    source = rng.normal(size=(40, 3))
    true = Similarity(0.5, rotation((1, 0, 0), 70), np.array([0.0, 1.0, 2.0]))
    target = true.apply(source)
    target[:10] += rng.normal(size=(10, 3)) * 5
    weights = np.r_[np.zeros(10), np.ones(30)]
    model = umeyama(source, target, True, weights=weights)
    assert model.scale == pytest.approx(0.5, rel=1e-9) and np.abs(model.rotation - true.rotation).max() < 1e-9
    mirrored = source * np.array([1.0, 1.0, -1.0])      # best fit would be a reflection
    assert np.linalg.det(umeyama(source, mirrored, False).rotation) == pytest.approx(1.0)


def test_ransac_recovers_similarity_with_60_percent_outliers():
    rng = np.random.default_rng(3)
    source = rng.uniform(-1, 1, size=(500, 3))
    true = Similarity(3.0, rotation((1, 1, 0), 50), np.array([0.2, 0.0, -1.0]))
    target = true.apply(source) + rng.normal(scale=0.002, size=(500, 3))
    outliers = rng.permutation(500)[:300]
    target[outliers] = rng.uniform(-4, 4, size=(300, 3))
    model, inliers = ransac_similarity(source, target, with_scale=True, threshold=0.02, seed=0)
    assert model.scale == pytest.approx(3.0, rel=2e-3)
    assert angle_deg(model.rotation.T @ true.rotation) < 0.2
    truth = np.ones(500, bool)
    truth[outliers] = False
    assert (inliers == truth).mean() > 0.99


def test_ransac_without_consensus_raises():
    rng = np.random.default_rng(4)
    with pytest.raises(AlignmentError, match="consensus"):
        ransac_similarity(rng.normal(size=(60, 3)), rng.normal(size=(60, 3)), with_scale=False,
                          threshold=0.01, min_inliers=9)


# ----------------------------------------------------------------------------- synthetic scenes
def test_match_features_lifts_consistent_3d_matches():
    (fs, ps, c2w_s), (fe, pe, c2w_e) = two_states(room(door=False), np.eye(4))
    matches = match_features(fs, ps, fe, pe)
    assert len(matches) > 50 and matches.n_ratio_passed >= len(matches)
    truth = np.linalg.inv(c2w_s) @ c2w_e
    moved = matches.points_b @ truth[:3, :3].T + truth[:3, 3]
    assert np.median(np.linalg.norm(moved - matches.points_a, axis=1)) < 0.01
    only_left = np.zeros((H, W), bool)
    only_left[:, : W // 2] = True
    masked = match_features(fs, ps, fe, pe, mask_a=only_left)
    assert 0 < len(masked) < len(matches) and masked.pixels_a[:, 0].max() < W // 2 + 1


def test_register_views_synthetic_three_views():
    rects = room(door=False)
    c2ws = [look_at(e) for e in ((-0.5, -0.4, 0.0), (0.0, -0.3, 0.1), (0.5, -0.5, 0.0))]
    views = [frame_of(*render(rects, c), "start", i) for i, c in enumerate(c2ws)]
    transforms, warnings = register_views([v[0] for v in views], [v[1] for v in views], with_scale=False)
    assert np.allclose(transforms[0], np.eye(4))
    for c2w, got in zip(c2ws[1:], transforms[1:]):
        true = np.linalg.inv(c2ws[0]) @ c2w
        assert angle_deg(got[:3, :3].T @ true[:3, :3]) < 0.3
        assert np.linalg.norm(got[:3, 3] - true[:3, 3]) < 0.01


def test_align_states_recovers_known_similarity_and_warns_on_scale():
    (fs, ps, c2w_s), (fe, pe, c2w_e) = two_states(room(), DOOR_MOTION)
    s = 3.7   # a relative-scale reconstruction of the end state
    scaled = transform_pointmap(pe, np.diag([s, s, s, 1.0]))
    result = align_states([fs], [ps], [fe], [scaled], with_scale=True)
    truth = np.linalg.inv(c2w_s) @ c2w_e @ np.diag([1 / s, 1 / s, 1 / s, 1.0])
    assert result.transform.scale == pytest.approx(1 / s, rel=0.01)
    assert angle_deg(result.transform.rotation.T @ truth[:3, :3] * s) < 0.5
    assert np.linalg.norm(result.transform.translation - truth[:3, 3]) < 0.02
    assert result.rmse < 0.03 and 0.3 < result.inliers.mean() < 1.0
    assert not any("scale" in w for w in result.warnings)
    huge = align_states([fs], [ps], [fe], [transform_pointmap(pe, np.diag([10.0, 10, 10, 1]))],
                        with_scale=True)
    assert any("outside [0.2, 5" in w for w in huge.warnings)


@pytest.mark.parametrize("motion", [DOOR_MOTION, DRAWER_MOTION], ids=["door", "drawer"])
def test_align_states_candidates_contain_the_moving_part(motion):
    (fs, ps, c2w_s), (fe, pe, c2w_e) = two_states(room(), motion)
    result = align_states([fs], [ps], [fe], [pe], with_scale=False)
    truth = np.linalg.inv(c2w_s) @ c2w_e
    assert angle_deg(result.transform.rotation.T @ truth[:3, :3]) < 0.5
    expected = np.linalg.inv(c2w_s) @ motion @ c2w_s     # start -> end door motion, start camera frame
    assert result.candidates, result.warnings
    best = result.candidates[0]
    assert angle_deg(best.transform[:3, :3].T @ expected[:3, :3]) < 2.0
    probe = best.points
    err = np.linalg.norm(probe @ best.transform[:3, :3].T + best.transform[:3, 3]
                         - (probe @ expected[:3, :3].T + expected[:3, 3]), axis=1)
    assert np.median(err) < 0.02 and best.support >= 8
    assert all(a.support >= b.support for a, b in zip(result.candidates, result.candidates[1:]))


# ----------------------------------------------------------------------------- error paths
def test_textureless_images_are_a_clear_error():
    (fs, ps, _), (fe, pe, _) = two_states(room("flat"), DOOR_MOTION)
    with pytest.raises(AlignmentError, match="too few feature matches") as info:
        align_states([fs], [ps], [fe], [pe], with_scale=False)
    message = str(info.value)
    assert "start/rgb/000.png" in message and "end/rgb/000.png" in message and "\n" not in message
    assert isinstance(info.value, SceneError)
    wall = [Rect((0, 0, 3.0), (1, 0, 0), (0, 1, 0), 2.0, 1.5, texture(0, "flat"))]   # planar: no fallback
    views = [frame_of(*render(wall, look_at(e, (0, 0, 3.0))), "start", i)
             for i, e in enumerate(((-0.2, 0, 0), (0.2, 0, 0)))]
    with pytest.raises(AlignmentError, match=r"start/rgb/001.png: view could not be registered"):
        register_views([v[0] for v in views], [v[1] for v in views], with_scale=False)


def test_collinear_matches_are_degenerate():
    wall = [Rect((0, 0, 3.0), (1, 0, 0), (0, 1, 0), 2.0, 1.5, texture(5, "strip"))]
    c2w_s, c2w_e = look_at((-0.2, 0, 0), (0, 0, 3)), look_at((0.2, 0.05, 0), (0, 0, 3))
    fs, ps = frame_of(*render(wall, c2w_s), "start", 0)
    fe, pe = frame_of(*render(wall, c2w_e), "end", 0)
    with pytest.raises(AlignmentError, match="degenerate"):
        align_states([fs], [ps], [fe], [pe], with_scale=False)


def test_ambiguous_static_part_is_warned():
    # A big frontal door gets almost as many matches as the static room (here: 201 vs 252).
    (fs, ps, _), (fe, pe, _) = two_states(room(door_half=(0.4, 0.6)), DOOR_MOTION)
    result = align_states([fs], [ps], [fe], [pe], with_scale=False)
    assert result.candidates and result.candidates[0].support > 0.7 * result.inliers.sum()
    assert any("ambiguous" in w for w in result.warnings), result.warnings
    (fs, ps, _), (fe, pe, _) = two_states(room(), DOOR_MOTION)   # small door: no warning
    assert not any("ambiguous" in w for w in align_states([fs], [ps], [fe], [pe], with_scale=False).warnings)


# ----------------------------------------------------------------------------- PartNet render
@pytest.fixture(scope="module")
def partnet_scene(tmp_path_factory):
    obj = PARTNET / "storage_40147"
    if not (obj / "mobility.urdf").is_file():
        pytest.skip(f"PartNet-Mobility objects not found at {PARTNET}")
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.io.scene import load_scene

    root = tmp_path_factory.mktemp("align") / "storage"
    render_partnet_scene(obj, root, views=3, seed=0, posed=False, same_cameras=False)
    return load_scene(root), json.loads((root / "gt.json").read_text())


def test_register_views_partnet_recovers_true_relative_poses(partnet_scene):
    scene, gt = partnet_scene
    assert not scene.posed
    for state in ("start", "end"):
        frames = scene.frames(state)
        pointmaps = [pointmap_from_depth(f, np.eye(4)) for f in frames]
        transforms, _ = register_views(frames, pointmaps, with_scale=False)
        c2w = [np.asarray(c, float) for c in gt["cameras"][state]]
        for i in range(1, len(frames)):
            true = np.linalg.inv(c2w[0]) @ c2w[i]
            assert angle_deg(transforms[i][:3, :3].T @ true[:3, :3]) < 1.0, (state, i)
            assert np.linalg.norm(transforms[i][:3, 3] - true[:3, 3]) < 0.01 * gt["scale"], (state, i)


# ----------------------------------------------------------------------------- joint registration
def _two_state_views(motion: np.ndarray, end_kind: str = "noise"):
    """Two views per state of the room with a door; the end state's door moved by ``motion`` and
    the end cameras elsewhere. Returns frames, pointmaps (own camera frames) and cameras per state."""
    rects = room()
    end_rects = [r.moved(motion) if r.moving else r for r in (rects if end_kind == "noise" else room(end_kind))]
    eyes = {"start": ((-0.3, -0.4, 0.0), (0.1, -0.3, 0.1)), "end": ((0.4, -0.2, 0.2), (-0.1, -0.5, 0.0))}
    frames, maps, cams = {}, {}, {}
    for state, scene_rects in (("start", rects), ("end", end_rects)):
        cams[state] = [look_at(e) for e in eyes[state]]
        views = [frame_of(*render(scene_rects, c), state, i) for i, c in enumerate(cams[state])]
        frames[state], maps[state] = [v[0] for v in views], [v[1] for v in views]
    return frames, maps, cams


def test_register_scene_places_every_view_and_finds_the_door():
    from sparseart.align.graph import register_scene
    from sparseart.align.scene import registration_report

    frames, maps, cams = _two_state_views(DOOR_MOTION)
    reg = register_scene(frames, maps, seed=0)
    assert reg.aligned, reg.warnings
    reference = cams["start"][0]
    for state in ("start", "end"):
        for pose, c2w in zip(reg.poses[state], cams[state]):
            true = np.linalg.inv(reference) @ c2w
            assert pose is not None
            assert angle_deg(pose[:3, :3].T @ true[:3, :3]) < 0.5, (state, reg.warnings)
            assert np.linalg.norm(pose[:3, 3] - true[:3, 3]) < 0.02
    expected = np.linalg.inv(reference) @ DOOR_MOTION @ reference   # start -> end door motion, result frame
    assert reg.candidates and angle_deg(reg.candidates[0].transform[:3, :3].T @ expected[:3, :3]) < 2.0
    report = registration_report(reg)
    assert [v["image"] for v in report["views"]] == ["start/rgb/000.png", "start/rgb/001.png",
                                                    "end/rgb/000.png", "end/rgb/001.png"]
    assert [v["how"] for v in report["views"]] == ["reference", "features", "features", "features"]
    assert all(v["registered"] and v["inliers"] > 20 and v["residual"] < 0.02 for v in report["views"])
    assert all(v["scale"] == 1.0 for v in report["views"])            # exact depth keeps its scale
    states = report["states"]
    assert states["method"] == "features" and states["trusted"] and states["inliers"] >= 15
    assert states["rmse"] < 0.02 and states["inliers"] <= states["matches"]
    json.dumps(report)                                                 # JSON-ready


def test_register_scene_without_common_texture_leaves_the_states_apart_and_says_so():
    from sparseart.align.graph import register_scene

    frames, maps, cams = _two_state_views(DRAWER_MOTION, end_kind="flat")
    reg = register_scene(frames, maps, seed=0, geometry_fallback=False)
    assert not reg.aligned and reg.states["method"] == "none" and not reg.candidates
    assert any("feature alignment of the states failed" in w for w in reg.warnings), reg.warnings
    true = np.linalg.inv(cams["start"][0]) @ cams["start"][1]
    assert angle_deg(reg.poses["start"][1][:3, :3].T @ true[:3, :3]) < 0.5
    assert reg.poses["end"][1] is None          # the flat end views match nothing
    assert any("end/rgb/001.png: view could not be registered" in w for w in reg.warnings)


def test_ransac_per_match_thresholds():
    rng = np.random.default_rng(3)
    source = rng.uniform(-1, 1, (200, 3)) * [1, 1, 0.2] + [0, 0, 3]
    R = rotation((0, 1, 0), 20.0)
    target = source @ R.T + [0.1, 0.0, 0.2]
    far = np.linalg.norm(target, axis=1)
    noisy = target * (1 + 0.01 * rng.standard_normal((200, 1)))      # depth-proportional error
    noisy[:60] = rng.uniform(-1, 1, (60, 3)) + [0, 0, 3]             # 30 % outliers
    model, inliers = ransac_similarity(source, noisy, with_scale=False, threshold=0.04 * far, seed=0)
    assert angle_deg(model.rotation.T @ R) < 1.0 and inliers[60:].mean() > 0.9 and inliers[:60].mean() < 0.2
    with pytest.raises(ValueError, match="threshold"):
        ransac_similarity(source, noisy, with_scale=False, threshold=np.ones(5))


def test_depth_roughness_separates_exact_from_noisy_depth():
    from sparseart.align.noise import depth_roughness

    frame, pointmap = frame_of(*render(room(), look_at((0.0, -0.3, 0.0))), "start", 0)
    assert depth_roughness(pointmap) < 1e-3
    rng = np.random.default_rng(0)
    noisy_depth = frame.depth * (1 + 0.005 * rng.standard_normal(frame.depth.shape))
    _, noisy = frame_of(frame.rgb, noisy_depth, "start", 0)
    assert 0.003 < depth_roughness(noisy) < 0.008


def _box_surface(rng: np.random.Generator, n: int, half: np.ndarray) -> np.ndarray:
    """(n, 3) points on the surface of an axis-aligned box of half-extents ``half`` (3,)."""
    points = rng.uniform(-1, 1, (n, 3)) * half
    face = rng.integers(0, 3, n)
    points[np.arange(n), face] = np.sign(rng.uniform(-1, 1, n)) * half[face]
    return points


def _static_only(start_points: np.ndarray, end_points: np.ndarray):
    """(start, end, labels): two LabelledClouds whose every point is labelled static (part 0)."""
    from sparseart.types import LabelledCloud, PartLabels, PartSpec

    def cloud(points: np.ndarray, state: str) -> LabelledCloud:
        n = len(points)
        return LabelledCloud(state=state, points=points, colors=np.zeros((n, 3)), segment=np.zeros(n, dtype=np.int64),
                             frame_index=np.zeros(n, dtype=np.int64), pixel_index=np.arange(n), confidence=np.ones(n))

    labels = PartLabels(parts=[PartSpec(id=0, role="static")], start_part=np.zeros(len(start_points), dtype=np.int64),
                        end_part=np.zeros(len(end_points), dtype=np.int64))
    return cloud(start_points, "start"), cloud(end_points, "end"), labels


def test_the_static_polish_runs_from_the_state_that_shows_less_of_the_static_part():
    """A stapler-like base: fully seen in one state, only its front end and a thin side strip in
    the other (the closed arm covers the rest). ICP of the full base onto the strip turns it by
    ~15 deg; the polish runs the strip onto the full base and stays within a few degrees,
    whichever state shows less."""
    from sparseart.align.static import polish_on_static
    from sparseart.geometry.transforms import rotation_angle

    rng = np.random.default_rng(0)

    def plate(n: int, x1: float, y1: float, x0: float = 0.0) -> np.ndarray:
        return np.column_stack([rng.uniform(x0, x1, n), rng.uniform(0, y1, n), rng.normal(0, 0.002, n)])

    full = plate(5000, 1.0, 0.25)
    partial = np.concatenate([plate(700, 0.15, 0.25), plate(800, 1.0, 0.03, x0=0.15)]) + rng.normal(0, 0.003, (1500, 3))

    for start_points, end_points in ((partial, full), (full, partial)):
        start, end, labels = _static_only(start_points, end_points)
        polished, _ = polish_on_static(start, end, labels, [], seed=0)
        # the polish is rigid: read its turn off the moved end points
        moved, before = polished.points - polished.points.mean(0), end.points - end.points.mean(0)
        u, _, vt = np.linalg.svd(before.T @ moved)
        assert np.degrees(rotation_angle((u @ vt).T)) < 5.0


def test_the_static_polish_does_not_depend_on_the_seed_below_its_point_budget():
    """The polish works on every static point up to POLISH_POINTS: a box-like body of 6000 points
    per state, the end state 1 deg and 1 cm off, comes out the same for any seed. On a random
    2000-point subsample the bottom of a flat valley moved with the seed (a realistic dishwasher's
    basket slid 0.404-0.500 over four seeds)."""
    from scipy.spatial.transform import Rotation

    from sparseart.align.static import polish_on_static

    rng = np.random.default_rng(3)
    body = _box_surface(rng, 6000, np.array([0.5, 0.4, 0.3]))
    turn = Rotation.from_rotvec(np.radians(1.0) * np.array([0.2, 1.0, 0.1]) / np.linalg.norm([0.2, 1.0, 0.1]))
    end_points = turn.apply(body + rng.normal(0, 0.002, body.shape)) + [0.01, 0.0, -0.005]

    start, end, labels = _static_only(body, end_points)
    polished = [polish_on_static(start, end, labels, [], seed=seed)[0].points for seed in (0, 1, 2)]
    assert np.abs(polished[0] - body).max() < 0.02                     # the offset is taken out
    assert np.array_equal(polished[0], polished[1]) and np.array_equal(polished[0], polished[2])


def test_on_rough_depth_the_static_polish_keeps_the_feature_translation():
    """rough_depth: the polish turns the end state about its static centroid and leaves that
    centroid where the feature alignment put it (warped surfaces steer ICP's translation along
    flat valleys); clean depth takes the whole ICP transform. A box-like body, the end state
    turned 2 deg and 1.5 cm off."""
    from scipy.spatial.transform import Rotation

    from sparseart.align.static import polish_on_static

    rng = np.random.default_rng(5)
    body = _box_surface(rng, 5000, np.array([0.5, 0.4, 0.3]))
    turn = Rotation.from_rotvec(np.radians(2.0) * np.array([0.3, 1.0, -0.2]) / np.linalg.norm([0.3, 1.0, -0.2]))
    end_points = turn.apply(body) + [0.015, 0.0, 0.0]

    start, end, labels = _static_only(body, end_points)
    rough, _ = polish_on_static(start, end, labels, [], seed=0, rough_depth=True)
    clean, _ = polish_on_static(start, end, labels, [], seed=0, rough_depth=False)
    np.testing.assert_allclose(rough.points.mean(0), end_points.mean(0), atol=1e-9)   # translation kept
    assert np.abs(rough.points - (body + [0.015, 0.0, 0.0])).max() < 2e-3               # turn taken out
    assert np.abs(clean.points - body).max() < 2e-3                                     # both taken out


def test_the_rough_depth_polish_leaves_turns_the_static_part_does_not_constrain():
    """A static part seen as a long narrow bar (a stapler's base under its arm) does not constrain
    a turn about its length: the polish's turn there is dropped, a turn across it is kept. A box
    constrains every turn: all of it is kept."""
    from scipy.spatial.transform import Rotation

    from sparseart.align.static import constrained_rotation

    rng = np.random.default_rng(2)
    bar = _box_surface(rng, 6000, np.array([0.5, 0.03, 0.02]))
    box = _box_surface(rng, 6000, np.array([0.5, 0.4, 0.3]))
    turn = Rotation.from_rotvec(np.radians([5.0, 0.0, 0.0])) * Rotation.from_rotvec(np.radians([0.0, 1.0, 0.0]))

    kept_on_bar = Rotation.from_matrix(constrained_rotation(turn.as_matrix(), bar)).as_rotvec()
    np.testing.assert_allclose(np.degrees(kept_on_bar), [0.0, 1.0, 0.0], atol=0.1)
    kept_on_box = Rotation.from_matrix(constrained_rotation(turn.as_matrix(), box))
    assert np.degrees((kept_on_box * turn.inv()).magnitude()) < 1e-6


def test_a_turn_the_static_part_does_not_fix_is_left_out_and_said(monkeypatch):
    """On rough depth an ICP turn of 5 deg about a bar's length (which its surfaces barely
    constrain) is not applied to the end state, and a warning says how much was left out."""
    from scipy.spatial.transform import Rotation

    import sparseart.align.static as static
    from sparseart.geometry.icp import RigidRegistration
    from sparseart.geometry.transforms import make_transform

    bar = _box_surface(np.random.default_rng(4), 6000, np.array([0.5, 0.03, 0.02]))
    turn = make_transform(Rotation.from_rotvec(np.radians([5.0, 0.0, 0.0])).as_matrix(), np.zeros(3))
    monkeypatch.setattr(static, "_subset_onto_superset", lambda source, target, seed: RigidRegistration(
        transform=turn, rmse=0.001, inlier_fraction=0.9, correspondences=np.zeros((0, 2), dtype=np.int64)))
    start, end, labels = _static_only(bar, bar.copy())
    warnings: list[str] = []
    polished, _ = static.polish_on_static(start, end, labels, warnings, rough_depth=True)
    assert np.abs(polished.points - bar).max() < 3e-4      # the 5 deg turn moved the bar's edges by 2.6e-3
    assert any("5.0 deg of the polish's turn left as the feature alignment had it" in w for w in warnings)


@requires_partnet
def test_noisy_depth_views_of_a_plain_fridge_are_placed_by_geometry(tmp_path):
    """A plain white fridge on a table (realistic render: warped, noisy, holed depth, seed 2): two
    views of each state find too few feature matches and go to the geometric fallback. Their right
    fits see through 2.5-5.3 % of the other view (holes, smeared edges, warps), which the clean-depth
    allowance (5 %) refused; noisy depth allows 10 %. Every view is placed, within 3 deg of its true
    rotation (before: 2 of 6 views, and the door unmatched)."""
    from scipy.spatial.transform import Rotation

    from sparseart.align.scene import align_scene
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.datasets.realism import PRESETS
    from sparseart.io.scene import load_scene
    from sparseart.lift.scene_lift import lift_scene

    scene_dir = tmp_path / "fridge"
    gt = render_partnet_scene(PARTNET_DIR / "refrigerator_11231", scene_dir, views=3, seed=2, posed=False,
                              write_masks=True, realism=PRESETS["realistic"])
    scene = load_scene(scene_dir)
    aligned = align_scene(scene, lift_scene(scene), seed=2)
    reference = np.linalg.inv(np.asarray(gt["cameras"]["start"][0]))
    for state in ("start", "end"):
        for pose, camera in zip(aligned.poses[state], gt["cameras"][state]):
            assert pose is not None
            true = reference @ np.asarray(camera)
            rotation = pose[:3, :3] / np.cbrt(np.linalg.det(pose[:3, :3]))
            assert np.degrees(Rotation.from_matrix(rotation @ true[:3, :3].T).magnitude()) < 3.0


def test_the_labelers_motions_follow_the_static_polish():
    """A motion found before the end cloud moved by T maps a start point onto the end point that now
    lies at T of it: initial and alternative motions become T @ M (the fit starts from them)."""
    from scipy.spatial.transform import Rotation

    from sparseart.align.static import carried
    from sparseart.types import PartLabels, PartSpec

    rng = np.random.default_rng(0)
    motion = np.eye(4)
    motion[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 0.6]).as_matrix()
    motion[:3, 3] = [0.1, -0.2, 0.05]
    polish = np.eye(4)
    polish[:3, :3] = Rotation.from_rotvec([0.03, -0.05, 0.02]).as_matrix()
    polish[:3, 3] = [0.02, 0.01, -0.03]
    labels = PartLabels(parts=[PartSpec(id=0, role="static"), PartSpec(id=1, role="movable")],
                        start_part=np.zeros(3, dtype=np.int64), end_part=np.zeros(3, dtype=np.int64),
                        initial_motion={1: motion}, alternative_motions={1: [np.eye(4)]})
    start = rng.normal(size=(20, 3))
    end = start @ motion[:3, :3].T + motion[:3, 3]
    end_polished = end @ polish[:3, :3].T + polish[:3, 3]
    moved = carried(labels, polish)
    follow = moved.initial_motion[1]
    np.testing.assert_allclose(start @ follow[:3, :3].T + follow[:3, 3], end_polished, atol=1e-12)
    np.testing.assert_allclose(moved.alternative_motions[1][0], polish, atol=1e-12)
    assert labels.initial_motion[1] is motion      # the input labels are left as they were


def test_a_geometric_edge_is_polished_at_full_resolution():
    """register_rigid fits on 2000-point subsamples; on a box with two slabs sticking out along x
    (drawers pulled out), a fit slid 6 % of the scene along them keeps their walls on each other.
    The full-resolution point-to-plane polish brings it back within 0.5 %; a polish that cannot
    raise the overlap leaves the result as it was."""
    from dataclasses import replace as with_transform

    from sparseart.align.geometric import _polished
    from sparseart.geometry.clouds import scene_size
    from sparseart.geometry.icp import RigidRegistration

    rng = np.random.default_rng(3)

    def surface(n: int) -> np.ndarray:
        faces = []
        for axis in range(3):
            for side in (-0.3, 0.3):
                face = rng.uniform(-0.3, 0.3, size=(n, 3))
                face[:, axis] = side
                faces.append(face)
        for z in (-0.15, 0.15):      # two drawers out along +x
            slab = np.column_stack([rng.uniform(0.3, 0.6, n), rng.uniform(-0.25, 0.25, n), np.full(n, z)])
            faces.append(slab)
        return np.concatenate(faces)

    source, target = surface(3000), surface(3000)
    size = scene_size(target)
    slid = np.eye(4)
    slid[0, 3] = 0.06 * size
    coarse = RigidRegistration(slid, 0.0, 0.7, np.zeros((0, 2), np.int64), {})
    polished = _polished(coarse, source, target, size)
    assert np.linalg.norm(polished.transform[:3, 3]) < 0.005 * size
    assert np.allclose(polished.transform[:3, :3], np.eye(3), atol=1e-2)
    exact = with_transform(coarse, transform=np.eye(4))
    assert np.allclose(_polished(exact, source, target, size).transform, np.eye(4), atol=1e-3)


@requires_partnet
def test_a_first_view_that_matches_no_other_gives_the_frame_to_the_rest(tmp_path):
    """The plain fridge on the realistic bench render, seed 3: the first view of each state (its
    side) matches neither of the two others (its front), which do match each other and their
    twins. From the first view's group two views are placed, from theirs four: the result takes
    the frame of start/rgb/001.png, says so, and finds the door (3.0 deg; in the first view's frame
    the four views were left out and the door was unmatched)."""
    import sparseart
    from sparseart.bench.evaluate import evaluate
    from sparseart.bench.grid import grid_settings
    from sparseart.bench.objects import render_cached
    from sparseart.io.scene import load_scene

    setting = next(s for s in grid_settings(3)[0] if s.name == "realistic")
    scene_dir = tmp_path / "fridge"
    gt, _ = render_cached(PARTNET_DIR / "refrigerator_11231", scene_dir, setting)
    result = sparseart.run(scene_dir, seed=3)
    assert result.frame_reference.endswith("start/rgb/001.png")
    assert any("results are in the OpenCV frame of start/rgb/001.png" in w for w in result.warnings)
    rows = evaluate(result, load_scene(scene_dir), gt)
    assert len(rows) == 1 and rows[0]["type_correct"] and rows[0]["axis_deg"] < 10.0, rows
