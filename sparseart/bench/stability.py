"""Stability report of the joint fitter (``sparseart bench --stability``).

The stiff and extreme cases of tests/test_stability.py as sweeps: rotation angle 0.5..179 deg,
pivot distance 0.5..20 x the part size, scale 1e-3..1e3, noise 0.05..3 % of the part size and
outlier fraction 0..75 %. Every case fits synthetic partial views of a box-union part (the test
shapes: an L-shaped bracket and a door with a handle; independent surface samples per state,
Gaussian noise) with ``fit_joint(joint_type="auto")`` and records ``metrics.joint_errors``: axis
angle error (deg), axis position error (part units; a prismatic answer: distance of its origin to
the true axis), state error (geodesic deg; a wrong type is charged the whole motion), chosen type,
the Jacobian condition number of the chosen fit and the fitter's warnings.

"Unreliable" is marked with the fitter's OWN warning thresholds (``FitConfig`` and the constants of
``sparseart.joints.fit``, imported here, not copied): rotation below ``small_angle_deg``, pivot
farther than ``far_pivot_factor`` x the part radius (also when a prismatic answer is given to a
motion that turns about such a pivot), condition number above ``ILL_CONDITIONED``, outliers (more
than ``MAX_SCATTER_FRACTION`` of the points off any surface and fewer than ``MIN_INLIER_FRACTION``
landing on the other state under the fit), a stated uncertainty above ``MAX_AXIS_SIGMA_DEG`` /
``MAX_RELATIVE_SIGMA`` of the estimate, a tiny slide, points removed by cleaning. A row is flagged
"!" when one of those warnings fired; the report names the first flagged value of each sweep and,
for comparison, the first value whose axis error exceeds the success threshold (10 deg).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sparseart.joints.fit import (ILL_CONDITIONED, MAX_AXIS_SIGMA_DEG, MAX_RELATIVE_SIGMA, MAX_SCATTER_FRACTION,
                         MIN_INLIER_FRACTION, FitConfig)
from sparseart.bench.metrics import SUCCESS_AXIS_DEG, joint_errors
from sparseart.io.scene import write_bytes_atomic, write_json_atomic

UNRELIABLE_WORDS = ("poorly defined", "ambiguous", "ill-conditioned", "cleaning removed", "fragile",
                    "collinear", "not a pure rotation", "unreliable", "uncertainty large")
VIEWPOINT = np.array([0.4, 0.6, 3.0])
SHAPES = {  # (size, centre) boxes, unit-size parts, asymmetric under 180-degree turns (as in the tests)
    "door": [((0.6, 1.0, 0.05), (0.0, 0.0, 0.0)), ((0.04, 0.2, 0.06), (0.2, 0.1, 0.055))],
    "lshape": [((0.6, 0.12, 0.12), (0.0, 0.0, 0.0)), ((0.12, 0.5, 0.12), (-0.24, 0.31, 0.0)),
               ((0.1, 0.1, 0.3), (0.25, 0.0, 0.2))],
}
LSHAPE_AXIS = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
LSHAPE_ORIGIN = np.array([-0.35, 0.0, 0.1])
DOOR_AXIS = np.array([0.0, 1.0, 0.0])
DOOR_ORIGIN = np.array([-0.3, 0.0, -0.025])


def sample_box_union(shape: str, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(count, 3) area-weighted surface points and (count, 3) outward normals of a SHAPES entry."""
    faces = []
    for size, centre in SHAPES[shape]:
        size, centre = np.asarray(size, float), np.asarray(centre, float)
        for axis in range(3):
            others = [a for a in range(3) if a != axis]
            for sign in (1.0, -1.0):
                faces.append((size[others[0]] * size[others[1]], size, centre, axis, sign))
    areas = np.array([f[0] for f in faces])
    pick = rng.choice(len(faces), count, p=areas / areas.sum())
    points, normals = np.empty((count, 3)), np.zeros((count, 3))
    for index, (_, size, centre, axis, sign) in enumerate(faces):
        rows = pick == index
        local = rng.uniform(-0.5, 0.5, (int(rows.sum()), 3)) * size
        local[:, axis] = sign * size[axis] / 2
        points[rows], normals[rows, axis] = local + centre, sign
    return points, normals


