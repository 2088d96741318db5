"""Fuzz suite of issue 15: every bad input is a clean exit 2 with ONE stderr line naming the file
and field, nothing hangs, nothing is half-written, no silent wrong answer.

Cases come from tests/fuzz_cases.py (scene folders, ``run_clouds`` inputs, a hostile VLM server).
Fast cases run in-process (``sparseart.cli.main`` with capfd, which also sees what native
libraries print to file descriptor 2); cases that would hang or eat memory if the boundary failed
run in a child process under a timeout and an address-space limit (``CHILD_MEMORY_BYTES``), which
reports its peak RSS. Heavy cases (real decompression bombs, 10 million points, a dripping VLM
through the whole CLI) are marked ``fuzz_heavy``: ``python3 -m pytest -m fuzz_heavy``.

Totals: set ``SPARSEART_FUZZ_REPORT=DIR`` and each worker writes ``DIR/fuzz-<worker>.json`` with
one row per case (kind, expected and actual exit code, stderr lines, seconds, peak MB).
"""
from __future__ import annotations

import json
import math
import os
import shutil
import stat
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

import fuzz_cases as fc
from sparseart.cli import main
from sparseart.types import LabelledCloud, SceneError

CHILD_MEMORY_BYTES = 3 * 2**30       # RLIMIT_AS of child cases
CHILD_TIMEOUT_S = 90.0               # a child still running after this is a hang
IN_PROCESS_BOUND_S = 30.0            # generous: the machine is shared; failures take milliseconds
RESULTS: list[dict] = []

CHILD_CODE = """
import resource, sys
limit, report = int(sys.argv[1]), sys.argv[2]
resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
code = 1
try:
    from sparseart.cli import main
    code = main(sys.argv[3:])
finally:
    # VmHWM: this process image's peak RSS (ru_maxrss would include the parent's at fork + exec)
    with open("/proc/self/status") as status:
        peak = next((line.split()[1] for line in status if line.startswith("VmHWM:")), "nan")
    with open(report, "w") as stream:
        stream.write(peak)
sys.exit(code)
"""


# ---------------------------------------------------------------------- fixtures and helpers


@pytest.fixture(scope="session")
def base_scene(tmp_path_factory) -> Path:
    """A small valid posed scene: the synthetic cabinet, 2 views per state at 80x60."""
    from sparseart.datasets.synth import render_synth_scene

    root = tmp_path_factory.mktemp("fuzz_base") / "scene"
    render_synth_scene(root, views=2, seed=0, width=80, height=60)
    (root / "gt.json").unlink()
    return root


@pytest.fixture(autouse=True)
def _heavy_only_on_request(request):
    """Heavy cases run only when asked for (``-m fuzz_heavy``), so the README's plain
    ``python3 -m pytest -q -n 2`` runs the fast ones."""
    if request.node.get_closest_marker("fuzz_heavy") and "fuzz_heavy" not in (request.config.getoption("markexpr") or ""):
        pytest.skip("heavy fuzz case: run with python3 -m pytest -m fuzz_heavy")


@pytest.fixture(scope="module", autouse=True)
def _totals():
    yield
    folder = os.environ.get("SPARSEART_FUZZ_REPORT")
    if folder and RESULTS:
        Path(folder).mkdir(parents=True, exist_ok=True)
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        (Path(folder) / f"fuzz-{worker}.json").write_text(json.dumps(RESULTS, indent=1))


def _copy_scene(base: Path, tmp: Path, name: str = "scene") -> Path:
    scene = tmp / name
    shutil.copytree(base, scene)
    return scene


def _tree(root: Path) -> set[str]:
    """Every path under ``root`` (what a run may not add)."""
    found = set()
    for folder, dirs, files in os.walk(root):
        for name in dirs + files:
            found.add(os.path.relpath(os.path.join(folder, name), root))
    return found


def _lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.strip()]


