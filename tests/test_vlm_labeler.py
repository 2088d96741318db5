"""The optional VLM labeler against a local fake chat-completions server (tests/fake_vlm_server.py).

Canned answers come from the ground truth of a small rendered cabinet (body 1, door 2, drawer 3)
whose mask ids are scrambled per image, so every image's ids differ.
"""
from __future__ import annotations

import base64
import json
import logging
import re
import socket
import time
import warnings

import cv2
import numpy as np
import pytest

from sparseart.bench.evaluate import evaluate, true_groups
from sparseart.labelers import MockLabeler
from sparseart.labelers.overlay import id_color, numbered_overlay, png_data_url
from sparseart.labelers.vlm import VlmLabeler, VlmLabelerConfig, _check_labelling, _check_types
from sparseart.labelers.vlm_client import (VlmAnswerError, VlmClient, VlmServiceError, extract_json,
                                           validate_json)
from sparseart.io.scene import load_scene

from fake_vlm_server import FakeVlmServer

SECRET = "sk-test-SECRET-7f3a9c1e5b2d4f60"
GT_TYPES = {2: "revolute", 3: "prismatic"}   # synth cabinet: door 2, drawer 3
SWAPPED_PAIR = 1                              # this pair's answers number the moving parts 3, 2


@pytest.fixture(scope="module")
def cabinet(tmp_path_factory):
    from sparseart.datasets.synth import render_synth_scene

    root = tmp_path_factory.mktemp("vlm") / "scene"
    gt = render_synth_scene(root, views=3, seed=0, width=128, height=96, scramble_masks=True)
    return load_scene(root), gt


def _frame_of(gt: dict, state: str, ids: list[int]) -> int:
    for index, table in enumerate(gt["mask_maps"][state]):
        if sorted(int(k) for k in table) == sorted(ids):
            return index
    raise AssertionError(f"no {state} image has masks {ids}")


def canned_responder(gt: dict, swapped_pair: int | None = SWAPPED_PAIR):
    """Correct answers derived from gt.json; pair ``swapped_pair`` swaps its moving part numbers."""

    def number(pair: int, group: int) -> int:
        return {2: 3, 3: 2}.get(group, group) if pair == swapped_pair else group

    def respond(body: dict) -> dict:
        text = body["messages"][0]["content"][0]["text"]
        if "Masks drawn in the START photo" in text:
            ids = {state: json.loads(re.search(rf"Masks drawn in the {state.upper()} photo: (\[.*?\])", text).group(1))
                   for state in ("start", "end")}
            pair = _frame_of(gt, "start", ids["start"])
            return {state: [{"mask": m, "part": number(pair, gt["mask_maps"][state][pair][str(m)])}
                            for m in ids[state]] for state in ("start", "end")}
        if '"joints"' in text:
            start_ids = [int(m) for m in re.findall(r'"mask": (\d+)', text.split('"start"')[-1].split("]")[0])]
            pair = _frame_of(gt, "start", start_ids)
            return {"joints": [{"part": number(pair, g), "type": t, "confidence": 0.9} for g, t in GT_TYPES.items()]}
        assert '"moving_parts"' in text
        return {"moving_parts": len(gt["joints"])}

    return respond


@pytest.fixture(scope="module")
def server(cabinet):
    fake = FakeVlmServer(canned_responder(cabinet[1])).start()
    yield fake
    fake.stop()


@pytest.fixture
def fake(server):
    server.reset("ok")
    return server


def _clouds(scene):
    from sparseart.lift.labels import build_labelled_cloud
    from sparseart.lift.scene_lift import lift_scene

    lifted = lift_scene(scene)
    return tuple(build_labelled_cloud(state, scene.frames(state), lifted.pointmaps[state]) for state in ("start", "end"))


@pytest.fixture(scope="module")
def clouds(cabinet):
    return _clouds(cabinet[0])


def _labeler(server, **kwargs) -> VlmLabeler:
    config = kwargs.pop("config", VlmLabelerConfig(overlay_min_side=96))
    kwargs.setdefault("timeout", 2.0)
    kwargs.setdefault("backoff", 0.01)
    return VlmLabeler(server.base_url, "fake-vlm", config=config, **kwargs)


# ---------------------------------------------------------------------- pure pieces


