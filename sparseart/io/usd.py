"""USD export with UsdPhysics joints (``usd-core``'s ``pxr``): ``<name>.usda``, self-contained.

Same links, frames, units, axis sign and limits as the URDF (:mod:`sparseart.sim.model`), written
the way UsdPhysics needs them:

* ``/object`` (default prim, ``PhysicsArticulationRootAPI``) holds one ``Xform`` per link as
  siblings (UsdPhysics rigid bodies are not nested), each translated to its link origin in the
  root frame, no rotation, with ``PhysicsRigidBodyAPI`` and ``PhysicsMassAPI`` (mass, centre of
  mass, principal inertia and axes), its visual ``Mesh`` (vertex ``displayColor``) and one
  ``PhysicsCollisionAPI`` mesh per convex piece (``convexHull`` approximation, purpose guide).
* ``base`` is fixed to the world by a ``PhysicsFixedJoint`` without ``body0``.
* Each joint is a ``PhysicsRevoluteJoint`` / ``PhysicsPrismaticJoint`` with ``axis = "X"``: a
  UsdPhysics axis is a token, so the joint frame is rotated onto the fitted axis instead --
  ``localRot0`` (and ``localRot1``, both link frames being parallel) is the rotation taking +X to
  the fitted unit axis, never a flipped one; ``localPos0`` is the child origin in the parent frame,
  ``localPos1`` is 0. A positive joint value turns right-handedly about / slides along the fitted
  axis, as in the URDF and MJCF. Revolute limits are in DEGREES (UsdPhysics), prismatic in units.
* Stage metadata: ``metersPerUnit`` 1 for metres (else 1 and the unit named in the comment),
  ``kilogramsPerUnit`` 1, ``upAxis`` Z (the root frame is the result's; for a camera frame the
  up direction is unknown and Z is only USD's required choice).
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sparseart.io.scene import write_bytes_atomic
from sparseart.types import Articulation

if TYPE_CHECKING:
    from sparseart.sim.model import SimModel


def axis_rotation(axis: np.ndarray) -> np.ndarray:
    """(3, 3) float64 proper rotation whose first column is the unit ``axis`` (takes +X to it)."""
    x = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    helper = np.array([0.0, 0.0, 1.0]) if abs(x[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    y = np.cross(helper, x)
    y /= np.linalg.norm(y)
    return np.stack([x, y, np.cross(x, y)], axis=1)


def _quat(rotation: np.ndarray):
    from pxr import Gf
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    return Gf.Quatf(float(w), Gf.Vec3f(float(x), float(y), float(z)))


def _mesh(stage, path: str, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None):
    from pxr import UsdGeom, Vt

    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(vertices, dtype=np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces, dtype=np.int32).ravel()))
    mesh.CreateSubdivisionSchemeAttr("none")
    if colors is not None:
        primvar = mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex)
        primvar.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(np.clip(colors, 0, 1), dtype=np.float32)))
    return mesh


def usd_stage(model: "SimModel"):
    """An in-memory ``Usd.Stage`` of a :class:`~sparseart.sim.model.SimModel` (see the module docstring)."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics

    stage = Usd.Stage.CreateInMemory()
    stage.SetMetadata("comment", model.header())
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, f"/{model.name}")
    stage.SetDefaultPrim(root.GetPrim())
    UsdPhysics.ArticulationRootAPI.Apply(root.GetPrim())
    for link in model.links:
        path = f"/{model.name}/{link.name}"
        xform = UsdGeom.Xform.Define(stage, path)
        xform.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*map(float, link.origin)))
        UsdPhysics.RigidBodyAPI.Apply(xform.GetPrim())
        mass = UsdPhysics.MassAPI.Apply(xform.GetPrim())
        mass.CreateMassAttr(float(link.mass))
        mass.CreateCenterOfMassAttr(Gf.Vec3f(*map(float, link.com)))
        moments, axes = np.linalg.eigh(link.inertia)
        if np.linalg.det(axes) < 0:
            axes[:, 2] *= -1.0
        mass.CreateDiagonalInertiaAttr(Gf.Vec3f(*map(float, np.maximum(moments, 0.0))))
        mass.CreatePrincipalAxesAttr(_quat(axes))
        _mesh(stage, f"{path}/visual", link.vertices, link.faces, link.colors)
        for k, (vertices, faces) in enumerate(link.hulls):
            piece = _mesh(stage, f"{path}/collision_{k}", vertices, faces)
            piece.CreatePurposeAttr(UsdGeom.Tokens.guide)
            UsdPhysics.CollisionAPI.Apply(piece.GetPrim())
            UsdPhysics.MeshCollisionAPI.Apply(piece.GetPrim()).CreateApproximationAttr(UsdPhysics.Tokens.convexHull)
    UsdGeom.Scope.Define(stage, f"/{model.name}/joints")
    fixed = UsdPhysics.FixedJoint.Define(stage, f"/{model.name}/joints/base_fixed")
    fixed.CreateBody1Rel().SetTargets([Sdf.Path(f"/{model.name}/base")])
    fixed.CreateLocalPos0Attr(Gf.Vec3f(0.0, 0.0, 0.0))
    fixed.CreateLocalPos1Attr(Gf.Vec3f(0.0, 0.0, 0.0))
    for joint in model.joints:
        kind = UsdPhysics.RevoluteJoint if joint.type == "revolute" else UsdPhysics.PrismaticJoint
        element = kind.Define(stage, f"/{model.name}/joints/{joint.name}")
        element.CreateBody0Rel().SetTargets([Sdf.Path(f"/{model.name}/{joint.parent}")])
        element.CreateBody1Rel().SetTargets([Sdf.Path(f"/{model.name}/{joint.child}")])
        element.CreateAxisAttr(UsdPhysics.Tokens.x)
        rotation = _quat(axis_rotation(joint.axis))
        element.CreateLocalPos0Attr(Gf.Vec3f(*map(float, joint.offset)))
        element.CreateLocalRot0Attr(rotation)
        element.CreateLocalPos1Attr(Gf.Vec3f(0.0, 0.0, 0.0))
        element.CreateLocalRot1Attr(rotation)
        scale = 180.0 / np.pi if joint.type == "revolute" else 1.0
        element.CreateLowerLimitAttr(float(joint.lower * scale))
        element.CreateUpperLimitAttr(float(joint.upper * scale))
        element.GetPrim().SetCustomDataByKey("sparseart_end_value", float(joint.end * scale))
    return stage


def write_usd(result: Articulation, out_dir: str | Path, name: str = "object",
              model: "SimModel | None" = None) -> Path:
    """Write ``out_dir/<name>.usda`` (meshes inside the file), atomically. ``model`` built here
    when not given. Raises ValueError for a joint with non-finite numbers or no labelled clouds."""
    from sparseart.sim.model import build_model

    model = model or build_model(result, name=name)
    stage = usd_stage(model)
    path = Path(out_dir) / f"{name}.usda"
    write_bytes_atomic(path, stage.GetRootLayer().ExportToString().encode())
    return path
