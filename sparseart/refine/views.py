"""Training views of the refinement: the scene's images at a reduced resolution with their
cameras, depth, background colour and a per-pixel weight.

Cameras: posed scenes use their ``cam_to_world``. Unposed scenes (results in the first start
camera's frame, the end state registered by the pipeline) recover each used frame's pose from
its own points: the cloud holds, for every valid pixel, both the pixel index and the point in the
scene frame, so the camera -> scene transform is the similarity between the unprojected pixels
and the cloud points (exact up to round-off; its scale is the view's registered depth scale,
and the camera keeps its rotation and centre).

Targets: the depth of a view is read off the cloud (its points' camera z, after the pipeline's
depth corrections), and pixels that hold depth but no cloud point -- the room, the table, a
hand, parts not modelled -- carry no weight: no Gaussian models them, so they are neither to be
filled nor to be left empty (measured on realistic renders, where the crop around the object
holds the table and wall: before, the silhouette term asked the Gaussians to cover them).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..types import LabelledCloud, Scene
from .render import Camera


@dataclass
class View:
    """One image of one state for the refinement.

    rgb: (H, W, 3) tensor in [0, 1]; depth: (H, W) tensor, camera z in frame units, 0 = invalid
    (None without depth); weight: (H, W) tensor in {0, 1}, 0 on pixels of parts not modelled;
    background: (3,) tensor, the colour of empty pixels; held_out: not used for fitting.
    """

    state: str
    index: int
    camera: Camera
    rgb: object
    depth: object
    weight: object
    background: object
    held_out: bool = False


def scaled_intrinsics(K: np.ndarray, scale_x: float, scale_y: float) -> np.ndarray:
    """(3, 3) intrinsics of an image resized by (scale_x, scale_y), with pixel centres at
    integer coordinates (OpenCV): u' = (u + 0.5) s - 0.5."""
    K2 = np.asarray(K, dtype=np.float64).copy()
    K2[0, 0] *= scale_x
    K2[0, 1] *= scale_x
    K2[1, 1] *= scale_y
    K2[0, 2] = (K[0, 2] + 0.5) * scale_x - 0.5
    K2[1, 2] = (K[1, 2] + 0.5) * scale_y - 0.5
    return K2


def recover_cam_to_world(frame_depth: np.ndarray, K: np.ndarray, cloud: LabelledCloud,
                         frame_index: int) -> np.ndarray | None:
    """(4, 4) rigid camera -> scene transform of one frame from its points in ``cloud``: the
    rotation and camera centre of the similarity between the unprojected pixels and the cloud
    points (Umeyama); None with fewer than 3 points. O(N)."""
    from sparseart.align.ransac import umeyama
    from sparseart.geometry.transforms import make_transform
    from ..lift.rgbd import pixel_rays

    here = cloud.frame_index == frame_index
    if here.sum() < 3:
        return None
    height, width = frame_depth.shape
    pixels = cloud.pixel_index[here]
    camera_points = pixel_rays(K, height, width)[pixels] * frame_depth.reshape(-1)[pixels][:, None]
    # a similarity: a view registered with its own depth scale lies scaled about its camera
    # centre, which the rigid part of the similarity keeps (a rigid fit would shift it)
    fit = umeyama(camera_points, cloud.points[here], with_scale=True)
    return make_transform(fit.rotation, fit.translation)


CROP_MARGIN = 0.1   # fraction of the object's box added on each side of the crop


def _cloud_depth(cloud: LabelledCloud, here: np.ndarray, world_to_cam: np.ndarray, height: int,
                 width: int) -> np.ndarray:
    """(H, W) float64 depth of one frame read off the cloud: the camera z of each of its points
    (``here``: (N,) bool) at its pixel, 0 elsewhere. The cloud is what the Gaussians are built
    from, after the pipeline's per-view depth scale and depth-ratio corrections; the frame's raw
    depth differs from it by those (1-3 % on reconstructor-grade depth). O(N)."""
    z = cloud.points[here] @ world_to_cam[2, :3] + world_to_cam[2, 3]
    depth = np.zeros(height * width, dtype=np.float64)
    depth[cloud.pixel_index[here]] = np.maximum(z, 0.0)
    return depth.reshape(height, width)


