import json, sys, numpy as np
from scipy.stats import mannwhitneyu
old = [r for r in json.load(open('rows_before.json')) if r['method'] == 'sparseart']
new = [r for r in json.load(open('rows_after.json')) if r['method'] == 'sparseart']
assert len(old) == len(new)
same = 0
for a, b in zip(old, new):
    assert (a['object'], a['setting'], a['name']) == (b['object'], b['setting'], b['name'])
    same += (a['axis_deg'] == b['axis_deg'] and a['pred_type'] == b['pred_type'] and a.get('axis_sigma_deg') == b.get('axis_sigma_deg'))
print(f"rows {len(old)}, identical axis/type/sigma {same}")
def auroc(rows, key):
    rows = [r for r in rows if not r['unmatched'] and r.get('confidence') is not None]
    right = np.array([r['confidence'] for r in rows if r['axis_deg'] < 10]); wrong = np.array([r['confidence'] for r in rows if r['axis_deg'] >= 10])
    a = mannwhitneyu(right, wrong).statistic / (len(right) * len(wrong)) if len(right) and len(wrong) else float('nan')
    return len(right), np.median(right) if len(right) else np.nan, len(wrong), np.median(wrong) if len(wrong) else np.nan, a
print("| setting (seeds 0-1) | right: n, median conf old -> new | wrong: n, median old -> new | AUROC old -> new |")
print("|---|---|---|---|")
settings = sorted({r['setting'] for r in old})
for s in settings + ['ALL']:
    o = [r for r in old if s in ('ALL', r['setting'])]; n = [r for r in new if s in ('ALL', r['setting'])]
    a, b = auroc(o, 'c'), auroc(n, 'c')
    print(f"| {s} | {a[0]}, {a[1]:.3f} -> {b[1]:.3f} | {a[2]}, {a[3]:.3f} -> {b[3]:.3f} | {a[4]:.3f} -> {b[4]:.3f} |")
