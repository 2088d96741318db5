"""Tests of the rendered-dataset generators (sparseart.datasets). Fast: a few seconds in total."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

o3d = pytest.importorskip("open3d")

from sparseart.datasets.meshes import RenderMesh, load_articulated_object, read_obj  # noqa: E402
from sparseart.datasets.partnet import (intrinsics, look_at, render_articulated_scene,  # noqa: E402
                                        render_partnet_scene, sample_joint_states)
from sparseart.datasets.raycast import PreparedScene, render_view  # noqa: E402
from sparseart.datasets.synth import box_mesh, build_cabinet, render_synth_scene  # noqa: E402
from sparseart.datasets.urdf import axis_angle_matrix, parse_urdf  # noqa: E402
from sparseart.types import SceneError  # noqa: E402

PARTNET = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "partnet"
needs_partnet = pytest.mark.skipif(not (PARTNET / "storage_40147" / "mobility.urdf").is_file(),
                                   reason=f"PartNet-Mobility objects not found at {PARTNET}")


def _unproject(depth: np.ndarray, K: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    r, c = np.nonzero(depth > 0)
    z = depth[r, c]
    pc = np.stack([(c - K[0, 2]) / K[0, 0] * z, (r - K[1, 2]) / K[1, 1] * z, z], axis=1)
    return pc @ c2w[:3, :3].T + c2w[:3, 3]


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Float64 closest points on triangles (a, b, c) to points p, all (N, 3) (Ericson, RTCD 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    dot = lambda x, y: np.einsum("ij,ij->i", x, y)  # noqa: E731
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp, cp = p - b, p - c
    d3, d4, d5, d6 = dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = va + vb + vc
    with np.errstate(divide="ignore", invalid="ignore"):
        v, w = vb / denom, vc / denom
        out = a + v[:, None] * ab + w[:, None] * ac
        cases = [
            (d1 <= 0) & (d2 <= 0), (d3 >= 0) & (d4 <= d3), (d6 >= 0) & (d5 <= d6),
            (vc <= 0) & (d1 >= 0) & (d3 <= 0), (vb <= 0) & (d2 >= 0) & (d6 <= 0),
            (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
        ]
        vals = [a, b, c, a + (d1 / (d1 - d3))[:, None] * ab, a + (d2 / (d2 - d6))[:, None] * ac,
                b + ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[:, None] * (c - b)]
    for m, val in reversed(list(zip(cases, vals))):
        out = np.where(m[:, None], val, out)
    return out


def _distance(meshes: list[RenderMesh], pts: np.ndarray) -> np.ndarray:
    """Upper bound of the distance to the mesh, float64: open3d picks the nearest triangle
    (float32), the distance to that triangle is then computed exactly in float64."""
    m = RenderMesh.concat(meshes)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(m.vertices.astype(np.float32)),
                        o3d.core.Tensor(m.triangles.astype(np.uint32)))
    tri = scene.compute_closest_points(o3d.core.Tensor(pts.astype(np.float32)))["primitive_ids"]
    v = m.vertices[m.triangles[tri.numpy().astype(np.int64)]]
    q = _closest_on_triangles(pts, v[:, 0], v[:, 1], v[:, 2])
    return np.linalg.norm(q - pts, axis=1)


def _sample_surface(mesh: RenderMesh, n: int, rng: np.random.Generator,
                    same_on: RenderMesh | None = None):
    """n area-uniform surface points (n, 3); with ``same_on`` (a mesh with the same triangles in
    another pose) also the points with the same barycentric coordinates on it."""
    v = mesh.vertices[mesh.triangles]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    idx = rng.choice(len(area), size=n, p=area / area.sum())
    a, b = rng.random((2, n))
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]

    def at(m: RenderMesh) -> np.ndarray:
        t = m.vertices[m.triangles][idx]
        return t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])

    return at(mesh) if same_on is None else (at(mesh), at(same_on))


def _apply_gt(j: dict, x: np.ndarray) -> np.ndarray:
    axis, origin = np.asarray(j["axis"]), np.asarray(j["origin"])
    if j["type"] == "revolute":
        return origin + (x - origin) @ axis_angle_matrix(axis, j["angle"]).T
    return x + j["distance"] * axis


def test_box_depth_is_analytic():
    box = box_mesh((-0.5, -0.5, 2.0), (0.5, 0.5, 3.0), (0.2, 0.6, 0.9))  # front face at z = 2
    K = intrinsics(64, 48)
    rgb, depth, label = render_view([(box, 7)], K, np.eye(4), 64, 48)
    assert rgb.dtype == np.uint8 and rgb.shape == (48, 64, 3)
    assert depth.dtype == np.float64 and label.dtype == np.uint16
    hit = depth > 0
    assert hit[24, 32] and hit.sum() > 100 and not hit[0, 0]
    np.testing.assert_allclose(depth[hit], 2.0, atol=1e-12)
    assert set(np.unique(label)) == {0, 7}
    assert np.array_equal(label > 0, hit)
    # Tilted camera at a known distance along its optical axis.
    c2w = look_at(np.array([0.0, -3.0, 2.5]), np.array([0.0, 0.0, 2.5]))
    _, d2, _ = render_view([(box, 1)], K, c2w, 64, 48)
    assert abs(d2[23, 31] - 2.5) < 0.02  # face y = -0.5 seen from y = -3 (pixel ~centre)


def test_look_at_is_right_handed_opencv():
    T = look_at(np.array([1.0, 2.0, 3.0]), np.zeros(3))
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(R[:, 2], -np.array([1, 2, 3]) / np.sqrt(14), atol=1e-12)
    assert R[2, 1] < 0  # image y (down) points down in the Z-up world


def test_unprojected_depth_lies_on_mesh():
    obj = build_cabinet()
    q = {"door_hinge": 0.7, "drawer_slide": 0.2}
    parts = obj.posed_parts(q)
    prep = PreparedScene(parts)
    K = intrinsics(160, 120)
    c2w = look_at(np.array([-1.5, -0.8, 1.3]), np.array([0.0, 0.0, 0.4]))
    rgb, depth, label = render_view(prep, K, c2w, 160, 120)
    pts = _unproject(depth, K, c2w)
    assert len(pts) > 2000
    scale = 1.12
    assert _distance([m for m, _ in parts], pts).max() < 1e-6 * scale
    assert set(np.unique(label)) == {0, 1, 2, 3}
    assert rgb[label > 0].std() > 10  # shading/colour contrast


def _grid_plane(n: int, z: float, color: tuple[float, float, float]) -> RenderMesh:
    """A unit square at height z split into 2 n^2 triangles of one colour."""
    u = np.linspace(-0.5, 0.5, n + 1)
    x, y = np.meshgrid(u, u)
    vertices = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)
    k = np.arange(n * (n + 1)).reshape(n, n + 1)[:, :n].ravel()
    triangles = np.concatenate([np.stack([k, k + 1, k + n + 2], 1), np.stack([k, k + n + 2, k + n + 1], 1)])
    return RenderMesh(vertices, triangles, np.tile(color, (len(triangles), 1)))


def test_coplanar_duplicates_keep_their_colour_when_another_part_moves():
    # a red and a blue copy of one surface (as PartNet meshes hold); a small box elsewhere moves
    # between two renders. The unmoved surface must look the same in both, red (the first listed)
    red = _grid_plane(12, 0.0, (1.0, 0.0, 0.0))
    blue = _grid_plane(17, 0.0, (0.0, 0.0, 1.0))
    box = box_mesh((-0.1, -0.1, -0.1), (0.1, 0.1, 0.1), (0.2, 0.8, 0.2))
    K = intrinsics(64, 48)
    c2w = look_at(np.array([0.3, -1.2, 1.4]), np.zeros(3))
    images = []
    for shift in (0.0, 0.35, 0.7):
        moved = box.transformed(np.array([[1, 0, 0, 0.8 + shift], [0, 1, 0, 0],
                                                               [0, 0, 1, 0.3], [0, 0, 0, 1.0]]))
        rgb, depth, label = render_view([(red, 1), (blue, 1), (moved, 2)], K, c2w, 64, 48)
        images.append(rgb[label == 1].astype(int))
    assert len(images[0]) > 500
    for rgb in images:
        assert np.all(rgb[:, 0] > 0) and np.all(rgb[:, 2] == 0)


def _check_gt_semantics(obj, gt: dict, q0: dict, q1: dict) -> None:
    rng = np.random.default_rng(0)
    p0 = dict((lab, m) for m, lab in obj.posed_parts(q0))
    p1 = dict((lab, m) for m, lab in obj.posed_parts(q1))
    assert gt["static_mask_id"] == 1
    np.testing.assert_allclose(p0[1].vertices, p1[1].vertices)
    for j in gt["joints"]:
        assert abs(np.linalg.norm(j["axis"]) - 1) < 1e-12
        m0, m1 = p0[j["mask_id"]], p1[j["mask_id"]]
        x0, x1_true = _sample_surface(m0, 2000, rng, same_on=m1)
        x1 = _apply_gt(j, x0)
        # Exact: the same surface point of the part, posed by forward kinematics at the end state.
        assert np.abs(x1 - x1_true).max() < 1e-9 * gt["scale"], j["name"]
        # Independent: the moved points lie on the end-state mesh (open3d nearest triangle is
        # float32, so a handful of points near slivers may pick a wrong triangle).
        d = _distance([m1], x1)
        assert np.quantile(d, 0.99) < 1e-6 * gt["scale"], (j["name"], np.quantile(d, 0.99))
        moved = np.linalg.norm(x1 - x0, axis=1).max()
        assert moved > 0.02 * gt["scale"], j["name"]


def test_synth_scene_layout_and_gt(tmp_path: Path):
    gt = render_synth_scene(tmp_path / "s", views=2, seed=3, width=96, height=72, depth_noise=0.0)
    root = tmp_path / "s"
    for state in ("start", "end"):
        for sub in ("rgb", "depth", "mask"):
            for i in range(2):
                assert (root / state / sub / f"{i:03d}.png").is_file()
    cams = json.loads((root / "cameras.json").read_text())
    assert cams["convention"] == "opencv" and cams["depth_scale"] == 1000.0
    assert len(cams["start"]) == 2 and "cam_to_world" in cams["end"][1]
    assert json.loads((root / "gt.json").read_text())["schema"] == "sparseart/gt/1"
    d = cv2.imread(str(root / "start/depth/000.png"), cv2.IMREAD_UNCHANGED)
    assert d.dtype == np.uint16 and (d > 0).sum() > 500
    pts = _unproject(d / 1000.0, np.array(cams["start"][0]["K"]), np.array(cams["start"][0]["cam_to_world"]))
    parts = build_cabinet(3).posed_parts(gt["joint_states"]["start"])
    assert np.median(_distance([m for m, _ in parts], pts)) < 2e-3  # mm quantisation
    _check_gt_semantics(build_cabinet(3), gt, gt["joint_states"]["start"], gt["joint_states"]["end"])
    assert {j["type"] for j in gt["joints"]} == {"revolute", "prismatic"}


def test_unposed_scrambled_masks(tmp_path: Path):
    kw = dict(views=3, seed=5, width=80, height=60)
    plain = render_synth_scene(tmp_path / "a", **kw)
    gt = render_synth_scene(tmp_path / "b", posed=False, scramble_masks=True, **kw)
    cams = json.loads((tmp_path / "b" / "cameras.json").read_text())
    assert all("cam_to_world" not in e for s in ("start", "end") for e in cams[s])
    assert len(gt["cameras"]["start"]) == 3 and plain["joints"] == gt["joints"]
    seen = []
    for state in ("start", "end"):
        for i in range(3):
            m = cv2.imread(str(tmp_path / "b" / state / "mask" / f"{i:03d}.png"), cv2.IMREAD_UNCHANGED)
            ref = cv2.imread(str(tmp_path / "a" / state / "mask" / f"{i:03d}.png"), cv2.IMREAD_UNCHANGED)
            lut = {int(k): v for k, v in gt["mask_maps"][state][i].items()}
            back = np.vectorize(lambda x: lut.get(int(x), 0))(m)
            assert np.array_equal(back, ref)
            seen.append(tuple(sorted(lut.items())))
    assert len(set(seen)) == len(seen)


@needs_partnet
def test_urdf_fk_storage():
    model = parse_urdf(PARTNET / "storage_40147" / "mobility.urdf")
    assert [(j.name, j.type) for j in model.movable_joints] == [("joint_0", "revolute"),
                                                                ("joint_1", "prismatic")]
    world = model.fk({})
    R_root = world["link_2"][:3, :3]
    np.testing.assert_allclose(R_root @ [0, 1, 0], [0, 0, 1], atol=1e-5)  # mesh Y-up -> world Z-up
    # README convention: child point x -> p + R(axis, q)(x - p) in the mesh frame, p = joint xyz.
    j = model.joint("joint_0")
    vis = model.links["link_0"].visuals[0]
    x = read_obj(PARTNET / "storage_40147" / vis.filename).vertices[:50]
    q = 0.8
    w = model.fk({"joint_0": q})["link_0"] @ vis.transform
    got = x @ w[:3, :3].T + w[:3, 3]
    expect = (j.xyz + (x - j.xyz) @ axis_angle_matrix(j.axis, q).T) @ R_root.T
    np.testing.assert_allclose(got, expect, atol=1e-12)
    j1 = model.joint("joint_1")
    w1 = model.fk({"joint_1": 0.3})["link_1"]
    np.testing.assert_allclose(w1[:3, 3], R_root @ (0.3 * j1.axis), atol=1e-12)
    groups, movable = model.part_groups()
    assert groups == {"base": 0, "link_2": 0, "link_0": 1, "link_1": 2}


@needs_partnet
def test_partnet_multi_joint_gt(tmp_path: Path):
    obj = load_articulated_object(PARTNET / "storage_40147")
    q0, q1 = sample_joint_states(obj, np.random.default_rng(1))
    gt = render_articulated_scene(obj, tmp_path / "s", q0, q1, views=1, width=64, height=48)
    assert [j["mask_id"] for j in gt["joints"]] == [2, 3]
    assert all(q0[k] != q1[k] for k in q0)
    _check_gt_semantics(obj, gt, q0, q1)


@needs_partnet
def test_partnet_scene_public_entry(tmp_path: Path):
    gt = render_partnet_scene(PARTNET / "drawer_26525", tmp_path / "s", views=1, width=64,
                              height=48, depth_noise=0.01)
    assert gt["object"] == "drawer_26525" and gt["joints"][0]["type"] == "prismatic"
    assert gt["joints"][0]["distance"] > 0


def test_bad_object_folders(tmp_path: Path):
    with pytest.raises(SceneError, match="mobility.urdf"):
        load_articulated_object(tmp_path)
    (tmp_path / "mobility.urdf").write_text(
        '<robot name="x"><link name="base"/><link name="a"><visual><geometry>'
        '<mesh filename="textured_objs/missing.obj"/></geometry></visual></link>'
        '<joint name="j" type="fixed"><parent link="base"/><child link="a"/></joint></robot>')
    with pytest.raises(SceneError, match="missing.obj"):
        load_articulated_object(tmp_path)
    shutil.rmtree(tmp_path)
