"""Geometric fallback for view registration: metric clouds registered without features.

Used when features leave a view unreached (weak texture): PCA/FPFH hypotheses + coloured ICP
(:func:`sparseart.geometry.icp.register_rigid`), accepted only with enough overlap and when
neither view sees through the other's surfaces (free-space check).

With the user's masks, when the two views share mask ids that name the same parts (a renderer's
or an annotation tool's part ids), the ids are evidence too: a box-like object turned a quarter
round lays its walls onto each other at a high overlap and without seeing through anything, but it
lays the drawer fronts onto a side wall. A plain fit whose ids disagree is held back; when no
plain fit places a view, the view is registered again from :func:`turns` (8 turns about the
centroids, for roughly upright cameras) ranked by overlap x id agreement, and that fit is kept
only when its ids agree (``LABEL_AGREEMENT``), it keeps the camera roughly upright
(``MAX_SEARCH_TILT_DEG``) and it sees through less than a plain fit may (``MAX_SEARCH_VIOLATION``;
measured: the searched fits of two ovens' views that slid 4 % of the object along its front saw
through 3.0-3.2 %, the right fits of a cabinet's and a dishwasher's 0.0-1.0 %). Ids that do not
name parts across images (a per-image segmenter's 1..k) never agree, so nothing changes for them.
"""
from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from sparseart.align.features import PLANAR_FRACTION, THRESHOLD_FRACTION
from sparseart.geometry.clouds import spread
from sparseart.geometry.icp import RigidRegistration, icp_polish, register_rigid
from sparseart.geometry.transforms import apply_transform, make_transform
from sparseart.types import Frame, Pointmap

GEOMETRY_MIN_OVERLAP = 0.5       # geometric fallback: accepted overlap fraction

MAX_FREE_SPACE_VIOLATION = 0.05  # geometric fallback: accepted share of points in seen-through space
# ... on noisy depth (a sensor's or reconstructor's: holes, smeared edges, smooth warps), where the
# true relative pose itself puts 0.7-21 % of the points there (median 3.6 %; 16 realistic renders,
# seeds 0-1, 96 view pairs). Measured on the 64 realistic renders of seeds 0-3: 340 -> 360 of 384
# views registered, every added one within 2.8 deg of its true rotation; the wrong fits of those
# pairs saw through 13-44 %.
NOISY_MAX_FREE_SPACE_VIOLATION = 0.10

LABEL_AGREEMENT = 0.8    # IdAgreement at or above this: a fit the mask ids vouch for
LABEL_MIN_IDS = 2        # mask ids both views must carry (each on LABEL_MIN_POINTS points) to be evidence
LABEL_MIN_POINTS = 30
LABEL_MIN_ID_NEAR = 10   # an id counts in the agreement when this many of its points land near a labelled point
LABEL_SAMPLE = 2000      # labelled source points sampled for the agreement
MAX_SEARCH_TILT_DEG = 60.0  # a searched fit may tilt the camera's y axis this far (upright cameras)
MAX_SEARCH_VIOLATION = 0.02  # ... and see through at most this share: 8 starts give more chances to a slid fit
TILTED_WEIGHT = 0.8         # edge weight factor of a fit that tilts it further: another view's fit is preferred


@lru_cache(maxsize=1)
def turns() -> tuple[np.ndarray, ...]:
    """The 8 start rotations of the labelled search, (3, 3) float64 each: turns about the camera's
    y axis in 45 deg steps. Cameras around an object (a phone, a robot head) stay roughly upright
    and differ mostly by a turn about the vertical, which is near image y; ICP takes a start within
    about 22 deg of the answer the rest of the way (measured: the same joints as 24 starts with
    +-30 deg tilts on the two-drawer cabinet and the toaster, at a third of the search's cost). A quarter
    roll about the optical axis is not searched: it lays a square front onto itself and a box's top
    onto its side, ids and all."""
    return tuple(Rotation.from_euler("y", yaw, degrees=True).as_matrix() for yaw in range(0, 360, 45))


def upright_starts(source: np.ndarray, target: np.ndarray) -> list[np.ndarray]:
    """(4, 4) source -> target starts of the labelled search: each of :func:`turns` about the
    source centroid, carrying it onto the target centroid. source (N, 3), target (M, 3). O(N + M)."""
    source_centre, target_centre = source.mean(axis=0), target.mean(axis=0)
    return [make_transform(turn, target_centre - turn @ source_centre) for turn in turns()]


def tilt_deg(transform: np.ndarray) -> float:
    """Angle (deg) between a camera's y axis and its image under a (4, 4) view -> view transform."""
    return float(np.degrees(np.arccos(np.clip(transform[1, 1], -1.0, 1.0))))


