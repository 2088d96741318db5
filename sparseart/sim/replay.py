"""Load an export in a real simulator, set a joint, read back where the links are -- the check that
an export moves the way the images showed (tests, ``sparseart bench --geometry``).

* MuJoCo (:class:`MujocoExport`): ``MjModel.from_xml_path``; the joint's ``qpos`` set and
  ``mj_forward`` run; each link's visual mesh as MuJoCo stores it (its own re-centred vertices)
  placed by the geom's world pose.
* PyBullet (:class:`PybulletExport`): ``loadURDF`` in a DIRECT client with a fixed base,
  ``resetJointState``; each link's OBJ vertices placed by the link's world frame
  (``getLinkState(computeForwardKinematics=True)``).
* USD (:class:`UsdExport`): the stage opened with ``pxr``; the UsdPhysics joint (``body0``,
  ``localPos0/Rot0``, ``axis`` token, ``localPos1/Rot1``) applied to the child as PhysX would, with
  the value in the joint's own units (degrees for revolute); the visual mesh points read from the
  stage.

Each ``links(values)`` returns ``{link: ((V, 3) float64 world vertices, (F, 3) int64 triangles)}`` and ``{joint: (3,) world axis}`` at the
given joint values (absent joints at 0). :func:`check_export` compares a moved part with the
observed end-state points and measures how deep a part sinks into its parent at rest.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sparseart.geometry.transforms import apply_transform

LANDING_BOUND = 0.03   # mean distance observed end points -> moved mesh, in object diagonals
SINK_MARGIN = 0.01     # deepest collision overlap of a part with its parent at rest, in object diagonals
                       # (the parent's pieces leave the child's rest box free, sparseart.sim.physics.carve;
                       # what remains is the simulators' contact margin, ~0.2 % measured)


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, triangles (F, 3) int64) of an OBJ as written by the exports."""
    lines = path.read_text().splitlines()
    vertices = [line.split()[1:4] for line in lines if line.startswith("v ")]
    faces = [[int(k.split("/")[0]) - 1 for k in line.split()[1:4]] for line in lines if line.startswith("f ")]
    return (np.asarray(vertices, dtype=np.float64).reshape(-1, 3), np.asarray(faces, dtype=np.int64).reshape(-1, 3))


class MujocoExport:
    """An MJCF export loaded in MuJoCo (``MjModel.from_xml_path``)."""

    def __init__(self, xml_path: str | Path) -> None:
        import mujoco

        self.mujoco = mujoco
        self.model = mujoco.MjModel.from_xml_path(str(xml_path))
        self.data = mujoco.MjData(self.model)

    def links(self, values: dict[str, float]) -> tuple[dict, dict]:
        """World visual meshes of every body and world joint axes with ``values`` set (others 0)."""
        model, data = self.model, self.data
        data.qpos[:] = 0.0
        for name, value in values.items():
            data.qpos[model.jnt_qposadr[model.joint(name).id]] = value
        self.mujoco.mj_forward(model, data)
        links, axes = {}, {}
        for body in range(1, model.nbody):
            name = model.body(body).name
            geom = model.geom(f"{name}_visual").id
            mesh = model.geom_dataid[geom]
            start, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
            local = np.asarray(model.mesh_vert[start:start + count], dtype=np.float64)
            first, faces = model.mesh_faceadr[mesh], model.mesh_facenum[mesh]
            links[name] = (local @ data.geom_xmat[geom].reshape(3, 3).T + data.geom_xpos[geom],
                           np.asarray(model.mesh_face[first:first + faces], dtype=np.int64))
        for joint in range(model.njnt):
            axes[model.joint(joint).name] = np.asarray(data.xaxis[joint], dtype=np.float64).copy()
        return links, axes

    def sink(self, child: str, parent: str) -> float:
        """Deepest overlap (>= 0, units) of any collision piece of ``child`` with any of
        ``parent`` at rest (all joints 0), by MuJoCo's signed geom distance."""
        model, data = self.model, self.data
        data.qpos[:] = 0.0
        self.mujoco.mj_forward(model, data)
        pieces = {name: [g for g in range(model.ngeom) if model.geom(g).name.startswith(f"{name}_collision_")]
                  for name in (child, parent)}
        deepest, fromto = 0.0, np.zeros(6)
        for a in pieces[child]:
            for b in pieces[parent]:
                deepest = max(deepest, -float(self.mujoco.mj_geomDistance(model, data, a, b, 1.0, fromto)))
        return deepest

    def close(self) -> None:
        pass


