"""Learned matchers from the REAL ONNX weights in ../shared/models (XFeat, XFeat 320x224,
LighterGlue L3): agreement with one homography on a real static-camera photo pair, 3D agreement of
lifted matches between two rendered views with ground-truth poses (vs SIFT), the post-processing
pieces on synthetic arrays, the feature cache, the LightGlue-pipeline adapter (with the stand-in
of ``lightglue_builders``) and the one-line errors of bad specs and wrong models."""
from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from conftest import PARTNET_DIR, PARTNET_REASON
from lightglue_builders import build_lightglue
from sparseart.align.matchers import (LightGluePipelineMatcher, LighterGlueMatcher, LiftedMatcher, MatcherError,
                                      PixelMatcher, PixelMatches, XFeatExtractor, XFeatMNNMatcher,
                                      keypoint_heatmap, lifted_matches, mutual_nearest_neighbours,
                                      nms_keypoints, open_matcher, sample_map)
from sparseart.types import SceneError

SHARED = Path(__file__).resolve().parents[2] / "shared"
MODELS = SHARED / "models"
XFEAT, XFEAT_FIXED, LIGHTERGLUE = MODELS / "xfeat.onnx", MODELS / "xfeat_320x224.onnx", MODELS / "lighterglue_L3.onnx"
REAL = SHARED / "data" / "real" / "screwmimic_close_laptop_2"
THREADS = 2


def _need(*paths: Path) -> None:
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        pytest.skip(f"real weights/data not found: {', '.join(missing)} (see ../shared/models/README.md)")


def _read_rgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


@pytest.fixture(scope="module")
def extractor() -> XFeatExtractor:
    _need(XFEAT)
    return XFeatExtractor(XFEAT, threads=THREADS)


@pytest.fixture(scope="module")
def lighterglue(extractor) -> LighterGlueMatcher:
    _need(LIGHTERGLUE)
    return LighterGlueMatcher(extractor, LIGHTERGLUE, threads=THREADS)


@pytest.fixture(scope="module")
def real_pair() -> tuple[np.ndarray, np.ndarray]:
    a, b = REAL / "start" / "rgb" / "000.png", REAL / "end" / "rgb" / "000.png"
    _need(a, b)
    return _read_rgb(a), _read_rgb(b)


def _homography_inliers(matches: PixelMatches) -> float:
    _, inliers = cv2.findHomography(matches.pixels_a, matches.pixels_b, cv2.RANSAC, 4.0, maxIters=5000,
                                    confidence=0.999)
    return float(inliers.mean())


def _check_matches(matches: PixelMatches, shape: tuple[int, ...]) -> None:
    h, w = shape[:2]
    assert matches.pixels_a.shape == matches.pixels_b.shape == (len(matches), 2)
    assert matches.scores.shape == (len(matches),)
    assert np.all((matches.scores >= 0) & (matches.scores <= 1))
    for pixels in (matches.pixels_a, matches.pixels_b):
        assert np.all((pixels >= -0.5) & (pixels <= [w - 0.5, h - 0.5]))


# ----------------------------------------------------------------------------- real photo pair


@pytest.mark.parametrize("kind", ["xfeat+lighterglue", "xfeat-mnn", "xfeat320x224+lighterglue"])
def test_real_static_camera_pair_fits_one_homography(kind, real_pair, extractor, lighterglue):
    """Static camera, a person moves the laptop lid: most matches lie on the static scene."""
    if kind == "xfeat+lighterglue":
        matcher = lighterglue
    elif kind == "xfeat-mnn":
        matcher = XFeatMNNMatcher(extractor)
    else:
        _need(XFEAT_FIXED)
        matcher = open_matcher(f"xfeat:{XFEAT_FIXED},{LIGHTERGLUE}", threads=THREADS)
        assert matcher.extractor.fixed_size == (224, 320)
    a, b = real_pair
    matches = matcher.match(a, b)
    _check_matches(matches, a.shape)
    fraction = _homography_inliers(matches)
    print(f"{kind}: {len(matches)} matches, keypoints {matches.n_keypoints}, homography inliers {fraction:.2f}")
    assert len(matches) >= 200
    assert fraction >= 0.6


