"""Command line: ``sparseart run | view | demo | render | bench``.

Exit codes: 0 success, 2 bad input (one line naming the file and the problem), 1 internal error.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import traceback
from pathlib import Path

from .errors import SceneError

EXIT_BAD_INPUT = 2
# Option ranges, checked where the options are parsed (argparse's one-line usage error, exit 2).
MAX_SEED = 2**31 - 1          # open3d's generator takes a C int; derived seeds wrap (geometry.o3d.seeded)
SEED_HELP = f"random seed, 0 .. {MAX_SEED} (default 0)"
MIN_RENDER_SIDE = 16          # pixels: fewer leave no object to see
MAX_RENDER_SIDE = 4096        # pixels: the scene reader's image cap (io.validate.MAX_IMAGE_PIXELS = 4096^2)
MAX_DEPTH_NOISE = 1.0         # a multiplicative depth sigma of 100 % is beyond any sensor


def _integer(low: int, high: int | None = None):
    """argparse ``type`` of an integer option in [low, high] (high None: no upper bound); a value
    outside is argparse's usage error naming the option."""
    def parse(text: str) -> int:
        try:
            value = int(text, 10)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low or (high is not None and value > high):
            bounds = f">= {low}" if high is None else f"in {low} .. {high}"
            raise argparse.ArgumentTypeError(f"must be an integer {bounds}, got {value}")
        return value
    return parse


