"""ONNX reconstructor adapter: exact tiny models (tests/onnx_builders.py) must reproduce the RGB-D
path, through pad, crop and scale mappings, both run modes, presets and contracts; every error
path ends in one clear line."""
from __future__ import annotations

import json
import re
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import requires_partnet, PARTNET_DIR
from onnx_builders import (build_passthrough, build_reconstructor, contract_json, encode_depth_rgb,
                           write_json)
from sparseart.datasets import partnet
from sparseart.datasets.synth import render_synth_scene
from sparseart.lift import build_labelled_cloud, pointmap_from_depth
from sparseart.lift.contract import ModelError, parse_contract
from sparseart.lift.onnx_model import (OnnxLiftOptions, Reconstructor, confidence_to_unit,
                                       decode_vggt_pose_encoding, lift_scene_with_model)
from sparseart.lift.preprocess import SizeRule, plan_mapping
from sparseart.io.scene import load_scene
from sparseart.types import SceneError

POINT_TOL = 1e-5  # metres: float32 depth, pose and field of view against the float64 RGB-D path


def _half_size_intrinsics(width: int, height: int, hfov_deg: float = partnet.DEFAULT_HFOV_DEG) -> np.ndarray:
    """VGGT's principal-point convention (W/2, H/2), so a VGGT-layout model can be exact."""
    f = width / (2.0 * math.tan(math.radians(hfov_deg) / 2.0))
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def _rgb_only_copy(scene_dir: Path, target: Path) -> Path:
    """The scene with each RGB image replaced by its depth PNG encoded in R, G, B (no depth/)."""
    for state in ("start", "end"):
        for depth_path in sorted((scene_dir / state / "depth").glob("*.png")):
            depth = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
            (target / state / "rgb").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(target / state / "rgb" / depth_path.name), encode_depth_rgb(depth)[:, :, ::-1])
        shutil.copytree(scene_dir / state / "mask", target / state / "mask")
    shutil.copy(scene_dir / "cameras.json", target / "cameras.json")
    return target


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("onnx_scenes")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(partnet, "intrinsics", _half_size_intrinsics)
        render_synth_scene(root / "half70", views=2, width=70, height=50)
    render_synth_scene(root / "center70", views=2, width=70, height=50)
    render_synth_scene(root / "center49", views=2, width=49, height=35)
    for name in ("half70", "center70", "center49"):
        _rgb_only_copy(root / name, root / f"{name}_rgb")
    return {name: root / name for name in ("half70", "center70", "center49")}


def _relative_poses(scene, world_to_reference: np.ndarray) -> list[np.ndarray]:
    """cam_from_reference (4, 4) of every frame, start then end."""
    return [np.linalg.inv(world_to_reference @ f.camera.cam_to_world) for f in scene.all_frames]


def _first_camera_model(scene_dir: Path, path: Path, grid: tuple[int, int], K_grid: np.ndarray, **kw) -> Path:
    scene = load_scene(scene_dir)
    poses = _relative_poses(scene, np.linalg.inv(scene.start[0].camera.cam_to_world))
    return build_reconstructor(path, width=grid[0], height=grid[1], K_grid=K_grid, cam_from_world=poses, **kw)


def _assert_matches_rgbd(scene_dir: Path, lift, mode: str, atol: float = POINT_TOL, rows_cut: int = 0) -> None:
    """Every pointmap equals pointmap_from_depth in the frame the lift says it uses."""
    scene = load_scene(scene_dir)
    for state in ("start", "end"):
        reference_c2w = (scene.start[0] if mode == "joint" else scene.frames(state)[0]).camera.cam_to_world
        for frame, pointmap, camera in zip(scene.frames(state), lift.pointmaps(state), lift.cameras(state)):
            to_reference = np.linalg.inv(reference_c2w) @ frame.camera.cam_to_world
            expected = pointmap_from_depth(frame, cam_to_world=to_reference)
            valid = expected.valid.reshape(frame.shape).copy()
            if rows_cut:
                valid[:rows_cut] = valid[-rows_cut:] = False
            valid = valid.reshape(-1)
            assert (pointmap.height, pointmap.width) == frame.shape
            np.testing.assert_array_equal(pointmap.valid, valid)
            np.testing.assert_allclose(pointmap.points[valid], expected.points[valid], atol=atol, rtol=0)
            assert np.all(np.isnan(pointmap.points[~valid]))
            np.testing.assert_allclose(camera.cam_to_world, to_reference, atol=1e-5)
            np.testing.assert_allclose(camera.K, frame.camera.K, atol=1e-4)


