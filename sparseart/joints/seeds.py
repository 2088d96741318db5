"""Seed motions of a fit: the initial rigid motion (given, or registered), and cheap screening of
several seeds on the screening sample before any full fit.

``initial_motion`` turns a caller's (4, 4) start -> end guess into normalised units, or registers
the two states (``geometry.icp.register_rigid``, O(W log W)) when there is none.
``screen_seeds`` scores seed motions of one part for the candidate search: each seed's joint
model(s) run the coarse alternation on the part's screening sample (``FitConfig.screen_points``
per side, the same sample the full fit starts with) and are scored by a truncated symmetric
Chamfer RMS on that sample -- comparable across seeds and types, so a seed scoring far above the
best can be dropped before its full fit. O(seeds x types x coarse alternation) ~ a few ms per
seed and type at 400 points.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from sparseart.geometry.icp import register_rigid
from sparseart.joints.config import FitConfig
from sparseart.joints.models import Model, initial_models
from sparseart.joints.optimise import alternate
from sparseart.joints.part import PartData, Sample, prepare_part

SCREEN_CLIP = 4.0  # Chamfer distances are truncated at this many screening-sample spacings


def initial_motion(part: PartData, initial_transform: np.ndarray | None, start_colors: np.ndarray | None,
                   end_colors: np.ndarray | None, config: FitConfig) -> tuple[np.ndarray, dict]:
    """Normalised (4, 4) start -> end motion and its diagnostics ({"initial", and after a
    registration "registration_inlier_fraction"}). Colours (input rows) help the registration only."""
    if initial_transform is not None:
        return part.normalise(initial_transform), {"initial": "given"}
    start_colors = None if start_colors is None else np.asarray(start_colors, dtype=np.float64)[part.start_rows]
    end_colors = None if end_colors is None else np.asarray(end_colors, dtype=np.float64)[part.end_rows]
    registration = register_rigid(part.start, part.end, start_colors, end_colors, seed=config.seed)
    return registration.transform, {"initial": f"register_rigid ({registration.diagnostics['chosen']})",
                                    "registration_inlier_fraction": registration.inlier_fraction}


def screen_score(model: Model, sample: Sample) -> float:
    """Truncated symmetric Chamfer RMS of ``sample`` under the model's reference motion
    (normalised units; distances clipped at ``SCREEN_CLIP`` spacings). O(s log s)."""
    rotation, translation = model.motion(model.x0)
    moved = sample.start @ rotation.T + translation
    clip = SCREEN_CLIP * max(sample.spacing, 1e-12)
    forward = np.minimum(sample.end_tree.query(moved)[0], clip)
    backward = np.minimum(cKDTree(moved).query(sample.end)[0], clip)
    return float(np.sqrt((np.sum(forward ** 2) + np.sum(backward ** 2)) / (forward.size + backward.size)))


@dataclass(frozen=True)
class SeedScreen:
    """Screening of one seed and joint type: ``score`` (input units, lower is better; comparable
    across the seeds and types of one part and config), ``seed_index`` into the given seeds, and
    the coarse motion (4, 4, input units) the full fit would start from."""

    seed_index: int
    joint_type: str
    score: float
    transform: np.ndarray


def screen_seeds(start_points: np.ndarray, end_points: np.ndarray, seeds: list[np.ndarray | None],
                 joint_type: str = "auto", config: FitConfig | None = None,
                 start_colors: np.ndarray | None = None, end_colors: np.ndarray | None = None) -> list[SeedScreen]:
    """Score every seed motion of one part (see the module docstring), best first.

    start_points (N, 3) / end_points (M, 3): the part in both states (same arrays as for
    ``fit_joint``: the prepared part is shared through its cache). seeds: (4, 4) start -> end
    guesses (None: registered). joint_type: "auto" scores both types per seed.
    """
    config = config or FitConfig()
    part = prepare_part(start_points, end_points, config)
    kinds = ("revolute", "prismatic") if joint_type == "auto" else (joint_type,)
    screens = []
    for index, seed in enumerate(seeds):
        initial, _ = initial_motion(part, seed, start_colors, end_colors, config)
        revolute, prismatic, _ = initial_models(initial, part.start)
        for kind in kinds:
            model = alternate(revolute if kind == "revolute" else prismatic, part.screen, config).model
            rotation, translation = model.motion(model.x0)
            transform = np.eye(4)
            transform[:3, :3] = rotation
            transform[:3, 3] = part.scale * translation + part.centre - rotation @ part.centre
            screens.append(SeedScreen(index, kind, screen_score(model, part.screen) * part.scale, transform))
    return sorted(screens, key=lambda s: s.score)