def test_validate_json_subset():
    schema = {"type": "object", "required": ["n", "items"], "additionalProperties": False,
              "properties": {"n": {"type": "integer", "minimum": 0, "maximum": 3},
                             "kind": {"type": "string", "enum": ["a", "b"]},
                             "items": {"type": "array", "items": {"type": ["number", "null"], "maximum": 1}}}}
    assert validate_json({"n": 2, "items": [0.5, None, 1]}, schema) == []
    cases = {"$.n: expected integer": {"n": True, "items": []},
             "$.n: 2.0": None,
             "$.n: 4 > maximum 3": {"n": 4, "items": []},
             "$.n: -1 < minimum 0": {"n": -1, "items": []},
             "missing required 'items'": {"n": 1},
             "unexpected property 'x'": {"n": 1, "items": [], "x": 0},
             "$.kind: 'c' is not one of": {"n": 1, "items": [], "kind": "c"},
             "$.items[1]: 2 > maximum 1": {"n": 1, "items": [0, 2]},
             "$: expected object": [1]}
    cases.pop("$.n: 2.0")
    cases["$.n: expected integer, got float"] = {"n": 2.5, "items": []}
    assert validate_json({"n": 2.0, "items": []}, schema) == []      # integral float is an integer
    for expected, value in cases.items():
        problems = validate_json(value, schema)
        assert any(expected in p for p in problems), (expected, problems)
    with pytest.raises(ValueError, match="unsupported keyword"):
        validate_json({}, {"type": "object", "oneOf": []})
    try:
        import jsonschema
    except ImportError:
        return
    for value in [{"n": 2, "items": [0.5, None]}, *cases.values()]:  # agree with the reference
        assert (validate_json(value, schema) == []) == jsonschema.Draft7Validator(schema).is_valid(value)


def test_prompt_schemas_accept_their_examples():
    from sparseart.labelers.vlm import PROMPTS_DIR

    for question in ("part_count", "mask_labels", "joint_types"):
        text = (PROMPTS_DIR / f"{question}.txt").read_text()
        schema = json.loads((PROMPTS_DIR / f"{question}.schema.json").read_text())
        example = extract_json(text.split("Example:")[1])
        assert validate_json(example, schema) == [], question
        assert validate_json({"bogus": 1}, schema) != [], question


def test_prompt_files_are_checked_when_the_labeler_is_built(tmp_path):
    import shutil

    from sparseart.labelers.vlm import PROMPTS_DIR

    folder = tmp_path / "prompts"
    shutil.copytree(PROMPTS_DIR, folder)
    config = VlmLabelerConfig(prompts_dir=folder)
    VlmLabeler("http://127.0.0.1:9/v1", "m", config=config)
    (folder / "joint_types.txt").write_text("type of $part?")
    with pytest.raises(ValueError, match="joint_types.txt: bad placeholder.*\\$labelling"):
        VlmLabeler("http://127.0.0.1:9/v1", "m", config=config)
    (folder / "part_count.schema.json").write_text("{oops")
    with pytest.raises(ValueError, match="part_count.schema.json: not valid JSON"):
        VlmLabeler("http://127.0.0.1:9/v1", "m", config=config)
    shutil.copy(PROMPTS_DIR / "part_count.schema.json", folder)
    (folder / "mask_labels.txt").unlink()
    with pytest.raises(ValueError, match="mask_labels.txt: cannot read"):
        VlmLabeler("http://127.0.0.1:9/v1", "m", config=config)


def test_extract_json_forms():
    assert extract_json('{"a": 1}') == {"a": 1}
    assert extract_json('Sure:\n```json\n{"a": [1, 2]}\n```\nDone.') == {"a": [1, 2]}
    assert extract_json('```\n{"a": 2}\n```') == {"a": 2}
    assert extract_json('<think>{not json}</think> The answer is {"a": 3} as asked.') == {"a": 3}
    for bad in ("no json here", "[1, 2]", '{"a": 1', ""):
        with pytest.raises(VlmAnswerError, match="no JSON object"):
            extract_json(bad)


