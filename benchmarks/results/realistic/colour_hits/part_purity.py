"""part_purity.py OUT.json: what the predicted movable parts are made of, by true mask group.

For every robot-shaped scene linked as S/<object>_r<seed> (robot-1view) or S/<object>_s<seed>
(robot-sensor-1view) -- links to the bench's cached scene folders -- run without masks with the
bench's seed and count, per state, the movable parts' points whose true group is background
(0: room, table, arm) and those on a true moving part. Writes the rows and prints the totals.
Run from the folder holding S/ with PYTHONPATH set to the code under test."""
import sys, os, json, glob, numpy as np, sparseart
from pathlib import Path
from sparseart import RunOptions
from sparseart.io.scene import load_scene
from sparseart.bench.evaluate import true_groups
rows = []
for name in sorted(glob.glob("S/*_[rs][0-3]")):
    seed = int(name[-1]); scene = load_scene(name); gt = json.loads((Path(name) / "gt.json").read_text())
    r = sparseart.run(scene, options=RunOptions(use_masks=False, seed=seed))
    parts = {j["mask_id"] for j in gt["joints"]}
    for st, cloud, lab in (("start", r.start_cloud, r.labels.start_part), ("end", r.end_cloud, r.labels.end_part)):
        g = true_groups(cloud, scene, gt)
        movable = np.isin(lab, [p.id for p in r.labels.parts if p.role == "movable"])
        rows.append((name, st, int(np.sum(movable & (g == 0))), int(np.sum(movable & np.isin(g, list(parts)))), int(np.sum(movable))))
json.dump(rows, open(sys.argv[1], "w"))
bg = sum(r[2] for r in rows); part = sum(r[3] for r in rows); tot = sum(r[4] for r in rows)
print(f"background {bg} part {part} all {tot} background share {bg / max(tot, 1):.3f}")