def _run_child(args: list[str], tmp: Path) -> tuple[int | None, str, float, float]:
    """(exit code or None on timeout, stderr, seconds, peak RSS MB from VmHWM) of ``sparseart`` in a
    child limited to ``CHILD_MEMORY_BYTES`` of address space."""
    report = tmp / ".child_peak"
    began = time.perf_counter()
    process = subprocess.Popen([sys.executable, "-c", CHILD_CODE, str(CHILD_MEMORY_BYTES), str(report), *args],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL)
    try:
        _, err = process.communicate(timeout=CHILD_TIMEOUT_S)
        code = process.returncode
    except subprocess.TimeoutExpired:
        process.kill()
        _, err = process.communicate()
        code = None
    seconds = time.perf_counter() - began
    peak = float(report.read_text()) / 1024.0 if report.exists() else math.nan
    report.unlink(missing_ok=True)
    return code, err.decode("utf-8", "replace"), seconds, peak


def _record(name: str, kind: str, expect: int, code, lines: list[str], seconds: float, peak: float = math.nan,
            leftovers: int = 0) -> None:
    RESULTS.append({"case": name, "kind": kind, "expect": expect, "code": code, "stderr_lines": len(lines),
                    "seconds": round(seconds, 3), "peak_mb": None if math.isnan(peak) else round(peak, 1),
                    "leftovers": leftovers})


def _check_failure(case_name: str, kind: str, expect: int, code, err: str, culprit: str, seconds: float,
                   bound: float, before: set[str], after: set[str], out: Path, out_existed: bool,
                   peak: float = math.nan) -> None:
    lines = _lines(err)
    leftovers = sorted(after - before)
    _record(case_name, kind, expect, code, lines, seconds, peak, len(leftovers))
    assert code is not None, f"hang: still running after {seconds:.0f} s"
    assert code == expect, err
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert culprit in lines[0], (culprit, lines[0])
    if expect == 2:
        assert lines[0].startswith("sparseart") and "error" in lines[0]
    assert not leftovers, leftovers
    assert out_existed or not os.path.lexists(out), f"{out} was created"
    assert seconds < bound, f"took {seconds:.1f} s"


# ---------------------------------------------------------------------- scene-folder cases

SCENE_CASES = fc.scene_cases()


@pytest.mark.parametrize("case", SCENE_CASES, ids=[c.name for c in SCENE_CASES])
def test_bad_scene_is_one_clean_line(case: fc.Case, base_scene: Path, tmp_path: Path, capfd) -> None:
    scene = _copy_scene(base_scene, tmp_path, case.scene_name)
    culprit = case.mutate(scene)
    out = case.out(scene, tmp_path) if case.out else tmp_path / "out"
    culprit = culprit or str(out)
    out_existed = os.path.lexists(out)
    out_before = out.read_bytes() if out_existed and out.is_file() else None
    before = _tree(tmp_path)
    args = ["run", str(scene), "--out", str(out), *case.args]
    if case.child:
        code, err, seconds, peak = _run_child(args, tmp_path)
        bound = CHILD_TIMEOUT_S
    else:
        capfd.readouterr()
        began = time.perf_counter()
        code = main(args)
        seconds = time.perf_counter() - began
        err, peak, bound = capfd.readouterr().err, math.nan, IN_PROCESS_BOUND_S
    _check_failure(case.name, case.kind, case.expect, code, err, culprit, seconds, bound,
                   before, _tree(tmp_path), out, out_existed, peak)
    if out_before is not None:
        assert out.read_bytes() == out_before


def test_case_count_and_classes() -> None:
    """The issue asks for >= 150 generated cases across every class."""
    kinds = {c.kind for c in SCENE_CASES}
    assert len(SCENE_CASES) + len(fc.cloud_cases()) + len(fc.VLM_MODES) >= 150
    assert {"malformed JSON", "deep JSON", "huge numbers", "bool as number", "NaN/inf", "wrong types",
            "missing files", "FIFO / device", "huge headers", "truncated files", "npz-as-npy",
            "unwritable --out", "tiny-id masks", "coordinates near 1e300"} <= kinds


def test_newline_path_is_escaped(base_scene: Path, tmp_path: Path, capfd) -> None:
    scene = _copy_scene(base_scene, tmp_path, "a\nb\rc")
    (scene / "start/rgb/000.png").write_bytes(b"junk")
    assert main(["run", str(scene), "--out", str(tmp_path / "out")]) == 2
    err = capfd.readouterr().err
    assert err.count("\n") == 1 and "a\\nb\\rc" in err


