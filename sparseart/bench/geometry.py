"""Geometry of the exports in the bench (``sparseart bench --geometry``): the Chamfer distance of the
fused part meshes against the ground-truth meshes, the seconds each export step costs, and the
simulator check of every export (:func:`sparseart.sim.replay.check_export`).

CD-s / CD-m / CD-w (PARIS, DTA, ArtGS): the static part, each movable part and the whole object,
all at the START state, in gt.json's world frame (unposed results mapped by the first start
camera's true pose, as the joint errors are). Each is :func:`sparseart.bench.metrics.chamfer_distance`
(squared L2, mean per direction, the two directions added; object units squared) between
``CD_SAMPLES`` area-uniform samples of the predicted and the true meshes; tables show it x 1000 as
the peers do. The fused meshes hold only what the views saw, so the true -> predicted term also
counts the unseen surface.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from sparseart.bench import metrics
from sparseart.types import Articulation, Scene

CD_SAMPLES = 10000
EXPORT_FORMATS = ("urdf", "mjcf", "usd")


def _samples(meshes: list[tuple[np.ndarray, np.ndarray]], seed: int = 0) -> np.ndarray:
    vertices, faces, offset = [], [], 0
    for v, f in meshes:
        vertices.append(np.asarray(v, dtype=np.float64))
        faces.append(np.asarray(f, dtype=np.int64) + offset)
        offset += len(v)
    return metrics.sample_mesh_points(np.concatenate(vertices), np.concatenate(faces), CD_SAMPLES, seed=seed)


def true_meshes(object_dir: str | Path, gt: dict[str, Any]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """mask id -> (vertices (V, 3) float64, triangles (F, 3) int64) of each true part group at the
    start state, world frame (1 = the static base, 2.. = each movable joint's subtree)."""
    from sparseart.datasets.meshes import load_articulated_object

    obj = load_articulated_object(object_dir)
    return {label: (np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64))
            for mesh, label in obj.posed_parts(gt["joint_states"]["start"])}


def object_geometry(result: Articulation, scene: Scene, gt: dict[str, Any], object_dir: str | Path,
                    out_dir: str | Path) -> dict[str, Any]:
    """Build and write every export of ``result`` into ``out_dir`` (timed), check them in the
    simulators and score the meshes against the truth.

    Returns {"seconds": {surfaces, collision, urdf, mjcf, usd}, "checks": check_export rows,
    "cd_s": float | None, "cd_w": float, "parts": {part id: (world vertices, triangles)},
    "truth": {mask id: (vertices, triangles)}}. CDs in object units squared.
    """
    from sparseart.bench.evaluate import _result_to_gt_frame
    from sparseart.geometry.transforms import apply_transform
    from sparseart.io.mjcf import write_mjcf
    from sparseart.io.urdf import write_urdf
    from sparseart.io.usd import write_usd
    from sparseart.sim.model import build_model
    from sparseart.sim.replay import check_export

    model = build_model(result, name="object")
    seconds = dict(model.seconds)
    for fmt, writer in zip(EXPORT_FORMATS, (write_urdf, write_mjcf, write_usd)):
        began = time.perf_counter()
        writer(result, out_dir, name="object", model=model)
        seconds[fmt] = time.perf_counter() - began
    checks = check_export(result, out_dir)
    to_world = _result_to_gt_frame(result, gt, scene)
    parts = {link.part_id: (apply_transform(to_world, link.vertices + link.origin), link.faces)
             for link in model.links if len(link.faces)}
    truth = true_meshes(object_dir, gt)
    static = gt.get("static_mask_id", 1)
    cd_s = (metrics.chamfer_distance(_samples([parts[0]]), _samples([truth[static]]))
            if 0 in parts and static in truth else None)
    cd_w = metrics.chamfer_distance(_samples(list(parts.values())), _samples(list(truth.values())))
    return {"seconds": seconds, "checks": checks, "cd_s": cd_s, "cd_w": cd_w, "parts": parts, "truth": truth}


def geometry_fields(result: Articulation, scene: Scene, gt: dict[str, Any], object_dir: str | Path,
                    rows: list[dict[str, Any]], out_dir: str | Path) -> None:
    """Add the geometry columns to one object's sparseart rows (one per true joint), in place:
    ``cd_s``, ``cd_w``, ``cd_m`` (the row's matched part against its true part; None when
    unmatched), ``export_seconds`` (per step), and of the row's part over the formats:
    ``landing_rel`` (worst), ``sink_rel`` (worst simulator), ``axis_dot`` (least agreeing)."""
    geometry = object_geometry(result, scene, gt, object_dir, out_dir)
    by_joint = {g["name"]: g for g in gt["joints"]}
    for row in rows:
        part = row.get("part")
        mask_id = by_joint.get(row.get("name"), {}).get("mask_id")
        cd_m = None
        if part in geometry["parts"] and mask_id in geometry["truth"]:
            cd_m = metrics.chamfer_distance(_samples([geometry["parts"][part]]), _samples([geometry["truth"][mask_id]]))
        checks = [c for c in geometry["checks"] if c["part"] == part]
        row.update(cd_s=geometry["cd_s"], cd_w=geometry["cd_w"], cd_m=cd_m, export_seconds=dict(geometry["seconds"]),
                   landing_rel=max((c["landing_rel"] for c in checks), default=None),
                   sink_rel=max((c["sink_rel"] for c in checks if c["sink_rel"] is not None), default=None),
                   axis_dot=min((c["axis_dot"] for c in checks), default=None))
