"""Realism knobs for rendered two-state scenes: what a phone + reconstructor + segmenter pipeline
adds on top of a perfect raycast (background clutter, depth warps and smears, holes, a hand on
the moving part, image noise and JPEG, ragged masks, pose error) -- each a named *level*.

A level is a float >= 0: 0 turns the knob off, 1 is the documented default strength (the value
in :data:`KNOB_TABLE`), other values scale it (0.5 = half, 2 = double; at most ``MAX_LEVEL``).
``Realism()`` (the ``clean`` preset) changes nothing: a clean render is byte-identical to a render
made before this module existed. ``PRESETS["realistic"]`` turns every knob on at level 1.

Every random draw comes from a generator seeded by the render seed, one independent stream per
(knob, state, view) (:func:`knob_rng`), so the same seed writes identical files and changing one
knob's level leaves the draws of the others unchanged (one-factor-at-a-time benchmarks stay
comparable). Geometry is float64; images are (H, W[, 3]) with H rows and W columns; depths are
camera-frame z in scene units (metres for metric objects), 0 = invalid.

Where each knob acts (see ``partnet.render_articulated_scene``):

* geometry, raycast with the object: ``background`` (table, floor, wall; mask label 0) and
  ``occluder`` (a hand + forearm on a moving part, END state only; mask label 0);
* per view, after raycasting (:func:`degrade_view`): depth ``edge_smear`` -> ``depth_warp`` ->
  ``depth_scale`` -> ``depth_noise`` (noise, then holes), ``confidence`` (``conf/NNN.npy``),
  rgb ``image_noise`` -> ``jpeg``, masks ``mask_ragged``;
* at writing (``scene_writer.write_scene``): ``pose_noise`` on the written cam_to_world, through
  ``scene_writer.perturb_pose`` with the bench's convention (degrees + object units).
"""
from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields, replace

import cv2
import numpy as np

from sparseart.datasets.meshes import RenderMesh
from sparseart.datasets.raycast import PreparedScene, camera_rays

from sparseart.datasets.knobs import (CONF_JITTER, DEPTH_NOISE_SIGMA, DEPTH_SCALE_SIGMA, DEPTH_WARP_AMPLITUDE,
                                     EDGE_RELATIVE_JUMP, EDGE_SMEAR_PX, EMPTY_BACKGROUND_GAP, FLOOR_LABEL,
                                     GRAZING_DROPOUT_COS, HAND_CLAMP, HAND_FRACTION, HOLE_RADIUS, HOLES_PER_VIEW,
                                     IMAGE_NOISE_SIGMA, JPEG_QUALITY_SLOPE, KNOB_TABLE, MASK_MERGE_P,
                                     MASK_RAGGED_MAX_PX, MASK_RAGGED_PX, MASK_SPLIT_P, MAX_LEVEL, OCCLUDER_LABEL,
                                     POSE_NOISE_DEG, POSE_NOISE_TRANSLATION, RESERVED_LABEL_MIN, TABLE_LABEL,
                                     WALL_LABEL)


@dataclass(frozen=True)
class Realism:
    """Levels of the realism knobs (0 = off, 1 = default strength, see :data:`KNOB_TABLE`).

    background: table + floor + wall around the object (label 0).
    depth_warp: smooth per-view multiplicative depth warp, max ~2 % at 1.
    depth_scale: per-view global depth scale error, sigma 1 % at 1.
    edge_smear: mixed (flying) depths within ~2 px of depth discontinuities.
    depth_noise: per-pixel depth noise (0.5 % at 1) plus holes and grazing dropout.
    confidence: write ``conf/NNN.npy`` (per-pixel depth confidence in [0, 1]).
    occluder: a hand + forearm on a moving part in the end state (label 0).
    image_noise: Gaussian RGB noise, sigma 4 grey levels at 1.
    jpeg: JPEG compression artefacts, quality 70 at 1.
    mask_ragged: frayed mask borders plus occasional id merges and splits.
    pose_noise: written camera pose error, 0.5 deg + 0.005 object units at 1.
    """

    background: float = 0.0
    depth_warp: float = 0.0
    depth_scale: float = 0.0
    edge_smear: float = 0.0
    depth_noise: float = 0.0
    confidence: float = 0.0
    occluder: float = 0.0
    image_noise: float = 0.0
    jpeg: float = 0.0
    mask_ragged: float = 0.0
    pose_noise: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or not 0 <= value <= MAX_LEVEL:
                raise ValueError(f"Realism.{f.name}: level must be a number in [0, {MAX_LEVEL:g}], got {value!r}")
            object.__setattr__(self, f.name, float(value))

    @property
    def is_clean(self) -> bool:
        """True when every knob is off (the render is the plain raycast)."""
        return all(v == 0.0 for v in self.levels().values())

    def levels(self) -> dict[str, float]:
        """{knob name: level} in declaration order."""
        return asdict(self)

    def with_levels(self, **levels: float) -> Realism:
        """A copy with the given knobs changed (unknown names raise TypeError)."""
        return replace(self, **levels)

    def pose_error(self) -> tuple[float, float]:
        """(degrees, object units) of the written pose error at this ``pose_noise`` level."""
        return POSE_NOISE_DEG * self.pose_noise, POSE_NOISE_TRANSLATION * self.pose_noise

    def key(self) -> str:
        """A short folder-name-safe key of the non-zero levels ("" when clean), e.g.
        ``re-bg1-oc0.5``, for render caches (``BenchSetting.render_key``)."""
        parts = [f"{KNOB_ABBREVIATIONS[k]}{v:g}" for k, v in self.levels().items() if v]
        return "re-" + "-".join(parts) if parts else ""

    @property
    def degrades_views(self) -> bool:
        """True when any per-view (image, depth, mask) knob is on."""
        return any(getattr(self, k) > 0 for k in ("depth_warp", "depth_scale", "edge_smear", "depth_noise",
                                                  "confidence", "image_noise", "jpeg", "mask_ragged"))


