"""The static frame's own error in the stated uncertainty (sparseart.joints.uncertainty.frame_misfit,
add_frame_sigma): zero when the static part's two states agree to their sampling, the frame's turn
when they do not, unit-free."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sparseart.joints.frame_shift import (DEPTH_RATIO_SHIFT_SHARE, REGISTRATION_SHIFT_SHARE, add_frame_shift,
                                          depth_ratio_shift, registration_shift)
from sparseart.joints.uncertainty import add_frame_sigma, frame_misfit
from sparseart.types import JointEstimate


def _box_surface(count: int, rng: np.random.Generator) -> np.ndarray:
    """Points on the surface of a 1 x 0.8 x 0.6 box (a cabinet carcass)."""
    points = rng.uniform(-0.5, 0.5, size=(count, 3)) * [1.0, 0.8, 0.6]
    face = rng.integers(0, 3, size=count)
    points[np.arange(count), face] = np.sign(rng.uniform(-1, 1, size=count)) * np.array([0.5, 0.4, 0.3])[face]
    return points


def test_states_that_agree_to_their_sampling_add_nothing():
    rng = np.random.default_rng(0)
    start = _box_surface(20000, rng)
    end = start + rng.normal(scale=1e-4, size=start.shape)    # the same surface, sampled alike
    misfit, radius = frame_misfit(start, end)
    assert misfit == 0.0 and radius > 0.3
    sigma = {"axis_deg": 0.5, "origin": 0.01, "angle": 0.01}
    assert add_frame_sigma(sigma, misfit, radius, 0.3) == sigma


def _turned_sigma(turn_deg: float, unit: float) -> dict:
    rng = np.random.default_rng(1)
    start = _box_surface(20000, rng)
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    end = Rotation.from_rotvec(np.radians(turn_deg) * axis).apply(start)
    misfit, radius = frame_misfit(start * unit, end * unit)
    return add_frame_sigma({"axis_deg": 0.3, "origin": 0.001 * unit, "distance": 0.002 * unit}, misfit, radius,
                           0.3 * unit)


def test_a_turned_static_frame_widens_the_sigma_with_its_turn_in_any_unit():
    small, large = _turned_sigma(2.0, 1.0), _turned_sigma(4.0, 1.0)   # (1 deg: below the spacing here)
    assert 0.3 < small["axis_deg"] < large["axis_deg"] < 4.0 * 2      # grows with the turn, never beyond ~it
    assert large["axis_deg"] > 1.0                                     # a 4 deg frame turn is not hidden
    assert large["origin"] > 0.001 and large["distance"] > 0.002 and "angle" not in large
    in_mm = _turned_sigma(4.0, 1000.0)
    assert in_mm["axis_deg"] == pytest.approx(large["axis_deg"], rel=1e-6)
    assert in_mm["origin"] == pytest.approx(1000.0 * large["origin"], rel=1e-6)


def test_too_few_static_points_give_no_term():
    assert frame_misfit(np.zeros((10, 3)), np.zeros((10, 3))) == (0.0, 0.0)


# -- the frame's turn in the type test (fit_joint(frame_error=)) and slides in disguise -------------

def _drawer_front(count: int, rng: np.random.Generator) -> np.ndarray:
    """Points on a 0.6 x 0.4 x 0.04 slab (a drawer front) at x = 0.52, normal +x."""
    points = rng.uniform(-0.5, 0.5, size=(count, 3)) * [0.04, 0.6, 0.4] + [0.52, 0.0, 0.0]
    face = rng.integers(0, 3, size=count)
    points[np.arange(count), face] = (np.sign(rng.uniform(-1, 1, size=count)) * np.array([0.02, 0.3, 0.2])[face]
                                      + np.array([0.52, 0.0, 0.0])[face])
    return points


def _slide_in_a_turned_frame(turn_deg: float):
    """A drawer front sliding 0.2 along +x, both states seen in a frame turned by ``turn_deg``
    (what a smooth depth warp does to the whole end state): part and static body turn alike."""
    rng = np.random.default_rng(3)
    body, front = _box_surface(20000, rng), _drawer_front(6000, rng)
    turn = Rotation.from_rotvec(np.radians(turn_deg) * np.array([0.0, 0.6, 0.8]))
    body_end = turn.apply(_box_surface(20000, rng))
    front_end = turn.apply(_drawer_front(6000, rng) + [0.2, 0.0, 0.0])
    noise = 5e-4
    return (body + rng.normal(scale=noise, size=body.shape), body_end + rng.normal(scale=noise, size=body_end.shape),
            front + rng.normal(scale=noise, size=front.shape), front_end + rng.normal(scale=noise, size=front_end.shape))


def test_a_slide_in_a_turned_frame_stays_a_slide_once_the_frame_turn_is_known():
    """Without the frame's error the 3 deg turn of the whole end state is a significant rotation of
    the part; with it (frame_misfit of the static body) the same data give a slide
    along the drawer's normal, with the turn in its stated axis sigma."""
    from sparseart.joints.fit import fit_joint

    body, body_end, front, front_end = _slide_in_a_turned_frame(3.0)
    blind = fit_joint(front, front_end)
    frame_error = frame_misfit(body, body_end)
    assert np.degrees(frame_error[0] / frame_error[1]) > 0.8   # (nearest-surface distances: below the turn)
    aware = fit_joint(front, front_end, frame_error=frame_error)
    assert aware.type == "prismatic"
    # the frame's turn is what makes the rotation insignificant (the far-pivot rule also calls the
    # blind fit a slide here, but on a significant rotation)
    assert blind.diagnostics["revolute_angle_z"] > 4.0 > aware.diagnostics["revolute_angle_z"]
    error = np.degrees(np.arccos(min(abs(aware.axis[0]), 1.0)))
    assert error < 15.0                      # the frame's turn tilts the slide (lever ~0.7 over 0.2)
    # the stated sigma grows from the frame (nearest-surface misfits see ~40 % of a rigid turn)
    assert aware.diagnostics["uncertainty_before_frame"]["axis_deg"] < 1.0 < 0.25 * error < aware.uncertainty["axis_deg"]


