"""Per predicted part: composition by true group; fit from true points."""
import sys, json, glob, numpy as np, sparseart
from pathlib import Path
from sparseart import RunOptions
from sparseart.io.scene import load_scene
from sparseart.bench.evaluate import true_groups
from sparseart.joints import fit_joint
name = glob.glob(sys.argv[1])[0]
use_masks = sys.argv[2] != "nomask" if len(sys.argv) > 2 else True
scene = load_scene(name); gt = json.loads((Path(name) / "gt.json").read_text())
r = sparseart.run(scene, options=RunOptions(use_masks=use_masks, seed=0, second_opinion=False))
print("gt joints:", [(j.get("name"), j["mask_id"], j["type"]) for j in gt["joints"]])
gs = true_groups(r.start_cloud, scene, gt); ge = true_groups(r.end_cloud, scene, gt)
ls, le = r.labels.start_part, r.labels.end_part
for p in r.labels.parts:
    cs = np.unique(gs[ls == p.id], return_counts=True); ce = np.unique(ge[le == p.id], return_counts=True)
    print(p.id, p.role, "start", dict(zip(*[a.tolist() for a in cs])), "end", dict(zip(*[a.tolist() for a in ce])))
for j in gt["joints"]:
    m = j["mask_id"]
    print("true group", m, "start n", int((gs == m).sum()), "end n", int((ge == m).sum()),
          "labelled as", dict(zip(*[a.tolist() for a in np.unique(ls[gs == m], return_counts=True)])),
          dict(zip(*[a.tolist() for a in np.unique(le[ge == m], return_counts=True)])))
for p, e in r.joints:
    print("part", p.part_id if hasattr(p,"part_id") else "", e.type, np.round(e.axis, 3), "conf", round(e.confidence, 3), e.diagnostics.get("warning_codes"))
for st, cloud, g, lab in (("start", r.start_cloud, gs, ls), ("end", r.end_cloud, ge, le)):
    for m in (3, 4):
        sel = g == m
        print(st, "group", m, "segments", dict(zip(*[a.tolist() for a in np.unique(cloud.segment[sel], return_counts=True)])))
    print(st, "segment -> label:", {int(s): dict(zip(*[a.tolist() for a in np.unique(lab[cloud.segment == s], return_counts=True)])) for s in np.unique(cloud.segment)})
print(r.warnings)
d = r.labels.diagnostics if hasattr(r.labels, "diagnostics") else {}
print({k: v for k, v in d.items() if k in ("set_aside", "unassigned", "one_state")})
