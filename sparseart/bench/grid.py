"""``sparseart bench``: a one-factor-at-a-time grid of settings over a set of objects, sparseart and
the ICP peer side by side, written as CSV + JSON + PNG plots.

A full factorial grid (views x pose x depth noise x pose noise x refinement) is far too expensive
on 2 cores, so every setting changes ONE factor of the default (3 views per state, posed, clean
depth, exact poses, no refinement). Scenes are rendered once per (object, rendering setting) and
cached under ``OUT/scenes``; a rerun with the same ``--out`` reuses them.

Outputs in ``OUT``: ``rows.csv`` / ``rows.json`` (one row per joint x setting x method),
``summary.csv`` / ``summary.json`` (aggregate per setting x method, and per object),
``table.txt`` (what is printed), ``error_vs_time.png``, ``error_vs_factor.png``.
"""
from __future__ import annotations

import csv
import io
import platform
import statistics
import sys
import time
from dataclasses import dataclass, replace
from datetime import date
from pathlib import Path
from collections.abc import Sequence
from typing import Any, TextIO

from sparseart.bench import metrics
from sparseart.bench.plots import plot_error_vs_factor, plot_error_vs_time
from sparseart.bench.objects import METHOD_PEER, METHOD_SPARSEART, BenchSetting, evaluate_object, refine_available
from sparseart.io.scene import write_bytes_atomic, write_json_atomic
from sparseart.types import SceneError

QUICK_OBJECTS = ("toaster_press_103486", "stapler_press_102990", "door_9168")
FLYING_FRACTION = 0.5  # fraction of depth-edge pixels made flying in the noisy-depth settings
CONFIG_FIELDS = ("views", "posed", "depth_noise", "flying_pixels", "pose_noise_deg", "pose_noise_m", "refine",
                 "scramble_masks", "use_masks", "segmenter", "realism", "matcher", "budget")
STAGES = ("read", "segment", "lift", "align", "align.register_views", "align.align_states", "align.static", "label",
          "fit", "refine",
          "peer_segment", "peer_register")


def shared_dir() -> Path:
    """``../shared`` next to the repository (objects, models)."""
    return Path(__file__).resolve().parents[3] / "shared"


def default_partnet_dir() -> Path:
    """``../shared/data/partnet`` next to the repository (the shared objects)."""
    return shared_dir() / "data" / "partnet"


def default_matcher_spec() -> str | None:
    """The real XFeat + LighterGlue weights in ``../shared/models`` as a matcher spec, or None when
    they are not there (the ``*-xfeat`` settings are then skipped with that reason)."""
    models = shared_dir() / "models"
    detector, matcher = models / "xfeat.onnx", models / "lighterglue_L3.onnx"
    return f"xfeat:{detector},{matcher}" if detector.is_file() and matcher.is_file() else None