# ---------------------------------------------------------------------- outputs as one unit


def test_failed_run_leaves_old_outputs_untouched(base_scene: Path, tmp_path: Path, capfd) -> None:
    scene = _copy_scene(base_scene, tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / "articulation.json").write_text('{"old": true}')
    (out / "notes.txt").write_text("mine")
    (scene / "end/depth/000.png").write_bytes(b"broken")
    assert main(["run", str(scene), "--out", str(out), "--urdf", "--ply"]) == 2
    assert len(_lines(capfd.readouterr().err)) == 1
    assert sorted(p.name for p in out.iterdir()) == ["articulation.json", "notes.txt"]
    assert (out / "articulation.json").read_text() == '{"old": true}'


def test_failing_export_leaves_nothing_half_written(base_scene: Path, tmp_path: Path, capfd, monkeypatch) -> None:
    """--urdf --ply where the PLY export fails after articulation.json and the URDF were written:
    nothing new appears, the old outputs stay."""
    import sparseart.io.ply as ply

    def broken(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ply, "write_labelled_clouds", broken)
    scene = _copy_scene(base_scene, tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / "articulation.json").write_text('{"old": true}')
    before = _tree(tmp_path)
    assert main(["run", str(scene), "--out", str(out), "--urdf", "--ply"]) == 2
    err = capfd.readouterr().err
    assert len(_lines(err)) == 1 and "No space left" in err and str(out) in err
    assert _tree(tmp_path) == before
    assert (out / "articulation.json").read_text() == '{"old": true}'


def test_outputs_replace_old_ones_and_honour_umask(base_scene: Path, tmp_path: Path, capfd) -> None:
    scene = _copy_scene(base_scene, tmp_path)
    out = tmp_path / "new" / "nested" / "out"
    old_mask = os.umask(0o027)
    try:
        assert main(["run", str(scene), "--out", str(out), "--urdf"]) == 0
    finally:
        os.umask(old_mask)
    capfd.readouterr()
    names = sorted(p.name for p in out.iterdir())
    assert names == ["articulation.json", "meshes", "object.urdf"], names
    assert stat.S_IMODE((out / "articulation.json").stat().st_mode) == 0o640
    assert stat.S_IMODE(out.stat().st_mode) == 0o750
    assert not [p for p in (tmp_path / "new" / "nested").iterdir() if p.name != "out"]
    # a second run into the existing folder replaces the files and keeps foreign ones
    (out / "notes.txt").write_text("mine")
    (out / "articulation.json").write_text("{}")
    assert main(["run", str(scene), "--out", str(out)]) == 0
    capfd.readouterr()
    assert json.loads((out / "articulation.json").read_text())["schema"] == "sparseart/articulation/1"
    assert sorted(p.name for p in out.iterdir()) == ["articulation.json", "meshes", "notes.txt", "object.urdf"]


# ---------------------------------------------------------------------- scale invariance


def test_same_scene_in_other_units_gives_the_same_joints(base_scene: Path, tmp_path: Path, capfd) -> None:
    """depth_scale 1, 1000 and 1e6 with the camera translations in the same unit: the joints agree
    up to the unit (axes within 0.5 deg, angles within 0.005 rad, origins and distances within
    2 mm after dividing by the unit; measured: identical to 1e-9 on this posed scene)."""
    results = {}
    for depth_scale in (1.0, 1000.0, 1e6):
        scene = _copy_scene(base_scene, tmp_path, f"scene_{depth_scale:g}")
        fc._scale_units(depth_scale)(scene)
        out = tmp_path / f"out_{depth_scale:g}"
        assert main(["run", str(scene), "--out", str(out)]) == 0, capfd.readouterr().err
        capfd.readouterr()
        results[depth_scale] = json.loads((out / "articulation.json").read_text())
    reference = results[1000.0]
    for depth_scale, doc in results.items():
        unit = 1000.0 / depth_scale
        assert len(doc["joints"]) == len(reference["joints"])
        for joint, ref in zip(doc["joints"], reference["joints"]):
            assert joint["type"] == ref["type"]
            cosine = min(1.0, abs(float(np.dot(joint["axis"], ref["axis"]))))
            assert np.degrees(np.arccos(cosine)) < 0.5
            np.testing.assert_allclose(np.array(joint["origin"]) / unit, ref["origin"], atol=2e-3)
            if joint["type"] == "revolute":
                assert joint["angle"] == pytest.approx(ref["angle"], abs=5e-3)
            else:
                assert joint["distance"] / unit == pytest.approx(ref["distance"], abs=2e-3)