def view_mask_ids(frame: Frame, pointmap: Pointmap) -> np.ndarray | None:
    """(K,) int64 mask id of each point of :func:`~sparseart.geometry.clouds.valid_points` (same
    order), or None when the frame has no mask. O(H W)."""
    if frame.mask is None or np.shape(frame.mask) != (pointmap.height, pointmap.width):
        return None
    keep = pointmap.valid & np.isfinite(pointmap.points).all(axis=1)
    return np.asarray(frame.mask, dtype=np.int64).reshape(-1)[keep]


class IdAgreement:
    """How well a source -> target transform lays each mask id onto the same id: of the sampled
    labelled source points that land within ``distance`` of a labelled target point, the share that
    also land within ``distance`` of a target point of their own id, averaged over the ids (each id
    that lands near on at least ``LABEL_MIN_ID_NEAR`` points weighs the same: a large static body
    agreeing with itself must not outvote the drawers it is laid onto). Asking for the own id
    nearby rather than the nearest point's id keeps a thin part beside the body (a lever, a handle)
    agreeing at the true pose. Only ids both views carry count; fewer than ``LABEL_MIN_IDS`` ids
    landing near is no evidence (0: a turn that lays one id onto itself and the others onto nothing
    proves nothing). O(S log M) per call for S <= LABEL_SAMPLE."""

    def __init__(self, source: np.ndarray, source_ids: np.ndarray, target: np.ndarray, target_ids: np.ndarray,
                 distance: float, seed: int) -> None:
        shared = [int(i) for i in np.intersect1d(source_ids[source_ids > 0], target_ids[target_ids > 0])
                  if min((source_ids == i).sum(), (target_ids == i).sum()) >= LABEL_MIN_POINTS]
        self.usable = len(shared) >= LABEL_MIN_IDS
        if not self.usable:
            return
        pick = np.flatnonzero(np.isin(source_ids, shared))
        if len(pick) > LABEL_SAMPLE:
            pick = np.sort(np.random.default_rng(seed).choice(pick, LABEL_SAMPLE, replace=False))
        self.source, self.source_ids = source[pick], source_ids[pick]
        self.tree = cKDTree(target[np.isin(target_ids, shared)])
        self.own = {i: cKDTree(target[target_ids == i]) for i in shared}
        self.distance = distance

    def __call__(self, transform: np.ndarray) -> float:
        moved = apply_transform(transform, self.source)
        near = np.isfinite(self.tree.query(moved, distance_upper_bound=self.distance)[0])
        if near.sum() < LABEL_MIN_POINTS:
            return 0.0
        shares = []
        for i, own in self.own.items():
            landed = near & (self.source_ids == i)
            if landed.sum() >= LABEL_MIN_ID_NEAR:
                shares.append(np.isfinite(own.query(moved[landed], distance_upper_bound=self.distance)[0]).mean())
        return float(np.mean(shares)) if len(shares) >= LABEL_MIN_IDS else 0.0


def id_agreement(source: np.ndarray, source_ids: np.ndarray, target: np.ndarray, target_ids: np.ndarray,
                 size: float, seed: int) -> IdAgreement | None:
    """:class:`IdAgreement` within 2 x ``THRESHOLD_FRACTION`` of the scene ``size`` (the distance
    every registration judged by mask ids uses), or None when the ids are no evidence."""
    agreement = IdAgreement(source, source_ids, target, target_ids, 2 * THRESHOLD_FRACTION * size, seed)
    return agreement if agreement.usable else None


def _free_space_violation(points: np.ndarray, frame: Frame, pointmap: Pointmap, size: float) -> float:
    """Fraction of ``points`` (in ``frame``'s camera frame) that land in front of the surface the
    camera saw (or on certain background): a wrong registration puts surfaces where this view saw
    through. O(N + H W)."""
    import cv2

    h, w = pointmap.height, pointmap.width
    valid = pointmap.valid.reshape(h, w)
    # Nearest seen surface over a 5x5 window: grazing surfaces change depth quickly per pixel.
    depth = np.where(valid, np.nan_to_num(pointmap.points[:, 2].reshape(h, w)), np.inf)
    depth = cv2.erode(depth.astype(np.float32), np.ones((5, 5), np.uint8)).astype(np.float64)
    background = cv2.dilate(valid.astype(np.uint8), np.ones((7, 7), np.uint8)) == 0
    points = points[points[:, 2] > 1e-9]
    uv = points @ frame.camera.K.T
    col, row = np.rint(uv[:, 0] / uv[:, 2]).astype(int), np.rint(uv[:, 1] / uv[:, 2]).astype(int)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    if inside.sum() < 30:
        return 0.0
    row, col, z = row[inside], col[inside], points[inside, 2]
    seen = depth[row, col]
    bad = background[row, col] | (np.isfinite(seen) & (z < seen - 2 * THRESHOLD_FRACTION * size))
    return float(bad.mean())