def grid_settings(seed: int = 0, quick: bool = False) -> tuple[list[BenchSetting], list[str]]:
    """The one-factor-at-a-time grid: (settings, skipped-setting reasons).

    Clean renders -- default: 3 views, posed, no depth noise, no pose noise, no refinement; then
    views 1 / 2 / 4, unposed, depth noise 1 % and 3 % (each with flying pixels on half the
    depth-edge pixels), pose noise 0.5 deg + 0.5 cm (object units), mask ids scrambled per image,
    no masks (motion split), unposed without masks (the hardest clean case for look-alike parts:
    two factors at once), both unposed ones again with the camera moved between the states
    (``*-moved``; every other setting keeps each view's camera in both states), the built-in
    image segmenter instead of the masks, the fit's ``fast`` and
    ``best`` budgets (error against seconds per budget), refinement.
    Realistic renders (:mod:`sparseart.datasets.realism`, every knob at level 1, unposed) --
    ``realistic`` (3 views), ``realistic-1view``, ``realistic+refine``, ``robot-1view`` (what a
    robot's calibrated static head camera gives: posed, one view per state from the same pose, no
    masks, every other knob at level 1 -- the shape of the real captures), ``robot-sensor-1view`` (the
    same with a depth sensor's errors only: no per-state warp or scale, no confidence map), and
    ``knob-NAME``: one knob
    alone at level 1 on the unposed 3-view default (posed for ``knob-pose_noise``, whose error
    lives in the written poses), so the table shows which error hurts most.
    ``quick``: the default setting only.
    """
    from sparseart.datasets.realism import KNOBS, PRESETS, Realism

    base = BenchSetting(seed=seed, name="default")
    if quick:
        return [base], []
    realistic = replace(base, posed=False, realism=PRESETS["realistic"], name="realistic")
    settings = [base, *(replace(base, views=v, name=f"views{v}") for v in (1, 2, 4)),
                replace(base, posed=False, name="unposed"),
                replace(base, depth_noise=0.01, flying_pixels=FLYING_FRACTION, name="depth1%+fly"),
                replace(base, depth_noise=0.03, flying_pixels=FLYING_FRACTION, name="depth3%+fly"),
                replace(base, pose_noise_deg=0.5, pose_noise_m=0.005, name="pose0.5deg0.5cm"),
                replace(base, scramble_masks=True, name="masks-scrambled"),
                replace(base, use_masks=False, name="no-masks"),
                replace(base, posed=False, use_masks=False, name="unposed-no-masks"),
                # the camera moved between the states (a phone walked round the object): the
                # unposed settings above keep each view's camera, so a still-camera alignment
                # (sparseart.align.still) is open to them and not to these
                replace(base, posed=False, same_cameras=False, name="unposed-moved"),
                replace(base, posed=False, use_masks=False, same_cameras=False, name="unposed-no-masks-moved"),
                replace(base, segmenter="builtin", name="builtin-segmenter"),
                replace(base, budget="fast", name="budget-fast"), replace(base, budget="best", name="budget-best"),
                realistic, replace(realistic, views=1, name="realistic-1view"),
                replace(base, views=1, use_masks=False, realism=PRESETS["realistic"].with_levels(pose_noise=0.0),
                        name="robot-1view"),
                # the same with a depth sensor instead of a reconstructor: no per-state warp or scale,
                # no confidence map (the real captures kept aside are robot RGB-D)
                replace(base, views=1, use_masks=False, name="robot-sensor-1view",
                        realism=PRESETS["realistic"].with_levels(pose_noise=0.0, depth_warp=0.0, depth_scale=0.0,
                                                                 confidence=0.0)),
                *(replace(base, posed=knob == "pose_noise", realism=Realism(**{knob: 1.0}), name=f"knob-{knob}")
                  for knob in KNOBS)]
    skipped = []
    xfeat = default_matcher_spec()
    if xfeat:
        # the same scenes registered by the learned matcher instead of SIFT (issue 14)
        settings += [replace(s, matcher=xfeat, name=f"{s.name}-xfeat")
                     for s in settings if s.name in ("unposed", "realistic", "realistic-1view")]
    else:
        skipped.append("*-xfeat: XFeat/LighterGlue weights not found in ../shared/models; settings skipped")
    if refine_available():
        settings += [replace(base, refine=True, name="refine"), replace(realistic, refine=True, name="realistic+refine")]
    else:
        skipped.append("refine: sparseart.pipeline.RunOptions has no 'refine' option yet (issue 5); setting skipped")
    return settings, skipped


def select_settings(settings: list[BenchSetting], patterns: Sequence[str] | None) -> list[BenchSetting]:
    """The settings whose name matches any of the shell-style ``patterns`` (all when None); a
    pattern matching nothing is a SceneError naming the known settings."""
    import fnmatch

    if not patterns:
        return settings
    chosen = [s for s in settings if any(fnmatch.fnmatchcase(s.name, p) for p in patterns)]
    unknown = [p for p in patterns if not any(fnmatch.fnmatchcase(s.name, p) for s in settings)]
    if unknown:
        raise SceneError(f"--settings: {', '.join(unknown)} matches no setting (known: "
                         f"{', '.join(s.name for s in settings)})")
    return chosen


class Progress:
    """A progress bar on a TTY, plain lines otherwise (logs, CI)."""

    def __init__(self, total: int, stream: TextIO | None = None) -> None:
        self.total, self.done, self.stream = total, 0, stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.began = time.perf_counter()

    def step(self, label: str) -> None:
        self.done += 1
        elapsed = time.perf_counter() - self.began
        if self.tty:
            filled = int(30 * self.done / max(self.total, 1))
            self.stream.write(f"\r[{'#' * filled}{'.' * (30 - filled)}] {self.done}/{self.total} "
                              f"{elapsed:6.0f}s {label[:40]:40s}")
            if self.done == self.total:
                self.stream.write("\n")
        else:
            left = elapsed / self.done * (self.total - self.done)
            self.stream.write(f"[{self.done}/{self.total}] {label} ({elapsed:.0f}s, ~{left / 60:.0f} min left)\n")
        self.stream.flush()


