"""A coloured triangle mesh per part, fused from the lifted views of both states.

Frames: every surface is in the result's frame with its part at the START state (joint position
0). A movable part's end-state points are mapped back through the inverse of its fitted motion
(:func:`world_motions`: the axis, origin and angle / distance the exports replay, after its
parent's motion when the parent moves too), so both states'
views of the part add to one surface; the static part keeps what both states saw of it.

Fusion: with a camera (``K``) per view, each view's points of the part become a depth image and
are integrated into open3d's TSDF voxel-block grid (the view's pose in the part's start frame is
the camera pose when it reprojects the points onto their pixels, else a PnP solve from the points
and their pixels -- this covers the end views of a moving part and end clouds moved by a static
alignment). Views without a usable camera fall back to screened Poisson reconstruction of the
points (pointmaps from a reconstructor). Voxel and search radii are fractions of the object's
diagonal (``VOXEL_FRACTION``), so the result does not depend on the unit (metres or mm).
Simplification: quadric decimation to at most ``TRIANGLE_BUDGET`` triangles per part.

Seen share: the area of the surface lying within ``SEEN_RADIUS_VOXELS`` of an observed point,
over the area of the convex hull of the fused surface, capped at 1 -- an estimate of the share of
the part's outside that the views covered (a slab seen from one side ~0.5). The bench measures the
true share against the ground-truth meshes.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sparseart.geometry.transforms import apply_transform, transform_from_prismatic, transform_from_revolute
from sparseart.sim.links import link_name
from sparseart.types import Articulation, Camera, JointEstimate

TRIANGLE_BUDGET = 8000          # triangles per part after quadric decimation (simulators load it in ms)
VOXEL_FRACTION = 1.0 / 160.0    # TSDF voxel edge / object diagonal
SDF_TRUNC_VOXELS = 4.0          # TSDF truncation, in voxels
SEEN_RADIUS_VOXELS = 2.0        # a surface point within this many voxels of a point counts as seen
MAX_REPROJECTION_PX = 1.0       # a view's pose is used when its points reproject this close (median)
MIN_VIEW_POINTS = 30            # fewer points of a part in a view: the view is left out of its TSDF
MIN_COMPONENT_SHARE = 0.02      # connected pieces with fewer triangles than this share are dropped
POISSON_DEPTH = 8
MIN_WEIGHT = 0.5              # TSDF voxels of weight <= this are not surface: one view is enough (open3d's default 3 drops
                              # everything a sparse capture saw once: the inside of an open drawer)
BLOCK_COUNT = 12000           # TSDF hash-map blocks of 8^3 voxels (~120 MB); the object spans ~160 voxels


@dataclass
class PartSurface:
    """One part's fused surface.

    vertices: (V, 3) float64, result frame, part at the start state. faces: (F, 3) int64.
    colors: (V, 3) float64 RGB in [0, 1]. method: "tsdf" | "poisson". seen_share: in [0, 1] (see
    the module docstring). points: observed points fused per state. views: views fused (TSDF) or 0.
    """

    part_id: int
    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    method: str
    seen_share: float
    points: dict[str, int] = field(default_factory=dict)
    views: int = 0

    @property
    def link(self) -> str:
        return link_name(self.part_id)

    @property
    def area(self) -> float:
        """Surface area, result units squared."""
        v = self.vertices[self.faces]
        return float(0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum())


def part_motion(joint: JointEstimate) -> np.ndarray:
    """(4, 4) start->end motion of a part as the exports replay it: from the joint's axis, origin
    and angle (revolute) or distance (prismatic) alone -- what a simulator moves at the end value."""
    if joint.type == "revolute":
        return transform_from_revolute(joint.axis, joint.origin, float(joint.angle))
    return transform_from_prismatic(joint.axis, float(joint.distance))


def world_motions(result: Articulation) -> dict[int, np.ndarray]:
    """part id -> (4, 4) start->end motion in the result frame as the exports' kinematic chain
    replays it: a part whose parent has a joint moves with its parent first,
    ``world(part) = world(parent) @ part_motion(part)`` (parents without a joint: the base)."""
    joints = {part.spec.id: (part, joint) for part, joint in result.joints}
    motions: dict[int, np.ndarray] = {}

    def world(part_id: int, seen: frozenset = frozenset()) -> np.ndarray:
        if part_id not in motions:
            part, joint = joints[part_id]
            parent = part.spec.parent
            above = world(parent, seen | {part_id}) if parent in joints and parent not in seen | {part_id} else np.eye(4)
            motions[part_id] = above @ part_motion(joint)
        return motions[part_id]

    for part_id in joints:
        world(part_id)
    return motions


def object_diagonal(result: Articulation) -> float:
    """Diagonal of the bounding box of the labelled start points (result units); the length every
    voxel and tolerance of the exports is a fraction of."""
    points = result.start_cloud.points[result.labels.start_part >= 0]
    if len(points) == 0:
        points = result.start_cloud.points
    return float(np.linalg.norm(points.max(0) - points.min(0)))


def exported_parts(result: Articulation) -> list[int]:
    """Part ids that become links: the static part 0 and every part with a joint."""
    return [0, *[part.spec.id for part, _ in result.joints]]


def _part_views(result: Articulation, part_id: int) -> list[dict]:
    """Each (state, frame) view of a part: its points in the part's start frame, colours, pixels."""
    motion = world_motions(result)
    undo = np.linalg.inv(motion[part_id]) if part_id in motion else np.eye(4)
    views = []
    for state, cloud, part_of in (("start", result.start_cloud, result.labels.start_part),
                                  ("end", result.end_cloud, result.labels.end_part)):
        mine = part_of == part_id
        points = cloud.points[mine] if state == "start" else apply_transform(undo, cloud.points[mine])
        for frame in np.unique(cloud.frame_index[mine]):
            here = cloud.frame_index[mine] == frame
            views.append({"state": state, "frame": int(frame), "points": points[here],
                          "colors": cloud.colors[mine][here], "pixels": cloud.pixel_index[mine][here],
                          "undo": undo if state == "end" else np.eye(4)})
    return views


