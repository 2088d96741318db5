"""Turns about a known axis direction (sparseart.geometry.axis_turns): a handle whose round cap
lands on itself whatever the angle is found by the exhaustive angle and the correlation shift."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sparseart.geometry.axis_turns import axis_turns
from sparseart.geometry.transforms import apply_transform, transform_from_revolute
from sparseart.labelers.correspondence import refine_icp


def _handle(rng: np.random.Generator) -> np.ndarray:
    """A cap (cylinder wall and top, radius 0.1, height 0.08, axis z through (0.3, -0.2)) and a
    lever (0.25 long, 0.02 thick) on its top: (N, 3) metres; the cap holds ~85 % of the points."""
    angle = rng.uniform(0, 2 * np.pi, 3000)
    height = rng.uniform(0, 0.08, 3000)
    wall = np.column_stack([0.1 * np.cos(angle), 0.1 * np.sin(angle), height])
    radius = 0.1 * np.sqrt(rng.uniform(0, 1, 1500))
    spin = rng.uniform(0, 2 * np.pi, 1500)
    top = np.column_stack([radius * np.cos(spin), radius * np.sin(spin), np.full(1500, 0.08)])
    lever = np.column_stack([rng.uniform(0.0, 0.25, 800), rng.uniform(-0.01, 0.01, 800), rng.uniform(0.08, 0.1, 800)])
    return np.concatenate([wall, top, lever]) + np.array([0.3, -0.2, 0.0])


@pytest.mark.parametrize("angle_deg", [73.0, -40.0, 150.0])
def test_a_handle_turned_about_its_cap_is_found_among_the_turns_about_the_body_axes(angle_deg: float) -> None:
    rng = np.random.default_rng(0)
    start = _handle(rng)
    truth = transform_from_revolute(np.array([0.0, 0.0, 1.0]), np.array([0.3, -0.2, 0.0]), np.radians(angle_deg))
    end = apply_transform(truth, _handle(rng))          # other samples of the same surfaces
    axes = Rotation.from_euler("z", 20, degrees=True).as_matrix() @ np.eye(3)   # body axes, z among them
    radius = 0.01
    turns = axis_turns(start, end, axes.T, radius)
    assert len(turns) == 6                              # keep=2 per axis
    refined = [refine_icp(start, end, turn, radius) for turn in turns]
    errors = [np.degrees(Rotation.from_matrix(r[:3, :3] @ truth[:3, :3].T).magnitude()) for r in refined]
    best = refined[int(np.argmin(errors))]
    assert min(errors) < 1.0
    assert np.abs(apply_transform(best, start) - apply_transform(truth, start)).max() < 0.01
    # the search is unit-free: the same scene in millimetres gives the same turns
    turns_mm = axis_turns(start * 1000, end * 1000, axes.T, radius * 1000)
    for metres, millimetres in zip(turns, turns_mm):
        np.testing.assert_allclose(millimetres[:3, :3], metres[:3, :3], atol=1e-9)
        np.testing.assert_allclose(millimetres[:3, 3], metres[:3, 3] * 1000, atol=1e-6)


def test_too_few_points_or_no_cell_give_no_turns() -> None:
    points = np.zeros((2, 3))
    assert axis_turns(points, points, np.eye(3), 0.01) == []
    assert axis_turns(np.random.default_rng(0).normal(size=(50, 3)), np.ones((50, 3)), np.eye(3), 0.0) == []
