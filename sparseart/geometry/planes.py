"""Planes and the hinge two planes imply: a RANSAC plane fit, the four turns about the line where a
part's start and end planes meet, the truncated Chamfer loss that picks among them, and the
dominant plane normals of a boxy body (its Manhattan frame).

Used by the joint fitter (a closed-form revolute seed for a slab; slides along the static body's
axes) and by the maskless labeler (candidate motions for doors and lids that registration from
identity cannot reach; the static body's frame). All points
are (N, 3) float64 in one frame; lengths are in the caller's unit.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from sparseart.geometry.clouds import pca_normals
from sparseart.geometry.transforms import apply_transform, make_transform

RANSAC_ITERATIONS = 300
RANSAC_SAMPLE = 5000


def ransac_plane(points: np.ndarray, distance: float,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
    """(unit normal, centroid) of the plane most points lie within ``distance`` of: RANSAC over
    ``RANSAC_ITERATIONS`` triples of at most ``RANSAC_SAMPLE`` points, then a least-squares refit
    on the inliers of all points. None below 10 points or 3 inliers. O(I S + N)."""
    sample = points[rng.choice(len(points), min(RANSAC_SAMPLE, len(points)), replace=False)]
    if len(sample) < 10:
        return None
    triples = sample[rng.integers(0, len(sample), size=(RANSAC_ITERATIONS, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    norms = np.linalg.norm(normals, axis=1)
    keep = norms > 1e-12
    if not keep.any():
        return None
    normals, triples = normals[keep] / norms[keep, None], triples[keep]
    support = (np.abs(sample @ normals.T - np.einsum("kj,kj->k", normals, triples[:, 0])) < distance).sum(axis=0)
    best = int(np.argmax(support))
    inliers = points[np.abs((points - triples[best, 0]) @ normals[best]) < distance]
    if len(inliers) < 3:
        return None
    centre = inliers.mean(axis=0)
    return np.linalg.svd(inliers - centre, full_matrices=False)[2][2], centre


def hinge_turns(start_plane: tuple[np.ndarray, np.ndarray], end_plane: tuple[np.ndarray, np.ndarray],
                min_turn_deg: float) -> list[np.ndarray]:
    """The four (4, 4) start->end turns that take a flat part from its start plane to its end
    plane about the line where the planes meet: by theta and pi - theta (theta between the
    normals), either sign. A door or lid turns about a hinge that lies in (or next to) its own
    plane, so that line is its hinge whatever the points look like. Each plane is (unit normal,
    a point on it). The pivot is the point of the line nearest the two plane points' midpoint.
    Empty when the normals are within ``min_turn_deg`` of parallel (a slide). O(1)."""
    (normal_s, centre_s), (normal_e, centre_e) = start_plane, end_plane
    axis = np.cross(normal_s, normal_e)
    if np.linalg.norm(axis) < np.sin(np.radians(min_turn_deg)):
        return []
    axis /= np.linalg.norm(axis)
    system = np.stack([normal_s, normal_e, axis])
    point = np.linalg.solve(system, [normal_s @ centre_s, normal_e @ centre_e, axis @ (centre_s + centre_e) / 2])
    theta = float(np.arccos(np.clip(abs(normal_s @ normal_e), 0.0, 1.0)))
    turns = []
    for angle in (theta, np.pi - theta, -theta, theta - np.pi):
        rotation = Rotation.from_rotvec(axis * angle).as_matrix()
        turns.append(make_transform(rotation, point - rotation @ point))
    return turns


def best_by_truncated_chamfer(transforms: list[np.ndarray], start_sample: np.ndarray, end_sample: np.ndarray,
                              clip: float) -> np.ndarray:
    """The (4, 4) start->end transform whose moved ``start_sample`` and ``end_sample`` are nearest
    each other: the mean of both directions' nearest distances, each clipped at ``clip`` (so one
    stray piece cannot outvote the rest). O(T (S + E) log(S + E))."""
    end_tree = cKDTree(end_sample)

    def loss(transform: np.ndarray) -> float:
        moved = apply_transform(transform, start_sample)
        forward = np.minimum(end_tree.query(moved, distance_upper_bound=clip)[0], clip)
        backward = np.minimum(cKDTree(moved).query(end_sample, distance_upper_bound=clip)[0], clip)
        return float(forward.mean() + backward.mean())

    return min(transforms, key=loss)


def manhattan_frame(points: np.ndarray, sample: int = 3000, candidates: int = 300) -> np.ndarray:
    """(3, 3) orthonormal axes (columns) along the dominant surface normals of a (boxy) body.

    Normals from local PCA (12 neighbours) of up to ``sample`` points; the first axis is the
    normal shared (within 10 deg) by most others, the second the same among the normals
    perpendicular to it, the third their cross product. Falls back to the principal axes of the
    points for tiny or featureless clouds. Deterministic (strided picks). O(S log N + C S).
    """
    points = np.asarray(points, dtype=np.float64)
    fallback = np.linalg.svd(points - points.mean(axis=0), full_matrices=False)[2].T if len(points) >= 3 else np.eye(3)
    if len(points) < 50:
        return fallback
    pick = points[np.linspace(0, len(points) - 1, min(sample, len(points))).astype(np.int64)]
    normals = pca_normals(points, pick, 12)
    cos10, sin10 = np.cos(np.radians(10.0)), np.sin(np.radians(10.0))

    def dominant(pool: np.ndarray) -> np.ndarray | None:
        if len(pool) < 10:
            return None
        tries = pool[np.linspace(0, len(pool) - 1, min(candidates, len(pool))).astype(np.int64)]
        support = (np.abs(tries @ pool.T) > cos10).sum(axis=1)
        best = tries[int(np.argmax(support))]
        members = pool[np.abs(pool @ best) > cos10]
        members = members * np.sign(members @ best)[:, None]
        mean = members.mean(axis=0)
        return mean / np.linalg.norm(mean)

    first = dominant(normals)
    if first is None:
        return fallback
    rest = normals[np.abs(normals @ first) < sin10]
    rest = rest - (rest @ first)[:, None] * first
    lengths = np.linalg.norm(rest, axis=1)
    rest = rest[lengths > 1e-9] / lengths[lengths > 1e-9, None]
    second = dominant(rest)
    if second is None:
        return fallback
    second = second - (second @ first) * first
    second /= np.linalg.norm(second)
    return np.stack([first, second, np.cross(first, second)], axis=1)
