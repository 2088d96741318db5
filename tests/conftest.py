"""Shared fixtures: where the shared PartNet data lives and a tiny valid scene-folder writer."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
PARTNET_DIR = REPO_ROOT.parent / "shared" / "data" / "partnet"
PARTNET_REASON = f"shared PartNet-Mobility data not found at {PARTNET_DIR} (see ../shared/README.md)"

requires_partnet = pytest.mark.skipif(not PARTNET_DIR.is_dir(), reason=PARTNET_REASON)

TINY_K = [[40.0, 0.0, 20.0], [0.0, 40.0, 15.0], [0.0, 0.0, 1.0]]


def write_tiny_scene(root: Path, views: int = 1, posed: bool = True, masks: bool = True) -> Path:
    """A valid 40x30 scene: a plane at 1 m, mask 1 on the left half and 2 on the right."""
    for state in ("start", "end"):
        for sub in ("rgb", "depth") + (("mask",) if masks else ()):
            (root / state / sub).mkdir(parents=True, exist_ok=True)
        for i in range(views):
            rgb = np.full((30, 40, 3), 120, np.uint8)
            rgb[:, 20:] = (200, 40, 40)
            cv2.imwrite(str(root / state / "rgb" / f"{i:03d}.png"), rgb[:, :, ::-1])
            cv2.imwrite(str(root / state / "depth" / f"{i:03d}.png"), np.full((30, 40), 1000, np.uint16))
            if masks:
                mask = np.ones((30, 40), np.uint8)
                mask[:, 20:] = 2
                cv2.imwrite(str(root / state / "mask" / f"{i:03d}.png"), mask)
    cameras = {"convention": "opencv", "depth_scale": 1000.0}
    for state in ("start", "end"):
        cameras[state] = [{"image": f"rgb/{i:03d}.png", "K": TINY_K,
                           **({"cam_to_world": np.eye(4).tolist()} if posed else {})} for i in range(views)]
    (root / "cameras.json").write_text(json.dumps(cameras))
    return root


@pytest.fixture
def tiny_scene(tmp_path: Path) -> Path:
    return write_tiny_scene(tmp_path / "scene")
