"""Free-space consistency: does a predicted surface agree with what a state's depth images saw?

A state's views are recovered in the labeler's frame from the state's own cloud: every point of a
frame is a pixel of that frame's depth image, so a similarity fit between the unprojected depth
pixels and the cloud points gives the view's camera in whatever frame the cloud is in (the world
frame of a posed scene, the start camera's frame of an unposed one, after any state alignment).

A predicted point (a part moved by a hypothesised joint) projected into a view is

* **consistent** when the view saw a surface at the predicted depth (within a margin),
* a **violation** when the view saw through it: the depth there is farther (or nothing at all
  was seen: background), so the space the point would occupy is empty,
* **hidden** when something nearer covers it, or it falls outside the image: no evidence.

Scores built on these ignore hidden points, so a drawer slid shut (its sides hidden inside the
carcass) is not charged for the sides the end views cannot see. Costs are O(N) per prediction for
N points and V views (one projection and two look-ups per point and view).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sparseart.types import LabelledCloud, Scene

MIN_VIEW_POINTS = 50          # a frame with fewer cloud points gives no view
EMPTY_DILATION_PIXELS = 2     # invalid depth farther than this from any valid pixel = seen empty
HIDDEN = 0
CONSISTENT = 1
VIOLATION = 2


@dataclass
class View:
    """One image of a state in the labeler's frame.

    world_to_cam: (4, 4) float64 rigid map labeler frame -> OpenCV camera frame; K: (3, 3);
    near / far: (H, W) float64 smallest / largest valid depth in each pixel's 3 x 3 neighbourhood
    (labeler units; inf / -inf where none is valid); empty: (H, W) bool, nothing seen there.
    """

    world_to_cam: np.ndarray
    K: np.ndarray
    near: np.ndarray
    far: np.ndarray
    empty: np.ndarray


@dataclass
class StateViews:
    """The views of one state; ``margin`` is the depth tolerance (labeler units)."""

    views: list[View]
    margin: float

    def __bool__(self) -> bool:
        return bool(self.views)

    def classify(self, points: np.ndarray) -> np.ndarray:
        """(N,) int8 per point: CONSISTENT if any view saw a surface there, else VIOLATION if any
        view saw through it, else HIDDEN. points: (N, 3) float64 in the labeler's frame. O(N V)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        consistent = np.zeros(len(points), dtype=bool)
        violation = np.zeros(len(points), dtype=bool)
        for view in self.views:
            camera = points @ view.world_to_cam[:3, :3].T + view.world_to_cam[:3, 3]
            z = camera[:, 2]
            front = z > 1e-9
            u = np.full(len(points), -1, dtype=np.int64)
            v = np.full(len(points), -1, dtype=np.int64)
            with np.errstate(divide="ignore", invalid="ignore"):
                u[front] = np.round(view.K[0, 0] * camera[front, 0] / z[front] + view.K[0, 2]).astype(np.int64)
                v[front] = np.round(view.K[1, 1] * camera[front, 1] / z[front] + view.K[1, 2]).astype(np.int64)
            height, width = view.near.shape
            inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
            if not inside.any():
                continue
            ui, vi, zi = u[inside], v[inside], z[inside]
            near, far, empty = view.near[vi, ui], view.far[vi, ui], view.empty[vi, ui]
            here_consistent = (near <= zi + self.margin) & (far >= zi - self.margin)
            here_violation = empty | (near > zi + self.margin)
            consistent[inside] |= here_consistent
            violation[inside] |= here_violation & ~here_consistent
        result = np.full(len(points), HIDDEN, dtype=np.int8)
        result[violation] = VIOLATION
        result[consistent] = CONSISTENT
        return result


def state_views(cloud: LabelledCloud, scene: Scene | None, margin: float) -> StateViews:
    """The views of ``cloud``'s state, each camera fitted from the cloud itself (module doc).

    Views need the frame's depth image and K; frames without them (an RGB-only reconstruction,
    clouds given without a scene) are left out, and no view at all gives an empty StateViews that
    callers treat as "no free-space evidence". O(H W) per frame.
    """
    if scene is None:
        return StateViews([], margin)
    from scipy.ndimage import binary_dilation, maximum_filter, minimum_filter

    frames = {frame.index: frame for frame in scene.frames(cloud.state)}
    views = []
    for index in np.unique(cloud.frame_index):
        frame = frames.get(int(index))
        if frame is None or frame.depth is None or frame.camera is None:
            continue
        rows = np.flatnonzero(cloud.frame_index == index)
        if len(rows) < MIN_VIEW_POINTS:
            continue
        depth = np.asarray(frame.depth, dtype=np.float64)
        height, width = depth.shape
        pick = rows[np.linspace(0, len(rows) - 1, min(len(rows), 3000)).astype(np.int64)]
        pixel = cloud.pixel_index[pick]
        d = depth.reshape(-1)[pixel]
        ok = d > 0
        if ok.sum() < MIN_VIEW_POINTS:
            continue
        K = np.asarray(frame.camera.K, dtype=np.float64)
        u, v = (pixel % width)[ok], (pixel // width)[ok]
        camera_points = np.stack([(u - K[0, 2]) / K[0, 0] * d[ok], (v - K[1, 2]) / K[1, 1] * d[ok], d[ok]], axis=1)
        scale, rotation, translation = _umeyama(camera_points, cloud.points[pick[ok]])
        if not scale > 0:
            continue
        # Camera coordinates in labeler units: R^T (x - t); the depth image times s matches them.
        world_to_cam = np.eye(4)
        world_to_cam[:3, :3] = rotation.T
        world_to_cam[:3, 3] = -rotation.T @ translation
        valid = depth > 0
        scaled = depth * scale
        near = minimum_filter(np.where(valid, scaled, np.inf), size=3)
        far = maximum_filter(np.where(valid, scaled, -np.inf), size=3)
        empty = ~binary_dilation(valid, iterations=EMPTY_DILATION_PIXELS)
        views.append(View(world_to_cam, K, near, far, empty))
    return StateViews(views, margin)


def _umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) with target ~ s R source + t (least squares). O(N)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    a, b = source - mu_s, target - mu_t
    covariance = b.T @ a / len(source)
    u, singular, vt = np.linalg.svd(covariance)
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    rotation = u @ np.diag(sign) @ vt
    variance = float(np.mean(np.sum(a * a, axis=1)))
    scale = float(np.sum(singular * sign) / variance) if variance > 0 else 0.0
    return scale, rotation, mu_t - scale * rotation @ mu_s


def visible_fraction(labels: np.ndarray, hits: np.ndarray, floor: float = 0.4) -> float:
    """Share of points that land on the target among the points the views could judge.

    labels: (N,) from :meth:`StateViews.classify`; hits: (N,) bool, the point landed on the
    target surface (a hit counts as seen even where the view's margin missed it). The denominator
    is at least ``floor`` x N, so a hypothesis that hides almost everything earns little. O(N).
    """
    if len(hits) == 0:
        return 0.0
    judged = hits | (labels != HIDDEN)
    return float(hits.sum() / max(judged.sum(), floor * len(hits), 1.0))
