"""Command line: ``sparseart run | demo | render``.

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

from .types import SceneError

EXIT_BAD_INPUT = 2


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sparseart", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show tracebacks of internal errors")
    commands = parser.add_subparsers(dest="command", required=True)

    run = commands.add_parser("run", help="recover the joints of a scene folder")
    run.add_argument("scene", type=Path, help="scene folder (start/, end/, cameras.json)")
    run.add_argument("--out", type=Path, required=True, help="output folder for articulation.json")
    run.add_argument("--joint-type", choices=["auto", "revolute", "prismatic"], default="auto",
                     help="known joint type of every movable part (default: classify)")
    run.add_argument("--no-masks", action="store_true", help="ignore the scene's masks")
    run.add_argument("--json", action="store_true", help="print articulation.json instead of a summary")
    run.add_argument("--seed", type=int, default=0)

    demo = commands.add_parser("demo", help="render a procedural cabinet and recover its joints")
    demo.add_argument("--views", type=int, default=3, choices=[1, 2, 3, 4])
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--keep", type=Path, default=None, help="keep the rendered scene and result here")

    render = commands.add_parser("render", help="render a PartNet-Mobility object at two joint states")
    render.add_argument("object_dir", type=Path, help="object folder with mobility.urdf")
    render.add_argument("scene", type=Path, help="scene folder to write")
    render.add_argument("--views", type=int, default=3, choices=[1, 2, 3, 4])
    render.add_argument("--seed", type=int, default=0)
    render.add_argument("--width", type=int, default=320)
    render.add_argument("--height", type=int, default=240)
    render.add_argument("--unposed", action="store_true", help="omit cam_to_world from cameras.json")
    render.add_argument("--scramble-masks", action="store_true", help="random mask ids per image")
    render.add_argument("--no-masks", action="store_true", help="write no masks")
    render.add_argument("--depth-noise", type=float, default=0.0, help="multiplicative depth noise sigma")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return {"run": _cmd_run, "demo": _cmd_demo, "render": _cmd_render}[args.command](args)
    except SceneError as error:
        print(f"sparseart: error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("sparseart: interrupted", file=sys.stderr)
        return 130
    except Exception as error:  # noqa: BLE001 - last line of defence: one line, not a traceback
        if args.debug:
            traceback.print_exc()
        print(f"sparseart: internal error: {type(error).__name__}: {error} (rerun with --debug for details)",
              file=sys.stderr)
        return 1


def _cmd_run(args: argparse.Namespace) -> int:
    from .export import articulation_to_dict, summary_lines, write_articulation
    from .pipeline import RunOptions, run

    if args.out.exists() and not args.out.is_dir():
        raise SceneError(f"{args.out}: --out exists and is not a folder")
    result = run(args.scene, options=RunOptions(joint_type=args.joint_type, use_masks=not args.no_masks,
                                                seed=args.seed))
    path = write_articulation(result, args.out)
    if args.json:
        print(json.dumps(articulation_to_dict(result), indent=2))
    else:
        print("\n".join(summary_lines(result)))
        print(f"wrote {path}")
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from .datasets.partnet import render_partnet_scene

    if not (args.object_dir / "mobility.urdf").exists():
        raise SceneError(f"{args.object_dir / 'mobility.urdf'}: not found (expected a PartNet-Mobility object)")
    gt = render_partnet_scene(args.object_dir, args.scene, views=args.views, seed=args.seed,
                              width=args.width, height=args.height, posed=not args.unposed,
                              scramble_masks=args.scramble_masks, depth_noise=args.depth_noise,
                              write_masks=not args.no_masks)
    for joint in gt["joints"]:
        amount = (f"angle {math.degrees(joint['angle']):.1f} deg" if joint["type"] == "revolute"
                  else f"distance {joint['distance']:.3f}")
        print(f"{joint['name']}: {joint['type']} {amount}")
    print(f"wrote {args.scene}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from .datasets.synth import render_synth_scene
    from .evaluate import evaluate
    from .export import summary_lines, write_articulation
    from .pipeline import run
    from .scene import load_scene

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
