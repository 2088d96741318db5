"""Global search for a turn about a known axis direction: every angle, and the in-plane shift by
2-D correlation.

A part that turns about its own symmetry axis (a faucet handle's round cap, a knob, a rotating
lid) mostly lands on itself: local registration from "stayed put" stays there, and principal-
frame hypotheses are dominated by the symmetric bulk. When the axis *direction* is known (one of
the static body's axes; man-made joints almost always turn about one), the remaining unknowns are
the angle and where the axis pierces the plane across it. Projected onto that plane, a turn about
any parallel axis is a 2-D rotation plus a 2-D shift: each angle of a fixed grid rotates the
source's projection, and the shift that lays the most occupied cells of it onto the target's is the
peak of the two occupancy grids' cross-correlation (FFT). The best angles per axis become 3-D
motions (no shift along the axis) for the caller to refine and score.

Frames: any one frame for both point sets (the labeler's), one unit; ``cell`` is in that unit.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

ANGLE_STEP_DEG = 5.0    # angle grid of the search; the caller's ICP refines within a step


def _plane_basis(axis: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal columns spanning the plane across the unit ``axis``."""
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(axis, u)], axis=1)


def _occupancy(points_2d: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Binary occupancy grid of (N, 2) points at ``cell`` spacing and its lower corner (2,)."""
    low = points_2d.min(axis=0)
    index = np.floor((points_2d - low) / cell).astype(np.int64)
    grid = np.zeros(index.max(axis=0) + 1)
    grid[index[:, 0], index[:, 1]] = 1.0
    return grid, low


def _correlation(target: np.ndarray, source: np.ndarray) -> np.ndarray:
    """Full 2-D cross-correlation of two grids by FFT: entry k counts the source cells landing on
    target cells when the source's corner cell sits at target cell ``k - (source.shape - 1)``."""
    shape = tuple(np.asarray(target.shape) + np.asarray(source.shape) - 1)
    product = np.fft.rfft2(target, shape) * np.fft.rfft2(source[::-1, ::-1], shape)
    return np.fft.irfft2(product, shape)


def axis_turns(source: np.ndarray, target: np.ndarray, axes: np.ndarray, cell: float,
               keep: int = 2) -> list[np.ndarray]:
    """Candidate turns of ``source`` onto ``target`` about lines parallel to each of ``axes``.

    source, target: (N, 3) / (M, 3) float64, one frame. axes: (K, 3) axis directions. cell: grid
    spacing (the caller's inlier radius). Returns up to ``keep`` (4, 4) motions per axis: the
    angles (of the ``ANGLE_STEP_DEG`` grid, identity excluded) whose best in-plane shift lays the
    largest share of the source's occupied cells onto the target's, best first per axis.
    O(K A (G log G + N)) for A angles and grids of G cells.
    """
    if len(source) < 3 or len(target) < 3 or not cell > 0:
        return []
    centre = source.mean(axis=0)
    motions = []
    for axis in np.asarray(axes, dtype=np.float64):
        axis = axis / np.linalg.norm(axis)
        basis = _plane_basis(axis)
        flat_source = (source - centre) @ basis
        target_grid, target_low = _occupancy(target @ basis, cell)
        found = []
        for angle in np.deg2rad(np.arange(ANGLE_STEP_DEG, 360.0, ANGLE_STEP_DEG)):
            c, s = np.cos(angle), np.sin(angle)
            turned = flat_source @ np.array([[c, s], [-s, c]])   # rows turned by +angle about axis
            source_grid, source_low = _occupancy(turned, cell)
            overlap = _correlation(target_grid, source_grid)
            peak = np.unravel_index(int(np.argmax(overlap)), overlap.shape)
            share = overlap[peak] / min(source_grid.sum(), target_grid.sum())
            # the source grid's corner cell lands on target cell ``peak - (shape - 1)``
            offset = (np.asarray(peak) - (np.asarray(source_grid.shape) - 1)) * cell
            found.append((-share, float(angle), target_low + offset - source_low))
        found.sort(key=lambda item: item[0])
        for _, angle, shift in found[:keep]:
            rotation = Rotation.from_rotvec(axis * angle).as_matrix()
            motion = np.eye(4)
            motion[:3, :3] = rotation
            # the centre goes to its in-plane target spot at its own height along the axis
            motion[:3, 3] = basis @ shift + axis * (centre @ axis) - rotation @ centre
            motions.append(motion)
    return motions
