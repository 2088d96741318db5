"""Calibration of the stated joint-axis uncertainty on the shared PartNet-Mobility objects.

    python benchmarks/uncertainty_calibration.py [--scenes DIR] [--out FILE] [--save-rows FILE]
                                                 [--before ROWS.json] [--timing] [OBJECT ...]

Renders every object of ../shared/data/partnet posed (default ``BenchSetting``: 3 views per state,
320x240, clean depth, masks given; renders cached in ``--scenes``), runs ``sparseart.pipeline.run``
+ ``sparseart.evaluate.evaluate`` and, per ground-truth joint matched to a predicted joint, reports
the true axis error, the stated 1-sigma axis uncertainty (``joint.uncertainty["axis_deg"]``), the
Jacobian-only sigma the fitter used to state (``joint.diagnostics["uncertainty_jacobian"]``, when
present) and their ratios, then the coverage: the fraction of non-failed joints (axis error < 10
deg) whose true error is within 1, 2, 3 stated sigma (honest Gaussian 1-sigma: 68 / 95 / 99.7 %; for
the axis angle -- the norm of two tangent components, sigma = their root-sum-square -- 63 / 98 /
99.99 %). The stated sigma's parts are listed too: σ_jk (spatial block jackknife), σ_hs
(half-sample refits); the calibrated floor is the rest. "inlier" = fraction of the part's points
that land on the other state under the fit, "scatter" = fraction off any surface (the quantities of
the overlap and outlier warnings).

``--before ROWS.json``: rows saved by ``--save-rows`` from a run of the previous code; its sigma is
reported as the "before" column and the point estimates (axis errors) are checked to be identical.
``--timing``: also time ``fit_joint`` on synthetic parts with and without the resampling step.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np

from sparseart.bench.objects import BenchSetting, render_cached

PARTNET = Path(__file__).resolve().parents[2] / "shared" / "data" / "partnet"
FAILED_AXIS_DEG = 10.0


def joint_rows(object_dir: Path, scenes: Path, setting: BenchSetting) -> list[dict]:
    """One row per ground-truth joint of one object (matched or not)."""
    from sparseart.bench.evaluate import evaluate
    from sparseart.pipeline import RunOptions, run
    from sparseart.io.scene import load_scene

    scene_dir = scenes / f"{object_dir.name}_{setting.render_key()}"
    gt, _ = render_cached(object_dir, scene_dir, setting)
    scene = load_scene(scene_dir)
    began = time.perf_counter()
    result = run(scene, options=RunOptions(use_masks=setting.use_masks, seed=setting.seed,
                                           segmenter=setting.segmenter))
    seconds = time.perf_counter() - began
    fit_seconds = sum(s.seconds for s in result.stages if s.name == "fit")
    joints = {part.spec.id: joint for part, joint in result.joints}
    rows = []
    for row in evaluate(result, scene, gt):
        joint = joints.get(row.get("part"))
        out = {"object": object_dir.name, "joint": row.get("name"), "gt_type": row.get("gt_type"),
               "pred_type": row.get("pred_type"), "axis_deg": float(row["axis_deg"]),
               "pipeline_seconds": seconds, "fit_seconds": fit_seconds}
        if joint is not None:
            jacobian = joint.diagnostics.get("uncertainty_jacobian", joint.uncertainty)
            out.update(sigma=float(joint.uncertainty["axis_deg"]), sigma_jacobian=float(jacobian["axis_deg"]),
                       sigma_resample=joint.diagnostics.get("uncertainty_resample", {}).get("axis_deg"),
                       sigma_half=joint.diagnostics.get("uncertainty_half", {}).get("axis_deg"),
                       match_fraction=joint.diagnostics.get("match_fraction"), warnings=list(joint.warnings),
                       residual=float(joint.residual), part_radius=joint.diagnostics.get("part_radius"),
                       pairs=joint.diagnostics.get("pairs"), n_start=joint.diagnostics.get("n_start"),
                       n_end=joint.diagnostics.get("n_end"), condition=joint.diagnostics.get("condition"),
                       sigma_floor=joint.diagnostics.get("uncertainty_floor", {}).get("axis_deg"),
                       inlier_fraction=joint.diagnostics.get("inlier_fraction"),
                       scatter_fraction=joint.diagnostics.get("scatter_fraction"),
                       screw_angle_deg=joint.diagnostics.get("screw_angle_deg"))
        rows.append(out)
    return rows


class FitClock:
    """Wraps ``sparseart.joints.fit.fit_joint`` (the pipeline imports it at call time) to sum the
    seconds of every fit and of its uncertainty step (``diagnostics["uncertainty_seconds"]``)."""

    def __init__(self):
        import sparseart.joints.fit as fit_module

        self.module, self.original = fit_module, fit_module.fit_joint
        self.fit_seconds = self.uncertainty_seconds = 0.0
        self.calls = 0

    def __enter__(self):
        def timed(*args, **kwargs):
            began = time.perf_counter()
            estimate = self.original(*args, **kwargs)
            self.fit_seconds += time.perf_counter() - began
            self.uncertainty_seconds += float(estimate.diagnostics.get("uncertainty_seconds", 0.0))
            self.calls += 1
            return estimate

        self.module.fit_joint = timed
        return self

    def __exit__(self, *exc):
        self.module.fit_joint = self.original


def coverage(errors: np.ndarray, sigmas: np.ndarray) -> list[float]:
    return [float(np.mean(errors <= k * sigmas)) for k in (1, 2, 3)]


def timing(repeats: int = 2) -> str:
    """Seconds of fit_joint (auto) with the resampling step off / on, synthetic partial views."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_joints import DOOR_AXIS, DOOR_ORIGIN, make_part

    from sparseart.joints import FitConfig, fit_joint, transform_from_prismatic, transform_from_revolute

    cases = [("door 2000 pts", make_part("door", transform_from_revolute(DOOR_AXIS, DOOR_ORIGIN, np.radians(30)),
                                         count=2000, noise=2e-3, seed=1)),
             ("drawer 2000 pts", make_part("drawer", transform_from_prismatic(np.array([0.0, 0.0, 1.0]), 0.2),
                                           count=2000, noise=2e-3, seed=2)),
             ("door 5000 pts", make_part("door", transform_from_revolute(DOOR_AXIS, DOOR_ORIGIN, np.radians(30)),
                                         count=5000, noise=2e-3, seed=3))]
    lines = ["fit_joint(auto) seconds, best of %d (resamples off -> on, added):" % repeats]
    total = {0: 0.0, 1: 0.0}
    for name, (start, end) in cases:
        best = {}
        for flag, config in ((0, FitConfig(uncertainty_resamples=0, half_samples=0)), (1, FitConfig())):
            times = []
            for _ in range(repeats):
                began = time.perf_counter()
                fit_joint(start, end, config=config)
                times.append(time.perf_counter() - began)
            best[flag] = min(times)
            total[flag] += best[flag]
        lines.append(f"  {name:16s} {best[0]:6.3f} -> {best[1]:6.3f} s  (+{best[1] - best[0]:.3f} s, "
                     f"{100 * (best[1] / best[0] - 1):+.1f} %)")
    lines.append(f"  total            {total[0]:6.3f} -> {total[1]:6.3f} s  ({100 * (total[1] / total[0] - 1):+.1f} %)")
    return "\n".join(lines)


