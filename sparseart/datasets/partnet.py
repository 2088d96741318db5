"""Two-state RGB-D scenes with ground-truth joints from articulated objects (PartNet-Mobility URDFs
or procedural ones): joint-state sampling, camera placement, rendering and gt.json.

gt.json (schema "sparseart/gt/1"), all in the Z-up world frame at the START configuration::

    {"schema": "sparseart/gt/1", "object": name, "frame": "world", "units": "object units",
     "scale": bbox diagonal at start, "static_mask_id": 1,
     "joints": [{"name", "type": "revolute"|"prismatic", "urdf_type", "mask_id", "axis", "origin",
                 "state_start", "state_end", "angle" | "distance", "lower", "upper"}],
     "joint_states": {"start": {name: q}, "end": {name: q}},
     "cameras": {"start": [c2w 4x4, ...], "end": [...]}, "posed": bool, "depth_noise": float,
     "mask_maps": {"start": [{written id: group label}], "end": [...]}   # only when scrambled
    }

Motion semantics: a start point x of the part with ``mask_id`` moves to
``origin + R(axis, angle) (x - origin)`` (revolute) or ``x + distance * axis`` (prismatic).
Revolute origins are the joint pivot; prismatic origins are the part's bbox centre at start.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sparseart.datasets.meshes import ArticulatedObject, RenderMesh, load_articulated_object
from sparseart.datasets.raycast import PreparedScene, render_view
from sparseart.datasets.realism import CLEAN, Realism
from sparseart.datasets.scene_writer import RenderedView, write_scene
from sparseart.datasets.urdf import Joint

GT_SCHEMA = "sparseart/gt/1"
DEFAULT_HFOV_DEG = 55.0


def joint_range(j: Joint) -> tuple[float, float]:
    """(lower, upper) used for sampling; continuous/unlimited revolute -> (0, pi), prismatic -> (0, 0.5)."""
    if j.type == "continuous" or j.lower is None or j.upper is None:
        return (0.0, math.pi) if j.type != "prismatic" else (0.0, 0.5)
    lo, hi = float(j.lower), float(j.upper)
    return (min(lo, hi), max(lo, hi))


MULTI_PART_DOOR_AJAR = 0.3  # fraction of a revolute range at start when several joints move


def sample_joint_states(obj: ArticulatedObject, rng: np.random.Generator,
                        start_fraction: float | None = None, end_fraction: float | None = None,
                        max_angle: float = math.pi / 2) -> tuple[dict[str, float], dict[str, float]]:
    """Start/end values (radians or units) for EVERY movable joint.

    Default: start at lower + U(0, 0.15)*range, end = start + U(0.3, 0.7)*range, revolute changes
    capped at ``max_angle``. ``start_fraction``/``end_fraction`` in [0, 1] of the range override.
    """
    q0: dict[str, float] = {}
    q1: dict[str, float] = {}
    for j in obj.model.movable_joints:
        lo, hi = joint_range(j)
        span = hi - lo
        f0 = rng.uniform(0.0, 0.15) if start_fraction is None else float(start_fraction)
        a = lo + f0 * span
        if end_fraction is not None:
            b = lo + float(end_fraction) * span
        else:
            delta = rng.uniform(0.3, 0.7) * span
            if j.type != "prismatic":
                delta = min(delta, max_angle)
            b = min(a + delta, hi)
        q0[j.name], q1[j.name] = float(a), float(b)
    return q0, q1


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """(4, 4) float64 OpenCV cam_to_world at ``eye`` looking at ``target`` (x right, y down, z fwd)."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight along up
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def intrinsics(width: int, height: int, hfov_deg: float = DEFAULT_HFOV_DEG) -> np.ndarray:
    """(3, 3) float64 pinhole K with square pixels and the principal point at the image centre."""
    f = width / (2.0 * math.tan(math.radians(hfov_deg) / 2.0))
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def _centroid(parts: list[tuple[RenderMesh, int]], label: int) -> np.ndarray | None:
    vs = [m.vertices for m, lab in parts if lab == label]
    return np.concatenate(vs).mean(axis=0) if vs else None


