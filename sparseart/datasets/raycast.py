"""RGB-D + label rendering of coloured meshes with open3d's RaycastingScene (CPU, vectorised).

Cameras are OpenCV (x right, y down, z forward); pixel (row r, col c) looks through image point
(c, r), i.e. ray direction in the camera frame is ``((c - cx) / fx, (r - cy) / fy, 1)``. Depth is
the camera-frame z of the hit (not the ray length). Open3D intersects in float32; every hit is
re-intersected with its triangle in float64 so unprojected depth lies on the mesh to ~1e-12.
Shading: two-sided Lambertian from a fixed world key light + a weaker fill light + ambient.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from sparseart.datasets.meshes import RenderMesh, sample_texture

KEY_LIGHT = np.array([0.35, -0.45, 0.82])
FILL_LIGHT = np.array([-0.6, 0.5, 0.3])
BACKGROUND = np.array([200, 200, 200], dtype=np.uint8)
# Bumped whenever the same scene would render differently; cached bench renders stamped with
# another version are rendered again. 2: coplanar duplicates resolved by triangle order.
RENDERER_VERSION = 2
# Triangles a ray meets within this relative depth of its first hit count as one surface
# (coplanar duplicates; float32 intersection is good to ~1e-7 relative, decals sit ~1e-4 off).
COPLANAR_RELATIVE_T = 1e-5


class PreparedScene:
    """Concatenated world-frame geometry with a built BVH; reuse it for every view of one state.

    parts: sequence of (RenderMesh in world frame, mask label int in [1, 65535]) or
    (open3d legacy TriangleMesh, label) pairs.
    """

    def __init__(self, parts: Sequence[tuple[RenderMesh, int]]):
        from sparseart.geometry.o3d import open3d
        o3d = open3d()

        meshes, labels = [], []
        for mesh, label in parts:
            if not isinstance(mesh, RenderMesh):
                mesh = RenderMesh.from_o3d(mesh)
            meshes.append(mesh)
            labels.append(np.full(mesh.n_triangles, int(label), dtype=np.uint16))
        self.mesh = RenderMesh.concat(meshes)
        self.tri_label = np.concatenate(labels) if labels else np.zeros(0, np.uint16)
        v, t = self.mesh.vertices, self.mesh.triangles
        self.v0 = v[t[:, 0]]
        self.e1 = v[t[:, 1]] - self.v0
        self.e2 = v[t[:, 2]] - self.v0
        n = np.cross(self.e1, self.e2)
        nn = np.linalg.norm(n, axis=1, keepdims=True)
        self.normals = n / np.maximum(nn, 1e-300)
        self.scene = o3d.t.geometry.RaycastingScene()
        if len(t):
            self.scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)),
                                     o3d.core.Tensor(t.astype(np.uint32)))

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Intersect rays ((N, 3) float64 origins, (N, 3) float64 directions, any length).

        Returns (t (N,) float64 in units of the direction length, inf = miss; tri (N,) int64, -1 = miss).
        """
        from sparseart.geometry.o3d import open3d
        o3d = open3d()

        n = len(origins)
        if len(self.tri_label) == 0:
            return np.full(n, np.inf), np.full(n, -1, np.int64)
        rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
        ans = self.scene.cast_rays(o3d.core.Tensor(rays))
        tri = ans["primitive_ids"].numpy().astype(np.int64)
        hit = np.isfinite(ans["t_hit"].numpy()) & (tri != np.iinfo(np.uint32).max) & (tri >= 0)
        tri = np.where(hit, tri, -1)
        t = np.full(n, np.inf)
        h = np.nonzero(hit)[0]
        th = tri[h]
        nrm = self.normals[th]
        denom = np.einsum("ij,ij->i", nrm, dirs[h])
        num = np.einsum("ij,ij->i", nrm, self.v0[th] - origins[h])
        with np.errstate(divide="ignore", invalid="ignore"):
            t64 = num / denom
        t32 = ans["t_hit"].numpy()[h].astype(np.float64)
        good = np.isfinite(t64) & (np.abs(t64 - t32) <= 1e-3 * np.maximum(t32, 1.0))
        t[h] = np.where(good, t64, t32)
        tri[h], t[h] = self._first_of_coplanar(rays[h], origins[h], dirs[h], th, t[h])
        return t, tri

    def _first_of_coplanar(self, rays: np.ndarray, origins: np.ndarray, dirs: np.ndarray, tri: np.ndarray,
                           t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The lowest-index triangle among those a ray meets at its first hit's depth (within
        ``COPLANAR_RELATIVE_T``), with its float64 t: (tri (N,) int64, t (N,) float64).

        Why: meshes such as PartNet-Mobility's hold coplanar duplicates (a textured face over an
        untextured one). Which of them the BVH reports first depends on the whole scene, so moving
        one part re-coloured the unmoved body (measured: 20 % of a refrigerator's static pixels,
        17 % of a storage unit's, 7 % of a faucet's changed colour between the states at equal
        depth, in half-triangle patches). A fixed rule keeps an unmoved surface's appearance.
        rays (N, 6) float32 as cast; origins / dirs (N, 3) float64; tri / t the first hits.
        O(total intersections along the rays).
        """
        from sparseart.geometry.o3d import open3d
        o3d = open3d()

        found = self.scene.list_intersections(o3d.core.Tensor(rays))
        ray = found["ray_ids"].numpy().astype(np.int64)
        prim = found["primitive_ids"].numpy().astype(np.int64)
        if not len(ray):
            return tri, t
        nrm = self.normals[prim]
        with np.errstate(divide="ignore", invalid="ignore"):
            t_each = (np.einsum("ij,ij->i", nrm, self.v0[prim] - origins[ray])
                      / np.einsum("ij,ij->i", nrm, dirs[ray]))
        t_each = np.where(np.isfinite(t_each), t_each, found["t_hit"].numpy().astype(np.float64))
        tied = np.abs(t_each - t[ray]) <= COPLANAR_RELATIVE_T * np.abs(t[ray])
        lowest = tri.copy()
        np.minimum.at(lowest, ray[tied], prim[tied])
        moved = lowest != tri
        if moved.any():
            pick = tied & moved[ray] & (prim == lowest[ray])
            t = t.copy()
            t[ray[pick]] = t_each[pick]
        return lowest, t

    def barycentric(self, points: np.ndarray, tri: np.ndarray) -> np.ndarray:
        """(N, 3) float64 barycentric weights of (N, 3) ``points`` in triangles ``tri`` (N,)."""
        e1, e2 = self.e1[tri], self.e2[tri]
        d = points - self.v0[tri]
        d11 = np.einsum("ij,ij->i", e1, e1)
        d12 = np.einsum("ij,ij->i", e1, e2)
        d22 = np.einsum("ij,ij->i", e2, e2)
        dp1 = np.einsum("ij,ij->i", d, e1)
        dp2 = np.einsum("ij,ij->i", d, e2)
        den = d11 * d22 - d12 * d12
        den = np.where(np.abs(den) < 1e-300, 1.0, den)
        b1 = (d22 * dp1 - d12 * dp2) / den
        b2 = (d11 * dp2 - d12 * dp1) / den
        return np.stack([1.0 - b1 - b2, b1, b2], axis=1)


def camera_rays(K: np.ndarray, cam_to_world: np.ndarray, width: int,
                height: int) -> tuple[np.ndarray, np.ndarray]:
    """World rays of every pixel, row-major: origins (H*W, 3), directions (H*W, 3) float64.

    Directions are R @ ((c - cx)/fx, (r - cy)/fy, 1), so the ray parameter equals camera depth z.
    """
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(cam_to_world, dtype=np.float64)
    r, c = np.mgrid[0:height, 0:width]
    y = (r.ravel() - K[1, 2]) / K[1, 1]
    x = (c.ravel() - K[0, 2] - K[0, 1] * y) / K[0, 0]  # K[0, 1] = skew, normally 0
    d_cam = np.stack([x, y, np.ones_like(x)], axis=1)
    dirs = d_cam @ T[:3, :3].T
    origins = np.broadcast_to(T[:3, 3], dirs.shape).copy()
    return origins, dirs


def render_view(meshes_with_ids: Sequence[tuple[RenderMesh, int]] | PreparedScene, K: np.ndarray,
                cam_to_world: np.ndarray, width: int, height: int,
                background: np.ndarray = BACKGROUND) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one view.

    meshes_with_ids: (world-frame RenderMesh or open3d TriangleMesh, mask label) pairs, or a
        :class:`PreparedScene` (faster when rendering several views of the same geometry).
    K: (3, 3) intrinsics in pixels; cam_to_world: (4, 4) OpenCV camera -> world, float64.
    Returns rgb (H, W, 3) uint8, depth (H, W) float64 camera z in world units (0 = no hit),
    label (H, W) uint16 (0 = background).
    """
    scene = meshes_with_ids if isinstance(meshes_with_ids, PreparedScene) else PreparedScene(meshes_with_ids)
    origins, dirs = camera_rays(K, cam_to_world, width, height)
    t, tri = scene.cast(origins, dirs)
    hit = (tri >= 0) & np.isfinite(t) & (t > 0)
    n_pix = width * height
    depth = np.zeros(n_pix)
    depth[hit] = t[hit]
    label = np.zeros(n_pix, dtype=np.uint16)
    rgb = np.empty((n_pix, 3), dtype=np.uint8)
    rgb[:] = np.asarray(background, dtype=np.uint8)
    h = np.nonzero(hit)[0]
    if len(h):
        th = tri[h]
        label[h] = scene.tri_label[th]
        mesh = scene.mesh
        albedo = mesh.tri_colors[th].copy()
        if mesh.tri_tex is not None and mesh.textures:
            tex_id = mesh.tri_tex[th]
            textured = tex_id >= 0
            if textured.any():
                ht = h[textured]
                pts = origins[ht] + t[ht, None] * dirs[ht]
                bary = scene.barycentric(pts, th[textured])
                uv = np.einsum("ik,ikj->ij", bary, mesh.tri_uv[th[textured]])
                sub = np.empty((len(ht), 3))
                for k in np.unique(tex_id[textured]):
                    s = tex_id[textured] == k
                    sub[s] = sample_texture(mesh.textures[k], uv[s])
                albedo[textured] = mesh.tri_kd[th[textured]] * sub
        nrm = scene.normals[th]
        flip = np.einsum("ij,ij->i", nrm, dirs[h]) > 0
        nrm[flip] *= -1.0
        key = KEY_LIGHT / np.linalg.norm(KEY_LIGHT)
        fill = FILL_LIGHT / np.linalg.norm(FILL_LIGHT)
        shade = 0.35 + 0.55 * np.clip(nrm @ key, 0, None) + 0.2 * np.clip(nrm @ fill, 0, None)
        rgb[h] = np.clip(albedo * shade[:, None] * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return rgb.reshape(height, width, 3), depth.reshape(height, width), label.reshape(height, width)
