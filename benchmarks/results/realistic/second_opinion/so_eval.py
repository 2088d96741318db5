"""Second opinion: per joint error, confidence and sigma with and without it."""
import sys, json, glob, numpy as np, sparseart
from sparseart.io.scene import load_scene
from sparseart.bench.evaluate import evaluate
out=open(sys.argv[1],'w')
for pat in sys.argv[2:]:
    for d in sorted(glob.glob(pat)):
        scene=load_scene(d); gt=json.load(open(d+'/gt.json'))
        res={}
        for so in (False, True):
            r=sparseart.run(d, use_masks=False, second_opinion=so)
            rows=evaluate(r, scene, gt); joints={p.spec.id: p.joint for p in r.parts if p.joint is not None}
            res[so]=[(row['name'], row['axis_deg'], joints[row['part']].confidence if row.get('part') in joints else None,
                      joints[row['part']].uncertainty['axis_deg'] if row.get('part') in joints else None) for row in rows]
            res[str(so)+'s']=sum(s.seconds for s in r.stages if s.ran)
        for a,b in zip(res[False],res[True]):
            out.write(json.dumps({'scene':d.split('/')[-1][:60],'joint':a[0],'err':a[1],'err2':b[1],'conf0':a[2],'conf1':b[2],'sig0':a[3],'sig1':b[3],'sec0':res['Falses'],'sec1':res['Trues']})+'\n'); out.flush()
