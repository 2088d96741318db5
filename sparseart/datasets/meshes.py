"""Coloured triangle meshes: a small OBJ/MTL reader (Kd colours + ``map_Kd`` textures) and the
"articulated object at joint values -> list of (mesh, mask label)" abstraction shared by the
PartNet and the procedural datasets.

A hand-written reader is used because open3d's OBJ loader merges materials and drops per-face
Kd colours of untextured materials. Meshes are float64; textures are float32 RGB in [0, 1].
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from sparseart.datasets.urdf import URDFModel, parse_urdf
from sparseart.types import SceneError

DEFAULT_KD = np.array([0.7, 0.7, 0.7])


@dataclass
class RenderMesh:
    """A triangle mesh with per-triangle appearance.

    vertices: (V, 3) float64 (frame given by context: file, link or world).
    triangles: (T, 3) int64 vertex indices.
    tri_colors: (T, 3) float64 RGB in [0, 1]: Kd times the texture at the triangle's UV centroid.
    tri_kd: (T, 3) float64 RGB Kd (multiplies the texture when sampled per hit).
    tri_uv: (T, 3, 2) float64 corner UVs (NaN when the triangle has none) or None.
    tri_tex: (T,) int64 index into ``textures`` (-1 = untextured) or None.
    textures: list of (H, W, 3) float32 RGB images in [0, 1] (OBJ ``v`` = 0 is the bottom row).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    tri_colors: np.ndarray
    tri_kd: np.ndarray | None = None
    tri_uv: np.ndarray | None = None
    tri_tex: np.ndarray | None = None
    textures: list[np.ndarray] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.tri_kd is None:
            self.tri_kd = self.tri_colors

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])

    def transformed(self, T: np.ndarray) -> "RenderMesh":
        """A copy with vertices mapped by the (4, 4) float64 rigid transform ``T``."""
        v = self.vertices @ T[:3, :3].T + T[:3, 3]
        return RenderMesh(v, self.triangles, self.tri_colors, self.tri_kd, self.tri_uv,
                          self.tri_tex, self.textures)

    @staticmethod
    def from_o3d(mesh, color: np.ndarray | tuple[float, float, float] | None = None) -> "RenderMesh":
        """From an open3d legacy TriangleMesh; ``color`` (3,) in [0, 1] or the mean vertex colour."""
        v = np.asarray(mesh.vertices, dtype=np.float64)
        t = np.asarray(mesh.triangles, dtype=np.int64)
        if color is None and mesh.has_vertex_colors():
            c = np.asarray(mesh.vertex_colors, dtype=np.float64)[t].mean(axis=1)
        else:
            c = np.tile(np.asarray(color if color is not None else DEFAULT_KD, float), (len(t), 1))
        return RenderMesh(v, t, c)

    def to_o3d(self):
        """An open3d legacy TriangleMesh with vertex colours averaged from the triangle colours."""
        from sparseart.geometry.o3d import open3d
        o3d = open3d()

        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices),
                                      o3d.utility.Vector3iVector(self.triangles.astype(np.int32)))
        vc = np.zeros_like(self.vertices)
        cnt = np.zeros(len(self.vertices))
        for k in range(3):
            np.add.at(vc, self.triangles[:, k], self.tri_colors)
            np.add.at(cnt, self.triangles[:, k], 1.0)
        m.vertex_colors = o3d.utility.Vector3dVector(vc / np.maximum(cnt, 1)[:, None])
        return m

    @staticmethod
    def concat(meshes: list["RenderMesh"]) -> "RenderMesh":
        """One mesh holding all triangles of ``meshes`` in order (texture lists merged)."""
        if not meshes:
            return RenderMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3)))
        textures: list[np.ndarray] = []
        tex_index: dict[int, int] = {}
        vs, ts, cs, kds, uvs, tis = [], [], [], [], [], []
        offset = 0
        for m in meshes:
            n = m.n_triangles
            vs.append(m.vertices)
            ts.append(m.triangles + offset)
            offset += len(m.vertices)
            cs.append(m.tri_colors)
            kds.append(m.tri_kd)
            uvs.append(m.tri_uv if m.tri_uv is not None else np.full((n, 3, 2), np.nan))
            remap = np.full(len(m.textures) + 1, -1, dtype=np.int64)
            for i, tex in enumerate(m.textures):
                if id(tex) not in tex_index:
                    tex_index[id(tex)] = len(textures)
                    textures.append(tex)
                remap[i] = tex_index[id(tex)]
            tt = m.tri_tex if m.tri_tex is not None else np.full(n, -1, dtype=np.int64)
            tis.append(remap[tt])  # -1 maps to the last entry, which is -1
        return RenderMesh(np.concatenate(vs), np.concatenate(ts), np.concatenate(cs),
                          np.concatenate(kds), np.concatenate(uvs), np.concatenate(tis), textures)


