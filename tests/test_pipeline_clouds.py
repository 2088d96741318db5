"""End to end from synthetic clouds: mock labeler and rule-based labeler, both joint types."""
from __future__ import annotations

import numpy as np
import pytest

from sparseart import run_clouds

from sparseart.bench import metrics
from sparseart.labelers import MockLabeler, RuleBasedLabeler

from synthetic import box_surface, make_clouds

CASES = [("revolute", np.radians(40)), ("revolute", np.radians(-25)), ("prismatic", 0.25)]


def _check(result, truth, axis_tol=1.0, position_tol=0.02) -> None:
    assert len(result.joints) == 1
    _, joint = result.joints[0]
    errors = metrics.joint_errors(joint, truth)
    assert errors["type_correct"], (joint.type, truth["type"])
    assert errors["axis_deg"] < axis_tol, errors
    if truth["type"] == "revolute":
        assert errors["position"] < position_tol, errors
        assert errors["state"] < 1.0, errors
    else:
        assert errors["state"] < 0.01, errors
    assert np.isfinite(list(joint.uncertainty.values())).all()


@pytest.mark.parametrize("kind,amount", CASES)
def test_mock_labeler_auto_type(kind, amount) -> None:
    start, end, truth = make_clouds(kind, amount)
    result = run_clouds(start, end, labeler=MockLabeler({1: 0, 2: 1}))
    _check(result, truth)
    assert [s.name for s in result.stages if s.ran] == ["label", "fit"]


@pytest.mark.parametrize("kind,amount", CASES[1:])
def test_the_type_comes_with_its_reason(kind, amount) -> None:
    """articulation.json and the CLI line say why a joint has its type: the type test's reading
    (both hypotheses' BIC) or the candidate search's residuals, or that the type was given."""
    from sparseart.io.articulation import articulation_to_dict, summary_lines

    start, end, truth = make_clouds(kind, amount)
    result = run_clouds(start, end, labeler=MockLabeler({1: 0, 2: 1}))
    evidence = articulation_to_dict(result)["joints"][0]["evidence"]
    assert evidence["type_reason"] and ("BIC" in evidence["type_reason"] or "residual" in evidence["type_reason"])
    if "bic_revolute" in evidence:
        better = "bic_revolute" if kind == "revolute" else "bic_prismatic"
        worse = "bic_prismatic" if kind == "revolute" else "bic_revolute"
        assert evidence[better] < evidence[worse]
    assert f"  why {kind}: {evidence['type_reason']}" in summary_lines(result)
    given = run_clouds(start, end, labeler=MockLabeler({1: 0, 2: 1}), joint_type=kind)
    assert articulation_to_dict(given)["joints"][0]["evidence"]["type_reason"] == "given by the user (joint_type)"


@pytest.mark.parametrize("kind,amount", CASES)
def test_mock_labeler_known_type_skips_classification(kind, amount) -> None:
    start, end, truth = make_clouds(kind, amount, seed=3)
    result = run_clouds(start, end, labeler=MockLabeler({1: 0, 2: 1}, joint_types={1: kind}))
    _check(result, truth)
    fit = next(s for s in result.stages if s.name == "fit")
    assert "classification skipped" in fit.why


@pytest.mark.parametrize("kind,amount", CASES)
def test_rule_labeler_with_masks(kind, amount) -> None:
    start, end, truth = make_clouds(kind, amount, seed=1)
    result = run_clouds(start, end, labeler=RuleBasedLabeler())
    _check(result, truth)
    labels = result.labels
    # body points are static, panel points belong to the movable part
    assert np.mean(labels.start_part[start.segment == 1] == 0) > 0.95
    assert np.mean(labels.start_part[start.segment == 2] == 1) > 0.95


def test_rule_labeler_ids_disagree_across_states() -> None:
    start, end, truth = make_clouds("revolute", np.radians(30), seed=4)
    end.segment = np.where(end.segment == 1, 7, 5)  # end ids swapped and renamed
    end.segment_source = {7: (0, 7), 5: (0, 5)}
    result = run_clouds(start, end)
    _check(result, truth)
    assert result.labels.end_segment_to_part == {7: 0, 5: 1}


def test_nothing_moved_gives_no_joint() -> None:
    start, _, _ = make_clouds("revolute", 0.5, seed=5)
    end = start.subset(np.arange(len(start)))
    end.state = "end"
    result = run_clouds(start, end)
    assert result.joints == [] and any("no part moved" in w for w in result.warnings)


def _wire_rack(rng: np.random.Generator) -> np.ndarray:
    """A flat wire rack (z = 0): 5 wires along x (0.4 long) every 0.05 in y, 3 cross bars."""
    pieces = []
    for y in np.arange(-0.1, 0.1001, 0.05):
        x = rng.uniform(-0.2, 0.2, 120)
        pieces.append(np.c_[x, np.full_like(x, y), np.zeros_like(x)])
    for x0 in (-0.2, 0.0, 0.2):
        y = rng.uniform(-0.1, 0.1, 60)
        pieces.append(np.c_[np.full_like(y, x0), y, np.zeros_like(y)])
    return np.vstack(pieces)