KNOBS: tuple[str, ...] = tuple(f.name for f in fields(Realism))
KNOB_ABBREVIATIONS = {"background": "bg", "depth_warp": "dw", "depth_scale": "ds", "edge_smear": "es",
                      "depth_noise": "dn", "confidence": "cf", "occluder": "oc", "image_noise": "in",
                      "jpeg": "jp", "mask_ragged": "mr", "pose_noise": "pn"}
CLEAN = Realism()
PRESETS: dict[str, Realism] = {"clean": CLEAN, "realistic": Realism(**{k: 1.0 for k in KNOBS})}


def preset(name: str) -> Realism:
    """The named preset (``clean`` | ``realistic``); ValueError naming the choices otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown realism preset {name!r}; choose one of {', '.join(PRESETS)}") from None


def knob_rng(seed: int, knob: str, *keys: int) -> np.random.Generator:
    """The generator of one knob for one (state, view, ...) key, derived from the render ``seed``.

    Streams are independent across knobs and keys, so each knob's draws do not depend on which
    other knobs are on.
    """
    entropy = [int(seed) % (1 << 63), zlib.crc32(knob.encode()), *(int(k) for k in keys)]
    return np.random.default_rng(np.random.SeedSequence(entropy))


STATE_KEYS = {"start": 0, "end": 1}


# ---- meshes --------------------------------------------------------------------------------------


def _mesh(vertices: np.ndarray, triangles: np.ndarray, color: Sequence[float]) -> RenderMesh:
    t = np.asarray(triangles, dtype=np.int64)
    return RenderMesh(np.asarray(vertices, dtype=np.float64), t, np.tile(np.asarray(color, float), (len(t), 1)))


_BOX_TRIS = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                      [2, 3, 7], [2, 7, 6], [1, 2, 6], [1, 6, 5], [0, 4, 7], [0, 7, 3]], dtype=np.int64)


def oriented_box(center: np.ndarray, axes: np.ndarray, half: Sequence[float],
                 color: Sequence[float]) -> RenderMesh:
    """Box mesh (8 vertices, 12 triangles). center (3,); axes (3, 3) orthonormal COLUMNS;
    half (3,) half sizes along them (scene units); color RGB in [0, 1]."""
    s = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                  [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=np.float64) * np.asarray(half, float)
    return _mesh(np.asarray(center, float) + s @ np.asarray(axes, float).T, _BOX_TRIS, color)


def capsule(a: np.ndarray, b: np.ndarray, radius: float, color: Sequence[float],
            segments: int = 12, rings: int = 4) -> RenderMesh:
    """Closed capsule mesh between end points ``a`` and ``b`` ((3,) scene units) of ``radius``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    axis = b - a
    length = float(np.linalg.norm(axis))
    z = axis / length if length > 1e-12 else np.array([0.0, 0.0, 1.0])
    x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    lat = np.concatenate([np.linspace(0, np.pi / 2, rings + 1)[1:], np.linspace(np.pi / 2, np.pi, rings + 1)[:-1]])
    shift = np.where(np.arange(len(lat)) < rings, 0.5 * length, -0.5 * length)
    phi = 2 * np.pi * np.arange(segments) / segments
    ring_pts = (radius * np.sin(lat)[:, None, None] * (np.cos(phi)[None, :, None] * x + np.sin(phi)[None, :, None] * y)
                + (radius * np.cos(lat) + shift)[:, None, None] * z)
    verts = np.concatenate([(0.5 * length + radius) * z[None], ring_pts.reshape(-1, 3),
                            (-0.5 * length - radius) * z[None]]) + 0.5 * (a + b)
    n_ring, south = len(lat), 1 + len(lat) * segments
    tris = []
    for j in range(segments):
        k = (j + 1) % segments
        tris.append([0, 1 + j, 1 + k])
        tris.append([south, 1 + (n_ring - 1) * segments + k, 1 + (n_ring - 1) * segments + j])
        for i in range(n_ring - 1):
            p, q = 1 + i * segments, 1 + (i + 1) * segments
            tris += [[p + j, q + j, q + k], [p + j, q + k, p + k]]
    return _mesh(verts, np.array(tris), color)


