"""Grow each moving part by its own motion: the points next to it that the motion carries onto it.

Without masks the parts come from a nearest-point split: a point counts as moved only when the
other state has nothing near it. A surface that slides along itself (a drawer's side panels, a
window pane in its frame) or turns within its own plane near the hinge keeps finding itself and is
called static, so a part keeps a fraction of its points (measured on a robot-shaped drawer: 766 of
its 2757 start points; the fit from those 28-33 deg off, from the true points 1.4-1.8 deg).

This step runs after the labeler has found the parts and their motions. Per movable part with a
motion T (start -> end), for ``rounds`` rounds: a point now static or unassigned, within
``2 r`` of the part's points in its own state, joins the part when

* T (T^-1 for end points) lays it within ``r`` of the part's points in the other state, and
* the two points' colours agree (mean absolute RGB difference < ``colour_gap``): a hand or a
  background wall that the motion happens to carry onto the part does not, and
* staying put does not explain it as well (``identity_excludes``): it does not lie within the
  distance it moved to of a point of the other state that is static, with agreeing colour.

r = ``radius_spacings`` x the clouds' median point spacing (full clouds). Each round is
O(C log P) for C candidates and P part points (k-d trees with a bounded search).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from sparseart.geometry.clouds import median_spacing
from ..types import LabelledCloud, PartLabels


@dataclass(frozen=True)
class GrowthConfig:
    """rounds: growth rounds (each can add a 2 r ring); radius_spacings: r in median spacings;
    colour_gap: largest mean |RGB| difference (colours in [0, 1]) of a point and its landing point;
    identity_excludes: a point that staying put lays on the other state's static points as well
    as the motion lays it on the part stays static."""

    rounds: int = 3
    radius_spacings: float = 3.0
    colour_gap: float = 0.06
    identity_excludes: bool = True
    takes_unassigned: bool = True


def grow_parts(labels: PartLabels, start: LabelledCloud, end: LabelledCloud, config: GrowthConfig,
               rng: np.random.Generator) -> dict[int, list[int]]:
    """Grow ``labels``' movable parts in place (module docstring); returns part id -> [start points
    added, end points added]. start / end: the full clouds the labels index."""
    spacing = max(median_spacing(start.points, sample=4000, rng=rng), median_spacing(end.points, sample=4000, rng=rng))
    radius = config.radius_spacings * spacing
    added: dict[int, list[int]] = {}
    for spec in labels.parts:
        if spec.role != "movable" or spec.id not in labels.initial_motion:
            continue
        motion = labels.initial_motion[spec.id]
        counts = [0, 0]
        for _ in range(config.rounds):
            in_start, in_end = labels.start_part == spec.id, labels.end_part == spec.id
            if in_start.sum() < 10 or in_end.sum() < 10:
                break
            start_tree, end_tree = cKDTree(start.points[in_start]), cKDTree(end.points[in_end])
            new = 0
            for side, (cloud, part, own_tree, other, other_part, other_tree, transform) in enumerate((
                    (start, labels.start_part, start_tree, end, labels.end_part, end_tree, motion),
                    (end, labels.end_part, end_tree, start, labels.start_part, start_tree, np.linalg.inv(motion)))):
                joined = _joiners(cloud, part, own_tree, other, other_part, other_tree, other_part == spec.id,
                                  transform, radius, config)
                part[joined] = spec.id
                counts[side] += len(joined)
                new += len(joined)
            if new == 0:
                break
        added[spec.id] = counts
    return added


def _joiners(cloud: LabelledCloud, part: np.ndarray, own_tree: cKDTree, other: LabelledCloud,
             other_part: np.ndarray, other_tree: cKDTree, other_members: np.ndarray, transform: np.ndarray,
             radius: float, config: GrowthConfig) -> np.ndarray:
    """Rows of ``cloud`` (static or unassigned, near the part) that ``transform`` lays on the
    part's points of the other state with agreeing colour. O(C log P)."""
    candidates = np.flatnonzero(part <= 0 if config.takes_unassigned else part == 0)
    if not len(candidates):
        return candidates
    near = own_tree.query(cloud.points[candidates], distance_upper_bound=2 * radius)[0] < 2 * radius
    candidates = candidates[near]
    if not len(candidates):
        return candidates
    points = cloud.points[candidates]
    moved = points @ transform[:3, :3].T + transform[:3, 3]
    distance, index = other_tree.query(moved, distance_upper_bound=radius)
    hit = distance < radius
    members = np.flatnonzero(other_members)
    colours = cloud.colors[candidates]
    gap = np.full(len(candidates), np.inf)
    gap[hit] = np.abs(colours[hit] - other.colors[members[index[hit]]]).mean(axis=1)
    hit &= gap < config.colour_gap
    if config.identity_excludes and hit.any():
        static = np.flatnonzero(other_part == 0)
        if len(static):
            still, where = cKDTree(other.points[static]).query(points[hit], distance_upper_bound=radius)
            stays = still < radius
            stays[stays] &= np.abs(colours[hit][stays] - other.colors[static[where[stays]]]).mean(axis=1) < config.colour_gap
            stays &= still <= distance[hit]
            hit[np.flatnonzero(hit)[stays]] = False
    return candidates[hit]
