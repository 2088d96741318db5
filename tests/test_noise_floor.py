"""The confidence reads the fit's residual beyond the part's own sampling and noise floor
(``sparseart.joints.noise_floor``; issue 13 item 4: thresholds relative to the noise level): depth
noise alone must not make a correct fit look unsure, and a wrong motion must still look unsure."""
from __future__ import annotations

import numpy as np
from test_joints import make_part

from sparseart.joints import fit_joint, transform_from_revolute

DOOR_TURN = transform_from_revolute(np.array([0.0, 1.0, 0.0]), np.array([0.3, 0.0, 0.0]), np.radians(40.0))
SMALL_TURN = transform_from_revolute(np.array([0.0, 1.0, 0.0]), np.array([0.3, 0.0, 0.0]), np.radians(10.0))


def _door(noise: float, transform: np.ndarray = DOOR_TURN) -> tuple[np.ndarray, np.ndarray]:
    return make_part("door", transform, count=3000, noise=noise, seed=1)


def test_floor_grows_with_depth_noise_and_keeps_a_correct_fit_confident() -> None:
    # A 1 m door turned 40 deg, 1 mm vs 10 mm Gaussian noise: the raw residual grows by half and
    # used to cost the noisy fit 14 % of its confidence (0.67 -> 0.58); the floor follows the noise.
    quiet = fit_joint(*_door(1e-3), joint_type="revolute")
    noisy = fit_joint(*_door(1e-2), joint_type="revolute")
    assert noisy.residual > 1.3 * quiet.residual
    assert noisy.diagnostics["residual_floor"] > 1.3 * quiet.diagnostics["residual_floor"]
    for joint in (quiet, noisy):
        assert 0.0 < joint.diagnostics["residual_floor"] <= 1.05 * joint.residual
    assert noisy.confidence >= 0.95 * quiet.confidence
    assert quiet.confidence > 0.7


def test_a_wrong_motion_stays_unsure_whatever_the_noise() -> None:
    # A 10 deg turn forced to a slide: its residual is 2-3 x the floor at either noise level.
    for noise in (1e-3, 1e-2):
        right = fit_joint(*_door(noise, SMALL_TURN), joint_type="revolute")
        wrong = fit_joint(*_door(noise, SMALL_TURN), joint_type="prismatic")
        assert wrong.residual > 1.5 * wrong.diagnostics["residual_floor"]
        assert wrong.confidence < 0.8 * right.confidence
