"""``sparseart view``: reading OUT/ (sources, frames, poses), the CLI's bad-input lines, and the page
in a real headless browser (Debian's chromium driven by Playwright; skipped only without it)."""
from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from sparseart.cli import main
from sparseart.geometry.transforms import apply_transform, transform_from_prismatic, transform_from_revolute
from sparseart.io.articulation import write_articulation
from sparseart.io.ply import part_colour, write_labelled_clouds, write_ply
from sparseart.sim.links import link_name
from sparseart.view import cone_mesh, load_view_data, part_poses, slider_range
from sparseart.types import (Articulation, JointEstimate, LabelledCloud, PartLabels, PartResult, PartSpec,
                             StageRecord)
from synthetic import joint_estimate, labelled_cloud

REPO_ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)
# Bounds (not asserts) on waiting for a software-rendered page on a busy 2-core machine.
PAGE_TIMEOUT_MS = 120_000
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]

HINGE_AXIS, HINGE_ORIGIN, DOOR_ANGLE = np.array([0.0, 0.0, 1.0]), np.array([0.3, -0.3, 0.4]), -1.0
SLIDE_AXIS, SLIDE_DISTANCE = np.array([0.0, -1.0, 0.0]), 0.25
KNOB_AXIS, KNOB_ORIGIN, KNOB_ANGLE = np.array([1.0, 0.0, 0.0]), np.array([0.3, 0.1, 0.6]), 0.8


_cloud = labelled_cloud


def _joint(kind: str, axis, origin, amount: float, transform: np.ndarray) -> JointEstimate:
    return joint_estimate(kind, axis, origin, amount, transform, axis_sigma_deg=4.0)   # cones wide enough to see


@pytest.fixture
def articulation() -> Articulation:
    """A cabinet: static body (0), a door (1, revolute, negative angle), a drawer (2, prismatic) and
    a knob (3) hinged on the door (parent 1); the end cloud is each part moved by its chain."""
    rng = np.random.default_rng(0)
    body = rng.uniform([-0.3, -0.3, 0.0], [0.3, 0.3, 0.8], (3000, 3))
    door = rng.uniform([-0.3, -0.32, 0.05], [0.3, -0.3, 0.75], (3000, 3))
    drawer = rng.uniform([-0.25, -0.29, 0.82], [0.25, 0.25, 0.95], (2000, 3))
    knob = rng.uniform([0.25, -0.36, 0.55], [0.28, -0.32, 0.65], (300, 3))
    door_motion = transform_from_revolute(HINGE_AXIS, HINGE_ORIGIN, DOOR_ANGLE)
    drawer_motion = transform_from_prismatic(SLIDE_AXIS, SLIDE_DISTANCE)
    knob_motion = transform_from_revolute(KNOB_AXIS, KNOB_ORIGIN, KNOB_ANGLE)
    start = np.concatenate([body, door, drawer, knob])
    end = np.concatenate([body, apply_transform(door_motion, door), apply_transform(drawer_motion, drawer),
                          apply_transform(door_motion @ knob_motion, knob)])
    part = np.repeat([0, 1, 2, 3], [3000, 3000, 2000, 300])
    part[:20] = -1
    parts = [PartSpec(0, "static"), PartSpec(1, "movable", parent=0), PartSpec(2, "movable", parent=0),
             PartSpec(3, "movable", parent=1)]
    labels = PartLabels(parts=parts, start_part=part, end_part=part.copy())
    joints = {1: _joint("revolute", HINGE_AXIS, HINGE_ORIGIN, DOOR_ANGLE, door_motion),
              2: _joint("prismatic", SLIDE_AXIS, drawer.mean(0), SLIDE_DISTANCE, drawer_motion),
              3: _joint("revolute", KNOB_AXIS, KNOB_ORIGIN, KNOB_ANGLE, knob_motion)}
    results = [PartResult(spec, int((part == spec.id).sum() * 2), joints.get(spec.id)) for spec in parts]
    return Articulation("world", "test", "metres", results, [StageRecord("fit", True, 1.0, "x")], [],
                        _cloud("start", start), _cloud("end", end), labels)


def _write_out(result: Articulation, out: Path, ply: bool = True, urdf: bool = True) -> Path:
    """OUT/ as ``sparseart run --ply`` writes it (the same writers), and with ``urdf`` each link's
    start points as ``meshes/<link>.ply`` in its link frame (the URDF's frames; what the viewer
    shows when a folder has link clouds but no fused OBJ meshes)."""
    out.mkdir(parents=True, exist_ok=True)
    write_articulation(result, out)
    if ply:
        write_labelled_clouds(result, out)
    if urdf:
        cloud, labels = result.start_cloud, result.labels.start_part
        for part in result.parts:
            origin = part.joint.origin if part.joint is not None else np.zeros(3)
            keep = labels == part.spec.id
            write_ply(out / "meshes" / f"{link_name(part.spec.id)}.ply", cloud.points[keep] - origin,
                      cloud.colors[keep])
    return out


