"""PNG plots of a ``sparseart bench`` summary (matplotlib, Agg backend, imported lazily).

* :func:`plot_error_vs_time`: median axis angle error against median seconds per scene, one point
  per (setting, method), the Pareto front (fastest for its error) drawn and its points ringed.
* :func:`plot_error_vs_factor`: median axis error and success rate against views per state and
  against depth-noise level, one line per method.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from sparseart.io.scene import write_bytes_atomic

METHOD_STYLE = {"sparseart": ("tab:blue", "o"), "icp_peer": ("tab:orange", "s")}
ERROR_FLOOR_DEG = 0.01  # log axis: errors below this are drawn at it


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points not dominated in (time, error): no other point is at most as slow and
    at most as wrong and strictly better in one. O(P^2) for P points (P ~ tens)."""
    front = []
    for i, (t, e) in enumerate(points):
        if not any(t2 <= t and e2 <= e and (t2 < t or e2 < e) for j, (t2, e2) in enumerate(points) if j != i):
            front.append(i)
    return front



def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(figure, path: Path) -> Path:
    import io

    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=120)
    write_bytes_atomic(path, buffer.getvalue())
    return path


def plot_error_vs_time(summary: list[dict[str, Any]], path: str | Path) -> Path:
    """Error against run time. summary: entries of ``bench_grid.aggregate(rows, ("setting",
    "method"))``. Writes ``path`` (PNG) atomically and returns it."""
    plt = _pyplot()
    entries = [s for s in summary if s.get("axis_deg_median") is not None]
    points = [(s["seconds_median"], max(s["axis_deg_median"], ERROR_FLOOR_DEG)) for s in entries]
    front = set(pareto_front(points))
    figure, axes = plt.subplots(figsize=(8, 5.5))
    for method in dict.fromkeys(s["method"] for s in entries):
        colour, marker = METHOD_STYLE.get(method, ("tab:gray", "^"))
        chosen = [i for i, s in enumerate(entries) if s["method"] == method]
        axes.scatter([points[i][0] for i in chosen], [points[i][1] for i in chosen], c=colour, marker=marker,
                     s=45, label=method, zorder=3)
        for i in chosen:
            axes.annotate(entries[i]["setting"], points[i], fontsize=7, xytext=(4, 3), textcoords="offset points")
    ordered = sorted(front, key=lambda i: points[i][0])
    if ordered:
        axes.plot([points[i][0] for i in ordered], [points[i][1] for i in ordered], "k--", lw=1, drawstyle="steps-post",
                  label="Pareto front", zorder=2)
        axes.scatter([points[i][0] for i in ordered], [points[i][1] for i in ordered], s=160,
                     facecolors="none", edgecolors="k", zorder=4)
    axes.set_yscale("log")
    axes.set_xlabel("median wall seconds per scene (pipeline, rendering excluded)")
    axes.set_ylabel("median axis angle error (deg, log)")
    axes.set_title("error against run time: one point per setting and method")
    axes.grid(True, which="both", alpha=0.3)
    axes.legend()
    figure.tight_layout()
    try:
        return _save(figure, Path(path))
    finally:
        plt.close(figure)


def _series(summary: list[dict[str, Any]], method: str, factor: str, base_only: dict[str, Any]) -> list[tuple]:
    """(factor value, axis median, success) of one method's settings that differ from the default
    in ``factor`` only."""
    out = []
    for s in summary:
        if s["method"] != method or s.get(factor) is None:
            continue
        if all(s.get(k, v) == v for k, v in base_only.items() if k != factor):
            out.append((s[factor], s["axis_deg_median"], s["success_rate"]))
    return sorted(out)


def plot_error_vs_factor(summary: list[dict[str, Any]], path: str | Path) -> Path:
    """Median axis error and success rate against views per state and depth-noise level (the
    noisy settings also carry flying pixels). Writes ``path`` (PNG) atomically and returns it."""
    plt = _pyplot()
    default = {"views": 3, "posed": True, "depth_noise": 0.0, "pose_noise_deg": 0.0, "refine": False}
    figure, axes = plt.subplots(2, 2, figsize=(10, 7), sharex="col")
    for method in dict.fromkeys(s["method"] for s in summary):
        colour, marker = METHOD_STYLE.get(method, ("tab:gray", "^"))
        for column, (factor, scale) in enumerate((("views", 1.0), ("depth_noise", 100.0))):
            series = _series(summary, method, factor, default)
            if not series:
                continue
            xs = [x * scale for x, _, _ in series]
            axes[0, column].plot(xs, [max(e, ERROR_FLOOR_DEG) for _, e, _ in series], marker=marker,
                                 color=colour, label=method)
            axes[1, column].plot(xs, [s for _, _, s in series], marker=marker, color=colour, label=method)
    for column, label in enumerate(("views per state", "depth noise sigma (%), with flying pixels")):
        axes[0, column].set_yscale("log")
        axes[0, column].set_ylabel("median axis error (deg)")
        axes[1, column].set_ylabel("success (axis < 10 deg)")
        axes[1, column].set_ylim(-0.05, 1.05)
        axes[1, column].set_xlabel(label)
        for row in range(2):
            axes[row, column].grid(True, alpha=0.3)
            axes[row, column].legend(fontsize=8)
    figure.suptitle("error against number of views and depth noise")
    figure.tight_layout()
    try:
        return _save(figure, Path(path))
    finally:
        plt.close(figure)
