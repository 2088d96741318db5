"""The field's standard articulation metrics (design section 4).

Definitions follow the PARIS / DTA / ArtGS evaluation code (see
``shared/research/peers-and-metrics.md`` section 9), with their known pitfalls fixed:

* every cosine is clipped to ``[-1, 1]`` before ``arccos`` (the reference code can return NaN);
* parallel axes use the point-to-line fallback (PARIS returns 0 for parallel lines, a bug).

Units
-----
* Angles are reported in **degrees**; joint angles passed in are **radians** (design section 3).
* Axis position error and prismatic state error are in **raw object / frame units** (PARIS
  convention). DTA, ArtGS and GaussianArt tables report position error ``x 10``; multiply by 10
  yourself when comparing with them. Prismatic state error has no such factor anywhere.
* Chamfer distance is in **squared** object units (pytorch3d ``chamfer_distance`` convention);
  DTA / ArtGS tables report it ``x 1000``.

All geometry is handled as float64. No function returns NaN for finite input.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

__all__ = [
    "PARALLEL_EPS",
    "SUCCESS_AXIS_DEG",
    "SUCCESS_POSITION",
    "UNMATCHED_AXIS_DEG",
    "axis_angle_error_deg",
    "axis_position_error",
    "point_to_line_distance",
    "rotation_from_axis_angle",
    "revolute_state_error_deg",
    "prismatic_state_error",
    "joint_errors",
    "unmatched_joint_errors",
    "chamfer_distance",
    "sample_mesh_points",
    "chamfer_cost_matrix",
    "match_parts",
    "motion_right",
    "summarise",
]

PARALLEL_EPS = 1e-6
"""Below this ``|a_p x a_g|`` (unit axes) two lines are treated as parallel."""

SUCCESS_AXIS_DEG = 10.0
"""A joint counts as a success when its axis angle error is below this many degrees."""

SUCCESS_STATE_DEG = 10.0
"""A full success also turns to within this many degrees of the true angle ..."""

SUCCESS_STATE_SHARE = 0.1
"""... or slides to within this share of the true travel."""

SUCCESS_POSITION = 0.05
"""The whole motion right also puts a revolute hinge line within this distance of the true one
(raw object units, :func:`axis_position_error`): the line a robot pulls about."""

UNMATCHED_AXIS_DEG = 90.0
"""Axis angle error charged to a ground-truth part that no prediction was matched to."""

_JOINT_TYPES = ("revolute", "prismatic")


# --------------------------------------------------------------------------------------------
# helpers


def _vec3(v: Any, name: str) -> np.ndarray:
    """Return ``v`` as a finite float64 ``(3,)`` array or raise ValueError."""
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,):
        raise ValueError(f"{name} must have 3 components, got shape {np.shape(v)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a.tolist()}")
    return a


def _unit(v: Any, name: str) -> np.ndarray:
    """Return ``v`` normalised to unit length as float64 ``(3,)``; ValueError on a zero vector."""
    a = _vec3(v, name)
    norm = float(np.linalg.norm(a))
    if norm < 1e-12:
        raise ValueError(f"{name} is a zero vector")
    return a / norm


def _acos_deg(c: float) -> float:
    """``deg(arccos(c))`` with ``c`` clipped to ``[-1, 1]``."""
    return math.degrees(math.acos(min(1.0, max(-1.0, float(c)))))


def _scalar(x: Any, name: str) -> float:
    if x is None:
        raise ValueError(f"{name} is missing")
    v = float(x)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    return v


# --------------------------------------------------------------------------------------------
# axis and state errors


def axis_angle_error_deg(axis_pred: Any, axis_gt: Any) -> float:
    """Angle between two joint axes, ignoring direction: ``deg(arccos(|a_p . a_g|))``.

    axis_pred, axis_gt: (3,) direction vectors, any non-zero length (normalised here).
    Returns degrees in ``[0, 90]``. Raises ValueError on a zero or non-finite vector.
    """
    a_p = _unit(axis_pred, "axis_pred")
    a_g = _unit(axis_gt, "axis_gt")
    return _acos_deg(abs(float(a_p @ a_g)))


def point_to_line_distance(point: Any, axis: Any, origin: Any) -> float:
    """Distance from ``point`` (3,) to the infinite line through ``origin`` (3,) along ``axis`` (3,).

    ``|(point - origin) x a_hat|``, in the units of the inputs.
    """
    a = _unit(axis, "axis")
    d = _vec3(point, "point") - _vec3(origin, "origin")
    return float(np.linalg.norm(np.cross(d, a)))


def axis_position_error(axis_pred: Any, origin_pred: Any, axis_gt: Any, origin_gt: Any) -> float:
    """Distance between the predicted and ground-truth joint axes as infinite lines.

    axis_*: (3,) directions (normalised here); origin_*: (3,) a point on each line.
    With unit axes and ``n = a_p x a_g``: ``|n . (o_p - o_g)| / |n|``; when ``|n| < 1e-6``
    (parallel or antiparallel) the point-to-line distance ``|(o_g - o_p) x a_p|``.

    Returned in **raw object units** (PARIS convention). DTA / ArtGS / GaussianArt report
    ``10 x`` this value (decimetres when the object is in metres, not centimetres).
    """
    a_p = _unit(axis_pred, "axis_pred")
    a_g = _unit(axis_gt, "axis_gt")
    o_p = _vec3(origin_pred, "origin_pred")
    o_g = _vec3(origin_gt, "origin_gt")
    n = np.cross(a_p, a_g)
    n_norm = float(np.linalg.norm(n))
    if n_norm < PARALLEL_EPS:
        return float(np.linalg.norm(np.cross(o_g - o_p, a_p)))
    return float(abs(float(n @ (o_p - o_g))) / n_norm)


def rotation_from_axis_angle(axis: Any, angle: float) -> np.ndarray:
    """Rotation matrix of ``angle`` radians, right-handed about ``axis``.

    axis: (3,) direction (normalised here). Returns (3, 3) float64 (scipy ``Rotation``).
    """
    a = _unit(axis, "axis")
    return Rotation.from_rotvec(a * _scalar(angle, "angle")).as_matrix().astype(np.float64)


def revolute_state_error_deg(axis_pred: Any, angle_pred: float, axis_gt: Any, angle_gt: float) -> float:
    """Geodesic distance between the full start->end rotations, in degrees.

    ``deg(arccos(clip((tr(R_p R_g^T) - 1) / 2, -1, 1)))`` with ``R = R(axis, angle)``.
    axis_*: (3,) directions; angle_*: radians. Returns degrees in ``[0, 180]``. Because the
    whole rotation is compared, axis-direction error is included, and a flipped axis with a
    negated angle is the same motion (error 0). Round-off near 0 is about 1e-6 degrees.
    """
    r_p = rotation_from_axis_angle(axis_pred, angle_pred)
    r_g = rotation_from_axis_angle(axis_gt, angle_gt)
    return _acos_deg((float(np.trace(r_p @ r_g.T)) - 1.0) / 2.0)


def prismatic_state_error(axis_pred: Any, distance_pred: float, axis_gt: Any, distance_gt: float) -> float:
    """``|t_p - t_g|`` with ``t = distance * a_hat``: error of the start->end translations.

    axis_*: (3,) directions (normalised here); distance_*: frame units. Returns frame units
    (no x10 in any reference). A flipped axis with a negated distance gives 0.
    """
    t_p = _unit(axis_pred, "axis_pred") * _scalar(distance_pred, "distance_pred")
    t_g = _unit(axis_gt, "axis_gt") * _scalar(distance_gt, "distance_gt")
    return float(np.linalg.norm(t_p - t_g))


# --------------------------------------------------------------------------------------------
# whole joints


def _field(joint: Any, key: str) -> Any:
    """Read ``key`` from a joint given as a mapping (articulation.json) or an object (JointEstimate)."""
    if isinstance(joint, Mapping):
        return joint.get(key)
    return getattr(joint, key, None)


def _joint_type(joint: Any, name: str) -> str:
    t = _field(joint, "type")
    if t not in _JOINT_TYPES:
        raise ValueError(f"{name} joint type must be one of {_JOINT_TYPES}, got {t!r}")
    return str(t)


def joint_errors(pred: Any, gt: Any) -> dict[str, Any]:
    """Errors of one predicted joint against its ground-truth joint.

    pred, gt: joints as in design section 3: ``{"type": "revolute"|"prismatic", "axis": (3,),
    "origin": (3,), "angle": radians}`` or ``{..., "distance": frame units}``. Objects with the
    same attribute names (e.g. ``sparseart.types.JointEstimate``) are accepted too.

    Returns a dict:

    * ``type_correct``: bool.
    * ``axis_deg``: axis angle error in degrees, ``[0, 90]`` (always computed).
    * ``position``: revolute ground truth only, raw object units; ``None`` for prismatic gt.
      Revolute prediction: distance between the two axis lines. Prismatic prediction (it has no
      axis line): distance from the ground-truth axis line to the predicted origin point.
    * ``state``: revolute gt -> degrees, prismatic gt -> frame units.
      Same types: :func:`revolute_state_error_deg` / :func:`prismatic_state_error`.
      Revolute gt, prismatic prediction: scored as a predicted rotation of angle 0, i.e. the
      geodesic angle of ``R_g`` alone (= ``|angle_gt|`` in degrees for ``|angle_gt| <= pi``).
      Prismatic gt, revolute prediction: scored as a predicted translation of 0, i.e.
      ``|t_g| = |distance_gt|``. In both cases the wrong-type prediction is charged the whole
      ground-truth motion, and the state stays in the ground truth's unit.
    * ``state_along``: same types only (else None): the angle (degrees) or slide (frame units)
      alone, each read along its own axis (a predicted axis the other way round negates its
      state): the quantity the stated ``state_sigma`` is about. ``state`` compares whole motions,
      so it also carries the axis error (a 55 deg turn about an axis 2.9 deg off is 2.7 deg away
      at the right angle; a 0.3 slide 3 deg off, 0.016).
    * ``gt_type``, ``pred_type``: the two type strings; ``unmatched``: False.
    """
    t_p = _joint_type(pred, "pred")
    t_g = _joint_type(gt, "gt")
    a_p = _unit(_field(pred, "axis"), "pred axis")
    a_g = _unit(_field(gt, "axis"), "gt axis")
    o_p = _vec3(_field(pred, "origin"), "pred origin")
    o_g = _vec3(_field(gt, "origin"), "gt origin")

    axis_deg = axis_angle_error_deg(a_p, a_g)
    position: float | None
    state_along: float | None = None
    sign = 1.0 if float(a_p @ a_g) >= 0 else -1.0
    if t_g == "revolute":
        angle_g = _scalar(_field(gt, "angle"), "gt angle")
        if t_p == "revolute":
            position = axis_position_error(a_p, o_p, a_g, o_g)
            angle_p = _scalar(_field(pred, "angle"), "pred angle")
            state = revolute_state_error_deg(a_p, angle_p, a_g, angle_g)
            state_along = float(np.degrees(abs(sign * angle_p - angle_g)))
        else:
            position = point_to_line_distance(o_p, a_g, o_g)
            state = revolute_state_error_deg(a_g, 0.0, a_g, angle_g)
    else:
        dist_g = _scalar(_field(gt, "distance"), "gt distance")
        position = None
        if t_p == "prismatic":
            dist_p = _scalar(_field(pred, "distance"), "pred distance")
            state = prismatic_state_error(a_p, dist_p, a_g, dist_g)
            state_along = abs(sign * dist_p - dist_g)
        else:
            state = abs(dist_g)
    return {
        "type_correct": t_p == t_g,
        "axis_deg": float(axis_deg),
        "position": None if position is None else float(position),
        "state": float(state),
        "state_along": None if state_along is None else float(state_along),
        "gt_state": _true_motion(gt, t_g),
        "gt_type": t_g,
        "pred_type": t_p,
        "unmatched": False,
    }


def _true_motion(gt: Any, gt_type: str) -> float:
    """The ground truth's own motion in the state error's unit: |angle| in degrees (revolute) or
    |distance| in frame units (prismatic)."""
    if gt_type == "revolute":
        return float(abs(np.degrees(_scalar(_field(gt, "angle"), "gt angle"))))
    return float(abs(_scalar(_field(gt, "distance"), "gt distance")))


def unmatched_joint_errors(gt: Any, position_max: float = math.inf, state_max: float | None = None) -> dict[str, Any]:
    """Worst-case errors for a ground-truth joint that no predicted part was matched to.

    gt: joint as in :func:`joint_errors`. ``axis_deg`` = 90, ``type_correct`` = False.
    position_max: charged position for a revolute gt (object units). The default ``inf`` makes
    mean position infinite; pass e.g. the object's bounding-box diagonal for a finite penalty.
    state_max: charged state; default 180 degrees (revolute gt) or ``|distance_gt|`` (prismatic
    gt, as if nothing moved). Same keys as :func:`joint_errors`, ``pred_type`` None,
    ``unmatched`` True.
    """
    t_g = _joint_type(gt, "gt")
    if state_max is None:
        state_max = 180.0 if t_g == "revolute" else abs(_scalar(_field(gt, "distance"), "gt distance"))
    return {
        "type_correct": False,
        "axis_deg": UNMATCHED_AXIS_DEG,
        "position": float(position_max) if t_g == "revolute" else None,
        "state": float(state_max),
        "state_along": None,
        "gt_state": _true_motion(gt, t_g),
        "gt_type": t_g,
        "pred_type": None,
        "unmatched": True,
    }


# --------------------------------------------------------------------------------------------
# geometry: Chamfer and part matching


def _points(p: Any, name: str) -> np.ndarray:
    a = np.asarray(p, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be (N, 3), got shape {a.shape}")
    if a.shape[0] == 0:
        raise ValueError(f"{name} is empty")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains non-finite values")
    return a


def chamfer_distance(points_a: Any, points_b: Any) -> float:
    """Symmetric Chamfer distance (pytorch3d convention).

    points_a: (N, 3), points_b: (M, 3), N, M >= 1.
    ``mean_a min_b |a - b|^2 + mean_b min_a |a - b|^2``: squared L2, mean per direction, the two
    directions added. Squared object units; DTA / ArtGS tables report ``x 1000``.
    """
    a = _points(points_a, "points_a")
    b = _points(points_b, "points_b")
    d_ab, _ = cKDTree(b).query(a, k=1)
    d_ba, _ = cKDTree(a).query(b, k=1)
    return float(np.mean(np.square(d_ab)) + np.mean(np.square(d_ba)))


def sample_mesh_points(vertices: Any, triangles: Any, n: int = 10000, seed: int | None = 0) -> np.ndarray:
    """Sample ``n`` points uniformly by area on a triangle mesh.

    vertices: (V, 3) float; triangles: (F, 3) int vertex indices. Returns (n, 3) float64.
    Triangles are chosen with probability proportional to area, then a uniform point inside
    each (``sqrt`` barycentric trick). Deterministic for a given ``seed``.
    Raises ValueError for an empty mesh or one of zero total area.
    """
    v = _points(vertices, "vertices")
    f = np.asarray(triangles)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"triangles must be (F, 3) with F >= 1, got shape {f.shape}")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError("triangles index outside vertices")
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=1)
    total = float(area.sum())
    if not total > 0.0:
        raise ValueError("mesh has zero total area")
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(f), size=n, p=area / total)
    u = rng.random(n)
    w = rng.random(n)
    s = np.sqrt(u)
    b0 = 1.0 - s
    b1 = s * (1.0 - w)
    b2 = s * w
    return b0[:, None] * p0[idx] + b1[:, None] * p1[idx] + b2[:, None] * p2[idx]


def chamfer_cost_matrix(pred_parts: Sequence[Any], gt_parts: Sequence[Any]) -> np.ndarray:
    """(P, G) float64 matrix of :func:`chamfer_distance` between each predicted and gt part.

    pred_parts, gt_parts: sequences of (N_i, 3) point arrays. Feed it to :func:`match_parts`.
    """
    cost = np.empty((len(pred_parts), len(gt_parts)), dtype=np.float64)
    for i, p in enumerate(pred_parts):
        for j, g in enumerate(gt_parts):
            cost[i, j] = chamfer_distance(p, g)
    return cost


def match_parts(cost: Any) -> tuple[list[tuple[int, int]], list[int]]:
    """Hungarian matching of predicted parts (rows) to ground-truth parts (columns).

    cost: (P, G) float, e.g. :func:`chamfer_cost_matrix` (match on geometry, not on type).
    Rectangular matrices are allowed. ``+inf`` marks a forbidden pair; NaN and ``-inf`` raise
    ValueError.

    Returns ``(matches, unmatched_gt)``: ``matches`` is a list of ``(p_index, g_index)`` sorted
    by ``p_index`` minimising the total cost; ``unmatched_gt`` lists the gt columns left without
    a prediction (more gt parts than predictions, or only forbidden pairs), sorted. Score them
    with :func:`unmatched_joint_errors` (90 degrees / max).
    """
    c = np.asarray(cost, dtype=np.float64)
    if c.ndim != 2:
        raise ValueError(f"cost must be 2-D (P, G), got shape {c.shape}")
    n_pred, n_gt = c.shape
    if n_pred == 0 or n_gt == 0:
        return [], list(range(n_gt))
    if np.any(np.isnan(c)) or np.any(c == -np.inf):
        raise ValueError("cost contains NaN or -inf")
    forbidden = np.isposinf(c)
    if forbidden.any():
        finite = c[~forbidden]
        big = (np.abs(finite).sum() + 1.0) * (1.0 + min(n_pred, n_gt)) if finite.size else 1.0
        c = np.where(forbidden, big, c)
    rows, cols = linear_sum_assignment(c)
    matches = [(int(r), int(g)) for r, g in zip(rows, cols) if not forbidden[r, g]]
    matched_gt = {g for _, g in matches}
    unmatched_gt = [g for g in range(n_gt) if g not in matched_gt]
    return sorted(matches), unmatched_gt


# --------------------------------------------------------------------------------------------
# aggregation


def _stats(values: list[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    a = np.asarray(values, dtype=np.float64)
    return float(np.mean(a)), float(np.median(a))


def _gt_type(e: Mapping[str, Any]) -> str:
    """An error dict's ground-truth type; dicts without ``gt_type`` are revolute when they carry a
    ``position``."""
    return e.get("gt_type") or ("revolute" if e.get("position") is not None else "prismatic")


def covered_share(errors: Sequence[Mapping[str, Any]], error: str, sigma: str, factor: float = 1.0,
                  right_type: bool = True) -> tuple[int, float | None]:
    """(joints judged, share whose ``error`` lies within ``factor`` x their stated ``sigma``) over
    the successful joints (axis below ``SUCCESS_AXIS_DEG``) that carry both keys, and that have
    the right type when ``right_type``; None share when there are none. O(R)."""
    within = [float(e[error]) <= factor * float(e[sigma]) for e in errors
              if e.get(sigma) is not None and e.get(error) is not None
              and (e.get("type_correct") or not right_type) and float(e["axis_deg"]) < SUCCESS_AXIS_DEG]
    return len(within), (sum(within) / len(within) if within else None)


def _fully_right(e: Mapping[str, Any]) -> bool | None:
    """Axis, type and state all right (:func:`summarise`'s ``full_success_rate``); None without
    ``gt_state``."""
    if e.get("gt_state") is None:
        return None
    if not e.get("type_correct") or float(e["axis_deg"]) >= SUCCESS_AXIS_DEG:
        return False
    limit = SUCCESS_STATE_DEG if _gt_type(e) == "revolute" else SUCCESS_STATE_SHARE * float(e["gt_state"])
    return float(e["state"]) < limit


def motion_right(e: Mapping[str, Any]) -> bool | None:
    """The whole motion right (:func:`summarise`'s ``motion_success_rate``): :func:`_fully_right`
    and, for a revolute truth, the hinge line within ``SUCCESS_POSITION`` of the true one (a
    revolute row without ``position`` -- unmatched -- is wrong). None without ``gt_state``."""
    full = _fully_right(e)
    if not full:
        return full
    if _gt_type(e) != "revolute":
        return True
    return e.get("position") is not None and float(e["position"]) < SUCCESS_POSITION


def summarise(errors: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Aggregate per-joint error dicts (from :func:`joint_errors` / :func:`unmatched_joint_errors`).

    Returns a flat dict:

    * ``count``: number of joints; ``n_revolute``, ``n_prismatic`` (by ground-truth type);
      ``n_unmatched``.
    * ``type_accuracy``: fraction with ``type_correct``.
    * ``success_rate``: fraction with ``axis_deg < 10``.
    * ``full_success_rate``: fraction that also has the right type and the state within
      ``SUCCESS_STATE_DEG`` (revolute) or ``SUCCESS_STATE_SHARE`` of the true travel (prismatic):
      the axis alone passes a door turned the wrong way about the right line, or a slide of the
      wrong length. None when a row carries no ``gt_state`` (rows from before it was recorded).
    * ``motion_success_rate``: the whole motion right (:func:`motion_right`): the full success
      and, for revolute joints, the hinge line within ``SUCCESS_POSITION`` object units.
    * ``axis_deg_mean``, ``axis_deg_median``: degrees, over all joints.
    * ``position_mean``, ``position_median``: object units (not x10), over revolute gt joints.
    * ``state_revolute_deg_mean`` / ``_median``: degrees, over revolute gt joints.
    * ``state_prismatic_mean`` / ``_median``: frame units, over prismatic gt joints.
    * ``sigma_coverage``: over the successful joints with a stated axis sigma (``axis_sigma_deg``),
      the fraction whose axis error is within it (honest: ~63 % for the axis angle, the norm of
      two tangent components); ``sigma_count``: how many such joints.
    * ``position_sigma_coverage``: the same for the hinge line's position (``position`` against
      ``origin_sigma``, successful revolute joints of the right type; honest: at least ~63 %, as
      the lines' closest distance is at most the hinge's 2-D offset across the axis).
    * ``state_sigma_coverage``: the same for the angle or slide (``state_along`` against
      ``state_sigma``, successful joints of the right type; honest ~68 %, one component).

    Statistics over an empty set are ``None`` (never NaN). The gt type is read from
    ``gt_type``; dicts without it are taken as revolute when ``position`` is not None.
    """
    n = len(errors)
    axis, pos, st_rev, st_pri = [], [], [], []
    n_type, n_success, n_unmatched = 0, 0, 0
    for e in errors:
        gt_type = _gt_type(e)
        a = float(e["axis_deg"])
        axis.append(a)
        n_success += a < SUCCESS_AXIS_DEG
        n_type += bool(e.get("type_correct", False))
        n_unmatched += bool(e.get("unmatched", False))
        if gt_type == "revolute":
            if e.get("position") is not None:
                pos.append(float(e["position"]))
            st_rev.append(float(e["state"]))
        else:
            st_pri.append(float(e["state"]))
    full = [_fully_right(e) for e in errors]
    motion = [motion_right(e) for e in errors]
    out: dict[str, Any] = {
        "count": n,
        "motion_success_rate": (sum(motion) / n) if n and all(m is not None for m in motion) else None,
        "full_success_rate": (sum(full) / n) if n and all(f is not None for f in full) else None,
        "n_revolute": len(st_rev),
        "n_prismatic": len(st_pri),
        "n_unmatched": n_unmatched,
        "type_accuracy": n_type / n if n else None,
        "success_rate": n_success / n if n else None,
    }
    out["sigma_count"], out["sigma_coverage"] = covered_share(errors, "axis_deg", "axis_sigma_deg", right_type=False)
    out["position_sigma_coverage"] = covered_share(errors, "position", "origin_sigma")[1]
    out["state_sigma_coverage"] = covered_share(errors, "state_along", "state_sigma")[1]
    for key, vals in (("axis_deg", axis), ("position", pos),
                      ("state_revolute_deg", st_rev), ("state_prismatic", st_pri)):
        mean, median = _stats(vals)
        out[f"{key}_mean"] = mean
        out[f"{key}_median"] = median
    return out