# ---------------------------------------------------------------------- no confident nonsense

NOTHING = fc.nothing_articulated()


@pytest.mark.parametrize("name", sorted(NOTHING))
def test_nothing_articulated_gives_no_confident_joint(name: str, tmp_path: Path) -> None:
    from sparseart import run

    result = run(NOTHING[name](tmp_path / "scene"))
    assert all(joint.confidence < 0.2 for _, joint in result.joints), [(j.type, j.confidence) for _, j in result.joints]
    assert result.warnings


def test_identical_states_give_no_joint(base_scene: Path, tmp_path: Path) -> None:
    from sparseart import run

    scene = _copy_scene(base_scene, tmp_path)
    shutil.rmtree(scene / "end")
    shutil.copytree(scene / "start", scene / "end")
    data = json.loads((scene / "cameras.json").read_text())
    data["end"] = data["start"]
    (scene / "cameras.json").write_text(json.dumps(data))
    result = run(scene)
    assert all(joint.confidence < 0.2 for _, joint in result.joints) and result.warnings


def test_noise_depth_with_noise_masks_is_no_joint_or_bad_input(tmp_path: Path, capfd) -> None:
    """Depth noise with random mask ids: either no confident joint (exit 0) or bad input (exit 2,
    one line, nothing written), never an internal error (the rules labeler's plain ValueError 'no
    usable segments' was reported as exit 1 on some versions; see the SceneError patch in issue 15)."""
    rng = np.random.default_rng(0)
    scene = fc.write_plain_scene(tmp_path / "scene", lambda s: rng.uniform(0.5, 3.0, (120, 160)),
                                 lambda s: rng.integers(1, 4, (120, 160)).astype(np.uint8))
    out = tmp_path / "out"
    code = main(["run", str(scene), "--out", str(out)])
    err = capfd.readouterr().err
    assert code in (0, 2), err
    if code == 2:
        assert len(_lines(err)) == 1 and not out.exists()
    else:
        joints = json.loads((out / "articulation.json").read_text())["joints"]
        assert all(j["confidence"] < 0.2 for j in joints)


# ---------------------------------------------------------------------- run_clouds

CLOUD_CASES = fc.cloud_cases()


def _cloud(state: str, fields: dict) -> LabelledCloud:
    return LabelledCloud(state=state, segment_source={}, **fields)


@pytest.mark.parametrize("name, breaker, culprit", CLOUD_CASES, ids=[c[0] for c in CLOUD_CASES])
def test_run_clouds_rejects_bad_clouds(name: str, breaker, culprit: str) -> None:
    from sparseart import run_clouds

    start = _cloud("start", fc.cloud_fields())
    end = _cloud("end", breaker(fc.cloud_fields(seed=1)))
    began = time.perf_counter()
    with pytest.raises(SceneError) as info:
        run_clouds(start, end)
    seconds = time.perf_counter() - began
    message = str(info.value)
    _record(f"clouds_{name}", "run_clouds", 2, 2, _lines(message), seconds)
    assert "\n" not in message and message.startswith(culprit), message
    assert seconds < 5.0


def test_run_clouds_rejects_non_clouds() -> None:
    from sparseart import run_clouds

    good = _cloud("start", fc.cloud_fields())
    for bad in (None, [], {"points": np.zeros((10, 3))}, np.zeros((100, 3))):
        with pytest.raises(SceneError, match="^end: expected a sparseart.types.LabelledCloud"):
            run_clouds(good, bad)


def test_validate_clouds_converts_and_keeps_good_clouds() -> None:
    from sparseart.io.validate import validate_clouds

    fields = fc.cloud_fields()
    cloud = _cloud("start", fields)
    same, _ = validate_clouds(cloud, cloud)
    assert same is cloud
    narrow = _cloud("start", {**fields, "points": fields["points"].astype(np.float32),
                              "segment": fields["segment"].astype(np.int16)})
    converted, _ = validate_clouds(narrow, cloud)
    assert converted.points.dtype == np.float64 and converted.segment.dtype == np.int64
    assert narrow.points.dtype == np.float32   # the caller's cloud is not modified


