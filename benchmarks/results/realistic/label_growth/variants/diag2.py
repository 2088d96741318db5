import sys, os, json, numpy as np, sparseart
from pathlib import Path
from sparseart import RunOptions
from sparseart.io.scene import load_scene
from sparseart.bench.evaluate import true_groups
import sparseart.labelers.rules as rules
from dataclasses import replace
orig = rules.grow_parts
mode = os.environ.get("GROW", "id")
def patched(labels, s, e, cfg, rng):
    before = labels.start_part.copy(), labels.end_part.copy()
    out = {} if mode == "off" else orig(labels, s, e, replace(cfg, identity_excludes=("id" in mode), takes_unassigned=("static" not in mode), colour_gap=float(os.environ.get("CGAP", "0.06"))), rng)
    patched.before = before
    return out
rules.grow_parts = patched
name = sys.argv[1]
scene = load_scene(name); gt = json.loads((Path(name) / "gt.json").read_text())
r = sparseart.run(scene, options=RunOptions(use_masks=False, seed=int(sys.argv[2]) if len(sys.argv) > 2 else 0, second_opinion=False))
gs = true_groups(r.start_cloud, scene, gt); ge = true_groups(r.end_cloud, scene, gt)
bs, be = patched.before
for st, g, b, a in (("start", gs, bs, r.labels.start_part), ("end", ge, be, r.labels.end_part)):
    for p in r.labels.parts:
        if p.role != "movable": continue
        was = dict(zip(*[x.tolist() for x in np.unique(g[b == p.id], return_counts=True)]))
        new = dict(zip(*[x.tolist() for x in np.unique(g[(a == p.id) & (b != p.id)], return_counts=True)]))
        print(st, "part", p.id, "had", was, "added", new)
print("true parts", {j["mask_id"]: (int((gs == j["mask_id"]).sum()), int((ge == j["mask_id"]).sum())) for j in gt["joints"]})
for part, j in r.joints:
    print(part.spec.id, j.type, np.round(j.axis, 3), "conf %.3f" % j.confidence)
print([np.round(j["axis"], 3).tolist() for j in gt["joints"]])
