"""Collision pieces and mass of a part surface.

Collision: approximate convex decomposition by ``coacd`` (CoACD; its manifold pre-processing
closes the open fused surfaces into thin shells first), at most ``MAX_HULLS`` pieces per part and
concavity threshold ``COACD_THRESHOLD`` (a fraction of the part's size, coacd normalises the mesh),
on the surface decimated to ``COACD_TRIANGLES`` and a shortened tree search (``COACD_SEARCH``).
A surface that already lies on its convex hull (every point within ``CONVEX_TOLERANCE`` of the
part's diagonal of the hull's boundary: a door, a lid, a closed drawer front) is its own single
piece, without coacd. Each piece is re-hulled with trimesh so it is closed and outward-wound. open3d is imported before
coacd: the other order makes ``import open3d`` fail (``std::bad_cast``, open3d 0.20 + coacd 1.0.14).

Carving (:func:`carve`): a parent's pieces leave each child's rest box free (the child was seen
there). Mass: the union of the pieces at ``DENSITY`` per cubic result unit (500 kg/m^3, light wood or
particle board, when the result is in metres; images do not measure density, so this is a stated
placeholder), through trimesh's mass properties: mass, centre of mass and the inertia tensor about
the centre of mass, in the axes of the frame the vertices are given in.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DENSITY = 500.0          # mass per cubic result unit (kg/m^3 for metres)
COACD_THRESHOLD = 0.08   # coacd concavity threshold (0.01 fine .. 1 coarse)
MAX_HULLS = 16           # convex pieces per part at most
COACD_TRIANGLES = 1000   # the surface is decimated to this many triangles before the decomposition
# coacd's search made cheap: its defaults took 30-80 s per part of the rendered cabinet on the
# shared 2-core machine, these 0.2-2 s (measured 2026-11-29, load ~12)
COACD_SEARCH = dict(mcts_iterations=10, mcts_nodes=5, mcts_max_depth=1, resolution=300,
                    preprocess_resolution=30, max_ch_vertex=64)
CONVEX_TOLERANCE = 0.05  # a surface within this share of its diagonal of its convex hull is its own hull
MIN_PIECE_VOLUME_SHARE = 1e-4
MIN_THICKNESS = 0.01     # mass and inertia floors: a slab this share of the part's diagonal thick   # pieces thinner than this share of the part's hull volume are dropped


@dataclass
class PartBody:
    """Collision and mass of one part, in the frame its surface was given in.

    hulls: list of (vertices (V, 3) float64, faces (F, 3) int64) closed convex pieces.
    mass: DENSITY x volume (kg for metres). com: (3,) float64 centre of mass. inertia: (3, 3)
    float64 inertia tensor about the centre of mass (kg m^2 for metres), axes of the frame.
    """

    hulls: list[tuple[np.ndarray, np.ndarray]]
    mass: float
    com: np.ndarray
    inertia: np.ndarray
    density: float = DENSITY


def convex_pieces(vertices: np.ndarray, faces: np.ndarray, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Convex decomposition of a surface by coacd; each piece closed by trimesh's convex hull.
    Falls back to the surface's convex hull when coacd returns nothing usable.

    vertices: (V, 3) float64; faces: (F, 3) int64. Returns a list of (vertices, faces)."""
    import trimesh

    whole = trimesh.convex.convex_hull(np.asarray(vertices, dtype=np.float64))
    if hull_gap(vertices, whole) <= CONVEX_TOLERANCE * np.linalg.norm(np.ptp(vertices, axis=0)):
        return [(np.asarray(whole.vertices, dtype=np.float64), np.asarray(whole.faces, dtype=np.int64))]
    from sparseart.geometry.o3d import open3d

    o3d = open3d()          # before coacd (see the module docstring)
    import coacd

    surface = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, dtype=np.float64)),
                                        o3d.utility.Vector3iVector(np.asarray(faces, dtype=np.int32)))
    if len(faces) > COACD_TRIANGLES:
        surface = surface.simplify_quadric_decimation(target_number_of_triangles=COACD_TRIANGLES)
    coacd.set_log_level("error")
    pieces = coacd.run_coacd(coacd.Mesh(np.asarray(surface.vertices, dtype=np.float64),
                                        np.asarray(surface.triangles, dtype=np.int64)),
                             threshold=COACD_THRESHOLD, max_convex_hull=MAX_HULLS, preprocess_mode="auto",
                             seed=seed, **COACD_SEARCH)
    hulls = []
    for piece_vertices, _ in pieces:
        try:
            hull = trimesh.convex.convex_hull(np.asarray(piece_vertices, dtype=np.float64))
        except Exception:   # noqa: BLE001 - a flat piece has no 3-D hull (qhull error)
            continue
        hulls.append(hull)
    hulls = [h for h in hulls if h.volume > MIN_PIECE_VOLUME_SHARE * whole.volume]
    if not hulls:
        hulls = [whole]
    return [(np.asarray(h.vertices, dtype=np.float64), np.asarray(h.faces, dtype=np.int64)) for h in hulls]


