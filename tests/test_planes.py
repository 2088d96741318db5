"""The hinge two planes imply (sparseart.geometry.planes): a slab turned about a line in its own
plane is found again from its start and end planes alone, in any unit."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sparseart.geometry.planes import best_by_truncated_chamfer, hinge_turns, ransac_plane
from sparseart.geometry.transforms import apply_transform, axis_angle_deg, make_transform


def _lid(rng: np.random.Generator, scale: float) -> np.ndarray:
    """(N, 3) points of a 0.4 x 0.3 x 0.01 slab, hinge edge along y at x = 0, z = 0."""
    return scale * (rng.uniform([0.0, -0.15, 0.0], [0.4, 0.15, 0.01], size=(3000, 3)))


@pytest.mark.parametrize("turn_deg", [35.0, 75.0, 110.0])
@pytest.mark.parametrize("scale", [1.0, 1000.0])
def test_the_planes_of_a_turned_lid_give_back_its_hinge_and_turn(turn_deg, scale):
    rng = np.random.default_rng(1)
    start = _lid(rng, scale)
    rotation = Rotation.from_rotvec(np.radians(turn_deg) * np.array([0.0, -1.0, 0.0])).as_matrix()
    pivot = scale * np.array([0.0, 0.0, 0.005])
    truth = make_transform(rotation, pivot - rotation @ pivot)
    end = apply_transform(truth, _lid(rng, scale)) + rng.normal(0.0, 0.001 * scale, size=(3000, 3))
    planes = [ransac_plane(points, 0.004 * scale, rng) for points in (start, end)]
    turns = hinge_turns(planes[0], planes[1], min_turn_deg=10.0)
    assert len(turns) == 4
    found = best_by_truncated_chamfer(turns, start[::3], end[::3], 0.03 * scale)
    axis_found = Rotation.from_matrix(found[:3, :3]).as_rotvec()
    assert abs(np.degrees(np.linalg.norm(axis_found)) - turn_deg) < 2.0
    assert axis_angle_deg(axis_found, [0.0, 1.0, 0.0]) < 2.0
    # the hinge line passes (near) the true edge: the moved start lands on the end lid
    assert np.median(np.linalg.norm(apply_transform(found, start) - apply_transform(truth, start), axis=1)) < 0.01 * scale


def test_parallel_planes_imply_no_hinge():
    plane = (np.array([0.0, 0.0, 1.0]), np.zeros(3))
    shifted = (np.array([0.0, np.sin(np.radians(3.0)), np.cos(np.radians(3.0))]), np.array([0.0, 0.0, 0.2]))
    assert hinge_turns(plane, shifted, min_turn_deg=10.0) == []
