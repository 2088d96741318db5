"""The realism knobs' level-1 strengths and their table (what each does, how strong at level 1):
plain data, so that the command line can list the knobs without loading the renderer. Applied
by :mod:`sparseart.datasets.realism`."""
from __future__ import annotations

MAX_LEVEL = 5.0

# ---- level-1 strengths (documented in KNOB_TABLE) -------------------------------------------------
DEPTH_WARP_AMPLITUDE = 0.02      # max |warp - 1| of the multiplicative low-frequency warp
DEPTH_SCALE_SIGMA = 0.01         # sigma of the per-view global depth scale error (clipped at 3 sigma)
EDGE_SMEAR_PX = 2.0              # pixels on each side of a depth discontinuity that get mixed depths
DEPTH_NOISE_SIGMA = 0.005        # multiplicative per-pixel sigma at the reference depth, head-on
HOLES_PER_VIEW = 6.0             # Poisson mean of elliptic holes (depth 0) per view
HOLE_RADIUS = (0.01, 0.04)       # hole semi-axes, fraction of min(H, W)
GRAZING_DROPOUT_COS = 0.15       # pixels seen at cos(incidence) below this drop out with p = 0.5 * level
IMAGE_NOISE_SIGMA = 4.0          # Gaussian sigma in 8-bit grey levels
JPEG_QUALITY_SLOPE = 30.0        # quality = 100 - 30 * level, clipped to [5, 95] (70 at level 1)
MASK_RAGGED_PX = 1.0             # sigma (px) of the random displacement that frays mask borders
MASK_RAGGED_MAX_PX = 2.5         # |displacement| per axis is clipped to this (px) times the level
MASK_MERGE_P = 0.1               # per-view probability that two ids are merged into one
MASK_SPLIT_P = 0.1               # per-view probability that one id is split in two by a line
POSE_NOISE_DEG = 0.5             # rotation error of each written cam_to_world (degrees, exact)
POSE_NOISE_TRANSLATION = 0.005   # translation error (object units = metres for metric objects, exact)
HAND_FRACTION = 0.45             # hand length (wrist to fingertip) / diagonal of the grasped part
HAND_CLAMP = (0.08, 0.3)         # ... clipped to these fractions of the object's diagonal
CONF_JITTER = 0.05               # log-normal sigma of the per-pixel jitter of the confidence

# ---- reserved raw labels (mapped to 0 in the written masks) --------------------------------------
RESERVED_LABEL_MIN = 65000
TABLE_LABEL, FLOOR_LABEL, WALL_LABEL = 65001, 65002, 65003
OCCLUDER_LABEL = 65100
EDGE_RELATIVE_JUMP = 0.03        # a 3x3 depth range above this fraction of the depth is a discontinuity
EMPTY_BACKGROUND_GAP = 0.25      # an empty (0) pixel stands for a background this much farther

KNOB_TABLE: dict[str, tuple[str, str]] = {
    "background": (("table top under the object (its footprint + 12 %, wood texture), a tiled floor and "
                    "a painted wall behind it, raycast with the object; mask label 0"),
                   "all three surfaces, texture contrast x level"),
    "depth_warp": (("smooth multiplicative depth warp per view: a random sum of 2D cosines of at most one "
                    "cycle per image"), f"max |warp - 1| = U(0.5, 1) x {DEPTH_WARP_AMPLITUDE:.0%}"),
    "depth_scale": ("global depth scale error per view", f"scale 1 + N(0, {DEPTH_SCALE_SIGMA:.0%})"),
    "edge_smear": (("flying pixels: depths within a band around each depth discontinuity blurred "
                    "between the near and far sides (empty pixels beside the object become valid)"),
                   f"band {EDGE_SMEAR_PX:g} px"),
    "depth_noise": (("per-pixel multiplicative noise growing with depth and grazing angle, elliptic "
                     "holes (depth 0) and grazing-angle dropout"),
                    (f"sigma {DEPTH_NOISE_SIGMA:.1%} at the object's median depth head-on; "
                     f"Poisson({HOLES_PER_VIEW:g}) holes")),
    "confidence": (("write {start,end}/conf/NNN.npy: float32 in [0, 1], low at depth edges, around holes, "
                    "where the warp is large, at grazing angles and far away; 0 where depth is 0"),
                   "conf = raw ** level"),
    "occluder": (("a hand (palm, 4 fingers, thumb) + forearm in a sleeve coming from outside the image, "
                  "resting on a moving part in the END state only; mask label 0"),
                 f"hand length {HAND_FRACTION:g} x part diagonal (x level)"),
    "image_noise": ("Gaussian noise on the 8-bit RGB", f"sigma {IMAGE_NOISE_SIGMA:g} grey levels"),
    "jpeg": ("JPEG round trip (cv2.imencode) before the PNG is written", "quality 70 (100 - 30 x level)"),
    "mask_ragged": (("mask borders frayed by a random displacement field; occasional merge of two ids "
                     "and split of one id by a line"),
                    (f"sigma {MASK_RAGGED_PX:g} px (max {MASK_RAGGED_MAX_PX:g}); merge / split p = "
                     f"{MASK_MERGE_P:g} / {MASK_SPLIT_P:g} per view")),
    "pose_noise": (("error of the cam_to_world written to cameras.json (posed scenes; gt.json keeps the "
                    "truth): rotation about a random axis + translation in a random direction"),
                   f"{POSE_NOISE_DEG:g} deg + {POSE_NOISE_TRANSLATION:g} object units (exact)"),
}
