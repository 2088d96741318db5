"""Registration of unposed scenes: views of one state to each other, then the end state to the start
state, then (after labelling) a polish on the static part.

    features.py   SIFT/RootSIFT keypoints and matches lifted to 3D (FeatureMatches)
    matchers.py   learned matchers (XFeat + LighterGlue, XFeat MNN, LightGlue pipeline) behind one interface
    lightglue.py  the end-to-end LightGlue-ONNX pipeline export
    ransac.py     robust Sim(3)/SE(3) from 3D matches (RANSAC + Umeyama), per-match thresholds
    noise.py      inlier thresholds that grow with depth and adapt to the noise; depth roughness
    graph.py      register_scene(): every view of both states at once (all pairs matched, pooled
                  merges checked against free space, joint robust solve with per-view depth scale,
                  checked state alignment, motion candidates, per-view report)
    geometric.py  featureless fallback for views (FPFH/PCA + ICP, free-space check)
    views.py      views of one state -> its first view (standalone; the pipeline uses graph.py)
    states.py     end state -> start state, plus candidate part motions (per-state reconstructions)
    static.py     ICP of the labelled static part (polish, or registration when features failed)
    scene.py      align_scene(): what the pipeline calls after the lift; registration_report()
"""
from sparseart.align.ransac import AlignmentError, Similarity, ransac_similarity, umeyama
from sparseart.align.graph import SceneRegistration, register_scene
from sparseart.align.scene import AlignedScene, align_scene, registration_report
from sparseart.align.states import MotionCandidate, StateAlignment, align_states
from sparseart.align.views import register_views
from sparseart.align.features import FeatureMatches, match_features
from sparseart.geometry.clouds import transform_pointmap

__all__ = ["AlignedScene", "AlignmentError", "FeatureMatches", "MotionCandidate", "SceneRegistration", "Similarity",
           "StateAlignment", "align_scene", "align_states", "match_features", "ransac_similarity", "register_scene",
           "register_views", "registration_report", "transform_pointmap", "umeyama"]