@pytest.mark.parametrize("seed", [0, 1])
def test_repeated_structure_slide_refit_from_static_axes(seed) -> None:
    """A rack slid 0.25 along x, seeded one wire sideways (the aliased local minimum a labeler can
    hand over): without a static part the fit stays ~11 deg off; with the static box's axes as extra
    seeds the slide is recovered and the re-fit is stated in a warning."""
    from sparseart.joints.candidates import fit_part

    rng = np.random.default_rng(seed)
    start, end = _wire_rack(rng), _wire_rack(rng) + [0.25, 0.0, 0.0]
    static = box_surface([1.0, 0.6, 0.5], [0.0, 0.0, 0.0], 4000, rng)[0]
    aliased = np.eye(4)
    aliased[:3, 3] = [0.25, 0.05, 0.0]
    colours = (np.full((len(start), 3), 0.5), np.full((len(end), 3), 0.5))
    alone = fit_part(start, end, *colours, "auto", [aliased], None)
    assert metrics.axis_angle_error_deg(alone.axis, [1, 0, 0]) > 5.0  # the trap is real
    joint = fit_part(start, end, *colours, "auto", [aliased], static)
    assert joint.type == "prismatic"
    assert metrics.axis_angle_error_deg(joint.axis, [1, 0, 0]) < 1.0
    assert abs(abs(joint.distance) - 0.25) < 0.01
    assert any("static part's axis" in w for w in joint.warnings)


def test_static_axis_seeds_point_along_the_slide() -> None:
    """Seeds: one per static principal axis not within 2 deg of the fitted slide, signed towards it,
    with the slide's length; none for revolute fits or without a static part."""
    from sparseart.joints.candidates import static_axis_seeds
    from sparseart.types import JointEstimate

    rng = np.random.default_rng(0)
    static = box_surface([1.0, 0.6, 0.4], [0.0, 0.0, 0.0], 4000, rng)[0]
    axis = np.array([-np.cos(0.3), np.sin(0.3), 0.0])
    joint = JointEstimate(type="prismatic", axis=axis, origin=np.zeros(3), angle=None, distance=0.2,
                          transform=np.eye(4), uncertainty={}, residual=0.01, confidence=1.0)
    seeds = static_axis_seeds(joint, static)
    assert len(seeds) == 3
    for seed in seeds:
        assert abs(np.linalg.norm(seed[:3, 3]) - 0.2) < 1e-12
        assert seed[:3, 3] @ axis >= 0
    assert static_axis_seeds(joint, None) == []
    centred = static - static.mean(axis=0)
    joint.axis = np.linalg.eigh(centred.T @ centred)[1][:, 2]  # the box's long axis: that seed adds nothing
    assert len(static_axis_seeds(joint, static)) == 2
    joint.type = "revolute"
    assert static_axis_seeds(joint, static) == []


def test_rival_slides_widen_the_axis_uncertainty() -> None:
    """A slide that another direction >= 10 deg away explains within +10 % residual gets its axis
    sigma raised to that angle and a warning; close rivals or worse rivals change nothing."""
    from sparseart.joints.candidates import widen_for_rival_slides
    from sparseart.types import JointEstimate

    def slide(degrees: float, residual: float) -> JointEstimate:
        axis = np.array([np.cos(np.radians(degrees)), np.sin(np.radians(degrees)), 0.0])
        return JointEstimate(type="prismatic", axis=axis, origin=np.zeros(3), angle=None, distance=0.2,
                             transform=np.eye(4), uncertainty={"axis_deg": 0.7, "origin": 0.0, "distance": 0.002},
                             residual=residual, confidence=1.0)

    chosen = slide(0.0, 0.0100)
    widen_for_rival_slides(chosen, [chosen, slide(4.0, 0.0101), slide(30.0, 0.0120)])
    assert chosen.uncertainty["axis_deg"] == 0.7 and not chosen.warnings
    widen_for_rival_slides(chosen, [chosen, slide(18.0, 0.0105)])
    assert chosen.uncertainty["axis_deg"] == pytest.approx(18.0)
    assert "18.0 deg away fits almost as well (residual +5 %)" in chosen.warnings[0]


def test_fallback_base_prefers_the_pair_that_staying_put_explains() -> None:
    """When no pair passed the static test, the base is the pair whose identity score is >= 80 % of
    its registered score (noisy depth: measured laptop base 0.33 vs a spurious motion's 0.38),
    else the largest pair as before."""
    from sparseart.labelers.rules import _fallback_base, _Group

    groups = [_Group(indices=np.arange(30000), segments=[0]), _Group(indices=np.arange(650), segments=[1])]
    lid, base = (0, 0, np.eye(4), 0.69), (1, 1, np.eye(4), 0.38)
    assert _fallback_base([lid, base], groups, {(0, 0): 0.08, (1, 1): 0.33}) is base
    assert _fallback_base([lid, base], groups, {(0, 0): 0.08, (1, 1): 0.20}) is lid   # largest
    assert _fallback_base([lid, base], groups, {}) is lid
