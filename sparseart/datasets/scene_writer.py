"""Write rendered two-state views as a scene folder (design section 2) plus ``gt.json``.

Layout: ``{start,end}/rgb/NNN.png`` (8-bit RGB), ``{start,end}/depth/NNN.png`` (uint16,
value = metres * depth_scale, 0 = invalid), ``{start,end}/mask/NNN.png`` (uint16 labels,
0 = background), ``cameras.json`` and ``gt.json``.
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
    cam_to_world (4, 4) float64 OpenCV camera -> world."""

    rgb: np.ndarray
    depth: np.ndarray
    label: np.ndarray
    K: np.ndarray
    cam_to_world: np.ndarray


def _write_png(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"{path}: cv2.imwrite failed")


def _write_json(path: Path, obj: dict) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2))
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


def write_scene(scene_dir: str | Path, start: list[RenderedView], end: list[RenderedView],
                gt: dict | None = None, *, depth_scale: float = 1000.0, posed: bool = True,
                scramble_masks: bool = False, depth_noise: float = 0.0, write_masks: bool = True,
                write_depth: bool = True, seed: int = 0) -> dict | None:
    """Write the views of both states, ``cameras.json`` and (if given) ``gt.json``.

    posed: include each camera's ``cam_to_world`` in cameras.json (gt.json always keeps them under
        ``"cameras"`` so evaluation can map between frames).
    scramble_masks: random per-image ids (seeded); gt gets ``"mask_maps"``
        {"start": [{written id (str): group label}, ...], "end": [...]}.
    depth_noise: sigma of multiplicative Gaussian depth noise (0.01 = 1 %), seeded.
    Returns the gt dict as written (or None).
    """
    scene_dir = Path(scene_dir)
    scene_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed + 7919)
    cams: dict = {"convention": "opencv", "depth_scale": float(depth_scale)}
    mask_maps: dict[str, list] = {}
    gt_cams: dict[str, list] = {}
    used: set[tuple] = set()
    for state, views in (("start", start), ("end", end)):
        entries, maps, c2ws = [], [], []
        for i, v in enumerate(views):
            name = f"{i:03d}.png"
            _write_png(scene_dir / state / "rgb" / name, np.ascontiguousarray(v.rgb[:, :, ::-1]))
            if write_depth:
                d = np.asarray(v.depth, dtype=np.float64).copy()
                valid = d > 0
                if depth_noise > 0:
                    d[valid] *= 1.0 + depth_noise * rng.standard_normal(int(valid.sum()))
                q = np.clip(np.round(d * depth_scale), 0, 65535).astype(np.uint16)
                q[valid & (q == 0)] = 1
                _write_png(scene_dir / state / "depth" / name, q)
            if write_masks:
                lab = v.label.astype(np.uint16)
                if scramble_masks:
                    lab, m = scramble_labels(lab, rng, used)
                    maps.append({str(k): val for k, val in sorted(m.items())})
                _write_png(scene_dir / state / "mask" / name, lab)
            e = {"image": f"rgb/{name}", "K": np.asarray(v.K, float).tolist(),
                 "width": int(v.rgb.shape[1]), "height": int(v.rgb.shape[0])}
            if posed:
                e["cam_to_world"] = np.asarray(v.cam_to_world, float).tolist()
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
    if write_masks and scramble_masks:
        gt["mask_maps"] = mask_maps
    _write_json(scene_dir / "gt.json", gt)
    return gt
