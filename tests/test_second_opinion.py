"""The second opinion on labels found without masks (sparseart.joints.second_opinion): a joint
whose counterpart in a run with another seed is missing, of another type or turned away is
marked (warning, confidence halved, axis sigma raised); a stable one keeps its numbers. And the
pipeline runs it only when the labels come from a motion split."""
from __future__ import annotations

import numpy as np
import pytest

from sparseart.joints.second_opinion import UNSTABLE_DEG, apply_second_opinion
from sparseart.types import JointEstimate, PartLabels, PartResult, PartSpec


def _joint(kind: str, axis, sigma: float = 1.0, confidence: float = 0.6) -> JointEstimate:
    axis = np.asarray(axis, dtype=np.float64)
    return JointEstimate(kind, axis / np.linalg.norm(axis), np.zeros(3), 0.5 if kind == "revolute" else None,
                         None if kind == "revolute" else 0.2, np.eye(4), {"axis_deg": sigma}, 0.001, confidence)


def _labels(ids_start: list[int], ids_end: list[int]) -> PartLabels:
    parts = [PartSpec(0, "static")] + [PartSpec(i, "movable") for i in sorted(set(ids_start) - {0, -1})]
    return PartLabels(parts, np.asarray(ids_start), np.asarray(ids_end))


def _run(joints: dict[int, JointEstimate | None]) -> list[PartResult]:
    return [PartResult(PartSpec(i, "movable"), 10, j) for i, j in joints.items()]


START = [0] * 10 + [1] * 10 + [2] * 10
END = [0] * 10 + [1] * 10 + [2] * 10


def test_stable_joint_keeps_its_confidence_and_its_sigma_reaches_the_labelling_spread():
    """A counterpart 3 deg away (below UNSTABLE_DEG) is no warning, but the gap is a sample of the
    labelling noise: each stated sigma is raised to at least gap / sqrt(2). A sigma already above
    it, or a counterpart that agrees exactly, leaves the sigma as it was."""
    parts = _run({1: _joint("revolute", [0, 0, 1]), 2: _joint("prismatic", [1, 0, 0])})
    parts[0].joint.uncertainty.update(origin=0.01, angle=0.05)
    parts[1].joint.uncertainty.update(origin=0.01, distance=0.005)
    # the second run: same points, axes 3 deg off, part ids swapped (ids are arbitrary); its hinge
    # 0.03 from this axis line (and 0.5 along it, which is the same line), its slide 0.21 and
    # read along an axis given the other way round
    turned = _joint("revolute", [np.sin(np.radians(3)), 0, np.cos(np.radians(3))])
    turned.origin = np.array([0.03, 0.0, 0.5])
    turned.angle = 0.54
    slid = _joint("prismatic", [-1, -0.02, 0])
    slid.distance = -0.21
    other = _run({7: turned, 8: slid})
    other_labels = _labels([0] * 10 + [7] * 10 + [8] * 10, [0] * 10 + [7] * 10 + [8] * 10)
    warnings: list[str] = []
    apply_second_opinion(parts, _labels(START, END), other, other_labels, warnings)
    assert warnings == []
    hinge, slide = parts[0].joint, parts[1].joint
    assert hinge.confidence == 0.6 and slide.confidence == 0.6
    assert hinge.diagnostics["second_opinion"]["axis_deg"] == pytest.approx(3.0, abs=1e-6)
    assert slide.diagnostics["second_opinion"]["type"] == "prismatic"
    root2 = np.sqrt(2.0)
    assert hinge.uncertainty["axis_deg"] == pytest.approx(3.0 / root2)
    assert hinge.uncertainty["origin"] == pytest.approx(0.03 / root2)
    assert hinge.uncertainty["angle"] == 0.05        # above the angles' spread 0.04 / sqrt(2)
    assert hinge.diagnostics["labelling_spread"]["angle"] == pytest.approx(0.04 / root2)
    assert slide.uncertainty["axis_deg"] == 1.0      # above the axes' spread 1.15 / sqrt(2) deg
    assert slide.uncertainty["distance"] == pytest.approx(0.01 / root2)
    assert slide.uncertainty["origin"] == 0.01     # a slide's origin is only where its part starts
    same = _run({1: _joint("revolute", [0, 0, 1])})
    apply_second_opinion(same, _labels(START, END), _run({1: _joint("revolute", [0, 0, 1])}),
                         _labels(START, END), warnings)
    assert same[0].joint.uncertainty["axis_deg"] == 1.0 and warnings == []