_TEXTURE_CACHE: dict[str, np.ndarray] = {}


def _load_texture(path: Path, owner: Path) -> np.ndarray:
    key = str(path.resolve())
    if key not in _TEXTURE_CACHE:
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise SceneError(f"{path}: texture referenced by {owner} is missing or unreadable")
        _TEXTURE_CACHE[key] = (img[:, :, ::-1].astype(np.float32) / 255.0).copy()
    return _TEXTURE_CACHE[key]


def _read_mtl(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray | None]]:
    """Material name -> (Kd (3,) float64, texture (H, W, 3) float32 or None)."""
    if not path.is_file():
        raise SceneError(f"{path}: material file not found")
    mats: dict[str, list] = {}
    cur = None
    for line in path.read_text(errors="replace").splitlines():
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "newmtl":
            cur = " ".join(tok[1:])
            mats[cur] = [DEFAULT_KD.copy(), None]
        elif cur is not None and tok[0] == "Kd" and len(tok) >= 4:
            mats[cur][0] = np.array([float(t) for t in tok[1:4]])
        elif cur is not None and tok[0] == "map_Kd" and len(tok) >= 2:
            mats[cur][1] = _load_texture(path.parent / tok[-1], path)
    return {k: (v[0], v[1]) for k, v in mats.items()}


