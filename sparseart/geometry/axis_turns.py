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

ANGLE_STEP_DEG = 10.0   # angle grid of the search; the caller's ICP refines within a step
GRID_CELLS = 64         # at most this many cells across a grid (the cell grows for large parts)


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
    grid = np.zeros(index.max(axis=0) + 1, dtype=np.float32)
    grid[index[:, 0], index[:, 1]] = 1.0
    return grid, low


def axis_turns(source: np.ndarray, target: np.ndarray, axes: np.ndarray, cell: float,
               keep: int = 2) -> list[np.ndarray]:
    """Candidate turns of ``source`` onto ``target`` about lines parallel to each of ``axes``.

    source, target: (N, 3) / (M, 3) float64, one frame. axes: (K, 3) axis directions. cell: grid
    spacing (the caller's inlier radius; coarsened so that no grid exceeds ``GRID_CELLS`` across).
    Returns up to ``keep`` (4, 4) motions per axis: the angles (of the ``ANGLE_STEP_DEG`` grid,
    identity excluded) whose best in-plane shift lays the largest share of the source's occupied
    cells onto the target's, best first per axis. All angles of an axis are correlated in one
    batched FFT. O(K A G log G + K A N) for A angles and grids of G cells.
    """
    if len(source) < 3 or len(target) < 3 or not cell > 0:
        return []
    from scipy.fft import irfft2, next_fast_len, rfft2

    centre = source.mean(axis=0)
    angles = np.deg2rad(np.arange(ANGLE_STEP_DEG, 360.0, ANGLE_STEP_DEG))
    cos, sin = np.cos(angles)[:, None], np.sin(angles)[:, None]
    motions = []
    for axis in np.asarray(axes, dtype=np.float64):
        axis = axis / np.linalg.norm(axis)
        basis = _plane_basis(axis)
        flat_source, flat_target = (source - centre) @ basis, target @ basis
        reach = float(np.linalg.norm(flat_source, axis=1).max())
        spread = float(np.ptp(flat_target, axis=0).max())
        step = max(cell, 2.0 * reach / GRID_CELLS, spread / GRID_CELLS)
        target_grid, target_low = _occupancy(flat_target, step)
        # every angle's turned source in one stack of grids with a common corner at -reach
        x, y = flat_source[:, 0][None], flat_source[:, 1][None]
        turned = np.stack([x * cos - y * sin, x * sin + y * cos], axis=-1)          # (A, N, 2)
        index = np.floor((turned + reach) / step).astype(np.int64)
        size = int(np.floor(2.0 * reach / step)) + 1
        grids = np.zeros((len(angles), size, size), dtype=np.float32)
        grids[np.repeat(np.arange(len(angles)), len(flat_source)), index[..., 0].ravel(), index[..., 1].ravel()] = 1.0
        full = (target_grid.shape[0] + size - 1, target_grid.shape[1] + size - 1)
        shape = tuple(next_fast_len(n, real=True) for n in full)      # zero padding beyond ``full`` is inert
        overlap = irfft2(rfft2(target_grid, shape)[None] * rfft2(grids[:, ::-1, ::-1], shape, axes=(1, 2)),
                         shape, axes=(1, 2))[:, :full[0], :full[1]]
        flat_peak = overlap.reshape(len(angles), -1).argmax(axis=1)
        share = overlap.reshape(len(angles), -1)[np.arange(len(angles)), flat_peak]
        share = share / np.minimum(grids.sum(axis=(1, 2)), target_grid.sum())
        for k in np.argsort(-share, kind="stable")[:keep]:
            peak = np.array(np.unravel_index(flat_peak[k], full))
            # the stack's corner cell (-reach, -reach) lands on target cell ``peak - (size - 1)``
            shift = target_low + (peak - (size - 1)) * step + reach
            rotation = Rotation.from_rotvec(axis * angles[k]).as_matrix()
            motion = np.eye(4)
            motion[:3, :3] = rotation
            # the centre goes to its in-plane target spot at its own height along the axis
            motion[:3, 3] = basis @ shift + axis * (centre @ axis) - rotation @ centre
            motions.append(motion)
    return motions
