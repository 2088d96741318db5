"""Where a run's time goes: seconds per stage and fit sub-step against points per state and parts.

Two sweeps on the shared PartNet objects (posed RGB-D, 3 views per state):

* points: one object rendered at the resolution that gives about 10k, 50k, 200k and 1M points
  per state (the default 320x240 gives ~40k; width scaled by sqrt(target / points at 320x240));
* parts: objects with 1, 2 and 5 movable parts at the default 320x240.

Each scene runs ``sparseart.run`` once (the first run of the process is a warm-up that pays the
imports, open3d's included, and is not reported). Stages come from the run's own clock
(read, lift, label, fit, ...) made to read the process's CPU time: on a shared 2-core machine
wall seconds swing 1-5x with the other users' load, CPU seconds do not (the wall total and the
load average are recorded next to them). The fit's sub-steps (prepare = cleaning + the shared
subsamples, seeds, optimise, select = type selection, uncertainty, reliability) are summed over
every ``fit_joint`` call of the candidate search (``sparseart.joints.fit.collect_seconds``).
``--cprofile`` adds the hottest functions of each run (CPU time).

Scenes are rendered once into ``--scenes`` (reused across runs). Writes ``table.txt``,
``results.json`` and ``profile.png`` into ``--out``.

    python3 benchmarks/profile_stages.py [--object microwave_7128] [--points 10000 50000 200000 1000000]
        [--parts-objects microwave_7128 storage_40147 oven_7179_multi] [--budget default]
        [--scenes /tmp/profile_scenes] [--out benchmarks/results/profile] [--cprofile]
    python3 benchmarks/profile_stages.py --guard default unposed depth1%+fly [--bench-dir /tmp/bench_speed]

``--guard``: the accuracy guard instead -- ``sparseart.bench.grid.run_bench`` on the 16 objects for
the named settings (success, median axis, type accuracy, seconds per scene, fit wall / CPU
seconds per joint) into ``OUT/guard.json``.

Hot paths and their cost (N points per state, P movable parts, n = 1500 matching / Chamfer
points per side): read O(pixels); lift O(pixels); label (rule labeler: per-state grouping,
pairwise rigid registration of segment groups) O(N log N) per registered pair; fit per part
O(W log W) preparation (W = min(N, 60k) working points: cleaning k-NN and radius graph,
normals of the samples, trees), then per seed motion and joint type a few sparse one-to-one
matchings (~O(n^1.5)) and robust solves O(n p^2) per evaluation, independent of N.
"""
from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import sparseart.clock as clock_module
from sparseart.bench.objects import BenchSetting, render_cached
from sparseart.io.scene import load_scene
from sparseart.joints.fit import SUB_STEPS, collect_seconds
from sparseart.pipeline import RunOptions, run

PARTNET = REPO.parent / "shared" / "data" / "partnet"
STAGES = ("read", "lift", "label", "align", "fit")
DEFAULT_WIDTH = 320


class _ProcessTime:
    """Stand-in for the ``time`` module inside the stage clock: CPU seconds of this process."""

    perf_counter = staticmethod(time.process_time)


def profile_scene(scene_dir: Path, options: RunOptions, cprofile: bool = False) -> dict:
    """Run one scene; CPU seconds per stage and fit sub-step, wall total, points per state,
    joints, load average."""
    load_before = os.getloadavg()[0]
    profiler = cProfile.Profile(time.process_time) if cprofile else None
    saved_time, clock_module.time = clock_module.time, _ProcessTime  # the stage clock reads CPU time
    cpu = time.process_time()
    wall = time.perf_counter()
    try:
        with collect_seconds() as fit_steps:
            if profiler:
                profiler.enable()
            began = time.process_time()
            scene = load_scene(scene_dir)
            read = time.process_time() - began
            result = run(scene, options=options)
            if profiler:
                profiler.disable()
    finally:
        clock_module.time = saved_time
    record = {"scene": scene_dir.name, "wall": time.perf_counter() - wall, "cpu": time.process_time() - cpu,
              "load": (load_before + os.getloadavg()[0]) / 2,
              "points_start": len(result.start_cloud.points), "points_end": len(result.end_cloud.points),
              "joints": len(result.joints), "stages": {"read": read},
              "fit_steps": {name: float(fit_steps.get(f"cpu.{name}", 0.0)) for name in SUB_STEPS},
              "fit_calls": int(fit_steps.get("calls", 0))}
    for stage in result.stages:
        if stage.ran:
            record["stages"][stage.name] = record["stages"].get(stage.name, 0.0) + stage.seconds
    if profiler:
        stream = io.StringIO()
        pstats.Stats(profiler, stream=stream).sort_stats("tottime").print_stats(12)
        lines = stream.getvalue().splitlines()
        start = next((i for i, line in enumerate(lines) if line.strip().startswith("ncalls")), len(lines))
        record["hot"] = [line for line in lines[start:start + 13] if line.strip()]
    return record


