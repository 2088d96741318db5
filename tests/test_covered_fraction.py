"""The confidence's coverage term reads how much of a part the fitted motion lays onto itself, not
how alike the two states' samplings are (``sparseart.joints.reliability.covered_fraction``).

A camera sees a turned lid at another angle, so the same surface is sampled with another density
pattern; one-to-one pairing of two such samples leaves points unpaired under a perfect motion
(measured: clean laptop renders 0.80-0.85, every point landing), which capped the confidence of
perfect fits there. A region seen in one state only must still lower it.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from test_joints import make_part

from sparseart.joints import fit_joint, transform_from_revolute
from sparseart.joints.reliability import covered_fraction

LID_TURN = transform_from_revolute(np.array([0.0, 1.0, 0.0]), np.array([0.3, 0.0, 0.0]), np.radians(60.0))


def _plate(rng: np.random.Generator, count: int, dense_left: float) -> np.ndarray:
    """(count, 3) points on a 1 x 1 plate (z = 0), ``dense_left`` of them on the left half."""
    left = int(dense_left * count)
    x = np.concatenate([rng.uniform(0.0, 0.5, left), rng.uniform(0.5, 1.0, count - left)])
    return np.stack([x, rng.uniform(0.0, 1.0, count), np.zeros(count)], axis=1)


def test_every_point_landing_covers_all_whatever_the_density() -> None:
    rng = np.random.default_rng(0)
    start, end = _plate(rng, 1500, 0.8), _plate(rng, 1500, 0.2)   # same surface, other density pattern
    covered = covered_fraction(start, end, cKDTree(end), np.eye(3), np.zeros(3), radius=0.05)
    assert covered > 0.98


def test_a_region_seen_in_one_state_only_lowers_it() -> None:
    rng = np.random.default_rng(1)
    start = _plate(rng, 1500, 0.5)
    end = start[start[:, 0] < 0.5]                                # the end sees the left half only
    covered = covered_fraction(start, end, cKDTree(end), np.eye(3), np.zeros(3), radius=0.05)
    assert 0.7 < covered < 0.8                                    # 1/2 of the start, all of the end


def test_a_wrong_motion_covers_little() -> None:
    rng = np.random.default_rng(2)
    start = _plate(rng, 1500, 0.5)
    shifted = covered_fraction(start, start, cKDTree(start), np.eye(3), np.array([0.6, 0.0, 0.0]), radius=0.05)
    assert shifted < 0.5


def test_a_correct_lid_fit_is_confident_near_one() -> None:
    start, end = make_part("door", LID_TURN, count=3000, noise=1e-3, seed=3)
    joint = fit_joint(start, end, joint_type="revolute")
    assert joint.diagnostics["covered_fraction"] > 0.95
    assert joint.diagnostics["covered_fraction"] >= joint.diagnostics["match_fraction"]
    assert joint.confidence > 0.85