# -- the shift of the whole frame that the alignment measured (add_frame_shift) ---------------------

def _joint(kind: str, unit: float = 1.0) -> JointEstimate:
    return JointEstimate(type=kind, axis=np.array([0.0, 0.0, 1.0]), origin=np.zeros(3),
                         angle=np.radians(60.0) if kind == "revolute" else None,
                         distance=None if kind == "revolute" else 0.3 * unit, transform=np.eye(4),
                         uncertainty={"axis_deg": 1.5, "origin": 0.004 * unit,
                                      **({"angle": 0.02} if kind == "revolute" else {"distance": 0.005 * unit})},
                         residual=0.01 * unit, confidence=0.9, diagnostics={})


def test_a_frame_shift_widens_the_hinge_line_and_the_slide_not_the_axis_in_any_unit():
    """Depth off by ~2 % moves surfaces along the camera rays: the hinge line, a slide's origin and
    its length carry the shift in quadrature; the axis and the angle (turns) keep theirs. In millimetres the same
    joint gets the same sigma x 1000. The two readings of the shift: REGISTRATION_SHIFT_SHARE x the
    states' feature residual, DEPTH_RATIO_SHIFT_SHARE x the depth disagreement x the distance."""
    assert registration_shift(0.05) == pytest.approx(REGISTRATION_SHIFT_SHARE * 0.05)
    assert depth_ratio_shift(0.02, 3.0) == pytest.approx(DEPTH_RATIO_SHIFT_SHARE * 0.06)
    assert depth_ratio_shift(0.02, 3000.0) == pytest.approx(1000.0 * depth_ratio_shift(0.02, 3.0))
    hinge, slide = _joint("revolute"), _joint("prismatic")
    add_frame_shift(hinge, 0.0175)
    add_frame_shift(slide, 0.0175)
    assert hinge.uncertainty["origin"] == pytest.approx(np.hypot(0.004, 0.0175))
    assert hinge.uncertainty["axis_deg"] == 1.5 and hinge.uncertainty["angle"] == 0.02
    assert slide.uncertainty["distance"] == pytest.approx(np.hypot(0.005, 0.0175))
    assert slide.uncertainty["origin"] == pytest.approx(np.hypot(0.004, 0.0175))     # a slide's origin moves too
    assert slide.diagnostics["frame_shift"] == pytest.approx(0.0175)
    only_line = _joint("prismatic")
    add_frame_shift(only_line, 0.0175, keys=("origin",))
    assert only_line.uncertainty["distance"] == 0.005
    in_mm = _joint("revolute", 1000.0)
    add_frame_shift(in_mm, 17.5)
    assert in_mm.uncertainty["origin"] == pytest.approx(1000.0 * hinge.uncertainty["origin"])
    for bad in (0.0, float("nan"), -1.0):
        untouched = _joint("revolute")
        add_frame_shift(untouched, bad)
        assert untouched.uncertainty["origin"] == 0.004 and "frame_shift" not in untouched.diagnostics


