"""cmp_rows.py BEFORE.csv AFTER.csv: rows by order (object, setting, name must agree); lists changes > 1 deg or across 10 deg or type."""
import csv, sys, numpy as np
b = [r for r in csv.DictReader(open(sys.argv[1])) if r['method'] == 'sparseart']
a = [r for r in csv.DictReader(open(sys.argv[2])) if r['method'] == 'sparseart']
def ax(r): return 90.0 if r['unmatched'] in ('True', '1', 'true') or r['axis_deg'] in ('', 'nan') else float(r['axis_deg'])
keys = lambda rows: [(r['object'], r['setting'], r['name']) for r in rows]
if keys(b) != keys(a):
    # align by key occurrence
    from collections import defaultdict
    db = defaultdict(list); [db[(r['object'], r['setting'], r['name'])].append(r) for r in b]
    pairs = []
    seen = defaultdict(int)
    for r in a:
        k = (r['object'], r['setting'], r['name']); i = seen[k]; seen[k] += 1
        if i < len(db[k]): pairs.append((db[k][i], r))
else:
    pairs = list(zip(b, a))
for s in sorted({p[0]['setting'] for p in pairs}):
    P = [p for p in pairs if p[0]['setting'] == s]
    eb = [ax(p[0]) for p in P]; ea = [ax(p[1]) for p in P]
    tb = sum(p[0]['type_correct'] == 'True' for p in P); ta = sum(p[1]['type_correct'] == 'True' for p in P)
    print(f"{s}: n {len(P)} success {sum(e < 10 for e in eb)} -> {sum(e < 10 for e in ea)}, type {tb} -> {ta}, median {np.median(eb):.2f} -> {np.median(ea):.2f}")
for p in pairs:
    x, y = ax(p[0]), ax(p[1])
    if abs(x - y) > 1.0 or (x < 10) != (y < 10) or p[0]['pred_type'] != p[1]['pred_type']:
        print(f"  {p[0]['object'][:24]:24s} {p[0]['setting'][:18]:18s} {p[0]['name']} {x:6.2f} -> {y:6.2f} {p[0]['pred_type']}->{p[1]['pred_type']}")
