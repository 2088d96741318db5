"""Whole-object consistency: a turn its sliding siblings' direction explains as well becomes a slide."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from sparseart.joints.fit import fit_joint
from sparseart.joints.siblings import slides_like_siblings
from sparseart.types import JointEstimate

SLIDE = np.array([0.0, 0.0, 1.0])    # the siblings' rails


def _rack(rng: np.random.Generator, count: int = 1500) -> np.ndarray:
    """A wire rack 0.6 x 0.4 in the x-z plane: 9 + 7 wires of points."""
    along_x = np.column_stack([rng.uniform(-0.3, 0.3, count // 2), np.zeros(count // 2),
                               rng.integers(-3, 4, count // 2) * 0.06])
    along_z = np.column_stack([rng.integers(-4, 5, count - count // 2) * 0.075, np.zeros(count - count // 2),
                               rng.uniform(-0.2, 0.2, count - count // 2)])
    return np.vstack([along_x, along_z])


def _sibling(axis: np.ndarray = SLIDE, sigma: float = 1.5) -> JointEstimate:
    return JointEstimate(type="prismatic", axis=axis, origin=np.zeros(3), angle=None, distance=0.2,
                         transform=np.eye(4), uncertainty={"axis_deg": sigma}, residual=0.01, confidence=0.9)


def _slid_rack_with_wall(rng: np.random.Generator, stray_share: float = 0.4):
    """A rack slid 0.2 along z whose points carry a share of the wall seen between its wires
    (still in both states), with a little noise."""
    start, end = _rack(rng), _rack(rng) + 0.2 * SLIDE
    strays = int(stray_share * len(start) / (1 - stray_share))
    wall = lambda: np.column_stack([rng.uniform(-0.3, 0.3, strays), np.full(strays, -0.03),  # noqa: E731
                                    rng.uniform(-0.2, 0.4, strays)])
    start, end = np.vstack([start, wall()]), np.vstack([end, wall()])
    return start + rng.normal(scale=0.002, size=start.shape), end + rng.normal(scale=0.002, size=end.shape)


def test_a_turn_that_a_sibling_slide_explains_as_well_becomes_that_slide():
    rng = np.random.default_rng(3)
    start, end = _slid_rack_with_wall(rng)
    turn = fit_joint(start, end, joint_type="revolute", uncertainty=False)
    sibling_points = (_rack(rng), _rack(rng) + 0.2 * SLIDE)
    joints = {1: turn, 2: _sibling()}
    points = {1: (start, end), 2: sibling_points}
    replaced = slides_like_siblings(joints, points, {1: {}, 2: {}}, free_type={1, 2})
    assert set(replaced) == {1}
    slide = replaced[1]
    assert slide.type == "prismatic"
    assert abs(slide.axis @ SLIDE) > 1 - 1e-9
    assert slide.residual <= 1.4 * turn.residual
    assert slide.uncertainty["axis_deg"] >= 1.5             # the sibling's direction error is carried over
    assert slide.diagnostics["sibling_of"]["part"] == 2
    assert any("sibling part 2" in w for w in slide.warnings)
    # a type that was given (by the user or the labeler) stays; so does a part among no look-alikes
    assert slides_like_siblings(joints, points, {1: {}, 2: {}}, free_type={2}) == {}
    big = {2: (sibling_points[0] * 3.0, sibling_points[1] * 3.0)}
    assert slides_like_siblings(joints, {**points, **big}, {1: {}, 2: {}}, free_type={1, 2}) == {}
    # a sibling that does not fix its own direction lends none ...
    assert slides_like_siblings({1: turn, 2: _sibling(sigma=20.0)}, points, {1: {}, 2: {}}, free_type={1, 2}) == {}
    # ... unless it runs along an axis of the static body's faces (within 10 deg: here 8)
    tilt = Rotation.from_euler("x", 8.0, degrees=True).as_matrix()
    body = tilt @ np.eye(3)
    lent = slides_like_siblings({1: turn, 2: _sibling(sigma=20.0)}, points, {1: {}, 2: {}}, free_type={1, 2},
                                body_axes=body)
    assert set(lent) == {1} and abs(lent[1].axis @ SLIDE) > 1 - 1e-9
    askew = Rotation.from_euler("x", 12.0, degrees=True).as_matrix()
    assert slides_like_siblings({1: turn, 2: _sibling(sigma=20.0)}, points, {1: {}, 2: {}}, free_type={1, 2},
                                body_axes=askew) == {}


def test_a_half_turn_among_sliding_siblings_gives_way_more_easily():
    """A turn that the sibling's slide explains at 1.7 x its residual stays; a half-turn (a
    symmetric part's flipped match) at the same ratio becomes the slide."""
    rng = np.random.default_rng(3)
    start, end = _slid_rack_with_wall(rng)
    held = fit_joint(start, end, joint_type="prismatic", slide_axis=SLIDE, uncertainty=False)
    points = {1: (start, end), 2: (_rack(rng), _rack(rng) + 0.2 * SLIDE)}

    def turn(angle_deg: float) -> JointEstimate:
        return JointEstimate(type="revolute", axis=np.array([0.0, 1.0, 0.0]), origin=np.zeros(3),
                             angle=np.radians(angle_deg), distance=None, transform=np.eye(4), uncertainty={},
                             residual=held.residual / 1.7, confidence=0.9)

    assert slides_like_siblings({1: turn(100.0), 2: _sibling()}, points, {1: {}, 2: {}}, free_type={1}) == {}
    flipped = slides_like_siblings({1: turn(174.0), 2: _sibling()}, points, {1: {}, 2: {}}, free_type={1})
    assert flipped[1].type == "prismatic" and abs(flipped[1].axis @ SLIDE) > 1 - 1e-9


def test_a_door_beside_a_sliding_sibling_stays_a_turn():
    """A door the size of its sliding sibling, turned 35 deg about its edge: a slide along the
    sibling's rails explains it far worse, so the turn stays."""
    rng = np.random.default_rng(4)
    door = np.column_stack([rng.uniform(0.0, 0.6, 3000), np.zeros(3000), rng.uniform(-0.2, 0.2, 3000)])
    turn = Rotation.from_rotvec(np.radians(35.0) * np.array([0.0, 0.0, 1.0]))
    start = door + rng.normal(scale=0.002, size=door.shape)
    end = turn.apply(door) + rng.normal(scale=0.002, size=door.shape)
    fitted = fit_joint(start, end, uncertainty=False)
    assert fitted.type == "revolute"
    sibling = (_rack(rng) + [0.3, 0.0, 0.0], _rack(rng) + [0.3, 0.0, 0.0] + 0.2 * SLIDE)
    replaced = slides_like_siblings({1: fitted, 2: _sibling()}, {1: (start, end), 2: sibling}, {1: {}, 2: {}},
                                    free_type={1, 2})
    assert replaced == {}


def test_sibling_slides_do_not_depend_on_the_unit():
    rng = np.random.default_rng(3)
    start, end = _slid_rack_with_wall(rng)
    sibling_points = (_rack(rng), _rack(rng) + 0.2 * SLIDE)
    results = []
    for scale in (1.0, 1000.0):
        turn = fit_joint(start * scale, end * scale, joint_type="revolute", uncertainty=False)
        replaced = slides_like_siblings({1: turn, 2: _sibling()},
                                        {1: (start * scale, end * scale),
                                         2: (sibling_points[0] * scale, sibling_points[1] * scale)},
                                        {1: {}, 2: {}}, free_type={1, 2})
        results.append(replaced[1].distance / scale)
    assert np.isclose(results[0], results[1], rtol=1e-6)