def test_validate_clouds_subsamples_to_the_budget() -> None:
    from sparseart.io.validate import validate_clouds

    cloud = _cloud("start", fc.cloud_fields(5000))
    small, _ = validate_clouds(cloud, cloud, budget=1000)
    again, _ = validate_clouds(cloud, cloud, budget=1000)
    assert len(small) == 1000 and np.array_equal(small.pixel_index, again.pixel_index)
    assert np.all(np.diff(small.pixel_index) > 0)   # a subset, in order


# ---------------------------------------------------------------------- a hostile VLM server


@pytest.mark.parametrize("mode", fc.VLM_MODES)
def test_vlm_client_survives_a_hostile_server(mode: str) -> None:
    from sparseart.labelers.vlm_client import VlmClient, VlmError

    server = fc.HostileVlmServer(mode, drip=0.05)
    try:
        client = VlmClient(server.base_url, "m", timeout=1.0, max_retries=1, backoff=0.01)
        began = time.perf_counter()
        with pytest.raises(VlmError) as info:
            client.ask_json("how many?", [], {"type": "object", "properties": {
                "moving_parts": {"type": "integer", "minimum": 0, "maximum": 10}}, "required": ["moving_parts"]})
        seconds = time.perf_counter() - began
    finally:
        server.close()
    message = str(info.value)
    _record(f"vlm_{mode}", "VLM server", 0, 0, _lines(message), seconds)
    assert "\n" not in message
    assert seconds < 2 * 1.0 + 2.0, f"{seconds:.1f} s for a 1 s timeout and 2 attempts"


@pytest.fixture(scope="module")
def vlm_inputs(base_scene):
    from sparseart.io.scene import load_scene
    from sparseart.lift.labels import build_labelled_cloud
    from sparseart.lift.scene_lift import lift_scene

    scene = load_scene(base_scene)
    lifted = lift_scene(scene)
    clouds = tuple(build_labelled_cloud(s, scene.frames(s), lifted.pointmaps[s]) for s in ("start", "end"))
    return scene, clouds


@pytest.mark.parametrize("mode", ["deep_content", "nan_content", "list_content_nested", "huge_body", "drip_body",
                                  "bool_count", "reset"])
def test_vlm_labeler_falls_back_to_rules(mode: str, vlm_inputs) -> None:
    from sparseart.labelers import MockLabeler
    from sparseart.labelers.vlm import VlmLabeler, VlmLabelerConfig

    scene, (start, end) = vlm_inputs
    server = fc.HostileVlmServer(mode, drip=0.05)
    try:
        labeler = VlmLabeler(server.base_url, "m", timeout=1.0, max_retries=0, backoff=0.0,
                             config=VlmLabelerConfig(max_pairs=1, answer_retries=0, overlay_min_side=64),
                             fallback=MockLabeler({1: 0}))
        began = time.perf_counter()
        labels = labeler.label(start, end, scene)
        seconds = time.perf_counter() - began
    finally:
        server.close()
    assert labeler.last_report["fallback"], labeler.last_report
    assert labels.warnings[0].startswith("VLM labeler not used (")
    assert seconds < 10.0


@pytest.mark.parametrize("error", [RecursionError("deep"), TypeError("list indices"), KeyError("choices"),
                                   MemoryError(), OverflowError("int too large")])
def test_any_vlm_failure_falls_back(error: BaseException, vlm_inputs, monkeypatch) -> None:
    from sparseart.labelers import MockLabeler
    from sparseart.labelers.vlm import VlmLabeler

    scene, (start, end) = vlm_inputs
    labeler = VlmLabeler("http://127.0.0.1:9/v1", "m", fallback=MockLabeler({1: 0}))

    def explode(*args, **kwargs):
        raise error

    monkeypatch.setattr(labeler, "_answers", explode)
    labels = labeler.label(start, end, scene)
    assert type(error).__name__ in labels.warnings[0] and labels.warnings[0].startswith("VLM labeler not used")


