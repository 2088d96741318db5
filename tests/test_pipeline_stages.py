"""Stage wiring of the pipeline: segmenter choice, labeler choice from the CLI, stage records."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fake_vlm_server import FakeVlmServer
from sparseart.cli import main
from sparseart.datasets.synth import render_synth_scene
from sparseart.bench.evaluate import evaluate
from sparseart.pipeline import run
from sparseart.io.scene import load_scene
from sparseart.types import SceneError


@pytest.fixture(scope="module")
def unmasked(tmp_path_factory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("stages") / "scene"
    gt = render_synth_scene(root, views=2, seed=2, width=160, height=120)
    return root, gt


def _without_masks(scene_dir: Path):
    scene = load_scene(scene_dir)
    for frame in scene.all_frames:
        frame.mask = None
    return scene


def _stage(result, name):
    return next(s for s in result.stages if s.name == name)


def test_auto_without_masks_splits_by_motion(unmasked):
    scene_dir, gt = unmasked
    result = run(_without_masks(scene_dir))
    segment = _stage(result, "segment")
    assert not segment.ran and "motion" in segment.why
    assert any("motion-based split" in w for w in result.warnings)
    rows = evaluate(result, load_scene(scene_dir), gt)  # the rendered masks define the true parts
    assert sum(r["type_correct"] for r in rows) >= 1, rows


def test_builtin_segmenter_runs_in_the_pipeline(unmasked):
    scene_dir, _ = unmasked
    scene = _without_masks(scene_dir)
    result = run(scene, segmenter="builtin")
    segment = _stage(result, "segment")
    assert segment.ran and segment.seconds > 0 and "builtin" in segment.why
    assert all(f.mask is not None and f.mask.max() > 1 for f in scene.all_frames)
    assert np.mean(result.start_cloud.segment >= 0) > 0.5  # segments reached the points
    assert result.labels is not None and len(result.labels.parts) >= 1


def test_segmenter_errors_name_the_problem(unmasked, tmp_path, capsys):
    scene_dir, _ = unmasked
    with pytest.raises(SceneError, match=r"000\.png: segmenter 'given' needs a mask"):
        run(_without_masks(scene_dir), segmenter="given")
    with pytest.raises(SceneError, match="unknown segmenter spec 'blobs'"):
        run(scene_dir, segmenter="blobs")
    assert main(["run", str(scene_dir), "--out", str(tmp_path / "o"), "--segmenter", "sam:missing.onnx"]) == 2
    err = capsys.readouterr().err
    assert "sam:ENCODER.onnx,DECODER.onnx" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_cli_vlm_labeler_falls_back_on_nonsense_and_never_prints_the_key(unmasked, tmp_path, capsys,
                                                                          monkeypatch):
    scene_dir, _ = unmasked
    secret = "sk-cli-SECRET-0123456789"
    monkeypatch.setenv("SPARSEART_VLM_API_KEY", secret)
    server = FakeVlmServer().start()
    try:
        server.reset("malformed")
        code = main(["run", str(scene_dir), "--out", str(tmp_path / "out"), "--labeler", "vlm",
                     "--vlm-base-url", server.base_url, "--vlm-model", "fake", "--vlm-timeout", "2",
                     "--vlm-pairs", "1", "--json"])
        printed = capsys.readouterr()
        assert code == 0, printed.err
        assert server.requests and server.requests[0]["headers"].get("Authorization") == f"Bearer {secret}"
    finally:
        server.stop()
    written = (tmp_path / "out" / "articulation.json").read_text()
    assert secret not in printed.out + printed.err + written
    assert any("VLM" in w and "rule" in w for w in json.loads(written)["warnings"])
    assert main(["run", str(scene_dir), "--out", str(tmp_path / "o2"), "--labeler", "vlm", "--vlm-pairs", "0"]) == 2
    assert "--vlm-pairs" in capsys.readouterr().err
