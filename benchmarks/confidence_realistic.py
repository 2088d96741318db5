"""Does the depth confidence (``{state}/conf/NNN.npy``) help? Issue 13 item 4.

Renders each object with ``sparseart render OBJECT SCENE --realism realistic --views 3 --seed 0``
(posed, and ``--unposed``), runs the pipeline once per variant and prints one JSON row per ground
truth joint (``sparseart.bench.evaluate``):

    none      conf/ ignored (frame.depth_confidence cleared after loading: a scene without conf/)
    drop      labelled clouds without points below the threshold (``build_labelled_cloud``)
    weight    pairs and Chamfer residuals weighted by sqrt(c_start c_end) (``FitConfig.confidence_weights``)
    both      drop + weight

Usage: PYTHONPATH=. python3 benchmarks/confidence_realistic.py SCENES_DIR posed|unposed OBJECT VARIANT [THRESHOLD]
(SCENES_DIR/posed/OBJECT, SCENES_DIR/unposed/OBJECT rendered beforehand). Results:
benchmarks/results/confidence_realistic.txt.
"""
from __future__ import annotations

import json
import sys
import time

import sparseart
import sparseart.io.scene as scene_io
from sparseart import pipeline
from sparseart.bench.evaluate import evaluate
from sparseart.io.scene import load_scene
from sparseart.joints.config import FitConfig
from sparseart.lift import labels


def main(argv: list[str]) -> None:
    root, mode, obj, variant = argv[:4]
    threshold = float(argv[4]) if len(argv) > 4 else 0.15
    scene_dir = f"{root}/{mode}/{obj}"
    with open(f"{scene_dir}/gt.json") as stream:
        gt = json.load(stream)
    if variant == "none":
        read_state = scene_io._read_state

        def without_conf(*args, **kwargs):
            frames = read_state(*args, **kwargs)
            for frame in frames:
                frame.depth_confidence = None
            return frames
        scene_io._read_state = without_conf
    labels.DEPTH_CONFIDENCE_MIN = threshold if variant in ("drop", "both") else 0.0
    fit = FitConfig(confidence_weights=variant in ("weight", "both"))
    began = time.time()
    result = sparseart.run(scene_dir, options=pipeline.RunOptions(fit=fit))
    for row in evaluate(result, load_scene(scene_dir), gt):
        print(json.dumps({"mode": mode, "obj": obj, "variant": variant, "thr": threshold,
                          "sec": round(time.time() - began, 1),
                          **{k: row.get(k) for k in ("name", "part", "axis_deg", "position", "type_correct")}}))


if __name__ == "__main__":
    main(sys.argv[1:])