def _smooth_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """(size, size) float64 noise, bicubic from a (cells, cells) N(0, 1) grid, std ~1."""
    coarse = rng.standard_normal((cells, cells)).astype(np.float32)
    out = cv2.resize(coarse, (size, size), interpolation=cv2.INTER_CUBIC).astype(np.float64)
    return out / max(out.std(), 1e-9)


def _texture(kind: str, rng: np.random.Generator, contrast: float, size: int = 128) -> np.ndarray:
    """(size, size, 3) float32 RGB in [0, 1]: ``wood`` grain, floor ``tiles`` (2 x 2 with grout),
    wall ``paint`` (blotches + a few darker rectangles)."""
    u = (np.arange(size) + 0.5) / size
    fine = rng.standard_normal((size, size))
    if kind == "wood":
        base = np.array([0.55, 0.36, 0.2]) * rng.uniform(0.8, 1.2) + rng.uniform(-0.04, 0.04, 3)
        grain = np.sin(2 * np.pi * (5 * u[None, :] + 0.35 * _smooth_noise(rng, size, 6)))
        shade = 1.0 + contrast * (0.12 * grain + 0.03 * fine)
    elif kind == "tiles":
        base = np.array([0.62, 0.6, 0.56]) * rng.uniform(0.75, 1.15) + rng.uniform(-0.05, 0.05, 3)
        tile = (u * 2).astype(int)
        per_tile = rng.uniform(-0.08, 0.08, (2, 2))[tile[:, None], tile[None, :]]
        grout = ((np.abs(u * 2 - np.round(u * 2)) < 0.025)[:, None] | (np.abs(u * 2 - np.round(u * 2)) < 0.025)[None, :])
        shade = 1.0 + contrast * (per_tile + 0.04 * fine - 0.35 * grout)
    elif kind == "paint":
        base = np.array([0.86, 0.84, 0.78]) * rng.uniform(0.85, 1.05) + rng.uniform(-0.05, 0.05, 3)
        shade = 1.0 + contrast * (0.04 * _smooth_noise(rng, size, 5) + 0.015 * fine)
        for _ in range(3):  # pictures / switches: features for matchers
            r0, c0 = rng.integers(0, size - 24, 2)
            h, w = rng.integers(8, 24, 2)
            shade[r0:r0 + h, c0:c0 + w] -= contrast * rng.uniform(0.15, 0.45)
    else:
        raise ValueError(kind)
    return np.clip(base[None, None, :] * shade[:, :, None], 0, 1).astype(np.float32)


def _textured(mesh: RenderMesh, texture: np.ndarray, period: float) -> RenderMesh:
    """``mesh`` with ``texture`` mapped by planar projection along each triangle's dominant
    normal axis, repeating every ``period`` scene units."""
    corners = mesh.vertices[mesh.triangles]                                   # (T, 3, 3)
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    dominant = np.argmax(np.abs(n), axis=1)
    keep = np.array([[1, 2], [0, 2], [0, 1]])[dominant]                        # (T, 2)
    uv = np.take_along_axis(corners, keep[:, None, :].repeat(3, axis=1), axis=2) / period
    kd = np.ones((mesh.n_triangles, 3))
    mean = texture.reshape(-1, 3).mean(axis=0).astype(np.float64)
    return RenderMesh(mesh.vertices, mesh.triangles, np.tile(mean, (mesh.n_triangles, 1)), kd, uv,
                      np.zeros(mesh.n_triangles, np.int64), [texture])