def _camera(result: Articulation, state: str, frame: int) -> Camera | None:
    cameras = result.cameras.get(state, [])
    return cameras[frame] if 0 <= frame < len(cameras) else None


def _reprojection(K: np.ndarray, world_to_cam: np.ndarray, points: np.ndarray, uv: np.ndarray) -> float:
    cam = apply_transform(world_to_cam, points)
    if np.any(cam[:, 2] <= 0):
        return np.inf
    projected = (cam @ K.T)[:, :2] / cam[:, 2:3]
    return float(np.median(np.linalg.norm(projected - uv, axis=1)))


def view_pose(camera: Camera, view: dict) -> np.ndarray | None:
    """(4, 4) world->camera pose of a view in the part's start frame, or None when neither the
    camera's pose nor a PnP solve reprojects the view's points onto their pixels within
    ``MAX_REPROJECTION_PX`` (median)."""
    import cv2

    K = np.asarray(camera.K, dtype=np.float64)
    points = view["points"]
    uv = np.stack([view["pixels"] % camera.width, view["pixels"] // camera.width], axis=1).astype(np.float64)
    if camera.cam_to_world is not None:
        world_to_cam = np.linalg.inv(view["undo"] @ np.asarray(camera.cam_to_world, dtype=np.float64))
        if _reprojection(K, world_to_cam, points, uv) <= MAX_REPROJECTION_PX:
            return world_to_cam
    step = max(1, len(points) // 2000)
    try:
        ok, rvec, tvec = cv2.solvePnP(np.ascontiguousarray(points[::step], dtype=np.float64),
                                      np.ascontiguousarray(uv[::step], dtype=np.float64), K, None,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
    except cv2.error:   # degenerate point sets (too few, collinear)
        return None
    if not ok:
        return None
    world_to_cam = np.eye(4)
    world_to_cam[:3, :3] = cv2.Rodrigues(rvec)[0]
    world_to_cam[:3, 3] = tvec.ravel()
    return world_to_cam if _reprojection(K, world_to_cam, points, uv) <= MAX_REPROJECTION_PX else None


def _tsdf(o3d, views: list[tuple[Camera, np.ndarray, dict]], voxel: float):
    """Integrate each view's part-masked depth (colour) into open3d's TSDF voxel-block grid and
    extract its zero level set; returns (legacy mesh, views integrated). (The tensor ``VoxelBlockGrid``: the legacy ``ScalableTSDFVolume``
    integrates nothing from these sparse masked depth images in open3d 0.20, measured.)"""
    core = o3d.core
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"), attr_dtypes=(core.float32, core.float32, core.float32),
        attr_channels=((1), (1), (3)), voxel_size=voxel, block_resolution=8, block_count=BLOCK_COUNT,
        device=core.Device("CPU:0"))
    integrated = 0
    for camera, world_to_cam, view in views:
        depth = np.zeros((camera.height, camera.width), dtype=np.float32)
        color = np.zeros((camera.height, camera.width, 3), dtype=np.float32)
        rows, cols = view["pixels"] // camera.width, view["pixels"] % camera.width
        depth[rows, cols] = apply_transform(world_to_cam, view["points"])[:, 2]
        color[rows, cols] = view["colors"]
        depth_image, color_image = o3d.t.geometry.Image(core.Tensor(depth)), o3d.t.geometry.Image(core.Tensor(color))
        K = core.Tensor(np.asarray(camera.K, dtype=np.float64))
        pose = core.Tensor(np.ascontiguousarray(world_to_cam, dtype=np.float64))
        far = float(depth.max()) * 2.0
        try:
            blocks = grid.compute_unique_block_coordinates(depth_image, K, pose, depth_scale=1.0, depth_max=far,
                                                           trunc_voxel_multiplier=float(SDF_TRUNC_VOXELS))
            grid.integrate(blocks, depth_image, color_image, K, K, pose, depth_scale=1.0, depth_max=far,
                           trunc_voxel_multiplier=float(SDF_TRUNC_VOXELS))
            integrated += 1
        except RuntimeError:   # open3d: "No block is touched" (a view's few pixels touch no block)
            continue
    if integrated == 0:
        return o3d.geometry.TriangleMesh(), 0
    return grid.extract_triangle_mesh(weight_threshold=MIN_WEIGHT).to_legacy(), integrated


def _poisson(o3d, points: np.ndarray, colors: np.ndarray, voxel: float):
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.colors = o3d.utility.Vector3dVector(colors)
    cloud = cloud.voxel_down_sample(voxel * 0.5)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4.0 * voxel, max_nn=30))
    centre = np.asarray(cloud.points).mean(0)
    cloud.orient_normals_towards_camera_location(centre)
    cloud.normals = o3d.utility.Vector3dVector(-np.asarray(cloud.normals))   # outward, away from the centre
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=POISSON_DEPTH)
    density = np.asarray(density)
    mesh.remove_vertices_by_mask(density < np.quantile(density, 0.05))
    box = cloud.get_axis_aligned_bounding_box()
    box = o3d.geometry.AxisAlignedBoundingBox(box.min_bound - 2 * voxel, box.max_bound + 2 * voxel)
    return mesh.crop(box)


