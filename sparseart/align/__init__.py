"""Registration of unposed scenes: views of one state to each other, then the end state to the start
state. Features (SIFT, learned matchers) lifted to 3D, robust Sim(3)/SE(3) RANSAC, geometric
fallbacks, and the static-part polish."""
