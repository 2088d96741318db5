"""End to end: an RGB-only scene through a (tiny, exact) ONNX reconstructor gives the RGB-D result.

The test model decodes depth from the image pixels (tests/onnx_builders.py), so the reference RGB-D
scene carries the same depth-encoding RGB images: both runs see identical colours and geometry,
and any difference comes from the model route itself (pre-processing, pose decoding, frames).
"""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from onnx_builders import build_reconstructor, encode_depth_rgb  # noqa: E402
from sparseart import pipeline  # noqa: E402
from sparseart.cli import main  # noqa: E402
from sparseart.datasets import partnet  # noqa: E402
from sparseart.datasets.synth import render_synth_scene  # noqa: E402
from sparseart.bench.metrics import axis_angle_error_deg  # noqa: E402
from sparseart.io.scene import load_scene  # noqa: E402
from sparseart.types import SceneError  # noqa: E402

AXIS_TOLERANCE_DEG = 1.5
WIDTH, HEIGHT = 140, 98  # both multiples of 14: the VGGT grid equals the image (no padding)


def _half_size_intrinsics(width: int, height: int, hfov_deg: float = partnet.DEFAULT_HFOV_DEG) -> np.ndarray:
    f = width / (2.0 * math.tan(math.radians(hfov_deg) / 2.0))
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def _encode_rgb(scene_dir: Path, target: Path, keep_depth: bool) -> Path:
    """Copy of the scene whose RGB images carry the depth (R high byte, G low byte, B valid)."""
    shutil.copytree(scene_dir, target)
    for state in ("start", "end"):
        for depth_path in sorted((scene_dir / state / "depth").glob("*.png")):
            depth = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(target / state / "rgb" / depth_path.name), encode_depth_rgb(depth)[:, :, ::-1])
        if not keep_depth:
            shutil.rmtree(target / state / "depth")
    return target


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("onnx_pipeline")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(partnet, "intrinsics", _half_size_intrinsics)
        render_synth_scene(root / "rendered", views=2, width=WIDTH, height=HEIGHT, seed=3)
    rgbd = _encode_rgb(root / "rendered", root / "rgbd", keep_depth=True)
    rgb = _encode_rgb(root / "rendered", root / "rgb", keep_depth=False)
    # Re-express the RGB-D cameras in the first start camera's frame: the reference then works in
    # the very coordinates the model route reports in.
    cameras = json.loads((rgbd / "cameras.json").read_text())
    start0_from_world = np.linalg.inv(np.asarray(cameras["start"][0]["cam_to_world"]))
    for state in ("start", "end"):
        for entry in cameras[state]:
            entry["cam_to_world"] = (start0_from_world @ np.asarray(entry["cam_to_world"])).tolist()
    (rgbd / "cameras.json").write_text(json.dumps(cameras))
    scene = load_scene(rgbd)
    poses = [np.linalg.inv(f.camera.cam_to_world) for f in scene.all_frames]
    model = build_reconstructor(root / "vggt.onnx", width=WIDTH, height=HEIGHT,
                                K_grid=scene.start[0].camera.K, cam_from_world=poses)
    return {"rgbd": rgbd, "rgb": rgb, "model": model}


def test_rgb_only_through_onnx_reproduces_rgbd(scenes):
    reference = pipeline.run(scenes["rgbd"])
    lifted = pipeline.run(scenes["rgb"], model=scenes["model"])
    assert reference.frame_kind == "world" and lifted.frame_kind == "camera"
    assert lifted.units == "relative"  # the VGGT preset declares relative scale
    stages = {s.name: s for s in lifted.stages}
    assert stages["lift.reconstruct"].ran and "ONNX" in stages["lift"].why
    ref_joints = {part.spec.id: joint for part, joint in reference.joints}
    got_joints = {part.spec.id: joint for part, joint in lifted.joints}
    assert len(ref_joints) == len(got_joints) == 2
    for part_id, ref in ref_joints.items():
        got = got_joints[part_id]
        assert got.type == ref.type
        # The inputs agree to float32 rounding (test_onnx_lift checks the points to 1e-5); the
        # joints then differ by what such a perturbation plus the ICP polish of the static part
        # moves a fit on a 140 x 98 image: up to ~1 deg for the small drawer front.
        assert axis_angle_error_deg(got.axis, ref.axis) < AXIS_TOLERANCE_DEG
        if ref.type == "revolute":
            assert abs(abs(got.angle) - abs(ref.angle)) < math.radians(AXIS_TOLERANCE_DEG)
            gap = np.linalg.norm(np.cross(got.origin - ref.origin, ref.axis))
            assert gap < 0.01
        else:
            assert abs(abs(got.distance) - abs(ref.distance)) < 0.03 * abs(ref.distance) + 1e-3


def test_cli_model_flags_and_errors(scenes, tmp_path, capsys):
    assert main(["run", str(scenes["rgb"]), "--out", str(tmp_path / "out"), "--model", str(scenes["model"]),
                 "--onnx-mode", "joint", "--threads", "1"]) == 0
    assert (tmp_path / "out" / "articulation.json").exists()
    capsys.readouterr()
    # no depth and no model: one line naming an image and the way out
    assert main(["run", str(scenes["rgb"]), "--out", str(tmp_path / "o2")]) == 2
    error = capsys.readouterr().err
    assert "no depth" in error and "--model" in error and "rgb" in error and "Traceback" not in error
    assert main(["run", str(scenes["rgb"]), "--out", str(tmp_path / "o3"), "--model", str(tmp_path / "nope.onnx")]) == 2
    assert "nope.onnx" in capsys.readouterr().err
    assert main(["run", str(scenes["rgb"]), "--out", str(tmp_path / "o4"), "--model", str(scenes["model"]),
                 "--conf-threshold", "2"]) == 2
    assert "conf" in capsys.readouterr().err
    assert main(["run", str(scenes["rgbd"]), "--out", str(tmp_path / "o5"), "--contract", "x.json"]) == 2
    assert "--contract needs --model" in capsys.readouterr().err
    assert not (tmp_path / "o3").exists() and not (tmp_path / "o4").exists()


def test_scene_error_when_model_route_has_no_depth_and_no_model(scenes):
    with pytest.raises(SceneError, match="no depth image and no reconstructor"):
        pipeline.run(load_scene(scenes["rgb"], require_depth=False))