def background_parts(vertices: np.ndarray, cameras: Sequence[np.ndarray], scale: float, level: float,
                     rng: np.random.Generator) -> tuple[list[tuple[RenderMesh, int]], dict]:
    """A table top (+ 4 legs), a floor and a wall behind the object (world Z-up).

    vertices: (N, 3) float64 object vertices of BOTH states (the table covers every footprint).
    cameras: (4, 4) cam_to_world of all views (the wall goes on the side away from them).
    scale: object diagonal (scene units). Returns ([(mesh, reserved label)], info dict).
    """
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    center = 0.5 * (lo + hi)
    radius = float(np.linalg.norm(vertices - center, axis=1).max())
    foot = float(max(hi[0] - lo[0], hi[1] - lo[1]))
    margin = 0.12 * foot + 0.02 * scale
    top_z = lo[2] - 0.002 * scale
    thick, leg, leg_h = 0.03 * scale, 0.03 * scale, 0.45 * scale
    floor_z = top_z - thick - leg_h
    tlo = np.array([lo[0] - margin, lo[1] - margin, top_z - thick])
    thi = np.array([hi[0] + margin, hi[1] + margin, top_z])
    eye = np.eye(3)
    contrast = min(level, 2.0)
    wood = _texture("wood", rng, contrast)
    table = [_textured(oriented_box(0.5 * (tlo + thi), eye, 0.5 * (thi - tlo), (0, 0, 0)), wood, 0.4 * scale)]
    leg_color = wood.reshape(-1, 3).mean(axis=0) * 0.7
    for sx in (0, 1):
        for sy in (0, 1):
            cx = tlo[0] + leg + sx * (thi[0] - tlo[0] - 2 * leg)
            cy = tlo[1] + leg + sy * (thi[1] - tlo[1] - 2 * leg)
            table.append(oriented_box(np.array([cx, cy, floor_z + 0.5 * leg_h]), eye,
                                      (0.5 * leg, 0.5 * leg, 0.5 * leg_h), leg_color))
    half_floor = 8.0 * radius
    floor = oriented_box(np.array([center[0], center[1], floor_z - 0.005 * scale]), eye,
                         (half_floor, half_floor, 0.005 * scale), (0, 0, 0))
    floor = _textured(floor, _texture("tiles", rng, contrast), 0.6 * scale)
    look = np.zeros(2)
    for c2w in cameras:
        d = np.asarray(c2w, float)[:2, 3] - center[:2]
        look += d / max(np.linalg.norm(d), 1e-12)
    back = -look / np.linalg.norm(look) if np.linalg.norm(look) > 1e-9 else np.array([1.0, 0.0])
    back3 = np.array([back[0], back[1], 0.0])
    corners = np.array([[x, y, 0.0] for x in (tlo[0], thi[0]) for y in (tlo[1], thi[1])])
    reach = max(float(((vertices - center) * back3).sum(axis=1).max()),
                float(((corners - center) * back3).sum(axis=1).max()))
    side = np.cross([0.0, 0.0, 1.0], back3)
    wall_h = 10.0 * radius
    wall_center = center + back3 * (reach + 0.25 * scale + 0.01 * scale)
    wall_center[2] = floor_z + 0.5 * wall_h
    wall = oriented_box(wall_center, np.stack([back3, side, [0.0, 0.0, 1.0]], axis=1),
                        (0.01 * scale, 8.0 * radius, 0.5 * wall_h), (0, 0, 0))
    wall = _textured(wall, _texture("paint", rng, contrast), 0.8 * scale)
    parts = [(RenderMesh.concat(table), TABLE_LABEL), (floor, FLOOR_LABEL), (wall, WALL_LABEL)]
    info = {"table_top_z": float(top_z), "table_xy": [tlo[:2].tolist(), thi[:2].tolist()],
            "floor_z": float(floor_z), "wall_normal": (-back3).tolist(),
            "wall_distance": float(reach + 0.26 * scale)}
    return parts, info


def _scaled_intrinsics(K: np.ndarray, factor: float) -> np.ndarray:
    """K of the same camera at ``factor`` x the resolution (pixel-centre convention)."""
    Ks = np.asarray(K, float).copy()
    Ks[:2, :2] *= factor
    Ks[0, 2] = (K[0, 2] + 0.5) * factor - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) * factor - 0.5
    return Ks