def geometry_edge(j: int, i: int, frames: list[Frame], pointmaps: list[Pointmap], clouds: list[np.ndarray],
                  size: float, seed: int, max_violation: float = MAX_FREE_SPACE_VIOLATION,
                  polish: bool = True) -> tuple[np.ndarray, float, float] | None:
    """Geometric fallback view j -> view i for metric clouds in their camera frames
    (:func:`sparseart.geometry.icp.register_rigid`: PCA/FPFH hypotheses + coloured ICP).

    None for planar clouds (they slide), small overlap, or when either view sees through the other
    one's surfaces more than ``max_violation`` (free-space check, which rejects the turned-around
    fits of symmetric objects; ``NOISY_MAX_FREE_SPACE_VIOLATION`` for noisy depth). ``polish``:
    polish the fit at full resolution (:func:`_polished`; clean depth only, as the graph's own polish).
    Returns ((4, 4) j -> i, overlap fraction, edge weight in [0, 1)). O(N log N + H W)."""
    if _planar(j, i, clouds, size):
        return None
    result = register_rigid(clouds[j], clouds[i], *_colours(j, i, frames, pointmaps), seed=seed)
    if polish:
        result = _polished(result, clouds[j], clouds[i], size)
    return _checked(result, j, i, frames, pointmaps, clouds, size, max_violation)


POLISH_MAX_POINTS = 6000   # the full-resolution polish of a geometric edge reads at most this many points per view


def _polished(result: RigidRegistration, source: np.ndarray, target: np.ndarray, size: float) -> RigidRegistration:
    """``result`` (:class:`~sparseart.geometry.icp.RigidRegistration` of view clouds ``source`` /
    ``target``, (N, 3) / (M, 3)) with its transform polished by the project's point-to-plane ICP
    (:func:`~sparseart.geometry.icp.icp_polish` at ``THRESHOLD_FRACTION`` of the scene ``size``, on
    an even subsample of at most ``POLISH_MAX_POINTS`` points per view), when that raises the
    overlap; else unchanged.

    Why: register_rigid fits on 2000-point subsamples, so its answer is only as fine as their
    spacing. On a box whose drawers are open, a slide along the drawers keeps their walls on each
    other: measured on a clean textureless cabinet's end views (drawer_19179_multi, unposed), the
    fit was 6.2 % of the scene off along them at overlap 0.692 (true pose 0.697), nothing seen
    through; the start views placed through those views inherited it, and a drawer's moved points
    then lay on start points (unmatched). Polished: 0.1 %. At most 6000 points per view: at
    20 000 the clean unposed cabinet and fridge scenes took 13.5-14.0 s instead of 9.8-10.5 s, at
    6000 10.1 and 9.8 s with the same joints (every candidate edge is polished). Clean depth
    only: on the realistic renders (noisy, warped depth) it moved 12 of 84 joints both ways (one
    success lost, the slowest scene's registration 8 -> 19 s), as the graph's polish once did
    (``noise.MAX_CLEAN_ROUGHNESS``). O((N + M) log(N + M))."""
    polished = icp_polish(source, target, result.transform, THRESHOLD_FRACTION * size, max_points=POLISH_MAX_POINTS)
    return result if polished is None else replace(result, transform=np.asarray(polished, dtype=np.float64))


