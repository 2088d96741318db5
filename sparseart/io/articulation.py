"""Serialisation of an :class:`~sparseart.types.Articulation` (design section 3)."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from sparseart.io.scene import write_json_atomic
from sparseart.types import Articulation, JointEstimate

SCHEMA = "sparseart/articulation/1"


def _finite(value: float | None) -> float | None:
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def joint_to_dict(part_id: int, parent: int, joint: JointEstimate) -> dict[str, Any]:
    """One joint entry of articulation.json; non-finite numbers become null, never NaN."""
    entry: dict[str, Any] = {
        "part": part_id,
        "parent": parent,
        "type": joint.type,
        "axis": [float(v) for v in np.asarray(joint.axis, dtype=np.float64)],
        "origin": [float(v) for v in np.asarray(joint.origin, dtype=np.float64)],
    }
    if joint.type == "revolute":
        entry["angle"] = _finite(joint.angle)
        entry["slide"] = _finite(joint.slide)
    else:
        entry["distance"] = _finite(joint.distance)
    entry["uncertainty"] = {k: _finite(v) for k, v in joint.uncertainty.items()}
    entry["residual"] = _finite(joint.residual)
    entry["confidence"] = _finite(joint.confidence)
    entry["evidence"] = joint_evidence(joint)
    if "refine" in joint.diagnostics:  # the refinement stage's before/after values and seconds
        entry["refine"] = _jsonable(joint.diagnostics["refine"])
    return entry


# What a joint's evidence holds: diagnostics key -> articulation.json key
EVIDENCE_KEYS = {"bic_revolute": "bic_revolute", "bic_prismatic": "bic_prismatic",
                 "angle_significant": "angle_significant", "free_space_violation": "free_space_violation",
                 "blocked_share": "blocked_share", "pairing_confidence": "pairing_confidence"}


def joint_evidence(joint: JointEstimate) -> dict[str, Any]:
    """Why this joint: ``type_reason`` (the type test's reading: both hypotheses' BIC -- lower is
    better -- and whether the turn is significant, or the search step that set the type), the
    share of the moved part the cameras saw through (``free_space_violation``,
    :mod:`sparseart.joints.free_space_check`), the share its turn pushes into the static part
    (``blocked_share``), the labeler's trust in its pairing; keys absent when not measured."""
    diagnostics = joint.diagnostics
    evidence: dict[str, Any] = {"type_reason": type_reason(joint)}
    evidence.update({out: _jsonable(diagnostics[key]) for key, out in EVIDENCE_KEYS.items() if key in diagnostics})
    return evidence


def type_reason(joint: JointEstimate) -> str:
    """One line: why the joint has its type (the type test's reason and BIC margin, or the
    candidate search's note when the type was not decided by the test)."""
    reason = joint.diagnostics.get("type_reason")
    if reason and joint.diagnostics.get("type_choice", joint.type) == joint.type:
        return str(reason)
    return "set after the fit (a look-alike sibling's slide, or the type given)"


def _jsonable(value: Any) -> Any:
    """Numbers, arrays, dicts and lists as JSON-safe values (non-finite -> None)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return _finite(float(value))
    if value is None or isinstance(value, str):
        return value
    return str(value)


def articulation_to_dict(result: Articulation) -> dict[str, Any]:
    """The articulation.json document (schema "sparseart/articulation/1")."""
    return {
        "schema": SCHEMA,
        "frame": {"kind": result.frame_kind, "reference": result.frame_reference, "units": result.units},
        "parts": [{"id": p.spec.id, "role": p.spec.role, "n_points": p.n_points} for p in result.parts],
        "joints": [joint_to_dict(p.spec.id, p.spec.parent if p.spec.parent is not None else 0, j)
                   for p, j in result.joints],
        "stages": [{"name": s.name, "ran": s.ran, "seconds": round(s.seconds, 4), "why": s.why}
                   for s in result.stages],
        "warnings": list(result.warnings),
        # how the views and states were registered (align.scene.registration_report); {} when unknown
        "registration": _jsonable(getattr(result, "registration", None) or {}),
    }


def write_articulation(result: Articulation, out_dir: str | Path) -> Path:
    """Write ``out_dir/articulation.json`` atomically and return its path."""
    path = Path(out_dir) / "articulation.json"
    write_json_atomic(path, articulation_to_dict(result))
    return path


def summary_lines(result: Articulation) -> list[str]:
    """A short human summary: one line per joint, then stage times and warnings."""
    lines = [f"frame: {result.frame_kind} ({result.frame_reference}), units: {result.units}"]
    if not result.joints:
        lines.append("no movable part found")
    for part, joint in result.joints:
        axis = ", ".join(f"{v:+.3f}" for v in joint.axis)
        if joint.type == "revolute":
            amount = (f"angle {math.degrees(joint.angle):.2f} deg "
                      f"± {math.degrees(joint.uncertainty.get('angle', float('nan'))):.2f}")
        else:
            amount = f"distance {joint.distance:.4f} ± {joint.uncertainty.get('distance', float('nan')):.4f}"
        lines.append(f"part {part.spec.id}: {joint.type:9s} axis [{axis}] "
                     f"± {joint.uncertainty.get('axis_deg', float('nan')):.2f} deg, {amount}, "
                     f"origin ± {joint.uncertainty.get('origin', float('nan')):.4f}, "
                     f"confidence {joint.confidence:.2f}")
        lines.append(f"  why {joint.type}: {type_reason(joint)}")
    timing = ", ".join(f"{s.name} {s.seconds:.2f}s" for s in result.stages if s.ran)
    lines.append(f"time: {timing} (total {sum(s.seconds for s in result.stages):.2f}s)")
    lines.extend(f"warning: {w}" for w in result.warnings)
    return lines