def hand_parts(parts_end: Sequence[tuple[RenderMesh, int]], prep_end: PreparedScene,
               cameras_end: Sequence[np.ndarray], K: np.ndarray, width: int, height: int,
               scale: float, level: float, rng: np.random.Generator,
               static_label: int = 1) -> tuple[list[tuple[RenderMesh, int]], dict | None]:
    """A hand resting on a visible point of one moving part (END state) + a forearm leaving the image.

    parts_end: the object's (world mesh, label) parts at the end state; prep_end: the same,
    prepared for raycasting; cameras_end: (4, 4) cam_to_world of the end views (the contact
    point is the most interior visible pixel of the part in the first view that sees it);
    scale: object diagonal. Returns ([(mesh, OCCLUDER_LABEL)], info) or ([], None) when no moving
    part is visible. Hand length = ``level`` x HAND_FRACTION x the part's diagonal, clipped to
    HAND_CLAMP x scale; the forearm (sleeve) is 3 object radii long, tilted 20 deg off the surface.
    """
    movable = sorted({int(lab) for _, lab in parts_end if lab != static_label})
    if not movable or level <= 0:
        return [], None
    target = int(movable[int(rng.integers(len(movable)))])
    allv = np.concatenate([m.vertices for m, _ in parts_end])
    center = 0.5 * (allv.min(0) + allv.max(0))
    radius = float(np.linalg.norm(allv - center, axis=1).max())
    factor = min(1.0, 96.0 / width)
    ws, hs = max(8, round(width * factor)), max(6, round(height * factor))
    Ks = _scaled_intrinsics(K, factor)
    hit = None
    for view, c2w in enumerate(cameras_end):
        origins, dirs = camera_rays(Ks, c2w, ws, hs)
        t, tri = prep_end.cast(origins, dirs)
        lab = np.where(tri >= 0, prep_end.tri_label[np.maximum(tri, 0)], 0).reshape(hs, ws)
        sel = (lab == target).astype(np.uint8)
        if sel.sum() == 0:
            continue
        inner = cv2.distanceTransform(np.pad(sel, 1), cv2.DIST_L2, 3)[1:-1, 1:-1]
        candidates = np.flatnonzero(inner.ravel() >= 0.6 * inner.max())
        pix = int(candidates[int(rng.integers(len(candidates)))])
        p = origins[pix] + t[pix] * dirs[pix]
        n = prep_end.normals[tri[pix]].copy()
        if n @ dirs[pix] > 0:
            n = -n
        hit = (view, p, n, np.asarray(c2w, float))
        break
    if hit is None:
        return [], None
    view, p, n, c2w = hit
    part_v = np.concatenate([m.vertices for m, lab in parts_end if lab == target])
    part_diag = float(np.linalg.norm(part_v.max(0) - part_v.min(0)))
    h = level * float(np.clip(HAND_FRACTION * part_diag, HAND_CLAMP[0] * scale, HAND_CLAMP[1] * scale))

    def along(v: np.ndarray) -> np.ndarray:
        w = v - (v @ n) * n
        nv = np.linalg.norm(w)
        return w / nv if nv > 1e-9 else np.zeros(3)

    out_dir = along(along(p - center) + 0.5 * along(c2w[:3, 1]))   # outward + toward the image bottom
    if not np.any(out_dir):
        out_dir = along(c2w[:3, 0])
    turn = math.radians(rng.uniform(-30, 30))
    side0 = np.cross(n, out_dir)
    out_dir = math.cos(turn) * out_dir + math.sin(turn) * side0
    f = -out_dir                                                     # fingers point inward
    s = np.cross(n, f) * (1 if rng.random() < 0.5 else -1)           # thumb side (left / right hand)
    skin = np.clip(np.array([0.85, 0.64, 0.52]) * rng.uniform(0.55, 1.08) + rng.uniform(-0.03, 0.03, 3), 0, 1)
    sleeve = np.clip(rng.uniform(0.05, 0.6, 3), 0, 1)
    gap = 0.01 * h
    lift = gap + 0.06 * h
    palm_c = p + n * lift
    meshes = [oriented_box(palm_c, np.stack([f, np.cross(n, f), n], axis=1), (0.25 * h, 0.22 * h, 0.06 * h), skin)]
    for off, ln in zip((-0.165, -0.055, 0.055, 0.165), (0.8, 1.0, 0.95, 0.75)):
        a = palm_c + f * 0.22 * h + np.cross(n, f) * off * h
        meshes.append(capsule(a, a + f * 0.45 * h * ln, 0.045 * h, skin))
    ta = palm_c + s * 0.18 * h - f * 0.08 * h
    tdir = (f + s) / np.linalg.norm(f + s)
    meshes.append(capsule(ta, ta + tdir * 0.3 * h, 0.05 * h, skin))
    arm = math.cos(math.radians(20)) * out_dir + math.sin(math.radians(20)) * n
    wrist = palm_c - f * 0.22 * h
    elbow = wrist + arm * 0.6 * h
    meshes.append(capsule(wrist, elbow, 0.11 * h, skin))
    meshes.append(capsule(elbow, elbow + arm * 3.0 * radius, 0.15 * h, sleeve))
    info = {"part_mask_id": target, "contact": p.tolist(), "normal": n.tolist(), "hand_length": h,
            "found_in_view": view}
    return [(RenderMesh.concat(meshes), OCCLUDER_LABEL)], info


def scene_extras(realism: Realism, seed: int, parts_start: Sequence[tuple[RenderMesh, int]],
                 parts_end: Sequence[tuple[RenderMesh, int]], prep_end: PreparedScene,
                 cameras: dict[str, Sequence[np.ndarray]], K: np.ndarray, width: int, height: int,
                 scale: float) -> tuple[dict[str, list[tuple[RenderMesh, int]]], dict]:
    """Extra geometry raycast with the object: {"start": [...], "end": [...]} (mesh, reserved
    label) lists, and an info dict for gt.json. ``cameras``: {"start": [c2w], "end": [c2w]}."""
    extras: dict[str, list[tuple[RenderMesh, int]]] = {"start": [], "end": []}
    info: dict = {}
    if realism.background > 0:
        allv = np.concatenate([m.vertices for m, _ in list(parts_start) + list(parts_end)])
        parts, info["background"] = background_parts(allv, list(cameras["start"]) + list(cameras["end"]), scale,
                                                     realism.background, knob_rng(seed, "background"))
        extras["start"] += parts
        extras["end"] += parts
    if realism.occluder > 0:
        parts, hand = hand_parts(parts_end, prep_end, cameras["end"], K, width, height, scale,
                                 realism.occluder, knob_rng(seed, "occluder"))
        extras["end"] += parts
        info["occluder"] = hand
    return extras, info


