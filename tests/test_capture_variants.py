"""The real-capture variant builders (sparseart.datasets.capture_variants) on a small synthetic
scene folder: the geometry they write must be the capture's own, seen as the variant says."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from sparseart.datasets import capture_variants as cv

K = [[50.0, 0.0, 20.0], [0.0, 50.0, 15.0], [0.0, 0.0, 1.0]]


@pytest.fixture()
def capture(tmp_path):
    """40 x 30 views of a tilted plane 1-1.08 m away; the end state's plane 5 cm nearer."""
    scene = tmp_path / "capture"
    v, u = np.mgrid[0:30, 0:40]
    for state, offset in (("start", 0.0), ("end", -0.05)):
        (scene / state / "rgb").mkdir(parents=True)
        (scene / state / "depth").mkdir()
        depth = 1.0 + 0.002 * u + offset
        cv2.imwrite(str(scene / state / "depth" / "000.png"), np.round(depth * 1000).astype(np.uint16))
        rgb = np.stack([u * 6, v * 8, (u + v) * 3], axis=2).astype(np.uint8)
        cv2.imwrite(str(scene / state / "rgb" / "000.png"), rgb)
    pose = np.eye(4)
    pose[:3, 3] = [0.1, 0.2, 0.3]
    cameras = {"convention": "opencv", "depth_scale": 1000.0,
               "start": [{"image": "rgb/000.png", "K": K, "cam_to_world": pose.tolist()}],
               "end": [{"image": "rgb/000.png", "K": K, "cam_to_world": pose.tolist()}]}
    (scene / "cameras.json").write_text(json.dumps(cameras))
    return scene


def _points(folder, state: str) -> np.ndarray:
    """The view's valid pixels unprojected into its camera frame, (N, 3) metres."""
    view = json.loads((folder / "cameras.json").read_text())[state][0]
    depth = cv2.imread(str(folder / state / "depth" / "000.png"), cv2.IMREAD_UNCHANGED) / 1000.0
    k = np.asarray(view["K"])
    v, u = np.nonzero(depth > 0)
    z = depth[v, u]
    return np.stack([(u - k[0, 2]) / k[0, 0] * z, (v - k[1, 2]) / k[1, 1] * z, z], axis=1)


def test_downscaled_keeps_the_points_of_the_kept_pixels(capture, tmp_path) -> None:
    small = cv.downscaled(capture, tmp_path / "small", 2, 60)
    view = json.loads((small / "cameras.json").read_text())["start"][0]
    assert view["image"] == "rgb/000.jpg" and (small / "start" / "rgb" / "000.jpg").is_file()
    assert cv2.imread(str(small / "start" / "rgb" / "000.jpg")).shape[:2] == (15, 20)
    full = _points(capture, "start").reshape(30, 40, 3)[::2, ::2].reshape(-1, 3)
    assert np.allclose(_points(small, "start"), full, atol=1e-9)
    assert not (capture / "start" / "rgb" / "000.jpg").exists()     # the source is untouched


def test_played_backwards_and_without_poses(capture, tmp_path) -> None:
    backwards = cv.played_backwards(capture, tmp_path / "backwards")
    assert np.allclose(_points(backwards, "start"), _points(capture, "end"))
    unposed = json.loads((cv.without_poses(capture, tmp_path / "unposed") / "cameras.json").read_text())
    assert all("cam_to_world" not in view for state in ("start", "end") for view in unposed[state])


def test_moved_end_camera_sees_the_same_surface_from_its_new_pose(capture, tmp_path) -> None:
    moved = cv.moved_end_camera(capture, tmp_path / "moved", 0.05, 4.0)
    before = json.loads((capture / "cameras.json").read_text())["end"][0]["cam_to_world"]
    after = json.loads((moved / "cameras.json").read_text())["end"][0]["cam_to_world"]
    world = [np.asarray(pose) for pose in (before, after)]
    old = _points(capture, "end") @ world[0][:3, :3].T + world[0][:3, 3]
    new = _points(moved, "end") @ world[1][:3, :3].T + world[1][:3, 3]
    # every re-rendered point lies on the old plane in the world (depth rounding 1 mm, and a
    # pixel takes the depth of the point that landed within half a pixel of its centre)
    centre = old.mean(axis=0)
    normal = np.linalg.svd(old - centre)[2][2]
    assert len(new) > 0.6 * len(old)
    assert np.max(np.abs((new - centre) @ normal)) < 0.003
    assert not np.allclose(world[0], world[1])


def test_noise_and_still_twice(capture, tmp_path) -> None:
    noisy = cv.with_depth_noise(capture, tmp_path / "noisy", 0.0, 0.01, seed=1)
    assert np.array_equal(_points(noisy, "start"), _points(capture, "start"))
    gap = _points(noisy, "end")[:, 2] / _points(capture, "end")[:, 2] - 1.0
    assert 0.005 < np.std(gap) < 0.015
    still = cv.still_twice(capture, tmp_path / "still", 0.0, 0.0)
    assert np.allclose(_points(still, "end"), _points(capture, "start"))