def observe(shape: str, transform: np.ndarray, count: int, noise: float, seed: int,
            partial: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Start and end observations (each (<= count, 3) float64) of a part moved by ``transform``
    (4, 4): independent samples, only faces toward VIEWPOINT when ``partial``, Gaussian ``noise``."""
    rng = np.random.default_rng(seed)
    views = []
    for state_transform in (np.eye(4), transform):
        points, normals = sample_box_union(shape, 3 * count, rng)
        points = points @ state_transform[:3, :3].T + state_transform[:3, 3]
        if partial:
            facing = np.einsum("ij,ij->i", normals @ state_transform[:3, :3].T, VIEWPOINT - points) > 0
            points = points[facing]
        points = points[rng.choice(len(points), min(count, len(points)), replace=False)]
        views.append(points + rng.normal(scale=noise, size=points.shape))
    return views[0], views[1]


@dataclass
class Case:
    sweep: str
    value: float
    unit: str
    shape: str
    joint_type: str
    axis: np.ndarray
    origin: np.ndarray
    amount: float  # radians or part units
    noise: float = 1e-3
    scale: float = 1.0
    outliers: float = 0.0
    partial: bool = True


def cases(quick: bool = False) -> list[Case]:
    """The sweeps. ``quick``: three values per sweep (the extremes and one in between)."""
    angles = [0.5, 1.0, 2.0, 5.0, 30.0, 90.0, 150.0, 170.0, 179.0]
    pivots = [0.5, 2.0, 5.0, 10.0, 20.0]
    scales = [1e-3, 1e-1, 1.0, 1e1, 1e3]
    noises = [0.0005, 0.001, 0.003, 0.01, 0.03]
    outliers = [0.0, 0.1, 0.25, 0.5, 0.75]
    if quick:
        angles, pivots, scales, noises, outliers = ([v[0], v[len(v) // 2], v[-1]]
                                                    for v in (angles, pivots, scales, noises, outliers))
    door = dict(shape="door", joint_type="revolute", axis=DOOR_AXIS, origin=DOOR_ORIGIN, amount=math.radians(35))
    out = [Case("angle", a, "deg", "lshape", "revolute", LSHAPE_AXIS, LSHAPE_ORIGIN, math.radians(a),
                partial=a < 150) for a in angles]
    direction = np.cross(LSHAPE_AXIS, [0.0, 0.0, 1.0])
    direction /= np.linalg.norm(direction)
    out += [Case("pivot", p, "x part size", "lshape", "revolute", LSHAPE_AXIS, -p * direction, math.radians(10))
            for p in pivots]
    out += [Case("scale", s, "x", scale=s, **door) for s in scales]
    out += [Case("noise", n * 100, "% of size", noise=n, **door) for n in noises]
    out += [Case("outliers", f * 100, "% of points", outliers=f, **door) for f in outliers]
    return out


def run_case(case: Case, count: int = 2000, seed: int = 0) -> dict[str, Any]:
    """Fit one case; errors are in part units (divided by ``case.scale``) so sweeps compare."""
    from sparseart.joints import fit_joint, transform_from_revolute

    transform = transform_from_revolute(case.axis, case.origin, case.amount)
    start, end = observe(case.shape, transform, count, case.noise, seed, case.partial)
    if case.outliers > 0:
        rng = np.random.default_rng(seed + 1)
        low = np.minimum(start.min(0), end.min(0)) - 0.3
        high = np.maximum(start.max(0), end.max(0)) + 0.3
        extra = int(round(case.outliers / (1.0 - case.outliers) * len(start))) if case.outliers < 1 else 0
        start = np.concatenate([start, rng.uniform(low, high, (extra, 3))])
        end = np.concatenate([end, rng.uniform(low, high, (extra, 3))])
    estimate = fit_joint(start * case.scale, end * case.scale)
    predicted = {"type": estimate.type, "axis": estimate.axis, "origin": estimate.origin / case.scale,
                 "angle": estimate.angle,
                 "distance": None if estimate.distance is None else estimate.distance / case.scale}
    truth = {"type": case.joint_type, "axis": case.axis, "origin": case.origin, "angle": case.amount}
    errors = joint_errors(predicted, truth)
    row: dict[str, Any] = {"sweep": case.sweep, "value": case.value, "unit": case.unit,
                           "pred_type": estimate.type, "type_correct": errors["type_correct"],
                           "axis_deg": errors["axis_deg"], "position": errors["position"], "state": errors["state"],
                           "condition": float(estimate.diagnostics.get("condition", float("nan"))),
                           "uncertainty_axis_deg": float(estimate.uncertainty.get("axis_deg", float("nan"))),
                           "warnings": list(estimate.warnings)}
    row["flagged"] = (any(word in w for w in estimate.warnings for word in UNRELIABLE_WORDS)
                      or row["condition"] > ILL_CONDITIONED)
    return row


def thresholds() -> dict[str, Any]:
    """The fitter's warning thresholds that define "unreliable" here."""
    config = FitConfig()
    return {"small_angle_deg": config.small_angle_deg, "far_pivot_factor": config.far_pivot_factor,
            "ill_conditioned": ILL_CONDITIONED, "few_points": config.few_points,
            "max_scatter_fraction": MAX_SCATTER_FRACTION, "min_inlier_fraction": MIN_INLIER_FRACTION,
            "max_axis_sigma_deg": MAX_AXIS_SIGMA_DEG,
            "max_relative_sigma": MAX_RELATIVE_SIGMA,
            "min_angle_deg (type test)": config.min_angle_deg, "angle_z (type test)": config.angle_z}


def format_report(rows: list[dict[str, Any]]) -> str:
    """Table per sweep with the flagged rows marked "!" and the two boundaries named."""
    lines = ["thresholds (from the fitter's warnings): "
             + ", ".join(f"{k} {v:g}" for k, v in thresholds().items()),
             f"{'sweep':9s} {'value':>9s} {'unit':12s} {'type':9s} {'axis°':>7s} {'±σ°':>7s} {'pos':>8s} "
             f"{'state°':>8s} {'cond':>9s}  flag warnings"]
    for sweep in dict.fromkeys(r["sweep"] for r in rows):
        group = [r for r in rows if r["sweep"] == sweep]
        for r in group:
            position = "-" if r["position"] is None else f"{r['position']:.4f}"
            state = "-" if r["state"] is None else f"{r['state']:.3f}"
            short = "; ".join(w.split(":")[-1].strip()[:40] for w in r["warnings"])
            lines.append(f"{sweep:9s} {r['value']:9.4g} {r['unit']:12s} {r['pred_type']:9s} {r['axis_deg']:7.3f} "
                         f"{r['uncertainty_axis_deg']:7.3f} {position:>8s} {state:>8s} {r['condition']:9.3g}  "
                         f"{'!' if r['flagged'] else ' ':4s} {short}")
        flagged = [r["value"] for r in group if r["flagged"]]
        failed = [r["value"] for r in group if r["axis_deg"] >= SUCCESS_AXIS_DEG or not r["type_correct"]]
        lines.append(f"  -> {sweep}: warnings flag {flagged or 'none'}; axis >= {SUCCESS_AXIS_DEG:g} deg or "
                     f"wrong type at {failed or 'none'}")
    return "\n".join(lines)


def run_stability(out_dir: str | Path, quick: bool = False, count: int | None = None) -> str:
    """Run every case, write ``stability.txt`` and ``stability.json`` into ``out_dir`` (atomically)
    and return the table. ``quick``: 3 values per sweep, 800 points per state (~20 s on 2 shared
    cores; the full sweep ~2.5 min)."""
    out_dir = Path(out_dir)
    count = count or (800 if quick else 2000)
    rows = [run_case(case, count=count) for case in cases(quick)]
    text = format_report(rows)
    write_bytes_atomic(out_dir / "stability.txt", (text + "\n").encode())
    write_json_atomic(out_dir / "stability.json", {"thresholds": thresholds(), "points_per_state": count,
                                                   "rows": rows})
    return text
