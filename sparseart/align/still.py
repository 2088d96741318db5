"""A camera that did not move between the states: the states' alignment read off one view pair.

A robot's head camera, a tripod or a phone propped on a shelf sees the start and the end from
one place. Start view k and end view k then agree pixel by pixel wherever nothing moved (the
room, the table, the object's body): same depth up to the sensor's scale, same colour. That
pixel-level agreement is evidence no registration needs: the end state's frame maps onto the
start state's through view k's camera, exactly, even for a textureless box that features cannot
match and that its own symmetry lets geometry lay a quarter turn round.

:func:`still_camera` tests every view index seen in both states and returns the pair whose
images coincide: their phase-correlation shift is at most ``STILL_MAX_SHIFT_PX`` and at least
``STILL_MIN_SHARE`` of the pixels valid in both agree in depth and colour; the states' reference
views first (no registration error), then the share. :func:`place_through_twins` gives a view
that was left out of one state the pose of its same-camera twin in the other state.

Measured (experiment EXP-036, benchmarks/EXPERIMENTS.md): one camera, 63 view pairs of 21
realistic renders: shift 0.0-1.3 px (median 0.1), 62 pass; 63 pairs of 21 clean renders without
background: 54 pass (the rest are views a moved door or lid fills: shifts up to 37 px); the two
real robot captures (static head camera): shift 0.0-0.2 px, 38-44 % agreeing, both pass. Cameras
moved 10-21 deg between the states, 57 pairs of 19 clean renders: shift 3.6-99 px, none passes
(agreement alone let a door's flat front pass from 10 deg away: 47 % of its pixels). A door or
lid that fills the view drags the whole picture's shift (up to 45 px); the view's tiles still
tell the camera stood still (:func:`still_tiles`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sparseart.types import Frame, Pointmap

STILL_MIN_SHARE = 0.3           # share of the pixels valid in both views that must agree
STILL_DEPTH_TOLERANCE = 0.02    # relative depth difference of an agreeing pixel (after the views' depth ratio)
STILL_COLOUR_TOLERANCE = 0.08   # mean |RGB| difference (in [0, 1]) of an agreeing pixel
STILL_MIN_PIXELS = 500          # fewer pixels valid in both views: no judgement
STILL_MAX_SHIFT_PX = 1.0        # the images' phase-correlation shift of a camera that did not move
K_TOLERANCE = 1e-3              # relative difference of two intrinsics matrices that are one camera


@dataclass(frozen=True)
class StillCamera:
    """A view pair taken from one camera position.

    view: the view index k (start/rgb/k and end/rgb/k); share: of the pixels valid in both, the
    share whose depth (after ``scale``) and colour agree; scale: median start / end depth ratio of
    the pair (the sensor's or reconstructor's scale drift between the two images); transform:
    (4, 4) float64 end state frame -> start state frame (a similarity when ``scale`` != 1).
    """

    view: int
    share: float
    scale: float
    transform: np.ndarray


def still_camera(start: list[Frame], end: list[Frame], start_maps: list[Pointmap], end_maps: list[Pointmap],
                 start_poses: list[np.ndarray | None], end_poses: list[np.ndarray | None]) -> StillCamera | None:
    """The view pair whose camera did not move between the states, or None.

    start / end: the frames of each state (RGB, depth, intrinsics); start_maps / end_maps: their
    pointmaps (depth when a frame has none); start_poses / end_poses: (4, 4) view camera -> state
    frame (None: view not registered). Pairs need the same image size and intrinsics and a pose in
    both states. O(V H W).
    """
    best, best_rank = None, None
    for k in range(min(len(start), len(end))):
        if start_poses[k] is None or end_poses[k] is None:
            continue
        judged = _same_place(start[k], end[k], start_maps[k], end_maps[k])
        if judged is None:
            continue
        # A state's reference view (pose = identity) carries no registration error: pairs of
        # reference views first, then the share (measured: a cabinet's best-agreeing pair had an
        # end view registered 3.9 % of the object off, and its drawers came out 7-9 deg off).
        rank = (sum(bool(np.allclose(p, np.eye(4))) for p in (start_poses[k], end_poses[k])), judged[0])
        if best_rank is not None and rank <= best_rank:
            continue
        share, scale = judged
        transform = np.asarray(start_poses[k], dtype=np.float64) @ _zoom(scale) @ np.linalg.inv(end_poses[k])
        best, best_rank = StillCamera(k, share, scale, transform), rank
    return best


def place_through_twins(start: list[Frame], end: list[Frame], start_maps: list[Pointmap], end_maps: list[Pointmap],
                        start_poses: list[np.ndarray | None], end_poses: list[np.ndarray | None],
                        end_to_start: np.ndarray, zoom: bool = True) -> dict[tuple[str, int], tuple[np.ndarray, float]]:
    """Poses for views left out of one state whose twin (same index, same camera, other state) is
    registered and agrees with them pixel by pixel (share >= ``STILL_MIN_SHARE``): the twin's pose
    carried across the states. end_to_start: (4, 4) end state frame -> start state frame
    (identity when both states are in the start frame already). zoom: scale the placed view by
    the two images' depth ratio (:func:`pixel_agreement`) -- for depth of unknown scale only; metric
    depth keeps its scale, as the registered views do (measured on a clean textureless cabinet,
    unposed, both drawers pulled towards the camera: the ratio's median read 1.115 where the depth
    is exact, the static quarter of the pixels 1.000; the view placed at that zoom lay 30 point
    spacings off the others and a drawer went unmatched).

    Returns {(state, k): ((4, 4) float64 view camera -> that state's frame, share)}; empty when
    no view is placed. O(V H W)."""
    placed: dict[tuple[str, int], tuple[np.ndarray, float]] = {}
    start_to_end = np.linalg.inv(end_to_start)
    for k in range(min(len(start), len(end))):
        missing = "start" if start_poses[k] is None else "end" if end_poses[k] is None else None
        twin_pose = end_poses[k] if missing == "start" else start_poses[k]
        if missing is None or twin_pose is None:
            continue
        judged = _same_place(start[k], end[k], start_maps[k], end_maps[k])
        if judged is None:
            continue
        share, scale = judged   # start depth = scale x end depth
        scale = scale if zoom else 1.0
        if missing == "start":
            pose = end_to_start @ np.asarray(twin_pose, dtype=np.float64) @ _zoom(1.0 / scale)
        else:
            pose = start_to_end @ np.asarray(twin_pose, dtype=np.float64) @ _zoom(scale)
        placed[(missing, k)] = (pose, share)
    return placed


def still_pairs(start: list[Frame], end: list[Frame], start_maps: list[Pointmap],
                end_maps: list[Pointmap]) -> dict[int, int]:
    """end view index -> start view index of every view index seen in both states whose camera
    did not move (:func:`_same_place`) and whose whole picture lies still (:func:`image_shift` at
    most ``STILL_MAX_SHIFT_PX``): the pairs whose depth is matched between the states
    (``depth_ratio.match_end_depth``). A pair told still by its tiles alone (a moved door fills
    the view) is left out: its smooth depth ratio rests on the margins the door leaves (measured
    on a realistic fridge: end view 1 registered by geometry at 52 % overlap before its depth
    was matched that way, not after; the pair still places a view through its twin).
    O(V H W log(H W))."""
    pairs = {}
    for k in range(min(len(start), len(end))):
        if not _one_camera(start[k], end[k]):
            continue
        shift = image_shift(start[k].rgb, end[k].rgb)    # judged once: _same_place reads it too
        if shift <= STILL_MAX_SHIFT_PX and _same_place(start[k], end[k], start_maps[k], end_maps[k], shift) is not None:
            pairs[k] = k
    return pairs


def _same_place(start: Frame, end: Frame, start_map: Pointmap, end_map: Pointmap,
                shift: float | None = None) -> tuple[float, float] | None:
    """(share, scale) of :func:`pixel_agreement` for two images of one camera (same size and
    intrinsics) taken from one place (share >= ``STILL_MIN_SHARE``); None otherwise. ``shift``:
    the images' :func:`image_shift` when the caller has it. O(H W log(H W))."""
    if not _one_camera(start, end):
        return None
    judged = pixel_agreement(start, end, start_map, end_map, shift)
    return judged if judged is not None and judged[0] >= STILL_MIN_SHARE else None


def _zoom(scale: float) -> np.ndarray:
    """(4, 4) float64 scaling about the camera centre: a view's depth multiplied by ``scale``."""
    return np.diag([scale, scale, scale, 1.0])


def pixel_agreement(start: Frame, end: Frame, start_map: Pointmap, end_map: Pointmap,
                    shift: float | None = None) -> tuple[float, float] | None:
    """(share, scale) of two images of one camera: scale = median start / end depth over the
    pixels valid in both; share = the fraction of those pixels whose end depth x scale lies within
    ``STILL_DEPTH_TOLERANCE`` (relative) of the start depth and whose colours differ by less than
    ``STILL_COLOUR_TOLERANCE``. None when fewer than ``STILL_MIN_PIXELS`` pixels are valid in
    both, and share 0 when the images are shifted against each other by more than
    ``STILL_MAX_SHIFT_PX`` (:func:`image_shift`) and their tiles do not lie still
    (:func:`still_tiles`): large flat faces agree in depth and colour from a camera moved 10 deg
    as well (a door's front: 47 % of the pixels). ``shift``: the images' :func:`image_shift` when
    the caller has it (computed here otherwise). O(H W log(H W))."""
    depths = [view_depth(f, m) for f, m in ((start, start_map), (end, end_map))]
    if any(d is None for d in depths) or depths[0].shape != depths[1].shape or start.rgb.shape != end.rgb.shape:
        return None
    start_depth, end_depth = depths
    valid = (start_depth > 0) & (end_depth > 0) & np.isfinite(start_depth) & np.isfinite(end_depth)
    if int(valid.sum()) < STILL_MIN_PIXELS:
        return None
    near, far = start_depth[valid], end_depth[valid]
    scale = float(np.median(near / far))
    shift = image_shift(start.rgb, end.rgb) if shift is None else shift
    if shift > STILL_MAX_SHIFT_PX and not still_tiles(start.rgb, end.rgb):
        return 0.0, scale
    depth_agrees = np.abs(far * scale - near) <= STILL_DEPTH_TOLERANCE * near
    colour = np.abs(start.rgb.astype(np.float64) - end.rgb.astype(np.float64)).mean(axis=2)[valid] / 255.0
    return float(np.mean(depth_agrees & (colour < STILL_COLOUR_TOLERANCE))), scale


def image_shift(start_rgb: np.ndarray, end_rgb: np.ndarray) -> float:
    """Length (pixels) of the translation that best lays one image on the other: OpenCV's phase
    correlation of the grey images under a Hann window. ~0 for one camera (the parts that moved
    are a minority of the picture), several pixels when the camera moved (the image content
    shifts). (H, W, 3) uint8 RGB each. O(H W log(H W))."""
    import cv2

    grey = [cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY).astype(np.float64)
            for image in (start_rgb, end_rgb)]
    window = cv2.createHanningWindow((grey[0].shape[1], grey[0].shape[0]), cv2.CV_64F)
    (dx, dy), _ = cv2.phaseCorrelate(grey[0], grey[1], window)
    return float(np.hypot(dx, dy))


# A moved part that fills much of the view (a fridge door) drags the whole picture's phase
# correlation with it: the camera is still judged unmoved when at least STILL_MIN_TILES of the
# textured tiles of a TILE_GRID x TILE_GRID grid, and STILL_MIN_TILE_SHARE of them, lie still (shift
# <= STILL_MAX_SHIFT_PX). Measured (experiment EXP-047):
# camera moved 10-21 deg, 114 view pairs of 19 clean and 19 realistic renders: at most 2 still
# tiles; one camera, the pairs a door or a lid fills (whole-picture shift 20-45 px): a realistic
# fridge 10-12 of 16, a clean dishwasher 4 of 9 (and 2 of 8), a clean laptop 2 of 4.
TILE_GRID = 4
STILL_MIN_TILES = 4
STILL_MIN_TILE_SHARE = 0.4
TILE_MIN_TEXTURE = 4.0          # grey-level standard deviation (0-255) of a tile that phase correlation can place


def still_tiles(start_rgb: np.ndarray, end_rgb: np.ndarray) -> bool:
    """Whether the camera stood still by the tiles: enough textured tiles (both images' grey
    standard deviation >= ``TILE_MIN_TEXTURE``) of a ``TILE_GRID`` grid lie still (phase-correlation
    shift <= ``STILL_MAX_SHIFT_PX``): at least ``STILL_MIN_TILES`` and ``STILL_MIN_TILE_SHARE`` of
    the textured ones. (H, W, 3) uint8 RGB each. O(H W log(H W))."""
    import cv2

    grey = [cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY).astype(np.float64)
            for image in (start_rgb, end_rgb)]
    height, width = grey[0].shape[0] // TILE_GRID, grey[0].shape[1] // TILE_GRID
    if min(height, width) < 8:
        return False
    window = cv2.createHanningWindow((width, height), cv2.CV_64F)
    textured = still = 0
    for row in range(TILE_GRID):
        for column in range(TILE_GRID):
            tiles = [g[row * height:(row + 1) * height, column * width:(column + 1) * width] for g in grey]
            if min(t.std() for t in tiles) < TILE_MIN_TEXTURE:
                continue
            textured += 1
            (dx, dy), _ = cv2.phaseCorrelate(tiles[0], tiles[1], window)
            still += bool(np.hypot(dx, dy) <= STILL_MAX_SHIFT_PX)
    return still >= STILL_MIN_TILES and still >= STILL_MIN_TILE_SHARE * textured


def view_depth(frame: Frame, pointmap: Pointmap) -> np.ndarray | None:
    """(H, W) float64 depth of a view: the frame's own, else the pointmap's."""
    depth = frame.depth if frame.depth is not None else pointmap.depth
    return None if depth is None else np.asarray(depth, dtype=np.float64)


def _one_camera(a: Frame, b: Frame) -> bool:
    """Same image size and intrinsics (within ``K_TOLERANCE``, relative)."""
    if a.camera is None or b.camera is None or a.shape != b.shape:
        return False
    ka, kb = np.asarray(a.camera.K, dtype=np.float64), np.asarray(b.camera.K, dtype=np.float64)
    return bool(np.abs(ka - kb).max() <= K_TOLERANCE * max(np.abs(ka).max(), 1e-12))
