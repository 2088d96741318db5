"""Stability of sparseart.joints.fit_joint at hard and degenerate inputs.

Every result must be finite and within tolerance, or carry a warning naming the ill-conditioning.
Synthetic parts come from tests/test_joints.py (partial views, independent samples, 1 mm noise).
"""
from __future__ import annotations

import functools
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_joints import (DOOR_AXIS, DOOR_ORIGIN, axis_error_deg, line_distance,  # noqa: E402
                         make_part, rotation_error_deg)

from sparseart.joints import fit_joint, transform_from_prismatic, transform_from_revolute  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402


def assert_finite(estimate):
    values = [estimate.axis, estimate.origin, estimate.transform, estimate.residual, estimate.confidence,
              estimate.slide, *estimate.uncertainty.values()]
    values.append(estimate.angle if estimate.type == "revolute" else estimate.distance)
    assert all(np.all(np.isfinite(v)) for v in values), estimate
    assert np.isclose(np.linalg.norm(estimate.axis), 1.0)
    assert 0.0 <= estimate.confidence <= 1.0


def warned(estimate, *words) -> bool:
    return any(word in w for w in estimate.warnings for word in words)


LSHAPE_AXIS = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
LSHAPE_ORIGIN = np.array([-0.35, 0.0, 0.1])


@pytest.mark.parametrize("degrees", [0.5, 5.0, 90.0, 170.0, 179.0])
def test_revolute_angles(degrees):
    """Near 180 deg a single fixed viewpoint sees disjoint surfaces in the two states (nothing to
    register), so those cases use full visibility; the angle map itself is tested at pi in
    test_joints.py."""
    angle = np.radians(degrees)
    start, end = make_part("lshape", transform_from_revolute(LSHAPE_AXIS, LSHAPE_ORIGIN, angle), seed=int(degrees),
                           partial=degrees < 150)
    estimate = fit_joint(start, end)
    assert_finite(estimate)
    assert estimate.type == "revolute", estimate.diagnostics["type_reason"]
    truth = Rotation.from_rotvec(LSHAPE_AXIS * angle).as_matrix()
    assert rotation_error_deg(estimate.transform[:3, :3], truth) < 1.0
    assert abs(estimate.angle - angle) < np.radians(1.0)
    axis_error = axis_error_deg(estimate.axis, LSHAPE_AXIS)
    origin_error = line_distance(estimate.origin, estimate.axis, LSHAPE_ORIGIN, LSHAPE_AXIS)
    if degrees < 1.0:
        assert warned(estimate, "poorly defined")
        assert axis_error < 3 * estimate.uncertainty["axis_deg"] + 1.0
    else:
        assert axis_error < max(1.0, 3 * estimate.uncertainty["axis_deg"])
        assert origin_error < max(0.01, 3 * estimate.uncertainty["origin"])


def test_tiny_prismatic_slide():
    """A slide of 0.2 % of the object size (2 mm at unit size, 1 mm noise)."""
    axis = np.array([0.0, 0.0, 1.0])
    start, end = make_part("drawer", transform_from_prismatic(axis, 0.002), seed=3)
    estimate = fit_joint(start, end, joint_type="prismatic")
    assert_finite(estimate)
    assert abs(estimate.distance - 0.002) < 1e-3
    assert axis_error_deg(estimate.axis, axis) < 5.0 or warned(estimate, "tiny", "poorly defined")
    auto = fit_joint(start, end)
    assert_finite(auto)
    assert auto.type == "prismatic" or warned(auto, "poorly defined", "ambiguous")


def test_far_pivot():
    """Pivot 10x the object size away: still a real rotation, flagged as ambiguous."""
    origin, angle = np.array([-10.0, 0.0, 0.0]), np.radians(10)
    start, end = make_part("lshape", transform_from_revolute(LSHAPE_AXIS, origin, angle), seed=4)
    estimate = fit_joint(start, end)
    assert_finite(estimate)
    assert estimate.type == "revolute"
    assert warned(estimate, "ambiguous")
    assert axis_error_deg(estimate.axis, LSHAPE_AXIS) < 1.0
    assert line_distance(estimate.origin, estimate.axis, origin, LSHAPE_AXIS) < 0.1


@functools.lru_cache(maxsize=1)
def _door_reference():
    start, end = make_part("door", transform_from_revolute(DOOR_AXIS, DOOR_ORIGIN, np.radians(35)), seed=5)
    return start, end, fit_joint(start, end, joint_type="revolute")


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_scale_invariance(scale):
    start, end, reference = _door_reference()
    scaled = fit_joint(start * scale, end * scale, joint_type="revolute")
    assert_finite(scaled)
    assert abs(scaled.angle - reference.angle) < 1e-6
    assert np.allclose(scaled.origin, reference.origin * scale, rtol=1e-5, atol=1e-6 * scale)
    assert np.isclose(scaled.residual, reference.residual * scale, rtol=1e-5)
    assert np.isclose(scaled.uncertainty["origin"], reference.uncertainty["origin"] * scale, rtol=1e-4)
    assert np.allclose(scaled.transform[:3, 3], reference.transform[:3, 3] * scale, rtol=1e-5, atol=1e-6 * scale)
    axis = np.array([0.0, 0.0, 1.0])
    start, end = make_part("drawer", transform_from_prismatic(axis, 0.3), seed=6)
    drawer = fit_joint(start * scale, end * scale)
    assert drawer.type == "prismatic" and abs(drawer.distance - 0.3 * scale) < 0.01 * scale