def test_semantic_checks_of_labelling_and_types():
    ids = {"start": [4, 9], "end": [7]}
    good = {"start": [{"mask": 4, "part": 1}, {"mask": 9, "part": 2}], "end": [{"mask": 7, "part": 2}]}
    assert _check_labelling(good, ids, 1) == {"start": {4: 1, 9: 2}, "end": {7: 2}}
    bad = {"not in the image": {"start": [{"mask": 4, "part": 1}, {"mask": 9, "part": 2}, {"mask": 5, "part": 0}],
                                "end": [{"mask": 7, "part": 2}]},
           "labelled twice": {"start": [{"mask": 4, "part": 1}, {"mask": 4, "part": 2}, {"mask": 9, "part": 2}],
                              "end": [{"mask": 7, "part": 2}]},
           "not labelled": {"start": [{"mask": 4, "part": 1}], "end": [{"mask": 7, "part": 2}]},
           "part 3 > 2": {"start": [{"mask": 4, "part": 1}, {"mask": 9, "part": 3}], "end": [{"mask": 7, "part": 2}]},
           "static base": {"start": [{"mask": 4, "part": 0}, {"mask": 9, "part": 2}], "end": [{"mask": 7, "part": 2}]}}
    for message, answer in bad.items():
        with pytest.raises(VlmAnswerError, match=message):
            _check_labelling(answer, ids, 1)
    gap = {"start": [{"mask": 4, "part": 1}, {"mask": 9, "part": 3}], "end": [{"mask": 7, "part": 1}]}
    with pytest.raises(VlmAnswerError, match="not contiguous"):
        _check_labelling(gap, ids, 2)
    assert _check_types({"joints": [{"part": 2, "type": "prismatic", "confidence": 1}]}, [2]) == {2: ("prismatic", 1.0)}
    with pytest.raises(VlmAnswerError, match="expected \\[2, 3\\]"):
        _check_types({"joints": [{"part": 2, "type": "prismatic", "confidence": 1}]}, [2, 3])


