"""The real capture in turned world frames: does the answer depend on the frame it is given?

    python benchmarks/real_capture_frames.py [--capture ../shared/data/real/screwmimic_close_laptop_2]
                                             [--yaws 0 30 60 ...] [--tilt 0] [--rotation X Y Z --shift X Y Z]

A robot's base frame, or the object's placement on the table, fixes nothing about the object: the
same capture with every ``cam_to_world`` composed with one rigid map M (a turn by ``--yaws`` about
the vertical through the estimated hinge, after a ``--tilt`` about x; or any ``--rotation`` xyz
Euler angles in degrees plus ``--shift`` in metres) must give the same joint, moved by M. Per
frame it runs ``sparseart.run`` with the default options and prints every joint found: axis error
(deg) and hinge-line distance (mm) against ``gt_estimate.json`` moved by M, the turn (deg, to
compare with 180 - the estimate's ``angle_deg_abs``, see tests/test_real_capture.py), the
confidence and the seconds. Each frame is a copy of the capture in a temporary folder, removed
afterwards. O(frames x one run, ~10 s each on 2 cores).
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CAPTURE = REPO.parent / "shared" / "data" / "real" / "screwmimic_close_laptop_2"


def turned_copy(capture: Path, folder: Path, world: np.ndarray) -> None:
    """Copy ``capture`` to ``folder`` with every cam_to_world replaced by world @ cam_to_world."""
    shutil.copytree(capture, folder)
    cameras = json.loads((capture / "cameras.json").read_text())
    for state in ("start", "end"):
        for view in cameras[state]:
            view["cam_to_world"] = (world @ np.asarray(view["cam_to_world"], dtype=np.float64)).tolist()
    (folder / "cameras.json").write_text(json.dumps(cameras))


def frame_map(rotation: np.ndarray, pivot: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """(4, 4) rigid map turning by ``rotation`` about ``pivot`` (3,), then shifting by ``shift``."""
    world = np.eye(4)
    world[:3, :3] = rotation
    world[:3, 3] = pivot - rotation @ pivot + shift
    return world


def run_frame(capture: Path, world: np.ndarray, gt: dict) -> list[dict]:
    """The joints found in the turned copy, each scored against the moved estimate."""
    import sparseart
    from sparseart.bench.metrics import axis_angle_error_deg, point_to_line_distance

    axis = world[:3, :3] @ np.asarray(gt["axis"], dtype=np.float64)
    origin = world[:3, :3] @ np.asarray(gt["origin"], dtype=np.float64) + world[:3, 3]
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / capture.name
        turned_copy(capture, folder, world)
        began = time.perf_counter()
        result = sparseart.run(folder)
        seconds = time.perf_counter() - began
    rows = []
    for _, joint in result.joints:
        rows.append({"type": joint.type, "axis_deg": axis_angle_error_deg(joint.axis, axis),
                     "hinge_mm": (1000.0 * point_to_line_distance(origin, joint.axis, joint.origin)
                                  if joint.type == "revolute" else None),
                     "turn_deg": abs(math.degrees(joint.angle)) if joint.angle is not None else None,
                     "confidence": joint.confidence, "seconds": seconds})
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--capture", type=Path, default=DEFAULT_CAPTURE)
    parser.add_argument("--yaws", type=float, nargs="+", default=[0.0, 30.0, 60.0, 90.0, 120.0, 150.0, 180.0,
                                                                 210.0, 240.0, 270.0, 300.0, 330.0])
    parser.add_argument("--tilt", type=float, default=0.0, help="turn about x before the yaw (deg)")
    parser.add_argument("--rotation", type=float, nargs=3, help="xyz Euler angles (deg) instead of the yaws")
    parser.add_argument("--shift", type=float, nargs=3, default=[0.0, 0.0, 0.0], help="metres")
    args = parser.parse_args(argv)
    if not (args.capture / "gt_estimate.json").is_file():
        print(f"real_capture_frames: {args.capture / 'gt_estimate.json'} not found", file=sys.stderr)
        return 2
    gt = json.loads((args.capture / "gt_estimate.json").read_text())["joints"][0]
    pivot, shift = np.asarray(gt["origin"], dtype=np.float64), np.asarray(args.shift, dtype=np.float64)
    if args.rotation is not None:
        frames = [(f"xyz {args.rotation}", Rotation.from_euler("xyz", args.rotation, degrees=True).as_matrix())]
    else:
        frames = [(f"yaw {yaw:g} tilt {args.tilt:g}",
                   Rotation.from_euler("zx", [yaw, args.tilt], degrees=True).as_matrix()) for yaw in args.yaws]
    print(f"{'frame':22s} {'joints':>6s}  per joint: type, axis err deg, hinge mm, turn deg, confidence   seconds")
    for name, rotation in frames:
        rows = run_frame(args.capture, frame_map(rotation, pivot, shift), gt)
        found = "; ".join(f"{r['type'][:3]} {r['axis_deg']:.1f} {r['hinge_mm'] if r['hinge_mm'] is None else round(r['hinge_mm'], 1)} "
                          f"{r['turn_deg'] if r['turn_deg'] is None else round(r['turn_deg'], 1)} {r['confidence']:.2f}"
                          for r in rows)
        seconds = rows[0]["seconds"] if rows else float("nan")
        print(f"{name:22s} {len(rows):6d}  {found}   {seconds:.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
