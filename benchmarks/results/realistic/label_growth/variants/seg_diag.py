import sys, glob, numpy as np
from sparseart.io.scene import load_scene
import sparseart.labelers.rules as rules
orig = rules._merge_across_frames
def spy(cloud, segments, radius, config, rng, named=frozenset()):
    groups = orig(cloud, segments, radius, config, rng, named)
    ids, counts = np.unique(segments[segments >= 0], return_counts=True)
    kept = {s for g in groups for s in g.segments}
    print(cloud.state, "work points", len(cloud), "floor", max(config.min_segment_points, config.min_segment_share * len(cloud)),
          "dropped:", {int(i): int(c) for i, c in zip(ids, counts) if int(i) not in kept},
          "groups:", [(g.segments, len(g.indices)) for g in groups])
    return groups
rules._merge_across_frames = spy
import sparseart
from sparseart import RunOptions
sparseart.run(load_scene(glob.glob(sys.argv[1])[0]), options=RunOptions(seed=0, second_opinion=False))