def front_direction(parts0: list[tuple[RenderMesh, int]], parts1: list[tuple[RenderMesh, int]],
                    static_label: int = 1) -> np.ndarray:
    """Unit horizontal (3,) direction the moving parts face / move toward (default -X, the
    PartNet front after the root rpy)."""
    cs = _centroid(parts0, static_label)
    d = np.zeros(3)
    for (m0, lab), (m1, _) in zip(parts0, parts1):
        if lab == static_label:
            continue
        disp = m1.vertices.mean(axis=0) - m0.vertices.mean(axis=0)
        off = m1.vertices.mean(axis=0) - (cs if cs is not None else 0.0)
        for v, w in ((disp, 1.0), (off, 0.5)):
            v = np.array([v[0], v[1], 0.0])
            n = np.linalg.norm(v)
            if n > 1e-9:
                d += w * v / n
    n = np.linalg.norm(d)
    return d / n if n > 1e-6 else np.array([-1.0, 0.0, 0.0])


def best_azimuth(prep0: PreparedScene, prep1: PreparedScene, center: np.ndarray, dist: float,
                 prior: np.ndarray, n_az: int = 16, elevation_deg: float = 30.0) -> float:
    """Azimuth (radians, about world +Z) from which the moving parts are best seen.

    Renders tiny (48 x 36) label images of both states from ``n_az`` azimuths and scores moving-part
    pixels in each state plus twice the pixels whose label changes; ``prior`` (unit (3,)) breaks ties.
    """
    K = intrinsics(48, 36)
    el = math.radians(elevation_deg)
    base = math.atan2(prior[1], prior[0])
    best, best_score = base, -1.0
    for k in range(n_az):
        az = base + 2.0 * math.pi * k / n_az
        eye = center + dist * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                        math.sin(el)])
        c2w = look_at(eye, center)
        l0 = render_view(prep0, K, c2w, 48, 36)[2]
        l1 = render_view(prep1, K, c2w, 48, 36)[2]
        score = ((l0 > 1).sum() + (l1 > 1).sum() + 2.0 * (l0 != l1).sum()
                 + 0.05 * ((l0 > 0).sum() + (l1 > 0).sum())) * (1.0 + 0.1 * math.cos(az - base))
        if score > best_score:
            best, best_score = az, score
    return best


def camera_distance(radius: float, K: np.ndarray, width: int, height: int, fill: float) -> float:
    """Distance at which a sphere of ``radius`` spans ``fill`` of the smaller half field of view."""
    half = min(math.atan(width / 2.0 / K[0, 0]), math.atan(height / 2.0 / K[1, 1]))
    return radius / math.sin(fill * half)


def place_cameras(center: np.ndarray, dist: float, azimuth: float, views: int,
                  rng: np.random.Generator, spread_deg: float = 70.0) -> list[np.ndarray]:
    """``views`` cam_to_world (4, 4) on the upper hemisphere at ``dist`` from ``center``.

    Azimuths (radians about +Z) spread over ``spread_deg`` around ``azimuth`` (jittered +-6 deg),
    elevations 18-40 deg, all looking at ``center``.
    """
    out = []
    for i in range(views):
        frac = 0.0 if views == 1 else (i / (views - 1) - 0.5)
        az = azimuth + math.radians(spread_deg * frac + rng.uniform(-6, 6))
        el = math.radians(rng.uniform(18, 40))
        eye = center + dist * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                        math.sin(el)])
        out.append(look_at(eye, center))
    return out


def gt_joints(obj: ArticulatedObject, q0: dict[str, float], q1: dict[str, float],
              parts0: list[tuple[RenderMesh, int]]) -> list[dict]:
    """Ground-truth joint records (world frame, start configuration) for every movable joint."""
    _, movable = obj.part_groups()
    frames = obj.model.joint_frames(q0)
    out = []
    for g, j in enumerate(movable, start=1):
        F = frames[j.name]
        axis = F[:3, :3] @ j.axis
        axis /= np.linalg.norm(axis)
        lo, hi = joint_range(j)
        rec = {"name": j.name, "type": "prismatic" if j.type == "prismatic" else "revolute",
               "urdf_type": j.type, "mask_id": g + 1, "axis": axis.tolist(),
               "state_start": q0[j.name], "state_end": q1[j.name], "lower": lo, "upper": hi}
        if j.type == "prismatic":
            vs = [m.vertices for m, lab in parts0 if lab == g + 1]
            origin = (0.5 * (np.concatenate(vs).min(0) + np.concatenate(vs).max(0)) if vs
                      else F[:3, 3])
            rec["origin"] = np.asarray(origin, float).tolist()
            rec["distance"] = q1[j.name] - q0[j.name]
        else:
            rec["origin"] = F[:3, 3].tolist()
            rec["angle"] = q1[j.name] - q0[j.name]
        parent_group = obj.part_groups()[0][j.parent]
        rec["parent_mask_id"] = parent_group + 1
        out.append(rec)
    return out


