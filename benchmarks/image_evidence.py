"""How much do the pictures say about a fitted joint? The evidence a photometric refinement could use.

    python benchmarks/image_evidence.py SCENE_DIR [SCENE_DIR ...] [--setting realistic] [--true-cameras]

For each bench scene folder (rendered by ``sparseart bench``; ``gt.json`` beside it) the pipeline
runs as the bench runs it (``--setting``: its masks, matcher and budget). Then, per moving part
with a joint, the real XFeat + LighterGlue weights (``../shared/models``) match every start image
to every end image, and the matches whose two pixels lie on the part's pixels in both states
(dilated by one pixel) are kept. For each match the start pixel's ray, carried by a motion, must
meet the end pixel's ray: the residual is the end pixel's distance (px) to that carried ray's
image, the epipolar line. It needs no depth, so a depth warp cannot bias it; it needs the cameras:
the scene's poses when posed, else each view's camera recovered from its points
(``refine.views.recover_cam_to_world``), or with ``--true-cameras`` the renderer's true cameras
(an oracle no user has).

Printed per joint: the matches, the median residual under the fitted motion and under the true
motion, and what a MAP fit makes of them: the fitted joint's stated sigmas as its prior, plus the
matches' residuals (soft-L1 at 1.5 px), solved by least squares from the fit; its axis / state
error beside the fit's. If the pictures carried the joint more sharply than the points, the true
motion's residual would sit well below the fit's and the MAP fit would move towards the truth.
O(pairs x matcher + joints x least squares over the kept matches).
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
MODELS = REPO.parent / "shared" / "models"
SOFT_PX = 1.5          # soft-L1 scale of a match's epipolar residual (px)


def epipolar_residuals(transform: np.ndarray, matches: list[tuple]) -> np.ndarray:
    """(M,) signed distances (px) of each end pixel to the image of its start ray carried by
    ``transform`` ((4, 4) start -> end, scene frame). matches: tuples (K_s, cam_to_world_s, K_e,
    cam_to_world_e, pixels_s (k, 2), pixels_e (k, 2)) per image pair. O(M)."""
    out = []
    rotation, translation = transform[:3, :3], transform[:3, 3]
    for K_s, pose_s, K_e, pose_e, pixels_s, pixels_e in matches:
        rays = np.c_[pixels_s, np.ones(len(pixels_s))] @ np.linalg.inv(K_s).T @ pose_s[:3, :3].T
        to_end = np.linalg.inv(pose_e)
        origin = to_end[:3, :3] @ (rotation @ pose_s[:3, 3] + translation) + to_end[:3, 3]
        directions = rays @ rotation.T @ to_end[:3, :3].T
        lines = np.cross(origin[None, :], directions) @ np.linalg.inv(K_e)   # K^-T n, as rows
        ends = np.c_[pixels_e, np.ones(len(pixels_e))]
        out.append((lines * ends).sum(axis=1) / np.maximum(np.linalg.norm(lines[:, :2], axis=1), 1e-12))
    return np.concatenate(out) if out else np.zeros(0)


def part_pixels(cloud, part_of_point: np.ndarray, part_id: int, frame_index: int, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: the pixels of ``part_id``'s points in one frame, dilated by one pixel."""
    import cv2

    image = np.zeros(shape[0] * shape[1], dtype=np.uint8)
    image[cloud.pixel_index[(part_of_point == part_id) & (cloud.frame_index == frame_index)]] = 1
    return cv2.dilate(image.reshape(shape), np.ones((3, 3), np.uint8)) > 0


def cameras(scene, cloud, state: str, truth: dict | None, to_world: np.ndarray) -> dict[int, tuple]:
    """frame index -> (K, cam_to_world in the scene frame)."""
    from sparseart.refine.views import recover_cam_to_world

    found = {}
    for k, frame in enumerate(scene.frames(state)):
        if truth is not None:
            pose = np.linalg.inv(to_world) @ np.asarray(truth["cameras"][state][k], dtype=np.float64)
        elif scene.posed:
            pose = frame.camera.cam_to_world
        else:
            pose = recover_cam_to_world(frame.depth, frame.camera.K, cloud, frame.index)
        if pose is not None:
            found[frame.index] = (np.asarray(frame.camera.K, dtype=np.float64), np.asarray(pose, dtype=np.float64))
    return found


def true_motion(gt_joint: dict, to_world: np.ndarray, fitted: np.ndarray, residual) -> np.ndarray:
    """The true start -> end motion in the scene frame (of the two signs, the one the matches fit best)."""
    from sparseart.geometry.transforms import transform_from_prismatic, transform_from_revolute

    options = []
    for sign in (1.0, -1.0):
        if gt_joint["type"] == "revolute":
            world = transform_from_revolute(np.asarray(gt_joint["axis"]), np.asarray(gt_joint["origin"]),
                                            sign * gt_joint["angle"])
        else:
            world = transform_from_prismatic(np.asarray(gt_joint["axis"]), sign * gt_joint["distance"])
        options.append(np.linalg.inv(to_world) @ world @ to_world)
    return min(options, key=lambda t: float(np.median(np.abs(residual(t)))))