class PybulletExport:
    """A URDF export loaded in PyBullet (a DIRECT client, fixed base, inertia from the file)."""

    def __init__(self, urdf_path: str | Path) -> None:
        import pybullet

        self.pb = pybullet
        self.folder = Path(urdf_path).parent
        self.client = pybullet.connect(pybullet.DIRECT)
        self.body = pybullet.loadURDF(str(urdf_path), useFixedBase=True, flags=pybullet.URDF_USE_INERTIA_FROM_FILE,
                                      physicsClientId=self.client)
        self.joints = {}
        self.link_index = {"base": -1}
        for j in range(pybullet.getNumJoints(self.body, physicsClientId=self.client)):
            info = pybullet.getJointInfo(self.body, j, physicsClientId=self.client)
            self.joints[info[1].decode()] = (j, info[12].decode(), np.asarray(info[13], dtype=np.float64))
            self.link_index[info[12].decode()] = j
        self.meshes = {link: _read_obj(self.folder / "meshes" / f"{link}.obj") for link in self.link_index}

    def links(self, values: dict[str, float]) -> tuple[dict, dict]:
        """World visual meshes of every link and world joint axes with ``values`` set (others 0)."""
        pb, client = self.pb, self.client
        for name, (j, _, _) in self.joints.items():
            pb.resetJointState(self.body, j, values.get(name, 0.0), physicsClientId=client)
        position, orientation = pb.getBasePositionAndOrientation(self.body, physicsClientId=client)
        frames = {"base": (position, orientation)}
        inertial = {}
        for name, (j, link, _) in self.joints.items():
            state = pb.getLinkState(self.body, j, computeForwardKinematics=True, physicsClientId=client)
            frames[link] = (state[4], state[5])
            inertial[link] = state[1]
        links, axes = {}, {}
        for link, (position, orientation) in frames.items():
            rotation = np.asarray(pb.getMatrixFromQuaternion(orientation), dtype=np.float64).reshape(3, 3)
            local, faces = self.meshes[link]
            links[link] = (local @ rotation.T + np.asarray(position, dtype=np.float64), faces)
        for name, (j, link, axis) in self.joints.items():
            # pybullet gives the axis in the child's inertial (principal-axes) frame
            rotation = np.asarray(pb.getMatrixFromQuaternion(inertial[link]), dtype=np.float64).reshape(3, 3)
            axes[name] = rotation @ axis
        return links, axes

    def sink(self, child: str, parent: str) -> float:
        """Deepest overlap (>= 0, units) of ``child``'s collision shapes with ``parent``'s at rest
        (``getClosestPoints``)."""
        self.links({})
        points = self.pb.getClosestPoints(self.body, self.body, distance=0.0, linkIndexA=self.link_index[child],
                                          linkIndexB=self.link_index[parent], physicsClientId=self.client)
        return max([0.0, *(-float(p[8]) for p in points)])

    def close(self) -> None:
        self.pb.disconnect(self.client)


def _gf_matrix(position, rotation) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    transform = np.eye(4)
    w, (x, y, z) = rotation.GetReal(), rotation.GetImaginary()
    transform[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    transform[:3, 3] = np.asarray(position, dtype=np.float64)
    return transform


class UsdExport:
    """A USD export opened with ``pxr`` (no simulator: the UsdPhysics joints applied as PhysX would)."""

    def __init__(self, usd_path: str | Path) -> None:
        from pxr import Usd

        self.stage = Usd.Stage.Open(str(usd_path))

    def links(self, values: dict[str, float]) -> tuple[dict, dict]:
        return usd_links(self.stage, values)

    def close(self) -> None:
        pass


def usd_links(stage, values: dict[str, float]) -> tuple[dict, dict]:
    """World vertices of each link's visual mesh and world joint axes at ``values`` (radians or
    units, converted to the joint's USD units), from the UsdPhysics joints of an open stage."""
    from pxr import UsdGeom, UsdPhysics

    cache = UsdGeom.XformCache()
    rest = {}
    for prim in stage.Traverse():
        if prim.HasAPI(UsdPhysics.RigidBodyAPI):
            rest[str(prim.GetPath())] = np.asarray(cache.GetLocalToWorldTransform(prim), dtype=np.float64).T
    pose = dict(rest)
    axes = {}
    joints = [UsdPhysics.Joint(p) for p in stage.Traverse() if p.IsA(UsdPhysics.RevoluteJoint) or p.IsA(UsdPhysics.PrismaticJoint)]
    # parents before children: a child's pose needs its parent's
    pending = list(joints)
    while pending:
        for joint in list(pending):
            body0 = str(joint.GetBody0Rel().GetTargets()[0])
            if any(str(j.GetBody1Rel().GetTargets()[0]) == body0 for j in pending):
                continue
            pending.remove(joint)
            prim = joint.GetPrim()
            revolute = prim.IsA(UsdPhysics.RevoluteJoint)
            typed = UsdPhysics.RevoluteJoint(prim) if revolute else UsdPhysics.PrismaticJoint(prim)
            axis_index = "XYZ".index(typed.GetAxisAttr().Get())
            frame0 = _gf_matrix(joint.GetLocalPos0Attr().Get(), joint.GetLocalRot0Attr().Get())
            frame1 = _gf_matrix(joint.GetLocalPos1Attr().Get(), joint.GetLocalRot1Attr().Get())
            value = values.get(prim.GetName(), 0.0)
            motion = np.eye(4)
            if revolute:
                from scipy.spatial.transform import Rotation

                usd_value = np.degrees(value)           # the joint's USD position: degrees
                rotation_vector = np.zeros(3)
                rotation_vector[axis_index] = np.radians(usd_value)
                motion[:3, :3] = Rotation.from_rotvec(rotation_vector).as_matrix()
            else:
                motion[axis_index, 3] = value
            joint_world = pose[body0] @ frame0
            child = str(joint.GetBody1Rel().GetTargets()[0])
            pose[child] = joint_world @ motion @ np.linalg.inv(frame1)
            axes[prim.GetName()] = joint_world[:3, axis_index].copy()
    links = {}
    for path, transform in pose.items():
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"{path}/visual"))
        local = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
        faces = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
        links[path.rsplit("/", 1)[1]] = (apply_transform(transform, local), faces)
    return links, axes


