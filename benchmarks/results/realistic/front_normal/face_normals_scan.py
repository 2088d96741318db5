import sys, json, numpy as np, sparseart, glob
from pathlib import Path
from scipy.spatial import cKDTree
from sparseart import RunOptions
from sparseart.io.scene import load_scene
from sparseart.bench.evaluate import true_groups, _result_to_gt_frame
from sparseart.geometry.planes import ransac_plane
from sparseart.geometry.clouds import median_spacing
from sparseart.geometry.transforms import axis_angle_deg
from sparseart.joints.reliability import covered_fraction
name = glob.glob(sys.argv[1])[0]
scene = load_scene(name); gt = json.loads((Path(name) / "gt.json").read_text())
r = sparseart.run(scene, options=RunOptions(seed=0, use_masks=sys.argv[2] == "masks"))
tag = sys.argv[3] if len(sys.argv) > 3 else ""
T = _result_to_gt_frame(r, gt); Ti = np.linalg.inv(T)
gs = true_groups(r.start_cloud, scene, gt)
L = r.labels
rng = np.random.default_rng(0)
def sub(p, n=3000):
    return p[rng.choice(len(p), min(n, len(p)), replace=False)]
for part, jj in r.joints:
    ids,c=np.unique(gs[L.start_part==part.spec.id],return_counts=True); m=ids[np.argmax(c)]
    g=[g for g in gt["joints"] if g["mask_id"]==m]
    if not g or (g[0]["type"] != "prismatic" and jj.type != "prismatic"): continue
    g=g[0]; a=Ti[:3,:3]@np.array(g["axis"])
    sp=r.start_cloud.points[L.start_part==part.spec.id]; ep=r.end_cloud.points[L.end_part==part.spec.id]
    S, E = sub(sp), sub(ep)
    spacing = max(median_spacing(sp, sample=2000, rng=rng), median_spacing(ep, sample=2000, rng=rng))
    tau = 3 * spacing
    tree = cKDTree(E)
    shift = jj.transform[:3, 3] if jj.type == "prismatic" else (jj.transform[:3,:3] @ sp.mean(0) + jj.transform[:3,3] - sp.mean(0))
    free_cov = covered_fraction(S, E, tree, jj.transform[:3,:3], jj.transform[:3,3], tau)
    out = [f"{tag:10s} {Path(name).name[:24]:24s} {g['type'][:3]} {g['name']} {jj.type[:3]} err {axis_angle_deg(jj.axis,a):6.2f} freecov {free_cov:.3f}"]
    ns = []
    for nm, pts in (("S", sp), ("E", ep)):
        pl = ransac_plane(pts, 4 * spacing, np.random.default_rng(0))
        n = pl[0]; inl = np.mean(np.abs((pts - pl[1]) @ n) < 4 * spacing)
        n = n if n @ jj.axis >= 0 else -n
        ns.append(n)
        out.append(f"| {nm} inl {inl:.2f} nerr {axis_angle_deg(n,a):6.2f}")
    mn = ns[0] + ns[1]; mn /= np.linalg.norm(mn)
    out.append(f"| mean nerr {axis_angle_deg(mn,a):6.2f} free-to-n {axis_angle_deg(mn, jj.axis):6.2f} S-E {axis_angle_deg(ns[0], ns[1]):5.2f} sigma {jj.uncertainty.get('axis_deg', -1):5.2f}")
    print(" ".join(out), flush=True)