# ---- per-view degradations -----------------------------------------------------------------------


def depth_discontinuities(depth: np.ndarray, relative_jump: float = EDGE_RELATIVE_JUMP) -> np.ndarray:
    """(H, W) bool: pixels whose 3x3 neighbourhood holds valid depths spanning more than
    ``relative_jump`` of the nearest one, or valid and empty (0) pixels together."""
    depth = np.asarray(depth, dtype=np.float64)
    valid = depth > 0
    kernel = np.ones((3, 3), np.uint8)
    near = cv2.erode(np.where(valid, depth, np.inf).astype(np.float32), kernel).astype(np.float64)
    far = cv2.dilate(np.where(valid, depth, 0.0).astype(np.float32), kernel).astype(np.float64)
    any_valid = np.isfinite(near)
    any_empty = cv2.dilate((~valid).astype(np.uint8), kernel).astype(bool)
    near0 = np.where(any_valid, near, 0.0)
    return any_valid & ((far - near0 > relative_jump * near0) | any_empty)


def distance_to(mask: np.ndarray) -> np.ndarray:
    """(H, W) float64 Euclidean distance (px) of every pixel to the nearest True pixel of ``mask``
    (a large number when there is none)."""
    if not mask.any():
        return np.full(mask.shape, 1e6)
    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5).astype(np.float64)


def incidence_cosine(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W) float64 |cos| of the angle between each pixel's ray and the surface normal estimated
    from depth finite differences (0.5 where undefined: invalid pixels or neighbours)."""
    h, w = depth.shape
    r, c = np.mgrid[0:h, 0:w].astype(np.float64)
    z = np.where(depth > 0, depth, np.nan)
    P = np.stack([(c - K[0, 2]) / K[0, 0] * z, (r - K[1, 2]) / K[1, 1] * z, z], axis=-1)
    n = np.cross(np.gradient(P, axis=1), np.gradient(P, axis=0))
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs((n * P).sum(-1)) / (np.linalg.norm(n, axis=-1) * np.linalg.norm(P, axis=-1))
    return np.where(np.isfinite(cos), np.clip(cos, 0.0, 1.0), 0.5)


def warp_field(height: int, width: int, amplitude: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) float64 multiplicative warp ``1 + a f``: f a random sum of cos(pi kx u + phase)
    cos(pi ky v + phase), kx, ky in {0, 1, 2} (at most one cycle per image), scaled to max |f| = 1;
    a = amplitude x U(0.5, 1)."""
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    f = np.zeros((height, width))
    for kx in range(3):
        for ky in range(3):
            if kx == ky == 0:
                continue
            c = rng.standard_normal() / (1.0 + kx + ky)
            px, py = rng.uniform(0, 2 * np.pi, 2)
            f += c * np.cos(np.pi * ky * v + py)[:, None] * np.cos(np.pi * kx * u + px)[None, :]
    f /= max(np.abs(f).max(), 1e-12)
    return 1.0 + amplitude * rng.uniform(0.5, 1.0) * f


def smear_edges(depth: np.ndarray, edges: np.ndarray, radius_px: float, rng: np.random.Generator) -> np.ndarray:
    """Flying pixels: every pixel within ``radius_px`` of a discontinuity (``edges``) moves a random
    fraction U(0.5, 1) of the way to the Gaussian-blurred (sigma = radius/2) depth, i.e. between the
    near and far sides. Empty pixels there stand for a background 25 % beyond the farthest valid
    neighbour and may become valid. Returns a new (H, W) float64 array."""
    valid = depth > 0
    k = 2 * math.ceil(radius_px) + 3
    far = cv2.dilate(np.where(valid, depth, 0).astype(np.float32), np.ones((k, k), np.uint8)).astype(np.float64)
    filled = np.where(valid, depth, far * (1.0 + EMPTY_BACKGROUND_GAP))
    sigma = max(0.5 * radius_px, 0.5)
    weight = cv2.GaussianBlur((filled > 0).astype(np.float64), (0, 0), sigma)
    blurred = cv2.GaussianBlur(filled, (0, 0), sigma)
    with np.errstate(invalid="ignore", divide="ignore"):
        blurred = np.where(weight > 1e-6, blurred / weight, 0.0)
    band = (distance_to(edges) <= radius_px) & (filled > 0) & (blurred > 0)
    out = depth.copy()
    u = rng.uniform(0.5, 1.0, int(band.sum()))
    out[band] = filled[band] + u * (blurred[band] - filled[band])
    return out


