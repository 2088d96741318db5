"""End to end from synthetic clouds: mock labeler and rule-based labeler, both joint types."""
from __future__ import annotations

import numpy as np
import pytest

from sparseart import metrics, run_clouds
from sparseart.labelers import MockLabeler, RuleBasedLabeler

from synthetic import make_clouds

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