@pytest.mark.parametrize("mode", ["joint", "per_state"])
def test_vggt_preset_with_padding_reproduces_rgbd(scenes, tmp_path, mode):
    # 70x50 image -> 70x70 grid: 10 rows of white padding above and below (50 is not a multiple of 14)
    K = _half_size_intrinsics(70, 50)
    K_grid = K + [[0, 0, 0], [0, 0, 10], [0, 0, 0]]
    model = _first_camera_model(scenes["half70"], tmp_path / "vggt.onnx", (70, 70), K_grid)
    scene = load_scene(scenes["half70"].parent / "half70_rgb", require_depth=False)
    lift = lift_scene_with_model(scene, model, OnnxLiftOptions(mode=mode))
    assert lift.contract.startswith("vggt-1b-akretz (built-in preset")
    assert (lift.frame, lift.scale) == (mode, "relative") and lift.warnings == []
    _assert_matches_rgbd(scenes["half70"], lift, mode)
    cloud = build_labelled_cloud("start", scene.start, lift.start)
    assert len(cloud) == sum(int(p.valid.sum()) for p in lift.start) and np.all(cloud.segment >= -1)


def test_point_head_and_auto_mode(scenes, tmp_path):
    K_grid = _half_size_intrinsics(70, 50) + [[0, 0, 0], [0, 0, 10], [0, 0, 0]]
    model = _first_camera_model(scenes["half70"], tmp_path / "vggt.onnx", (70, 70), K_grid)
    scene = load_scene(scenes["half70"].parent / "half70_rgb", require_depth=False)
    lift = lift_scene_with_model(scene, model, OnnxLiftOptions(prefer="point_head"))
    assert lift.frame == "joint"  # auto: the model takes any number of frames
    _assert_matches_rgbd(scenes["half70"], lift, "joint", atol=1e-4)


def test_auto_mode_falls_back_to_per_state_and_joint_refuses(scenes, tmp_path):
    K_grid = _half_size_intrinsics(70, 50) + [[0, 0, 0], [0, 0, 10], [0, 0, 0]]
    model = _first_camera_model(scenes["half70"], tmp_path / "vggt.onnx", (70, 70), K_grid, fixed_frames=2)
    scene = load_scene(scenes["half70"].parent / "half70_rgb", require_depth=False)
    lift = lift_scene_with_model(scene, model, OnnxLiftOptions())
    assert lift.frame == "per_state"
    _assert_matches_rgbd(scenes["half70"], lift, "per_state")
    with pytest.raises(ModelError, match=r"takes 2-2 frames per pass, got 4"):
        lift_scene_with_model(scene, model, OnnxLiftOptions(mode="joint"))


def test_crop_mapping_sidecar_contract(scenes, tmp_path):
    # 70x50 image -> 70x42 grid: 4 rows cropped above and below; they have no output
    K_grid = _half_size_intrinsics(70, 50) - [[0, 0, 0], [0, 0, 4], [0, 0, 0]]
    model = _first_camera_model(scenes["half70"], tmp_path / "crop.onnx", (70, 42), K_grid, input_name="images")
    write_json(tmp_path / "crop.contract.json",
               contract_json("crop", resize="crop", interp="cubic", principal_point="half_size"))
    scene = load_scene(scenes["half70"].parent / "half70_rgb", require_depth=False)
    lift = lift_scene_with_model(scene, model, OnnxLiftOptions(mode="per_state"))
    assert lift.contract.startswith("crop (") and lift.scale == "metric"
    _assert_matches_rgbd(scenes["half70"], lift, "per_state", rows_cut=4)


