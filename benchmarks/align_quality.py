"""Registration quality of unposed scenes, SIFT vs a learned matcher, through the whole pipeline.

Runs ``sparseart.bench.grid.run_bench`` on the shared PartNet-Mobility objects for the settings
``unposed`` (clean RGB-D, 3 views, no camera poses) and ``realistic`` (every realism knob at level 1:
background, depth warp / scale / smear / noise, hand occluder, image noise, JPEG, ragged masks),
once with SIFT (no matcher) and once per ``--matcher`` spec (e.g. XFeat + LighterGlue), and reads
the registration report of every scene (``AlignedScene.registration``, the same dict the pipeline
puts into ``articulation.json``) by wrapping :func:`sparseart.align.scene.align_scene`.

Per setting and matcher: share of views registered, share of scenes with every view registered,
share of state alignments done (and trusted) by features, joint accuracy (axis error median,
success = axis < 10 deg, type accuracy), mean seconds per scene (pipeline, and its matching step).
Then the matcher's cost per image (detector) and per image pair (matcher) on this CPU.

    python3 benchmarks/align_quality.py [--objects DIR ...] [--out /tmp/align_quality] \
        [--matcher xfeat:../shared/models/xfeat.onnx,../shared/models/lighterglue_L3.onnx] [--no-sift] \
        [--settings unposed realistic] [--result benchmarks/results/align_quality.txt]

Rendered scenes are cached in OUT/scenes (shared by every matcher run).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import sparseart.align.scene as align_scene_module  # noqa: E402
from sparseart.bench.grid import grid_settings, run_bench  # noqa: E402

PARTNET = REPO.parent / "shared" / "data" / "partnet"
MODELS = REPO.parent / "shared" / "models"
DEFAULT_MATCHER = f"xfeat:{MODELS / 'xfeat.onnx'},{MODELS / 'lighterglue_L3.onnx'}"


def capture_reports() -> dict[str, dict]:
    """Wrap align_scene so every scene's registration report (and align seconds) is kept, keyed by
    the scene folder's name."""
    reports: dict[str, dict] = {}
    original = align_scene_module.align_scene

    def wrapped(scene, lifted, **kwargs):
        aligned = original(scene, lifted, **kwargs)
        reports[Path(scene.root).name] = {"registration": aligned.registration, "alignment": aligned.alignment,
                                          "seconds": dict(aligned.seconds)}
        return aligned

    align_scene_module.align_scene = wrapped
    return reports


def summarise(rows: list[dict], reports: dict[str, dict], scene_names: dict[tuple[str, str], str]) -> dict:
    objects = sorted({r["object"] for r in rows})
    views = registered = complete = by_features = 0
    match_seconds, scene_seconds = [], []
    for obj in objects:
        row = next(r for r in rows if r["object"] == obj)
        scene_seconds.append(row["pipeline_seconds"])
        report = reports.get(scene_names[(obj, row["setting"])], {})
        entries = report.get("registration", {}).get("views", [])
        views += len(entries)
        done = sum(1 for v in entries if v["registered"])
        registered += done
        complete += int(bool(entries) and done == len(entries))
        by_features += int(report.get("alignment") == "features")
        match_seconds.append(report.get("registration", {}).get("seconds", {}).get("match", 0.0))
    axis = [r["axis_deg"] for r in rows]
    return {"objects": len(objects), "joints": len(rows),
            "views_registered": registered / max(views, 1), "views": f"{registered}/{views}",
            "scenes_all_views": f"{complete}/{len(objects)}",
            "states_by_features": by_features / max(len(objects), 1), "states": f"{by_features}/{len(objects)}",
            "axis_median": statistics.median(axis) if axis else None,
            "success": sum(a < 10 for a in axis) / max(len(axis), 1),
            "type_accuracy": sum(bool(r["type_correct"]) for r in rows) / max(len(rows), 1),
            "seconds_per_scene": statistics.mean(scene_seconds) if scene_seconds else None,
            "match_seconds_per_scene": statistics.mean(match_seconds) if match_seconds else None}