def test_strict_json_limits() -> None:
    from sparseart.labelers.vlm_client import VlmAnswerError, extract_json, validate_json

    for text in ['{"a": NaN}', '{"a": Infinity}', '{"a": 1e400}', "[" * 5000 + "]" * 5000,
                 '{"a": ' + "[" * 100 + "]" * 100 + "}"]:
        with pytest.raises(VlmAnswerError):
            extract_json(text)
    schema = {"type": "object", "properties": {"x": {"type": "number", "minimum": 0, "maximum": 1}}}
    assert validate_json({"x": float("nan")}, schema)
    assert validate_json({"x": True}, schema)
    assert not validate_json({"x": 0.5}, schema)


# ---------------------------------------------------------------------- heavy (python3 -m pytest -m fuzz_heavy)


def _real_png_bomb(path: Path, side: int) -> None:
    """A genuinely valid side x side RGB PNG of zeros (about 1.2 MB for 20000): decoding it would
    take side^2 * 3 bytes."""
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0)
    compressor = zlib.compressobj(9)
    row = b"\0" * (1 + 3 * side)
    chunks = [compressor.compress(row) for _ in range(side)]
    data = b"".join(chunks) + compressor.flush()
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + fc._png_chunk(b"IHDR", ihdr) + fc._png_chunk(b"IDAT", data)
                     + fc._png_chunk(b"IEND", b""))


@pytest.mark.fuzz_heavy
@pytest.mark.parametrize("rel", ["start/rgb/000.png", "end/depth/000.png", "start/mask/000.png"])
def test_heavy_real_decompression_bomb(rel: str, base_scene: Path, tmp_path: Path) -> None:
    scene = _copy_scene(base_scene, tmp_path)
    _real_png_bomb(scene / rel, 20000)
    out = tmp_path / "out"
    before = _tree(tmp_path)
    code, err, seconds, peak = _run_child(["run", str(scene), "--out", str(out)], tmp_path)
    _check_failure(f"bomb_{rel}", "huge headers", 2, code, err, rel, seconds, CHILD_TIMEOUT_S, before,
                   _tree(tmp_path), out, False, peak)
    assert peak < 1024, f"peak {peak:.0f} MB"


@pytest.mark.fuzz_heavy
def test_heavy_too_many_pixels(tmp_path: Path) -> None:
    """A consistent scene of 4096 x 4096 views, two per state: the scene pixel budget refuses it
    at the third image instead of running out of memory."""
    import cv2

    from conftest import write_tiny_scene

    scene = write_tiny_scene(tmp_path / "scene", views=2)
    side = 4096
    for state in ("start", "end"):
        for i in range(2):
            cv2.imwrite(str(scene / state / "rgb" / f"{i:03d}.png"), np.zeros((side, side, 3), np.uint8))
            cv2.imwrite(str(scene / state / "depth" / f"{i:03d}.png"), np.full((side, side), 1000, np.uint16))
            cv2.imwrite(str(scene / state / "mask" / f"{i:03d}.png"), np.ones((side, side), np.uint8))
    data = json.loads((scene / "cameras.json").read_text())
    for state in ("start", "end"):
        for entry in data[state]:
            entry["K"] = [[side, 0, side / 2], [0, side, side / 2], [0, 0, 1]]
    (scene / "cameras.json").write_text(json.dumps(data))
    before = _tree(tmp_path)
    code, err, seconds, peak = _run_child(["run", str(scene), "--out", str(tmp_path / "out")], tmp_path)
    _check_failure("scene_pixel_budget", "huge headers", 2, code, err, "end/rgb/000.png", seconds,
                   CHILD_TIMEOUT_S, before, _tree(tmp_path), tmp_path / "out", False, peak)


