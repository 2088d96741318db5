"""The measurement behind joints/sweep_check.py (stop 53): for every revolute joint of a bench scene,
the blocked-step share of its fitted turn with the static part of BOTH states as obstacles ("both")
and with only the same state's static points ("own", what the labeler's physics reads), at 2 and 4
point spacings. usage: python sweep_measure.py SETTING SCENE_DIR... (rows: measured_*.txt)"""
import json, sys
from pathlib import Path
import numpy as np
from scipy.spatial import cKDTree
from sparseart.bench.grid import grid_settings
from sparseart.bench.evaluate import evaluate
from sparseart.io.scene import load_scene
from sparseart.joints.config import FitConfig
from sparseart.pipeline import RunOptions, run
from sparseart.geometry.sweep import blocked_step_share
from sparseart.geometry.clouds import median_spacing

setting_name = sys.argv[1]
settings, _ = grid_settings(0)
setting = [s for s in settings if s.name == setting_name][0]


def share(transform, direction, points, obstacles_tree, radius):
    def near(p):
        return obstacles_tree.query(p, k=1, distance_upper_bound=radius)[0] < radius
    return blocked_step_share(transform, direction, points, radius, near, surface=obstacles_tree)


for d in sys.argv[2:]:
    scene_dir = Path(d)
    gt = json.loads((scene_dir / "gt.json").read_text())
    seed = int(scene_dir.name.split("_s")[1].split("_")[0]) if "_s" in scene_dir.name else 0
    options = RunOptions(use_masks=setting.use_masks, seed=seed, segmenter=setting.segmenter, matcher=setting.matcher,
                         fit=FitConfig.for_budget(setting.budget))
    scene = load_scene(scene_dir)
    result = run(scene, options=options)
    rows = evaluate(result, scene, gt)
    lab = result.labels
    sc, ec = result.start_cloud, result.end_cloud
    static_ids = [p.id for p in lab.parts if p.role == "static"]
    s_static = sc.points[np.isin(lab.start_part, static_ids)]
    e_static = ec.points[np.isin(lab.end_part, static_ids)]
    spacing = median_spacing(sc.points, sample=5000, rng=np.random.default_rng(0))
    for r in rows:
        part = next((p for p in result.parts if p.spec.id == r.get("part")), None)
        if part is None or part.joint is None or part.joint.type != "revolute":
            continue
        j = part.joint
        ps = sc.points[lab.start_part == part.spec.id]
        pe = ec.points[lab.end_part == part.spec.id]
        ps = ps[:: max(1, len(ps) // 400)]
        pe = pe[:: max(1, len(pe) // 400)]
        out = []
        for mult in (2.0, 4.0):
            radius = mult * spacing
            both = cKDTree(np.concatenate([s_static, e_static]))
            own_s, own_e = cKDTree(s_static), cKDTree(e_static)
            fs_both = share(j.transform, 1.0, ps, both, radius)
            fe_both = share(j.transform, -1.0, pe, both, radius)
            fs_own = share(j.transform, 1.0, ps, own_s, radius)
            fe_own = share(j.transform, -1.0, pe, own_e, radius)
            out.append(f"r{mult:g}: both {fs_both:.2f}/{fe_both:.2f} own {fs_own:.2f}/{fe_own:.2f}")
        gst = r.get("gt_state")
        right = r["axis_deg"] < 10 and r["state"] < 20
        print(f"{setting_name:18s} {scene_dir.name[:20]:20s} s{seed} {r['name']:8s} {'RIGHT' if right else 'WRONG'} axis {r['axis_deg']:5.1f} state {r['state']:6.1f} conf {j.confidence:.2f} | " + " | ".join(out), flush=True)
