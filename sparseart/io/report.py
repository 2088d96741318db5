"""Pictures for people: a one-page report PNG of an :class:`~sparseart.types.Articulation`.

Left and middle: the start and end clouds (3-D scatter, at most ``MAX_PLOT_POINTS`` each, chosen
with a fixed seed) coloured by part, with every joint drawn: a revolute axis as a line through its
origin (length = the part's extent) and a prismatic axis as an arrow of the fitted distance from
the part centre. Right: wall seconds per pipeline stage. matplotlib (Agg) is imported lazily.
"""
from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np

from sparseart.io.ply import part_colour, part_colours
from sparseart.geometry.sampling import random_subset
from sparseart.io.scene import write_bytes_atomic
from sparseart.types import Articulation

MAX_PLOT_POINTS = 15000


def _draw_joints(axes, result: Articulation, points: np.ndarray, part_of: np.ndarray) -> None:
    for part, joint in result.joints:
        own = points[part_of == part.spec.id]
        extent = float(np.linalg.norm(np.ptp(own, axis=0))) if len(own) else 0.1
        colour = part_colour(part.spec.id)
        axis, origin = np.asarray(joint.axis), np.asarray(joint.origin)
        if joint.type == "revolute":
            ends = np.stack([origin - 0.6 * extent * axis, origin + 0.6 * extent * axis])
            axes.plot(*ends.T, color="k", lw=3.5)
            axes.plot(*ends.T, color=colour, lw=2.0, label=f"part {part.spec.id}: revolute "
                      f"{math.degrees(joint.angle):.1f}°")
        else:
            axes.quiver(*origin, *(axis * joint.distance), color=colour, lw=2.5, arrow_length_ratio=0.2,
                        label=f"part {part.spec.id}: prismatic {joint.distance:.3f}")


def _equal_box(axes, points: np.ndarray) -> None:
    centre = 0.5 * (points.max(0) + points.min(0))
    half = 0.5 * float(np.ptp(points, axis=0).max()) or 1.0
    axes.set_xlim(centre[0] - half, centre[0] + half)
    axes.set_ylim(centre[1] - half, centre[1] + half)
    axes.set_zlim(centre[2] - half, centre[2] + half)


def report_figure(result: Articulation):
    """The matplotlib Figure of the report (caller closes it). Raises ValueError without clouds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if result.start_cloud is None or result.end_cloud is None or result.labels is None:
        raise ValueError("--report: the result carries no clouds/labels to draw")
    rng = np.random.default_rng(0)
    figure = plt.figure(figsize=(15, 5.2))
    every = np.concatenate([result.start_cloud.points, result.end_cloud.points])
    for column, (state, cloud, part_of) in enumerate((("start", result.start_cloud, result.labels.start_part),
                                                       ("end", result.end_cloud, result.labels.end_part))):
        axes = figure.add_subplot(1, 3, column + 1, projection="3d")
        keep = random_subset(len(cloud), MAX_PLOT_POINTS, rng)
        axes.scatter(*cloud.points[keep].T, c=part_colours(part_of[keep]), s=0.6, depthshade=False)
        _draw_joints(axes, result, result.start_cloud.points, result.labels.start_part)
        _equal_box(axes, every)
        axes.set_title(f"{state}: {len(cloud)} points, coloured by part")
        axes.set_xlabel("x")
        axes.set_ylabel("y")
        axes.set_zlabel("z")
        if result.joints and column == 0:
            axes.legend(fontsize=7, loc="upper left")
    axes = figure.add_subplot(1, 3, 3)
    ran = [s for s in result.stages if s.ran]
    axes.barh([s.name for s in ran], [s.seconds for s in ran], color="tab:blue")
    for k, stage in enumerate(ran):
        axes.text(stage.seconds, k, f" {stage.seconds:.2f}s", va="center", fontsize=8)
    axes.invert_yaxis()
    axes.set_xlabel("wall seconds")
    axes.set_title(f"stages (total {sum(s.seconds for s in result.stages):.2f}s)")
    figure.suptitle(f"sparseart: {len(result.joints)} joint(s), frame {result.frame_kind}, units {result.units}"
                    + (f", {len(result.warnings)} warning(s)" if result.warnings else ""))
    figure.tight_layout()
    return figure


def write_report(result: Articulation, path: str | Path) -> Path:
    """Render :func:`report_figure` to ``path`` (PNG) atomically and return the path."""
    figure = report_figure(result)  # selects the Agg backend before pyplot is imported here
    import matplotlib.pyplot as plt

    try:
        buffer = io.BytesIO()
        figure.savefig(buffer, format="png", dpi=100)
    finally:
        plt.close(figure)
    path = Path(path)
    write_bytes_atomic(path, buffer.getvalue())
    return path