def test_overlay_numbers_and_data_url():
    rgb = np.full((40, 60, 3), 90, np.uint8)
    labels = np.zeros((40, 60), np.int64)
    labels[5:35, 5:25], labels[5:35, 30:55] = 17, 301
    out = numbered_overlay(rgb, labels, [17], min_side=120, color_by="id")
    assert out.shape == (120, 180, 3) and out.dtype == np.uint8
    big = cv2.resize(labels.astype(np.int32), (180, 120), interpolation=cv2.INTER_NEAREST)
    assert np.all(out[big == 301] == 90)                 # not asked for: untouched
    tinted = out[big == 17]
    expected = np.round(0.55 * 90 + 0.45 * np.array(id_color(17)))
    assert np.array_equal(np.median(tinted, axis=0), expected)   # interior: the id's tint
    assert id_color(17) == id_color(17) and id_color(17) != id_color(18)
    assert (tinted == 255).all(axis=1).any()             # white digits written inside
    url = png_data_url(out)
    assert url.startswith("data:image/png;base64,")
    decoded = cv2.imdecode(np.frombuffer(base64.b64decode(url.split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR)
    assert np.array_equal(decoded[:, :, ::-1], out)
    by_rank = numbered_overlay(rgb, labels, min_side=120)            # 17 is the first drawn id
    assert np.array_equal(np.median(by_rank[big == 17], axis=0), np.round(0.55 * 90 + 0.45 * np.array(id_color(0))))
    with pytest.raises(ValueError, match="labels must be"):
        numbered_overlay(rgb, labels[:10])


def test_client_configuration_from_options_and_env(monkeypatch):
    for name in ("SPARSEART_VLM_BASE_URL", "OPENAI_BASE_URL", "SPARSEART_VLM_MODEL", "SPARSEART_VLM_API_KEY",
                 "OPENAI_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    with pytest.raises(ValueError, match="no base URL"):
        VlmClient(model="m")
    with pytest.raises(ValueError, match="no model"):
        VlmClient("http://127.0.0.1:1/v1")
    with pytest.raises(ValueError, match="http"):
        VlmClient("ftp://host/v1", "m")
    monkeypatch.setenv("SPARSEART_VLM_BASE_URL", "http://127.0.0.1:9/v1/")
    monkeypatch.setenv("SPARSEART_VLM_MODEL", "local-model")
    monkeypatch.setenv("OPENAI_API_KEY", SECRET)
    client = VlmClient()
    assert client.endpoint == "http://127.0.0.1:9/v1/chat/completions" and client.model == "local-model"
    assert not client.has_key                      # an OpenAI key is not sent to another server
    monkeypatch.delenv("SPARSEART_VLM_BASE_URL")
    monkeypatch.setenv("OPENAI_BASE_URL", "https://api.example.com/v1")
    assert VlmClient().has_key                     # ... but is with OPENAI_BASE_URL
    monkeypatch.setenv("SPARSEART_VLM_API_KEY", "other")
    assert VlmClient(api_key="").has_key is False  # explicit "" = no key
    assert SECRET not in repr(VlmClient()) and SECRET not in repr(VlmLabeler(model="m"))


# ---------------------------------------------------------------------- against the fake server


@pytest.mark.parametrize("key", [None, SECRET])
def test_request_format(fake, key):
    client = VlmClient(fake.base_url, "fake-vlm", api_key=key if key else "", timeout=2.0)
    fake.responder, saved = (lambda body: {"moving_parts": 1}), fake.responder
    try:
        url = png_data_url(np.zeros((4, 4, 3), np.uint8))
        assert client.ask_json("how many?", [url, url]) == {"moving_parts": 1}
    finally:
        fake.responder = saved
    (request,) = fake.requests
    assert request["path"] == "/v1/chat/completions"
    headers = {k.lower(): v for k, v in request["headers"].items()}
    assert headers["content-type"] == "application/json"
    assert headers.get("authorization") == (f"Bearer {key}" if key else None)
    body = request["body"]
    assert body["model"] == "fake-vlm" and body["temperature"] == 0
    assert body["response_format"] == {"type": "json_object"}
    (message,) = body["messages"]
    assert message["role"] == "user"
    assert [part["type"] for part in message["content"]] == ["text", "image_url", "image_url"]
    assert message["content"][0]["text"] == "how many?"
    assert all(part["image_url"]["url"].startswith("data:image/png;base64,") for part in message["content"][1:])


def _check_parts_match_gt(labels, scene, gt, cloud, state):
    groups = true_groups(cloud, scene, gt)                      # 1 body, 2 door, 3 drawer
    part = labels.start_part if state == "start" else labels.end_part
    assigned = part >= 0
    assert assigned.mean() > 0.8
    for group, part_id in ((1, 0), (2, 1), (3, 2)):           # reference pair 0 numbers 2, 3 as gt
        here = assigned & (groups == group)
        assert np.mean(part[here] == part_id) > 0.98, (state, group)


def test_correct_answers_give_ground_truth_parts(fake, cabinet, clouds):
    scene, gt = cabinet
    labeler = _labeler(fake, config=VlmLabelerConfig(max_pairs=2, overlay_min_side=96))
    labels = labeler.label(*clouds, scene, aligned=True)
    assert labeler.last_report["fallback"] is None
    assert labeler.last_report["renumbered"] == {SWAPPED_PAIR: {2: 3, 3: 2}}
    assert [(p.id, p.role, p.joint_type) for p in labels.parts] == [(0, "static", None), (1, "movable", "revolute"),
                                                                    (2, "movable", "prismatic")]
    assert labels.type_prior == {1: "revolute", 2: "prismatic"}
    for cloud in clouds:        # frame 2 was in no pair: its masks were labelled by 3D votes
        _check_parts_match_gt(labels, scene, gt, cloud, cloud.state)
        unpaired = [s for s, (frame, _) in cloud.segment_source.items() if frame == 2]
        mapping = labels.start_segment_to_part if cloud.state == "start" else labels.end_segment_to_part
        assert unpaired and all(s in mapping for s in unpaired)
    assert len(fake.requests) == 2 * 3                          # count, labels, types per pair
    labeler.label(*clouds, scene, aligned=False)                # pipeline's second call: cached
    assert len(fake.requests) == 6


def test_pipeline_with_vlm_gives_correct_joints(fake, cabinet, tmp_path):
    from sparseart.io.articulation import write_articulation
    from sparseart.pipeline import run

    scene, gt = cabinet
    fake.reset("fenced")                                        # answers wrapped in ```json fences
    result = run(scene, labeler=_labeler(fake))
    rows = evaluate(result, scene, gt)
    assert all(row["type_correct"] for row in rows), rows
    assert max(row["axis_deg"] for row in rows) < 2.0, rows
    fit = next(s for s in result.stages if s.name == "fit")
    assert "classification skipped" in fit.why
    assert len(fake.requests) == 3 * 3
    assert not any("VLM" in w for w in result.warnings), result.warnings
    write_articulation(result, tmp_path)


def test_retry_after_server_errors_then_success(fake, cabinet, clouds):
    for status in (500, 429):
        fake.reset("error_then_ok", error_status=status, errors_left=2)
        labeler = _labeler(fake, max_retries=2)
        labels = labeler.label(*clouds, cabinet[0])
        assert labeler.last_report["fallback"] is None, status
        assert len(labels.movable) == 2
        assert len(fake.requests) == 9 + 2


def _fallback_labeler():
    return MockLabeler({1: 0})


@pytest.mark.parametrize("mode, settings, cause, n_requests", [
    ("status", {"error_status": 401}, "HTTP 401", 1),                         # no retry on 4xx
    ("status", {"error_status": 400}, "HTTP 400", 1),
    ("redirect", {}, "HTTP 307", 1),                                           # not followed
    ("status", {"error_status": 503}, "HTTP 503.*after 2 attempts", 2),
    ("slow", {"slow_seconds": 0.8}, "timed out", 2),
    ("malformed", {}, "no JSON object", 3 * 2),                                # every pair, re-asked once
    ("schema", {}, "violates the schema", 3 * 2),
    ("garbage", {}, "not a chat-completions response", 3 * 2),
])
def test_failures_fall_back_with_the_cause(fake, cabinet, clouds, mode, settings, cause, n_requests):
    fake.reset(mode, **settings)
    labeler = _labeler(fake, api_key=SECRET, timeout=0.3, max_retries=1, fallback=_fallback_labeler())
    began = time.perf_counter()
    labels = labeler.label(*clouds, cabinet[0])
    assert time.perf_counter() - began < 3.0
    assert re.search(cause, labeler.last_report["fallback"]), labeler.last_report
    assert labels.warnings[0].startswith("VLM labeler not used (") and "mock labeler" in labels.warnings[0]
    assert re.search(cause, labels.warnings[0])
    assert len(fake.requests) == n_requests
    assert all(SECRET not in w for w in labels.warnings)


def test_no_server_no_scene_no_masks_fall_back(cabinet, clouds):
    with socket.socket() as probe:                      # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    labeler = VlmLabeler(f"http://127.0.0.1:{port}/v1", "m", max_retries=1, backoff=0.01, timeout=0.5,
                         fallback=_fallback_labeler())
    labeler.label(*clouds, cabinet[0])
    assert "connection refused" in labeler.last_report["fallback"]
    labeler.label(*clouds, None)
    assert "no scene images" in labeler.last_report["fallback"]


def test_default_fallback_is_rule_based(fake, cabinet, clouds):
    fake.reset("malformed")
    labeler = _labeler(fake, config=VlmLabelerConfig(max_pairs=1, answer_retries=0, overlay_min_side=96))
    labels = labeler.label(*clouds, cabinet[0])
    assert "rules labeler" in labels.warnings[0] and len(labels.movable) == 2


def test_api_key_never_leaks(fake, cabinet, clouds, caplog):
    """Every error path with a distinctive key: the key is in no exception, warning, log or output."""
    from sparseart.io.articulation import articulation_to_dict
    from sparseart.pipeline import run_clouds

    from sparseart.labelers.vlm import PROMPTS_DIR

    caplog.set_level(logging.DEBUG)
    schema = json.loads((PROMPTS_DIR / "part_count.schema.json").read_text())
    seen: list[str] = []
    client = VlmClient(fake.base_url, "fake-vlm", api_key=SECRET, timeout=0.3, max_retries=1, backoff=0.01)
    seen.append(repr(client))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for mode, settings in [("status", {"error_status": 401}), ("status", {"error_status": 404}),
                               ("status", {"error_status": 500}), ("slow", {"slow_seconds": 0.6}),
                               ("malformed", {}), ("schema", {}), ("garbage", {}), ("redirect", {})]:
            fake.reset(mode, **settings)
            with pytest.raises((VlmServiceError, VlmAnswerError)) as error:
                client.ask_json('how many? {"moving_parts": n}', [], schema)
            seen += [str(error.value), repr(error.value), str(error.value.__cause__), str(error.value.__context__)]
            assert any(r["headers"].get("Authorization") == f"Bearer {SECRET}" for r in fake.requests)
        fake.reset("status", error_status=401)
        labeler = _labeler(fake, api_key=SECRET, fallback=_fallback_labeler())
        result = run_clouds(*_clouds(cabinet[0]), labeler=labeler)
        labeler.label(*clouds, cabinet[0])
        seen += [json.dumps(articulation_to_dict(result)), json.dumps(labeler.last_report, default=str),
                 repr(labeler)]
    seen += [str(w.message) for w in caught] + [caplog.text]
    assert any("HTTP 401" in text for text in seen)
    for text in seen:
        assert SECRET not in text and SECRET[:8] not in text and SECRET[-4:] not in text, text