def map_fit(joint, residual):
    """The fitted joint moved by least squares on soft-L1 epipolar residuals plus its own stated
    sigmas as a prior. Returns the new JointEstimate."""
    from scipy.optimize import least_squares

    from sparseart.geometry.transforms import (tangent_basis, transform_from_prismatic,
                                               transform_from_revolute, unit)

    basis = tangent_basis(joint.axis)
    sigma = joint.uncertainty
    axis_sigma = np.radians(max(sigma.get("axis_deg", 1.0), 0.05))
    revolute = joint.type == "revolute"

    def build(x):
        axis = unit(joint.axis + basis @ x[:2])
        if revolute:
            origin = joint.origin + basis @ x[2:4]
            return replace(joint, axis=axis, origin=origin, angle=joint.angle + x[4],
                           transform=transform_from_revolute(axis, origin, joint.angle + x[4]))
        return replace(joint, axis=axis, distance=joint.distance + x[2],
                       transform=transform_from_prismatic(axis, joint.distance + x[2]))

    def prior(x):
        if revolute:
            return np.r_[x[:2] / axis_sigma, x[2:4] / max(sigma.get("origin", 0.01), 1e-4),
                         x[4] / max(sigma.get("angle", 0.02), 1e-3)]
        return np.r_[x[:2] / axis_sigma, x[2] / max(sigma.get("distance", 0.01), 1e-4)]

    def cost(x):
        r = residual(build(x).transform) / SOFT_PX
        return np.r_[np.sqrt(2.0 * (np.sqrt(1.0 + r * r) - 1.0)), prior(x)]

    solution = least_squares(cost, np.zeros(5 if revolute else 3))
    return build(solution.x)


def run_scene(scene_dir: Path, setting_name: str, true_cameras: bool, matcher) -> list[str]:
    from sparseart.bench.evaluate import _result_to_gt_frame, evaluate
    from sparseart.bench.grid import grid_settings
    from sparseart.io.scene import load_scene
    from sparseart.joints.config import FitConfig
    from sparseart.pipeline import RunOptions, run

    setting = next(s for s in grid_settings(0)[0] if s.name == setting_name)
    gt = json.loads((scene_dir / "gt.json").read_text())
    scene = load_scene(scene_dir)
    result = run(scene, options=RunOptions(use_masks=setting.use_masks, seed=0, segmenter=setting.segmenter,
                                           matcher=setting.matcher, fit=FitConfig.for_budget(setting.budget)))
    before = evaluate(result, scene, gt)
    to_world = _result_to_gt_frame(result, gt, scene)
    truth = gt if true_cameras else None
    start, end, labels = result.start_cloud, result.end_cloud, result.labels
    cams = {state: cameras(scene, cloud, state, truth, to_world) for state, cloud in (("start", start), ("end", end))}
    frames = {state: {f.index: f for f in scene.frames(state)} for state in ("start", "end")}
    pixel_matches = {(a, b): matcher.match(frames["start"][a].rgb, frames["end"][b].rgb)
                     for a in cams["start"] for b in cams["end"]}
    lines, notes = [], {}
    for row in before:
        part = next((p for p in result.parts if p.spec.id == row.get("part")), None)
        if part is None or part.joint is None:
            continue
        kept = []
        for (a, b), found in pixel_matches.items():
            on_start = part_pixels(start, labels.start_part, part.spec.id, a, frames["start"][a].rgb.shape[:2])
            on_end = part_pixels(end, labels.end_part, part.spec.id, b, frames["end"][b].rgb.shape[:2])
            ia, ib = np.round(found.pixels_a).astype(int), np.round(found.pixels_b).astype(int)
            keep = on_start[ia[:, 1], ia[:, 0]] & on_end[ib[:, 1], ib[:, 0]]
            if keep.any():
                kept.append((*cams["start"][a], *cams["end"][b], found.pixels_a[keep], found.pixels_b[keep]))
        count = sum(len(k[4]) for k in kept)
        residual = lambda transform: epipolar_residuals(transform, kept)  # noqa: E731
        if count < 8:
            notes[row["name"]] = f"{count:4d} matches"
            continue
        gt_joint = next(j for j in gt["joints"] if j["name"] == row["name"])
        at_fit = float(np.median(np.abs(residual(part.joint.transform))))
        at_truth = float(np.median(np.abs(residual(true_motion(gt_joint, to_world, part.joint.transform, residual)))))
        part.joint = map_fit(part.joint, residual)
        notes[row["name"]] = f"{count:4d} matches  fit {at_fit:5.2f} px  truth {at_truth:5.2f} px"
    after = {r["name"]: r for r in evaluate(result, scene, gt)}
    for row in before:
        if row["name"] not in notes:
            continue
        moved = after[row["name"]]
        mapped = (f"  MAP axis {moved['axis_deg']:6.2f}  state {moved['state']:8.3f}" if "px" in notes[row["name"]] else "")
        lines.append(f"{scene_dir.name[:24]:24s} {row['name']:8s} {notes[row['name']]}  fitted axis "
                     f"{row['axis_deg']:6.2f}  state {row['state']:8.3f}{mapped}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="+", type=Path)
    parser.add_argument("--setting", default="realistic")
    parser.add_argument("--true-cameras", action="store_true")
    args = parser.parse_args(argv)
    from sparseart.align.matchers import open_matcher

    detector, glue = MODELS / "xfeat.onnx", MODELS / "lighterglue_L3.onnx"
    if not (detector.is_file() and glue.is_file()):
        print(f"image_evidence: {MODELS}: the XFeat / LighterGlue weights are not there", file=sys.stderr)
        return 2
    matcher = open_matcher(f"xfeat:{detector},{glue}")
    for scene_dir in args.scenes:
        for line in run_scene(scene_dir, args.setting, args.true_cameras, matcher):
            print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
