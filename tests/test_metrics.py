"""Hand-computed cases for sparseart.bench.metrics (design section 4)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from sparseart.bench.metrics import (
    axis_angle_error_deg,
    axis_position_error,
    chamfer_cost_matrix,
    chamfer_distance,
    joint_errors,
    match_parts,
    point_to_line_distance,
    prismatic_state_error,
    revolute_state_error_deg,
    rotation_from_axis_angle,
    sample_mesh_points,
    summarise,
    unmatched_joint_errors,
)

X, Y, Z = np.eye(3)
TOL_DEG = 1e-5  # arccos near +-1 loses ~1e-6 degrees to round-off


def rev(axis, origin, angle):
    return {"type": "revolute", "axis": list(axis), "origin": list(origin), "angle": angle}


def pri(axis, origin, distance):
    return {"type": "prismatic", "axis": list(axis), "origin": list(origin), "distance": distance}


# ---------------------------------------------------------------- axis angle


def test_axis_angle_basic():
    assert axis_angle_error_deg(Z, Z) == pytest.approx(0.0, abs=TOL_DEG)
    assert axis_angle_error_deg(Z, -Z) == pytest.approx(0.0, abs=TOL_DEG)  # folded
    assert axis_angle_error_deg(X, Z) == pytest.approx(90.0)
    assert axis_angle_error_deg([1, 1, 0], X) == pytest.approx(45.0)
    assert axis_angle_error_deg([-1, -1, 0], X) == pytest.approx(45.0)
    assert axis_angle_error_deg([0, 0, 5.0], [0, 0, 0.1]) == pytest.approx(0.0, abs=TOL_DEG)  # unnormalised


def test_axis_angle_never_nan_for_nearly_identical():
    a = np.array([0.1, 0.2, 0.3])
    for scale in (1.0, 1 + 1e-15, 3.0, 1e-8):
        v = axis_angle_error_deg(a * scale, a)
        assert math.isfinite(v) and 0.0 <= v <= 90.0


def test_zero_axis_raises():
    with pytest.raises(ValueError):
        axis_angle_error_deg([0, 0, 0], Z)
    with pytest.raises(ValueError):
        axis_position_error(Z, [0, 0, 0], [0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError):
        rotation_from_axis_angle([0, 0, 0], 1.0)


# ---------------------------------------------------------------- axis position


def test_parallel_axes_far_apart():
    # both along z, through (0,0,0) and (3,4,7): separation 5 (z offset is along the line)
    assert axis_position_error(Z, [0, 0, 0], Z, [3, 4, 7]) == pytest.approx(5.0)


def test_antiparallel_axes():
    assert axis_angle_error_deg(Z, -Z) == pytest.approx(0.0, abs=TOL_DEG)
    assert axis_position_error(-Z, [0, 0, 0], Z, [3, 4, -2]) == pytest.approx(5.0)
    # unnormalised, nearly parallel (|n| < 1e-6) still uses the fallback
    assert axis_position_error([0, 1e-9, 2.0], [0, 0, 0], Z, [0, 2, 0]) == pytest.approx(2.0)


def test_perpendicular_skew_lines():
    # x-axis through origin vs y-direction line through (0, 0, 2): distance 2
    assert axis_position_error(X, [0, 0, 0], Y, [0, 0, 2]) == pytest.approx(2.0)
    # moving the points along their lines changes nothing
    assert axis_position_error(X, [5, 0, 0], Y, [0, -7, 2]) == pytest.approx(2.0)
    # skew at 45 degrees, offset 1.5 along the common normal z
    assert axis_position_error([1, 1, 0], [1, 2, 0], X, [0, 0, 1.5]) == pytest.approx(1.5)
    d = axis_position_error([1, 1, 0], [0, 0, 0], X, [4, 0, 1.5])
    assert d == pytest.approx(1.5)


def test_intersecting_lines():
    assert axis_position_error(X, [1, 1, 1], Y, [1, 1, 1]) == pytest.approx(0.0, abs=1e-12)
    assert axis_position_error(X, [4, 1, 1], [0, 1, 1], [1, 3, 3]) == pytest.approx(0.0, abs=1e-12)


def test_point_to_line():
    assert point_to_line_distance([3, 4, 9], Z, [0, 0, 0]) == pytest.approx(5.0)


# ---------------------------------------------------------------- rotations and state


def test_rotation_from_axis_angle():
    r = rotation_from_axis_angle([0, 0, 2.0], math.pi / 2)
    assert r.dtype == np.float64 and r.shape == (3, 3)
    np.testing.assert_allclose(r @ X, Y, atol=1e-12)  # right-handed


def test_revolute_state_180():
    assert revolute_state_error_deg(Z, math.pi, Z, 0.0) == pytest.approx(180.0)
    assert revolute_state_error_deg(X, 0.0, Z, math.pi) == pytest.approx(180.0)


def test_revolute_state_wraps():
    e = revolute_state_error_deg(Z, math.radians(179), Z, math.radians(-179))
    assert e == pytest.approx(2.0, abs=1e-6)


def test_revolute_state_flipped_axis_negated_angle():
    assert revolute_state_error_deg(-Z, -0.7, Z, 0.7) == pytest.approx(0.0, abs=TOL_DEG)
    assert revolute_state_error_deg(Z, 0.5, Z, 0.2) == pytest.approx(math.degrees(0.3))


def test_revolute_state_includes_axis_error():
    # same angle, axes 90 degrees apart: geodesic of R_x(90) R_z(90)^T is 120 degrees
    assert revolute_state_error_deg(X, math.pi / 2, Z, math.pi / 2) == pytest.approx(120.0)


def test_prismatic_state():
    assert prismatic_state_error(-Z, -0.3, Z, 0.3) == pytest.approx(0.0, abs=1e-12)
    assert prismatic_state_error(Z, 0.5, Z, 0.2) == pytest.approx(0.3)
    assert prismatic_state_error(X, 3.0, Y, 4.0) == pytest.approx(5.0)


# ---------------------------------------------------------------- joint_errors


def test_identical_joints_all_zero():
    e = joint_errors(rev(Z, [1, 2, 3], 0.8), rev(Z, [1, 2, 3], 0.8))
    assert e["type_correct"] is True
    assert e["axis_deg"] == pytest.approx(0.0, abs=TOL_DEG)
    assert e["position"] == pytest.approx(0.0, abs=1e-12)
    assert e["state"] == pytest.approx(0.0, abs=TOL_DEG)
    p = joint_errors(pri(X, [0, 0, 0], 0.2), pri(X, [5, 5, 5], 0.2))
    assert p["type_correct"] is True
    assert p["axis_deg"] == pytest.approx(0.0, abs=TOL_DEG)
    assert p["position"] is None
    assert p["state"] == pytest.approx(0.0, abs=1e-12)


def test_flipped_joint_same_motion():
    e = joint_errors(rev(-Z, [0, 0, 4], -1.1), rev(Z, [0, 0, 0], 1.1))
    assert e["axis_deg"] == pytest.approx(0.0, abs=TOL_DEG)
    assert e["position"] == pytest.approx(0.0, abs=1e-12)
    assert e["state"] == pytest.approx(0.0, abs=TOL_DEG)
    p = joint_errors(pri(-Y, [0, 0, 0], -0.4), pri(Y, [0, 0, 0], 0.4))
    assert p["state"] == pytest.approx(0.0, abs=1e-12)


def test_wrong_type_revolute_gt():
    gt = rev(Z, [0, 0, 0], math.radians(40))
    e = joint_errors(pri(X, [3, 4, 10], 0.3), gt)
    assert e["type_correct"] is False
    assert e["axis_deg"] == pytest.approx(90.0)
    assert e["position"] == pytest.approx(5.0)  # gt line to the predicted origin point
    assert e["state"] == pytest.approx(40.0)  # as if predicted angle 0
    assert e["gt_type"] == "revolute" and e["pred_type"] == "prismatic"


def test_state_along_reads_the_angle_or_slide_alone():
    """The stated angle / slide sigma is about the state along the joint's own axis; the whole
    motion's error also carries the axis error. An axis given the other way round negates the
    state; the wrong type has no state along an axis."""
    tilted = np.array([np.sin(np.radians(3.0)), 0.0, np.cos(np.radians(3.0))])
    e = joint_errors(rev(tilted, [0, 0, 0], math.radians(56.0)), rev(Z, [0, 0, 0], math.radians(55.0)))
    assert e["state_along"] == pytest.approx(1.0) and e["state"] > 2.5
    flipped = joint_errors(rev(-Z, [0, 0, 0], math.radians(-57.0)), rev(Z, [0, 0, 0], math.radians(55.0)))
    assert flipped["state_along"] == pytest.approx(2.0)
    slide = joint_errors(pri(-tilted, [0, 0, 0], -0.31), pri(Z, [0, 0, 0], 0.3))
    assert slide["state_along"] == pytest.approx(0.01) and slide["state"] > 0.016
    assert joint_errors(pri(X, [0, 0, 0], 0.3), rev(Z, [0, 0, 0], 1.0))["state_along"] is None
    assert unmatched_joint_errors(pri(Z, [0, 0, 0], 0.3))["state_along"] is None


def test_wrong_type_prismatic_gt():
    e = joint_errors(rev(Z, [0, 0, 0], 1.0), pri(Z, [0, 0, 0], -0.25))
    assert e["type_correct"] is False
    assert e["axis_deg"] == pytest.approx(0.0, abs=TOL_DEG)
    assert e["position"] is None
    assert e["state"] == pytest.approx(0.25)  # |t_g|, as if predicted distance 0


def test_joint_errors_accepts_objects():
    class J:
        type = "revolute"
        axis = np.array([0.0, 0.0, 1.0])
        origin = np.zeros(3)
        angle = 0.5
        distance = None

    e = joint_errors(J(), rev(Z, [1, 0, 0], 0.5))
    assert e["position"] == pytest.approx(1.0)


def test_joint_errors_bad_type():
    with pytest.raises(ValueError):
        joint_errors({"type": "fixed", "axis": Z, "origin": Z}, rev(Z, [0, 0, 0], 0.1))


# ---------------------------------------------------------------- chamfer and sampling


def test_chamfer_identical_is_zero():
    pts = np.random.default_rng(0).random((200, 3))
    assert chamfer_distance(pts, pts) == 0.0
    assert chamfer_distance(pts, pts[::-1]) == 0.0


def test_chamfer_shifted_single_points():
    d = 0.3
    assert chamfer_distance([[0, 0, 0]], [[0, d, 0]]) == pytest.approx(2 * d * d)


def test_chamfer_asymmetric_sets():
    # a = {0}, b = {0, 2} along x: a->b mean 0, b->a mean (0 + 4)/2 = 2
    assert chamfer_distance([[0, 0, 0]], [[0, 0, 0], [2, 0, 0]]) == pytest.approx(2.0)
    with pytest.raises(ValueError):
        chamfer_distance(np.zeros((0, 3)), [[0, 0, 0]])


def test_sample_mesh_points_area_weighted():
    # unit square z=0 (area 1, two triangles) and a tiny triangle of area 0.005 far away at z=5
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                  [0, 0, 5], [0.1, 0, 5], [0, 0.1, 5]], dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6]])
    p = sample_mesh_points(v, f, n=10000, seed=1)
    assert p.shape == (10000, 3) and p.dtype == np.float64
    frac_far = np.mean(p[:, 2] > 1)
    assert frac_far == pytest.approx(0.005 / 1.005, abs=0.004)
    flat = p[p[:, 2] < 1]
    assert flat.min() >= -1e-12 and flat[:, :2].max() <= 1 + 1e-12
    assert abs(flat[:, 0].mean() - 0.5) < 0.02 and abs(flat[:, 1].mean() - 0.5) < 0.02
    np.testing.assert_array_equal(p, sample_mesh_points(v, f, n=10000, seed=1))


# ---------------------------------------------------------------- matching


def test_match_parts_permuted_diagonal():
    perm = [2, 0, 3, 1]
    cost = np.ones((4, 4))
    for p, g in enumerate(perm):
        cost[p, g] = 0.0
    matches, unmatched = match_parts(cost)
    assert matches == [(p, g) for p, g in enumerate(perm)]
    assert unmatched == []


def test_match_parts_rectangular():
    cost = np.array([[5.0, 0.1, 3.0]])  # one prediction, three gt parts
    matches, unmatched = match_parts(cost)
    assert matches == [(0, 1)] and unmatched == [0, 2]
    matches, unmatched = match_parts(cost.T)  # three predictions, one gt part
    assert matches == [(1, 0)] and unmatched == []
    matches, unmatched = match_parts(np.array([[np.inf, 1.0], [np.inf, 2.0]]))
    assert matches == [(0, 1)] and unmatched == [0]


def test_match_parts_on_chamfer():
    rng = np.random.default_rng(3)
    gt = [rng.random((50, 3)) + 3 * k for k in range(3)]
    pred = [gt[2] + 0.01, gt[0] - 0.01, gt[1]]
    matches, unmatched = match_parts(chamfer_cost_matrix(pred, gt))
    assert matches == [(0, 2), (1, 0), (2, 1)] and unmatched == []


# ---------------------------------------------------------------- summary


def test_summarise():
    errors = [
        joint_errors(rev(Z, [0, 0, 0], 0.5), rev(Z, [0, 0, 0], 0.5)),  # perfect
        joint_errors(rev([1, 0, 1], [0, 1, 0], 0.5), rev(Z, [0, 0, 0], 0.5)),  # 45 deg, pos 1
        joint_errors(pri(Z, [0, 0, 0], 0.1), pri(Z, [0, 0, 0], 0.4)),  # state 0.3
        unmatched_joint_errors(rev(Z, [0, 0, 0], 1.0), position_max=2.0),
    ]
    s = summarise(errors)
    assert s["count"] == 4 and s["n_revolute"] == 3 and s["n_prismatic"] == 1
    assert s["n_unmatched"] == 1
    assert s["type_accuracy"] == pytest.approx(0.75)
    assert s["success_rate"] == pytest.approx(0.5)
    assert s["axis_deg_mean"] == pytest.approx((0 + 45 + 0 + 90) / 4, abs=1e-5)
    assert s["axis_deg_median"] == pytest.approx(22.5, abs=1e-5)
    assert s["position_mean"] == pytest.approx(1.0)  # (0 + 1 + 2) / 3
    assert s["position_median"] == pytest.approx(1.0)
    assert s["state_revolute_deg_median"] == pytest.approx(errors[1]["state"])
    assert s["state_revolute_deg_mean"] == pytest.approx((0 + errors[1]["state"] + 180) / 3, abs=1e-5)
    assert s["state_prismatic_mean"] == pytest.approx(0.3)
    for v in s.values():
        assert not (isinstance(v, float) and math.isnan(v))


def test_summarise_empty():
    s = summarise([])
    assert s["count"] == 0
    assert s["axis_deg_mean"] is None and s["type_accuracy"] is None


def test_summarise_sigma_coverage_counts_successful_joints_with_a_stated_sigma():
    rows = [{"axis_deg": 0.5, "axis_sigma_deg": 1.0, "type_correct": True, "position": 0.0, "state": 0.0},
            {"axis_deg": 2.0, "axis_sigma_deg": 1.0, "type_correct": True, "position": 0.0, "state": 0.0},
            {"axis_deg": 3.0, "axis_sigma_deg": 4.0, "type_correct": True, "position": 0.0, "state": 0.0},
            {"axis_deg": 40.0, "axis_sigma_deg": 50.0, "type_correct": True, "position": 0.0, "state": 0.0},
            {"axis_deg": 1.0, "axis_sigma_deg": None, "type_correct": True, "position": 0.0, "state": 0.0}]
    out = summarise(rows)
    assert out["sigma_count"] == 3 and out["sigma_coverage"] == pytest.approx(2 / 3)   # failures and no-sigma left out
    assert summarise(rows[3:])["sigma_coverage"] is None


def test_full_success_needs_the_state_too():
    """The axis alone passes a door turned the wrong way about its hinge line (measured on robot
    renders: state errors of 112-180 deg at axis errors of 0.2-5 deg) and a slide of the wrong
    length; a full success also turns to within 10 deg or slides to within 10 % of the truth."""
    door = joint_errors(rev(Z, [0, 0, 0], 0.6), rev(Z, [0, 0, 0], 0.64))         # 2.3 deg short
    wrong_way = joint_errors(rev(Z, [0, 0, 0], -1.35), rev(Z, [0, 0, 0], 0.64))  # turned back
    drawer = joint_errors(pri(X, [0, 0, 0], 0.19), pri(X, [0, 0, 0], 0.2))       # 5 % short
    short = joint_errors(pri(X, [0, 0, 0], 0.15), pri(X, [0, 0, 0], 0.2))        # 25 % short
    assert door["gt_state"] == pytest.approx(np.degrees(0.64)) and drawer["gt_state"] == pytest.approx(0.2)
    assert wrong_way["axis_deg"] < 1e-6 and summarise([wrong_way])["success_rate"] == 1.0
    out = summarise([door, wrong_way, drawer, short])
    assert out["success_rate"] == 1.0 and out["full_success_rate"] == pytest.approx(0.5)
    assert summarise([unmatched_joint_errors(rev(Z, [0, 0, 0], 0.5))])["full_success_rate"] == 0.0
    assert summarise([{k: v for k, v in door.items() if k != "gt_state"}])["full_success_rate"] is None


def test_summarise_position_and_state_coverage_read_their_own_sigma():
    """The hinge line's position and the angle or slide have their own stated sigma; each is
    judged over the successful joints of the right type that state one."""
    def row(position, origin_sigma, state, state_sigma, axis=1.0, right_type=True):
        return {"axis_deg": axis, "axis_sigma_deg": 2.0, "type_correct": right_type, "gt_type": "revolute",
                "position": position, "origin_sigma": origin_sigma, "state": 50.0, "state_along": state,
                "state_sigma": state_sigma}

    rows = [row(0.01, 0.02, 1.0, 2.0), row(0.03, 0.02, 3.0, 2.0), row(0.01, 0.02, 3.0, 2.0),
            row(0.01, None, 1.0, None),                         # no sigma stated: left out
            row(0.01, 0.02, 1.0, 2.0, axis=40.0),               # a failure: left out
            row(0.01, 0.02, 1.0, 2.0, right_type=False)]        # the wrong type: left out
    out = summarise(rows)
    assert out["position_sigma_coverage"] == pytest.approx(2 / 3)
    assert out["state_sigma_coverage"] == pytest.approx(1 / 3)
    assert summarise(rows[3:])["position_sigma_coverage"] is None