def test_planar_panel():
    angle = np.radians(30)
    start, end = make_part("panel", transform_from_revolute(DOOR_AXIS, DOOR_ORIGIN, angle), count=3000, seed=7)
    estimate = fit_joint(start, end, joint_type="revolute")
    assert_finite(estimate)
    assert warned(estimate, "planar")
    assert abs(estimate.angle - angle) < np.radians(1.0)
    assert axis_error_deg(estimate.axis, DOOR_AXIS) < 1.0


def test_collinear_rod():
    axis, origin, angle = np.array([0.0, 0.0, 1.0]), np.array([-0.5, 0.0, 0.0]), np.radians(30)
    start, end = make_part("rod", transform_from_revolute(axis, origin, angle), seed=8)
    estimate = fit_joint(start, end, joint_type="revolute")
    assert_finite(estimate)
    assert warned(estimate, "collinear")


def test_outliers_twenty_percent():
    angle = np.radians(35)
    start, end = make_part("door", transform_from_revolute(DOOR_AXIS, DOOR_ORIGIN, angle), seed=9)
    rng = np.random.default_rng(9)
    low, high = np.minimum(start.min(0), end.min(0)) - 0.3, np.maximum(start.max(0), end.max(0)) + 0.3
    start = np.concatenate([start, rng.uniform(low, high, (len(start) // 4, 3))])
    end = np.concatenate([end, rng.uniform(low, high, (len(end) // 4, 3))])
    estimate = fit_joint(start, end)
    assert_finite(estimate)
    assert estimate.type == "revolute"
    assert axis_error_deg(estimate.axis, DOOR_AXIS) < 1.0
    assert abs(estimate.angle - angle) < np.radians(1.0)
    assert line_distance(estimate.origin, estimate.axis, DOOR_ORIGIN, DOOR_AXIS) < 0.01


def test_duplicated_points_and_nan_rows():
    angle = np.radians(35)
    start, end = make_part("door", transform_from_revolute(DOOR_AXIS, DOOR_ORIGIN, angle), count=1500, seed=10)
    start = np.repeat(start, 2, axis=0)
    end = np.concatenate([end, end[:300], np.full((5, 3), np.nan)])
    estimate = fit_joint(start, end)
    assert_finite(estimate)
    assert estimate.type == "revolute" and axis_error_deg(estimate.axis, DOOR_AXIS) < 1.0


@pytest.mark.parametrize("count", [0, 2])
def test_too_few_points_raise(count):
    points = np.random.default_rng(0).normal(size=(count, 3))
    with pytest.raises(ValueError, match="at least"):
        fit_joint(points, points + 0.1)


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="coincide"):
        fit_joint(np.ones((50, 3)), np.ones((50, 3)))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        fit_joint(np.zeros((10, 2)), np.zeros((10, 2)))
    with pytest.raises(ValueError, match="joint_type"):
        fit_joint(np.zeros((10, 3)), np.zeros((10, 3)), joint_type="screw")


def test_outlier_warning_seventy_five_percent():
    """75 % uniform outliers: the fit may fail, but it must say so (same rule as the stability report)."""
    from sparseart.joints.fit import MAX_SCATTER_FRACTION
    from sparseart.bench.stability import cases, run_case

    case = next(c for c in cases() if c.sweep == "outliers" and c.value == 75.0)
    row = run_case(case, count=800)
    assert row["flagged"], row
    assert any("many outliers" in w and f"> {100 * MAX_SCATTER_FRACTION:.0f} %" in w for w in row["warnings"]), row


def test_far_pivot_twenty_part_sizes_warns():
    """Pivot 20x the part size, 10 deg, 800 points: whichever type wins (it was silently
    prismatic and 90 deg off), the revolute/prismatic ambiguity is stated."""
    from sparseart.bench.stability import cases, run_case

    case = next(c for c in cases() if c.sweep == "pivot" and c.value == 20.0)
    row = run_case(case, count=800)
    assert row["flagged"], row
    assert any("ambiguous" in w for w in row["warnings"]), row


def test_clean_fit_has_no_reliability_warning():
    """A plain door (35 deg, partial views, 1 mm noise) must not trip the new warnings."""
    start, end = make_part("door", transform_from_revolute(DOOR_AXIS, DOOR_ORIGIN, np.radians(35)), seed=11)
    estimate = fit_joint(start, end)
    assert estimate.type == "revolute"
    assert not warned(estimate, "unreliable", "uncertainty large", "ambiguous"), estimate.warnings