def crop_box(rows: np.ndarray, cols: np.ndarray, height: int, width: int) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1) crop around the given pixels plus ``CROP_MARGIN`` of their box on every
    side (at least 2 px), clipped to the image; the whole image when there are no pixels."""
    if len(rows) == 0:
        return 0, height, 0, width
    margin_y = int(np.ceil(CROP_MARGIN * (rows.max() - rows.min() + 1))) + 2
    margin_x = int(np.ceil(CROP_MARGIN * (cols.max() - cols.min() + 1))) + 2
    return (max(0, int(rows.min()) - margin_y), min(height, int(rows.max()) + 1 + margin_y),
            max(0, int(cols.min()) - margin_x), min(width, int(cols.max()) + 1 + margin_x))


def build_views(scene: Scene, cloud: LabelledCloud, part_of_point: np.ndarray, modelled_parts: set[int],
                long_side: int, holdout: int, dtype=None) -> list[View]:
    """The views of one state (``cloud.state``): each image cropped to the box of its points (plus
    a margin) and resized so the longer side is at most ``long_side`` px; K follows the crop.

    part_of_point: (N,) part id of every cloud point (-1 = unassigned); pixels whose point belongs
    to a part outside ``modelled_parts`` (and outside -1) get weight 0.
    holdout: the last ``holdout`` frames are marked held out (only if the state keeps at least
    one frame for fitting). Frames without any point in the cloud are skipped.
    """
    import cv2
    import torch

    dtype = dtype or torch.float32
    frames = [f for f in scene.frames(cloud.state) if np.any(cloud.frame_index == f.index)]
    held = set(f.index for f in frames[len(frames) - holdout:]) if 0 < holdout < len(frames) else set()
    views = []
    for frame in frames:
        camera = frame.camera
        if camera is None:
            raise ValueError(f"{frame.rgb_path}: refinement needs the camera intrinsics K")
        cam_to_world = camera.cam_to_world if scene.posed else None
        if cam_to_world is None:
            if frame.depth is None:
                raise ValueError(f"{frame.rgb_path}: unposed refinement needs depth to place the camera")
            cam_to_world = recover_cam_to_world(frame.depth, camera.K, cloud, frame.index)
            if cam_to_world is None:
                continue
        world_to_cam = np.linalg.inv(cam_to_world)
        full_h, full_w = frame.shape
        excluded = np.zeros(full_h * full_w, dtype=np.float64)
        here = cloud.frame_index == frame.index
        foreign = ~np.isin(part_of_point[here], list(modelled_parts) + [-1])
        excluded[cloud.pixel_index[here][foreign]] = 1.0
        if frame.depth is not None:
            # a pixel with depth but no point of the cloud (the room, the table, a hand, a pixel the
            # lift dropped) shows something no Gaussian models: neither filled nor empty
            unmodelled = np.asarray(frame.depth, dtype=np.float64).reshape(-1) > 0
            unmodelled[cloud.pixel_index[here]] = False
            excluded[unmodelled] = 1.0
        rows, cols = np.unravel_index(cloud.pixel_index[here], (full_h, full_w))
        y0, y1, x0, x1 = crop_box(rows, cols, full_h, full_w)
        height, width = y1 - y0, x1 - x0
        scale = min(1.0, long_side / max(height, width))
        new_w, new_h = max(1, int(round(width * scale))), max(1, int(round(height * scale)))
        K = np.asarray(camera.K, dtype=np.float64).copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        K = scaled_intrinsics(K, new_w / width, new_h / height)
        rgb = cv2.resize(frame.rgb[y0:y1, x0:x1], (new_w, new_h), interpolation=cv2.INTER_AREA).astype(np.float64) / 255.0
        depth = None
        if frame.depth is not None:
            depth = cv2.resize(_cloud_depth(cloud, here, world_to_cam, full_h, full_w)[y0:y1, x0:x1], (new_w, new_h),
                               interpolation=cv2.INTER_NEAREST)
        excluded = cv2.resize(excluded.reshape(full_h, full_w)[y0:y1, x0:x1], (new_w, new_h),
                              interpolation=cv2.INTER_AREA)
        weight = (excluded <= 0).astype(np.float64)
        empty = frame.depth <= 0 if frame.depth is not None else None
        background = (np.median(frame.rgb[empty], axis=0) / 255.0 if empty is not None and empty.any()
                      else np.zeros(3))
        views.append(View(
            state=cloud.state, index=frame.index,
            camera=Camera(K=K, world_to_cam=world_to_cam, width=new_w, height=new_h),
            rgb=torch.as_tensor(rgb, dtype=dtype), weight=torch.as_tensor(weight, dtype=dtype),
            depth=None if depth is None else torch.as_tensor(depth, dtype=dtype),
            background=torch.as_tensor(background, dtype=dtype), held_out=frame.index in held))
    return views
