import json, sys
def auc(pos, neg):
    if not pos or not neg: return float('nan')
    s = sum((p > n) + 0.5 * (p == n) for p in pos for n in neg)
    return s / (len(pos) * len(neg))
"""AUROC of the joint confidence, right (axis < 10 deg) against wrong found joints, per bench rows.json:
    python confidence_auc.py RUN/rows.json [...]"""
for f in sys.argv[1:]:
    rows = [r for r in json.load(open(f)) if not r.get('unmatched') and r.get('confidence') is not None]
    right = [r['confidence'] for r in rows if r['axis_deg'] < 10]
    wrong = [r['confidence'] for r in rows if r['axis_deg'] >= 10]
    import numpy as np
    print(f"{f}: found {len(rows)} right {len(right)} wrong {len(wrong)} AUC {auc(right, wrong):.3f} median conf right {np.median(right):.2f} wrong {np.median(wrong):.2f}; right <0.3: {sum(c<0.3 for c in right)}, wrong <0.3: {sum(c<0.3 for c in wrong)}")
