"""URDF / PLY / report-PNG exports: round trips through real readers (yourdfpy, open3d)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from sparseart.geometry.transforms import apply_transform, transform_from_prismatic, transform_from_revolute
from sparseart.io.ply import part_colour, write_labelled_clouds
from sparseart.types import (Articulation, JointEstimate, LabelledCloud, PartLabels, PartResult, PartSpec,
                             StageRecord)
from sparseart.io.urdf import write_urdf
from sparseart.io.report import write_report

from synthetic import box_surface, joint_estimate, labelled_cloud

HINGE_AXIS = np.array([0.0, 0.0, 1.0])
HINGE_ORIGIN = np.array([0.3, -0.2, 0.4])
DOOR_ANGLE = -0.7  # negative: the lower limit must be the angle
SLIDE_AXIS = np.array([1.0, 0.0, 0.0])
SLIDE_DISTANCE = 0.25
KNOB_AXIS = np.array([0.0, 1.0, 0.0])
KNOB_ORIGIN = np.array([0.5, -0.2, 0.6])


_cloud, _joint = labelled_cloud, joint_estimate


@pytest.fixture
def articulation() -> Articulation:
    return make_articulation()


@pytest.fixture(scope="module")
def urdf_export(tmp_path_factory):
    """(articulation, folder) of one --urdf export of the articulation, shared by the URDF tests
    (the surfaces and coacd pieces take seconds)."""
    folder = tmp_path_factory.mktemp("urdf")
    result = make_articulation()
    return result, write_urdf(result, folder, name="object")


def make_articulation() -> Articulation:
    """Static body (0), a door (1, revolute, negative angle), a drawer (2, prismatic) and a knob (3)
    hinged on the door (parent 1)."""
    rng = np.random.default_rng(0)
    counts = [6000, 3000, 2000, 500]   # points on box surfaces, dense enough for a clean Poisson surface
    body = box_surface([1.0, 1.0, 0.8], [0.0, 0.0, 0.4], counts[0], rng)[0]
    door = box_surface([0.1, 0.5, 0.8], [0.3, 0.05, 0.4], counts[1], rng)[0]
    drawer = box_surface([0.4, 0.1, 0.2], [0.0, -0.35, 0.2], counts[2], rng)[0]
    knob = box_surface([0.1, 0.1, 0.1], [0.5, -0.2, 0.6], counts[3], rng)[0]
    door_motion = transform_from_revolute(HINGE_AXIS, HINGE_ORIGIN, DOOR_ANGLE)
    drawer_motion = transform_from_prismatic(SLIDE_AXIS, SLIDE_DISTANCE)
    start = np.concatenate([body, door, drawer, knob])
    knob_motion = transform_from_revolute(KNOB_AXIS, KNOB_ORIGIN, 0.3)   # the knob turns on the moving door
    end = np.concatenate([body, apply_transform(door_motion, door), apply_transform(drawer_motion, drawer),
                          apply_transform(door_motion @ knob_motion, knob)])
    part = np.repeat([0, 1, 2, 3], counts)
    part[:10] = -1
    parts = [PartSpec(0, "static"), PartSpec(1, "movable", parent=0), PartSpec(2, "movable", parent=0),
             PartSpec(3, "movable", parent=1)]
    labels = PartLabels(parts=parts, start_part=part, end_part=part.copy())
    joints = {1: _joint("revolute", HINGE_AXIS, HINGE_ORIGIN, DOOR_ANGLE, door_motion),
              2: _joint("prismatic", SLIDE_AXIS, drawer.mean(0), SLIDE_DISTANCE, drawer_motion),
              3: _joint("revolute", KNOB_AXIS, KNOB_ORIGIN, 0.3, knob_motion)}
    results = [PartResult(spec, int((part == spec.id).sum() * 2), joints.get(spec.id)) for spec in parts]
    stages = [StageRecord("lift", True, 0.1, "x"), StageRecord("label", True, 0.5, "x"),
              StageRecord("fit", True, 1.2, "x"), StageRecord("refine", False, 0.0, "not requested")]
    return Articulation("world", "test", "metres", results, stages, ["a warning"], _cloud("start", start),
                        _cloud("end", end), labels)


def test_urdf_round_trip_through_yourdfpy(urdf_export):
    yourdfpy = pytest.importorskip("yourdfpy")
    _, path = urdf_export
    model = yourdfpy.URDF.load(str(path), load_collision_meshes=True)  # loads the OBJ meshes too (relative paths)
    assert model.validate()
    assert set(model.link_map) == {"base", "part_1", "part_2", "part_3"}
    assert len(model.scene.geometry) == 4
    for link in model.link_map.values():
        assert link.collisions and link.inertial.mass > 0
        assert np.all(np.linalg.eigvalsh(link.inertial.inertia) > 0)
    joints = model.joint_map
    assert joints["joint_1"].type == "revolute" and joints["joint_2"].type == "prismatic"
    assert joints["joint_3"].parent == "part_1"
    np.testing.assert_allclose(joints["joint_1"].axis, HINGE_AXIS, atol=1e-9)
    np.testing.assert_allclose(joints["joint_1"].origin[:3, 3], HINGE_ORIGIN, atol=1e-9)
    np.testing.assert_allclose(joints["joint_3"].origin[:3, 3], KNOB_ORIGIN - HINGE_ORIGIN, atol=1e-9)
    assert (joints["joint_1"].limit.lower, joints["joint_1"].limit.upper) == pytest.approx((DOOR_ANGLE, 0.0))
    assert (joints["joint_2"].limit.lower, joints["joint_2"].limit.upper) == pytest.approx((0.0, SLIDE_DISTANCE))


def test_urdf_end_configuration_reproduces_the_end_state(urdf_export):
    """At joint position 0 every part's mesh (in its link frame) lies on its start points; setting
    each joint to its fitted angle / distance moves it where the fitted motion takes it: the frame
    conventions agree."""
    yourdfpy = pytest.importorskip("yourdfpy")
    import trimesh
    from scipy.spatial import cKDTree

    articulation, path = urdf_export
    model = yourdfpy.URDF.load(str(path))
    labels, start = articulation.labels.start_part, articulation.start_cloud.points
    local = {link: np.asarray(trimesh.load(path.parent / "meshes" / f"{link}.obj", process=False).vertices)
             for link in ("part_1", "part_2", "part_3")}
    model.update_cfg({"joint_1": 0.0, "joint_2": 0.0, "joint_3": 0.0})
    rest = {link: apply_transform(model.get_transform(link, "base"), v) for link, v in local.items()}
    for part_id in (1, 2, 3):
        points = start[labels == part_id]
        extent = np.linalg.norm(points.max(0) - points.min(0))
        assert cKDTree(rest[f"part_{part_id}"]).query(points)[0].mean() < 0.1 * extent
    model.update_cfg({"joint_1": DOOR_ANGLE, "joint_2": SLIDE_DISTANCE, "joint_3": 0.0})
    for part_id, link in ((1, "part_1"), (2, "part_2"), (3, "part_3")):
        placed = apply_transform(model.get_transform(link, "base"), local[link])
        motion = articulation.parts[1].joint.transform if part_id != 2 else articulation.parts[2].joint.transform
        np.testing.assert_allclose(placed, apply_transform(motion, rest[link]), atol=1e-6)


def test_urdf_rejects_non_finite_joint(articulation, tmp_path):
    articulation.parts[1].joint.origin = np.array([np.nan, 0.0, 0.0])
    with pytest.raises(ValueError, match="part 1"):
        write_urdf(articulation, tmp_path)
    assert not any(tmp_path.iterdir())


def test_ply_round_trip_through_open3d(articulation, tmp_path):
    import open3d as o3d

    paths = write_labelled_clouds(articulation, tmp_path)
    assert [p.name for p in paths] == ["start_parts.ply", "end_parts.ply"]
    for path, cloud, part in zip(paths, (articulation.start_cloud, articulation.end_cloud),
                                 (articulation.labels.start_part, articulation.labels.end_part)):
        legacy = o3d.io.read_point_cloud(str(path))
        np.testing.assert_array_equal(np.asarray(legacy.points), cloud.points)  # float64 kept exactly
        colours = np.asarray(legacy.colors)
        np.testing.assert_allclose(colours[part == 2][0], part_colour(2), atol=1 / 255)
        assert not np.allclose(colours[part == 1][0], colours[part == 2][0])
        tensor = o3d.t.io.read_point_cloud(str(path))
        np.testing.assert_array_equal(tensor.point["part"].numpy().ravel(), part)


def test_report_png_is_drawn(articulation, tmp_path):
    path = write_report(articulation, tmp_path / "report.png")
    image = cv2.imread(str(path))
    assert image is not None and image.shape[0] > 300 and image.shape[1] > 900
    assert float(image.std()) > 10.0  # not a blank canvas
    blue = np.array(part_colour(1))[::-1] * 255  # BGR of the door colour appears (points or axis)
    assert np.any(np.all(np.abs(image.astype(float) - blue) < 20, axis=2))


def test_exports_need_clouds(articulation, tmp_path):
    articulation.start_cloud = None
    with pytest.raises(ValueError, match="--ply"):
        write_labelled_clouds(articulation, tmp_path)
    with pytest.raises(ValueError, match="--report"):
        write_report(articulation, tmp_path / "r.png")


def test_cli_run_writes_extras_beside_articulation_json(tiny_scene, tmp_path, capsys):
    from sparseart.cli import main

    out = tmp_path / "out"
    assert main(["run", str(tiny_scene), "--out", str(out), "--urdf", "--ply", "--report"]) == 0
    for name in ("articulation.json", "object.urdf", "meshes/base.obj", "start_parts.ply", "end_parts.ply",
                 "report.png"):
        assert (out / name).is_file(), name
    assert "report.png" in capsys.readouterr().out
    assert not [p for p in out.rglob("*.tmp")]
    assert '<link name="base">' in (out / "object.urdf").read_text()


def test_sim_exports_without_the_sim_extra_fail_in_one_line_before_any_work(tiny_scene, tmp_path, capsys,
                                                                            monkeypatch):
    import importlib.util

    from sparseart.cli import main

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *rest: None if name == "coacd" else real(name, *rest))
    out = tmp_path / "out"
    assert main(["run", str(tiny_scene), "--out", str(out), "--mjcf"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--mjcf needs coacd" in err and "sparseart[sim]" in err
    assert not out.exists()