def test_scaled_grid_explicit_contract(scenes, tmp_path):
    # 49x35 image -> x2 (nearest) = 98x70, padded to 98x98 (14 rows each side); principal point (W-1)/2
    K = load_scene(scenes["center49"]).start[0].camera.K
    K_grid = np.array([[2 * K[0, 0], 0, 2 * K[0, 2] + 0.5], [0, 2 * K[1, 1], 2 * K[1, 2] + 0.5 + 14], [0, 0, 1]])
    model = _first_camera_model(scenes["center49"], tmp_path / "x2.onnx", (98, 98), K_grid, input_name="images")
    contract = write_json(tmp_path / "explicit.json", contract_json("x2", long_side=98))
    scene = load_scene(scenes["center49"].parent / "center49_rgb", require_depth=False)
    lift = lift_scene_with_model(scene, model, OnnxLiftOptions(contract_path=contract))
    assert lift.start[0].width == 49 and lift.start[0].height == 35
    _assert_matches_rgbd(scenes["center49"], lift, "joint")
    # the same model read with VGGT's principal point convention is measurably wrong
    wrong = write_json(tmp_path / "wrong.json", contract_json("x2", long_side=98, principal_point="half_size"))
    off = lift_scene_with_model(scene, model, OnnxLiftOptions(contract_path=wrong))
    with pytest.raises(AssertionError):
        _assert_matches_rgbd(scenes["center49"], off, "joint")


def test_da3_preset_world_frame_is_reexpressed(scenes, tmp_path):
    # DA3 layout: ImageNet normalisation on the host, w2c extrinsics in the scene's world frame
    scene_rgbd = load_scene(scenes["center70"])
    K_grid = scene_rgbd.start[0].camera.K + [[0, 0, 0], [0, 0, 10], [0, 0, 0]]
    model = build_reconstructor(tmp_path / "da3.onnx", width=70, height=70, K_grid=K_grid, layout="da3",
                                cam_from_world=_relative_poses(scene_rgbd, np.eye(4)))
    scene = load_scene(scenes["center70"].parent / "center70_rgb", require_depth=False)
    lift = lift_scene_with_model(scene, model, OnnxLiftOptions(mode="joint"))
    assert lift.contract.startswith("depth-anything-3-official (built-in preset")
    _assert_matches_rgbd(scenes["center70"], lift, "joint", atol=2e-5)


def test_float16_model_matches_float32(scenes, tmp_path):
    K_grid = _half_size_intrinsics(70, 50) + [[0, 0, 0], [0, 0, 10], [0, 0, 0]]
    model = _first_camera_model(scenes["half70"], tmp_path / "fp16.onnx", (70, 70), K_grid, float16=True)
    reconstructor = Reconstructor(model)
    assert reconstructor.input_dtype == np.float16
    assert any("float16" in w for w in reconstructor.warnings)
    scene = load_scene(scenes["half70"].parent / "half70_rgb", require_depth=False)
    lift = lift_scene_with_model(scene, reconstructor, OnnxLiftOptions(mode="joint"))
    _assert_matches_rgbd(scenes["half70"], lift, "joint")


def test_wrong_quaternion_order_is_flagged(scenes, tmp_path):
    K_grid = _half_size_intrinsics(70, 50) + [[0, 0, 0], [0, 0, 10], [0, 0, 0]]
    model = _first_camera_model(scenes["half70"], tmp_path / "q.onnx", (70, 70), K_grid, input_name="images")
    data = contract_json("wxyz", principal_point="half_size")
    data["outputs"]["camera"]["quat_order"] = "wxyz"
    write_json(tmp_path / "q.contract.json", data)
    scene = load_scene(scenes["half70"].parent / "half70_rgb", require_depth=False)
    lift = lift_scene_with_model(scene, model, OnnxLiftOptions(mode="joint"))
    assert any("px (median) from its pixels" in w for w in lift.warnings)