def _end_values() -> dict[int, float]:
    return {1: np.degrees(DOOR_ANGLE), 2: SLIDE_DISTANCE, 3: np.degrees(KNOB_ANGLE)}


# ---------------------------------------------------------------------- reading OUT/ (no viser needed)


def test_geometry_sources_obj_then_link_ply_then_labelled_cloud(articulation, tmp_path):
    trimesh = pytest.importorskip("trimesh")
    out = _write_out(articulation, tmp_path / "out")
    start, labels = articulation.start_cloud.points, articulation.labels.start_part
    data = load_view_data(out)
    assert {p: g.source for p, g in data.geometry.items()} == {0: "points", 1: "points", 2: "points", 3: "points"}
    for part, geometry in data.geometry.items():  # link-frame PLY shifted back into the root frame
        np.testing.assert_allclose(geometry.points, start[labels == part], atol=1e-9)
    assert set(data.observed) == {"start", "end"}

    box = trimesh.creation.box(extents=(0.6, 0.02, 0.7))  # the door's mesh in its link frame, coloured
    box.visual.vertex_colors = np.tile([200, 100, 50, 255], (len(box.vertices), 1))
    box.export(out / "meshes" / "part_1.obj")
    data = load_view_data(out)
    assert data.geometry[1].source == "mesh" and data.geometry[1].faces.shape == (12, 3)
    np.testing.assert_allclose(data.geometry[1].points, np.asarray(box.vertices) + HINGE_ORIGIN, atol=1e-6)
    np.testing.assert_allclose(data.geometry[1].colours, np.tile([200, 100, 50], (8, 1)) / 255.0, atol=1e-6)
    assert data.geometry[2].source == "points"

    shutil.rmtree(out / "meshes")
    data = load_view_data(out)
    assert {g.source for g in data.geometry.values()} == {"labelled"}
    np.testing.assert_allclose(data.geometry[3].points, start[labels == 3])


def test_sliders_at_the_end_values_move_every_part_onto_its_end_points(articulation, tmp_path):
    data = load_view_data(_write_out(articulation, tmp_path / "out", urdf=False))
    end, labels = articulation.end_cloud.points, articulation.labels.end_part
    poses = part_poses(data, _end_values())
    for part in (0, 1, 2, 3):  # the knob (3) hangs on the door: its pose composes both turns
        np.testing.assert_allclose(apply_transform(poses[part], data.geometry[part].points), end[labels == part],
                                   atol=1e-9)
    at_start = part_poses(data, {})
    assert all(np.allclose(pose, np.eye(4)) for pose in at_start.values())


def test_slider_range_spans_both_states_and_beyond(articulation, tmp_path):
    data = load_view_data(_write_out(articulation, tmp_path / "out", urdf=False))
    for part, end in _end_values().items():
        low, high, step = slider_range(data.joints[part], data.size())
        assert low < min(0.0, end) and high > max(0.0, end) and 0 < step < (high - low) / 50
    door = data.joints[1]
    door.amount = None  # an unknown angle still gets a slider both ways
    low, high, _ = slider_range(door, data.size())
    assert low < 0 < high


def test_cone_has_its_apex_on_the_axis_and_the_stated_half_angle():
    apex, direction = np.array([0.1, 0.2, 0.3]), np.array([0.0, 0.6, 0.8])
    vertices, faces = cone_mesh(apex, direction, 10.0, 0.5)
    offsets = vertices - apex
    lengths = np.linalg.norm(offsets, axis=1)
    assert faces.max() < len(vertices) and np.isclose(lengths.min(), 0.0)
    tilt = np.degrees(np.arccos(np.clip(offsets[lengths > 1e-9] @ direction / lengths[lengths > 1e-9], -1, 1)))
    assert tilt.max() == pytest.approx(10.0, abs=1e-6)
    assert (offsets @ direction).max() == pytest.approx(0.5)


@pytest.mark.parametrize("missing, named", [("articulation.json", "articulation.json"),
                                            ("geometry", "start_parts.ply")])
