"""The refinement stages on a small rendered PartNet scene: stage switching and timing, the
acceptance guard, pipeline/CLI wiring and the written outputs (PLY, renders, refine.json)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from tests.conftest import PARTNET_DIR, requires_partnet

torch = pytest.importorskip("torch")

OBJECT = "drawer_26525"
TINY = dict(long_side=48, max_gaussians=400, per_state_iters=3, static_chamfer_iters=5, cross_static_iters=2,
            joint_restarts=1, joint_chamfer_iters=3, cross_mobile_iters=3)


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.pipeline import run
    from sparseart.io.scene import load_scene

    root = tmp_path_factory.mktemp("refine") / "scene"
    render_partnet_scene(PARTNET_DIR / OBJECT, root, views=2, seed=0, width=128, height=96)
    scene = load_scene(root)
    return root, scene, run(scene)


@requires_partnet
def test_stages_can_be_switched_off_and_keep_the_seed(small_run):
    from sparseart.clock import StageClock
    from sparseart.refine.api import RefineOptions, refine_part

    _, scene, result = small_run
    part, seed = result.joints[0]
    clock = StageClock()
    options = RefineOptions(**TINY, per_state=False, cross_static=False, cross_mobile=False, mobility_correction=False)
    outcome = refine_part(result.start_cloud, result.end_cloud, result.labels, part.spec.id, seed, scene, options,
                          clock)
    ran = {r.name: r.ran for r in clock.records}
    assert ran == {"refine.build": True, "refine.fit_states": False, "refine.cross_static": False,
                   "refine.cross_mobile": False, "refine.mobility_correction": False, "refine.accept": True}
    assert all(r.why.startswith(f"part {part.spec.id}: ") for r in clock.records)
    assert not outcome.accepted and "seed joint is kept" in outcome.diagnostics["why"]
    np.testing.assert_array_equal(outcome.joint.axis, seed.axis)
    assert outcome.joint.distance == seed.distance and outcome.joint.angle == seed.angle


@requires_partnet
def test_pipeline_refine_replaces_the_joint_and_records_stages(small_run):
    from sparseart.pipeline import RunOptions, run
    from sparseart.refine.api import RefineOptions

    _, scene, plain = small_run
    options = RunOptions(refine=True, refine_options=RefineOptions(**TINY, holdout_views=1))
    result = run(scene, options=options)
    names = [s.name for s in result.stages if s.ran]
    for name in ("refine.build", "refine.fit_states", "refine.cross_static", "refine.cross_mobile",
                 "refine.mobility_correction", "refine.accept"):
        assert name in names
    (part, joint), = result.joints
    info = joint.diagnostics["refine"]
    json.dumps(info)   # the before/after record is plain JSON
    assert set(info) >= {"accepted", "why", "before", "after", "render_loss", "geometric_residual", "psnr", "seconds"}
    assert np.isfinite(info["render_loss"]["seed"]) and np.isfinite(info["render_loss"]["refined"])
    assert info["psnr"]["heldout_views"] == 2 and np.isfinite(info["psnr"]["heldout"])
    assert joint.type == plain.joints[0][1].type
    chosen = info["after"] if info["accepted"] else info["before"]
    np.testing.assert_allclose(joint.axis, chosen["axis"])
    for gaussians in part.refinement.sets.values():
        for tensor in gaussians.tensors().values():
            assert torch.isfinite(tensor).all()


@requires_partnet
def test_cli_run_refine_writes_splats_and_renders(small_run, tmp_path, monkeypatch):
    from sparseart import cli
    from sparseart.refine import api
    from sparseart.refine.ply import read_gaussians_ply

    root, _, _ = small_run
    monkeypatch.setattr(api.RefineOptions, "__init__", _tiny_init(api.RefineOptions.__init__))
    out = tmp_path / "out"
    code = cli.main(["run", str(root), "--out", str(out), "--refine", "--refine-iters", "3",
                     "--render-states", "0,1"])
    assert code == 0
    document = json.loads((out / "articulation.json").read_text())
    assert any(s["name"] == "refine.cross_mobile" and s["ran"] for s in document["stages"])
    part = document["joints"][0]["part"]
    assert "before" in json.dumps(document["joints"][0]["refine"])  # the stage's before/after values
    splats = read_gaussians_ply(out / f"splats_part{part}_start.ply")
    assert len(splats["means"]) > 0 and np.all((splats["mobility"] >= 0) & (splats["mobility"] <= 1))
    import cv2

    for name in (f"render_part{part}_state0.png", f"render_part{part}_state1.png", f"turntable_part{part}.png"):
        image = cv2.imread(str(out / name))
        assert image is not None and image.std() > 0, name
    assert json.loads((out / "refine.json").read_text())[str(part)]["why"]
    assert cli.main(["run", str(root), "--out", str(tmp_path / "bad"), "--refine", "--render-states", "a,b"]) == 2
    assert not (tmp_path / "bad").exists()


def _tiny_init(original):
    def init(self, **kwargs):
        original(self, **{**TINY, **kwargs})
    return init


def test_object_budget_shares_iterations_between_parts():
    from sparseart.refine.api import RefineOptions, budget_ratio, scaled_iterations

    assert budget_ratio(None, 0.0, 5, 70.0) == 1.0
    assert budget_ratio(110.0, 0.0, 1, 70.0) == 1.0             # one part fits the budget
    assert budget_ratio(110.0, 0.0, 2, 70.0) == pytest.approx(55.0 / 70.0)
    assert budget_ratio(110.0, 50.0, 3, 70.0) == pytest.approx(60.0 / 3 / 70.0)
    assert budget_ratio(110.0, 200.0, 2, 70.0) == 0.05           # over budget: the floor, never zero
    options = RefineOptions()
    half = scaled_iterations(options, 0.5)
    assert half.cross_mobile_iters == round(options.cross_mobile_iters * 0.5) and half.joint_restarts == options.joint_restarts
    assert scaled_iterations(options, 0.001).per_state_iters == 1
    assert scaled_iterations(options, 1.0) is options
    with pytest.raises(ValueError, match="object_budget_seconds"):
        RefineOptions(object_budget_seconds=0).validate()


def test_sigma_moves_measures_the_refined_joint_in_seed_sigmas():
    """Axis angle, pivot offset from the refined line and state change, each over its sigma; an
    axis of opposite sign is the same line (the state's sign follows)."""
    from sparseart.refine.api import sigma_moves

    seed = {"type": "revolute", "axis": np.array([0.0, 0.0, 1.0]), "origin": np.zeros(3), "angle": 0.5,
            "distance": None}
    tilt = np.radians(2.0)
    refined = {"type": "revolute", "axis": -np.array([np.sin(tilt), 0.0, np.cos(tilt)]),
               "origin": np.array([0.0, 0.03, 5.0]), "angle": -0.52, "distance": None}
    moves = sigma_moves(seed, refined, {"axis_deg": 0.5, "origin": 0.01, "angle": 0.01})
    assert moves["axis"] == pytest.approx(4.0, rel=1e-6)
    assert moves["origin"] == pytest.approx(np.hypot(0.03, 5.0 * np.sin(tilt)) / 0.01, rel=1e-9)
    assert moves["angle"] == pytest.approx(2.0, rel=1e-6)
    slide = {"type": "prismatic", "axis": np.array([1.0, 0.0, 0.0]), "origin": np.zeros(3), "angle": None,
             "distance": 0.20}
    moved = dict(slide, distance=0.203)
    assert sigma_moves(slide, moved, {"axis_deg": 1.0, "distance": 0.001}) == pytest.approx(
        {"axis": 0.0, "distance": 3.0})
    assert "distance" not in sigma_moves(slide, moved, {"axis_deg": 1.0})     # no sigma, no term


def test_refine_budget_flag(tiny_scene, tmp_path):
    """--refine-budget sets the per-object budget (0 = none); a negative one is a clear error."""
    import argparse

    from sparseart import cli

    def settings(budget):
        args = argparse.Namespace(render_states="0,1", seed=0, refine_holdout=0, refine_iters=None,
                                  refine_budget=budget)
        return cli._refine_settings(args)[0].object_budget_seconds

    assert settings(None) == 100.0 and settings(45.0) == 45.0 and settings(0.0) is None
    assert cli.main(["run", str(tiny_scene), "--out", str(tmp_path / "bad"), "--refine",
                     "--refine-budget", "-5"]) == 2
    assert not (tmp_path / "bad").exists()