def test_external_data_model_loads_and_missing_data_is_named(scenes, tmp_path):
    K_grid = _half_size_intrinsics(70, 50) + [[0, 0, 0], [0, 0, 10], [0, 0, 0]]
    model = _first_camera_model(scenes["half70"], tmp_path / "ext.onnx", (70, 70), K_grid, external_data=True)
    assert (tmp_path / "ext.onnx.data").stat().st_size > (tmp_path / "ext.onnx").stat().st_size
    scene = load_scene(scenes["half70"].parent / "half70_rgb", require_depth=False)
    _assert_matches_rgbd(scenes["half70"], lift_scene_with_model(scene, model), "joint")
    (tmp_path / "ext.onnx.data").rename(tmp_path / "moved.data")
    with pytest.raises(ModelError, match=r"ext\.onnx: external data file .*ext\.onnx\.data not found"):
        Reconstructor(model)


@requires_partnet
def test_partnet_object_per_state(tmp_path):
    partnet.render_partnet_scene(PARTNET_DIR / "drawer_26525", tmp_path / "drawer", views=2, width=70, height=50)
    scene_rgbd = load_scene(tmp_path / "drawer")
    K_grid = scene_rgbd.start[0].camera.K + [[0, 0, 0], [0, 0, 10], [0, 0, 0]]
    model = build_reconstructor(tmp_path / "da3.onnx", width=70, height=70, K_grid=K_grid, layout="da3",
                                cam_from_world=_relative_poses(scene_rgbd, np.eye(4)))
    scene = load_scene(_rgb_only_copy(tmp_path / "drawer", tmp_path / "drawer_rgb"), require_depth=False)
    lift = lift_scene_with_model(scene, model, OnnxLiftOptions(mode="per_state"))
    _assert_matches_rgbd(tmp_path / "drawer", lift, "per_state", atol=2e-5)


# --------------------------------------------------------------------------- pure functions


def test_pixel_map_round_trips_and_grid_rules():
    for width, height, rule in [(1024, 768, SizeRule(long_side=518, resize="pad")),
                                (768, 1024, SizeRule(long_side=518, resize="crop")),
                                (640, 480, SizeRule(height=518, width=518, resize="pad")),
                                (333, 250, SizeRule(long_side=None, resize="stretch"))]:
        mapping = plan_mapping(width, height, rule)
        assert mapping.grid_width % 14 == 0 and mapping.grid_height % 14 == 0
        u = np.array([0.0, width - 1.0, 17.25])
        v = np.array([0.0, height - 1.0, 3.5])
        back = mapping.to_image(*mapping.to_grid(u, v))
        np.testing.assert_allclose(back, (u, v), atol=1e-12)
        K = np.array([[500.0, 0.0, width / 2 - 3], [0.0, 490.0, height / 2 + 2], [0.0, 0.0, 1.0]])
        np.testing.assert_allclose(mapping.K_to_image(mapping.K_to_grid(K)), K, atol=1e-9)
    pad = plan_mapping(1024, 768, SizeRule(long_side=518, resize="pad"))
    assert (pad.grid_width, pad.grid_height, pad.offset_x, pad.offset_y) == (518, 392, 0.0, 2.0)