def test_the_pipeline_reads_the_shift_off_what_the_alignment_measured():
    """States aligned by features (trusted): the registration residual, on hinges and slides.
    States in one frame from posed cameras: the depth-ratio disagreement x the part's distance from
    its camera, on the origins only (both states' depth moved alike, a slide's length keeps its
    sigma). Nothing for a still camera without poses, an untrusted alignment, or no report."""
    from sparseart.joints.frame_shift import add_alignment_shift
    from sparseart.types import Camera, Frame, LabelledCloud, PartLabels, PartResult, PartSpec, Scene

    points = np.array([[0.0, 0.0, 3.0], [0.1, 0.0, 3.0], [0.0, 0.1, 3.0]])
    start = LabelledCloud(state="start", points=points, colors=np.zeros((3, 3)), segment=np.zeros(3, dtype=np.int64),
                          frame_index=np.zeros(3, dtype=np.int64), pixel_index=np.arange(3), confidence=np.ones(3))
    labels = PartLabels(parts=[PartSpec(id=0, role="static"), PartSpec(id=1, role="movable"),
                               PartSpec(id=2, role="movable")],
                        start_part=np.array([1, 1, 2]), end_part=np.array([1, 1, 2]))
    def frame(pose: np.ndarray | None) -> Frame:
        return Frame(state="start", index=0, rgb_path=Path("start/rgb/000.png"), rgb=np.zeros((4, 4, 3), np.uint8),
                     camera=Camera(K=np.eye(3), width=4, height=4, cam_to_world=pose))

    posed = Scene(root=Path("."), start=[frame(np.eye(4))], end=[])

    def parts() -> list:
        return [PartResult(PartSpec(id=1, role="movable"), 2, _joint("revolute")),
                PartResult(PartSpec(id=2, role="movable"), 1, _joint("prismatic"))]

    unposed = Scene(root=Path("."), start=[frame(None)], end=[])
    for registration, scene in (({}, posed), ({"states": {"method": "still camera", "trusted": True}}, unposed),
                                ({"states": {"method": "features", "trusted": False, "rmse": 0.05}}, posed),
                                ({"depth_ratio": [{"largest": 0.02}]}, unposed),
                                ({"depth_ratio": [{"largest": 0.02}]}, None)):
        kept = parts()
        add_alignment_shift(kept, registration, start, labels, scene)
        assert kept[0].joint.uncertainty["origin"] == 0.004 and kept[1].joint.uncertainty["distance"] == 0.005
    featured = parts()
    add_alignment_shift(featured, {"states": {"method": "features", "trusted": True, "rmse": 0.05}}, start, labels, None)
    assert featured[0].joint.diagnostics["frame_shift"] == pytest.approx(registration_shift(0.05))
    assert featured[1].joint.uncertainty["distance"] > 0.005
    ratio = parts()
    add_alignment_shift(ratio, {"states": {"method": "cameras"}, "depth_ratio": [{"largest": 0.02}]}, start, labels, posed)
    distance = float(np.median(np.linalg.norm(points[:2], axis=1)))
    assert ratio[0].joint.diagnostics["frame_shift"] == pytest.approx(depth_ratio_shift(0.02, distance))
    assert ratio[1].joint.uncertainty["distance"] == 0.005 and ratio[1].joint.uncertainty["origin"] > 0.004
