"""The fitted turn's physics check (sparseart/joints/sweep_check.py): a turn that drives the part
into the static body is said and trusted less; one that swings it into free space is not."""
import numpy as np
from scipy.spatial import cKDTree

from sparseart.geometry.transforms import transform_from_prismatic, transform_from_revolute
from sparseart.joints.sweep_check import BLOCKED_TRUST, blocked_turn_share, check_turn
from sparseart.types import JointEstimate

SPACING = 0.02


def _grid(x0, x1, y0, y1, z):
    x, y = np.meshgrid(np.arange(x0, x1 + 1e-9, SPACING), np.arange(y0, y1 + 1e-9, SPACING))
    return np.column_stack([x.ravel(), y.ravel(), np.full(x.size, z)])


def _door_and_wall():
    """A 1 x 1 door in the plane z = 0, hinged along its bottom edge (the x axis), and the static
    wall 5 cm behind it (z = -0.05), which only the open door lets a camera see."""
    return _grid(0.0, 1.0, 0.0, 1.0, 0.0), _grid(-0.2, 1.2, -0.2, 1.2, -0.05)


def _turn(angle_deg: float) -> JointEstimate:
    axis, origin, angle = np.array([1.0, 0.0, 0.0]), np.zeros(3), np.radians(angle_deg)
    return JointEstimate(type="revolute", axis=axis, origin=origin, angle=angle, distance=None,
                         transform=transform_from_revolute(axis, origin, angle), uncertainty={}, residual=0.0,
                         confidence=0.9)


def test_a_door_turned_into_its_wall_is_blocked_and_one_turned_away_is_not() -> None:
    door, wall = _door_and_wall()
    tree = cKDTree(wall)
    outward, inward = _turn(40.0), _turn(-40.0)
    ends = {id(j): door @ j.transform[:3, :3].T + j.transform[:3, 3] for j in (outward, inward)}
    assert blocked_turn_share(outward, door, ends[id(outward)], tree, SPACING) == 0.0
    assert blocked_turn_share(inward, door, ends[id(inward)], tree, SPACING) > 0.2

    check_turn(outward, door, ends[id(outward)], tree, SPACING)
    check_turn(inward, door, ends[id(inward)], tree, SPACING)
    assert outward.confidence == 0.9 and not outward.warnings
    assert inward.confidence == 0.9 * BLOCKED_TRUST
    assert any("into the static part" in w for w in inward.warnings)
    assert inward.diagnostics["blocked_share"] > 0.2


def test_a_slide_along_its_wall_is_not_checked() -> None:
    door, wall = _door_and_wall()
    slide = JointEstimate(type="prismatic", axis=np.array([1.0, 0.0, 0.0]), origin=np.zeros(3), angle=None,
                          distance=0.3, transform=transform_from_prismatic(np.array([1.0, 0.0, 0.0]), 0.3),
                          uncertainty={}, residual=0.0, confidence=0.9)
    check_turn(slide, door, door + [0.3, 0.0, 0.0], cKDTree(wall), SPACING)
    assert slide.confidence == 0.9 and "blocked_share" not in slide.diagnostics


def test_the_fitter_flags_a_panel_turned_into_its_body_and_not_one_turned_away() -> None:
    # tests/synthetic.py's panel hangs on the body's front edge (hinge: the z axis at x = y = 0);
    # turned by +40 deg it swings into the body (y > 0), by -40 deg out in front of it
    from synthetic import make_clouds

    from sparseart.joints.candidates import fit_parts
    from sparseart.types import PartLabels, PartSpec

    def fitted(angle_deg: float) -> JointEstimate:
        start, end, _ = make_clouds("revolute", np.radians(angle_deg))
        labels = PartLabels(parts=[PartSpec(id=0, role="static"), PartSpec(id=1, role="movable")],
                            start_part=np.where(start.segment == 2, 1, 0), end_part=np.where(end.segment == 2, 1, 0))
        return fit_parts(start, end, labels, warnings=[])[1].joint

    into, away = fitted(40.0), fitted(-40.0)
    assert abs(abs(np.degrees(into.angle)) - 40.0) < 1.0 and abs(abs(np.degrees(away.angle)) - 40.0) < 1.0
    assert into.diagnostics["blocked_share"] > 0.1 and any("into the static part" in w for w in into.warnings)
    assert away.diagnostics["blocked_share"] < 0.05 and not any("into the static part" in w for w in away.warnings)
    assert into.confidence < 0.6 * away.confidence
