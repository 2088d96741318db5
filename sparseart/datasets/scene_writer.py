"""Write rendered two-state views as a scene folder (design section 2) plus ``gt.json``.

Layout: ``{start,end}/rgb/NNN.png`` (8-bit RGB), ``{start,end}/depth/NNN.png`` (uint16,
value = metres * depth_scale, 0 = invalid), ``{start,end}/mask/NNN.png`` (uint16 labels,
0 = background), optional ``{start,end}/conf/NNN.npy`` (float32 depth confidence in [0, 1], when a
view carries one), ``cameras.json`` and ``gt.json``; ``gt_mask/{start,end}/NNN.png`` (true group
labels) when a view's written mask was degraded on purpose (``RenderedView.true_label``).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np


@dataclass
class RenderedView:
    """One rendered image. rgb (H, W, 3) uint8; depth (H, W) float64 metres (0 = invalid);
    label (H, W) uint16 unscrambled group labels (0 = background); K (3, 3) and
    cam_to_world (4, 4) float64 OpenCV camera -> world.

    Optional (realism, ``sparseart.datasets.realism``): conf (H, W) float32 depth confidence in
    [0, 1] written as ``conf/NNN.npy``; label_groups {id in ``label``: true group label} when the
    ids of ``label`` are not the groups (a split made a new id); true_label (H, W) uint16 group
    labels when ``label`` was degraded on purpose (written under ``gt_mask/``)."""

    rgb: np.ndarray
    depth: np.ndarray
    label: np.ndarray
    K: np.ndarray
    cam_to_world: np.ndarray
    conf: np.ndarray | None = None
    label_groups: dict[int, int] | None = None
    true_label: np.ndarray | None = None


def _write_png(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"{path}: cv2.imwrite failed")


def _write_json(path: Path, obj: dict) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2))
    os.replace(tmp, path)


def _write_npy(path: Path, array: np.ndarray, shape: tuple[int, ...]) -> None:
    """Save ``array`` as float32 .npy (atomically); its shape must be ``shape``."""
    a = np.asarray(array, dtype=np.float32)
    if a.shape != tuple(shape):
        raise ValueError(f"{path}: confidence shape {a.shape} differs from the depth's {tuple(shape)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npy")
    np.save(tmp, a)
    os.replace(tmp, path)


def scramble_labels(label: np.ndarray, rng: np.random.Generator,
                    used: set[tuple] | None = None) -> tuple[np.ndarray, dict[int, int]]:
    """Remap non-zero ids of a (H, W) uint16 label image to random distinct ids in [1, 999].

    Returns (new label image uint16, {written id: original id}). ``used`` collects the id
    assignments of earlier images; a new draw repeats until it differs from all of them.
    """
    ids = [int(i) for i in np.unique(label) if i != 0]
    for _ in range(100):
        new = rng.choice(np.arange(1, 1000), size=len(ids), replace=False)
        key = tuple(zip(ids, new.tolist()))
        if used is None or key not in used or not ids:
            break
    if used is not None:
        used.add(key)
    lut = np.zeros(int(label.max()) + 1 if label.size else 1, dtype=np.uint16)
    for o, n in zip(ids, new.tolist()):
        lut[o] = n
    return lut[label], {int(n): int(o) for o, n in zip(ids, new.tolist())}


FLYING_EDGE_RELATIVE_JUMP = 0.03  # a 3x3 depth range above this fraction of the depth is an edge
FLYING_BACKGROUND_GAP = 0.25      # an empty (0) neighbour stands for a background this much farther


def add_flying_pixels(depth: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """Mix foreground and background depth on depth-edge pixels, as time-of-flight and stereo
    sensors do where one pixel straddles a silhouette.

    depth: (H, W) float64 metres, 0 = invalid. Edge pixels are those whose 3x3 neighbourhood holds
    valid depths spanning more than ``FLYING_EDGE_RELATIVE_JUMP`` of the nearest one, or valid and
    empty pixels together (an empty neighbour stands for a background ``FLYING_BACKGROUND_GAP``
    farther). A ``fraction`` in [0, 1] of them (chosen with ``rng``) gets ``near + u (far - near)``,
    u ~ U(0, 1), so empty pixels beside the object can become valid. Returns a new (H, W) array. O(H W).
    """
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"flying_pixels must be a fraction in [0, 1], got {fraction}")
    depth = np.asarray(depth, dtype=np.float64)
    valid = depth > 0
    kernel = np.ones((3, 3), np.uint8)
    near = cv2.erode(np.where(valid, depth, np.inf).astype(np.float32), kernel).astype(np.float64)
    far = cv2.dilate(np.where(valid, depth, 0.0).astype(np.float32), kernel).astype(np.float64)
    any_valid = np.isfinite(near)
    any_empty = cv2.dilate((~valid).astype(np.uint8), kernel).astype(bool)
    far = np.where(any_empty & any_valid, np.maximum(far, near * (1.0 + FLYING_BACKGROUND_GAP)), far)
    near_or_zero = np.where(any_valid, near, 0.0)
    edge = any_valid & (far - near_or_zero > FLYING_EDGE_RELATIVE_JUMP * near_or_zero)
    chosen = edge & (rng.random(depth.shape) < fraction)
    out = depth.copy()
    out[chosen] = near[chosen] + rng.random(int(chosen.sum())) * (far[chosen] - near[chosen])
    return out


def perturb_pose(cam_to_world: np.ndarray, rotation_deg: float, translation: float,
                 rng: np.random.Generator) -> np.ndarray:
    """A (4, 4) cam_to_world with pose noise: rotated by exactly ``rotation_deg`` degrees about a
    random axis through the camera centre and moved by exactly ``translation`` (scene units, i.e.
    metres for metric objects) in a random direction. Models calibration / odometry error."""
    from scipy.spatial.transform import Rotation

    if rotation_deg < 0 or translation < 0:
        raise ValueError(f"pose noise must be >= 0, got {rotation_deg} deg, {translation}")
    out = np.asarray(cam_to_world, dtype=np.float64).copy()
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    out[:3, :3] = Rotation.from_rotvec(np.radians(rotation_deg) * axis).as_matrix() @ out[:3, :3]
    direction = rng.standard_normal(3)
    out[:3, 3] += translation * direction / np.linalg.norm(direction)
    return out


def write_scene(scene_dir: str | Path, start: list[RenderedView], end: list[RenderedView],
                gt: dict | None = None, *, depth_scale: float = 1000.0, posed: bool = True,
                scramble_masks: bool = False, depth_noise: float = 0.0, write_masks: bool = True,
                write_depth: bool = True, seed: int = 0, flying_pixels: float = 0.0,
                pose_noise_deg: float = 0.0, pose_noise_m: float = 0.0) -> dict | None:
    """Write the views of both states, ``cameras.json`` and (if given) ``gt.json``.

    posed: include each camera's ``cam_to_world`` in cameras.json (gt.json always keeps them under
        ``"cameras"`` so evaluation can map between frames).
    scramble_masks: random per-image ids (seeded); gt gets ``"mask_maps"``
        {"start": [{written id (str): group label}, ...], "end": [...]}.
    depth_noise: sigma of multiplicative Gaussian depth noise (0.01 = 1 %), seeded.
    flying_pixels: fraction of depth-edge pixels given a mixed foreground/background depth
        (:func:`add_flying_pixels`), applied before the noise; seeded.
    pose_noise_deg / pose_noise_m: error of the cam_to_world written to cameras.json
        (:func:`perturb_pose`; degrees, scene units); gt.json keeps the true poses; seeded.
    Views with ``conf`` get ``conf/NNN.npy``; ``label_groups`` are composed into gt's
    ``"mask_maps"`` (written whenever some written id is not its group); ``true_label`` goes to
    ``gt_mask/{state}/NNN.png`` (recorded in gt as ``"gt_masks"``).
    Returns the gt dict as written (or None).
    """
    scene_dir = Path(scene_dir)
    scene_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed + 7919)
    cams: dict = {"convention": "opencv", "depth_scale": float(depth_scale)}
    mask_maps: dict[str, list] = {}
    gt_cams: dict[str, list] = {}
    used: set[tuple] = set()
    remapped = False
    wrote_true = False
    for state, views in (("start", start), ("end", end)):
        entries, maps, c2ws = [], [], []
        for i, v in enumerate(views):
            name = f"{i:03d}.png"
            _write_png(scene_dir / state / "rgb" / name, np.ascontiguousarray(v.rgb[:, :, ::-1]))
            if write_depth:
                d = np.asarray(v.depth, dtype=np.float64).copy()
                if flying_pixels > 0:
                    d = add_flying_pixels(d, flying_pixels, rng)
                valid = d > 0
                if depth_noise > 0:
                    d[valid] *= 1.0 + depth_noise * rng.standard_normal(int(valid.sum()))
                q = np.clip(np.round(d * depth_scale), 0, 65535).astype(np.uint16)
                q[valid & (q == 0)] = 1
                _write_png(scene_dir / state / "depth" / name, q)
                if v.conf is not None:
                    _write_npy(scene_dir / state / "conf" / f"{i:03d}.npy", v.conf, q.shape)
            if write_masks:
                lab = v.label.astype(np.uint16)
                groups = v.label_groups
                if groups is not None and any(int(k) != int(g) for k, g in groups.items()):
                    remapped = True
                if scramble_masks:
                    lab, m = scramble_labels(lab, rng, used)
                    if groups is not None:
                        m = {k: int(groups.get(o, o)) for k, o in m.items()}
                elif groups is not None:
                    m = {int(k): int(g) for k, g in groups.items()}
                else:  # identity, in case another view's ids need a map
                    m = {int(k): int(k) for k in np.unique(lab) if k != 0}
                maps.append({str(k): val for k, val in sorted(m.items())})
                _write_png(scene_dir / state / "mask" / name, lab)
                if v.true_label is not None:
                    _write_png(scene_dir / "gt_mask" / state / name, v.true_label.astype(np.uint16))
                    wrote_true = True
            e = {"image": f"rgb/{name}", "K": np.asarray(v.K, float).tolist(),
                 "width": int(v.rgb.shape[1]), "height": int(v.rgb.shape[0])}
            if posed:
                written = np.asarray(v.cam_to_world, float)
                if pose_noise_deg > 0 or pose_noise_m > 0:
                    written = perturb_pose(written, pose_noise_deg, pose_noise_m, rng)
                e["cam_to_world"] = written.tolist()
            entries.append(e)
            c2ws.append(np.asarray(v.cam_to_world, float).tolist())
        cams[state] = entries
        mask_maps[state] = maps
        gt_cams[state] = c2ws
    _write_json(scene_dir / "cameras.json", cams)
    if gt is None:
        return None
    gt = dict(gt)
    gt["cameras"] = gt_cams
    gt["posed"] = bool(posed)
    gt["depth_noise"] = float(depth_noise)
    gt["flying_pixels"] = float(flying_pixels)
    gt["pose_noise"] = {"deg": float(pose_noise_deg), "translation": float(pose_noise_m)}
    if write_masks and (scramble_masks or remapped):
        gt["mask_maps"] = mask_maps
    if wrote_true:
        gt["gt_masks"] = "gt_mask/{state}/NNN.png"
    _write_json(scene_dir / "gt.json", gt)
    return gt