def matcher_cost(spec: str, scene_dirs: list[Path], threads: int = 2) -> dict:
    """Wall and CPU seconds of the detector per image and the matcher per pair (features cached),
    on the first start and end image of each scene."""
    import cv2

    from sparseart.align.matchers import open_matcher

    matcher = open_matcher(spec, threads=threads)
    extractor = getattr(matcher, "extractor", None)
    images = []
    for d in scene_dirs:
        for state in ("start", "end"):
            images.append(cv2.cvtColor(cv2.imread(str(d / state / "rgb" / "000.png")), cv2.COLOR_BGR2RGB))
    detect_wall, detect_cpu = [], []
    if extractor is not None:
        for i, image in enumerate(images):
            wall, cpu = time.perf_counter(), time.process_time()
            extractor.features(image, key=("cost", i))
            detect_wall.append(time.perf_counter() - wall)
            detect_cpu.append(time.process_time() - cpu)
    pair_wall, pair_cpu = [], []
    for i in range(0, len(images) - 1, 2):
        wall, cpu = time.perf_counter(), time.process_time()
        matcher.match(images[i], images[i + 1], key_a=("cost", i), key_b=("cost", i + 1))
        pair_wall.append(time.perf_counter() - wall)
        pair_cpu.append(time.process_time() - cpu)
    med = lambda xs: statistics.median(xs) if xs else None  # noqa: E731
    return {"detector_wall_per_image": med(detect_wall), "detector_cpu_per_image": med(detect_cpu),
            "matcher_wall_per_pair": med(pair_wall), "matcher_cpu_per_pair": med(pair_cpu),
            "images": len(images), "pairs": len(pair_wall), "threads": threads}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--objects", nargs="*", type=Path)
    parser.add_argument("--out", type=Path, default=Path("/tmp/align_quality"))
    parser.add_argument("--matcher", nargs="*", default=[DEFAULT_MATCHER])
    parser.add_argument("--no-sift", action="store_true")
    parser.add_argument("--settings", nargs="*", default=["unposed", "realistic"])
    parser.add_argument("--result", type=Path, default=REPO / "benchmarks" / "results" / "align_quality.txt")
    args = parser.parse_args(argv)
    objects = args.objects or sorted(p for p in PARTNET.iterdir() if (p / "mobility.urdf").is_file())
    if len(objects) == 1 and not (objects[0] / "mobility.urdf").is_file():
        objects = sorted(p for p in objects[0].iterdir() if (p / "mobility.urdf").is_file())
    base, _ = grid_settings()
    chosen = [s for s in base if s.name in args.settings]
    reports = capture_reports()
    runs = ([("sift", None)] if not args.no_sift else []) + [(_label(m), m) for m in args.matcher]
    results, lines = [], []
    for label, spec in runs:
        for setting in chosen:
            run_setting = replace(setting, matcher=spec)
            began = time.perf_counter()
            bench = run_bench(objects, args.out, settings=[run_setting], peer=False, plots=False)
            scene_names = {(o.name, setting.name): f"{o.name}_{run_setting.render_key()}" for o in objects}
            rows = [r for r in bench.rows if r.get("method", "sparseart") == "sparseart"]
            summary = summarise(rows, reports, scene_names)
            summary.update(matcher=label, setting=setting.name, failures=bench.failures,
                           wall=time.perf_counter() - began)
            results.append(summary)
            lines.append(_line(summary))
            print(lines[-1], flush=True)
            (args.out / f"reports_{label}_{setting.name}.json").write_text(json.dumps(
                {name: reports[name] for name in scene_names.values() if name in reports}, indent=1, default=str))
            (args.out / f"rows_{label}_{setting.name}.json").write_text(json.dumps(rows, indent=1, default=str))
    costs = {}
    scene_dirs = sorted((args.out / "scenes").glob("*_unposed_*"))[:4]
    for label, spec in runs:
        if spec is not None and scene_dirs:
            costs[label] = matcher_cost(spec, scene_dirs)
    text = _report(results, costs, objects)
    print(text)
    args.result.parent.mkdir(parents=True, exist_ok=True)
    args.result.write_text(text)
    args.result.with_suffix(".json").write_text(json.dumps({"results": results, "costs": costs}, indent=1, default=str))
    return 0


def _label(spec: str) -> str:
    text = str(spec)
    if text.startswith("xfeat:"):
        return "xfeat+lighterglue" if "," in text else "xfeat-mnn"
    return Path(text).stem


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def _line(s: dict) -> str:
    return (f"{s['setting']:10s} {s['matcher']:18s} views {s['views']:>7s} ({_fmt(s['views_registered'], '.0%'):>4s}), "
            f"all views {s['scenes_all_views']:>5s}, states by features {s['states']:>5s} "
            f"({_fmt(s['states_by_features'], '.0%'):>4s}); joints {s['joints']}: axis median "
            f"{_fmt(s['axis_median'], '.2f')} deg, success {_fmt(s['success'], '.0%')}, type "
            f"{_fmt(s['type_accuracy'], '.0%')}; {_fmt(s['seconds_per_scene'], '.1f')} s/scene "
            f"(matching {_fmt(s['match_seconds_per_scene'], '.1f')} s)")


def _report(results: list[dict], costs: dict, objects: list[Path]) -> str:
    from sparseart.bench.grid import machine_line

    lines = [f"# unposed registration, {len(objects)} PartNet-Mobility objects, 3 views per state, 320x240; "
             f"{machine_line()} (shared with other jobs: seconds are upper bounds)",
             "# views = registered / all views of both states (registration report); states by features = "
             "state alignments done and trusted by features (else the static-part ICP fallback ran)", ""]
    lines += [_line(s) for s in results]
    for s in results:
        lines += [f"failed: {s['setting']} {s['matcher']}: {f}" for f in s["failures"]]
    for label, cost in costs.items():
        lines.append(f"{label}: detector {_fmt(cost['detector_wall_per_image'], '.3f')} s wall / "
                     f"{_fmt(cost['detector_cpu_per_image'], '.3f')} s CPU per image, matcher "
                     f"{_fmt(cost['matcher_wall_per_pair'], '.3f')} s wall / {_fmt(cost['matcher_cpu_per_pair'], '.3f')} "
                     f"s CPU per pair ({cost['threads']} onnxruntime threads, 320x240 images upscaled to 640x480)")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