def test_missing_inputs_are_one_line_and_exit_2(articulation, tmp_path, capsys, missing, named):
    out = _write_out(articulation, tmp_path / "out", ply=missing != "geometry", urdf=missing != "geometry")
    if missing == "articulation.json":
        (out / "articulation.json").unlink()
    assert main(["view", str(out), "--seconds", "0", "--port", "0"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and named in lines[0] and str(out) in lines[0]


def test_malformed_articulation_json_is_bad_input(articulation, tmp_path, capsys):
    out = _write_out(articulation, tmp_path / "out")
    (out / "articulation.json").write_text('{"schema": "sparseart/articulation/1", "joints": [{"part": 1, '
                                           '"type": "revolute", "axis": [0, 0], "origin": [0, 0, 0]}]}')
    assert main(["view", str(out), "--seconds", "0", "--port", "0"]) == 2
    assert "joints[0].axis" in capsys.readouterr().err


def test_help_and_run_do_not_import_viser(tmp_path):
    code = ("import sys, contextlib, io\n"
            "from sparseart.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    try: main(['--help'])\n"
            "    except SystemExit: pass\n"
            f"assert main(['run', {str(tmp_path / 'absent')!r}, '--out', {str(tmp_path / 'o')!r}]) == 2\n"
            "assert 'viser' not in sys.modules, 'viser imported'\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True, text=True, timeout=120,
                          env={"PYTHONPATH": str(REPO_ROOT), "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr


# ---------------------------------------------------------------------- the page in a real browser


def test_cli_serves_for_the_given_seconds_and_prints_the_address(articulation, tmp_path, capsys):
    pytest.importorskip("viser")
    out = _write_out(articulation, tmp_path / "out")
    assert main(["view", str(out), "--port", "0", "--seconds", "0"]) == 0
    printed = capsys.readouterr().out
    assert "sparseart view: http://127.0.0.1:" in printed


def _screenshot(page) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(page.screenshot(timeout=PAGE_TIMEOUT_MS), np.uint8),
                        cv2.IMREAD_COLOR)[:, :, ::-1]  # RGB


def _mask_of(image: np.ndarray, part: int, tolerance: float = 30.0) -> np.ndarray:
    """Pixels within ``tolerance`` (per channel, 0..255) of a part's colour."""
    rgb = np.asarray(part_colour(part)) * 255.0
    return np.all(np.abs(image.astype(float) - rgb) < tolerance, axis=2)


def _wait_for(page, check, seconds: float = 60.0):
    """Screenshots until ``check(image)`` holds (bounded; the last image either way)."""
    deadline = time.monotonic() + seconds
    while True:
        image = _screenshot(page)
        if check(image) or time.monotonic() > deadline:
            return image
        time.sleep(0.3)


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium at /usr/bin/chromium or on PATH "
                                             "(apt-get install chromium; scripts/setup.sh does)")
def test_page_draws_the_parts_and_the_slider_moves_the_door(articulation, tmp_path):
    pytest.importorskip("viser")
    playwright = pytest.importorskip("playwright.sync_api")
    from sparseart.view import start_viewer

    out = _write_out(articulation, tmp_path / "out")
    viewer = start_viewer(load_view_data(out), port=0)
    address = viewer.url.split("/")[2]
    hosts: set[str] = set()
    try:
        with playwright.sync_playwright() as driver:
            browser = driver.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            try:
                page = browser.new_page(viewport={"width": 800, "height": 450})
                page.set_default_timeout(PAGE_TIMEOUT_MS)
                page.on("request", lambda request: hosts.add(request.url.split("/")[2]))
                page.goto(viewer.url)
                page.wait_for_selector("canvas")
                page.get_by_text("angle (deg)").first.wait_for()
                sliders = page.get_by_role("slider")
                assert sliders.count() == 3  # door, drawer, knob
                page.evaluate("document.querySelectorAll('.mantine-Notification-closeButton')"
                              ".forEach(button => button.click())")  # the "software WebGL" notice

                def drawn(image):  # the door (blue), the body (grey) and the drawer (orange)
                    return min(_mask_of(image, part).sum() for part in (0, 1, 2)) > 300
                before = _wait_for(page, drawn)
                cv2.imwrite(str(tmp_path / "start.png"), before[:, :, ::-1])
                assert drawn(before), f"the parts are not drawn on the page (see {tmp_path / 'start.png'})"

                viewer.set_joint(1, np.degrees(DOOR_ANGLE))
                pose = viewer.poses()[1]
                np.testing.assert_allclose(pose, articulation.parts[1].joint.transform, atol=1e-9)
                np.testing.assert_allclose(viewer.part_nodes[1].position, pose[:3, 3], atol=1e-6)
                door_before = _mask_of(before, 1)

                def moved(image):
                    door = _mask_of(image, 1)
                    overlap = (door & door_before).sum() / max((door | door_before).sum(), 1)
                    return door.sum() > 500 and overlap < 0.7
                after = _wait_for(page, moved)
                cv2.imwrite(str(tmp_path / "end.png"), after[:, :, ::-1])
                assert moved(after), f"the door did not move on the page (see {tmp_path / 'end.png'})"
                page.wait_for_function(  # the page's own slider followed the server's value
                    "v => [...document.querySelectorAll('[role=slider]')].some("
                    "s => Math.abs(parseFloat(s.getAttribute('aria-valuenow')) - v) < 0.5)",
                    arg=float(np.degrees(DOOR_ANGLE)))
                box = page.locator("input:visible:not([type=checkbox])").first  # the door slider's number box
                box.fill("-20")
                box.press("Enter")
                deadline = time.monotonic() + 30.0
                while abs(viewer.values[1] + 20.0) > 1e-6 and time.monotonic() < deadline:
                    time.sleep(0.1)
                assert viewer.values[1] == pytest.approx(-20.0), "the page's slider did not reach the server"
            finally:
                browser.close()
    finally:
        viewer.close()
    assert hosts == {address}, f"the page fetched from elsewhere: {hosts}"
