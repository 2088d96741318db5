"""Gaussians, mobility bookkeeping, joint motion in torch, compositions and the 3DGS PLY."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from sparseart.geometry.transforms import transform_from_prismatic, transform_from_revolute  # noqa: E402
from sparseart.refine.compose import components, novel_state_components  # noqa: E402
from sparseart.refine.gaussians import gaussians_from_points, initial_mobility  # noqa: E402
from sparseart.refine.joint import JointParams, matrix_to_quaternion, move_gaussians  # noqa: E402
from sparseart.refine.ply import read_gaussians_ply, write_gaussians_ply  # noqa: E402
from sparseart.refine.render import quaternion_to_matrix  # noqa: E402
from sparseart.types import SceneError  # noqa: E402


def _set(state="start", n=50, seed=0):
    rng = np.random.default_rng(seed)
    parts = rng.choice([-1, 0, 1], n)
    return gaussians_from_points(state, rng.normal(size=(n, 3)), rng.uniform(size=(n, 3)),
                                 initial_mobility(parts, 1), dtype=torch.float64), parts


def test_static_and_mobile_opacities_sum_to_the_opacity():
    gaussians, parts = _set()
    gaussians.mobility_logits = torch.randn(len(gaussians), dtype=torch.float64) * 4
    total = gaussians.static_opacities() + gaussians.mobile_opacities()
    torch.testing.assert_close(total, gaussians.opacities(), atol=1e-15, rtol=0)
    assert (gaussians.mobility() >= 0).all() and (gaussians.mobility() <= 1).all()


def test_initial_mobility_follows_the_labels():
    gaussians, parts = _set()
    m = gaussians.mobility().numpy()
    assert np.all(m[parts == 0] < 0.1) and np.all(m[parts == 1] > 0.9)
    np.testing.assert_allclose(m[parts == -1], 0.5, atol=1e-9)
    np.testing.assert_allclose(gaussians.colors().numpy(), np.clip(gaussians.to_numpy()["colors"], 0, 1), atol=1e-12)


def test_gaussians_from_points_rejects_bad_input():
    with pytest.raises(ValueError, match="non-empty"):
        gaussians_from_points("start", np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    with pytest.raises(ValueError, match="NaN"):
        gaussians_from_points("start", np.full((5, 3), np.nan), np.zeros((5, 3)), np.zeros(5))


@pytest.mark.parametrize("angle", [0.0, 0.7, np.pi - 1e-9, -2.5])
def test_revolute_motion_matches_the_fitter_semantics(angle):
    axis, pivot = np.array([0.3, -0.2, 0.9]), np.array([0.1, 0.5, -0.3])
    joint = JointParams.from_values("revolute", axis, pivot, angle, dtype=torch.float64)
    rotation, translation = joint.motion()
    expected = transform_from_revolute(axis, pivot, angle)
    np.testing.assert_allclose(rotation.numpy(), expected[:3, :3], atol=1e-12)
    np.testing.assert_allclose(translation.numpy(), expected[:3, 3], atol=1e-12)
    back_r, back_t = joint.motion(inverse=True)
    np.testing.assert_allclose((back_r @ rotation).numpy(), np.eye(3), atol=1e-12)
    np.testing.assert_allclose((back_r @ translation + back_t).numpy(), 0, atol=1e-12)
    # orientation moves with the centre: the quaternion of R equals R, for every branch
    np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(rotation)[None])[0].numpy(),
                               rotation.numpy(), atol=1e-9)


def test_prismatic_motion_and_moved_gaussians():
    joint = JointParams.from_values("prismatic", [0, 0, 2.0], [0, 0, 0], 0.4, dtype=torch.float64)
    rotation, translation = joint.motion(0.5)
    np.testing.assert_allclose(translation.numpy(), transform_from_prismatic([0, 0, 1], 0.2)[:3, 3])
    revolute = JointParams.from_values("revolute", [0, 0, 1], [1.0, 0, 0], np.pi / 2, dtype=torch.float64)
    r, t = revolute.motion()
    quats = torch.tensor([[1.0, 0, 0, 0], [0.5, 0.5, 0.5, 0.5]], dtype=torch.float64)
    means, moved = move_gaussians(torch.zeros(2, 3, dtype=torch.float64), quats, r, t)
    np.testing.assert_allclose(means.numpy(), [[1.0, -1.0, 0.0]] * 2, atol=1e-12)
    np.testing.assert_allclose(quaternion_to_matrix(moved).numpy(), (r @ quaternion_to_matrix(quats)).numpy(),
                               atol=1e-12)


def test_compositions_draw_the_right_components():
    start, _ = _set("start", 30, 1)
    end, _ = _set("end", 20, 2)
    sets = {"start": start, "end": end}
    joint = JointParams.from_values("prismatic", [1.0, 0, 0], [0, 0, 0], 0.5, dtype=torch.float64)
    own = components("start", sets, joint, "own")
    cross_static = components("start", sets, joint, "cross_static")
    cross_mobile = components("start", sets, joint, "cross_mobile")
    assert [len(c[0]) for c in (own, cross_static, cross_mobile)] == [30, 50, 70]
    torch.testing.assert_close(cross_static[3][30:], end.static_opacities())
    torch.testing.assert_close(cross_mobile[3][50:], end.mobile_opacities())
    torch.testing.assert_close(cross_mobile[0][50:], end.means - torch.tensor([0.5, 0, 0], dtype=torch.float64))
    novel = novel_state_components(sets, joint, 0.0)
    # at fraction 0 the start components sit where they are; end's mobile ones moved back fully
    torch.testing.assert_close(novel[0][30:60], start.means)
    torch.testing.assert_close(novel[0][80:], end.means - torch.tensor([0.5, 0, 0], dtype=torch.float64))
    with pytest.raises(ValueError, match="composition mode"):
        components("start", sets, joint, "bogus")


def test_ply_round_trip_and_header(tmp_path):
    gaussians, _ = _set()
    arrays = gaussians.to_numpy()
    path = write_gaussians_ply(tmp_path / "splats.ply", arrays)
    header = path.read_bytes()[:600].decode("ascii", errors="replace")
    for name in ("x", "nx", "f_dc_0", "opacity", "scale_2", "rot_3", "mobility"):
        assert f"property float {name}\n" in header
    back = read_gaussians_ply(path)
    for key in ("means", "f_dc", "opacity_logits", "log_scales", "quats", "mobility"):
        np.testing.assert_allclose(back[key], arrays[key], rtol=1e-6, atol=1e-6)
    assert not list(tmp_path.glob(".*tmp"))


def test_ply_errors_name_the_file(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply")
    with pytest.raises(SceneError, match="bad.ply"):
        read_gaussians_ply(bad)
    gaussians, _ = _set()
    arrays = gaussians.to_numpy()
    arrays["means"][0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        write_gaussians_ply(tmp_path / "nan.ply", arrays)
    assert not (tmp_path / "nan.ply").exists()
    good = write_gaussians_ply(tmp_path / "good.ply", gaussians.to_numpy())
    (tmp_path / "cut.ply").write_bytes(good.read_bytes()[:-10])
    with pytest.raises(SceneError, match="truncated"):
        read_gaussians_ply(tmp_path / "cut.ply")
