"""The static body's own axes: the normals of its dominant faces (its Manhattan frame), and
whether a slide runs along one of them.

Drawers, racks and trays slide along their carcass' axes. Two readings use this: the fitter
re-fits a slide that runs along none of them (:func:`~sparseart.joints.candidates.body_axis_fits`),
and a sibling slide along one lends its direction even when a rival widened its own sigma
(:func:`~sparseart.joints.siblings.slides_like_siblings`). Both use one window,
``BODY_AXIS_WINDOW_DEG``.
"""
from __future__ import annotations

import numpy as np

from sparseart.geometry.planes import manhattan_frame
from sparseart.geometry.transforms import axis_angle_deg

BODY_FRAME_POINTS = 20000    # static points (strided) whose normals give the body's Manhattan frame
BODY_AXIS_WINDOW_DEG = 10.0  # a slide within this of an axis of the body's frame runs along the body


def static_body_axes(static_points: np.ndarray | None) -> np.ndarray | None:
    """(3, 3) columns: the static body's Manhattan frame (the normals of its dominant faces,
    :func:`~sparseart.geometry.planes.manhattan_frame`) from at most ``BODY_FRAME_POINTS`` of
    ``static_points`` ((S, 3) float64, scene frame); None with fewer than 50. Unlike the principal
    axes, the faces do not move with what else the static part holds: measured on the realistic
    oven renders (seeds 0, 2, 3) its axes lay 0.9-4.2 deg from the racks' slide, the principal axes
    8.4-15.8 deg. O(S log S) for the normals."""
    if static_points is None or len(static_points) < 50:
        return None
    return manhattan_frame(static_points[:: max(1, len(static_points) // BODY_FRAME_POINTS)])


def along_body_axes(axis: np.ndarray, body_axes: np.ndarray | None) -> bool:
    """Does the direction ``axis`` (3,) run within ``BODY_AXIS_WINDOW_DEG`` of a column of
    ``body_axes`` ((3, 3), :func:`static_body_axes`)? False without a frame. O(1)."""
    return body_axes is not None and min(axis_angle_deg(axis, b) for b in np.asarray(body_axes).T) \
        <= BODY_AXIS_WINDOW_DEG