def _holes(valid: np.ndarray, cos_inc: np.ndarray, level: float, rng: np.random.Generator) -> np.ndarray:
    h, w = valid.shape
    mask = np.zeros((h, w), np.uint8)
    ys, xs = np.nonzero(valid)
    for _ in range(int(rng.poisson(HOLES_PER_VIEW * level))):
        if not len(ys):
            break
        i = int(rng.integers(len(ys)))
        axes = np.maximum(1, np.round(rng.uniform(*HOLE_RADIUS, 2) * min(h, w))).astype(int)
        cv2.ellipse(mask, (int(xs[i]), int(ys[i])), (int(axes[0]), int(axes[1])), float(rng.uniform(0, 180)),
                    0, 360, 1, -1)
    graze = (cos_inc < GRAZING_DROPOUT_COS) & (rng.random((h, w)) < min(1.0, 0.5 * level))
    return (mask > 0) | graze


@dataclass
class DegradedView:
    """One view after the per-view knobs. rgb (H, W, 3) uint8; depth (H, W) float64 (0 = invalid);
    label (H, W) uint16 written mask (reserved labels -> 0); conf (H, W) float32 in [0, 1] or None;
    label_groups {written id: true group label} (None = identity); true_label (H, W) uint16 group
    labels before the mask knobs; info: per-view draws for gt.json."""

    rgb: np.ndarray
    depth: np.ndarray
    label: np.ndarray
    conf: np.ndarray | None
    label_groups: dict[int, int] | None
    true_label: np.ndarray
    info: dict


def degrade_rgb(rgb: np.ndarray, realism: Realism, rng: np.random.Generator) -> np.ndarray:
    """Gaussian noise (sigma IMAGE_NOISE_SIGMA x level grey levels) then a JPEG round trip at
    quality 100 - 30 x level (clipped to [5, 95]). rgb (H, W, 3) uint8 -> same."""
    out = rgb
    if realism.image_noise > 0:
        noisy = rgb.astype(np.float64) + IMAGE_NOISE_SIGMA * realism.image_noise * rng.standard_normal(rgb.shape)
        out = np.clip(np.round(noisy), 0, 255).astype(np.uint8)
    if realism.jpeg > 0:
        out = jpeg_round_trip(out, jpeg_quality(realism.jpeg))
    return out


def jpeg_quality(level: float) -> int:
    """JPEG quality of a ``jpeg`` level (70 at 1)."""
    return int(np.clip(round(100 - JPEG_QUALITY_SLOPE * level), 5, 95))


