"""SPLART refinement on rendered PartNet-Mobility objects: joint errors before/after and seconds.

    python benchmarks/refine_partnet.py [--views 4] [--holdout 1] [--perturb] [--out FILE] [OBJECT ...]

For each object: render a posed two-state scene (320x240, clean depth, masks), run the default
pipeline (the seed joints), refine every movable joint with the default RefineOptions, and
score with sparseart.bench.evaluate. ``--perturb`` first degrades each seed (axis tilted 5 deg, pivot
moved 3 % of the object size, angle +5 deg or distance +10 %) to test recovery from a worse
seed. Reports, per joint: axis / position / state error of the seed, of the refined candidate
and of the accepted joint (the guard keeps the seed unless the refinement is better), whether it
was accepted, PSNR and the refinement's seconds. Timings are wall-clock on a shared machine.
"""
from __future__ import annotations

import argparse
import copy
import json
import platform
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np

PARTNET = Path(__file__).resolve().parents[2] / "shared" / "data" / "partnet"
DEFAULT_OBJECTS = ("door_9168", "drawer_26525", "laptop_rotate_10211", "microwave_7128", "storage_40147")


def _perturb(joint, diameter: float, rng: np.random.Generator):
    from scipy.spatial.transform import Rotation

    from sparseart.geometry.transforms import transform_from_prismatic, transform_from_revolute

    bad = copy.deepcopy(joint)
    tilt = rng.normal(size=3)
    tilt -= tilt.dot(bad.axis) * bad.axis
    tilt /= np.linalg.norm(tilt)
    bad.axis = Rotation.from_rotvec(np.radians(5.0) * tilt).apply(bad.axis)
    if bad.type == "revolute":
        offset = rng.normal(size=3)
        offset -= offset.dot(bad.axis) * bad.axis
        bad.origin = bad.origin + 0.03 * diameter * offset / np.linalg.norm(offset)
        bad.angle = bad.angle + np.radians(5.0)
        bad.transform = transform_from_revolute(bad.axis, bad.origin, bad.angle)
    else:
        bad.distance = 1.1 * bad.distance
        bad.transform = transform_from_prismatic(bad.axis, bad.distance)
    return bad


def _errors(result, scene, gt) -> list[dict]:
    from sparseart.bench.evaluate import evaluate

    return evaluate(result, scene, gt)


def bench_object(name: str, work: Path, views: int, holdout: int, perturb: bool) -> list[dict]:
    from sparseart.datasets.partnet import render_partnet_scene
    from sparseart.bench.evaluate import load_gt
    from sparseart.pipeline import run
    from sparseart.refine.api import RefineOptions, refine_part
    from sparseart.io.scene import load_scene

    scene_dir = work / name
    render_partnet_scene(PARTNET / name, scene_dir, views=views, seed=0)
    scene = load_scene(scene_dir)
    gt = load_gt(scene_dir / "gt.json")
    began = time.perf_counter()
    result = run(scene)
    pipeline_seconds = time.perf_counter() - began
    points = result.start_cloud.points
    diameter = float(np.linalg.norm(points.max(0) - points.min(0)))
    rng = np.random.default_rng(0)
    if perturb:
        for part in result.parts:
            if part.joint is not None:
                part.joint = _perturb(part.joint, diameter, rng)
    before = _errors(result, scene, gt)
    candidate = copy.deepcopy(result)
    centre = np.median(points, axis=0)
    outcomes = {}
    for part in result.parts:
        if part.joint is None:
            continue
        outcome = refine_part(result.start_cloud, result.end_cloud, result.labels, part.spec.id, part.joint, scene,
                              RefineOptions(holdout_views=holdout), None, centre)
        outcomes[part.spec.id] = outcome
        part.joint = outcome.joint
        after = outcome.diagnostics["after"]
        for other in candidate.parts:
            if other.spec.id == part.spec.id:
                other.joint.axis, other.joint.origin = np.array(after["axis"]), np.array(after["origin"])
                other.joint.angle, other.joint.distance = after["angle"], after["distance"]
    accepted = _errors(result, scene, gt)
    refined = _errors(candidate, scene, gt)
    rows = []
    for b, r, a in zip(before, refined, accepted):
        outcome = outcomes.get(b.get("part"))
        info = outcome.diagnostics if outcome else {}
        rows.append({"object": name, "joint": b["name"], "type": b.get("pred_type"), "perturbed": perturb,
                     "axis_before": b["axis_deg"], "axis_refined": r["axis_deg"], "axis_after": a["axis_deg"],
                     "pos_before": b["position"], "pos_refined": r["position"], "pos_after": a["position"],
                     "state_before": b["state"], "state_refined": r["state"], "state_after": a["state"],
                     "accepted": info.get("accepted"), "why": info.get("why"),
                     "psnr_train": (info.get("psnr") or {}).get("train"),
                     "psnr_heldout": (info.get("psnr") or {}).get("heldout"),
                     "refine_seconds": info.get("seconds"), "pipeline_seconds": pipeline_seconds})
    return rows


def _fmt(value, digits=3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def format_rows(rows: list[dict]) -> str:
    head = (f"{'object':22s} {'joint':8s} {'type':9s} {'axis° seed/ref/out':>22s} {'pos seed/ref/out':>24s} "
            f"{'state seed/ref/out':>24s} {'acc':>4s} {'PSNR tr/ho':>12s} {'refine s':>8s}")
    lines = [head]
    for r in rows:
        lines.append(f"{r['object']:22s} {str(r['joint']):8s} {str(r['type']):9s} "
                     f"{_fmt(r['axis_before'], 2):>6s}/{_fmt(r['axis_refined'], 2):>6s}/{_fmt(r['axis_after'], 2):>6s}   "
                     f"{_fmt(r['pos_before'], 4):>7s}/{_fmt(r['pos_refined'], 4):>7s}/{_fmt(r['pos_after'], 4):>7s}  "
                     f"{_fmt(r['state_before'], 4):>7s}/{_fmt(r['state_refined'], 4):>7s}/{_fmt(r['state_after'], 4):>7s}  "
                     f"{'yes' if r['accepted'] else 'no':>4s} {_fmt(r['psnr_train'], 1):>5s}/{_fmt(r['psnr_heldout'], 1):>5s} "
                     f"{_fmt(r['refine_seconds'], 1):>8s}")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("objects", nargs="*")
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--holdout", type=int, default=1)
    parser.add_argument("--perturb", action="store_true")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if not PARTNET.is_dir():
        print(f"no shared data at {PARTNET}", file=sys.stderr)
        return 2
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for name in args.objects or DEFAULT_OBJECTS:
            began = time.perf_counter()
            rows.extend(bench_object(name, Path(work), args.views, args.holdout, args.perturb))
            print(f"{name}: {time.perf_counter() - began:.1f}s", file=sys.stderr, flush=True)
    header = (f"# {date.today()} {platform.machine()}, 2 torch threads on a shared 2-core VM (timings inflated by "
              f"other jobs), views={args.views} (holdout {args.holdout}/state), 320x240 posed clean depth, "
              f"{'seeds perturbed (5 deg, 3 % pivot, +5 deg / +10 %)' if args.perturb else 'pipeline seeds'}; "
              f"default RefineOptions. seed = pipeline joint, ref = refined candidate, out = after the guard. "
              f"axis/state in deg (prismatic state in object units), pos in object units.")
    table = header + "\n" + format_rows(rows)
    print(table)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(table + "\n")
        args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
