"""Accuracy against run time on rendered PartNet-Mobility objects.

``evaluate_object`` renders one object at two joint states (the same open3d renderer as
``sparseart render``), runs the pipeline and scores every ground-truth joint (design section 4).
The test suite and ``benchmarks/`` use it; ``sparseart bench`` (issue 6) builds on it.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from . import metrics


@dataclass
class BenchSetting:
    """One rendering + pipeline configuration."""

    views: int = 3
    seed: int = 0
    posed: bool = True
    use_masks: bool = True
    scramble_masks: bool = False
    depth_noise: float = 0.0
    width: int = 320
    height: int = 240


def evaluate_object(object_dir: str | Path, work_dir: str | Path,
                    setting: BenchSetting | None = None) -> list[dict[str, Any]]:
    """Render, run and score one object.

    Returns one row per ground-truth joint: object, joint name, gt/pred type, axis_deg,
    position (revolute, object units), state (deg | object units), seconds (render, pipeline per
    stage), warnings count.
    """
    from .datasets.partnet import render_partnet_scene
    from .evaluate import evaluate
    from .pipeline import RunOptions, run
    from .scene import load_scene

    setting = setting or BenchSetting()
    object_dir = Path(object_dir)
    scene_dir = Path(work_dir) / f"{object_dir.name}_v{setting.views}_s{setting.seed}"
    began = time.perf_counter()
    gt = render_partnet_scene(object_dir, scene_dir, views=setting.views, seed=setting.seed,
                              width=setting.width, height=setting.height, posed=setting.posed,
                              scramble_masks=setting.scramble_masks, depth_noise=setting.depth_noise,
                              write_masks=True)
    render_seconds = time.perf_counter() - began
    began = time.perf_counter()
    scene = load_scene(scene_dir)
    result = run(scene, options=RunOptions(use_masks=setting.use_masks, seed=setting.seed))
    pipeline_seconds = time.perf_counter() - began
    rows = evaluate(result, scene, gt)
    stage_seconds = {s.name: s.seconds for s in result.stages if s.ran}
    for row in rows:
        row.update(object=object_dir.name, render_seconds=render_seconds,
                   pipeline_seconds=pipeline_seconds, stage_seconds=stage_seconds,
                   n_predicted=len(result.joints), warnings=list(result.warnings))
    return rows


def format_table(rows: list[dict[str, Any]]) -> str:
    """A plain-text table: one line per joint, then the summary of design section 4."""
    lines = [f"{'object':26s} {'joint':9s} {'gt':9s} {'pred':9s} {'axis°':>7s} {'pos':>7s} "
             f"{'state':>8s} {'sec':>6s}"]
    for row in rows:
        position = "-" if row["position"] is None else f"{row['position']:.4f}"
        state_unit = "°" if row["gt_type"] == "revolute" else ""
        lines.append(f"{row['object']:26s} {str(row['name']):9s} {row['gt_type']:9s} "
                     f"{str(row['pred_type']):9s} {row['axis_deg']:7.2f} {position:>7s} "
                     f"{row['state']:7.3f}{state_unit:1s} {row['pipeline_seconds']:6.2f}")
    summary = metrics.summarise(rows)
    lines.append("")
    lines.append(_summary_line(summary))
    return "\n".join(lines)


def _summary_line(summary: dict[str, Any]) -> str:
    def fmt(value: Any, digits: int = 3) -> str:
        return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"

    return (f"joints {summary['count']}: type acc {fmt(summary['type_accuracy'])}, success "
            f"{fmt(summary['success_rate'])}, axis mean/median {fmt(summary['axis_deg_mean'], 2)}/"
            f"{fmt(summary['axis_deg_median'], 2)} deg, position mean/median "
            f"{fmt(summary['position_mean'], 4)}/{fmt(summary['position_median'], 4)}, state rev "
            f"median {fmt(summary['state_revolute_deg_median'], 2)} deg, state pris median "
            f"{fmt(summary['state_prismatic_median'], 4)}")
