"""Share of the static body's pixels whose colour changes between the two states at equal depth,
seen from the same camera (the body did not move, so the answer should be 0).

Usage: python coplanar_colour_check.py [PARTNET_DIR ...]   (default: ../shared/data/partnet and
partnet-twins beside the repository). Renders each object's default bench scene (3 views, seed 0,
posed) into a temporary folder and re-renders both states from the start cameras.
Measured 2026-11-27 before the raycaster took the lowest-index coplanar triangle: refrigerator
19.8 %, storage 17.1 %, faucet 6.8 %, microwave 3.0 %, the others <= 0.2 %; after: 0.0 % for all 19.
"""
from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from sparseart.datasets.meshes import load_articulated_object
from sparseart.datasets.partnet import render_partnet_scene
from sparseart.datasets.raycast import render_view

SHARED = Path(__file__).resolve().parents[4].parent / "shared" / "data"
roots = [Path(a) for a in sys.argv[1:]] or [SHARED / "partnet", SHARED / "partnet-twins"]
objects = sorted(d for root in roots for d in root.iterdir() if (d / "mobility.urdf").is_file())
for obj in objects:
    with tempfile.TemporaryDirectory() as tmp:
        gt = render_partnet_scene(obj, Path(tmp) / "scene", views=3, seed=0, posed=True)
        cameras = json.loads((Path(tmp) / "scene" / "cameras.json").read_text())
    model = load_articulated_object(obj)
    static, total, changed = gt["static_mask_id"], 0, 0
    for camera in cameras["start"]:
        K, pose = np.asarray(camera["K"]), np.asarray(camera["cam_to_world"])
        (rgb0, depth0, label0), (rgb1, depth1, label1) = (
            render_view(model.posed_parts(gt["joint_states"][state]), K, pose, camera["width"], camera["height"])
            for state in ("start", "end"))
        same = (label0 == static) & (label1 == static) & (np.abs(depth0 - depth1) < 1e-6)
        total += int(same.sum())
        changed += int((np.abs(rgb0.astype(int) - rgb1.astype(int)).sum(-1)[same] > 10).sum())
    print(f"{obj.name:32s} static pixels {total:6d}  changed colour {changed:6d}  ({changed / max(total, 1):.1%})")
