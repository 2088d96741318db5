"""A real RGB-D capture as users might have given it otherwise: the same scene played backwards,
without camera poses, from a cheaper camera, with noisier depth, from a camera that moved between
the states, or with nothing moved at all.

Each builder copies a scene folder (design section 2: ``start/``, ``end/``, ``cameras.json``;
uint16 PNG depth) into a new folder and changes one thing, so a test or a benchmark can ask whether
the answer holds (``tests/test_real_capture.py``, ``benchmarks/real_capture_variants.py``). Every
builder returns the new folder; the source is never modified. Depth units follow the capture's
``depth_scale`` (default 1000 per metre). Costs are O(H W) per image.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from sparseart.lift.rgbd import pixel_rays

STATES = ("start", "end")


def _cameras(capture: Path) -> dict:
    return json.loads((capture / "cameras.json").read_text())


def _write_cameras(folder: Path, cameras: dict) -> None:
    (folder / "cameras.json").write_text(json.dumps(cameras))


def _copy(capture: Path, folder: Path, sources: tuple[str, str] = STATES) -> dict:
    """Copy the capture's states ``sources`` as the new start and end (their cameras with them);
    return the cameras to edit and write."""
    folder.mkdir(parents=True)
    cameras = _cameras(capture)
    for state, source in zip(STATES, sources):
        shutil.copytree(capture / source, folder / state)
    return {**cameras, **{state: cameras[source] for state, source in zip(STATES, sources)}}


def _depth_path(folder: Path, state: str, view: dict) -> Path:
    return folder / state / "depth" / (Path(view["image"]).stem + ".png")


def played_backwards(capture: Path, folder: Path) -> Path:
    """The end state as start and the start as end: the opposite motion (a lid opened, not closed)."""
    _write_cameras(folder, _copy(capture, folder, ("end", "start")))
    return folder


def without_poses(capture: Path, folder: Path) -> Path:
    """No ``cam_to_world`` anywhere: the answer comes in the first start camera's frame."""
    cameras = _copy(capture, folder)
    for state in STATES:
        for view in cameras[state]:
            view.pop("cam_to_world", None)
    _write_cameras(folder, cameras)
    return folder


def downscaled(capture: Path, folder: Path, factor: int = 2, jpeg_quality: int | None = 60) -> Path:
    """Every image ``factor`` times smaller: depth subsampled (no mixing across depth edges), the
    pictures area-averaged and, with ``jpeg_quality``, saved as JPEG; K divided by ``factor``, which
    the kept depth samples (each block's top-left pixel) match exactly; the pictures' block centres
    sit (factor - 1) / (2 factor) px off, below what registration resolves."""
    cameras = _copy(capture, folder)
    for state in STATES:
        for view in cameras[state]:
            rgb_path = folder / state / view["image"]
            depth_path = _depth_path(folder, state, view)
            rgb = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR)
            small = cv2.resize(rgb, (rgb.shape[1] // factor, rgb.shape[0] // factor), interpolation=cv2.INTER_AREA)
            if jpeg_quality is not None:
                rgb_path.unlink()
                rgb_path = rgb_path.with_suffix(".jpg")
                cv2.imwrite(str(rgb_path), small, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
                view["image"] = str(Path(view["image"]).with_suffix(".jpg"))
            else:
                cv2.imwrite(str(rgb_path), small)
            if depth_path.is_file():
                depth = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
                cv2.imwrite(str(depth_path), np.ascontiguousarray(depth[::factor, ::factor]))
            K = np.asarray(view["K"], dtype=np.float64)
            K[:2] /= factor      # the depth keeps each block's top-left pixel: pixel i was pixel factor i
            view["K"] = K.tolist()
    _write_cameras(folder, cameras)
    return folder


def _noisy(depth: np.ndarray, share: float, rng: np.random.Generator) -> np.ndarray:
    """uint16 depth with multiplicative white noise of sigma ``share`` on its valid pixels."""
    depth = depth.astype(np.float64)
    noisy = np.where(depth > 0, depth * (1.0 + share * rng.standard_normal(depth.shape)), 0.0)
    return np.clip(np.round(noisy), 0, 65535).astype(np.uint16)


def with_depth_noise(capture: Path, folder: Path, start_share: float, end_share: float, seed: int = 0) -> Path:
    """Per-pixel multiplicative depth noise of sigma ``start_share`` / ``end_share`` (0.01 = 1 % of
    the distance) added to each state's depth images (a cheaper or farther sensor)."""
    cameras = _copy(capture, folder)
    rng = np.random.default_rng(seed)
    for state, share in zip(STATES, (start_share, end_share)):
        for view in cameras[state]:
            path = _depth_path(folder, state, view)
            if share > 0 and path.is_file():
                cv2.imwrite(str(path), _noisy(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), share, rng))
    _write_cameras(folder, cameras)
    return folder


def still_twice(capture: Path, folder: Path, depth_share: float = 0.003, image_sigma: float = 4.0,
                seed: int = 0) -> Path:
    """The start state twice, the second copy with depth noise (``depth_share``) and image noise
    (``image_sigma`` grey levels): nothing moved."""
    cameras = _copy(capture, folder, ("start", "start"))
    rng = np.random.default_rng(seed)
    for view in cameras["end"]:
        path = _depth_path(folder, "end", view)
        if path.is_file():
            cv2.imwrite(str(path), _noisy(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), depth_share, rng))
        rgb_path = folder / "end" / view["image"]
        rgb = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR).astype(np.float64)
        cv2.imwrite(str(rgb_path), np.clip(rgb + image_sigma * rng.standard_normal(rgb.shape), 0, 255).astype(np.uint8))
    _write_cameras(folder, cameras)
    return folder


