import json, sys, numpy as np
rows=[json.loads(l) for l in open(sys.argv[1])]
def auroc(scores, labels):
    s=np.array(scores); y=np.array(labels)
    pos=s[y]; neg=s[~y]
    if len(pos)==0 or len(neg)==0: return float('nan')
    return float(np.mean([(p>n)+0.5*(p==n) for p in pos for n in neg]))
found=[r for r in rows if r['conf0'] is not None]
succ=[r['err']<10 for r in found]
assert all(abs(r['err']-r['err2'])<1e-9 for r in rows), 'errors changed'
print(sys.argv[1], 'joints', len(rows), 'found', len(found), 'success', sum(r['err']<10 for r in rows))
print(' AUROC conf (success vs failure among found): before %.2f after %.2f'%(auroc([r['conf0'] for r in found],succ), auroc([r['conf1'] for r in found],succ)))
fl=[r['conf1']<r['conf0']-1e-12 for r in found]
print(' flagged: successes %d/%d, failures %d/%d'%(sum(f and s for f,s in zip(fl,succ)), sum(succ), sum(f and not s for f,s in zip(fl,succ)), sum(not s for s in succ)))
for k in ('sig0','sig1'):
    cov=np.mean([r['err']<=r[k] for r in found]); cov2=np.mean([r['err']<=2*r[k] for r in found])
    print(f' {k}: 1-sigma covers {cov:.2f} of found joints, 2-sigma {cov2:.2f}')
print(' mean conf success before %.2f after %.2f; failure before %.2f after %.2f'%(np.mean([r['conf0'] for r,s in zip(found,succ) if s]), np.mean([r['conf1'] for r,s in zip(found,succ) if s]), np.mean([r['conf0'] for r,s in zip(found,succ) if not s]), np.mean([r['conf1'] for r,s in zip(found,succ) if not s])))
secs={}
for r in rows: secs[r['scene']]=(r['sec0'],r['sec1'])
a=np.array(list(secs.values())); print(' median seconds per scene: without %.2f with %.2f'%tuple(np.median(a,axis=0)))