@pytest.mark.fuzz_heavy
def test_heavy_ten_million_points_subsampled() -> None:
    from sparseart import run_clouds
    from sparseart.io.validate import CLOUD_POINT_BUDGET
    from sparseart.labelers import MockLabeler
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    n = 10_000_000
    body = rng.uniform([-0.5, -0.5, 0.0], [0.5, 0.5, 0.02], (n // 2, 3))
    door = rng.uniform([0.0, -0.5, 0.03], [0.6, 0.5, 0.05], (n - n // 2, 3))
    turn = Rotation.from_rotvec([0.0, 0.6, 0.0]).as_matrix()
    moved = door @ turn.T
    segment = np.concatenate([np.full(n // 2, 1), np.full(n - n // 2, 2)]).astype(np.int64)

    def cloud(state: str, points: np.ndarray) -> LabelledCloud:
        return LabelledCloud(state=state, points=points, colors=np.full((n, 3), 0.5, np.float32),
                             segment=segment, frame_index=np.zeros(n, np.int32), pixel_index=np.arange(n),
                             confidence=np.ones(n, np.float32), segment_source={1: (0, 1), 2: (0, 2)})

    began = time.perf_counter()
    result = run_clouds(cloud("start", np.vstack([body, door])), cloud("end", np.vstack([body, moved])),
                        labeler=MockLabeler({1: 0, 2: 1}), joint_type="revolute")
    seconds = time.perf_counter() - began
    assert len(result.start_cloud) == CLOUD_POINT_BUDGET
    (_, joint), = result.joints
    assert abs(abs(joint.axis[1]) - 1.0) < 0.01 and joint.angle == pytest.approx(0.6, abs=0.01)
    _record("clouds_10M", "run_clouds", 0, 0, [], seconds)


@pytest.mark.fuzz_heavy
def test_heavy_dripping_vlm_through_the_cli(base_scene: Path, tmp_path: Path) -> None:
    """--vlm-timeout 2 against a server dripping a byte every 0.2 s: the run falls back to the
    rules and ends in bounded time (3 attempts x 2 s + backoff), exit 0 with the warning."""
    scene = _copy_scene(base_scene, tmp_path)
    out = tmp_path / "out"
    server = fc.HostileVlmServer("drip_body", drip=0.2)
    try:
        code, err, seconds, peak = _run_child(["run", str(scene), "--out", str(out), "--labeler", "vlm",
                                               "--vlm-base-url", server.base_url, "--vlm-model", "m",
                                               "--vlm-timeout", "2"], tmp_path)
    finally:
        server.close()
    _record("vlm_drip_cli", "VLM server", 0, code, _lines(err), seconds, peak)
    assert code == 0, err
    warnings = json.loads((out / "articulation.json").read_text())["warnings"]
    assert any("VLM labeler not used" in w and "timed out" in w for w in warnings), warnings
    assert seconds < 60


@pytest.mark.fuzz_heavy
@pytest.mark.parametrize("case", [c for c in SCENE_CASES if not c.child][::7],
                         ids=[c.name for c in SCENE_CASES if not c.child][::7])
def test_heavy_scene_cases_in_a_child(case: fc.Case, base_scene: Path, tmp_path: Path) -> None:
    """Every 7th in-process case again in a child: the real stderr (fd 2) and the peak memory."""
    scene = _copy_scene(base_scene, tmp_path, case.scene_name)
    culprit = case.mutate(scene)
    out = case.out(scene, tmp_path) if case.out else tmp_path / "out"
    culprit = culprit or str(out)
    out_existed = os.path.lexists(out)
    before = _tree(tmp_path)
    code, err, seconds, peak = _run_child(["run", str(scene), "--out", str(out), *case.args], tmp_path)
    _check_failure(f"child_{case.name}", case.kind, case.expect, code, err,
                   culprit.replace("\n", "\\n"), seconds, CHILD_TIMEOUT_S, before, _tree(tmp_path), out,
                   out_existed, peak)


STILL = fc.still_under_noise()


@pytest.mark.parametrize("name", sorted(STILL))
def test_still_scene_under_depth_noise_gives_no_joint(name: str, tmp_path: Path) -> None:
    """Issue 61: nothing moved and the states differ only by 1 % depth noise: no joint at all,
    and a warning that says nothing moved (measurably)."""
    from sparseart import run

    result = run(STILL[name](tmp_path / "scene"))
    assert result.joints == [], [(j.type, j.confidence, j.distance) for _, j in result.joints]
    assert any("no part moved" in w or "no measurable motion" in w for w in result.warnings), result.warnings


def test_a_real_slide_under_the_same_noise_is_still_found(tmp_path: Path) -> None:
    """The control of the test above: the box slid 12 cm under the same noise is a slide along z."""
    from sparseart import run

    result = run(fc.box_slid_under_noise()(tmp_path / "scene"))
    slides = [j for _, j in result.joints if j.type == "prismatic" and abs(j.axis[2]) > 0.98]
    assert slides and abs(slides[0].distance - 0.12) < 0.03, [(j.type, j.axis, j.distance) for _, j in result.joints]


# ---------------------------------------------------------------------- fragmented masks (issue 61)


def _checkerboard_masks(scene: Path, block: int) -> None:
    """Replace every mask of the scene by square blocks of ``block`` pixels over the object."""
    import cv2

    for path in sorted(scene.glob("*/mask/*.png")):
        old = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        rows, cols = np.mgrid[0:old.shape[0], 0:old.shape[1]]
        blocks = (rows // block) * (-(-old.shape[1] // block)) + cols // block + 1
        cv2.imwrite(str(path), np.where(old > 0, blocks, 0).astype(np.uint16))


@pytest.fixture(scope="module")
def cabinet_160(tmp_path_factory) -> tuple[Path, dict]:
    """The synthetic cabinet (door turned 49 deg about z, drawer slid 0.29 along -x), 2 views per
    state at 160x120, with its true joints."""
    from sparseart.datasets.synth import render_synth_scene

    root = tmp_path_factory.mktemp("cabinet_160") / "scene"
    gt = render_synth_scene(root, views=2, seed=0, width=160, height=120)
    return root, {j["type"]: j for j in gt["joints"]}


def _is_true_joint(joint, truth: dict) -> bool:
    """The joint is one of the cabinet's: same type, axis within 5 deg, angle within 3 deg and the
    hinge line within 3 cm, or the slide within 2 cm."""
    true = truth.get(joint.type)
    if true is None or np.degrees(np.arccos(min(1.0, abs(float(np.dot(joint.axis, true["axis"])))))) > 5.0:
        return False
    if joint.type == "prismatic":
        return abs(joint.distance - true["distance"]) < 0.02
    offset = np.asarray(joint.origin) - np.asarray(true["origin"])
    off_line = offset - (offset @ np.asarray(true["axis"])) * np.asarray(true["axis"])
    return abs(np.degrees(joint.angle - true["angle"])) < 3.0 and float(np.linalg.norm(off_line)) < 0.03


@pytest.mark.parametrize("block", [8, 16])
def test_checkerboard_masks_fall_back_to_the_motion_split(block: int, cabinet_160, tmp_path: Path) -> None:
    """Masks cut into square blocks (an over-eager segmenter; 8 px: ~60 effective pieces per
    image, 16 px: ~16-24) are not used, with a warning naming the images, and the motion split
    finds the door and the drawer; no wrong joint at confidence >= 0.5 (before: 16 px blocks gave
    a hinge 21 deg off at 0.58)."""
    from sparseart import run

    base, truth = cabinet_160
    scene = _copy_scene(base, tmp_path)
    _checkerboard_masks(scene, block)
    result = run(scene)
    named = [w for w in result.warnings if w.startswith("masks not used")]
    assert named and "start/mask/000.png" in named[0] and "end/mask/001.png" in named[0], result.warnings
    assert result.labels.diagnostics.get("motion_split") is True
    wrong = [(j.type, j.confidence) for _, j in result.joints if j.confidence >= 0.5 and not _is_true_joint(j, truth)]
    assert wrong == []
    assert sorted(j.type for _, j in result.joints if _is_true_joint(j, truth)) == ["prismatic", "revolute"]


def test_speckled_checkerboard_masks_are_a_clear_error(cabinet_160, tmp_path: Path, capfd) -> None:
    """4-pixel blocks leave no id of a usable size: bad input, one line naming the mask, exit 2."""
    base, _ = cabinet_160
    scene = _copy_scene(base, tmp_path)
    _checkerboard_masks(scene, 4)
    out = tmp_path / "out"
    assert main(["run", str(scene), "--out", str(out)]) == 2
    lines = _lines(capfd.readouterr().err)
    assert len(lines) == 1 and "mask/000.png" in lines[0] and not out.exists()