def moved_end_camera(capture: Path, folder: Path, shift: float, yaw_deg: float, posed: bool = True) -> Path:
    """Each end view re-rendered from its camera moved by ``shift`` metres along its x axis and
    turned by ``yaw_deg`` about its y axis (a head or a phone that moved between the pictures):
    the end points (:func:`~sparseart.lift.rgbd.pixel_rays` x depth) forward-projected through K
    with a z-buffer, one-pixel cracks filled from their
    neighbours (depth by a 3 x 3 closing, colour by inpainting), what the old camera never saw
    left empty, and so is every pixel whose depth the old view lacked (no point carries its colour).
    ``cam_to_world`` follows the move; with ``posed`` False every pose is dropped."""
    cameras = _copy(capture, folder)
    scale = float(cameras.get("depth_scale", 1000.0))
    move = np.eye(4)
    move[:3, :3] = Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix()
    move[:3, 3] = [shift, 0.0, 0.0]
    for view in cameras["end"]:
        K = np.asarray(view["K"], dtype=np.float64)
        depth_path, rgb_path = _depth_path(folder, "end", view), folder / "end" / view["image"]
        depth = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED).astype(np.float64) / scale
        rgb = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR)
        height, width = depth.shape
        valid = (depth > 0).reshape(-1)
        points = pixel_rays(K, height, width)[valid] * depth.reshape(-1, 1)[valid]
        moved = (points - move[:3, 3]) @ move[:3, :3]            # old camera frame -> new
        ahead = moved[:, 2] > 1e-3
        moved, colours = moved[ahead], rgb.reshape(-1, 3)[valid][ahead]
        pixels = (moved / moved[:, 2:]) @ K.T                      # (u, v, 1) in the new image
        uu, vv = np.round(pixels[:, 0]).astype(np.int64), np.round(pixels[:, 1]).astype(np.int64)
        inside = (uu >= 0) & (uu < width) & (vv >= 0) & (vv < height)
        order = np.argsort(-moved[inside, 2])                      # far first: the near overwrite
        new_depth, new_rgb = np.zeros((height, width)), np.zeros_like(rgb)
        new_depth[vv[inside][order], uu[inside][order]] = moved[inside, 2][order]
        new_rgb[vv[inside][order], uu[inside][order]] = colours[inside][order]
        closed = cv2.morphologyEx(new_depth.astype(np.float32), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
        crack = (new_depth == 0) & (closed > 0)
        new_depth[crack] = closed[crack]
        new_rgb = cv2.inpaint(new_rgb, crack.astype(np.uint8), 2, cv2.INPAINT_TELEA)
        cv2.imwrite(str(depth_path), np.clip(np.round(new_depth * scale), 0, 65535).astype(np.uint16))
        cv2.imwrite(str(rgb_path), new_rgb)
        if "cam_to_world" in view:
            view["cam_to_world"] = (np.asarray(view["cam_to_world"], dtype=np.float64) @ move).tolist()
    if not posed:
        for state in STATES:
            for view in cameras[state]:
                view.pop("cam_to_world", None)
    _write_cameras(folder, cameras)
    return folder