def _number(low: float, high: float | None = None, low_open: bool = False):
    """argparse ``type`` of a finite float option in [low, high] ((low, high] with ``low_open``;
    high None: no upper bound); NaN, infinities and values outside are usage errors."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        below = value <= low if low_open else value < low
        if not math.isfinite(value) or below or (high is not None and value > high):
            bounds = (f"{'>' if low_open else '>='} {low:g}" if high is None else
                      f"in {'(' if low_open else '['}{low:g}, {high:g}]")
            raise argparse.ArgumentTypeError(f"must be a finite number {bounds}, got {text}")
        return value
    return parse


_seed = _integer(0, MAX_SEED)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sparseart", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show tracebacks of internal errors")
    commands = parser.add_subparsers(dest="command", required=True)

    run = commands.add_parser("run", help="recover the joints of a scene folder")
    run.add_argument("scene", type=Path, help="scene folder (start/, end/, cameras.json)")
    run.add_argument("--out", type=Path, required=True, help="output folder for articulation.json")
    run.add_argument("--joint-type", choices=["auto", "revolute", "prismatic"], default="auto",
                     help="known joint type of every movable part (default: classify)")
    run.add_argument("--no-masks", action="store_true", help="ignore masks; split the parts by motion")
    run.add_argument("--no-second-opinion", action="store_true",
                     help="without masks, do not label and fit a second time with another seed to mark "
                          "unstable joints (saves about half the time of a maskless run)")
    run.add_argument("--segmenter", default="auto",
                     help="auto (scene masks when every image has one, else none) | given | builtin | "
                          "sam:ENCODER.onnx,DECODER.onnx | none (parts split by motion)")
    onnx = run.add_argument_group("RGB-only scenes (ONNX reconstructor, see models/README.md)")
    onnx.add_argument("--model", type=Path, default=None, help="reconstructor .onnx (VGGT-style)")
    onnx.add_argument("--contract", type=Path, default=None,
                      help="pointmap-onnx/1 contract JSON (default: sidecar, model metadata, built-in preset)")
    onnx.add_argument("--onnx-mode", choices=["auto", "joint", "per_state"], default="auto",
                      help="one pass over both states (joint) or one per state, aligned after (default auto)")
    onnx.add_argument("--conf-threshold", type=_number(0.0, 1.0), default=None,
                      help="drop pixels whose confidence (mapped to [0, 1]) is below this")
    onnx.add_argument("--threads", type=_integer(0), default=0, help="onnxruntime threads (0 = physical cores)")
    onnx.add_argument("--matcher", default=None,
                      help="learned matcher for unposed scenes instead of SIFT: xfeat:DET.onnx,MATCHER.onnx "
                           "(XFeat + LighterGlue), xfeat:DET.onnx (mutual nearest neighbours), a "
                           "sparseart-matcher/1 .json, or a LightGlue-ONNX pipeline export (.onnx)")
    onnx.add_argument("--matcher-min-score", type=_number(0.0, 1.0), default=None,
                      help="drop (Lighter/Light)Glue matches scoring below this (default 0.1)")
    vlm = run.add_argument_group("part labeler")
    vlm.add_argument("--labeler", choices=["rules", "vlm"], default="rules",
                     help="rules (default, no model) or vlm (OpenAI-compatible chat API; key from "
                          "$SPARSEART_VLM_API_KEY)")
    vlm.add_argument("--vlm-base-url", default=None, help="e.g. http://127.0.0.1:8000/v1 ($SPARSEART_VLM_BASE_URL)")
    vlm.add_argument("--vlm-model", default=None, help="model name ($SPARSEART_VLM_MODEL)")
    vlm.add_argument("--vlm-timeout", type=_number(0.0, low_open=True), default=30.0, help="seconds per request (default 30)")
    vlm.add_argument("--vlm-pairs", type=_integer(1), default=3, help="image pairs to ask about (default 3)")
    run.add_argument("--json", action="store_true", help="print articulation.json instead of a summary")
    run.add_argument("--seed", type=_seed, default=0, help=SEED_HELP)
    run.add_argument("--budget", choices=["fast", "default", "best"], default="default",
                     help="joint-fit budget: fast (~0.7x the fit time), default, best (~2x; dense real captures)")
    run.add_argument("--refine", action="store_true",
                     help="refine the joints with 3D Gaussians (SPLART; needs torch); writes PLY and renders")
    run.add_argument("--render-states", default="0,0.5,1",
                     help="with --refine: articulation states to render, fractions of the motion (default 0,0.5,1)")
    run.add_argument("--refine-iters", type=_integer(0), default=None,
                     help="with --refine: cross-mobile rendering steps; the other stages scale with it (default 80)")
    run.add_argument("--refine-budget", type=_number(0.0), default=None,
                     help="with --refine: seconds for all parts of the object, shared between them "
                          "(default 100; 0 = no budget)")
    run.add_argument("--refine-holdout", type=_integer(0), default=0,
                     help="with --refine: last views per state held out of fitting for PSNR (default 0)")
    run.add_argument("--urdf", action="store_true",
                     help="also write object.urdf + meshes/ (fused part meshes, convex collision pieces, inertia)")
    run.add_argument("--mjcf", action="store_true", help="also write object.xml (MuJoCo) + meshes/")
    run.add_argument("--usd", action="store_true", help="also write object.usda (UsdPhysics joints, meshes inside)")
    run.add_argument("--ply", action="store_true", help="also write start_parts.ply / end_parts.ply (part ids)")
    run.add_argument("--report", action="store_true", help="also write report.png (clouds, axes, stage times)")

    view = commands.add_parser("view", help="an interactive 3-D page of a run's output folder (needs the view extra)")
    view.add_argument("out", type=Path, help="output folder of sparseart run (articulation.json; --ply and/or --urdf)")
    view.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1: this machine only)")
    view.add_argument("--port", type=_integer(0, 65535), default=8080,
                      help="port (default 8080; a busy port moves to the next; 0 = any)")
    view.add_argument("--up", choices=["+x", "-x", "+y", "-y", "+z", "-z"], default=None,
                      help="the scene's up direction (default: -y for a camera frame, +z for a world frame)")
    view.add_argument("--seconds", type=_number(0.0), default=None,
                      help="serve this long, then exit (headless scripts and tests; default: until Ctrl-C)")

    demo = commands.add_parser("demo", help="render a procedural cabinet and recover its joints")
    demo.add_argument("--views", type=int, default=3, choices=[1, 2, 3, 4])
    demo.add_argument("--seed", type=_seed, default=0, help=SEED_HELP)
    demo.add_argument("--keep", type=Path, default=None, help="keep the rendered scene and result here")

    render = commands.add_parser("render", help="render a PartNet-Mobility object at two joint states")
    render.add_argument("object_dir", type=Path, help="object folder with mobility.urdf")
    render.add_argument("scene", type=Path, help="scene folder to write")
    render.add_argument("--views", type=int, default=3, choices=[1, 2, 3, 4])
    render.add_argument("--seed", type=_seed, default=0, help=SEED_HELP)
    render.add_argument("--width", type=_integer(MIN_RENDER_SIDE, MAX_RENDER_SIDE), default=320)
    render.add_argument("--height", type=_integer(MIN_RENDER_SIDE, MAX_RENDER_SIDE), default=240)
    render.add_argument("--unposed", action="store_true", help="omit cam_to_world from cameras.json")
    render.add_argument("--scramble-masks", action="store_true", help="random mask ids per image")
    render.add_argument("--no-masks", action="store_true", help="write no masks")
    render.add_argument("--depth-noise", type=_number(0.0, MAX_DEPTH_NOISE), default=0.0, help="multiplicative depth noise sigma")
    real = render.add_argument_group(
        "realism (sparseart.datasets.realism)",
        "each knob is a level: 0 = off, 1 = its default strength (below), other values scale it (max 5); "
        "--realism picks a preset, the knob flags override single levels, e.g. "
        "--realism realistic --occluder 0 --jpeg 0.5")
    real.add_argument("--realism", choices=["clean", "realistic"], default="clean",
                      help="clean (default: the plain raycast, unchanged scenes) or realistic (every knob at 1)")
    from .datasets.knobs import KNOB_TABLE, MAX_LEVEL

    for knob, (what, at_one) in KNOB_TABLE.items():
        real.add_argument(_knob_flag(knob), type=_number(0.0, MAX_LEVEL), default=None, metavar="LEVEL", dest=f"realism_{knob}",
                          help=f"{what} (at 1: {at_one})".replace("%", "%%"))
    bench = commands.add_parser("bench", help="accuracy against run time over rendered objects, with an ICP peer")
    bench.add_argument("--objects", type=Path, nargs="+", default=None,
                       help="object folders (or folders of them); default ../shared/data/partnet")
    bench.add_argument("--corpus", action="store_true",
                       help="the whole corpus: ../shared/data/partnet, partnet-more and partnet-twins")
    bench.add_argument("--jobs", type=_integer(1), default=None, metavar="N",
                       help="scenes evaluated side by side in N processes (default: every core; same rows as 1)")
    bench.add_argument("--out", type=Path, default=Path("bench_out"), help="results and scene cache folder")
    bench.add_argument("--quick", action="store_true", help="about a minute: 3 small objects, default setting")
    bench.add_argument("--seeds", type=_seed, nargs="+", default=[0], help="render/run seeds (default 0)")
    bench.add_argument("--no-peer", action="store_true", help="skip the ICP baseline")
    bench.add_argument("--settings", nargs="+", default=None, metavar="NAME",
                       help="run only these settings (shell patterns, e.g. default 'realistic*' 'knob-*')")
    bench.add_argument("--geometry", action="store_true",
                       help="also build the URDF / MJCF / USD exports, check them in MuJoCo, PyBullet and pxr, and "
                            "score the part meshes against the true ones (CD-s / CD-m / CD-w); needs .[sim]")
    bench.add_argument("--stability", action="store_true",
                       help="the stiff/extreme-case stability report of the joint fitter instead")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit code (0 ok, 2 bad input, 1 internal error, 130 ^C).

    Every failure prints exactly one line to stderr: bad input (a :class:`SceneError`, a bad
    option) names the file or option and the problem; anything else is a bug, reported in one line
    with a pointer to ``--debug`` (which prints the traceback). Without ``--debug`` Python and
    numpy warnings are silenced, so they cannot add lines to stderr.
    """
    args = _parse_args(argv)
    if isinstance(args, int):
        return args
    import warnings

    import numpy as np

    command = {"run": _cmd_run, "view": _cmd_view, "demo": _cmd_demo, "render": _cmd_render,
               "bench": _cmd_bench}[args.command]
    try:
        with warnings.catch_warnings(), np.errstate(all="ignore" if not args.debug else "warn"):
            if not args.debug:
                warnings.simplefilter("ignore")
            return command(args)
    except SceneError as error:
        print(f"sparseart: error: {_one_line(str(error))}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("sparseart: interrupted", file=sys.stderr)
        return 130
    except BaseException as error:  # noqa: BLE001 - last line of defence: one line, not a traceback
        if isinstance(error, SystemExit):
            raise
        if args.debug:
            traceback.print_exc()
        detail = _one_line(str(error))[:300]
        print(f"sparseart: internal error: {type(error).__name__}{': ' + detail if detail else ''} "
              f"(rerun with --debug for details)", file=sys.stderr)
        return 1


def _one_line(text: str) -> str:
    from sparseart.io.validate import one_line

    return one_line(text)


def _parse_args(argv: list[str] | None) -> argparse.Namespace | int:
    """Parsed arguments, or the exit code after a usage error printed as ONE line (argparse's own
    usage block is dropped; ``--help`` still prints in full)."""
    import contextlib
    import io

    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            return _parser().parse_args(argv)
    except SystemExit as stop:
        code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else EXIT_BAD_INPUT)
        lines = [line for line in captured.getvalue().splitlines() if line.strip()]
        if code != 0 and lines:
            print(_one_line(lines[-1]), file=sys.stderr)
        elif lines:
            print("\n".join(lines), file=sys.stderr)
        return code