SURFACE_SAMPLES = 20000


def _landing(mesh: tuple[np.ndarray, np.ndarray], observed: np.ndarray) -> tuple[float, float]:
    """(mean observed -> moved surface distance, symmetric Chamfer (mean of both directions' means))."""
    import trimesh
    from scipy.spatial import cKDTree

    moved = trimesh.sample.sample_surface(trimesh.Trimesh(*mesh, process=False), SURFACE_SAMPLES, seed=0)[0]
    to_mesh = cKDTree(moved).query(observed)[0]
    to_points = cKDTree(observed).query(moved)[0]
    return float(to_mesh.mean()), float(0.5 * (to_mesh.mean() + to_points.mean()))


def check_export(result, out_dir: str | Path, name: str = "object", formats=("mjcf", "urdf", "usd")) -> list[dict]:
    """For each joint and format: drive the joints from 0 to their fitted end values in the
    simulator (all at once: the end state) and compare the moved part's mesh with the observed end-state points of the part.

    Returns rows {joint, part, format, landing (mean end point -> moved mesh, units), chamfer
    (symmetric, units), landing_rel / chamfer_rel (in object diagonals), rest_landing_rel (the
    same at 0: the bound must separate the two), sink / sink_rel (deepest overlap with the parent
    at rest; mjcf and urdf), axis_dot (world axis after loading . fitted axis)}.
    """
    from sparseart.sim.surfaces import object_diagonal

    out_dir = Path(out_dir)
    diagonal = object_diagonal(result)
    loaders = {"mjcf": lambda: MujocoExport(out_dir / f"{name}.xml"),
               "urdf": lambda: PybulletExport(out_dir / f"{name}.urdf"),
               "usd": lambda: UsdExport(out_dir / f"{name}.usda")}
    end_values = {f"joint_{part.spec.id}": float(joint.angle if joint.type == "revolute" else joint.distance)
                  for part, joint in result.joints}
    rows = []
    for fmt in formats:
        loaded = loaders[fmt]()
        rest_links, _ = loaded.links({})
        links, axes = loaded.links(end_values)     # every joint at its end value: the end state
        for part, joint in result.joints:
            part_id = part.spec.id
            joint_name, link = f"joint_{part_id}", f"part_{part_id}"
            end_value = end_values[joint_name]
            observed = result.end_cloud.points[result.labels.end_part == part_id]
            landing, chamfer = _landing(links[link], observed)
            rest_landing, _ = _landing(rest_links[link], observed)
            parent = "base" if part.spec.parent in (None, 0) else f"part_{part.spec.parent}"
            if parent != "base" and parent not in links:
                parent = "base"
            sink = loaded.sink(link, parent) if hasattr(loaded, "sink") else None
            axis = np.asarray(joint.axis, dtype=np.float64) / np.linalg.norm(joint.axis)
            rows.append({"joint": joint_name, "part": part_id, "format": fmt, "type": joint.type,
                         "end_value": end_value, "landing": landing, "chamfer": chamfer,
                         "landing_rel": landing / diagonal, "chamfer_rel": chamfer / diagonal,
                         "rest_landing_rel": rest_landing / diagonal,
                         "sink": sink, "sink_rel": None if sink is None else sink / diagonal,
                         "axis_dot": float(np.dot(axes[joint_name] / np.linalg.norm(axes[joint_name]), axis))})
        loaded.close()
    return rows
