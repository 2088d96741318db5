import sys, numpy as np, sparseart
from scipy.spatial import cKDTree
from sparseart import RunOptions
from sparseart.io.scene import load_scene
from sparseart.labelers.consistency import state_views, HIDDEN, CONSISTENT, VIOLATION
from sparseart.geometry.clouds import median_spacing
scene = load_scene(sys.argv[1])
r = sparseart.run(scene, options=RunOptions(use_masks=len(sys.argv) > 2, seed=0, second_opinion=False))
s, e, L = r.start_cloud, r.end_cloud, r.labels
sp = median_spacing(s.points, sample=4000, rng=np.random.default_rng(0))
vs, ve = state_views(s, scene, 3 * sp), state_views(e, scene, 3 * sp)
for part, j in r.joints:
    pid = part.spec.id
    T = j.transform
    ps, pe = s.points[L.start_part == pid], e.points[L.end_part == pid]
    for name, src, dst, views, M in (("start->end", ps, pe, ve, T), ("end->start", pe, ps, vs, np.linalg.inv(T))):
        moved = src @ M[:3, :3].T + M[:3, 3]
        d = cKDTree(dst).query(moved)[0]
        hit = d < 4 * sp
        c = views.classify(moved)
        print(pid, name, "n", len(src), "hit %.3f" % hit.mean(),
              {k: (int((c == v).sum()), round(float(hit[c == v].mean()) if (c == v).any() else -1, 3)) for k, v in (("hidden", HIDDEN), ("consistent", CONSISTENT), ("violation", VIOLATION))},
              "conf", round(j.confidence, 3), "mf", round(j.diagnostics["match_fraction"], 3))