def test_feature_cache_runs_each_image_once(real_pair, extractor):
    a, b = real_pair
    mnn = XFeatMNNMatcher(extractor)
    before = extractor.runs
    first = mnn.match(a, b)
    mnn.match(b, a)                              # same pixels: hash keys hit the cache
    again = mnn.match(a.copy(), b)               # a copy has the same hash
    assert extractor.runs - before <= 2
    np.testing.assert_array_equal(first.pixels_a, again.pixels_a)
    keyed = extractor.features(a, key="start/000")
    assert extractor.features(a, key="start/000") is keyed
    runs = extractor.runs
    extractor.features(cv2.resize(a, (320, 240)), key="start/000")   # other shape: not served stale
    assert extractor.runs == runs + 1


def test_extractor_output_contract(real_pair, extractor):
    a, _ = real_pair
    features = extractor.extract(a)
    assert 0 < len(features) <= extractor.max_keypoints
    assert features.image_size == (a.shape[1], a.shape[0])
    np.testing.assert_allclose(np.linalg.norm(features.descriptors, axis=1), 1.0, atol=1e-5)
    assert np.all(np.diff(features.scores) <= 0) and np.all(features.scores > 0)
    assert extractor.model_size(480, 640) == (480, 640)
    assert extractor.model_size(240, 320) == (480, 640)     # small images are enlarged (upscale)
    assert extractor.model_size(1080, 1920) == (352, 640)


# ----------------------------------------------------------------------------- rendered pair, GT poses


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    obj = PARTNET_DIR / "box_rotate_100221"
    if not obj.is_dir():
        pytest.skip(PARTNET_REASON)
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.io.scene import load_scene
    from sparseart.lift.rgbd import pointmap_from_depth

    root = tmp_path_factory.mktemp("matchers") / "scene"
    render_partnet_scene(obj, root, views=3, seed=0)
    frames = load_scene(root).start[:2]
    return frames, [pointmap_from_depth(f) for f in frames]   # world frame (cameras.json poses)


def test_rendered_views_lifted_matches_agree_in_3d(rendered, extractor, lighterglue):
    from sparseart.align.features import match_features
    from sparseart.geometry.clouds import valid_points

    frames, pointmaps = rendered
    points = np.concatenate([valid_points(p) for p in pointmaps])
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    counts = {}
    for name, matcher in (("xfeat+lighterglue", lighterglue), ("xfeat-mnn", XFeatMNNMatcher(extractor))):
        matches = lifted_matches(matcher, frames[0], pointmaps[0], frames[1], pointmaps[1])
        distance = np.linalg.norm(matches.points_a - matches.points_b, axis=1)
        counts[name] = len(matches)
        print(f"{name}: {len(matches)} lifted matches ({matches.n_ratio_passed} before lifting), median 3D "
              f"distance {np.median(distance) / diagonal:.4f} of the object diagonal")
        assert len(matches) >= 100
        assert np.median(distance) < 0.03 * diagonal
        assert matches.view_a.shape == (len(matches),) and matches.n_keypoints[0] > 0
    sift = match_features(frames[0], pointmaps[0], frames[1], pointmaps[1])
    print(f"SIFT: {len(sift)} lifted matches")
    assert counts["xfeat+lighterglue"] > 3 * max(len(sift), 1)
    # align.py's pair-matcher interface gives the same matches.
    same = LiftedMatcher(lighterglue).match(frames[0], pointmaps[0], frames[1], pointmaps[1])
    assert len(same) == counts["xfeat+lighterglue"]


# ----------------------------------------------------------------------------- pure pieces