def _cmd_run(args: argparse.Namespace) -> int:
    """``sparseart run``: check --out first, run, write every output into a staging folder beside
    --out and move them in together at the end (:mod:`sparseart.io.outputs`)."""
    from sparseart.io.articulation import articulation_to_dict, summary_lines, write_articulation
    from sparseart.io.outputs import StagedOutputs, check_out_dir
    from .joints.config import FitConfig
    from .pipeline import RunOptions, run

    check_out_dir(args.out, args.scene)
    _check_sim_extra(args)
    refine_options, render_states = _refine_settings(args) if args.refine else (None, ())
    options = RunOptions(joint_type=args.joint_type, use_masks=not args.no_masks, seed=args.seed,
                         refine=args.refine, refine_options=refine_options, segmenter=args.segmenter,
                         model=args.model, onnx_options=_onnx_settings(args), threads=args.threads,
                         matcher=args.matcher, matcher_min_score=_matcher_min_score(args),
                         fit=FitConfig.for_budget(args.budget), second_opinion=not args.no_second_opinion)
    labeler = _labeler(args)
    with StagedOutputs(args.out, args.scene) as staged:
        result = run(args.scene, labeler=labeler, options=options)
        try:
            written = [write_articulation(result, staged.path)]
            if args.refine:
                from .refine.outputs import write_refine_outputs

                written += list(write_refine_outputs(result, staged.path, render_states))
            written += _write_extras(result, args, staged.path)
        except OSError as error:
            raise SceneError(f"{args.out}: cannot write the outputs ({error.strerror or error})") from None
        staged.commit()
    path, *extras = [staged.final(p) for p in written]
    if args.json:
        print(json.dumps(articulation_to_dict(result), indent=2))
    else:
        print("\n".join(summary_lines(result)))
        print(f"wrote {path}" + "".join(f", {extra}" for extra in extras))
    return 0


