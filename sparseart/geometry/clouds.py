"""Point-cloud helpers shared by every stage: spacing, extent, principal spread, valid points.

All points are (N, 3) float64 in whatever frame and unit the caller uses; every length returned
is in that unit, so callers stay unit-free by expressing thresholds as multiples of these.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from sparseart.geometry.transforms import apply_transform
from sparseart.types import Pointmap


def median_spacing(points: np.ndarray, *, sample: int | None = None, rng: np.random.Generator | None = None,
                   tree: cKDTree | None = None) -> float:
    """Median nearest-neighbour distance of a cloud (its sampling density), in the cloud's unit.

    points: (N, 3) float64. sample: query at most this many points (chosen by ``rng``, default
    seed 0) against the WHOLE cloud; None = every point. tree: a prebuilt cKDTree of ``points``.
    Falls back to 1e-3 of the largest extent for clouds with duplicate points, and to 1.0 for
    fewer than 2 points. O(N log N) for the tree + O(S log N) for S queries.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if points.shape[0] < 2:
        return 1.0
    tree = tree if tree is not None else cKDTree(points)
    query = points
    if sample is not None and points.shape[0] > sample:
        rng = rng if rng is not None else np.random.default_rng(0)
        query = points[rng.choice(points.shape[0], size=sample, replace=False)]
    distances, _ = tree.query(query, k=2)
    spacing = float(np.median(distances[:, 1]))
    if spacing > 0:
        return spacing
    return float(np.ptp(points, axis=0).max() * 1e-3) or 1e-12


def pca_normals(points: np.ndarray, positions: np.ndarray, neighbours: int,
                tree: cKDTree | None = None) -> np.ndarray:
    """(S, 3) unoriented unit surface normals at ``positions`` (S, 3): the smallest principal axis
    of the ``neighbours`` nearest of ``points`` (N, 3) around each. tree: a prebuilt cKDTree of
    ``points``. O(S k log N) (+ O(N log N) without ``tree``)."""
    tree = tree if tree is not None else cKDTree(points)
    _, index = tree.query(positions, k=neighbours)
    local = points[index] - points[index].mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))[1][:, :, 0]


def normals_with_variation(points: np.ndarray, neighbours: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) unoriented unit normals of every point of ``points`` (N, 3) from the scatter of its
    ``neighbours`` nearest points (open3d's covariance estimate, C++), and (N,) the surface
    variation: the scatter's smallest eigenvalue over the sum of all three (0 on a plane, 1/3 for
    isotropic noise; unit-free). Each point's estimate depends on its own neighbours only, so the
    result does not depend on open3d's threads. O(N k log N)."""
    from .o3d import open3d

    o3d = open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    cloud.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(int(min(neighbours, len(points)))))
    values, vectors = np.linalg.eigh(np.asarray(cloud.covariances))
    return vectors[:, :, 0], values[:, 0] / np.maximum(values.sum(axis=1), 1e-300)


SLAB_THICKNESS_SHARE = 0.3  # a slab (door, lid): third principal extent at most this share of the second


def slab_axes(points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(centre (3,), axes (3, 3)) of ``points`` (N, 3) when they form a slab -- the smallest RMS
    principal extent at most ``SLAB_THICKNESS_SHARE`` of the middle one -- else None. axes: rows,
    principal directions by decreasing extent (row 2 = the slab's normal). O(N)."""
    centre = points.mean(axis=0)
    if len(points) < 3:   # fewer points than dimensions: flat by construction
        return centre, np.linalg.svd(points - centre, full_matrices=True)[2]
    _, singular, axes = np.linalg.svd(points - centre, full_matrices=False)
    return (centre, axes) if singular[2] <= SLAB_THICKNESS_SHARE * singular[1] else None


def radius_components(points: np.ndarray, link_radius: float) -> np.ndarray:
    """Connected components of the radius graph of ``points`` (N, 3): (N,) int64 component label
    per point, 0..k-1; points closer than ``link_radius`` (same units) are linked. O(N log N + E)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pairs = cKDTree(points).query_pairs(link_radius, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points),) * 2)
    _, labels = connected_components(graph, directed=False)
    return labels.astype(np.int64)


def nearest_gap(points: np.ndarray, probes: np.ndarray, bound: float) -> float:
    """Least distance from any of ``probes`` ((P, 3) float64) to ``points`` ((N, 3), same frame);
    inf when none comes within ``bound``. Both non-empty. O((N + P) log N)."""
    return float(np.min(cKDTree(points).query(probes, k=1, distance_upper_bound=bound)[0]))


def scene_size(points: np.ndarray, max_points: int = 20000) -> float:
    """Median distance of the finite points to their centroid (the scale of RANSAC thresholds).

    Uses at most ``max_points`` evenly strided points. O(N)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    if points.shape[0] == 0:
        return 0.0
    if points.shape[0] > max_points:
        points = points[np.linspace(0, points.shape[0] - 1, max_points).astype(int)]
    return float(np.median(np.linalg.norm(points - points.mean(axis=0), axis=1)))


def rms_radius(points: np.ndarray) -> float:
    """RMS distance of (N, 3) ``points`` to their centroid (their units). O(N)."""
    return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))


def spread(points: np.ndarray) -> np.ndarray:
    """(3,) RMS extent of the points along their principal axes, largest first. O(N)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if points.shape[0] < 2:
        return np.zeros(3)
    singular = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return np.pad(singular, (0, 3 - singular.size)) / np.sqrt(points.shape[0])


def valid_points(pointmap: Pointmap) -> np.ndarray:
    """(K, 3) float64 points of a pointmap's valid, finite pixels, in the pointmap's frame."""
    return pointmap.points[pointmap.valid & np.isfinite(pointmap.points).all(axis=1)]


def transform_pointmap(pointmap: Pointmap, transform: np.ndarray) -> Pointmap:
    """A copy of ``pointmap`` with its points mapped by a (4, 4) transform (NaN stays NaN). O(H W)."""
    return replace(pointmap, points=apply_transform(transform, pointmap.points))