def report(rows: list[dict], before: list[dict] | None, seed: int = 0) -> str:
    header = (f"# {date.today()} on {platform.machine()}, default BenchSetting (3 views/state, posed, clean depth, "
              f"masks, 320x240, seed {seed}); sigma = stated 1-sigma axis uncertainty (deg)")
    old = {(r["object"], r["joint"]): r for r in (before or [])}
    lines = [header, f"{'object':26s} {'joint':18s} {'type':9s} {'err°':>7s} {'σ_old°':>7s} {'σ_jac°':>7s} "
                     f"{'σ_jk°':>7s} {'σ_hs°':>7s} {'σ_new°':>7s} {'err/σo':>7s} {'err/σn':>7s} "
                     f"{'inlier':>6s} {'scatter':>7s}  warnings"]
    identical = True
    for r in rows:
        if "sigma" not in r:
            lines.append(f"{r['object']:26s} {str(r['joint']):18s} unmatched (axis error {r['axis_deg']:.1f})")
            continue
        previous = old.get((r["object"], r["joint"]))
        sigma_old = previous["sigma"] if previous and "sigma" in previous else r["sigma_jacobian"]
        if previous is not None and abs(previous["axis_deg"] - r["axis_deg"]) > 1e-6:
            identical = False
        rs, hs = r.get("sigma_resample"), r.get("sigma_half")
        short = "; ".join(w.split(":")[0][:38] for w in r.get("warnings", []))
        lines.append(f"{r['object']:26s} {str(r['joint'])[:18]:18s} {str(r['pred_type'])[:9]:9s} {r['axis_deg']:7.3f} "
                     f"{sigma_old:7.3f} {r['sigma_jacobian']:7.3f} {'-' if rs is None else f'{rs:7.3f}':>7s} "
                     f"{'-' if hs is None else f'{hs:7.3f}':>7s} "
                     f"{r['sigma']:7.3f} {r['axis_deg'] / sigma_old:7.2f} {r['axis_deg'] / r['sigma']:7.2f} "
                     f"{r.get('inlier_fraction') or 0:6.2f} {r.get('scatter_fraction') or 0:7.2f}  {short}")
    good = [r for r in rows if "sigma" in r and r["axis_deg"] < FAILED_AXIS_DEG]
    failed = [r for r in rows if "sigma" in r and r["axis_deg"] >= FAILED_AXIS_DEG]
    errors = np.array([r["axis_deg"] for r in good])
    columns = {"before (old stated sigma)": np.array([old[(r["object"], r["joint"])]["sigma"]
                                                      if (r["object"], r["joint"]) in old else r["sigma_jacobian"]
                                                      for r in good]),
               "Jacobian part only (new code)": np.array([r["sigma_jacobian"] for r in good]),
               "after (stated sigma)": np.array([r["sigma"] for r in good])}
    lines.append("")
    lines.append(f"coverage over {len(good)} non-failed joints (axis error < {FAILED_AXIS_DEG:g} deg); ideal for a "
                 "1-D Gaussian 68 / 95 / 99.7 %, for the axis angle (2 tangent components, sigma = their RSS, "
                 "isotropic) 63 / 98 / 99.99 %:")
    for name, sigmas in columns.items():
        c = coverage(errors, sigmas)
        ratio = errors / sigmas
        lines.append(f"  {name:30s} <=1σ {100 * c[0]:5.1f} %  <=2σ {100 * c[1]:5.1f} %  <=3σ {100 * c[2]:5.1f} %   "
                     f"err/σ median {np.median(ratio):6.2f}  max {ratio.max():7.2f}")
    if failed:
        lines.append(f"failed joints (axis >= {FAILED_AXIS_DEG:g} deg): "
                     + ", ".join(f"{r['object']}/{r['joint']} {r['axis_deg']:.1f}° σ_new {r['sigma']:.2f}° "
                                 f"warned={'yes' if r.get('warnings') else 'no'}" for r in failed))
    if before is not None:
        lines.append(f"point estimates identical to the 'before' run: {'yes' if identical else 'NO'}")
    def stage_total(table: list[dict]) -> float:
        return sum({r["object"]: r["fit_seconds"] for r in table}.values())

    lines.append(f"fit stage seconds summed over objects: {stage_total(rows):.1f}"
                 + (f" (before: {stage_total(before):.1f}; shared 2-core machine, noisy)" if before else ""))
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("objects", nargs="*")
    parser.add_argument("--scenes", type=Path, default=None, help="render cache (default: a temporary folder)")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--save-rows", type=Path, default=None)
    parser.add_argument("--before", type=Path, default=None)
    parser.add_argument("--timing", action="store_true")
    parser.add_argument("--seed", type=int, default=0, help="render/pipeline seed (views differ per seed)")
    args = parser.parse_args()
    names = args.objects or sorted(p.name for p in PARTNET.iterdir() if (p / "mobility.urdf").exists())
    setting = BenchSetting(seed=args.seed)
    scenes = args.scenes or Path(tempfile.mkdtemp(prefix="sparseart_unc_"))
    rows = []
    with FitClock() as clock:
        for name in names:
            began = time.perf_counter()
            rows.extend(joint_rows(PARTNET / name, scenes, setting))
            print(f"{name}: {time.perf_counter() - began:.1f}s", file=sys.stderr, flush=True)
    if args.save_rows:
        args.save_rows.write_text(json.dumps(rows, indent=1, default=str))
    before = json.loads(args.before.read_text()) if args.before else None
    text = report(rows, before, args.seed)
    if clock.calls:
        base = clock.fit_seconds - clock.uncertainty_seconds
        text += (f"\nfit_joint calls: {clock.calls}, {clock.fit_seconds:.1f} s in all, of which the uncertainty step "
                 f"(block jackknife + half-sample refits + inlier/scatter fractions) {clock.uncertainty_seconds:.1f} s "
                 f"= +{100 * clock.uncertainty_seconds / max(base, 1e-9):.1f} % over the fit without it")
    if args.timing:
        text += "\n\n" + timing()
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
