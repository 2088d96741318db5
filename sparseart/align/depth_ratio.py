"""Depth of the two states made to agree where the camera did not move (posed scenes, and
unposed views whose camera the still test finds unmoved: :func:`sparseart.align.still.still_pairs`).

A robot's head camera sees both states from one pose, but the two depth maps need not agree on
the static scene: a reconstructor run once per state warps and scales each output on its own, and
a sensor may drift. On the realistic renders (warp ~2 % and scale ~1 % drawn per state) the two
states' depths differ by up to 1.3 % over the static scene, 3 cm at 2.5 m, about the motion
split's radius; with that knob alone the robot-shaped setting (one posed view per state, no
masks) found 38 % of the joints against 62 % without it, and 57 % with this correction.

The static scene fills most pixels, so the ratio of the two depths at the same pixel is, on most
pixels, that smooth relative warp; the moving part, a hand and revealed surfaces are outliers.
:func:`match_end_depth` takes the same-camera pairs it is given (unposed) or finds every end view
whose camera equals a start view's (same K; pose
within ``SAME_POSE_DEG`` and ``SAME_POSE_SHARE`` of the depth), takes ``log(z_end / z_start)`` as
medians over small image blocks (a block median is several times less noisy than a pixel, so a
sensor's per-pixel noise does not hide the warp nor fake one), fits them with a smooth tensor
Legendre basis (degree ``DEGREE`` per image axis) by iteratively reweighted least squares (Tukey
weights, started at the mode so that a large moving part cannot pull the start), and divides the
end depth by the fitted ratio when all of these hold:

* the ratio departs from 1 by at least ``MIN_CORRECTION`` over the static pixels (below that a
  sensor's depth already agrees) and by ``SIGNIFICANCE`` standard errors of the fit (independent
  per-pixel noise fits no smooth ratio);
* it stays below ``MAX_CORRECTION`` (beyond that the fit bent onto the moving part);
* at least ``MIN_INLIER_SHARE`` of the blocks seen in both views agree with it.

Measured (one posed view per state, the 16 shared objects, `bench`-rendered): applied to all 16
views with a per-state warp and scale (1.2-1.4 %), to none with clean depth, with 0.5 % per-pixel
noise only, or on the real laptop capture; to 1 of 48 and 5 of 48 object-only views with 1 % / 3 %
per-pixel noise (there a door's motion fills much of the picture and bends the fit; those
settings keep their success rates). Cost per same-camera pair: O(H W) for the block medians plus
O(I b B^2) for I <= ``ITERATIONS`` reweightings over b ~ 10^3 blocks and B = (DEGREE + 1)^2 basis
functions (~10 ms at 320 x 240).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from sparseart.geometry.transforms import rotation_angle
from sparseart.types import Frame, Pointmap

SAME_POSE_DEG = 0.2        # cameras closer than this in rotation ...
SAME_POSE_SHARE = 0.002    # ... and this share of the median depth in position are one camera
DEGREE = 2                 # Legendre degree per image axis of the log depth ratio
ITERATIONS = 8
TUKEY_C = 4.685            # Tukey biweight constant, in robust sigmas
START_BAND = 0.1           # the mode is searched among log ratios within +-this
MODE_BIN = 0.002           # histogram bin of the log ratio for the starting mode
START_SIGMAS = 3.0         # first fit: blocks within this many peak widths (sigma) of the mode
MIN_CORRECTION = 0.005     # largest |ratio - 1| below this: nothing to correct (sensor-level)
LARGEST_PERCENTILE = 95.0  # "largest": this percentile of |ratio - 1| over the static blocks
SIGNIFICANCE = 10.0        # the largest ratio must exceed this many standard errors of the fit
MAX_CORRECTION = 0.1       # a fitted ratio beyond 10 % is the moving part, not a warp
MIN_INLIER_SHARE = 0.5     # the static blocks must be at least this share of the blocks seen in both
SIGMA_FLOOR = 1e-4         # robust sigma floor of the log ratio (clean renders agree exactly)
BLOCK_SHARE = 1.0 / 30.0   # the ratio is fitted on block medians: block side = this x the short side
MIN_BLOCKS_PER_TERM = 5    # at least this many blocks per basis function


@dataclass
class DepthRatio:
    """The fitted relative depth of one end view against the start view with the same camera.

    start_image, end_image: the two images (``STATE/rgb/NAME``); applied: whether the end depth
    was divided by the ratio; largest: the ``LARGEST_PERCENTILE`` percentile of |ratio - 1| over
    the static blocks; standard_error: of the fitted log ratio (typical block); spread_before /
    spread_after: robust sigma of the block log ratios kept as static before and after the fit;
    inliers: share of the blocks the fit kept as static; reason: why it was not applied
    ("" when applied).
    """

    start_image: str
    end_image: str
    applied: bool
    largest: float
    standard_error: float
    spread_before: float
    spread_after: float
    inliers: float
    reason: str = ""

    def report(self) -> dict:
        """JSON-ready entry of the registration report."""
        entry = {"start": self.start_image, "end": self.end_image, "applied": self.applied,
                 "largest": round(self.largest, 5), "standard_error": round(self.standard_error, 6),
                 "spread_before": round(self.spread_before, 6), "spread_after": round(self.spread_after, 6),
                 "inliers": round(self.inliers, 3)}
        if self.reason:
            entry["reason"] = self.reason
        return entry


def same_camera(a: Frame, b: Frame, depth: float) -> bool:
    """Do two frames hold one camera: same size and K, poses within ``SAME_POSE_DEG`` and
    ``SAME_POSE_SHARE`` x ``depth`` (the scene's depth, its units)? False without poses. O(1)."""
    ca, cb = a.camera, b.camera
    if ca is None or cb is None or ca.cam_to_world is None or cb.cam_to_world is None:
        return False
    if (ca.width, ca.height) != (cb.width, cb.height) or not np.allclose(ca.K, cb.K, rtol=1e-6, atol=1e-6):
        return False
    turn = np.degrees(rotation_angle(ca.cam_to_world[:3, :3].T @ cb.cam_to_world[:3, :3]))
    gap = np.linalg.norm(ca.cam_to_world[:3, 3] - cb.cam_to_world[:3, 3])
    return turn <= SAME_POSE_DEG and gap <= SAME_POSE_SHARE * depth


def _basis(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(P, (DEGREE + 1)^2) tensor Legendre basis at normalised pixel coordinates u, v in [-1, 1]."""
    from numpy.polynomial import legendre

    pu = legendre.legvander(u, DEGREE)
    pv = legendre.legvander(v, DEGREE)
    return (pu[:, :, None] * pv[:, None, :]).reshape(len(u), -1)


def _block_medians(depth_start: np.ndarray, depth_end: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """log(depth_end / depth_start) as medians over square blocks (side ``BLOCK_SHARE`` of the
    short image side, at least 4 px) of the pixels valid in both, for blocks at least half valid:
    a block median is ~6x less noisy than a pixel (8 x 8 blocks), and a block straddling a moving
    part's border takes its majority. Returns (ratio, u, v), (B,) each, u / v the block centres
    normalised to [-1, 1]. O(H W log b)."""
    height, width = depth_start.shape
    side = max(4, int(round(BLOCK_SHARE * min(height, width))))
    rows, cols = height // side, width // side
    a = depth_start[:rows * side, :cols * side]
    b = depth_end[:rows * side, :cols * side]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where((a > 0) & (b > 0), np.log(b / a), np.nan)
    blocks = ratio.reshape(rows, side, cols, side).transpose(0, 2, 1, 3).reshape(rows, cols, side * side)
    filled = np.isfinite(blocks).mean(axis=2) >= 0.5
    medians = np.full((rows, cols), np.nan)
    if filled.any():
        medians[filled] = np.nanmedian(blocks[filled], axis=1)
    r, c = np.nonzero(filled)
    u = ((c + 0.5) * side) / width * 2.0 - 1.0
    v = ((r + 0.5) * side) / height * 2.0 - 1.0
    return medians[filled], u, v


def _robust_sigma(residual: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(residual - np.median(residual))))


def fit_log_ratio(depth_start: np.ndarray, depth_end: np.ndarray) -> tuple[np.ndarray | None, dict]:
    """Smooth fit of log(depth_end / depth_start) over the image (module doc).

    depth_*: (H, W) float64 depth along the optical axis (0 = invalid), one camera, any unit.
    Returns ((H, W) float64 fitted log ratio, or None when too few blocks have depth in both, and
    the numbers: largest, standard_error, spread_before / spread_after (robust sigma of the block
    log ratios kept as static, before and after the fit), inliers (their share of the blocks)).
    O(H W + I b B^2)."""
    height, width = depth_start.shape
    numbers = {"largest": 0.0, "spread_before": 0.0, "spread_after": 0.0, "inliers": 0.0, "standard_error": 0.0}
    basis_size = (DEGREE + 1) ** 2
    ratio, u, v = _block_medians(depth_start, depth_end)
    if len(ratio) < MIN_BLOCKS_PER_TERM * basis_size:
        return None, numbers
    basis = _basis(u, v)
    # Start at the mode, not the median: a large moving part may cover most of an object-only view.
    near = ratio[np.abs(ratio) < START_BAND]
    if len(near) < MIN_BLOCKS_PER_TERM * basis_size:
        return None, numbers
    counts, edges = np.histogram(near, bins=int(round(2 * START_BAND / MODE_BIN)), range=(-START_BAND, START_BAND))
    counts = np.convolve(counts, np.ones(3), mode="same")
    peak = int(counts.argmax())
    centre = float(0.5 * (edges[peak] + edges[peak + 1]))
    # The peak's half width at half height is the static blocks' spread (the moving ones lie outside).
    low, high = peak, peak
    while low > 0 and counts[low - 1] > 0.5 * counts[peak]:
        low -= 1
    while high < len(counts) - 1 and counts[high + 1] > 0.5 * counts[peak]:
        high += 1
    spread = (high - low + 1) * MODE_BIN / 2.355
    band = min(START_BAND, max(START_SIGMAS * spread, TUKEY_C * SIGMA_FLOOR))
    weights = (np.abs(ratio - centre) < band).astype(np.float64)
    sigma_before = _robust_sigma(ratio[weights > 0]) if weights.any() else 0.0
    coefficients = np.zeros(basis_size)
    for _ in range(ITERATIONS):
        if weights.sum() < MIN_BLOCKS_PER_TERM * basis_size:
            return None, numbers
        root = np.sqrt(weights)
        coefficients = np.linalg.lstsq(basis * root[:, None], ratio * root, rcond=None)[0]
        residual = ratio - basis @ coefficients
        sigma = max(_robust_sigma(residual[weights > 0]), SIGMA_FLOOR)
        z = residual / (TUKEY_C * sigma)
        weights = np.where(np.abs(z) < 1.0, (1.0 - z * z) ** 2, 0.0)
    inliers = weights > 0
    if not inliers.any():
        return None, numbers
    grid_v, grid_u = np.meshgrid((np.arange(height) + 0.5) / height * 2.0 - 1.0,
                                 (np.arange(width) + 0.5) / width * 2.0 - 1.0, indexing="ij")
    fitted = basis @ coefficients
    # Beyond the blocks the fit saw, a polynomial runs away: hold it within the fitted range.
    field = np.clip((_basis(grid_u.ravel(), grid_v.ravel()) @ coefficients).reshape(height, width),
                    fitted[inliers].min(), fitted[inliers].max())
    sigma_after = _robust_sigma(residual[inliers])
    numbers.update(largest=float(np.percentile(np.abs(np.expm1(fitted[inliers])), LARGEST_PERCENTILE)),
                   spread_before=sigma_before,
                   spread_after=sigma_after, inliers=float(inliers.mean()),
                   standard_error=sigma_after * float(np.sqrt(basis_size / max(int(inliers.sum()), 1))))
    return field, numbers


def _scaled_pointmap(pointmap: Pointmap, frame: Frame, factor: np.ndarray) -> Pointmap:
    """Every point moved along its camera ray by ``factor`` (H, W) of its depth; the camera sits
    at its pose's centre, or at the origin for an unposed view (its pointmap is in its own camera
    frame)."""
    pose = frame.camera.cam_to_world if frame.camera is not None else None
    centre = pose[:3, 3] if pose is not None else np.zeros(3)
    points = centre + (pointmap.points - centre) * factor.reshape(-1, 1)
    depth = pointmap.depth * factor if pointmap.depth is not None else None
    return replace(pointmap, points=points, depth=depth)


def match_end_depth(start_frames: list[Frame], end_frames: list[Frame], start_maps: list[Pointmap],
                    end_maps: list[Pointmap], pairs: dict[int, int] | None = None,
                    ) -> tuple[list[Frame], list[Pointmap], list[DepthRatio]]:
    """End views that share a start view's camera, their depth divided by the fitted ratio.

    pairs: end view index -> start view index of the pairs known to share one camera (an unposed
    scene's still cameras, :func:`~sparseart.align.still.still_pairs`); None = found from the
    frames' poses (posed RGB-D: depth images and cam_to_world). Frames without depth pass
    unchanged. Returns (end frames with corrected depth, end pointmaps moved along their rays,
    one DepthRatio per same-camera pair). O(V_s V_e + pairs x fit)."""
    frames, maps, report = list(end_frames), list(end_maps), []
    for e, end in enumerate(end_frames):
        if end.depth is None:
            continue
        valid = end.depth[end.depth > 0]
        if valid.size == 0:
            continue
        if pairs is not None:
            match = pairs.get(e)
        else:   # the pose gap is judged against the view's median depth
            depth = float(np.median(valid))
            match = next((s for s, start in enumerate(start_frames)
                          if start.depth is not None and same_camera(start, end, depth)), None)
        if match is None or start_frames[match].depth is None:
            continue
        field, numbers = fit_log_ratio(start_frames[match].depth, end.depth)
        reason = ""
        if field is None:
            reason = "too few pixels with depth in both views"
        elif numbers["largest"] < MIN_CORRECTION:
            reason = f"depths agree already (largest ratio {numbers['largest']:.2%} < {MIN_CORRECTION:.2%})"
        elif numbers["largest"] > MAX_CORRECTION:
            reason = f"the fitted ratio reaches {numbers['largest']:.0%}: that is motion, not a depth warp"
        elif numbers["inliers"] < MIN_INLIER_SHARE:
            reason = f"only {numbers['inliers']:.0%} of the image agrees on one smooth ratio"
        elif numbers["largest"] < SIGNIFICANCE * numbers["standard_error"]:
            reason = "the smooth ratio is within the noise of the fit"
        applied = not reason
        if applied:
            factor = np.exp(-field)
            frames[e] = replace(end, depth=np.where(end.depth > 0, end.depth * factor, 0.0))
            maps[e] = _scaled_pointmap(end_maps[e], end, factor)
        report.append(DepthRatio(start_frames[match].image, end.image, applied, numbers["largest"],
                                 numbers["standard_error"], numbers["spread_before"], numbers["spread_after"],
                                 numbers["inliers"], reason))
    return frames, maps, report
