"""The CLI on rendered scenes: run (posed / unposed / no masks), demo, render."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sparseart.cli import main
from sparseart.datasets.synth import render_synth_scene
from sparseart.bench.evaluate import evaluate, load_gt
from sparseart.pipeline import run
from sparseart.io.scene import load_scene

from conftest import PARTNET_DIR, requires_partnet


@pytest.fixture(scope="module")
def cabinet_scene(tmp_path_factory) -> Path:
    scene = tmp_path_factory.mktemp("cabinet") / "scene"
    render_synth_scene(scene, views=3, seed=0)
    return scene


def test_run_writes_schema(cabinet_scene: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "out"
    assert main(["run", str(cabinet_scene), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "revolute" in printed and "prismatic" in printed and "time:" in printed
    doc = json.loads((out / "articulation.json").read_text())
    assert doc["schema"] == "sparseart/articulation/1"
    assert doc["frame"] == {"kind": "world", "reference": "cameras.json world frame", "units": "metres"}
    assert {p["role"] for p in doc["parts"]} == {"static", "movable"}
    assert sorted(j["type"] for j in doc["joints"]) == ["prismatic", "revolute"]
    for joint in doc["joints"]:
        assert abs(np.linalg.norm(joint["axis"]) - 1) < 1e-9 and len(joint["origin"]) == 3
        assert set(joint["uncertainty"]) >= {"axis_deg", "origin"}
        assert ("angle" in joint) == (joint["type"] == "revolute")
    stages = {s["name"]: s for s in doc["stages"]}
    assert stages["align"]["ran"] is False and "cameras given" in stages["align"]["why"]
    assert stages["reconstruct"]["ran"] is False and stages["refine"]["ran"] is False
    assert [p.name for p in out.iterdir()] == ["articulation.json"]


def test_budget_reaches_the_fit(cabinet_scene: Path, tmp_path: Path, monkeypatch) -> None:
    """``--budget fast`` hands the fit FitConfig.for_budget("fast") and still finds both joints."""
    import sparseart.pipeline as pipeline
    from sparseart.joints.config import FitConfig

    seen = []
    fit_parts = pipeline.fit_parts
    monkeypatch.setattr(pipeline, "fit_parts", lambda *a, config, **k: seen.append(config) or fit_parts(*a, config=config, **k))
    assert main(["run", str(cabinet_scene), "--out", str(tmp_path / "out"), "--budget", "fast"]) == 0
    assert seen == [FitConfig.for_budget("fast")]
    doc = json.loads((tmp_path / "out" / "articulation.json").read_text())
    assert sorted(j["type"] for j in doc["joints"]) == ["prismatic", "revolute"]


def test_run_json_flag_prints_document(cabinet_scene: Path, tmp_path: Path, capsys) -> None:
    assert main(["run", str(cabinet_scene), "--out", str(tmp_path / "o"), "--json",
                 "--joint-type", "revolute"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert all(j["type"] == "revolute" for j in doc["joints"])


def test_cabinet_accuracy_with_and_without_masks(cabinet_scene: Path) -> None:
    scene = load_scene(cabinet_scene)
    gt = load_gt(cabinet_scene / "gt.json")
    for use_masks in (True, False):
        rows = evaluate(run(scene, use_masks=use_masks), scene, gt)
        assert all(r["type_correct"] for r in rows), rows
        assert max(r["axis_deg"] for r in rows) < 3.0, rows


def test_unposed_single_view_in_first_camera_frame(tmp_path: Path) -> None:
    scene_dir = tmp_path / "scene"
    gt = render_synth_scene(scene_dir, views=1, seed=1, posed=False)
    scene = load_scene(scene_dir)
    assert not scene.posed
    result = run(scene)
    assert result.frame_kind == "camera"
    # evaluate() maps a camera-frame result into gt.json's world frame with the true first start camera
    rows = evaluate(result, scene, gt)
    assert all(r["type_correct"] for r in rows), rows
    assert max(r["axis_deg"] for r in rows) < 5.0, rows
    # how each view and the states were registered reaches the result and its JSON
    report = result.registration
    assert [v["image"] for v in report["views"]] == ["start/rgb/000.png", "end/rgb/000.png"], report
    assert report["views"][0]["how"] == "reference"
    assert report["states"]["method"] in ("features", "still camera", "none")
    from sparseart.io.articulation import articulation_to_dict

    assert articulation_to_dict(result)["registration"]["views"] == report["views"]


def test_demo_runs(capsys) -> None:
    assert main(["demo", "--views", "2"]) == 0
    printed = capsys.readouterr().out
    assert "estimated vs true" in printed and "door_hinge" in printed


@requires_partnet
def test_render_command_writes_scene(tmp_path: Path, capsys) -> None:
    scene = tmp_path / "door"
    assert main(["render", str(PARTNET_DIR / "door_9168"), str(scene), "--views", "2", "--seed", "3"]) == 0
    loaded = load_scene(scene)
    assert len(loaded.start) == 2 and loaded.posed and loaded.has_masks
    assert load_gt(scene / "gt.json")["joints"][0]["type"] == "revolute"


def test_render_command_bad_object(tmp_path: Path, capsys) -> None:
    assert main(["render", str(tmp_path), str(tmp_path / "s")]) == 2
    assert "mobility.urdf" in capsys.readouterr().err


def test_no_second_opinion_flag_skips_the_second_labelling(cabinet_scene: Path, tmp_path: Path) -> None:
    """Without masks the second labelling runs by default and is reported as a stage;
    ``--no-second-opinion`` skips it (and says why)."""
    for flags, ran in (([], True), (["--no-second-opinion"], False)):
        out = tmp_path / f"out{len(flags)}"
        assert main(["run", str(cabinet_scene), "--out", str(out), "--no-masks", *flags]) == 0
        stages = {s["name"]: s for s in json.loads((out / "articulation.json").read_text())["stages"]}
        assert stages["second_opinion"]["ran"] is ran, stages["second_opinion"]


@pytest.mark.parametrize("argv, flag", [
    (["demo", "--seed", "-1"], "--seed"),
    (["render", "obj", "scene", "--seed", "-1"], "--seed"),
    (["render", "obj", "scene", "--width", "0"], "--width"),
    (["render", "obj", "scene", "--height", "100000"], "--height"),
    (["render", "obj", "scene", "--depth-noise", "-0.01"], "--depth-noise"),
    (["render", "obj", "scene", "--depth-noise", "nan"], "--depth-noise"),
    (["render", "obj", "scene", "--jpeg", "6"], "--jpeg"),
    (["render", "obj", "scene", "--depth-noise-level", "-1"], "--depth-noise-level"),
    (["bench", "--jobs", "0"], "--jobs"),
    (["bench", "--seeds", "0", "-1"], "--seeds"),
    (["run", "scene", "--out", "o", "--seed", "-1"], "--seed"),
    (["run", "scene", "--out", "o", "--vlm-pairs", "0"], "--vlm-pairs"),
])
def test_bad_option_values_are_usage_errors(argv: list[str], flag: str, tmp_path: Path, capfd,
                                            monkeypatch) -> None:
    """Issue 61: an option value out of range is argparse's usage error where it is parsed: exit
    2, one stderr line naming the option, nothing run or written (was: ``--seed -1`` an internal
    error, exit 1)."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    captured = capfd.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert len(lines) == 1 and f"argument {flag}" in lines[0], captured.err
    assert "internal error" not in captured.err and captured.out == ""
    assert list(tmp_path.iterdir()) == []


def test_largest_seed_runs(tmp_path: Path) -> None:
    """The largest accepted seed reaches every stage's own seed (derived seeds wrap for open3d)."""
    scene = tmp_path / "scene"
    render_synth_scene(scene, views=1, seed=0, width=80, height=60)
    from sparseart.cli import MAX_SEED

    assert main(["run", str(scene), "--out", str(tmp_path / "out"), "--seed", str(MAX_SEED), "--no-masks"]) == 0