def _cmd_view(args: argparse.Namespace) -> int:
    """``sparseart view OUT``: serve the interactive page of an output folder (sparseart.view;
    viser is imported only here; --port and --seconds are checked by the parser)."""
    from sparseart.view import load_view_data, serve

    data = load_view_data(args.out)  # bad input is reported before viser is needed
    try:
        import viser  # noqa: F401
    except ImportError:
        raise SceneError("sparseart view needs viser: pip install 'sparseart[view]'") from None
    return serve(data, host=args.host, port=args.port, seconds=args.seconds, up=args.up)


def _matcher_min_score(args: argparse.Namespace) -> float | None:
    """--matcher-min-score (None: the matcher's own default; its range is checked by the parser)."""
    if args.matcher is None and args.matcher_min_score is not None:
        raise SceneError("--matcher-min-score needs --matcher")
    return args.matcher_min_score


def _onnx_settings(args: argparse.Namespace):
    """OnnxLiftOptions from --contract/--onnx-mode/--conf-threshold/--threads (None without --model)."""
    if args.model is None:
        for flag, value in (("--contract", args.contract), ("--conf-threshold", args.conf_threshold)):
            if value is not None:
                raise SceneError(f"{flag} needs --model")
        return None
    from .lift.onnx_model import OnnxLiftOptions

    try:
        return OnnxLiftOptions(contract_path=args.contract, mode=args.onnx_mode,
                               confidence_threshold=args.conf_threshold, threads=args.threads)
    except ValueError as error:
        raise SceneError(str(error).replace("OnnxLiftOptions.", "--")) from None


