"""The static-part step of alignment, after labelling: the end cloud moved onto the start cloud by a
robust ICP of the labelled static part (part 0).

``polish_on_static`` refines an alignment that features or a reconstructor already gave (ICP from
identity); ``align_on_static`` registers states that were never aligned, seeded by the labeler's
static motion. Both return the moved end cloud and append warnings; ``polish_on_static`` also
returns the labels with their start -> end motions carried into the polished frame (the
unaligned labelling that seeds ``align_on_static`` is done again afterwards, so its labels are not
carried).

With mask ids that name parts in both states, ``align_on_static`` lets them vouch for the
registration as the geometric view fallback does (:mod:`sparseart.align.geometric`): a box-like
static part turned a quarter round fits itself well but lays the other parts' ids onto its walls.
When fewer than ``LABEL_AGREEMENT`` of the overlapping labelled points agree, the static part is
registered again from the turns of :func:`~sparseart.align.geometric.turns`, ranked by static
overlap x id agreement, and that fit is kept when its score beats the first one's by
``STATE_SEARCH_MARGIN``. Unlike two views of one state, the states do not agree fully even at the
true pose (a part that moved lands on the body), so the score is compared, not held to
``LABEL_AGREEMENT``.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from sparseart.align.geometric import LABEL_AGREEMENT, id_agreement, upright_starts
from sparseart.geometry.clouds import normals_with_variation, rms_radius, scene_size
from sparseart.geometry.icp import register_rigid
from sparseart.geometry.sampling import random_subset
from sparseart.geometry.transforms import apply_transform, make_transform, rotation_angle
from sparseart.types import LabelledCloud, PartLabels

MIN_STATIC_POINTS = 20
POLISH_WARN_DEG = 3.0       # an ICP polish larger than this means the feature alignment was off
MIN_STATIC_AGREEMENT = 0.5  # share of static points that must agree after the ICP
STATE_SEARCH_MARGIN = 0.05  # static overlap x mask-id agreement a searched registration must gain
# Static points per state the polish works on (a random subsample above it; all of them below). On
# 2000 (register_rigid's default) the static surfaces of an unposed realistic dishwasher left a flat
# valley whose bottom moved with the subsample: basket slides of 0.404-0.500 over four seeds (true
# 0.484, stated sigma 0.009); on 20000, 0.469-0.478. Realistic s0-3: slides within 10 % of their
# travel 22 -> 25 of 34, full success 75 -> 79 %; +0.23 s per unposed scene (median).
POLISH_POINTS = 20000
# A turn of the polish about a direction whose point-to-plane information is below this share of
# the best-constrained direction's is left as the feature alignment had it (rough depth only;
# :func:`constrained_rotation`). Measured weakest shares: a strip-like stapler base 0.014-0.027
# (the turns that hurt), a faucet's round base 0.06-0.10 (helped), boxes and cabinets 0.16-0.88.
WEAK_TURN_SHARE = 0.05
TURN_NORMAL_NEIGHBOURS = 20


def polish_on_static(start: LabelledCloud, end: LabelledCloud, labels: PartLabels, warnings: list[str],
                     seed: int = 0, rough_depth: bool = False) -> tuple[LabelledCloud, PartLabels]:
    """Refine a feature/model alignment: robust ICP of the end static points onto the start static
    points from identity; the end cloud moves by the result, and so do the labeler's start -> end
    motions (:func:`carried`). Returns (end cloud, labels), both unchanged when the polish is not
    kept. ``rough_depth`` (a sensor's or reconstructor's depth, :data:`~sparseart.align.noise.MAX_CLEAN_ROUGHNESS`):
    keep only the polish's turn, and of it only what the static surfaces constrain
    (:func:`constrained_rotation`, :func:`turn_about_centroid`). O(I N log N) for I ICP iterations over
    N static points."""
    pair = _static_points(start, end, labels)
    if pair is None:
        warnings.append("static part too small to polish the alignment of the states")
        return end, labels
    registration = _subset_onto_superset(pair[1], pair[0], seed)
    if rough_depth:
        turn = registration.transform[:3, :3]
        constrained = constrained_rotation(turn, min(pair, key=len), seed)
        dropped = float(np.degrees(rotation_angle(turn.T @ constrained)))
        if dropped > POLISH_WARN_DEG:
            warnings.append(f"the static part does not fix every turn (a strip-like or flat base): {dropped:.1f} deg "
                            f"of the polish's turn left as the feature alignment had it")
        registration = replace(registration, transform=turn_about_centroid(constrained, pair[1]))
    angle = float(np.degrees(rotation_angle(registration.transform[:3, :3])))
    if registration.inlier_fraction < MIN_STATIC_AGREEMENT:
        warnings.append(f"alignment polish is weak: {registration.inlier_fraction:.0%} of the static points "
                        f"agree; kept the feature alignment")
        return end, labels
    if angle > POLISH_WARN_DEG:
        warnings.append(f"the static part needed a {angle:.1f} deg correction after feature alignment")
    return moved(end, registration.transform), carried(labels, registration.transform)


def constrained_rotation(rotation: np.ndarray, surfaces: np.ndarray, seed: int = 0) -> np.ndarray:
    """The (3, 3) ``rotation`` with the parts of its turn that the static surfaces barely constrain
    taken out: its rotation vector projected onto the directions whose point-to-plane information
    is at least ``WEAK_TURN_SHARE`` of the best-constrained one's.

    ``surfaces``: (M, 3) the static points the ICP ran from (the state that shows less of them:
    only they have counterparts). Information of a turn about unit direction u: the mean of
    ((p - c) / r x n) . u)^2 over those points (n: their normals, c: centroid, r: RMS radius) --
    the Hessian of point-to-plane ICP in the rotation, as in degeneracy-aware ICP (Zhang, Kaess &
    Singh 2016). A long, narrow base seen as a strip (a stapler's, under its closed arm:
    principal variances 0.003 / 0.010 / 0.988) constrains a turn about its length at 1-3 % of
    the others, and the polish turned it there by 2.9-6.0 deg on rough depth, moving the arm's
    axis 6.4 / 9.1 deg off where the feature alignment alone gave 3.6 / 4.6. Realistic s0-3 (64
    scenes): every other static part had its weakest turn at >= 6 % (a faucet's round base
    6-10 %, whose polish helped: 4.9 -> 2.7 deg), boxes and cabinets 16-88 %.
    O(M k log M) for the normals (k neighbours), M <= ``POLISH_POINTS``."""
    from scipy.spatial.transform import Rotation

    surfaces = np.asarray(surfaces, dtype=np.float64)
    surfaces = surfaces[random_subset(len(surfaces), POLISH_POINTS, np.random.default_rng(seed))]
    normals, _ = normals_with_variation(surfaces, TURN_NORMAL_NEIGHBOURS)
    arms = np.cross((surfaces - surfaces.mean(axis=0)) / max(rms_radius(surfaces), 1e-12), normals)
    values, vectors = np.linalg.eigh(arms.T @ arms / len(arms))
    kept = vectors[:, values >= WEAK_TURN_SHARE * values.max()]
    turn = kept @ (kept.T @ Rotation.from_matrix(np.asarray(rotation, dtype=np.float64)).as_rotvec())
    return Rotation.from_rotvec(turn).as_matrix()


def turn_about_centroid(rotation: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The (4, 4) transform that turns by ``rotation`` (3, 3) about the centroid of ``points``
    ((N, 3), the frame it acts in): the centroid stays where it is. On rough depth it replaces the
    polish: its turn (constrained, :func:`constrained_rotation`) without its translation.

    Why: on rough depth the static surfaces' smooth warps steer the polish's translation, while
    the feature alignment pins it through matched pixels. A dishwasher (realistic s2) whose inner
    walls run along the basket's slide: the features had the slide at 0.302 (true 0.299), the full
    polish moved the end state 0.09 along it (0.395). Realistic s0-3 (rotation only vs full):
    slides within 10 % of their travel 25 -> 27 of 34, full success 0.79 -> 0.81, median axis
    1.94 -> 1.98 deg; without any polish the axes lose (success 77 -> 75 of 84). On clean depth
    the ICP's translation is the better one (twins unposed: the storage drawer 0.5 -> 5.7 deg with
    the rotation only), so clean depth keeps the whole polish. O(N)."""
    rotation = np.asarray(rotation, dtype=np.float64)
    centroid = np.asarray(points, dtype=np.float64).mean(axis=0)
    return make_transform(rotation, centroid - rotation @ centroid)


