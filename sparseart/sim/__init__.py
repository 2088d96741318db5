"""Simulation-ready objects: a fused surface per part (:mod:`.surfaces`), collision pieces and mass
(:mod:`.physics`), the one link/joint description every export is written from (:mod:`.model`),
and the simulator replays that check an export moves as the images showed (:mod:`.replay`).

Nothing here is imported by ``sparseart run`` unless ``--urdf``, ``--mjcf`` or ``--usd`` is given.
"""