@dataclass
class BenchResult:
    rows: list[dict[str, Any]]
    summary: list[dict[str, Any]]
    per_object: list[dict[str, Any]]
    per_category: list[dict[str, Any]]
    skipped: list[str]
    failures: list[str]
    seconds: float


def category_of(object_name: str) -> str:
    """An object's category from its folder name: the part before its PartNet id, without the
    task verb (``laptop_rotate_10040`` -> ``laptop``, ``oven_7179_multi`` -> ``oven``,
    ``washing_machine_103508`` -> ``washing_machine``)."""
    import re

    head = re.split(r"_\d+", object_name, maxsplit=1)[0]
    return re.sub(r"_(rotate|press|push|swing|slide|open|turn)$", "", head) or object_name


def _evaluate_group(tasks: list[tuple[int, Path, Path, BenchSetting, bool]]) -> list[tuple[int, list, str | None]]:
    """Evaluate tasks that share one rendered scene folder, in order (one process renders it).
    Returns (task index, rows, failure line or None) per task."""
    out = []
    for index, object_dir, scenes, setting, peer in tasks:
        try:
            out.append((index, evaluate_object(object_dir, scenes, setting, peer=peer), None))
        except Exception as error:  # noqa: BLE001 - one broken object must not end a long run
            out.append((index, [], f"{object_dir.name} [{setting.name}]: {type(error).__name__}: {error}"))
    return out


def default_jobs() -> int:
    """Worker processes for the bench: the machine's cores."""
    import os

    return max(1, os.cpu_count() or 1)


def run_grid(objects: list[Path], out_dir: Path, settings: list[BenchSetting], peer: bool = True,
             progress: Progress | None = None, jobs: int = 1) -> tuple[list[dict[str, Any]], list[str]]:
    """Evaluate every object under every setting. Returns (rows, failure lines). An object that
    fails one setting (bad mesh, pipeline error) is reported and skipped, the rest go on.

    ``jobs`` > 1 runs the scenes in that many worker processes (spawned, so no state leaks between
    them). Tasks that share a rendered scene folder (same object and render key, e.g. ``default``
    and ``no-masks``) run in one worker, in order, so no folder is rendered twice at once. Rows come
    back in the sequential run's order whatever the schedule, and every stage is deterministic
    (:mod:`sparseart.parallel`), so the rows are those of ``jobs=1``. Wall time ~ total / jobs."""
    scenes = out_dir / "scenes"
    tasks = [(i, object_dir, scenes, setting, peer)
             for i, (setting, object_dir) in enumerate((s, o) for s in settings for o in objects)]
    groups: dict[str, list] = {}
    for task in tasks:
        groups.setdefault(f"{task[1].name}_{task[3].render_key()}", []).append(task)
    results: dict[int, tuple[list, str | None]] = {}

    def collect(group_out: list[tuple[int, list, str | None]]) -> None:
        for index, rows, failure in group_out:
            results[index] = (rows, failure)
            if progress:
                progress.step(f"{tasks[index][1].name} [{tasks[index][3].name}]")

    if jobs <= 1 or len(groups) <= 1:
        for group in groups.values():
            collect(_evaluate_group(group))
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=min(jobs, len(groups)), mp_context=context) as pool:
            # longest groups first: the last worker to finish is not the one that got the big tail
            ordered = sorted(groups.values(), key=len, reverse=True)
            for future in as_completed([pool.submit(_evaluate_group, g) for g in ordered]):
                collect(future.result())
    rows, failures = [], []
    for index in sorted(results):
        group_rows, failure = results[index]
        rows.extend(group_rows)
        if failure:
            failures.append(failure)
    return rows, failures


def _scene_key(row: dict[str, Any]) -> tuple:
    """One scene per object, setting, method and seed (every seed renders its own scene)."""
    return row["object"], row["setting"], row["method"], row.get("config", {}).get("seed")