def carried(labels: PartLabels, transform: np.ndarray) -> PartLabels:
    """The labels with their start -> end motions (``initial_motion``, ``alternative_motions``)
    composed with a (4, 4) ``transform`` that moved the end cloud: a motion M found before maps a
    start point onto the end point that now lies at ``transform @ M`` of it.

    Why: the fit starts from these motions. Left in the old frame, a polish of 4.3 deg (a desk
    whose feature alignment of the states was off) left every drawer's seed turning by 4.3 deg,
    and the fits stayed there (axes 4-15 deg off, two drawers called ambiguous). O(parts)."""
    transform = np.asarray(transform, dtype=np.float64)
    return replace(labels,
                   initial_motion={k: transform @ m for k, m in labels.initial_motion.items()},
                   alternative_motions={k: [transform @ m for m in ms] for k, ms in labels.alternative_motions.items()})


def align_on_static(start: LabelledCloud, end: LabelledCloud, labels: PartLabels, warnings: list[str],
                    seed: int = 0) -> LabelledCloud:
    """Bring the end cloud into the start frame through the static part (part 0): the labeler's
    static start->end motion (identity for a still camera) seeds a robust ICP of the end static
    points onto the start static points; the end cloud is moved by the result."""
    pair = _static_points(start, end, labels)
    if pair is None:
        warnings.append("static part too small to align the unposed states; they are used as they are")
        return end
    initial = np.linalg.inv(labels.initial_motion.get(0, np.eye(4)))
    registration = register_rigid(pair[1], pair[0], init=initial, seed=seed)
    registration = _vouched_by_mask_ids(start, end, pair, registration, warnings, seed)
    if registration.inlier_fraction < MIN_STATIC_AGREEMENT:
        warnings.append(f"unposed alignment is weak: {registration.inlier_fraction:.0%} of the static points "
                        f"agree after registration")
    return moved(end, registration.transform)