def _labeler(args: argparse.Namespace):
    """The part labeler of --labeler (None = the pipeline's default rule-based one)."""
    if args.labeler == "rules":
        return None
    from .labelers.vlm import VlmLabeler, VlmLabelerConfig

    try:
        return VlmLabeler(args.vlm_base_url, args.vlm_model, timeout=args.vlm_timeout,
                          config=VlmLabelerConfig(max_pairs=args.vlm_pairs))
    except ValueError as error:
        raise SceneError(f"--labeler vlm: {error}") from None


def _write_extras(result, args: argparse.Namespace, out_dir: Path | None = None) -> list[Path]:
    """The --urdf / --mjcf / --usd / --ply / --report files beside articulation.json, in ``out_dir`` (default
    ``args.out``; ``_cmd_run`` passes its staging folder)."""
    out_dir = Path(args.out if out_dir is None else out_dir)
    written: list[Path] = []
    written.extend(_write_sim_exports(result, args, out_dir))
    if getattr(args, "ply", False):
        from sparseart.io.ply import write_labelled_clouds

        written.extend(write_labelled_clouds(result, out_dir))
    if getattr(args, "report", False):
        from sparseart.io.report import write_report

        written.append(write_report(result, out_dir / "report.png"))
    return written


def _sim_flags(args: argparse.Namespace) -> list[str]:
    """The simulator exports asked for: "urdf", "mjcf", "usd" in that order."""
    return [flag for flag in ("urdf", "mjcf", "usd") if getattr(args, flag, False)]


def _check_sim_extra(args: argparse.Namespace) -> None:
    """Before any work: --urdf / --mjcf / --usd need the ``sim`` extra (coacd, trimesh; pxr for USD)."""
    import importlib.util

    flags = _sim_flags(args)
    needed = ["coacd", "trimesh", *(["pxr"] if "usd" in flags else [])] if flags else []
    missing = [module for module in needed if importlib.util.find_spec(module) is None]
    if missing:
        names = " / ".join(f"--{flag}" for flag in flags)
        raise SceneError(f"{names} needs {', '.join(missing)}: pip install 'sparseart[sim]' (scripts/setup.sh does)")


def _write_sim_exports(result, args: argparse.Namespace, out_dir: Path) -> list[Path]:
    """--urdf / --mjcf / --usd from one :class:`~sparseart.sim.model.SimModel` (surfaces, collision and
    mass built once; nothing imported without these flags); the seconds of each step go to
    meshes/summary.json."""
    import time

    flags = _sim_flags(args)
    if not flags:
        return []
    names = " / ".join(f"--{flag}" for flag in flags)
    from sparseart.io.mjcf import write_mjcf
    from sparseart.io.urdf import write_urdf
    from sparseart.io.usd import write_usd
    from sparseart.sim.model import build_model, write_summary

    try:
        model = build_model(result, name="object", seed=args.seed)
        written = []
        for flag in flags:
            began = time.perf_counter()
            written.append({"urdf": write_urdf, "mjcf": write_mjcf, "usd": write_usd}[flag](
                result, out_dir, name="object", model=model))
            model.seconds[flag] = time.perf_counter() - began
    except ValueError as error:
        raise SceneError(f"{names}: {error}") from None
    write_summary(model, out_dir)
    return written


def _cmd_bench(args: argparse.Namespace) -> int:
    if args.out.exists() and not args.out.is_dir():
        raise SceneError(f"{args.out}: --out exists and is not a folder")
    if args.stability:
        from sparseart.bench.stability import run_stability

        print(run_stability(args.out, quick=args.quick))
        return 0
    from sparseart.bench.grid import QUICK_OBJECTS, corpus_dirs, default_jobs, find_objects, report_text, run_bench

    objects = find_objects([*(args.objects or []), *(corpus_dirs() if args.corpus else [])] or None)
    if args.quick:
        small = [o for o in objects if o.name in QUICK_OBJECTS]
        objects = small or objects[:3]
    result = run_bench(objects, args.out, seeds=args.seeds, quick=args.quick, peer=not args.no_peer,
                       names=args.settings, jobs=args.jobs or default_jobs(), geometry=args.geometry)
    print(report_text(result))
    print(f"wrote {args.out}/table.txt, rows.csv/json, summary.csv/json, error_vs_time.png, error_vs_factor.png")
    return 0 if result.rows else 1