def render_articulated_scene(obj: ArticulatedObject, scene_dir: str | Path,
                             q_start: dict[str, float], q_end: dict[str, float], *, views: int = 3,
                             seed: int = 0, width: int = 320, height: int = 240, posed: bool = True,
                             scramble_masks: bool = False, depth_noise: float = 0.0,
                             write_masks: bool = True, same_cameras: bool = True,
                             hfov_deg: float = DEFAULT_HFOV_DEG, fill: float = 0.95,
                             flying_pixels: float = 0.0, pose_noise_deg: float = 0.0,
                             pose_noise_m: float = 0.0, realism: Realism = CLEAN) -> dict:
    """Render ``obj`` at ``q_start`` and ``q_end`` into ``scene_dir`` (design section 2) + gt.json.

    Mask label = 1 + part group (1 = static base, 2.. = each movable joint's child subtree).
    ``same_cameras=False`` draws fresh camera poses for the end state; ``fill`` is the fraction of
    the smaller half field of view spanned by the bounding sphere. ``flying_pixels`` (fraction of
    depth-edge pixels), ``pose_noise_deg`` (degrees) and ``pose_noise_m`` (object units = metres
    for metric objects) degrade the written scene (see ``scene_writer.write_scene``).
    ``realism`` (``sparseart.datasets.realism``; default clean = the plain raycast, byte-identical
    to renders made without it) adds background, a hand in the end state, depth / image / mask
    degradations, ``conf/`` files and pose error; its levels and draws go to gt.json under
    ``"realism"``. Camera placement never depends on it. Returns the gt dict.
    """
    rng = np.random.default_rng(seed)
    parts0 = obj.posed_parts(q_start)
    parts1 = obj.posed_parts(q_end)
    allv = np.concatenate([m.vertices for m, _ in parts0 + parts1])
    lo, hi = allv.min(0), allv.max(0)
    center = 0.5 * (lo + hi)
    radius = float(np.linalg.norm(allv - center, axis=1).max())
    v0 = np.concatenate([m.vertices for m, _ in parts0])
    scale = float(np.linalg.norm(v0.max(0) - v0.min(0)))
    K = intrinsics(width, height, hfov_deg)
    preps = {"start": PreparedScene(parts0), "end": PreparedScene(parts1)}
    dist = camera_distance(radius, K, width, height, fill)
    az = best_azimuth(preps["start"], preps["end"], center, dist, front_direction(parts0, parts1))
    cams0 = place_cameras(center, dist, az, views, rng)
    cams1 = cams0 if same_cameras else place_cameras(center, dist, az, views, rng)
    rendered = {}
    if realism.is_clean:
        for state, cams in (("start", cams0), ("end", cams1)):
            rendered[state] = [RenderedView(*render_view(preps[state], K, c, width, height), K, c)
                               for c in cams]
        realism_info = None
    else:
        rendered, realism_info = _render_realistic(realism, seed, parts0, parts1, preps,
                                                   {"start": cams0, "end": cams1}, K, width, height, scale)
    gt = {"schema": GT_SCHEMA, "object": obj.name, "frame": "world", "units": "object units",
          "scale": scale, "static_mask_id": 1, "joints": gt_joints(obj, q_start, q_end, parts0),
          "joint_states": {"start": dict(q_start), "end": dict(q_end)}}
    if realism_info is not None:
        gt["realism"] = realism_info
    extra_deg, extra_m = realism.pose_error()
    return write_scene(scene_dir, rendered["start"], rendered["end"], gt, posed=posed,
                       scramble_masks=scramble_masks, depth_noise=depth_noise,
                       write_masks=write_masks, seed=seed, flying_pixels=flying_pixels,
                       pose_noise_deg=pose_noise_deg + extra_deg, pose_noise_m=pose_noise_m + extra_m)