def render(partnet: Path, object_name: str, scenes: Path, width: int) -> Path:
    height = round(width * 3 / 4)
    setting = BenchSetting(width=width, height=height)
    scene_dir = scenes / f"{object_name}_{setting.render_key()}"
    render_cached(partnet / object_name, scene_dir, setting)
    return scene_dir


def widths_for(points_at_default: int, targets: list[int]) -> list[int]:
    """Render widths (multiples of 8) expected to give ``targets`` points per state."""
    return [max(64, round(DEFAULT_WIDTH * (target / points_at_default) ** 0.5 / 8) * 8) for target in targets]


def table(records: list[dict], key: str) -> str:
    """Markdown table: one row per run, CPU seconds per stage and fit sub-step, wall total."""
    extra = [] if key == "joints" else [key]
    head = ["scene", *extra, "joints", "fit calls", *STAGES, *(f"fit.{s}" for s in SUB_STEPS), "cpu total", "wall",
            "load"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in records:
        cells = [r["scene"], *(str(r[k]) for k in extra), str(r["joints"]), str(r["fit_calls"]),
                 *(f"{r['stages'].get(s, 0.0):.2f}" for s in STAGES),
                 *(f"{r['fit_steps'][s]:.2f}" for s in SUB_STEPS),
                 f"{r['cpu']:.2f}", f"{r['wall']:.2f}", f"{r['load']:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(points: list[dict], parts: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(13, 5))
    def stage(name):
        return lambda r: r["stages"].get(name, 0.0)

    def fit_step(name):
        return lambda r: r["fit_steps"][name]

    series = [*((name, stage(name)) for name in ("read", "lift", "label", "fit")),
              *((f"fit.{name}", fit_step(name)) for name in ("prepare", "optimise", "uncertainty")),
              ("total", lambda r: r["cpu"])]
    x = [r["points_start"] for r in points]
    for name, value in series:
        style = "--" if name.startswith("fit.") else "-"
        axes[0].loglog(x, [max(value(r), 1e-3) for r in points], style, marker="o", label=name)
    axes[0].set_xlabel("points per state (start)")
    axes[0].set_ylabel("CPU seconds")
    axes[0].set_title(f"cost vs points: {points[0]['scene'].split('_v')[0] if points else ''}")
    axes[0].grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    labels = [f"{r['scene'].split('_v')[0]}\n{r['joints']} joints" for r in parts]
    bottom = [0.0] * len(parts)
    for stage in STAGES:
        heights = [r["stages"].get(stage, 0.0) for r in parts]
        axes[1].bar(labels, heights, bottom=bottom, label=stage)
        bottom = [b + h for b, h in zip(bottom, heights)]
    axes[1].set_ylabel("CPU seconds")
    axes[1].set_title("cost vs movable parts (320x240, 3 views)")
    axes[1].legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def accuracy_guard(partnet: Path, bench_dir: Path, names: list[str]) -> list[dict]:
    """The bench's accuracy and speed on the 16 shared objects for the named grid settings
    (``sparseart.bench.grid.run_bench``, no peer, no plots; scenes cached under ``bench_dir``):
    success, median axis error, type accuracy, median seconds per scene, and the fit's median
    wall / CPU seconds per predicted joint."""
    import statistics

    from sparseart.bench import grid, metrics

    settings = {setting.name: setting for setting in grid.grid_settings(0)[0]}
    evaluate = grid.evaluate_object

    def evaluate_with_fit_cpu(*args, **kwargs):
        with collect_seconds() as fit_steps:
            rows = evaluate(*args, **kwargs)
        for row in rows:
            row["fit_cpu"] = sum(v for k, v in fit_steps.items() if k.startswith("cpu."))
        return rows

    grid.evaluate_object = evaluate_with_fit_cpu
    try:
        records = []
        for name in names:
            result = grid.run_bench(grid.find_objects([partnet]), bench_dir, settings=[settings[name]], peer=False,
                                    plots=False)
            rows = [r for r in result.rows if r["method"] == "sparseart"]
            summary = metrics.summarise(rows)
            scenes = list({r["object"]: r for r in rows}.values())
            fit_wall = statistics.median(r["stage_seconds"].get("fit", 0.0) / max(r["n_predicted"], 1) for r in scenes)
            fit_cpu = statistics.median(r["fit_cpu"] / max(r["n_predicted"], 1) for r in scenes)
            records.append({"setting": name, "joints": summary["count"], "success": summary["success_rate"],
                            "median_axis_deg": summary["axis_deg_median"], "type_accuracy": summary["type_accuracy"],
                            "seconds_per_scene": statistics.median(r["pipeline_seconds"] for r in scenes),
                            "fit_wall_per_joint": fit_wall, "fit_cpu_per_joint": fit_cpu,
                            "load": os.getloadavg()[0], "failures": result.failures})
            print(json.dumps(records[-1]), flush=True)
        return records
    finally:
        grid.evaluate_object = evaluate


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--object", default="microwave_7128")
    parser.add_argument("--points", type=int, nargs="*", default=[10000, 50000, 200000, 1000000])
    parser.add_argument("--parts-objects", nargs="*", default=["microwave_7128", "storage_40147", "oven_7179_multi"])
    parser.add_argument("--partnet", type=Path, default=PARTNET, help="the shared PartNet objects")
    parser.add_argument("--budget", default=None, help="RunOptions.budget when the pipeline has it")
    parser.add_argument("--scenes", type=Path, default=Path(tempfile.gettempdir()) / "profile_scenes")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "profile")
    parser.add_argument("--cprofile", action="store_true")
    parser.add_argument("--guard", nargs="*", default=None, metavar="SETTING",
                        help="instead of the profile: the accuracy guard (bench settings, e.g. default unposed)")
    parser.add_argument("--bench-dir", type=Path, default=Path(tempfile.gettempdir()) / "bench_speed")
    args = parser.parse_args(argv)
    if not args.partnet.is_dir():
        print(f"skipped: {args.partnet} not found (the shared PartNet objects)")
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    args.scenes.mkdir(parents=True, exist_ok=True)
    if args.guard is not None:
        records = accuracy_guard(args.partnet, args.bench_dir, args.guard or ["default"])
        (args.out / "guard.json").write_text(json.dumps(records, indent=1))
        return 0
    options = RunOptions()
    if args.budget is not None:
        if not hasattr(options, "budget"):
            parser.error("this pipeline has no RunOptions.budget")
        options.budget = args.budget
    default_scene = render(args.partnet, args.object, args.scenes, DEFAULT_WIDTH)
    warm = profile_scene(default_scene, options)  # imports (open3d, ...) paid here, not reported
    widths = widths_for(warm["points_start"], args.points)
    point_runs = []
    for target, width in zip(args.points, widths):
        scene_dir = render(args.partnet, args.object, args.scenes, width)
        record = profile_scene(scene_dir, options, args.cprofile)
        record.update(target=target, width=width)
        point_runs.append(record)
        print(f"{scene_dir.name}: {record['points_start']} points, {record['cpu']:.2f} s CPU "
              f"(fit {record['stages'].get('fit', 0.0):.2f} s, label {record['stages'].get('label', 0.0):.2f} s)",
              flush=True)
    part_runs = []
    for name in args.parts_objects:
        record = profile_scene(render(args.partnet, name, args.scenes, DEFAULT_WIDTH), options, args.cprofile)
        part_runs.append(record)
        print(f"{name}: {record['joints']} joints, {record['cpu']:.2f} s CPU", flush=True)
    text = [(f"# stage profile ({time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores, shared machine). Stage and "
             "fit sub-step columns are CPU seconds of the process (steady under the other engineers' load; "
             "multi-threaded stages can exceed wall); 'wall' = the run's wall clock, 'load' = 1-min load average."),
            "",
            f"## points per state ({args.object}, 3 views per state, resolution scaled)", "",
            table(point_runs, "points_start"), "", "## movable parts (320x240, 3 views per state)", "",
            table(part_runs, "joints")]
    if args.cprofile:
        for record in point_runs + part_runs:
            text += ["", f"### hottest functions: {record['scene']}", "", "```", *record.get("hot", []), "```"]
    (args.out / "table.txt").write_text("\n".join(text) + "\n")
    (args.out / "results.json").write_text(json.dumps({"points": point_runs, "parts": part_runs}, indent=1))
    plot(point_runs, part_runs, args.out / "profile.png")
    print("\n".join(text))
    return 0


if __name__ == "__main__":
    sys.exit(main())