def jpeg_round_trip(rgb: np.ndarray, quality: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB encoded and decoded as JPEG at ``quality`` (cv2, deterministic)."""
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("cv2.imencode('.jpg') failed")
    return np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1])


def ragged_mask(label: np.ndarray, level: float, rng: np.random.Generator,
                max_label: int) -> tuple[np.ndarray, dict[int, int], list[dict]]:
    """Fray the borders of a (H, W) uint16 label image and maybe merge / split ids.

    Border: every pixel takes the label at itself + a displacement (Gaussian-blurred white noise,
    sigma MASK_RAGGED_PX x level px, clipped to MASK_RAGGED_MAX_PX x level px per axis), so only
    pixels that close to a label border change. Then with p = MASK_MERGE_P x level two ids become
    one, and with p = MASK_SPLIT_P x level one id (>= 40 px) is cut in two by a random line through
    its centroid; the new id is above ``max_label`` and every id in the image.
    Returns (label, {written id: true group}, events).
    """
    h, w = label.shape
    amp, cap = MASK_RAGGED_PX * level, MASK_RAGGED_MAX_PX * level
    disp = []
    for _ in range(2):
        noise = cv2.GaussianBlur(rng.standard_normal((h, w)), (0, 0), 2.5)
        noise /= max(noise.std(), 1e-12)
        disp.append(np.clip(amp * noise, -cap, cap))
    r, c = np.mgrid[0:h, 0:w]
    src_r = np.clip(np.round(r + disp[0]).astype(np.int64), 0, h - 1)
    src_c = np.clip(np.round(c + disp[1]).astype(np.int64), 0, w - 1)
    out = label[src_r, src_c].astype(np.uint16)
    groups = {int(i): int(i) for i in np.unique(out) if i != 0}
    events: list[dict] = []
    ids = sorted(groups)
    merge_draw, split_draw = rng.random(), rng.random()
    if len(ids) >= 2 and merge_draw < MASK_MERGE_P * level:
        a, b = (int(x) for x in rng.choice(ids, 2, replace=False))
        out[out == b] = a
        groups.pop(b)
        events.append({"merge": [b, a]})
    big = [i for i in sorted(groups) if (out == i).sum() >= 40]
    if big and split_draw < MASK_SPLIT_P * level:
        i = int(big[int(rng.integers(len(big)))])
        ys, xs = np.nonzero(out == i)
        angle = rng.uniform(0, np.pi)
        side = (xs - xs.mean()) * math.cos(angle) + (ys - ys.mean()) * math.sin(angle) > 0
        new = int(max(max_label, int(out.max()))) + 1
        out[ys[side], xs[side]] = new
        groups[new] = groups[i]
        events.append({"split": [i, new]})
    return out, groups, events


def degrade_view(rgb: np.ndarray, depth: np.ndarray, label: np.ndarray, K: np.ndarray, realism: Realism,
                 seed: int, state: str, index: int, max_label: int) -> DegradedView:
    """Apply the per-view knobs to one raycast view.

    rgb (H, W, 3) uint8; depth (H, W) float64 camera z (0 = no hit); label (H, W) uint16 raw
    labels (object groups 1..max_label, reserved labels >= RESERVED_LABEL_MIN for background and
    occluder); K (3, 3). ``seed``/``state``/``index`` key the random streams.
    """
    key = (STATE_KEYS[state], int(index))
    info: dict = {}
    true_label = np.where(label >= RESERVED_LABEL_MIN, 0, label).astype(np.uint16)
    clean = np.asarray(depth, dtype=np.float64)
    h, w = clean.shape
    edges = depth_discontinuities(clean)
    edge_dist = distance_to(edges)
    cos_inc = incidence_cosine(clean, K)
    obj = (true_label > 0) & (clean > 0)
    d_ref = float(np.median(clean[obj])) if obj.any() else (float(np.median(clean[clean > 0])) if (clean > 0).any() else 1.0)
    d = clean.copy()
    if realism.edge_smear > 0:
        d = smear_edges(d, edges, EDGE_SMEAR_PX * realism.edge_smear, knob_rng(seed, "edge_smear", *key))
    warp = None
    if realism.depth_warp > 0:
        warp = warp_field(h, w, DEPTH_WARP_AMPLITUDE * realism.depth_warp, knob_rng(seed, "depth_warp", *key))
        d *= warp
        info["warp_max"] = float(np.abs(warp - 1).max())
    if realism.depth_scale > 0:
        g = knob_rng(seed, "depth_scale", *key)
        s = 1.0 + DEPTH_SCALE_SIGMA * realism.depth_scale * float(np.clip(g.standard_normal(), -3, 3))
        d *= s
        info["depth_scale"] = s
    holes = np.zeros((h, w), bool)
    if realism.depth_noise > 0:
        g = knob_rng(seed, "depth_noise", *key)
        valid = d > 0
        rel = np.clip(np.where(clean > 0, clean, d) / d_ref, 0.5, 3.0) * (1.5 - 0.5 * cos_inc)
        sigma = DEPTH_NOISE_SIGMA * realism.depth_noise * rel
        d[valid] *= 1.0 + sigma[valid] * g.standard_normal(int(valid.sum()))
        # finite-difference normals are meaningless at discontinuities: no grazing dropout there
        holes = _holes(valid, np.where(edge_dist <= 2.0, 1.0, cos_inc), realism.depth_noise, g) & valid
        d[holes] = 0.0
        info["hole_fraction"] = float(holes.mean())
    conf = None
    if realism.confidence > 0:
        g = knob_rng(seed, "confidence", *key)
        width_px = max(EDGE_SMEAR_PX * realism.edge_smear, 1.5)
        strength = 0.85 if realism.edge_smear > 0 else 0.6
        raw = 1.0 - strength * np.exp(-0.5 * (edge_dist / width_px) ** 2)
        raw *= 0.3 + 0.7 * cos_inc
        with np.errstate(divide="ignore"):
            raw *= np.clip(d_ref / np.where(clean > 0, clean, np.inf), 0.2, 1.0)
        if holes.any():
            raw *= np.clip(distance_to(holes) / 3.0, 0.0, 1.0)
        if warp is not None:
            raw *= 1.0 - 0.5 * np.clip(np.abs(warp - 1.0) / DEPTH_WARP_AMPLITUDE, 0.0, 1.0)
        raw = np.clip(raw, 0.0, 1.0) ** realism.confidence
        raw *= np.exp(CONF_JITTER * realism.confidence * g.standard_normal((h, w)))
        conf = np.where(d > 0, np.clip(raw, 0.0, 1.0), 0.0).astype(np.float32)
    out_rgb = degrade_rgb(rgb, realism, knob_rng(seed, "image", *key)) if (realism.image_noise > 0 or realism.jpeg > 0) else rgb
    out_label, groups = true_label, None
    if realism.mask_ragged > 0:
        out_label, groups, events = ragged_mask(true_label, realism.mask_ragged,
                                                knob_rng(seed, "mask_ragged", *key), max_label)
        if events:
            info["mask_events"] = events
    return DegradedView(out_rgb, d, out_label, conf, groups, true_label, info)
