"""Choosing among a part's candidate fits (sparseart.joints.candidates): revolute fits that are
slides in disguise or half-turn twins of a symmetric part give way to the simpler motion."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sparseart.joints.body_axes import static_body_axes
from sparseart.joints.candidates import (body_axis_fits, detached_slide_seeds, mirror_seed, plausible_fits,
                                        without_half_turns)
from sparseart.joints.config import FitConfig
from sparseart.types import JointEstimate


def _estimate(kind: str, residual: float, angle_deg: float = 11.5, **diagnostics) -> JointEstimate:
    return JointEstimate(type=kind, axis=np.array([1.0, 0.0, 0.0]), origin=np.zeros(3),
                         angle=np.radians(angle_deg) if kind == "revolute" else None, distance=None if kind == "revolute" else 0.2,
                         transform=np.eye(4), uncertainty={}, residual=residual, confidence=1.0,
                         diagnostics=diagnostics)


def test_revolute_candidates_that_are_slides_in_disguise_give_way_to_a_slide():
    slide = _estimate("prismatic", 0.026)
    flap = _estimate("revolute", 0.022, revolute_angle_z=9.0, revolute_pivot_factor=5.8)    # far pivot
    frame_turn = _estimate("revolute", 0.021, revolute_angle_z=1.0, revolute_pivot_factor=0.5)  # insignificant
    hinge = _estimate("revolute", 0.020, revolute_angle_z=60.0, revolute_pivot_factor=1.5)
    config = FitConfig()
    assert plausible_fits([slide, flap, frame_turn, hinge], config) == [slide, hinge]
    assert plausible_fits([flap, frame_turn], config) == [flap, frame_turn]     # no slide to give way to


def test_a_turn_about_an_axis_clear_of_the_part_gives_way_to_a_slide():
    """A hinge touches its part: a significant turn about a near pivot whose axis line passes
    two part radii clear of the part (a drawer front's "flap" fitted under depth warps) goes
    when a slide is among the candidates; the same turn about an axis along the part's edge
    stays, and so does the detached one with no slide to give way to."""
    rng = np.random.default_rng(3)
    front = np.column_stack([rng.uniform(-0.3, 0.3, 2000), rng.uniform(-0.2, 0.2, 2000), np.zeros(2000)])
    radius = np.sqrt(np.mean(np.sum(front ** 2, axis=1)))
    slide = _estimate("prismatic", 0.026)
    edge = _estimate("revolute", 0.024, revolute_angle_z=8.0, revolute_pivot_factor=1.6)
    edge.origin = np.array([0.0, 0.2, 0.0])                  # axis x along the front's top edge
    detached = _estimate("revolute", 0.024, revolute_angle_z=8.0, revolute_pivot_factor=3.8)
    detached.origin = np.array([0.0, 0.2, 2.0 * radius])     # parallel, 2 radii in front of it
    config = FitConfig()
    assert plausible_fits([slide, edge, detached], config, front) == [slide, edge]
    assert plausible_fits([edge, detached], config, front) == [edge, detached]
    # unit-free: the same scene in millimetres keeps the same fits
    for fit in (edge, detached):
        fit.origin = fit.origin * 1000.0
    assert plausible_fits([slide, edge, detached], config, front * 1000.0) == [slide, edge]


def test_a_half_turn_gives_way_to_a_comparable_smaller_motion():
    slide = _estimate("prismatic", 0.0125)
    spin = _estimate("revolute", 0.0124, angle_deg=179.8)
    door = _estimate("revolute", 0.0124, angle_deg=96.0)
    assert without_half_turns([spin, slide]) == [slide]
    assert without_half_turns([spin, door]) == [door]
    fair = _estimate("prismatic", 0.03)                         # 2.4 x worse: still an alternative (a flip
    assert without_half_turns([spin, fair]) == [fair]           # of a symmetric handle fitted 2.5 x better)
    far = _estimate("prismatic", 0.04)                          # 3.2 x worse: not an alternative
    assert without_half_turns([spin, far]) == [spin, far]
    assert without_half_turns([door, slide]) == [door, slide]   # nothing turns that far
    # the best turns less and its mirror half-turn is comparable: the half-turn goes too, so that
    # no tie-break among hinges can pick it (a door opened 28 deg and its 155 deg mirror)
    mirror = _estimate("revolute", 0.0130, angle_deg=155.0)
    assert without_half_turns([door, mirror]) == [door]


def _box(count: int, half: list[float], rng: np.random.Generator) -> np.ndarray:
    """Points on the surface of a box of half-extents ``half`` centred at the origin."""
    half = np.asarray(half, dtype=np.float64)
    points = rng.uniform(-1, 1, size=(count, 3)) * half
    face = rng.integers(0, 3, size=count)
    points[np.arange(count), face] = np.sign(rng.uniform(-1, 1, size=count)) * half[face]
    return points


def test_the_mirror_of_a_half_turned_box_is_its_slide():
    """A box-shaped drawer (no slab) fitted as a 180 deg turn about x gets a mirror seed: the
    same end pose reached with no turn, i.e. the slide; a 90 deg turn of the box gets none."""
    rng = np.random.default_rng(5)
    start = _box(4000, [0.25, 0.2, 0.15], rng)      # a drawer
    spin = np.eye(4)
    spin[:3, :3] = Rotation.from_rotvec([np.pi, 0.0, 0.0]).as_matrix()
    spin[:3, 3] = [0.3, 0.0, 0.0]
    turned = JointEstimate(type="revolute", axis=np.array([1.0, 0.0, 0.0]), origin=np.zeros(3), angle=np.pi,
                           distance=None, transform=spin, uncertainty={}, residual=0.01, confidence=1.0)
    seed = mirror_seed(turned, start)
    assert seed is not None
    np.testing.assert_allclose(seed[:3, :3], np.eye(3), atol=1e-9)
    np.testing.assert_allclose(seed[:3, 3], [0.3, 0.0, 0.0], atol=0.01)    # (about the sampled centroid)
    quarter = JointEstimate(type="revolute", axis=np.array([1.0, 0.0, 0.0]), origin=np.zeros(3),
                            angle=np.pi / 2, distance=None, transform=spin, uncertainty={}, residual=0.01,
                            confidence=1.0)
    assert mirror_seed(quarter, start) is None


PANE = [0.3, 0.2, 0.01]   # half-extents of a 0.6 x 0.4 x 0.02 window sash


def test_a_part_whose_every_hinge_is_detached_gets_slide_seeds_along_the_body():
    """Every fit a turn about an axis clear of the part (a thin rack's few points registered
    with a turn): slide seeds are offered -- the centroid's shift and that length along each
    axis of the static body, pointing with the shift. One hinge touching the part, or a slide
    already among the fits, and nothing is offered."""
    rng = np.random.default_rng(5)
    rack = np.column_stack([rng.uniform(-0.3, 0.3, 800), np.zeros(800), rng.uniform(-0.2, 0.2, 800)])
    shift = np.array([0.0, 0.0, 0.25])
    radius = np.sqrt(np.mean(np.sum(rack ** 2, axis=1)))
    body = np.column_stack([rng.uniform(-0.5, 0.5, 3000), rng.uniform(-0.6, 0.6, 3000), rng.uniform(-0.4, 0.4, 3000)])
    detached = _estimate("revolute", 0.05, revolute_angle_z=9.0, revolute_pivot_factor=2.0)
    detached.origin = np.array([0.0, 2.0 * radius, 0.0])     # axis x, two radii above the rack
    seeds = detached_slide_seeds([detached], rack, rack + shift, body)
    assert len(seeds) == 4
    assert np.allclose(seeds[0][:3, 3], shift)
    along = [seed[:3, 3] for seed in seeds[1:]]
    assert all(np.isclose(np.linalg.norm(t), 0.25) and t @ shift >= 0 for t in along)
    assert max(abs(t @ shift) for t in along) > 0.99 * 0.25 * 0.25     # the body's z axis is the shift's
    touching = _estimate("revolute", 0.05, revolute_angle_z=9.0, revolute_pivot_factor=1.0)
    touching.origin = np.array([0.0, 0.0, 0.2])              # axis x along the rack's edge
    assert detached_slide_seeds([detached, touching], rack, rack + shift, body) == []
    assert detached_slide_seeds([detached, _estimate("prismatic", 0.05)], rack, rack + shift, body) == []
    # unit-free: the same scene in millimetres gives the same seeds, scaled
    detached.origin = detached.origin * 1000.0
    seeds_mm = detached_slide_seeds([detached], rack * 1000.0, (rack + shift) * 1000.0, body * 1000.0)
    assert np.allclose(seeds_mm[0][:3, 3], shift * 1000.0)


def _turned_pane(angle_deg: float, pivot_radii: float):
    """A pane turned by ``angle_deg`` about a vertical axis ``pivot_radii`` part radii away."""
    from sparseart.joints.fit import fit_joint

    rng = np.random.default_rng(9)
    start = _box(5000, PANE, rng)
    radius = float(np.sqrt(np.mean(np.sum(start ** 2, axis=1))))
    pivot = np.array([-pivot_radii * radius, 0.0, 0.0])
    turn = Rotation.from_rotvec(np.radians(angle_deg) * np.array([0.0, 1.0, 0.0]))
    end = turn.apply(_box(5000, PANE, rng) - pivot) + pivot
    noise = 2e-4
    return fit_joint(start + rng.normal(scale=noise, size=start.shape), end + rng.normal(scale=noise, size=end.shape))


def test_a_small_turn_about_a_far_pivot_is_a_slide_and_a_hinge_stays_a_hinge():
    far = _turned_pane(4.0, 20.0)          # moves 0.35 radii-ish sideways, turning 4 deg
    assert far.type == "prismatic"
    assert "slide" in far.diagnostics["type_reason"]
    near = _turned_pane(30.0, 2.0)
    assert near.type == "revolute"
    assert abs(np.degrees(near.angle) - 30.0) < 1.0


def test_a_half_turn_is_flagged_and_lowers_the_confidence():
    """A fit turning 178 deg (a fridge door seen edge-on, matched flipped) warns and halves the
    confidence; the real laptop's 96 deg does not."""
    from sparseart.joints.reliability import WarningCode, confidence, revolute_warnings

    def codes(degrees: float) -> set:
        return {w.code for w in revolute_warnings(np.radians(degrees), 0.5, 1.0, 0.0, 0.1, 0.0, 2.0, 5.0)}

    assert WarningCode.HALF_TURN in codes(178.0) and WarningCode.HALF_TURN in codes(-178.0)
    assert WarningCode.HALF_TURN not in codes(96.0)
    flagged = revolute_warnings(np.radians(178.0), 0.5, 1.0, 0.0, 0.1, 0.0, 2.0, 5.0)
    assert confidence(1.0, 0.0, 1.0, flagged) == 0.5 * confidence(1.0, 0.0, 1.0, [])


def test_tied_hinge_rivals_widen_the_axis_sigma_and_far_ones_do_not():
    """choose_fit takes the hinge axis nearest the static part (among those about as near, the
    lowest residual when even the nearest is far from it). A rival that fits as well and lies
    about as near (a rod's roll) makes that choice a coin toss: the sigma covers the rival. A rival
    the attachment rule tells apart (its axis far from the body) leaves the sigma alone."""
    from sparseart.joints.candidates import choose_fit, widen_for_tied_hinges

    rng = np.random.default_rng(0)
    static = np.column_stack([np.zeros(400), rng.uniform(-1, 1, 400), rng.uniform(-1, 1, 400)])  # a wall x = 0
    part = np.column_stack([rng.uniform(0.1, 0.5, 200), rng.uniform(-0.2, 0.2, 200), np.zeros(200)])

    def hinge(residual: float, axis: list[float], origin: list[float]) -> JointEstimate:
        estimate = _estimate("revolute", residual, angle_deg=60.0)
        estimate.axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
        estimate.origin = np.asarray(origin, dtype=np.float64)
        estimate.uncertainty = {"axis_deg": 2.0}
        return estimate

    on_wall = hinge(0.0101, [0, 0, 1], [0.0, 0.0, 0.0])
    tilted = hinge(0.0100, [0, np.sin(np.radians(9)), np.cos(np.radians(9))], [0.0, 0.0, 0.0])  # as near, 9 deg
    far = hinge(0.0099, [0, 1, 0], [0.6, 0.0, 0.0])                                           # off the wall
    chosen = choose_fit([on_wall, tilted, far], part, static)
    assert (chosen is on_wall or chosen is tilted) and chosen.diagnostics["tied_hinge"]["axis_deg"] == pytest.approx(9.0, abs=1e-6)
    widen_for_tied_hinges(chosen, chosen.diagnostics["tied_hinge"])
    assert chosen.uncertainty["axis_deg"] == pytest.approx(9.0) and "rival hinge axis" in chosen.warnings[-1]

    # a rival on the wall that fits 35 % worse still goes to the tie-break (within 1.5 x): the
    # attachment wins; at 1.6 x it does not
    better = hinge(0.0310, [0, 1, 0], [0.6, 0.0, 0.0])
    assert choose_fit([better, on_wall := hinge(0.0420, [0, 0, 1], [0.0, 0.0, 0.0])], part, static) is on_wall
    assert choose_fit([better, hinge(0.0500, [0, 0, 1], [0.0, 0.0, 0.0])], part, static) is better

    # two hinges about as near the wall: attached (0.05 and 0.06 from it, the part's radius ~0.15),
    # the nearer wins whatever the residual; with the wall seen only far off (0.3 and 0.35 away, over
    # 0.5 part radii) the attachment tells nothing and the lower residual wins
    wall = np.column_stack([np.zeros(40000), rng.uniform(-1, 1, 40000), rng.uniform(-1, 1, 40000)])
    tilt = [0, np.sin(np.radians(12)), np.cos(np.radians(12))]
    nearer, fits_better = hinge(0.0105, [0, 0, 1], [-0.05, 0.0, 0.0]), hinge(0.0100, tilt, [-0.06, 0.0, 0.0])
    assert choose_fit([nearer, fits_better], part, wall) is nearer
    nearer, fits_better = hinge(0.0105, [0, 0, 1], [-0.30, 0.0, 0.0]), hinge(0.0100, tilt, [-0.35, 0.0, 0.0])
    chosen = choose_fit([nearer, fits_better], part, wall)
    assert chosen is fits_better and chosen.diagnostics["tied_hinge"]["axis_deg"] == pytest.approx(12.0, abs=1e-6)
    assert choose_fit([nearer, hinge(0.0100, [0, 0, 1], [-0.45, 0.0, 0.0])], part, wall) is nearer  # 1.5 x: told apart
    # the best fit lies farther still (0.6, out of the tie): the better of the two about as near
    # wins, and the warning says that no hinge axis lies on the static part seen
    nearer, fits_better = hinge(0.0105, [0, 0, 1], [-0.30, 0.0, 0.0]), hinge(0.0102, tilt, [-0.35, 0.0, 0.0])
    chosen = choose_fit([nearer, fits_better, hinge(0.0100, [0, 0, 1], [-0.60, 0.0, 0.0])], part, wall)
    assert chosen is fits_better and "no hinge axis lies on the static part seen" in chosen.warnings[-1]
    chosen = choose_fit([hinge(0.0105, [0, 0, 1], [-0.05, 0.0, 0.0]), hinge(0.0100, tilt, [-0.35, 0.0, 0.0])], part, wall)
    assert "chose the axis nearest the static part" in chosen.warnings[-1]

    alone = hinge(0.0101, [0, 0, 1], [0.0, 0.0, 0.0])
    chosen = choose_fit([alone, hinge(0.0099, [0, 1, 0], [0.6, 0.0, 0.0])], part, static)
    assert chosen is alone and "tied_hinge" not in chosen.diagnostics
    widen_for_tied_hinges(chosen, chosen.diagnostics.get("tied_hinge"))
    assert chosen.uncertainty["axis_deg"] == 2.0


def test_tied_hinge_rivals_widen_the_hinge_line_and_angle_sigma():
    """A flat lid turned by 90 deg fixes its hinge line only through its edges: rivals at about
    the same residual and as near the static part lie across the line from the chosen one, and
    turn a little more or less. The chosen fit's origin and angle sigma cover the widest of them
    (a rival given with its axis the other way round is read along the chosen axis); a sigma
    already wider stays, and no axis warning is added when the axis sigma does not grow."""
    from sparseart.joints.candidates import tied_spread, widen_for_tied_hinges

    def hinge(residual: float, axis: list[float], origin: list[float], angle_deg: float) -> JointEstimate:
        estimate = _estimate("revolute", residual, angle_deg=angle_deg)
        estimate.axis = np.asarray(axis, dtype=np.float64)
        estimate.origin = np.asarray(origin, dtype=np.float64)
        estimate.uncertainty = {"axis_deg": 2.0, "origin": 0.003, "angle": np.radians(0.5)}
        return estimate

    chosen = hinge(0.0100, [0, 0, 1], [0.0, 0.0, 0.0], 90.0)
    across = hinge(0.0104, [0, 0, 1], [0.0, 0.03, 0.2], 91.0)            # 0.03 across the line (0.2 along it)
    reversed_rival = hinge(0.0105, [0, 0, -1], [0.01, 0.0, 0.0], -92.0)  # the same motion written backwards
    spread = tied_spread(chosen, [across, reversed_rival])
    assert spread["origin"] == pytest.approx(0.03) and spread["angle"] == pytest.approx(np.radians(2.0))
    assert spread["axis_deg"] == pytest.approx(0.0, abs=1e-6)
    # the slab's mirror (turned the other way about the far edge) is a discrete alternative: its
    # 0.57 and 180 deg stay out of the sigma, its axis counts
    mirror = hinge(0.0101, [0, np.sin(np.radians(3.0)), -np.cos(np.radians(3.0))], [0.57, 0.0, 0.0], 90.0)
    with_mirror = tied_spread(chosen, [across, reversed_rival, mirror])
    assert with_mirror["origin"] == pytest.approx(0.03) and with_mirror["angle"] == pytest.approx(np.radians(2.0))
    assert with_mirror["axis_deg"] == pytest.approx(3.0)
    warnings_before = len(chosen.warnings)
    widen_for_tied_hinges(chosen, spread)
    assert chosen.uncertainty["origin"] == pytest.approx(0.03)
    assert chosen.uncertainty["angle"] == pytest.approx(np.radians(2.0))
    assert chosen.uncertainty["axis_deg"] == 2.0 and len(chosen.warnings) == warnings_before

    wide = hinge(0.0100, [0, 0, 1], [0.0, 0.0, 0.0], 90.0)
    wide.uncertainty["origin"] = 0.1
    widen_for_tied_hinges(wide, spread)
    assert wide.uncertainty["origin"] == 0.1


def _face(rng: np.random.Generator, noise: float = 0.001) -> np.ndarray:
    """A 0.4 x 0.2 face in the z = 0 plane (normal +z), about 3000 points, with depth noise."""
    points = np.column_stack([rng.uniform(-0.2, 0.2, 3000), rng.uniform(-0.1, 0.1, 3000), np.zeros(3000)])
    points[:, 2] += rng.normal(0.0, noise, len(points))
    return points


def _slide(axis: np.ndarray, distance: float) -> JointEstimate:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    transform = np.eye(4)
    transform[:3, 3] = axis * distance
    return JointEstimate(type="prismatic", axis=axis, origin=np.zeros(3), angle=None, distance=distance,
                         transform=transform, uncertainty={"axis_deg": 1.0}, residual=0.001, confidence=0.9)


def test_a_slide_along_a_given_axis_fits_only_the_distance():
    from sparseart.joints.fit import fit_joint

    rng = np.random.default_rng(0)
    start = _face(rng)
    end = _face(rng) + np.array([0.0, 0.0, 0.2])
    tilted = np.array([0.0, np.sin(np.radians(20.0)), np.cos(np.radians(20.0))])
    held = fit_joint(start, end, joint_type="prismatic", slide_axis=tilted * 3.0)
    assert np.allclose(held.axis, tilted, atol=1e-12)             # the direction is held exactly (unit)
    assert held.diagnostics["slide_axis_held"] is True
    assert "ill_conditioned" not in held.diagnostics["warning_codes"]   # the held tangents are no defect
    true = fit_joint(start, end, joint_type="prismatic", slide_axis=[0.0, 0.0, 1.0])
    assert abs(true.distance - 0.2) < 0.005
    assert true.residual < held.residual                           # the wrong direction fits worse
    with pytest.raises(ValueError, match="slide_axis"):
        fit_joint(start, end, joint_type="auto", slide_axis=[0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="slide_axis"):
        fit_joint(start, end, joint_type="prismatic", slide_axis=[0.0, 0.0, 0.0])


def test_front_normal_needs_one_face_seen_alike_in_both_states():
    from sparseart.joints.candidates import front_normal

    rng = np.random.default_rng(1)
    start, end = _face(rng), _face(rng) + np.array([0.0, 0.0, 0.2])
    normal, disagreement = front_normal(start, end, np.array([0.0, 0.3, -1.0]))
    assert np.degrees(np.arccos(min(1.0, -normal[2]))) < 1.0       # oriented along the given direction
    assert disagreement < 1.0
    # a pane sliding within its face: the normal is perpendicular to the slide, and the two
    # states' normals must not cancel when averaged
    for k in range(8):     # (each state's plane fit picks either sign of its normal)
        pane_end = _face(np.random.default_rng(10 + k)) + np.array([0.15, 0.0, 0.0])
        pane, _ = front_normal(start, pane_end, np.array([1.0, 0.0, 0.0]), seed=k)
        assert abs(pane[2]) > 0.999
    # two views of the start that read the face 8 deg apart (each view's own depth warp): the
    # fused normal is not trusted when the views are known, and is without them
    tilted = _face(rng) @ Rotation.from_euler("y", 8.0, degrees=True).as_matrix().T
    fused = np.concatenate([start[:1500], tilted[:1500]])
    views = np.repeat([0, 1], 1500)
    assert front_normal(fused, end, np.array([0.0, 0.0, 1.0]), start_views=views,
                        end_views=np.zeros(len(end), dtype=int)) is None
    assert front_normal(fused, end, np.array([0.0, 0.0, 1.0])) is not None
    agreeing = front_normal(start, end, np.array([0.0, 0.0, 1.0]), start_views=np.arange(len(start)) % 2,
                            end_views=np.arange(len(end)) % 3)
    assert agreeing is not None and agreeing[1] < 2.0
    blob = rng.normal(0.0, 0.1, (3000, 3))                          # no dominant plane
    assert front_normal(blob, blob + 0.2, np.array([0.0, 0.0, 1.0])) is None
    turned = end @ Rotation.from_euler("x", 10.0, degrees=True).as_matrix().T   # the face turned: no slide
    assert front_normal(start, turned, np.array([0.0, 0.0, 1.0])) is None


def _open_drawer(rng: np.random.Generator, front_points: int, slide: float = 0.2) -> np.ndarray:
    """An open drawer slid by ``slide`` along +z: ``front_points`` of its front (the ``_face``
    plane, moved), 1300 of its bottom (y = -0.1) and 900 of a side (x = 0.2) behind the front."""
    front = _face(rng)[:front_points] + np.array([0.0, 0.0, slide])
    bottom = np.column_stack([rng.uniform(-0.2, 0.2, 1300), np.full(1300, -0.1), rng.uniform(0.0, slide, 1300)])
    side = np.column_stack([np.full(900, 0.2), rng.uniform(-0.1, 0.1, 900), rng.uniform(0.0, slide, 900)])
    box = np.concatenate([bottom, side])
    box += rng.normal(0.0, 0.001, box.shape)
    return np.concatenate([front, box])


def test_front_normal_reads_the_face_of_an_open_drawer_from_its_closed_state():
    """Closed, a drawer shows its front alone; open, its box outweighs the front (here the front
    holds 27 % of the points, the bottom 43 %): the open state's face is read from its points
    facing like the closed front, in either order of the states; a box without its front gives none."""
    from sparseart.joints.candidates import front_normal

    rng = np.random.default_rng(3)
    closed, opened = _face(rng), _open_drawer(rng, 800)
    for start, end in ((closed, opened), (opened, closed)):
        found = front_normal(start, end, np.array([0.0, 0.2, 1.0]))
        assert found is not None
        normal, disagreement = found
        assert np.degrees(np.arccos(min(1.0, normal[2]))) < 1.0 and disagreement < 2.0
    # the views of the open state are not read (they see too little of the front), the closed one's are
    views = np.arange(len(closed)) % 2
    assert front_normal(closed, opened, np.array([0.0, 0.0, 1.0]), start_views=views,
                        end_views=np.arange(len(opened)) % 3) is not None
    assert front_normal(closed, _open_drawer(rng, 0), np.array([0.0, 0.0, 1.0])) is None     # no front
    assert front_normal(closed, _open_drawer(rng, 300), np.array([0.0, 0.0, 1.0])) is None   # 12 %: too little


def test_a_face_that_kept_its_normal_seeds_a_slide_by_the_face_shift():
    """All of a drawer's seed motions can turn (its front laid onto its box's bottom); a face that
    kept its normal did not turn, so it seeds a slide along the normal by how far the face moved
    (not by the centroids', which the open box drags back); a turned face seeds none."""
    from sparseart.joints.candidates import face_slide_seed

    rng = np.random.default_rng(4)
    closed, opened = _face(rng), _open_drawer(rng, 800)
    seed = face_slide_seed(closed, opened)
    assert seed is not None and np.allclose(seed[:3, :3], np.eye(3))
    assert np.allclose(seed[:3, 3], [0.0, 0.0, 0.2], atol=0.01)
    assert (opened.mean(axis=0) - closed.mean(axis=0))[2] < 0.15          # what the centroids say
    back = face_slide_seed(opened, closed)
    assert back is not None and np.allclose(back[:3, 3], [0.0, 0.0, -0.2], atol=0.01)
    turned = _face(rng) @ Rotation.from_euler("x", 40.0, degrees=True).as_matrix().T + np.array([0.0, 0.0, 0.1])
    assert face_slide_seed(closed, turned) is None


def test_a_slide_tilted_within_its_face_is_taken_along_the_face_normal():
    from sparseart.joints.candidates import along_front_normal
    from sparseart.joints.fit import fit_joint

    rng = np.random.default_rng(2)
    start, end = _face(rng), _face(rng) + np.array([0.0, 0.0, 0.2])
    # a free fit 20 deg off in the face's plane (what a made-up outline does on real input),
    # with the residual such a fit has on real input: about that of the slide along the normal
    tilted = _slide([0.0, np.sin(np.radians(20.0)), np.cos(np.radians(20.0))], 0.21)
    tilted.residual = 1.05 * fit_joint(start, end, joint_type="prismatic", slide_axis=[0.0, 0.0, 1.0]).residual
    held = along_front_normal(tilted, start, end, {})
    assert held is not tilted
    assert np.degrees(np.arccos(min(1.0, held.axis[2]))) < 1.0
    assert abs(held.distance - 0.2) < 0.005
    assert held.diagnostics["free_slide"]["tilt_deg"] == pytest.approx(20.0, abs=1.0)
    assert any("face normal" in w for w in held.warnings)
    # a slide within the face (a window pane, a rack) and one that already follows the normal are kept
    pane_end = _face(rng) + np.array([0.15, 0.0, 0.0])
    pane = _slide([1.0, 0.0, 0.0], 0.15)
    assert along_front_normal(pane, start, pane_end, {}) is pane
    straight = _slide([0.0, np.sin(np.radians(1.0)), np.cos(np.radians(1.0))], 0.2)
    assert along_front_normal(straight, start, end, {}) is straight
    # a face whose outline does fix a slide 20 deg off its normal (clean points, the free fit
    # lays it far better than a slide along the normal would): the data's answer stays
    oblique = np.array([0.0, np.sin(np.radians(20.0)), np.cos(np.radians(20.0))])
    oblique_end = _face(rng) + 0.2 * oblique
    free = fit_joint(start, oblique_end, joint_type="prismatic", slide_axis=oblique)
    assert along_front_normal(free, start, oblique_end, {}) is free
    turn = _slide([0.0, 0.0, 1.0], 0.2)
    turn.type, turn.distance, turn.angle = "revolute", None, 0.3
    assert along_front_normal(turn, start, end, {}) is turn


def test_a_slide_that_does_not_fix_its_direction_takes_its_face_normal_from_farther_off():
    """A free slide 40 deg off its face's normal is kept while its own sigma says the data fix
    it (an oblique face, a toaster lever's); the same slide stated +-15 deg (a rival direction
    fits as well) gives way to the face normal."""
    from sparseart.joints.candidates import along_front_normal
    from sparseart.joints.fit import fit_joint

    rng = np.random.default_rng(4)
    start, end = _face(rng), _face(rng) + np.array([0.0, 0.0, 0.2])
    normal_residual = fit_joint(start, end, joint_type="prismatic", slide_axis=[0.0, 0.0, 1.0]).residual
    sure = _slide([0.0, np.sin(np.radians(40.0)), np.cos(np.radians(40.0))], 0.26)
    sure.residual = 1.05 * normal_residual
    assert along_front_normal(sure, start, end, {}) is sure
    unsure = _slide([0.0, np.sin(np.radians(40.0)), np.cos(np.radians(40.0))], 0.26)
    unsure.residual, unsure.uncertainty["axis_deg"] = 1.05 * normal_residual, 15.0
    held = along_front_normal(unsure, start, end, {})
    assert held is not unsure
    assert np.degrees(np.arccos(min(1.0, held.axis[2]))) < 1.0
    assert held.diagnostics["free_slide"]["tilt_deg"] == pytest.approx(40.0, abs=1.0)
    beyond = _slide([0.0, np.sin(np.radians(70.0)), np.cos(np.radians(70.0))], 0.6)   # slides within the face
    beyond.residual, beyond.uncertainty["axis_deg"] = 1.05 * normal_residual, 15.0
    assert along_front_normal(beyond, start, end, {}) is beyond


def test_a_face_read_loosely_is_held_only_where_the_data_cannot_tell_it_from_the_free_slide():
    """A drawer front read 7 deg apart in its two states (smooth depth warps tilt each state's
    face differently): beyond FRONT_STATES_AGREE_DEG, so the face is held only when its slide
    fits within LOOSE_FACE_RESIDUAL_RATIO (1.1) of the free slide's residual -- at 1.05 it is, at
    1.15 (which a face read within 5 deg would take, up to 1.2) the free slide stays -- and the
    free slide lies outside the reading's spread (20 deg off: held; 4 deg off: kept)."""
    from sparseart.joints.candidates import FRONT_STATES_AGREE_DEG, LOOSE_FACE_RESIDUAL_RATIO, along_front_normal
    from sparseart.joints.fit import fit_joint

    rng = np.random.default_rng(6)
    tilt = Rotation.from_rotvec(np.radians(7.0) * np.array([1.0, 0.0, 0.0])).as_matrix()
    start, end = _face(rng), _face(rng) @ tilt.T + np.array([0.0, 0.0, 0.2])
    mean_normal = np.array([0.0, -np.sin(np.radians(3.5)), np.cos(np.radians(3.5))])
    held_residual = fit_joint(start, end, joint_type="prismatic", slide_axis=mean_normal).residual
    assert FRONT_STATES_AGREE_DEG < 7.0 and LOOSE_FACE_RESIDUAL_RATIO < 1.15
    free_axis = [0.0, np.sin(np.radians(20.0)), np.cos(np.radians(20.0))]
    close = _slide(free_axis, 0.21)
    close.residual = held_residual / 1.05
    held = along_front_normal(close, start, end, {})
    assert held is not close
    assert held.diagnostics["free_slide"]["face_states_deg"] == pytest.approx(7.0, abs=1.5)
    assert np.degrees(np.arccos(min(1.0, abs(held.axis @ mean_normal)))) < 1.5
    apart = _slide(free_axis, 0.21)
    apart.residual = held_residual / 1.15
    assert along_front_normal(apart, start, end, {}) is apart
    # a free slide within the reading's spread (4 deg from the mean normal < 7 deg): kept
    within = _slide(Rotation.from_rotvec(np.radians(4.0) * np.array([0.0, 1.0, 0.0])).apply(mean_normal), 0.2)
    within.residual = held_residual / 1.05
    assert along_front_normal(within, start, end, {}) is within


def _slide(axis, residual: float, distance: float = 0.2) -> JointEstimate:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return JointEstimate(type="prismatic", axis=axis, origin=np.zeros(3), angle=None, distance=distance,
                         transform=np.eye(4), uncertainty={}, residual=residual, confidence=1.0)


def test_a_slide_off_every_body_axis_is_refitted_from_them_and_kept_only_in_their_basin():
    """Body-axis re-fits: only for a slide > 10 deg off every axis of the body's frame; a re-fit
    is kept when it fits at least as well and ends nearer its axis than the first fit."""
    axes = np.eye(3)
    first = _slide([np.cos(0.6), np.sin(0.6), 0.0], residual=0.05)        # 34 deg off x, 56 off y
    tried = []

    def attempt(seed: np.ndarray) -> JointEstimate:
        direction = seed[:3, 3] / np.linalg.norm(seed[:3, 3])
        tried.append(direction)
        assert abs(np.linalg.norm(seed[:3, 3]) - 0.2) < 1e-12 and direction @ first.axis >= 0
        if abs(direction[0]) > 0.9:   # from x: settles 8 deg off x, better
            return _slide([np.cos(0.14), np.sin(0.14), 0.0], residual=0.045)
        if abs(direction[1]) > 0.9:   # from y: runs back to the first fit's valley
            return _slide([np.cos(0.55), np.sin(0.55), 0.0], residual=0.049)
        return _slide(direction, residual=0.08)                           # from z: worse
    kept = body_axis_fits(first, axes, attempt)
    assert len(tried) == 3
    assert len(kept) == 1 and np.degrees(np.arccos(kept[0].axis[0])) < 9.0
    assert "static body's axis" in kept[0].warnings[0]
    tried.clear()
    assert body_axis_fits(_slide([np.cos(0.1), np.sin(0.1), 0.0], 0.05), axes, attempt) == []   # 6 deg off x
    assert body_axis_fits(first, None, attempt) == [] and not tried
    turn = _slide([0.0, 0.0, 1.0], 0.05)
    turn.type = "revolute"
    assert body_axis_fits(turn, axes, attempt) == [] and not tried


def test_the_body_axes_follow_the_faces_not_what_else_the_static_part_holds():
    """The static body's frame comes from its faces: a cabinet with a ramp beside it (which tilts
    the principal axes) still gives the cabinet's axes."""
    rng = np.random.default_rng(4)
    faces = []
    size = np.array([1.0, 0.6, 0.8])
    for axis in range(3):
        for side in (-0.5, 0.5):
            face = rng.uniform(-0.5, 0.5, size=(1500, 3)) * size
            face[:, axis] = side * size[axis]
            faces.append(face)
    clutter = np.column_stack([rng.uniform(0.5, 2.0, 1500), np.zeros(1500), rng.uniform(-0.4, 0.4, 1500)])
    clutter[:, 1] = 0.6 * (clutter[:, 0] - 0.5) + 0.3          # a ramp beside it, along none of its axes
    rotation = Rotation.from_rotvec([0.2, -0.4, 0.3]).as_matrix()
    body = np.concatenate(faces + [clutter]) @ rotation.T
    axes = static_body_axes(body)
    np.testing.assert_allclose(np.abs(axes.T @ rotation).max(axis=1), 1.0, atol=0.01)
    centred = body - body.mean(axis=0)
    principal = np.linalg.eigh(centred.T @ centred)[1]
    assert np.abs(principal.T @ rotation).max(axis=1).min() < 0.99     # the principal axes are tilted
    assert static_body_axes(body[:40]) is None and static_body_axes(None) is None


def test_the_cameras_overrule_the_attachment_among_turns_that_fit_alike():
    """Of turns that fit alike, one the cameras contradict (its part moved where they saw empty
    space) drops out before the attachment rule: the less attached turn the views accept wins; with
    no views, or views contradicting both alike, the attachment decides as before."""
    from sparseart.joints.candidates import choose_fit

    rng = np.random.default_rng(0)
    static = np.column_stack([np.zeros(400), rng.uniform(-1, 1, 400), rng.uniform(-1, 1, 400)])  # a wall x = 0
    part = np.column_stack([rng.uniform(0.1, 0.5, 200), rng.uniform(-0.2, 0.2, 200), np.zeros(200)])
    on_wall, off_wall = _estimate("revolute", 0.0110, angle_deg=60.0), _estimate("revolute", 0.0100, angle_deg=70.0)
    for estimate, origin in ((on_wall, [0.0, 0.0, 0.0]), (off_wall, [0.3, 0.0, 0.0])):
        estimate.axis, estimate.origin = np.array([0.0, 0.0, 1.0]), np.asarray(origin)
        estimate.transform = np.eye(4)
        estimate.transform[0, 3] = origin[0]          # a tag the fake test below reads
    assert choose_fit([on_wall, off_wall], part, static) is on_wall

    def seen_through(transform: np.ndarray) -> float:
        return 0.32 if transform[0, 3] == 0.0 else 0.08

    assert choose_fit([on_wall, off_wall], part, static, seen_through) is off_wall
    assert choose_fit([on_wall, off_wall], part, static, lambda transform: 0.2) is on_wall
    # a slab's mirror (turning the other way about its mid-line) is not judged against the hinge:
    # the hinge's line may sit beside the true one until the free-space search moves it
    mirror = _estimate("revolute", 0.0100, angle_deg=-110.0)
    mirror.axis, mirror.origin = np.array([0.0, 0.0, 1.0]), np.array([0.3, 0.0, 0.0])
    mirror.transform = np.eye(4)
    mirror.transform[0, 3] = 0.5
    assert choose_fit([on_wall, mirror], part, static, lambda t: 0.32 if t[0, 3] == 0.0 else 0.05) is on_wall


def test_the_cameras_overrule_a_slide_that_fits_a_turned_handle_alike():
    """A handle whose round cap stays on itself: standing still (a tiny slide) fits the cap as well
    as the true turn and wins on the residual, but leaves the turned lever where the other state's
    cameras saw empty space; the physical test drops it, across types. Without views the residual
    decides as before; a turn contradicted more than a comparable slide drops out likewise."""
    from sparseart.joints.candidates import choose_fit

    rng = np.random.default_rng(1)
    part = rng.normal(size=(200, 3))
    still, turned = _estimate("prismatic", 0.0090), _estimate("revolute", 0.0092, angle_deg=73.0)
    still.transform, turned.transform = np.eye(4), np.eye(4)
    turned.transform[0, 3] = 1.0                                  # a tag the fake test below reads

    def seen_through(transform: np.ndarray) -> float:
        return 0.02 if transform[0, 3] == 1.0 else 0.14

    assert choose_fit([still, turned], part, None) is still
    assert choose_fit([still, turned], part, None, seen_through) is turned
    assert choose_fit([still, turned], part, None, lambda transform: 0.3 - seen_through(transform)) is still
    assert choose_fit([still, turned], part, None, lambda transform: 0.05) is still