def test_vggt_pose_decoding_and_confidence():
    quarter = np.array([0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)])  # 90 deg about z, xyzw
    pose = np.concatenate([[0.1, -0.2, 0.3], quarter, [2 * math.atan(0.5), 2 * math.atan(0.75)]])[None]
    K, cam_from_world = decode_vggt_pose_encoding(pose, width=60, height=40)
    np.testing.assert_allclose(cam_from_world[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(cam_from_world[0, :3, 3], [0.1, -0.2, 0.3])
    np.testing.assert_allclose(K[0], [[40.0, 0, 30.0], [0, 40.0, 20.0], [0, 0, 1]], atol=1e-12)
    K_center, _ = decode_vggt_pose_encoding(pose, width=60, height=40, principal_point="center")
    assert (K_center[0, 0, 2], K_center[0, 1, 2]) == (29.5, 19.5)
    with pytest.raises(ModelError, match="zero quaternion"):
        decode_vggt_pose_encoding(np.zeros((1, 9)), 60, 40)
    np.testing.assert_allclose(confidence_to_unit(np.array([1.0, 2.0, 4.0, np.nan]), "expp1"), [0, 0.5, 0.75, 0])
    np.testing.assert_allclose(confidence_to_unit(np.array([0.0]), "logit"), [0.5])


# --------------------------------------------------------------------------- errors


@pytest.fixture
def tiny_model(tmp_path) -> Path:
    K = np.array([[20.0, 0, 7.0], [0, 20.0, 7.0], [0, 0, 1]])
    return build_reconstructor(tmp_path / "tiny.onnx", width=14, height=14, K_grid=K,
                               cam_from_world=[np.eye(4)] * 4, input_name="images")


def test_missing_and_corrupt_model_files(tmp_path):
    with pytest.raises(SceneError, match=r"nothere\.onnx: model file not found"):
        Reconstructor(tmp_path / "nothere.onnx")
    (tmp_path / "bad.onnx").write_bytes(b"\x08\x07not a protobuf" * 20)
    with pytest.raises(ModelError, match=r"bad\.onnx: not a valid ONNX model"):
        Reconstructor(tmp_path / "bad.onnx")


def test_unmatched_model_lists_inputs_and_outputs(tmp_path):
    model = build_passthrough(tmp_path / "other.onnx")
    with pytest.raises(ModelError) as error:
        Reconstructor(model)
    message = str(error.value)
    assert "\n" not in message and "no built-in preset matches" in message
    assert "inputs: foo [?, 3, 14, 14] float" in message and "outputs: bar [?, 3, 14, 14] float" in message


@pytest.mark.parametrize("kw, pattern", [({"ir_version": 99}, r"IR version 99 is newer than onnxruntime"),
                                         ({"opset": 99}, r"opset 99 is not supported by onnxruntime")])
def test_unsupported_ir_and_opset(tmp_path, kw, pattern):
    K = np.array([[20.0, 0, 7.0], [0, 20.0, 7.0], [0, 0, 1]])
    model = build_reconstructor(tmp_path / "new.onnx", width=14, height=14, K_grid=K, cam_from_world=[np.eye(4)], **kw)
    with pytest.raises(ModelError, match=r"new\.onnx: model " + pattern):
        Reconstructor(model)


def test_memory_checks_fail_with_numbers(tiny_model, tmp_path):
    write_json(tmp_path / "tiny.contract.json", contract_json("tiny", long_side=14))
    size = tiny_model.stat().st_size
    with pytest.raises(ModelError, match=r"weights take 0\.\d+ MB but only 0\.\d+ MB of RAM"):
        Reconstructor(tiny_model, OnnxLiftOptions(memory_limit_bytes=size // 2))
    reconstructor = Reconstructor(tiny_model, OnnxLiftOptions(memory_limit_bytes=size + 1000))
    image = encode_depth_rgb(np.full((10, 14), 900, np.uint16))
    with pytest.raises(ModelError, match=r"running 2 frames at 14x14 needs about [\d.]+ MB \(inputs .*\) but only [\d.]+ MB of RAM"):
        reconstructor.reconstruct([image, image])
    generous = Reconstructor(tiny_model, OnnxLiftOptions(memory_limit_bytes=10**9))
    assert generous.reconstruct([image])[0].valid.any()


def test_contract_precedence(tiny_model, tmp_path):
    K = np.array([[20.0, 0, 7.0], [0, 20.0, 7.0], [0, 0, 1]])
    meta = json.dumps(contract_json("from-metadata", input_name="input_images", long_side=14))
    model = build_reconstructor(tmp_path / "m.onnx", width=14, height=14, K_grid=K, cam_from_world=[np.eye(4)],
                                metadata={"pointmap-onnx": meta})
    assert Reconstructor(model).contract.name == "from-metadata"
    write_json(tmp_path / "m.contract.json", contract_json("from-sidecar", input_name="input_images"))
    assert Reconstructor(model).contract.name == "from-sidecar"
    explicit = write_json(tmp_path / "x.json", contract_json("explicit", input_name="input_images"))
    assert Reconstructor(model, OnnxLiftOptions(contract_path=explicit)).contract.name == "explicit"
    plain = build_reconstructor(tmp_path / "p.onnx", width=14, height=14, K_grid=K, cam_from_world=[np.eye(4)],
                                metadata={"pointmap_contract": meta})
    assert Reconstructor(plain).contract.name == "from-metadata"  # the research doc's key works too
    bare = build_reconstructor(tmp_path / "b.onnx", width=14, height=14, K_grid=K, cam_from_world=[np.eye(4)])
    assert Reconstructor(bare).contract.name == "vggt-1b-akretz"


@pytest.mark.parametrize("edit, pattern", [
    (lambda c: c["inputs"]["images"].update(layout="SXHW"), r"field 'inputs\.images\.layout' 'SXHW' is not a valid layout"),
    (lambda c: c.update(schema="pointmap-onnx/9"), r"field 'schema' must be 'pointmap-onnx/1'"),
    (lambda c: c["outputs"]["depth_conf"].update(kind="softplus"), r"field 'outputs\.depth_conf\.kind' must be one of"),
    (lambda c: c["inputs"]["images"].update(mean=[0.5, 0.5]), r"field 'inputs\.images\.mean' must be a list of 3"),
    (lambda c: c["inputs"]["images"].update(interpolation="cubic"), r"field 'inputs\.images\.interpolation' is not a known field"),
    (lambda c: c["outputs"].pop("camera") and c["outputs"].pop("points"), r"field 'outputs\.camera' is required"),
    (lambda c: c.update(confidence={"threshold": 2}), r"field 'confidence\.threshold' must be in \[0\.0, 1\.0\]"),
])
def test_invalid_contract_names_file_and_field(tiny_model, tmp_path, edit, pattern):
    data = contract_json("tiny")
    edit(data)
    path = write_json(tmp_path / "tiny.contract.json", data)
    with pytest.raises(ModelError, match=re.escape(str(path)) + ": contract " + pattern):
        Reconstructor(tiny_model)


def test_contract_syntax_error_and_missing_output(tiny_model, tmp_path):
    (tmp_path / "tiny.contract.json").write_text('{"schema": "pointmap-onnx/1",\n "name": }')
    with pytest.raises(ModelError, match=r"tiny\.contract\.json: invalid JSON at line 2"):
        Reconstructor(tiny_model)
    data = contract_json("tiny", output_names={"depth": "depth_map"})
    write_json(tmp_path / "tiny.contract.json", data)
    with pytest.raises(ModelError, match=r"names output 'depth_map', but the model has inputs: images"):
        Reconstructor(tiny_model)
    with pytest.raises(ModelError, match=r"contract file not found"):
        Reconstructor(tiny_model, OnnxLiftOptions(contract_path=tmp_path / "absent.json"))


def test_option_validation():
    with pytest.raises(ValueError, match="mode"):
        OnnxLiftOptions(mode="both")
    with pytest.raises(ValueError, match="confidence_threshold"):
        OnnxLiftOptions(confidence_threshold=1.5)
    with pytest.raises(ModelError, match="preset x: contract field 'inputs' is missing"):
        parse_contract({"schema": "pointmap-onnx/1", "name": "x"}, "preset x")


def test_confidence_threshold_and_percentile_invalidate_pixels(tiny_model, tmp_path):
    write_json(tmp_path / "tiny.contract.json", contract_json("tiny", long_side=14, threshold=0.5))
    image = encode_depth_rgb(np.full((14, 14), 900, np.uint16))
    image[:, 7:, 2] = 51  # raw confidence 1 + 10 * 0.2 = 3 -> 1 - 1/3 = 0.667 (left half: 11 -> 0.909)
    default = Reconstructor(tiny_model).reconstruct([image])[0]
    assert default.valid.all()
    np.testing.assert_allclose(default.confidence.reshape(14, 14)[0, [0, 13]], [1 - 1 / 11, 1 - 1 / 3], rtol=1e-6)
    strict = Reconstructor(tiny_model, OnnxLiftOptions(confidence_threshold=0.8)).reconstruct([image])[0]
    assert np.array_equal(strict.valid.reshape(14, 14), np.arange(14)[None, :].repeat(14, 0) < 7)
    assert np.all(np.isnan(strict.points[~strict.valid])) and np.all(strict.confidence[~strict.valid] == 0)
    top = Reconstructor(tiny_model, OnnxLiftOptions(confidence_percentile=60)).reconstruct([image])[0]
    assert np.array_equal(top.valid, strict.valid)
