"""Prototype: complete part labels by the part's motion (post-labeler)."""
import os, numpy as np
from scipy.spatial import cKDTree
import sparseart.labelers.rules as rules
from sparseart.geometry.clouds import median_spacing

VARIANT = os.environ.get("COMPLETE", "")
def apply(T, p): return p @ T[:3, :3].T + T[:3, 3]

def complete(labels, start, end, rounds=3, factor=3.0):
    rng = np.random.default_rng(0)
    sp = max(median_spacing(start.points, sample=4000, rng=rng), median_spacing(end.points, sample=4000, rng=rng))
    r = factor * sp
    for spec in labels.parts:
        if spec.role != "movable" or spec.id not in labels.initial_motion: continue
        T = labels.initial_motion[spec.id]; Ti = np.linalg.inv(T)
        added = [0, 0]
        for _ in range(rounds):
            ms = labels.start_part == spec.id; me = labels.end_part == spec.id
            if ms.sum() < 10 or me.sum() < 10: break
            ts, te = cKDTree(start.points[ms]), cKDTree(end.points[me])
            new = 0
            for pts, lab, own_tree, other_tree, other_static, M, k in (
                    (start.points, labels.start_part, ts, te, end.points[labels.end_part == 0], T, 0),
                    (end.points, labels.end_part, te, ts, start.points[labels.start_part == 0], Ti, 1)):
                cand = np.flatnonzero((lab == 0) | (lab == -1))
                if not len(cand): continue
                near = own_tree.query(pts[cand], distance_upper_bound=2 * r)[0] < 2 * r
                cand = cand[near]
                if not len(cand): continue
                dist, idx = other_tree.query(apply(M, pts[cand]), distance_upper_bound=r)
                hit = dist < r
                if "C" in VARIANT:
                    own_cols = (start.colors if k == 0 else end.colors)[cand]
                    other_cols = (end.colors[me] if k == 0 else start.colors[ms])
                    gap = np.full(len(cand), np.inf)
                    gap[hit] = np.abs(own_cols[hit] - other_cols[idx[hit]]).mean(axis=1)
                    hit &= gap < float(os.environ.get("CGAP", "0.06"))
                if "A" in VARIANT and len(other_static):
                    st = cKDTree(other_static).query(pts[cand], distance_upper_bound=r)[0] < r
                    hit &= ~st
                lab[cand[hit]] = spec.id
                added[k] += int(hit.sum()); new += int(hit.sum())
            if new == 0: break
        if os.environ.get("DBG_COMPLETE"):
            print(f"complete part {spec.id}: +{added[0]} start, +{added[1]} end (r={r:.4f})")
    return labels

orig = rules.RuleBasedLabeler.label
def label(self, start, end, *a, **kw):
    labels = orig(self, start, end, *a, **kw)
    return complete(labels, start, end) if VARIANT else labels
rules.RuleBasedLabeler.label = label
