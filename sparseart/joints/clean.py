"""Outlier and fragment removal for one part's point set (any frame, any units).

``clean_part_points`` = statistical outlier removal (mean distance to the k nearest neighbours,
robust threshold) followed by connected components of the k-NN graph's short edges (eps from the
median point spacing), keeping every cluster that holds at least ``min_cluster_fraction`` of the
largest one.
Cost O(N log N) for the one k-NN query; the clusters reuse its neighbours (O(N k)).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from sparseart.geometry.clouds import pca_normals


def clean_part_points(
    points: np.ndarray,
    neighbours: int = 8,
    mad_factor: float = 4.0,
    eps_factor: float = 2.5,
    min_cluster_fraction: float = 0.05,
) -> np.ndarray:
    """Boolean keep-mask (N,) for ``points`` (N, 3) float64.

    A point is an outlier when its mean distance to its ``neighbours`` nearest neighbours exceeds
    ``max(median + mad_factor * 1.4826 * MAD, 2 * median)`` of that statistic over the set.
    Survivors are linked when one is among the other's ``neighbours`` nearest and closer than
    ``eps = eps_factor * median k-NN mean distance``;
    connected clusters smaller than ``min_cluster_fraction`` x the largest are dropped.
    Non-finite rows are always dropped. Sets too small for statistics (< neighbours + 2 finite
    points) are returned unchanged apart from non-finite rows. Never returns an all-False mask
    for a non-empty finite input.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    keep = np.all(np.isfinite(points), axis=1)
    finite_index = np.flatnonzero(keep)
    if finite_index.size < neighbours + 2:
        return keep
    finite_points = points[finite_index]
    tree = cKDTree(finite_points)
    distances, index = tree.query(finite_points, k=neighbours + 1)
    mean_distance = distances[:, 1:].mean(axis=1)
    median = float(np.median(mean_distance))
    mad = float(np.median(np.abs(mean_distance - median)))
    threshold = max(median + mad_factor * 1.4826 * mad, 2.0 * median)
    inlier = mean_distance <= threshold if median > 0 else np.ones(finite_index.size, bool)
    survivors = finite_index[inlier]
    if survivors.size < neighbours + 2 or median <= 0:
        keep[:] = False
        keep[survivors] = True
        return keep
    component = _knn_components(distances, index, inlier, eps_factor * median)
    sizes = np.bincount(component)
    big = sizes >= min_cluster_fraction * sizes.max()
    keep[:] = False
    keep[survivors[big[component]]] = True
    return keep


def _knn_components(distances: np.ndarray, index: np.ndarray, inlier: np.ndarray, link: float) -> np.ndarray:
    """Connected components (labels 0..k-1 per inlier row) of the k-NN graph already queried,
    keeping the edges shorter than ``link`` between two inliers. On a sampled surface every
    point's k nearest lie within ``link`` (2.5 x their mean distance), so this links what the
    radius graph links except through a bridge of points whose k nearest all lie on one side,
    without the radius graph's second query (measured 0.08 s of 0.14 s at 40k points).
    distances / index: (N, k + 1) of ``cKDTree.query`` (column 0 = the point itself);
    inlier: (N,) bool. Every index is valid: the query has no distance bound and N > k. O(N k)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows = np.repeat(np.arange(len(index)), index.shape[1] - 1)
    cols = index[:, 1:].reshape(-1)
    near = distances[:, 1:].reshape(-1) < link
    near &= inlier[rows] & inlier[cols]
    renumber = np.cumsum(inlier) - 1                         # inlier row -> survivor index
    count = int(inlier.sum())
    graph = coo_matrix((np.ones(int(near.sum())), (renumber[rows[near]], renumber[cols[near]])), shape=(count, count))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def estimate_normals(points: np.ndarray, neighbours: int = 12, at: np.ndarray | None = None,
                     tree: cKDTree | None = None) -> np.ndarray:
    """Unoriented unit normals by PCA of the k nearest neighbours in ``points`` (N, 3).

    at: (S,) int rows of ``points`` to estimate the normals of (default all); the neighbours
    still come from the whole set, so a row's normal does not depend on ``at``. tree: a prebuilt
    cKDTree of ``points``. Returns (S, 3). O(S k log N) (+ O(N log N) without ``tree``).
    Used to gate matches: on partial views a point whose surface is hidden in the other state
    would otherwise pull on the nearest visible surface of a different orientation.
    """
    count = points.shape[0]
    rows = np.arange(count) if at is None else np.asarray(at)
    if count < 4:
        return np.tile([0.0, 0.0, 1.0], (len(rows), 1))
    return pca_normals(points, points[rows], min(neighbours, count), tree=tree)
