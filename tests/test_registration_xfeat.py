"""Registration of unposed scenes with the REAL XFeat + LighterGlue weights in ../shared/models, on a
PartNet-Mobility object rendered with every realism knob at level 1 (table, floor and wall with
repetitive texture, depth warp / scale / smear / noise, a hand on the door in the end state, image
noise, JPEG): every view of both states is registered (the side views only through the pooled,
densely checked merges), the states are aligned by features, the poses agree with the rendering
cameras, and the pipeline recovers the joint -- where SIFT leaves views of the same scene out.
Skipped with the reason when the weights or the objects are missing."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import PARTNET_DIR, PARTNET_REASON

MODELS = Path(__file__).resolve().parents[2] / "shared" / "models"
XFEAT, LIGHTERGLUE = MODELS / "xfeat.onnx", MODELS / "lighterglue_L3.onnx"
SPEC = f"xfeat:{XFEAT},{LIGHTERGLUE}"
OBJECT = PARTNET_DIR / "door_9168"


def _need() -> None:
    missing = [str(p) for p in (XFEAT, LIGHTERGLUE) if not p.exists()]
    if missing:
        pytest.skip(f"real matcher weights not found: {', '.join(missing)} (see ../shared/models/README.md)")
    if not (OBJECT / "mobility.urdf").is_file():
        pytest.skip(PARTNET_REASON)


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1))))


@pytest.fixture(scope="module")
def realistic(tmp_path_factory):
    _need()
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.datasets.realism import PRESETS

    root = tmp_path_factory.mktemp("xfeat") / "door_realistic"
    render_partnet_scene(OBJECT, root, views=3, seed=0, posed=False, realism=PRESETS["realistic"])
    return root, json.loads((root / "gt.json").read_text())


@pytest.fixture(scope="module")
def lifted_scene(realistic):
    from sparseart.io.scene import load_scene
    from sparseart.lift.scene_lift import lift_scene

    scene = load_scene(realistic[0])
    return scene, lift_scene(scene)


def test_xfeat_registers_every_view_of_a_realistic_render(realistic, lifted_scene):
    from sparseart.align.matchers import LiftedMatcher, open_matcher
    from sparseart.align.scene import align_scene

    _, gt = realistic
    scene, lifted = lifted_scene
    aligned = align_scene(scene, lifted, seed=0, matcher=LiftedMatcher(open_matcher(SPEC, threads=2)))
    report = aligned.registration
    assert aligned.alignment == "features", aligned.warnings
    assert [v["registered"] for v in report["views"]] == [True] * 6, aligned.warnings
    assert report["states"]["method"] == "features" and report["states"]["trusted"]
    assert report["states"]["inliers"] > 500 and report["depth_noise"] > 0.002   # noisy depth: no ICP polish
    reference = np.asarray(gt["cameras"]["start"][0])
    for state in ("start", "end"):
        for pose, c2w in zip(aligned.poses[state], gt["cameras"][state]):
            true = np.linalg.inv(reference) @ np.asarray(c2w)
            scale = float(np.cbrt(np.linalg.det(pose[:3, :3])))
            assert abs(scale - 1) < 0.05                            # a depth scale error, not a free scale
            assert _angle(pose[:3, :3] / scale, true[:3, :3]) < 5.0, (state, aligned.warnings)
            assert np.linalg.norm(pose[:3, 3] - true[:3, 3]) < 0.15 * gt["scale"]


def test_pipeline_gives_the_joint_where_sift_leaves_views_out(realistic, lifted_scene):
    from sparseart.align.graph import register_scene
    from sparseart.bench.evaluate import evaluate
    from sparseart.pipeline import run

    root, gt = realistic
    scene, lifted = lifted_scene
    sift = register_scene({s: scene.frames(s) for s in ("start", "end")}, lifted.pointmaps, seed=0,
                          geometry_fallback=False)
    assert sum(v.how == "unregistered" for v in sift.views) >= 2, sift.warnings   # the side views
    result = run(root, matcher=SPEC, threads=2)
    rows = evaluate(result, scene, gt)
    assert rows and all(r["type_correct"] and r["axis_deg"] < 10.0 for r in rows), (rows, result.warnings)
    assert not any("could not be registered" in w for w in result.warnings), result.warnings
