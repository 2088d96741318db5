"""The refinement's training views on a scene with a background: the pixels no Gaussian models
carry no weight, the depth target is the cloud's, and an unposed view registered with its own
depth scale keeps its camera centre."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

H, W = 48, 64
K = np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])


def _one_view(scale: float):
    """A wall 3 m away fills the picture; a 1 m-away box face covers its middle. The cloud holds
    only the box face's pixels, unprojected and scaled by ``scale`` about the camera (a view
    registered with its own depth scale); the camera sits at (0.2, -0.1, 0.3), turned 10 deg."""
    from scipy.spatial.transform import Rotation

    from sparseart.lift.rgbd import pixel_rays
    from sparseart.types import Camera, Frame, LabelledCloud, Scene

    depth = np.full((H, W), 3.0)
    depth[16:32, 20:44] = 1.0
    rgb = np.full((H, W, 3), 90, dtype=np.uint8)
    rgb[16:32, 20:44] = 200
    box = np.zeros((H, W), dtype=bool)
    box[16:32, 20:44] = True
    pixels = np.flatnonzero(box.reshape(-1))
    camera_points = pixel_rays(K, H, W)[pixels] * depth.reshape(-1)[pixels][:, None]
    cam_to_world = np.eye(4)
    cam_to_world[:3, :3] = Rotation.from_euler("y", 10, degrees=True).as_matrix()
    cam_to_world[:3, 3] = [0.2, -0.1, 0.3]
    points = (scale * camera_points) @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]
    frame = Frame(state="start", index=0, rgb_path=Path("start/rgb/000.png"), rgb=rgb, depth=depth,
                  camera=Camera(K=K, width=W, height=H))
    cloud = LabelledCloud(state="start", points=points, colors=np.full((len(pixels), 3), 200 / 255.0),
                          segment=np.full(len(pixels), -1), frame_index=np.zeros(len(pixels), dtype=np.int64),
                          pixel_index=pixels, confidence=np.ones(len(pixels)))
    scene = Scene(root=Path("."), start=[frame], end=[])
    return scene, cloud, cam_to_world, box


def test_scaled_view_keeps_its_camera_centre_and_the_cloud_depth():
    """A view whose cloud was scaled 3 % about its camera: the recovered camera sits where the
    camera is (a rigid fit put it ~4 cm off), and the depth target is the cloud's (1.03 m), not
    the image's 1.00 m."""
    from sparseart.refine.views import build_views, recover_cam_to_world

    scene, cloud, cam_to_world, _ = _one_view(scale=1.03)
    recovered = recover_cam_to_world(scene.start[0].depth, K, cloud, 0)
    assert np.allclose(recovered, cam_to_world, atol=1e-6)
    view = build_views(scene, cloud, np.zeros(len(cloud), dtype=np.int64), {0}, long_side=64, holdout=0)[0]
    depth, weight = view.depth.numpy(), view.weight.numpy()
    face = (depth > 0) & (weight > 0)
    assert face.any() and np.allclose(depth[face], 1.03, atol=1e-4)


def test_pixels_without_a_modelled_point_carry_no_weight():
    """The wall around the box holds depth but no cloud point: weight 0 (the silhouette and depth
    terms must not ask the Gaussians to cover it); the box face keeps weight 1."""
    from sparseart.refine.views import build_views

    scene, cloud, _, box = _one_view(scale=1.0)
    view = build_views(scene, cloud, np.zeros(len(cloud), dtype=np.int64), {0}, long_side=64, holdout=0)[0]
    weight, depth = view.weight.numpy(), view.depth.numpy()
    # the crop is the box plus a margin: its border rows and columns are wall
    assert weight.shape[0] < H and weight.shape[1] < W
    assert np.all(weight[0] == 0) and np.all(weight[:, 0] == 0)
    assert np.all(depth[weight > 0] > 0)
    assert weight.sum() >= 0.8 * box.sum()