def hull_gap(vertices: np.ndarray, hull) -> float:
    """99th percentile distance (units) of the vertices from the boundary of their convex hull
    (a trimesh convex mesh): how far the surface departs from being convex."""
    normals = np.asarray(hull.face_normals, dtype=np.float64)
    offsets = np.einsum("ij,ij->i", normals, np.asarray(hull.triangles_center, dtype=np.float64))
    inside = offsets[None, :] - np.asarray(vertices, dtype=np.float64) @ normals.T   # >= 0 inside each face plane
    return float(np.percentile(inside.min(axis=1), 99))


def carve(hulls: list[tuple[np.ndarray, np.ndarray]], child_points: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The parent's convex pieces with the child's rest box left free.

    A part was seen where it rests, so that space is not solid parent: coacd's pieces of a partly
    seen body fill its cavities (a dishwasher's rack slot, a drawer's slot) and the child would
    rest inside its parent. Each piece meeting the oriented bounding box of ``child_points`` (the
    child's collision vertices at rest, in the pieces' frame) is replaced by its parts outside
    each of the box's six face planes (convex, closed by trimesh's capped plane slices; they may
    overlap each other, which collision does not mind). Pieces clear of the box are kept as they are.
    """
    import trimesh

    to_box, extents = trimesh.bounds.oriented_bounds(np.asarray(child_points, dtype=np.float64))
    from_box = np.linalg.inv(to_box)
    half = 0.5 * np.asarray(extents, dtype=np.float64)
    carved = []
    for vertices, faces in hulls:
        local = np.asarray(vertices, dtype=np.float64) @ to_box[:3, :3].T + to_box[:3, 3]
        if np.any(local.min(0) >= half) or np.any(local.max(0) <= -half):
            carved.append((vertices, faces))          # separated along a box axis: untouched
            continue
        piece = trimesh.Trimesh(vertices, faces, process=False)
        for axis in range(3):
            for sign in (1.0, -1.0):
                normal = np.zeros(3)
                normal[axis] = sign
                origin = from_box[:3, :3] @ (normal * half) + from_box[:3, 3]
                world_normal = from_box[:3, :3] @ normal
                try:
                    part = trimesh.intersections.slice_mesh_plane(piece, world_normal, origin, cap=True)
                except (ValueError, IndexError):   # the plane misses the piece or leaves nothing
                    continue
                if part is not None and len(part.faces) >= 4 and part.volume > MIN_PIECE_VOLUME_SHARE * piece.volume:
                    hull = trimesh.convex.convex_hull(part.vertices)
                    carved.append((np.asarray(hull.vertices, dtype=np.float64), np.asarray(hull.faces, dtype=np.int64)))
    return carved


def mass_properties(hulls: list[tuple[np.ndarray, np.ndarray]], density: float = DENSITY) -> tuple[float, np.ndarray, np.ndarray]:
    """(mass, com (3,), inertia (3, 3) about the com) of the union of closed convex pieces
    (overlaps counted twice; coacd's pieces barely overlap) at ``density`` per cubic unit."""
    import trimesh

    union = trimesh.util.concatenate([trimesh.Trimesh(v, f, process=False) for v, f in hulls])
    union.density = float(density)
    return (float(union.mass), np.asarray(union.center_mass, dtype=np.float64),
            np.asarray(union.moment_inertia, dtype=np.float64))


def part_body(vertices: np.ndarray, faces: np.ndarray, density: float = DENSITY, seed: int = 0) -> PartBody:
    """Collision pieces and mass of one surface (see the module docstring)."""
    hulls = convex_pieces(vertices, faces, seed=seed)
    mass, com, inertia = mass_properties(hulls, density)
    # a flat part (a sheet seen from one side) has ~no volume: floor it as a slab MIN_THICKNESS of
    # its diagonal thick, so a simulator gets a positive mass and inertia
    size = float(np.linalg.norm(np.ptp(np.asarray(vertices, dtype=np.float64), axis=0)))
    floor_mass = density * (MIN_THICKNESS * size) ** 3
    if not np.isfinite(mass) or mass < floor_mass:
        mass, com = floor_mass, np.asarray(vertices, dtype=np.float64).mean(0)
        inertia = np.zeros((3, 3))
    moments, axes = np.linalg.eigh(0.5 * (inertia + inertia.T))
    moments = np.maximum(moments, mass * (MIN_THICKNESS * size) ** 2 / 6.0)
    return PartBody(hulls, mass, com, (axes * moments) @ axes.T, density)