def _refine_settings(args: argparse.Namespace):
    """(RefineOptions, render-state fractions) from the run command's --refine-* options (their
    ranges are checked by the parser)."""
    from .refine.api import RefineOptions, with_iterations

    try:
        states = tuple(float(v) for v in args.render_states.split(",") if v.strip())
    except ValueError:
        raise SceneError(f"--render-states: expected comma-separated numbers, got {args.render_states!r}") from None
    if not states or not all(math.isfinite(v) for v in states):
        raise SceneError(f"--render-states: expected finite numbers, got {args.render_states!r}")
    options = RefineOptions(seed=args.seed, holdout_views=args.refine_holdout)
    if args.refine_iters is not None:
        options = with_iterations(options, args.refine_iters)
    if args.refine_budget is not None:
        options.object_budget_seconds = args.refine_budget or None
    return options, states


def _knob_flag(knob: str) -> str:
    """Command-line flag of a realism knob (``depth_noise`` -> ``--depth-noise-level``, since
    ``--depth-noise`` is the older plain sigma)."""
    return "--depth-noise-level" if knob == "depth_noise" else "--" + knob.replace("_", "-")


def _realism_settings(args: argparse.Namespace):
    """The Realism of --realism and the knob flags."""
    from .datasets.realism import KNOBS, preset

    levels = {k: getattr(args, f"realism_{k}") for k in KNOBS if getattr(args, f"realism_{k}", None) is not None}
    try:
        return preset(args.realism).with_levels(**levels)
    except ValueError as error:
        flags = {f"Realism.{k}": _knob_flag(k) for k in KNOBS}
        message = str(error)
        for name, flag in flags.items():
            message = message.replace(name + ":", flag + ":")
        raise SceneError(message) from None


def _cmd_render(args: argparse.Namespace) -> int:
    from .datasets.partnet import render_partnet_scene

    if not (args.object_dir / "mobility.urdf").exists():
        raise SceneError(f"{args.object_dir / 'mobility.urdf'}: not found (expected a PartNet-Mobility object)")
    realism = _realism_settings(args)
    gt = render_partnet_scene(args.object_dir, args.scene, views=args.views, seed=args.seed,
                              width=args.width, height=args.height, posed=not args.unposed,
                              scramble_masks=args.scramble_masks, depth_noise=args.depth_noise,
                              write_masks=not args.no_masks, realism=realism)
    for joint in gt["joints"]:
        amount = (f"angle {math.degrees(joint['angle']):.1f} deg" if joint["type"] == "revolute"
                  else f"distance {joint['distance']:.3f}")
        print(f"{joint['name']}: {joint['type']} {amount}")
    if not realism.is_clean:
        print("realism: " + ", ".join(f"{k} {v:g}" for k, v in realism.levels().items() if v))
    print(f"wrote {args.scene}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from .datasets.synth import render_synth_scene
    from sparseart.bench.evaluate import evaluate
    from sparseart.io.articulation import summary_lines, write_articulation
    from .pipeline import run
    from sparseart.io.scene import load_scene

    with tempfile.TemporaryDirectory(prefix="sparseart-demo-") as temp:
        base = args.keep or Path(temp)
        scene_dir = base / "scene"
        print(f"rendering a procedural cabinet (door + drawer), {args.views} views per state -> {scene_dir}")
        gt = render_synth_scene(scene_dir, views=args.views, seed=args.seed)
        scene = load_scene(scene_dir)
        result = run(scene)
        print("\n".join(summary_lines(result)))
        rows = evaluate(result, scene, gt)
        print("\nestimated vs true:")
        print(f"{'joint':10s} {'true type':10s} {'est type':10s} {'axis err':>9s} {'pos err':>8s} {'state err':>10s}")
        for row, truth in zip(rows, gt["joints"]):
            unit = "deg" if truth["type"] == "revolute" else "m"
            position = "-" if row["position"] is None else f"{row['position']:.4f}"
            print(f"{row['name'] or '?':10s} {truth['type']:10s} {row['pred_type'] or 'missed':10s} "
                  f"{row['axis_deg']:8.2f}° {position:>8s} {row['state']:8.3f} {unit}")
        if args.keep:
            write_articulation(result, base / "out")
            print(f"kept {scene_dir} and {base / 'out'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