def test_turned_missing_or_retyped_counterparts_are_marked():
    parts = _run({1: _joint("revolute", [0, 0, 1], sigma=2.0), 2: _joint("prismatic", [1, 0, 0])})
    far = 2 * UNSTABLE_DEG
    other = _run({1: _joint("revolute", [np.sin(np.radians(far)), 0, np.cos(np.radians(far))])})
    other_labels = _labels(START[:20] + [0] * 10, END[:20] + [-1] * 10)   # part 2 not found again
    warnings: list[str] = []
    apply_second_opinion(parts, _labels(START, END), other, other_labels, warnings)
    turned, missing = parts[0].joint, parts[1].joint
    assert turned.confidence == pytest.approx(0.3) and turned.uncertainty["axis_deg"] == pytest.approx(far)
    assert missing.confidence == pytest.approx(0.3) and missing.uncertainty["axis_deg"] == 90.0
    assert missing.diagnostics["second_opinion"] == {"axis_deg": None, "type": None, "overlap": 0.0}
    assert len(warnings) == 2 and warnings[0].startswith("part 1: unstable without masks")
    retyped = _run({1: _joint("revolute", [0, 0, 1])})
    apply_second_opinion(retyped, _labels(START, END), _run({1: _joint("prismatic", [0, 0, 1])}),
                         _labels(START, END), warnings)
    assert retyped[0].joint.uncertainty["axis_deg"] == 90.0 and "fits it as prismatic" in warnings[-1]


def test_pipeline_runs_it_only_without_masks():
    """Two posed clouds of a box whose lid turns: with masks the labels are the masks' and no
    second labelling runs; without them it runs and records its opinion on the joint."""
    from tests.synthetic import make_clouds

    import sparseart

    start, end, _ = make_clouds("revolute", amount=np.radians(40))
    with_masks = sparseart.run_clouds(start, end)
    assert not next(s for s in with_masks.stages if s.name == "second_opinion").ran
    start.segment[:] = -1
    end.segment[:] = -1
    without = sparseart.run_clouds(start, end)
    stage = next(s for s in without.stages if s.name == "second_opinion")
    assert stage.ran
    joint = next(p.joint for p in without.parts if p.joint is not None)
    assert joint.diagnostics["second_opinion"]["axis_deg"] is not None


def test_the_second_opinion_beside_the_first_labelling_is_the_sequential_one():
    """The second labelling runs in a thread beside the first (pipeline._SecondOpinion): the
    joints come out exactly as a second labelling and fit done afterwards (seed + 1) make them."""
    from tests.synthetic import make_clouds

    import sparseart
    from sparseart.joints.candidates import fit_parts
    from sparseart.joints.fit import FitConfig
    from sparseart.labelers.rules import RuleBasedLabeler, RuleLabelerConfig

    start, end, _ = make_clouds("revolute", amount=np.radians(40))
    start.segment[:] = -1
    end.segment[:] = -1
    threaded = sparseart.run_clouds(start, end)
    plain = sparseart.run_clouds(start, end, second_opinion=False)
    other_labels = RuleBasedLabeler(RuleLabelerConfig(seed=1)).label(plain.start_cloud, plain.end_cloud, None,
                                                                     aligned=True, motion_hints=[], posed=None)
    other_parts = fit_parts(plain.start_cloud, plain.end_cloud, other_labels, joint_type="auto",
                            config=FitConfig(seed=1), warnings=[])
    apply_second_opinion(plain.parts, plain.labels, other_parts, other_labels, [])
    joints = [(p.joint, q.joint) for p, q in zip(threaded.parts, plain.parts) if p.joint is not None]
    assert joints and len(threaded.parts) == len(plain.parts)
    for a, b in joints:
        assert np.array_equal(a.axis, b.axis) and np.array_equal(a.origin, b.origin)
        assert a.uncertainty == b.uncertainty and a.confidence == b.confidence and a.warnings == b.warnings
        assert a.diagnostics["second_opinion"] == b.diagnostics["second_opinion"]