def _vouched_by_mask_ids(start: LabelledCloud, end: LabelledCloud, pair: tuple[np.ndarray, np.ndarray],
                         registration, warnings: list[str], seed: int):
    """The static registration end -> start, or a better one the mask ids vouch for (module doc).
    O(N log N) for the agreement; the search adds 8 coarse ICPs on <= 2000 points."""
    if not start.segment_source or not end.segment_source:
        return registration
    agreement = id_agreement(end.points, end.mask_ids(), start.points, start.mask_ids(), scene_size(start.points), seed)
    if agreement is None:
        return registration
    before = agreement(registration.transform)
    if before >= LABEL_AGREEMENT:
        return registration
    searched = register_rigid(pair[1], pair[0], seed=seed, hypotheses=upright_starts(pair[1], pair[0]),
                              agreement=agreement)
    after = agreement(searched.transform)
    if (searched.inlier_fraction * after < registration.inlier_fraction * before + STATE_SEARCH_MARGIN
            or searched.inlier_fraction < MIN_STATIC_AGREEMENT):
        return registration
    angle = float(np.degrees(rotation_angle(np.linalg.inv(registration.transform)[:3, :3]
                                            @ searched.transform[:3, :3])))
    warnings.append(f"the states were registered again with the mask ids as evidence: static overlap "
                    f"{registration.inlier_fraction:.0%} -> {searched.inlier_fraction:.0%}, id agreement {before:.0%} -> "
                    f"{after:.0%}, {angle:.0f} deg from the first registration")
    return searched


def moved(cloud: LabelledCloud, transform: np.ndarray) -> LabelledCloud:
    """The same cloud with its points moved by a (4, 4) transform (other arrays shared). O(N)."""
    return replace(cloud, points=apply_transform(transform, cloud.points))


def _subset_onto_superset(source: np.ndarray, target: np.ndarray, seed: int):
    """The (4, 4) source -> target ICP polish from identity, run from the state that shows less of
    the static part onto the one that shows more, whose points then all have a counterpart (a
    stapler's base, mostly hidden under the closed arm: its 1574 start points against 5403 open
    ones; ICP of the larger onto the smaller turned the states by 34-45 deg). The registration
    carries the source -> target transform either way. Works on at most ``POLISH_POINTS`` per state.
    O(I N log N) for I ICP iterations over N <= ``POLISH_POINTS`` points."""
    if len(source) <= len(target):
        return register_rigid(source, target, init=np.eye(4), seed=seed, max_points=POLISH_POINTS)
    reverse = register_rigid(target, source, init=np.eye(4), seed=seed, max_points=POLISH_POINTS)
    return replace(reverse, transform=np.linalg.inv(reverse.transform),
                   correspondences=reverse.correspondences[:, ::-1].copy())


def _static_points(start: LabelledCloud, end: LabelledCloud,
                   labels: PartLabels) -> tuple[np.ndarray, np.ndarray] | None:
    start_static = start.points[labels.start_part == 0]
    end_static = end.points[labels.end_part == 0]
    if len(start_static) < MIN_STATIC_POINTS or len(end_static) < MIN_STATIC_POINTS:
        return None
    return start_static, end_static