def _render_realistic(realism: Realism, seed: int, parts0: list[tuple[RenderMesh, int]],
                      parts1: list[tuple[RenderMesh, int]], preps: dict[str, PreparedScene],
                      cams: dict[str, list[np.ndarray]], K: np.ndarray, width: int, height: int,
                      scale: float) -> tuple[dict[str, list[RenderedView]], dict]:
    """Raycast both states with the realism geometry (background, end-state hand) and apply the
    per-view knobs. Returns ({state: [RenderedView]}, gt "realism" record)."""
    from sparseart.datasets.realism import degrade_view, scene_extras

    extras, info = scene_extras(realism, seed, parts0, parts1, preps["end"], cams, K, width, height, scale)
    max_label = max(int(lab) for _, lab in parts0 + parts1)
    rendered: dict[str, list[RenderedView]] = {}
    views_info: dict[str, list[dict]] = {}
    for state, parts in (("start", parts0), ("end", parts1)):
        prep = PreparedScene(list(parts) + extras[state]) if extras[state] else preps[state]
        rendered[state], views_info[state] = [], []
        for i, c in enumerate(cams[state]):
            rgb, depth, label = render_view(prep, K, c, width, height)
            v = degrade_view(rgb, depth, label, K, realism, seed, state, i, max_label)
            rendered[state].append(RenderedView(v.rgb, v.depth, v.label, K, c, conf=v.conf,
                                                label_groups=v.label_groups,
                                                true_label=v.true_label if realism.mask_ragged > 0 else None))
            views_info[state].append(v.info)
    record = {"levels": realism.levels(), **info, "views": views_info}
    return rendered, record


def render_partnet_scene(object_dir: str | Path, scene_dir: str | Path, views: int = 3,
                         seed: int = 0, width: int = 320, height: int = 240, posed: bool = True,
                         scramble_masks: bool = False, depth_noise: float = 0.0,
                         write_masks: bool = True, start_fraction: float | None = None,
                         end_fraction: float | None = None, same_cameras: bool = True,
                         flying_pixels: float = 0.0, pose_noise_deg: float = 0.0,
                         pose_noise_m: float = 0.0, realism: Realism = CLEAN) -> dict:
    """Render a PartNet-Mobility object folder (``mobility.urdf`` + meshes) as a two-state scene.

    Every movable joint changes between start and end (see :func:`sample_joint_states`).
    Objects with several movable joints start with their revolute joints at >= 30 % of their
    range (doors ajar), so parts behind a door (an oven's racks) are seen in both states: a part
    hidden in one state cannot be measured from geometry by any method. ``realism``: see
    :func:`render_articulated_scene` (joint states and cameras do not depend on it).
    Raises SceneError naming the file when the URDF or a mesh/texture is missing. Returns the gt.
    """
    obj = load_articulated_object(object_dir)
    rng = np.random.default_rng(seed)
    q0, q1 = sample_joint_states(obj, rng, start_fraction, end_fraction)
    if start_fraction is None and len(obj.model.movable_joints) > 1:
        for joint in obj.model.movable_joints:
            if joint.type != "prismatic":
                lo, hi = joint_range(joint)
                shift = max(0.0, lo + MULTI_PART_DOOR_AJAR * (hi - lo) - q0[joint.name])
                q0[joint.name] += shift
                q1[joint.name] = min(q1[joint.name] + shift, hi)
    return render_articulated_scene(obj, scene_dir, q0, q1, views=views, seed=seed, width=width,
                                    height=height, posed=posed, scramble_masks=scramble_masks,
                                    depth_noise=depth_noise, write_masks=write_masks,
                                    same_cameras=same_cameras, flying_pixels=flying_pixels,
                                    pose_noise_deg=pose_noise_deg, pose_noise_m=pose_noise_m,
                                    realism=realism)
