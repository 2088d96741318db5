"""Scene-folder validation: every malformed input is one clear line naming the file, exit code 2,
and no partial output."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from sparseart.cli import main
from sparseart.io.scene import load_scene, write_json_atomic
from sparseart.types import SceneError

from conftest import write_tiny_scene


def _cameras(scene: Path) -> dict:
    return json.loads((scene / "cameras.json").read_text())


def _set_cameras(scene: Path, data: dict) -> None:
    (scene / "cameras.json").write_text(json.dumps(data))


DELETE = object()


def _set_camera_field(scene: Path, path: tuple, value) -> None:
    """Set (or, with DELETE, remove) one field of cameras.json addressed by keys/indices."""
    data = _cameras(scene)
    container = data
    for key in path[:-1]:
        container = container[key]
    if value is DELETE:
        del container[path[-1]]
    else:
        container[path[-1]] = value
    _set_cameras(scene, data)


def test_valid_scene_loads(tiny_scene: Path) -> None:
    scene = load_scene(tiny_scene)
    assert scene.posed and scene.has_depth and scene.has_masks
    assert scene.start[0].depth.dtype == np.float64
    np.testing.assert_allclose(scene.start[0].depth, 1.0)
    assert tuple(scene.start[0].rgb[0, 25]) == (200, 40, 40)  # RGB order, not OpenCV's BGR


def _break_missing_state(s: Path) -> Path:
    import shutil
    shutil.rmtree(s / "end")
    return s / "end"


def _break_depth_size(s: Path) -> Path:
    cv2.imwrite(str(s / "start/depth/000.png"), np.full((10, 10), 1000, np.uint16))
    return s / "start/depth/000.png"


def _break_k_missing(s: Path) -> Path:
    _set_camera_field(s, ("start", 0, "K"), DELETE)
    return s / "start/depth/000.png"


def _break_no_cameras(s: Path) -> Path:
    (s / "cameras.json").unlink()
    return s / "start/depth/000.png"


def _break_nonfinite_pose(s: Path) -> Path:
    _set_camera_field(s, ("end", 0, "cam_to_world", 0, 3), float("nan"))
    return s / "cameras.json"


def _break_nonrigid_pose(s: Path) -> Path:
    _set_camera_field(s, ("end", 0, "cam_to_world", 0, 0), 2.0)
    return s / "cameras.json"


def _break_empty_mask(s: Path) -> Path:
    cv2.imwrite(str(s / "end/mask/000.png"), np.zeros((30, 40), np.uint8))
    return s / "end/mask/000.png"


def _break_unreadable_rgb(s: Path) -> Path:
    (s / "start/rgb/000.png").write_bytes(b"not a png")
    return s / "start/rgb/000.png"


def _break_zero_depth(s: Path) -> Path:
    cv2.imwrite(str(s / "end/depth/000.png"), np.zeros((30, 40), np.uint16))
    return s / "end/depth/000.png"


def _break_bad_json(s: Path) -> Path:
    (s / "cameras.json").write_text("{ not json")
    return s / "cameras.json"


def _break_depth_dtype(s: Path) -> Path:
    cv2.imwrite(str(s / "start/depth/000.png"), np.full((30, 40, 3), 9, np.uint8))
    return s / "start/depth/000.png"


def _break_npy_depth(s: Path) -> Path:
    (s / "start/depth/000.png").unlink()
    np.save(s / "start/depth/000.npy", np.array(["a", "b"]))
    return s / "start/depth/000.npy"


def _break_missing_depth_file(s: Path) -> Path:
    (s / "end/depth/000.png").unlink()
    return s / "end/depth"


def _break_mask_size(s: Path) -> Path:
    cv2.imwrite(str(s / "start/mask/000.png"), np.ones((5, 5), np.uint8))
    return s / "start/mask/000.png"


def _break_no_images(s: Path) -> Path:
    (s / "start/rgb/000.png").unlink()
    return s / "start/rgb"


def _break_negative_scale(s: Path) -> Path:
    _set_camera_field(s, ("depth_scale",), -1)
    return s / "cameras.json"


def _break_bad_k(s: Path) -> Path:
    _set_camera_field(s, ("start", 0, "K"), [[0, 0, 1], [0, 1, 1], [0, 0, 1]])
    return s / "cameras.json"


BREAKERS = [_break_missing_state, _break_depth_size, _break_k_missing, _break_no_cameras,
            _break_nonfinite_pose, _break_nonrigid_pose, _break_empty_mask, _break_unreadable_rgb,
            _break_zero_depth, _break_bad_json, _break_depth_dtype, _break_npy_depth,
            _break_missing_depth_file, _break_mask_size, _break_no_images, _break_negative_scale,
            _break_bad_k]


@pytest.mark.parametrize("breaker", BREAKERS, ids=lambda f: f.__name__[7:])
def test_bad_input_names_file(tmp_path: Path, breaker) -> None:
    scene = write_tiny_scene(tmp_path / "scene")
    culprit = breaker(scene)
    with pytest.raises(SceneError) as info:
        load_scene(scene)
    message = str(info.value)
    assert "\n" not in message
    assert str(culprit) in message


@pytest.mark.parametrize("breaker", BREAKERS, ids=lambda f: f.__name__[7:])
def test_cli_bad_input_exit_2_without_output(tmp_path: Path, breaker, capsys) -> None:
    scene = write_tiny_scene(tmp_path / "scene")
    culprit = breaker(scene)
    out = tmp_path / "out"
    code = main(["run", str(scene), "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 2
    lines = [line for line in captured.err.splitlines() if line]
    assert len(lines) == 1 and str(culprit) in lines[0] and "Traceback" not in captured.err
    assert not out.exists()


def test_missing_scene_folder(tmp_path: Path, capsys) -> None:
    assert main(["run", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_rgb_only_scene_needs_model(tmp_path: Path) -> None:
    scene = write_tiny_scene(tmp_path / "scene")
    import shutil
    for state in ("start", "end"):
        shutil.rmtree(scene / state / "depth")
    with pytest.raises(SceneError, match="--model"):
        load_scene(scene)


def test_partly_posed_scene_is_unposed_with_warning(tmp_path: Path) -> None:
    scene = write_tiny_scene(tmp_path / "scene")
    _set_camera_field(scene, ("end", 0, "cam_to_world"), DELETE)
    loaded = load_scene(scene)
    assert not loaded.posed and any("unposed" in w for w in loaded.warnings)


def test_more_than_four_views_warns(tmp_path: Path) -> None:
    loaded = load_scene(write_tiny_scene(tmp_path / "scene", views=5))
    assert len(loaded.start) == 5 and any("1-4" in w for w in loaded.warnings)


def test_npy_depth_accepted(tmp_path: Path) -> None:
    scene = write_tiny_scene(tmp_path / "scene")
    (scene / "start/depth/000.png").unlink()
    depth = np.full((30, 40), 1.5, np.float32)
    depth[0, 0] = np.nan
    np.save(scene / "start/depth/000.npy", depth)
    loaded = load_scene(scene)
    assert loaded.start[0].depth[0, 0] == 0.0 and loaded.start[0].depth[1, 1] == pytest.approx(1.5)


def test_atomic_write_leaves_old_file_on_failure(tmp_path: Path) -> None:
    path = tmp_path / "articulation.json"
    write_json_atomic(path, {"a": 1})
    with pytest.raises(TypeError):
        write_json_atomic(path, {"a": object()})
    assert json.loads(path.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["articulation.json"]