def test_heatmap_layout_nms_and_sampling():
    logits = np.full((65, 2, 3), -20.0, np.float32)
    logits[64] = 0.0
    logits[8 * 5 + 2, 1, 2] = 20.0          # cell (row 1, col 2), sub-pixel row 5, col 2
    heat = keypoint_heatmap(logits)
    assert heat.shape == (16, 24)
    assert np.unravel_index(heat.argmax(), heat.shape) == (8 + 5, 16 + 2)
    np.testing.assert_array_equal(nms_keypoints(heat), [[18, 13]])
    plateau = np.zeros((10, 10), np.float32)
    plateau[2, 2] = plateau[2, 3] = 0.5     # ties are both kept (torch max-pool NMS)
    plateau[7, 7] = 0.04                    # below the threshold
    assert len(nms_keypoints(plateau)) == 2

    maps = np.random.default_rng(0).normal(size=(4, 5, 6)).astype(np.float32)
    u, v = np.array([0.0, 3.0, 5.0]), np.array([0.0, 2.0, 4.0])
    for mode in ("bilinear", "bicubic"):
        np.testing.assert_allclose(sample_map(maps, u, v, mode), maps[:, v.astype(int), u.astype(int)].T, atol=1e-5)
    half = sample_map(maps, np.array([1.5]), np.array([2.0]))
    np.testing.assert_allclose(half[0], (maps[:, 2, 1] + maps[:, 2, 2]) / 2, atol=1e-6)
    outside = sample_map(maps, np.array([-0.5]), np.array([0.0]))   # half a cell into the zero border
    np.testing.assert_allclose(outside[0], maps[:, 0, 0] / 2, atol=1e-6)


def test_mutual_nearest_neighbours():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(300, 64)).astype(np.float32)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    order = rng.permutation(300)
    b = a[order] + 0.01 * rng.normal(size=(300, 64)).astype(np.float32)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    ia, ib, sim = mutual_nearest_neighbours(a, b[:250], 0.82)
    assert len(ia) == 250 - np.sum(order[:250] >= 300)
    np.testing.assert_array_equal(order[ib], ia)
    assert np.all(sim > 0.82)
    empty = mutual_nearest_neighbours(a, np.zeros((0, 64), np.float32))
    assert all(len(x) == 0 for x in empty)


# ----------------------------------------------------------------------------- pipeline adapter, specs


def test_lightglue_pipeline_adapter(tmp_path):
    pix = np.array([[10.0, 20.0], [100.0, 50.0], [30.0, 70.0]])
    model = build_lightglue(tmp_path / "lg.onnx", pix, pix + 5, np.array([[0, 0, 0], [0, 1, 1], [0, 2, 2], [1, 0, 0]]),
                            np.array([0.9, 0.8, 0.05, 0.9]), height=None, width=None, channels=3)
    matcher = open_matcher(str(model), threads=1)
    assert isinstance(matcher, LightGluePipelineMatcher) and isinstance(matcher, PixelMatcher)
    image = np.zeros((120, 160, 3), np.uint8)
    matches = matcher.match(image, image)
    np.testing.assert_allclose(matches.pixels_a, pix[:2])     # 160 x 120 <= max_side: identity mapping
    np.testing.assert_allclose(matches.pixels_b, pix[:2] + 5)
    np.testing.assert_allclose(matches.scores, [0.9, 0.8], atol=1e-6)
    contract = tmp_path / "m.json"
    contract.write_text(json.dumps({"schema": "sparseart-matcher/1", "kind": "lightglue-pipeline",
                                    "matcher": "lg.onnx", "min_score": 0.85}))
    assert len(open_matcher(contract, threads=1).match(image, image)) == 1
    assert len(open_matcher(contract, threads=1, min_score=0.0).match(image, image)) == 3   # override wins


def test_json_contract_resolves_relative_paths(tmp_path):
    _need(XFEAT, LIGHTERGLUE)
    contract = tmp_path / "sub" / "matcher.json"
    contract.parent.mkdir()
    contract.write_text(json.dumps({
        "schema": "sparseart-matcher/1", "kind": "xfeat+lighterglue",
        "detector": os.path.relpath(XFEAT, contract.parent), "matcher": os.path.relpath(LIGHTERGLUE, contract.parent),
        "min_score": 0.3, "max_keypoints": 512, "max_side": 320, "upscale": False}))
    matcher = open_matcher(contract, threads=1)
    assert isinstance(matcher, LighterGlueMatcher) and matcher.min_score == 0.3
    assert matcher.extractor.max_keypoints == 512 and matcher.extractor.model_size(480, 640) == (256, 320)
    contract.write_text(json.dumps({"schema": "sparseart-matcher/1", "kind": "xfeat",
                                    "detector": str(XFEAT), "min_similarity": 0.9}))
    mnn = open_matcher(contract, threads=1)
    assert isinstance(mnn, XFeatMNNMatcher) and mnn.min_similarity == 0.9
    with pytest.raises(MatcherError, match="min_score does not apply"):
        open_matcher(contract, threads=1, min_score=0.5)
    assert open_matcher(f"xfeat:{XFEAT},{LIGHTERGLUE}", threads=1, min_score=0.5).min_score == 0.5


