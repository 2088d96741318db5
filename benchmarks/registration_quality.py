"""Registration alone (lift + align_scene, no labeling or fit) on cached unposed renders: per scene the
alignment ("features" | "none"), how each view was placed (reference | features | geometry |
unregistered) and the worst view rotation error against the rendering cameras (gt.json); then the
share of views registered and of scenes whose states were aligned by features.

    python3 benchmarks/registration_quality.py "OUT/scenes/*_unposed_*_r*" [sift | MATCHER_SPEC]

MATCHER_SPEC as for ``sparseart run --matcher`` (e.g. xfeat:../shared/models/xfeat.onnx,
../shared/models/lighterglue_L3.onnx). Scenes: render them with ``sparseart bench --settings
realistic`` (cached in OUT/scenes). Results of 2026-11-24: experiment EXP-014.
"""
import sys, json, glob, time, numpy as np
from sparseart.io.scene import load_scene
from sparseart.lift.scene_lift import lift_scene
from sparseart.align.scene import align_scene
pattern, spec = sys.argv[1], (sys.argv[2] if len(sys.argv) > 2 and sys.argv[2] != "sift" else None)
matcher = None
if spec:
    from sparseart.align.matchers import LiftedMatcher, open_matcher
    matcher = LiftedMatcher(open_matcher(spec, threads=2))
def ang(R): return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
tot_v = reg_v = good_v = scenes = feat = 0; secs = []
for d in sorted(glob.glob(pattern)):
    scene = load_scene(d); gt = json.load(open(d + "/gt.json"))
    t = time.time(); a = align_scene(scene, lift_scene(scene), seed=0, matcher=matcher); secs.append(time.time() - t)
    rep = a.registration; scenes += 1
    feat += a.alignment == "features"
    ref = np.asarray(gt["cameras"]["start"][0]); errs = []
    for state in ("start", "end"):
        if not a.poses: break
        for pose, c2w in zip(a.poses[state], gt["cameras"][state]):
            tot_v += 1
            if pose is None: continue
            reg_v += 1
            if state == "end" and a.alignment != "features":
                continue
            true = np.linalg.inv(ref) @ np.asarray(c2w); s = np.cbrt(np.linalg.det(pose[:3, :3]))
            e = ang((pose[:3, :3] / s).T @ true[:3, :3]); errs.append(e); good_v += e < 2.0
    print(d.split("/")[-1][:30], a.alignment, [v["how"][:4] for v in rep.get("views", [])], "maxrot %.2f" % max(errs or [np.nan]), "%.1fs" % secs[-1], flush=True)
print(f"SUMMARY views registered {reg_v}/{tot_v}, states by features {feat}/{scenes}, median s {np.median(secs):.1f}")