def _stage_stats(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Median seconds per stage and in total over the distinct scenes of ``rows`` (one per object,
    setting, method and seed: every seed renders its own scene)."""
    scenes = {_scene_key(r): r for r in rows}.values()
    out = {"seconds_median": statistics.median(r["pipeline_seconds"] for r in scenes),
           "seconds_mean": statistics.fmean(r["pipeline_seconds"] for r in scenes)}
    for stage in STAGES:
        values = [r["stage_seconds"][stage] for r in scenes if stage in r["stage_seconds"]]
        if values:
            out[f"{stage}_seconds_median"] = statistics.median(values)
    return out


def geometry_stats(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """With ``--geometry`` (:mod:`sparseart.bench.geometry`): medians of CD-s / CD-w over the
    distinct scenes and of CD-m over the matched joints (object units squared), the median
    seconds of each export step, the share of the joints whose whole motion is right
    (:func:`~sparseart.bench.metrics.motion_right`) whose moved mesh lands within
    ``LANDING_BOUND`` in every format, the worst sink (object diagonals) and whether every axis
    kept its sign (dot > 0.9999) in every format. {} without geometry columns."""
    rows = [r for r in rows if "cd_w" in r]
    if not rows:
        return {}
    from sparseart.sim.replay import LANDING_BOUND

    scenes = list({_scene_key(r): r for r in rows}.values())
    out: dict[str, Any] = {}
    for key in ("cd_s", "cd_w"):
        values = [r[key] for r in scenes if r.get(key) is not None]
        out[f"{key}_median"] = statistics.median(values) if values else None
    values = [r["cd_m"] for r in rows if r.get("cd_m") is not None]
    out["cd_m_median"] = statistics.median(values) if values else None
    for step in ("surfaces", "collision", "urdf", "mjcf", "usd"):
        values = [r["export_seconds"][step] for r in scenes if step in (r.get("export_seconds") or {})]
        out[f"export_{step}_seconds_median"] = statistics.median(values) if values else None
    right = [r for r in rows if metrics.motion_right(r) and r.get("landing_rel") is not None]
    out["landing_within_bound"] = (sum(r["landing_rel"] <= LANDING_BOUND for r in right) / len(right)) if right else None
    out["n_landing_checked"] = len(right)
    sinks = [r["sink_rel"] for r in rows if r.get("sink_rel") is not None]
    out["sink_max"] = max(sinks) if sinks else None
    dots = [r["axis_dot"] for r in rows if r.get("axis_dot") is not None]
    out["axis_sign_agrees"] = all(d > 0.9999 for d in dots) if dots else None
    return out


def geometry_table(summary: list[dict[str, Any]]) -> str:
    """One line per setting (sparseart rows with --geometry): CD-s / CD-m / CD-w medians x 1000,
    the median seconds of each export step, landing share, worst sink, axis signs."""
    rows = [s for s in summary if s.get("cd_w_median") is not None]
    if not rows:
        return ""
    lines = [f"{'setting':17s} {'CD-s':>7s} {'CD-m':>7s} {'CD-w':>7s} {'surf s':>6s} {'coll s':>6s} {'urdf s':>6s} "
             f"{'mjcf s':>6s} {'usd s':>6s} {'land ok':>7s} {'sink max':>8s} {'axes':>5s}"]
    for s in rows:
        def k(key: str) -> str:
            return _fmt(None if s.get(key) is None else 1000 * s[key], 2)
        lines.append(f"{s['setting']:17s} {k('cd_s_median'):>7s} {k('cd_m_median'):>7s} {k('cd_w_median'):>7s} "
                     + " ".join(f"{_fmt(s.get(f'export_{step}_seconds_median'), 2):>6s}"
                                for step in ("surfaces", "collision", "urdf", "mjcf", "usd"))
                     + f" {_fmt(s.get('landing_within_bound'), 2):>7s} {_fmt(s.get('sink_max'), 3):>8s} "
                       f"{'ok' if s.get('axis_sign_agrees') else 'FLIP':>5s}")
    return "\n".join(lines)


def extra_parts(rows: list[dict[str, Any]]) -> dict[str, int]:
    """Movable parts reported that match no true joint: per distinct scene (:func:`_scene_key`)
    the predicted parts (``n_predicted``) beyond the true joints they were matched to (rows not
    ``unmatched``). A part that did not move, or an arm taken for one, tells a robot something
    moved that did not; success and axis error cannot show it (the evaluation pairs predictions
    with true joints and drops the rest). Returns {"extra_parts": total, "extra_scenes": scenes
    with any}. O(R)."""
    predicted: dict[tuple, int] = {}
    matched: dict[tuple, int] = {}
    for row in rows:
        key = _scene_key(row)
        predicted[key] = int(row.get("n_predicted") or 0)
        matched[key] = matched.get(key, 0) + (not row.get("unmatched", False))
    extra = [max(0, predicted[key] - matched[key]) for key in predicted]
    return {"extra_parts": sum(extra), "extra_scenes": sum(e > 0 for e in extra)}


def aggregate(rows: list[dict[str, Any]], keys: tuple[str, ...]) -> list[dict[str, Any]]:
    """``metrics.summarise`` plus stage timings per group of ``keys`` (e.g. setting, method)."""
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault(tuple(category_of(row["object"]) if k == "category" else row[k] for k in keys),
                          []).append(row)
    out = []
    for key, group in groups.items():
        entry = dict(zip(keys, key))
        config = group[0].get("config") or {}
        entry.update({k: config[k] for k in CONFIG_FIELDS if k in config})
        entry.update(metrics.summarise(group))
        entry.update(_stage_stats(group))
        entry.update(extra_parts(group))
        entry.update(geometry_stats(group))
        out.append(entry)
    return out


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def summary_table(summary: list[dict[str, Any]]) -> str:
    """One line per setting and method: the whole motion right first (``motion``: type, axis,
    angle or slide and, for a turn, the hinge line, :func:`~sparseart.bench.metrics.motion_right`), type accuracy, success, full success (``full``: the type
    and the state right too, :func:`~sparseart.bench.metrics.summarise`), axis mean/median, position median,
    state medians, median seconds, the share of successful joints whose axis error is within the
    stated 1-sigma (``1σ cov``; ~63 % is honest for the axis angle), the same for the hinge line's
    position and the angle or slide (``pos 1σ``, at least ~63 %; ``st 1σ``, ~68 %) and the movable parts
    reported that match no true joint (``extra``, :func:`extra_parts`)."""
    header = (f"{'setting':17s} {'method':9s} {'n':>3s} {'motion':>6s} {'type':>5s} {'succ':>5s} {'full':>5s} {'axis mean':>9s} "
              f"{'axis med':>8s} {'pos med':>8s} {'rev° med':>8s} {'pris med':>8s} {'sec med':>7s} {'1σ cov':>6s} "
              f"{'pos 1σ':>6s} {'st 1σ':>6s} {'extra':>5s}")
    lines = [header]
    for s in summary:
        lines.append(f"{s['setting']:17s} {s['method']:9s} {s['count']:3d} "
                     f"{_fmt(s.get('motion_success_rate'), 2):>6s} {_fmt(s['type_accuracy'], 2):>5s} "
                     f"{_fmt(s['success_rate'], 2):>5s} {_fmt(s.get('full_success_rate'), 2):>5s} "
                     f"{_fmt(s['axis_deg_mean'], 2):>9s} "
                     f"{_fmt(s['axis_deg_median'], 2):>8s} {_fmt(s['position_median'], 4):>8s} "
                     f"{_fmt(s['state_revolute_deg_median'], 2):>8s} {_fmt(s['state_prismatic_median'], 4):>8s} "
                     f"{_fmt(s['seconds_median'], 2):>7s} {_fmt(s.get('sigma_coverage'), 2):>6s} "
                     f"{_fmt(s.get('position_sigma_coverage'), 2):>6s} {_fmt(s.get('state_sigma_coverage'), 2):>6s} "
                     f"{_fmt(s.get('extra_parts')):>5s}")
    return "\n".join(lines)


def category_table(per_category: list[dict[str, Any]]) -> str:
    """The whole motion right per category and setting, sparseart beside the ICP peer: one line per
    category, one column per setting (``ours/peer`` of ``n`` joints). Empty without categories."""
    if not per_category:
        return ""
    settings = list(dict.fromkeys(s["setting"] for s in per_category))
    by = {(s["category"], s["setting"], s["method"]): s for s in per_category}
    categories = sorted({s["category"] for s in per_category})
    width = max(15, *(len(c) for c in categories))
    lines = [f"{'category':{width}s} " + " ".join(f"{name[:17]:>17s}" for name in settings),
             f"{'':{width}s} " + " ".join(f"{'motion ours/peer n':>17s}" for _ in settings)]
    for category in categories:
        cells = []
        for setting in settings:
            ours, peer = by.get((category, setting, METHOD_SPARSEART)), by.get((category, setting, METHOD_PEER))
            if ours is None:
                cells.append(f"{'-':>17s}")
                continue
            peer_text = _fmt(peer.get("motion_success_rate"), 2) if peer else "-"
            cells.append(f"{_fmt(ours.get('motion_success_rate'), 2) + '/' + peer_text + ' ' + str(ours['count']):>17s}")
        lines.append(f"{category:{width}s} " + " ".join(cells))
    return "\n".join(lines)


def ratio_note(summary: list[dict[str, Any]]) -> str:
    """The closing note: sparseart vs the ICP peer per setting (median axis error and median
    seconds ratios, success rates), and where each wins."""
    by = {(s["setting"], s["method"]): s for s in summary}
    lines = []
    for setting in dict.fromkeys(s["setting"] for s in summary):
        ours, peer = by.get((setting, METHOD_SPARSEART)), by.get((setting, METHOD_PEER))
        if not ours or not peer:
            continue
        axis_ratio = (ours["axis_deg_median"] / peer["axis_deg_median"]
                      if peer["axis_deg_median"] else float("nan"))
        time_ratio = ours["seconds_median"] / peer["seconds_median"] if peer["seconds_median"] else float("nan")
        winner = ("sparseart" if (ours["success_rate"], -ours["axis_deg_median"]) >
                  (peer["success_rate"], -peer["axis_deg_median"]) else "icp_peer")
        lines.append(f"{setting}: sparseart/peer median axis error x{axis_ratio:.2f}, median seconds "
                     f"x{time_ratio:.2f}; success {ours['success_rate']:.2f} vs {peer['success_rate']:.2f}, "
                     f"type acc {ours['type_accuracy']:.2f} vs {peer['type_accuracy']:.2f} -> more accurate: {winner}")
    return "\n".join(lines)


CSV_FIELDS = ("object", "category", "setting", "method", "name", "gt_type", "pred_type", "type_correct", "unmatched",
              "axis_deg", "position", "state", "state_along", "gt_state", "render_seconds", "pipeline_seconds",
              *(f"{s}_seconds" for s in STAGES), "n_predicted", "n_warnings", "seed",
              "axis_sigma_deg", "origin_sigma", "state_sigma", "confidence", "covered_fraction", "residual_excess",
              "residual_floor", "blocked_share",
              # --geometry (sparseart.bench.geometry): CDs in object units squared, landing / sink in diagonals
              "cd_s", "cd_m", "cd_w", "landing_rel", "sink_rel", "axis_dot",
              *(f"export_{step}_seconds" for step in ("surfaces", "collision", "urdf", "mjcf", "usd")))


def rows_csv(rows: list[dict[str, Any]]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=CSV_FIELDS, extrasaction="ignore")
    writer.writeheader()
    for row in rows:
        flat = dict(row, n_warnings=len(row.get("warnings", [])), seed=row.get("config", {}).get("seed"),
                    category=category_of(row["object"]))
        flat.update({f"{s}_seconds": row["stage_seconds"].get(s) for s in STAGES})
        flat.update({f"export_{k}_seconds": v for k, v in (row.get("export_seconds") or {}).items()})
        writer.writerow(flat)
    return buffer.getvalue()


def summary_csv(summary: list[dict[str, Any]]) -> str:
    fields = sorted({k for s in summary for k in s}, key=lambda k: (k not in ("object", "setting", "method"), k))
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=fields)
    writer.writeheader()
    writer.writerows(summary)
    return buffer.getvalue()


def machine_line() -> str:
    import os

    return (f"{date.today()} on {platform.machine()} ({platform.processor() or 'cpu'}), "
            f"{os.cpu_count()} cores, Python {platform.python_version()}")


def run_bench(objects: list[Path], out_dir: Path, seeds: list[int] | None = None, quick: bool = False,
              peer: bool = True, stream: TextIO | None = None,
              plots: bool = True, settings: list[BenchSetting] | None = None,
              names: Sequence[str] | None = None, jobs: int = 1, geometry: bool = False) -> BenchResult:
    """The whole benchmark: grid x seeds x objects, outputs written into ``out_dir`` (atomically,
    file by file). ``settings`` overrides the grid (tests); ``jobs`` worker processes
    (:func:`run_grid`); ``geometry``: also the exports, their simulator check and CD-s / CD-m /
    CD-w (:mod:`sparseart.bench.geometry`). Returns the rows and summaries (per setting, object
    and category)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    seeds = seeds or [0]
    all_settings, skipped = [], []
    for seed in seeds:
        grid, skipped = (settings, []) if settings is not None else grid_settings(seed, quick)
        grid = select_settings(grid, names)
        all_settings.extend(replace(s, seed=seed, geometry=geometry) for s in grid)
    began = time.perf_counter()
    progress = Progress(len(all_settings) * len(objects), stream)
    rows, failures = run_grid(objects, out_dir, all_settings, peer=peer, progress=progress, jobs=jobs)
    summary = aggregate(rows, ("setting", "method")) if rows else []
    per_object = aggregate(rows, ("object", "setting", "method")) if rows else []
    per_category = aggregate(rows, ("category", "setting", "method")) if rows else []
    result = BenchResult(rows, summary, per_object, per_category, skipped, failures, time.perf_counter() - began)
    write_outputs(result, out_dir, plots=plots)
    return result


def report_text(result: BenchResult) -> str:
    parts = [f"# sparseart bench, {machine_line()}; wall {result.seconds:.0f}s; "
             "positions in raw object units (not x10)", summary_table(result.summary)]
    categories = category_table(result.per_category)
    if categories:
        parts += ["", "the whole motion right per category (sparseart/peer, joints):", categories]
    geometry = geometry_table([r for r in result.summary if r.get("method") == "sparseart"])
    if geometry:
        parts += ["", "exports (--geometry): CD x 1000 (object units squared), median seconds per step, moved mesh "
                  "within the landing bound on the joints that are right, worst sink (object diagonals), axis signs:",
                  geometry]
    note = ratio_note(result.summary)
    if note:
        parts += ["", "sparseart vs ICP peer:", note]
    parts += [f"skipped: {s}" for s in result.skipped]
    parts += [f"failed: {f}" for f in result.failures]
    return "\n".join(parts)


def write_outputs(result: BenchResult, out_dir: Path, plots: bool = True) -> list[Path]:
    """rows/summary as CSV + JSON, the printed table, and the plots (when any row exists)."""
    written = []
    clean_rows = [{k: v for k, v in r.items() if k != "warnings"} | {"n_warnings": len(r.get("warnings", []))}
                  for r in result.rows]
    for name, payload in (("rows.csv", rows_csv(result.rows)), ("summary.csv", summary_csv(result.summary)),
                          ("table.txt", report_text(result) + "\n")):
        write_bytes_atomic(out_dir / name, payload.encode())
        written.append(out_dir / name)
    write_json_atomic(out_dir / "rows.json", clean_rows)
    write_json_atomic(out_dir / "summary.json", {"machine": machine_line(), "seconds": result.seconds,
                                                 "summary": result.summary, "per_object": result.per_object,
                                                 "per_category": result.per_category,
                                                 "skipped": result.skipped, "failures": result.failures})
    written += [out_dir / "rows.json", out_dir / "summary.json"]
    if plots and result.summary:
        written.append(plot_error_vs_time(result.summary, out_dir / "error_vs_time.png"))
        written.append(plot_error_vs_factor(result.summary, out_dir / "error_vs_factor.png"))
    return written


CORPUS = ("partnet", "partnet-more", "partnet-twins")
"""The corpus under ``../shared/data``: the 16 shared objects, 46 more of 14 categories, and 3
whose moving parts look alike."""


def corpus_dirs() -> list[Path]:
    """The corpus folders that exist under ``../shared/data`` (SceneError when none does)."""
    found = [shared_dir() / "data" / name for name in CORPUS if (shared_dir() / "data" / name).is_dir()]
    if not found:
        raise SceneError(f"{shared_dir() / 'data'}: none of the corpus folders {', '.join(CORPUS)} found")
    return found


def find_objects(dirs: list[Path] | None) -> list[Path]:
    """Object folders: each given folder that holds ``mobility.urdf``, or its sub-folders that do;
    default every object in the shared PartNet folder. SceneError-style ValueError when none."""
    from sparseart.types import SceneError

    roots = dirs or [default_partnet_dir()]
    found = []
    for root in roots:
        root = Path(root)
        if (root / "mobility.urdf").exists():
            found.append(root)
        elif root.is_dir():
            found.extend(sorted(p for p in root.iterdir() if (p / "mobility.urdf").exists()))
        else:
            raise SceneError(f"{root}: --objects folder not found")
    if not found:
        raise SceneError(f"{', '.join(map(str, roots))}: no object folder with mobility.urdf")
    return found

