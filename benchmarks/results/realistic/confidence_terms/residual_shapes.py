"""Confidence with other shapes of its residual term, recomputed from bench rows that carry the
confidence's terms (covered_fraction, residual_excess): new = confidence / f_now(excess) * f(excess).
Usage: python residual_shapes.py ROWS.json [ROWS.json ...]; prints AUROC (right = axis < 10 deg) and
the right / wrong joints' median confidence per setting, for each shape."""
import json, sys, numpy as np
from scipy.stats import mannwhitneyu
rows = []
for p in sys.argv[1:]:
    rows += [r for r in json.load(open(p)) if r['method'] == 'sparseart' and not r['unmatched'] and r.get('confidence') is not None and r.get('residual_excess') is not None]
C = 0.1
shapes = {
  'cauchy2 (now)': lambda x: 1 / (1 + (x / C) ** 2),
  'order4': lambda x: 1 / (1 + (x / C) ** 4),
  'order3': lambda x: 1 / (1 + (x / C) ** 3),
  'dead0.03': lambda x: 1 / (1 + (np.maximum(x - 0.03, 0) / C) ** 2),
  'gauss': lambda x: np.exp(-0.5 * (x / C) ** 2 * 2 * np.log(2) * 2),
  'none': lambda x: np.ones_like(x),
}
def auroc(right, wrong):
    return mannwhitneyu(right, wrong).statistic / (len(right) * len(wrong)) if len(right) and len(wrong) else float('nan')
settings = sorted({r['setting'] for r in rows}) + ['ALL']
print('real laptop x=0.0254 covered 0.982:', {k: round(0.982 * f(np.array(0.0254)), 3) for k, f in shapes.items()})
for name, f in shapes.items():
    out = []
    for s in settings:
        ch = [r for r in rows if s in ('ALL', r['setting'])]
        x = np.array([r['residual_excess'] for r in ch]); c = np.array([r['confidence'] for r in ch])
        new = c / shapes['cauchy2 (now)'](x) * f(x)
        ok = np.array([r['axis_deg'] < 10 for r in ch])
        out.append(f"{s[:12]} {auroc(new[ok], new[~ok]):.3f} ({np.median(new[ok]):.2f}/{np.median(new[~ok]) if (~ok).any() else float('nan'):.2f})")
    print(f"{name:14s}", ' | '.join(out))
ok = np.array([r['axis_deg'] < 10 for r in rows]); x = np.array([r['residual_excess'] for r in rows])
print('excess quantiles right', np.round(np.quantile(x[ok], [.1, .25, .5, .75, .9, .95]), 4), 'wrong', np.round(np.quantile(x[~ok], [.1, .25, .5, .75, .9]), 4))
for s in settings[:-1]:
    ch = np.array([r['setting'] == s for r in rows])
    print(s, 'right n', (ok & ch).sum(), 'excess median', np.round(np.median(x[ok & ch]), 4), 'wrong n', (~ok & ch).sum(), np.round(np.median(x[~ok & ch]), 4) if (~ok & ch).any() else '-')