def _tiny_model(path: Path) -> Path:
    """A valid ONNX model that is no feature model: x [1, 3, H, W] -> Relu -> y."""
    graph = helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "tiny",
                              [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, "H", "W"])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 3, "H", "W"])])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


def _one_line_error(spec, *needles: str) -> str:
    with pytest.raises(SceneError) as info:
        open_matcher(spec, threads=1)
    text = str(info.value)   # MatcherError, or lift's ModelError from the LightGlue pipeline adapter
    assert "\n" not in text and text.strip()
    for needle in needles:
        assert needle in text, text
    return text


def test_bad_specs_and_files(tmp_path):
    _one_line_error("", "empty")
    _one_line_error("xfeat:", "xfeat:DET.onnx")
    _one_line_error("xfeat:a.onnx,b.onnx,c.onnx", "xfeat:DET.onnx")
    _one_line_error("superglue:model.onnx", "unknown kind 'superglue'")
    _one_line_error(f"xfeat:{tmp_path / 'missing.onnx'}", "missing.onnx", "not found")
    _one_line_error(str(tmp_path / "missing_pipeline.onnx"), "missing_pipeline.onnx", "not found")
    (tmp_path / "notes.txt").write_text("x")
    _one_line_error(str(tmp_path / "notes.txt"), "notes.txt")
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a protobuf at all")
    _one_line_error(f"xfeat:{garbage}", "garbage.onnx")
    tiny = _tiny_model(tmp_path / "tiny.onnx")
    _one_line_error(f"xfeat:{tiny}", "tiny.onnx", "not an XFeat backbone", "x [1, 3, ?, ?] float")


def test_bad_json_contracts(tmp_path):
    contract = tmp_path / "m.json"

    def check(payload, *needles):
        contract.write_text(payload if isinstance(payload, str) else json.dumps(payload))
        _one_line_error(str(contract), "m.json", *needles)

    base = {"schema": "sparseart-matcher/1", "kind": "xfeat", "detector": "det.onnx"}
    check("{not json", "not valid JSON")
    check([1, 2], "JSON object")
    check({**base, "schema": "other/2"}, "'schema'")
    check({**base, "kind": "sift"}, "'kind'")
    check({**base, "treshold": 0.1}, "unknown field(s) treshold")
    check({**base, "min_score": 0.2}, "min_score", "do not apply")
    check({**base, "max_keypoints": 0}, "'max_keypoints'")
    check({**base, "min_similarity": "high"}, "'min_similarity'")
    check({**base, "upscale": "yes"}, "'upscale'")
    check({k: v for k, v in base.items() if k != "detector"}, "'detector'")
    check(base, "det.onnx", "not found")
    _one_line_error(str(tmp_path / "absent.json"), "absent.json", "not found")


def test_wrong_models_list_their_io(tmp_path):
    _need(XFEAT, LIGHTERGLUE)
    text = _one_line_error(f"xfeat:{LIGHTERGLUE}", "lighterglue_L3.onnx", "not an XFeat backbone", "kpts0 [1, ?, 2]")
    assert "outputs: matches" in text
    _one_line_error(f"xfeat:{XFEAT},{XFEAT}", "xfeat.onnx", "not a LighterGlue matcher", "keypoint_logits")
    _one_line_error(f"xfeat:{XFEAT},{_tiny_model(tmp_path / 'tiny.onnx')}", "tiny.onnx", "not a LighterGlue")
    with pytest.raises(MatcherError, match="uint8 RGB"):
        XFeatMNNMatcher(XFeatExtractor(XFEAT, threads=1)).match(np.zeros((10, 10, 3)), np.zeros((10, 10, 3)))
