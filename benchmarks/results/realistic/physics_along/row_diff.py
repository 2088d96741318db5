import csv, sys, numpy as np
from collections import Counter
def load(p):
    out={}; c=Counter()
    for r in csv.DictReader(open(p)):
        if r['method']!='sparseart': continue
        k=(r['setting'],r['object'],r['name']); out[k+(c[k],)]=r; c[k]+=1
    return out
a=load(sys.argv[1]); b=load(sys.argv[2])
def ax(r): return float(r['axis_deg'] or 90)
stats={}
for k in sorted(b):
    if k not in a: continue
    x=ax(a[k]); y=ax(b[k]); s=stats.setdefault(k[0],[0,0,0,0,0])
    s[0]+=1; s[1]+=x<10; s[2]+=y<10; s[3]+=a[k]['pred_type']==a[k]['gt_type']; s[4]+=b[k]['pred_type']==b[k]['gt_type']
    if abs(x-y)>0.3 or a[k]['pred_type']!=b[k]['pred_type']:
        if '-q' not in sys.argv: print(f"{k[0][:18]:18s} s{k[3]} {k[1][:22]:22s} {k[2]} {a[k]['pred_type'][:4]:4s} {x:7.2f} -> {b[k]['pred_type'][:4]:4s} {y:7.2f}")
for s,v in stats.items(): print(f"{s:20s} n {v[0]} success {v[1]} -> {v[2]}   type {v[3]} -> {v[4]}")