class GeometricEdges:
    """The geometric fallback's edges between views, each computed once (module docstring).

    ``plain(j, i, size)``: :func:`geometry_edge`, unless the mask ids disagree with it (then None).
    ``searched(j, i, size)``: where the ids are usable, the fit of the labelled search when the ids
    vouch for it, else the plain fit even if its ids disagree (a last resort); None without ids.
    Callers ask for searched edges only when no plain edge places a view: the search costs 8
    coarse ICPs on <= 2000 points. ``notes[j, i]`` says which of the two a searched edge is.

    ids: per view, the mask id of each cloud point (:func:`view_mask_ids`) or None; max_violation:
    the plain fits' free-space allowance, polish: whether fits are polished (:func:`geometry_edge`)."""

    def __init__(self, frames: list[Frame], pointmaps: list[Pointmap], clouds: list[np.ndarray], seed: int,
                 ids: list[np.ndarray | None], max_violation: float = MAX_FREE_SPACE_VIOLATION,
                 polish: bool = True) -> None:
        self.frames, self.pointmaps, self.clouds, self.seed, self.ids = frames, pointmaps, clouds, seed, ids
        self.max_violation, self.polish = max_violation, polish
        self._plain: dict[tuple[int, int], tuple] = {}
        self._searched: dict[tuple[int, int], tuple | None] = {}
        self.notes: dict[tuple[int, int], str] = {}     # (j, i) -> how a searched edge came about

    def _plain_and_ids(self, j: int, i: int, size: float) -> tuple:
        if (j, i) not in self._plain:
            edge = geometry_edge(j, i, self.frames, self.pointmaps, self.clouds, size, self.seed, self.max_violation,
                                 self.polish)
            agreement = None
            if self.ids[j] is not None and self.ids[i] is not None:
                agreement = id_agreement(self.clouds[j], self.ids[j], self.clouds[i], self.ids[i], size, self.seed)
            vouched = None if agreement is None or edge is None else agreement(edge[0]) >= LABEL_AGREEMENT
            self._plain[j, i] = (edge, agreement, vouched)
        return self._plain[j, i]

    def plain(self, j: int, i: int, size: float) -> tuple[np.ndarray, float, float] | None:
        edge, _, vouched = self._plain_and_ids(j, i, size)
        return edge if vouched is not False else None

    def searched(self, j: int, i: int, size: float) -> tuple[np.ndarray, float, float] | None:
        edge, agreement, vouched = self._plain_and_ids(j, i, size)
        if agreement is None or vouched:
            return None
        if (j, i) not in self._searched:
            found = self._search(j, i, size, agreement)
            self.notes[j, i] = ("found from upright turns, its mask ids agreeing" if found is not None
                                else "its mask ids disagree (no better fit found)")
            self._searched[j, i] = found or edge
        return self._searched[j, i]

    def _search(self, j: int, i: int, size: float, agreement: "IdAgreement") -> tuple[np.ndarray, float, float] | None:
        clouds = self.clouds
        if _planar(j, i, clouds, size):
            return None
        result = register_rigid(clouds[j], clouds[i], *_colours(j, i, self.frames, self.pointmaps), seed=self.seed,
                                hypotheses=upright_starts(clouds[j], clouds[i]), agreement=agreement)
        if self.polish:
            result = _polished(result, clouds[j], clouds[i], size)
        edge = _checked(result, j, i, self.frames, self.pointmaps, clouds, size, MAX_SEARCH_VIOLATION)
        if edge is None or agreement(edge[0]) < LABEL_AGREEMENT or tilt_deg(edge[0]) > MAX_SEARCH_TILT_DEG:
            return None
        return edge


def _planar(j: int, i: int, clouds: list[np.ndarray], size: float) -> bool:
    """Is either view's cloud planar (RMS spread along its third principal axis below
    ``PLANAR_FRACTION`` of the size)? Planar clouds slide: no geometric fit. O(N)."""
    return min(spread(clouds[i])[2], spread(clouds[j])[2]) < PLANAR_FRACTION * size


def _colours(j: int, i: int, frames: list[Frame], pointmaps: list[Pointmap]) -> list[np.ndarray]:
    """(K, 3) float64 colours in [0, 1] of the cloud points of views j and i. O(H W)."""
    return [frames[k].rgb.reshape(-1, 3)[pointmaps[k].valid & np.isfinite(pointmaps[k].points).all(axis=1)]
            / 255.0 for k in (j, i)]


def _checked(result, j: int, i: int, frames: list[Frame], pointmaps: list[Pointmap], clouds: list[np.ndarray],
             size: float, max_violation: float = MAX_FREE_SPACE_VIOLATION) -> tuple[np.ndarray, float, float] | None:
    """A registration j -> i as an edge, or None for a small overlap or a free-space violation.
    A fit that tilts the camera's y axis by more than ``MAX_SEARCH_TILT_DEG`` weighs
    ``TILTED_WEIGHT`` less, so a view's fit to another view that keeps it upright wins (measured:
    a dishwasher's end view fitted a quarter roll off, 94.7 deg tilt, at 0.86 overlap with every
    mask id agreeing, beside a right fit to another view at 0.82)."""
    if result.inlier_fraction < GEOMETRY_MIN_OVERLAP:
        return None
    forward = np.asarray(result.transform, dtype=np.float64)
    backward = np.linalg.inv(forward)
    violation = max(
        _free_space_violation(apply_transform(forward, clouds[j]), frames[i], pointmaps[i], size),
        _free_space_violation(apply_transform(backward, clouds[i]), frames[j], pointmaps[j], size))
    if violation > max_violation:
        return None
    upright = 1.0 if tilt_deg(forward) <= MAX_SEARCH_TILT_DEG else TILTED_WEIGHT
    return forward, result.inlier_fraction, 0.999 * result.inlier_fraction * (1.0 - violation) * upright