def _clean(o3d, mesh, budget: int):
    mesh.remove_duplicated_vertices()
    mesh.remove_degenerate_triangles()
    if len(mesh.triangles):
        clusters, counts, _ = mesh.cluster_connected_triangles()
        clusters, counts = np.asarray(clusters), np.asarray(counts)
        mesh.remove_triangles_by_mask(counts[clusters] < MIN_COMPONENT_SHARE * counts.max())
        mesh.remove_unreferenced_vertices()
    if len(mesh.triangles) > budget:
        mesh = mesh.simplify_quadric_decimation(target_number_of_triangles=budget)
        mesh.remove_unreferenced_vertices()
    return mesh


def _seen_share(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, radius: float) -> float:
    from scipy.spatial import ConvexHull, cKDTree

    if len(faces) == 0 or len(points) < 4:
        return 0.0
    v = vertices[faces]
    areas = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    near = cKDTree(points).query(v.mean(1), distance_upper_bound=radius)[0] <= radius
    try:   # the fused surface's hull: the raw points' is inflated by stray points (measured: a door's 8.3 m^2 vs 1.0)
        hull_area = ConvexHull(vertices).area
    except Exception:   # noqa: BLE001 - flat or degenerate point sets have no 3-D hull
        return 0.0
    return float(min(1.0, areas[near].sum() / hull_area)) if hull_area > 0 else 0.0


def fuse_part(result: Articulation, part_id: int, voxel: float, budget: int = TRIANGLE_BUDGET) -> PartSurface:
    """Fuse one part's views of both states into a :class:`PartSurface` (see the module docstring).

    voxel: TSDF voxel edge, result units. Raises ValueError when the part has no points."""
    from sparseart.geometry.o3d import open3d

    o3d = open3d()
    views = _part_views(result, part_id)
    points = np.concatenate([v["points"] for v in views]) if views else np.zeros((0, 3))
    if len(points) < 4:
        raise ValueError(f"part {part_id}: too few points for a surface")
    colors = np.concatenate([v["colors"] for v in views])
    posed = []
    for view in views:
        camera = _camera(result, view["state"], view["frame"])
        if camera is None or len(view["points"]) < MIN_VIEW_POINTS:
            continue
        pose = view_pose(camera, view)
        if pose is not None:
            posed.append((camera, pose, view))
    mesh, method, fused = None, "poisson", 0
    if posed:
        mesh, fused = _tsdf(o3d, posed, voxel)
        mesh, method = _clean(o3d, mesh, budget), "tsdf"
    if mesh is None or len(mesh.triangles) == 0:
        mesh, method, fused = _clean(o3d, _poisson(o3d, points, colors, voxel), budget), "poisson", 0
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.triangles, dtype=np.int64)
    vertex_colors = (np.asarray(mesh.vertex_colors, dtype=np.float64) if mesh.has_vertex_colors()
                     else np.full((len(vertices), 3), 0.6))
    counts = {state: int(sum(len(v["points"]) for v in views if v["state"] == state)) for state in ("start", "end")}
    return PartSurface(part_id, vertices, faces, vertex_colors, method,
                       _seen_share(vertices, faces, points, SEEN_RADIUS_VOXELS * voxel), counts, fused)


def fuse_parts(result: Articulation, budget: int = TRIANGLE_BUDGET) -> dict[int, PartSurface]:
    """A :class:`PartSurface` for every exported part (:func:`exported_parts`), keyed by part id.

    Raises ValueError when the result has no labelled clouds (clouds given without labels)."""
    if result.start_cloud is None or result.end_cloud is None or result.labels is None:
        raise ValueError("surfaces need the result's labelled start and end clouds")
    voxel = object_diagonal(result) * VOXEL_FRACTION
    if not np.isfinite(voxel) or voxel <= 0:
        raise ValueError("surfaces: the object has no extent")
    return {part_id: fuse_part(result, part_id, voxel, budget) for part_id in exported_parts(result)}
