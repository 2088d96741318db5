"""Quality and speed of the built-in segmenter on rendered PartNet-Mobility scenes.

Renders every object in ../shared/data/partnet (320x240, ``--views`` per state, seed ``--seed``),
segments every image with the built-in rule-based segmenter (with depth, and with ``--no-depth``
colour only) and compares with the rendered true-part masks (static_mask_id = 1, movable parts
2..). Per object: segments per image, purity, leakage, coverage (sparseart.segment.base.
segmentation_quality; the worst image is also shown) and milliseconds per image.

    python3 benchmarks/segment_quality.py [--views 2] [--seed 0] [--out benchmarks/results/segment_quality.txt]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from sparseart.datasets.partnet import render_partnet_scene  # noqa: E402
from sparseart.io.scene import load_scene, write_bytes_atomic  # noqa: E402
from sparseart.segment.base import segmentation_quality  # noqa: E402
from sparseart.segment.rules import RuleSegmenter  # noqa: E402

PARTNET = REPO.parent / "shared" / "data" / "partnet"


def evaluate_object(object_dir: Path, work: Path, views: int, seed: int, use_depth: bool,
                    segmenter: RuleSegmenter) -> dict:
    scene_dir = work / object_dir.name
    if not scene_dir.exists():
        render_partnet_scene(object_dir, scene_dir, views=views, seed=seed)
    scene = load_scene(scene_dir)
    rows, seconds = [], []
    for frame in scene.all_frames:
        truth = frame.mask
        frame.mask = None
        if not use_depth:
            frame.depth = None
        start = time.perf_counter()
        labels = segmenter.segment(frame)
        seconds.append(time.perf_counter() - start)
        rows.append(segmentation_quality(labels, truth))
    keys = ("segments", "purity", "leakage", "coverage")
    mean = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    mean["worst_purity"] = float(min(r["purity"] for r in rows))
    mean["ms"] = 1000.0 * float(np.median(seconds))
    return mean


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--objects", nargs="*", help="object folder names (default: all)")
    parser.add_argument("--out", type=Path, default=None, help="also write the table here (atomically)")
    args = parser.parse_args()
    objects = sorted(p for p in PARTNET.iterdir() if p.is_dir())
    if args.objects:
        objects = [p for p in objects if p.name in args.objects]
    segmenter = RuleSegmenter()
    lines = [f"built-in segmenter on rendered PartNet scenes: 320x240, {args.views} views per state, "
             f"seed {args.seed}, {2 * args.views} images per object; means over images",
             "purity = object pixels whose segment's majority part is their own; leakage = true part-"
             "boundary pixel pairs inside one segment; ms = median per image (2 shared cores, contended)"]
    with tempfile.TemporaryDirectory(prefix="segment_quality_") as tmp:
        for use_depth in (True, False):
            lines.append("")
            lines.append("RGB-D (depth + K)" if use_depth else "RGB only (no depth: no background, colour only)")
            lines.append(f"{'object':26s} {'segs':>5s} {'purity':>7s} {'worst':>7s} {'leak':>6s} "
                         f"{'cover':>6s} {'ms':>6s}")
            table = []
            for object_dir in objects:
                row = evaluate_object(object_dir, Path(tmp), args.views, args.seed, use_depth, segmenter)
                table.append(row)
                lines.append(f"{object_dir.name:26s} {row['segments']:5.1f} {row['purity']:7.3f} "
                             f"{row['worst_purity']:7.3f} {row['leakage']:6.3f} {row['coverage']:6.3f} "
                             f"{row['ms']:6.0f}")
                print(lines[-1], flush=True)
            lines.append(f"{'mean':26s} {np.mean([r['segments'] for r in table]):5.1f} "
                         f"{np.mean([r['purity'] for r in table]):7.3f} "
                         f"{min(r['worst_purity'] for r in table):7.3f} "
                         f"{np.mean([r['leakage'] for r in table]):6.3f} "
                         f"{np.mean([r['coverage'] for r in table]):6.3f} "
                         f"{np.median([r['ms'] for r in table]):6.0f}")
            print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    if args.out is not None:
        write_bytes_atomic(args.out, text.encode())
    else:
        print(text)


if __name__ == "__main__":
    main()
