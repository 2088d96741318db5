"""The ONNX LightGlue matcher: model checks, pixel mapping, filtering, and alignment where SIFT fails.

The scenes are the textured-rectangle rooms of ``test_align`` with *flat* (textureless) surfaces:
SIFT finds nothing there. The stand-in model (``lightglue_builders``) returns correspondences the
test computed from the true geometry, at half resolution, plus junk rows the adapter must drop.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from lightglue_builders import build_lightglue, build_split_extractor
from sparseart.align import AlignmentError, align_states, register_views
from sparseart.align.lightglue import LightGlueMatcher, LightGlueOptions
from sparseart.lift.contract import ModelError
from sparseart.bench.metrics import axis_angle_error_deg
from test_align import DOOR_MOTION, H, K, W, angle_deg, frame_of, look_at, render, room, two_states

MODEL_H, MODEL_W = H // 2, W // 2   # the stand-in runs at half resolution


def _to_model(pixels: np.ndarray) -> np.ndarray:
    return (pixels + 0.5) * (MODEL_W / W) - 0.5


def correspondences(depth_a, c2w_a, depth_b, c2w_b, motion_of=None, step: int = 6):
    """(pixels_a, pixels_b) (K, 2) x, y of grid pixels of image a that are seen in image b.

    motion_of: maps world points (N, 3) of state a to state b (moving parts); None = static scene.
    """
    rows, cols = np.mgrid[3:H:step, 3:W:step]
    z = depth_a[rows, cols]
    valid = z > 0
    pix_a = np.c_[cols[valid], rows[valid]].astype(float)
    z = z[valid]
    cam = np.c_[(pix_a[:, 0] - K[0, 2]) / K[0, 0] * z, (pix_a[:, 1] - K[1, 2]) / K[1, 1] * z, z]
    world = cam @ c2w_a[:3, :3].T + c2w_a[:3, 3]
    if motion_of is not None:
        world = motion_of(world)
    cam_b = (world - c2w_b[:3, 3]) @ c2w_b[:3, :3]
    pix_b = np.c_[K[0, 0] * cam_b[:, 0] / cam_b[:, 2] + K[0, 2], K[1, 1] * cam_b[:, 1] / cam_b[:, 2] + K[1, 2]]
    r, c = np.rint(pix_b[:, 1]).astype(int), np.rint(pix_b[:, 0]).astype(int)
    inside = (cam_b[:, 2] > 0) & (r >= 0) & (r < H) & (c >= 0) & (c < W)
    seen = np.zeros(len(pix_a), bool)
    seen[inside] = np.abs(depth_b[r[inside], c[inside]] - cam_b[inside, 2]) < 0.01
    return pix_a[seen], pix_b[seen]


def door_motion_of(rects):
    door = rects[-1]
    normal = np.cross(door.u, door.v)

    def move(world: np.ndarray) -> np.ndarray:
        offset = world - door.centre
        on_door = ((np.abs(offset @ normal) < 1e-6) & (np.abs(offset @ door.u) <= door.half[0] + 1e-9)
                   & (np.abs(offset @ door.v) <= door.half[1] + 1e-9))
        moved = world @ DOOR_MOTION[:3, :3].T + DOOR_MOTION[:3, 3]
        return np.where(on_door[:, None], moved, world)
    return move


def standin(path: Path, pix_a: np.ndarray, pix_b: np.ndarray, *, junk: bool = True, **kwargs) -> Path:
    """A stand-in whose true matches are (0, i, i) scored 0.9; with ``junk`` also low-score,
    out-of-range and wrong-batch rows the adapter must drop."""
    k = len(pix_a)
    matches = [[0, i, i] for i in range(k)]
    scores = [0.9] * k
    if junk:
        rng = np.random.default_rng(0)
        matches += [[0, i, int(rng.integers(k))] for i in range(0, k, 3)]
        scores += [0.05] * len(range(0, k, 3))
        matches += [[0, k + 5, 0], [0, 0, -1], [1, 0, 0]]
        scores += [0.9, 0.9, 0.9]
    return build_lightglue(path, _to_model(pix_a), _to_model(pix_b), np.array(matches), np.array(scores),
                           height=kwargs.pop("height", MODEL_H), width=kwargs.pop("width", MODEL_W), **kwargs)


@pytest.fixture(scope="module")
def flat_states():
    rects = room("flat")
    (fs, ps, c2w_s), (fe, pe, c2w_e) = two_states(rects, DOOR_MOTION)
    pix_a, pix_b = correspondences(fs.depth, c2w_s, fe.depth, c2w_e, door_motion_of(rects))
    return (fs, ps, c2w_s), (fe, pe, c2w_e), pix_a, pix_b


def test_match_maps_pixels_back_and_drops_junk(flat_states, tmp_path):
    (fs, ps, _), (fe, pe, _), pix_a, pix_b = flat_states
    assert len(pix_a) > 300
    matcher = LightGlueMatcher(standin(tmp_path / "lg.onnx", pix_a, pix_b))
    assert matcher.fixed_size == (MODEL_H, MODEL_W) and matcher.channels == 1
    matches = matcher.match(fs, ps, fe, pe)
    assert matches.n_ratio_passed == len(pix_a)           # low-score, out-of-range, batch-1 rows dropped
    assert len(matches) == len(pix_a)                      # every true match lifts (valid pixels)
    np.testing.assert_allclose(matches.pixels_a, pix_a, atol=1e-4)   # half-resolution grid -> original
    np.testing.assert_allclose(matches.pixels_b, pix_b, atol=1e-3)
    rows, cols = pix_a[:, 1].astype(int), pix_a[:, 0].astype(int)
    np.testing.assert_allclose(matches.points_a, ps.points[rows * W + cols])
    stricter = LightGlueMatcher(tmp_path / "lg.onnx", LightGlueOptions(min_score=0.95))
    assert len(stricter.match(fs, ps, fe, pe)) == 0


def test_matcher_aligns_textureless_states_where_sift_fails(flat_states, tmp_path):
    (fs, ps, c2w_s), (fe, pe, c2w_e), pix_a, pix_b = flat_states
    with pytest.raises(AlignmentError, match="too few feature matches"):
        align_states([fs], [ps], [fe], [pe], with_scale=False)
    matcher = LightGlueMatcher(standin(tmp_path / "lg.onnx", pix_a, pix_b))
    result = align_states([fs], [ps], [fe], [pe], with_scale=False, matcher=matcher)
    truth = np.linalg.inv(c2w_s) @ c2w_e
    assert angle_deg(result.transform.rotation.T @ truth[:3, :3]) < 0.2
    assert np.linalg.norm(result.transform.translation - truth[:3, 3]) < 0.01
    assert 0.3 < result.inliers.mean() < 1.0                   # the door's matches are outliers


def test_register_views_with_matcher(tmp_path):
    rects = room("flat", door=False)
    eyes = ((-0.3, -0.4, 0.0), (0.3, -0.3, 0.1))
    c2w = [look_at(e) for e in eyes]
    views = [frame_of(*render(rects, c), "start", i) for i, c in enumerate(c2w)]
    frames, pointmaps = [v[0] for v in views], [v[1] for v in views]
    with pytest.raises(AlignmentError, match="could not be registered"):
        register_views(frames, pointmaps, with_scale=False, geometry_fallback=False)
    pix_a, pix_b = correspondences(frames[0].depth, c2w[0], frames[1].depth, c2w[1])
    matcher = LightGlueMatcher(standin(tmp_path / "lg.onnx", pix_a, pix_b, junk=False, channels=3,
                                       height=None, width=None, float16=True),
                               LightGlueOptions(max_side=160))
    assert matcher.fixed_size is None and matcher.float16 and matcher.model_size(H, W) == (MODEL_H, MODEL_W)
    transforms, _ = register_views(frames, pointmaps, with_scale=False, geometry_fallback=False, matcher=matcher)
    truth = np.linalg.inv(c2w[0]) @ c2w[1]
    assert angle_deg(transforms[1][:3, :3].T @ truth[:3, :3]) < 0.2
    assert np.linalg.norm(transforms[1][:3, 3] - truth[:3, 3]) < 0.01


def test_bad_matcher_models_are_clear_errors(tmp_path):
    from onnx_builders import build_reconstructor

    with pytest.raises(ModelError, match=r"missing\.onnx: model file not found"):
        LightGlueMatcher(tmp_path / "missing.onnx")
    with pytest.raises(ModelError, match="split LightGlue export .* export the end-to-end pipeline"):
        LightGlueMatcher(build_split_extractor(tmp_path / "extractor.onnx"))
    reconstructor = build_reconstructor(tmp_path / "vggt.onnx", width=28, height=14, K_grid=np.array(
        [[20.0, 0, 14], [0, 20.0, 7], [0, 0, 1]]), cam_from_world=[np.eye(4)])
    with pytest.raises(ModelError, match="not a LightGlue pipeline export") as info:
        LightGlueMatcher(reconstructor)
    assert "pose_enc" in str(info.value) and "\n" not in str(info.value)
    pix = np.array([[1.0, 1.0], [2.0, 2.0]])
    with pytest.raises(ModelError, match="min_score"):
        LightGlueMatcher(standin(tmp_path / "lg.onnx", pix, pix), LightGlueOptions(min_score=2.0))


def _write_flat_scene(root: Path, fs, fe) -> Path:
    """Scene folder (unposed: K only) of the flat door room with masks (1 = room, 2 = door)."""
    for state, frame, rects_moved in (("start", fs, False), ("end", fe, True)):
        for sub in ("rgb", "depth", "mask"):
            (root / state / sub).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / state / "rgb" / "000.png"), frame.rgb[:, :, ::-1])
        cv2.imwrite(str(root / state / "depth" / "000.png"), np.round(frame.depth * 1000).astype(np.uint16))
    cameras = {"convention": "opencv", "depth_scale": 1000.0,
               **{s: [{"image": "rgb/000.png", "K": K.tolist()}] for s in ("start", "end")}}
    (root / "cameras.json").write_text(json.dumps(cameras))
    return root


def test_pipeline_and_cli_use_the_matcher(flat_states, tmp_path, capsys):
    from sparseart import cli
    from sparseart.pipeline import run

    (fs, ps, c2w_s), (fe, pe, c2w_e), pix_a, pix_b = flat_states
    rects = room("flat")
    door_start, door_end = rects[-1], rects[-1].moved(DOOR_MOTION)
    scene = _write_flat_scene(tmp_path / "scene", fs, fe)
    for state, c2w, door in (("start", c2w_s, door_start), ("end", c2w_e, door_end)):
        _, depth = render([door], c2w)
        full = cv2.imread(str(scene / state / "depth" / "000.png"), cv2.IMREAD_UNCHANGED) / 1000.0
        mask = np.where((depth > 0) & (np.abs(depth - full) < 2e-3), 2, 1).astype(np.uint8)
        cv2.imwrite(str(scene / state / "mask" / "000.png"), mask)
    model = standin(tmp_path / "lg.onnx", pix_a, pix_b)
    result = run(scene, matcher=model)
    assert not any("feature alignment of the states failed" in w for w in result.warnings), result.warnings
    assert result.frame_kind == "camera"
    (_, joint), = result.joints
    axis_true = c2w_s[:3, :3].T @ np.array([0.0, 1.0, 0.0])     # hinge axis in the start camera frame
    assert joint.type == "revolute" and axis_angle_error_deg(joint.axis, axis_true) < 2.0
    assert abs(np.degrees(abs(joint.angle)) - 30.0) < 2.0
    without = run(scene)
    assert any("feature alignment of the states failed" in w for w in without.warnings)
    out = tmp_path / "out"
    assert cli.main(["run", str(scene), "--matcher", str(model), "--out", str(out)]) == 0
    assert json.loads((out / "articulation.json").read_text())["joints"]
    assert cli.main(["run", str(scene), "--matcher-min-score", "0.5", "--out", str(out)]) != 0
    assert "--matcher-min-score needs --matcher" in capsys.readouterr().err