def sample_texture(tex: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Nearest-neighbour, wrapping sample of (H, W, 3) ``tex`` at (N, 2) OBJ UVs -> (N, 3) float64."""
    h, w = tex.shape[:2]
    u = np.mod(uv[:, 0], 1.0)
    v = np.mod(uv[:, 1], 1.0)
    col = np.minimum((u * w).astype(np.int64), w - 1)
    row = np.minimum(((1.0 - v) * h).astype(np.int64), h - 1)
    return tex[row, col].astype(np.float64)


def read_obj(path: str | Path) -> RenderMesh:
    """Read a triangle/polygon OBJ with its MTL (Kd, map_Kd). Vertices in the file's frame."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: mesh file not found")
    verts: list[list[float]] = []
    uvs: list[list[float]] = []
    faces: list[tuple[list[int], list[int], str | None]] = []
    mats: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
    cur = None
    for line in path.read_text(errors="replace").splitlines():
        if not line or line[0] == "#":
            continue
        tok = line.split()
        if not tok:
            continue
        key = tok[0]
        if key == "v":
            verts.append([float(tok[1]), float(tok[2]), float(tok[3])])
        elif key == "vt":
            uvs.append([float(tok[1]), float(tok[2]) if len(tok) > 2 else 0.0])
        elif key == "f":
            vi, ti = [], []
            for c in tok[1:]:
                parts = c.split("/")
                a = int(parts[0])
                vi.append(a - 1 if a > 0 else len(verts) + a)
                if len(parts) > 1 and parts[1]:
                    b = int(parts[1])
                    ti.append(b - 1 if b > 0 else len(uvs) + b)
                else:
                    ti.append(-1)
            for k in range(1, len(vi) - 1):  # fan triangulation
                faces.append(([vi[0], vi[k], vi[k + 1]], [ti[0], ti[k], ti[k + 1]], cur))
        elif key == "usemtl":
            cur = " ".join(tok[1:])
        elif key == "mtllib":
            mats.update(_read_mtl(path.parent / " ".join(tok[1:])))
    V = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    if not faces:
        return RenderMesh(V, np.zeros((0, 3), np.int64), np.zeros((0, 3)))
    tri = np.array([f[0] for f in faces], dtype=np.int64)
    if tri.min() < 0 or tri.max() >= len(V):
        raise SceneError(f"{path}: face index out of range")
    tuv_idx = np.array([f[1] for f in faces], dtype=np.int64)
    UV = np.asarray(uvs, dtype=np.float64).reshape(-1, 2)
    tri_uv = np.full((len(tri), 3, 2), np.nan)
    ok = tuv_idx >= 0
    if len(UV):
        tri_uv[ok] = UV[np.clip(tuv_idx[ok], 0, len(UV) - 1)]
    textures: list[np.ndarray] = []
    tex_ids: dict[int, int] = {}
    kd = np.tile(DEFAULT_KD, (len(tri), 1))
    tri_tex = np.full(len(tri), -1, dtype=np.int64)
    names = np.array([f[2] or "" for f in faces], dtype=object)
    for name in set(names.tolist()):
        sel = names == name
        if name not in mats:
            continue
        k, tex = mats[name]
        kd[sel] = k
        if tex is not None:
            if id(tex) not in tex_ids:
                tex_ids[id(tex)] = len(textures)
                textures.append(tex)
            has_uv = sel & np.all(ok, axis=1)
            tri_tex[has_uv] = tex_ids[id(tex)]
    colors = kd.copy()
    for i, tex in enumerate(textures):
        sel = tri_tex == i
        colors[sel] = kd[sel] * sample_texture(tex, tri_uv[sel].mean(axis=1))
    return RenderMesh(V, tri, np.clip(colors, 0, 1), kd, tri_uv, tri_tex, textures)


@dataclass
class ArticulatedObject:
    """Kinematics plus appearance: ``link_meshes[name]`` is that link's mesh in its LINK frame."""

    name: str
    model: URDFModel
    link_meshes: dict[str, RenderMesh]

    def part_groups(self) -> tuple[dict[str, int], list]:
        """See :meth:`URDFModel.part_groups`; mask label of group g is ``g + 1``."""
        return self.model.part_groups()

    def posed_parts(self, q: dict[str, float]) -> list[tuple[RenderMesh, int]]:
        """World-frame meshes at joint values ``q``, one per part group, with mask label (1 + group)."""
        groups, movable = self.part_groups()
        world = self.model.fk(q)
        per_group: dict[int, list[RenderMesh]] = {}
        for name, mesh in self.link_meshes.items():
            if mesh.n_triangles:
                per_group.setdefault(groups[name], []).append(mesh.transformed(world[name]))
        return [(RenderMesh.concat(ms), g + 1) for g, ms in sorted(per_group.items())]


_OBJECT_CACHE: dict[str, ArticulatedObject] = {}


def load_link_meshes(model: URDFModel, base_dir: Path) -> dict[str, RenderMesh]:
    """Each link's visuals read and placed in the link frame (visual origin applied)."""
    out: dict[str, RenderMesh] = {}
    for name, link in model.links.items():
        parts = [read_obj(base_dir / v.filename).transformed(v.transform) for v in link.visuals]
        out[name] = RenderMesh.concat(parts)
    return out


def load_articulated_object(object_dir: str | Path) -> ArticulatedObject:
    """Load ``object_dir/mobility.urdf`` and its meshes (cached per resolved folder)."""
    object_dir = Path(object_dir)
    key = str(object_dir.resolve())
    if key not in _OBJECT_CACHE:
        model = parse_urdf(object_dir / "mobility.urdf")
        meshes = load_link_meshes(model, object_dir)
        if sum(m.n_triangles for m in meshes.values()) == 0:
            raise SceneError(f"{object_dir / 'mobility.urdf'}: no visual triangles")
        _OBJECT_CACHE[key] = ArticulatedObject(object_dir.name, model, meshes)
    return _OBJECT_CACHE[key]
