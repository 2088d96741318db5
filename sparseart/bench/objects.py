"""Accuracy against run time on rendered PartNet-Mobility objects.

``evaluate_object`` renders one object at two joint states (the same open3d renderer as
``sparseart render``; cached per rendering setting), runs the pipeline -- and optionally the ICP
peer (``sparseart.bench.icp_peer``) on the same clouds -- and scores every ground-truth joint
(design section 4). The test suite, ``benchmarks/`` and ``sparseart bench`` (``bench_grid``) use it.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from sparseart.bench import metrics
from sparseart.datasets.raycast import RENDERER_VERSION
from sparseart.datasets.realism import CLEAN, Realism

METHOD_SPARSEART = "sparseart"
METHOD_PEER = "icp_peer"


@dataclass
class BenchSetting:
    """One rendering + pipeline configuration.

    views: images per state. posed: write cam_to_world. depth_noise: multiplicative sigma
    (0.01 = 1 %). flying_pixels: fraction of depth-edge pixels given mixed depths.
    pose_noise_deg / pose_noise_m: error of the written camera poses (degrees / object units,
    i.e. metres for metric objects). refine: ask the pipeline for refinement (needs
    ``RunOptions.refine``). segmenter: ``RunOptions.segmenter`` ("auto" = the rendered masks;
    "builtin" ignores them and segments the images). matcher: ``RunOptions.matcher`` spec (None = SIFT).
    budget: the joint fit's named budget (``FitConfig.for_budget``: fast | default | best).
    same_cameras: the end state is seen from the start state's cameras (a robot's head camera, a
    tripod); False draws fresh end cameras (a phone walked round the object between the states).
    name: label of the setting in tables and plots.
    geometry: also build the URDF / MJCF / USD exports, check them in the simulators and score the
    part meshes against the true ones (:mod:`sparseart.bench.geometry`; sparseart rows only).
    """

    views: int = 3
    seed: int = 0
    posed: bool = True
    use_masks: bool = True
    scramble_masks: bool = False
    depth_noise: float = 0.0
    width: int = 320
    height: int = 240
    flying_pixels: float = 0.0
    pose_noise_deg: float = 0.0
    pose_noise_m: float = 0.0
    refine: bool = False
    segmenter: str = "auto"
    realism: Realism = CLEAN
    matcher: str | None = None
    budget: str = "default"
    same_cameras: bool = True
    name: str = "default"
    geometry: bool = False

    def render_key(self) -> str:
        """A folder-name-safe key of every field that changes the rendered scene."""
        return (f"v{self.views}_s{self.seed}_{'posed' if self.posed else 'unposed'}"
                f"{'_scr' if self.scramble_masks else ''}_dn{self.depth_noise:g}_fp{self.flying_pixels:g}"
                f"_pn{self.pose_noise_deg:g}-{self.pose_noise_m:g}_{self.width}x{self.height}"
                + ("" if self.same_cameras else "_moved")
                + ("" if self.realism.is_clean else "_r" + realism_key(self.realism)))


def realism_key(realism: Realism) -> str:
    """The non-zero knobs of a realism setting as 'knob1-level1.knob2-level2' (sorted, short)."""
    return ".".join(f"{k}-{v:g}" for k, v in sorted(realism.levels().items()) if v > 0)


def refine_available() -> bool:
    """True when ``sparseart.pipeline.RunOptions`` has a ``refine`` option (added by issue 5)."""
    from sparseart.pipeline import RunOptions

    return hasattr(RunOptions(), "refine")


def render_cached(object_dir: str | Path, scene_dir: str | Path, setting: BenchSetting) -> tuple[dict, float]:
    """Render ``object_dir`` into ``scene_dir`` unless a complete render of the same setting is
    there (``gt.json`` + ``bench_render.json`` stamp). Returns (gt dict, render seconds; 0 when cached)."""
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.io.scene import write_json_atomic

    scene_dir = Path(scene_dir)
    stamp_path = scene_dir / "bench_render.json"
    stamp = {"object": str(Path(object_dir).resolve()), "key": setting.render_key(), "renderer": RENDERER_VERSION}
    if stamp_path.exists() and (scene_dir / "gt.json").exists():
        try:
            if json.loads(stamp_path.read_text()) == stamp:
                return json.loads((scene_dir / "gt.json").read_text()), 0.0
        except (OSError, ValueError):
            pass
    began = time.perf_counter()
    gt = render_partnet_scene(object_dir, scene_dir, views=setting.views, seed=setting.seed,
                              width=setting.width, height=setting.height, posed=setting.posed,
                              scramble_masks=setting.scramble_masks, depth_noise=setting.depth_noise,
                              write_masks=True, flying_pixels=setting.flying_pixels,
                              pose_noise_deg=setting.pose_noise_deg, pose_noise_m=setting.pose_noise_m,
                              same_cameras=setting.same_cameras, realism=setting.realism)
    seconds = time.perf_counter() - began
    write_json_atomic(stamp_path, stamp)
    return gt, seconds


def evaluate_object(object_dir: str | Path, work_dir: str | Path, setting: BenchSetting | None = None,
                    peer: bool = False, peer_options: Any = None) -> list[dict[str, Any]]:
    """Render (cached), run and score one object; with ``peer`` also the ICP peer on the same clouds.

    Returns one row per ground-truth joint and method: object, setting, method, joint name,
    gt/pred type, axis_deg, position (revolute, object units), state (deg | object units),
    seconds (render; pipeline total; per stage), warnings.
    The peer's ``pipeline_seconds`` = the shared stages it reuses (read, lift, align, label) plus
    its own registration, so both methods' totals cover the same work.
    """
    from sparseart.bench.evaluate import evaluate
    from sparseart.pipeline import RunOptions, run
    from sparseart.io.scene import load_scene

    setting = setting or BenchSetting()
    object_dir = Path(object_dir)
    scene_dir = Path(work_dir) / f"{object_dir.name}_{setting.render_key()}"
    gt, render_seconds = render_cached(object_dir, scene_dir, setting)
    from sparseart.joints.config import FitConfig

    options = RunOptions(use_masks=setting.use_masks, seed=setting.seed, segmenter=setting.segmenter,
                         matcher=setting.matcher, fit=FitConfig.for_budget(setting.budget))
    if setting.refine:
        if not hasattr(options, "refine"):
            raise ValueError("bench: setting asks for refinement but RunOptions has no 'refine' option")
        options.refine = True
    began = time.perf_counter()
    scene = load_scene(scene_dir)
    result = run(scene, options=options)
    read_seconds = time.perf_counter() - began - sum(s.seconds for s in result.stages)
    pipeline_seconds = time.perf_counter() - began
    outcomes = [(METHOD_SPARSEART, result, pipeline_seconds)]
    if peer:
        from sparseart.bench.icp_peer import icp_peer_from_result

        peer_result = icp_peer_from_result(result, peer_options)
        outcomes.append((METHOD_PEER, peer_result, max(read_seconds, 0.0) + sum(s.seconds for s in peer_result.stages)))
    rows = []
    for method, outcome, seconds in outcomes:
        stage_seconds = {s.name: s.seconds for s in outcome.stages if s.ran}
        scored = evaluate(outcome, scene, gt)
        if setting.geometry and method == METHOD_SPARSEART:
            from sparseart.bench.geometry import geometry_fields

            geometry_fields(outcome, scene, gt, object_dir, scored, scene_dir / f"exports_{setting.name}")
        for row in scored:
            row.update(object=object_dir.name, setting=setting.name, method=method, render_seconds=render_seconds,
                       pipeline_seconds=seconds, stage_seconds=stage_seconds, n_predicted=len(outcome.joints),
                       warnings=list(outcome.warnings), config={**asdict(setting), "realism": realism_key(setting.realism) or "clean"})
            rows.append(row)
    return rows


def format_table(rows: list[dict[str, Any]]) -> str:
    """A plain-text table: one line per joint (and method), then the summary of design section 4
    (one summary line per method when several are present)."""
    methods = sorted({row.get("method", METHOD_SPARSEART) for row in rows})
    show_method = len(methods) > 1
    lines = [f"{'object':26s} {'joint':9s} " + (f"{'method':9s} " if show_method else "")
             + f"{'gt':9s} {'pred':9s} {'axis°':>7s} {'pos':>7s} {'state':>8s} {'sec':>6s}"]
    for row in rows:
        position = "-" if row["position"] is None else f"{row['position']:.4f}"
        state_unit = "°" if row["gt_type"] == "revolute" else ""
        method = f"{row.get('method', METHOD_SPARSEART):9s} " if show_method else ""
        lines.append(f"{row['object']:26s} {str(row['name']):9s} {method}{row['gt_type']:9s} "
                     f"{str(row['pred_type']):9s} {row['axis_deg']:7.2f} {position:>7s} "
                     f"{row['state']:7.3f}{state_unit:1s} {row['pipeline_seconds']:6.2f}")
    lines.append("")
    for method in methods:
        summary = metrics.summarise([r for r in rows if r.get("method", METHOD_SPARSEART) == method])
        lines.append((f"{method}: " if show_method else "") + _summary_line(summary))
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
