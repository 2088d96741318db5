"""Minimal URDF reader and forward kinematics for PartNet-Mobility ``mobility.urdf`` files.

Conventions (checked against the 16 objects in ``../shared/data/partnet``):

* A joint's ``<origin xyz rpy>`` places the child link frame in the parent link frame; the joint
  motion happens in that child frame: revolute/continuous rotate about ``axis`` through the frame
  origin, prismatic translate along ``axis``. So ``T_child = T_parent @ O(xyz, rpy) @ M(q)``.
* ``rpy`` is URDF fixed-axis roll/pitch/yaw: ``R = Rz(yaw) Ry(pitch) Rx(roll)``
  (scipy ``Rotation.from_euler("xyz", rpy)``, lowercase = extrinsic).
* Visual ``<origin>`` places the mesh in its link frame. PartNet children carry
  ``xyz = -pivot`` so that all OBJ vertices live in one common object frame.
* The root joint ``base -> link`` carries ``rpy="1.5708 0 -1.5708"`` (Y-up mesh frame to Z-up
  world), so link world transforms from :meth:`URDFModel.fk` are in the Z-up world.

All geometry is float64; transforms are ``(4, 4)`` homogeneous matrices.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from sparseart.types import SceneError

MOVABLE_TYPES: tuple[str, ...] = ("revolute", "continuous", "prismatic")


def origin_matrix(xyz: np.ndarray | list[float], rpy: np.ndarray | list[float]) -> np.ndarray:
    """(4, 4) float64 transform of a URDF ``<origin xyz rpy>`` (rpy = fixed-axis roll, pitch, yaw)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", np.asarray(rpy, dtype=np.float64)).as_matrix()
    T[:3, 3] = np.asarray(xyz, dtype=np.float64)
    return T


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) float64 right-handed rotation by ``angle`` radians about unit ``axis`` (3,)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    return Rotation.from_rotvec(a * float(angle)).as_matrix()


@dataclass
class Visual:
    """One visual mesh of a link: ``filename`` relative to the URDF folder; origin in the link frame."""

    filename: str
    xyz: np.ndarray
    rpy: np.ndarray

    @property
    def transform(self) -> np.ndarray:
        """(4, 4) float64 mesh frame -> link frame."""
        return origin_matrix(self.xyz, self.rpy)


@dataclass
class Link:
    name: str
    visuals: list[Visual] = field(default_factory=list)


@dataclass
class Joint:
    """A URDF joint. ``axis`` (3,) unit float64 in the joint (child) frame; limits in radians or units.

    ``type`` is one of revolute, continuous, prismatic, fixed (floating/planar are read as fixed).
    ``lower``/``upper`` are None when the file gives no limit (e.g. continuous joints).
    """

    name: str
    type: str
    parent: str
    child: str
    xyz: np.ndarray
    rpy: np.ndarray
    axis: np.ndarray
    lower: float | None = None
    upper: float | None = None

    @property
    def movable(self) -> bool:
        return self.type in MOVABLE_TYPES

    @property
    def origin(self) -> np.ndarray:
        """(4, 4) float64 child frame at q=0 in the parent link frame."""
        return origin_matrix(self.xyz, self.rpy)

    def motion(self, q: float) -> np.ndarray:
        """(4, 4) float64 joint motion at value ``q`` (radians or units) in the joint frame."""
        M = np.eye(4)
        if self.type in ("revolute", "continuous"):
            M[:3, :3] = axis_angle_matrix(self.axis, q)
        elif self.type == "prismatic":
            M[:3, 3] = self.axis * float(q)
        return M


@dataclass
class URDFModel:
    """Kinematic tree of one object. ``links`` by name; ``joints`` in file order; ``root`` link name."""

    name: str
    links: dict[str, Link]
    joints: list[Joint]
    root: str
    base_dir: Path | None = None

    @property
    def movable_joints(self) -> list[Joint]:
        """Revolute, continuous and prismatic joints, in file order."""
        return [j for j in self.joints if j.movable]

    def joint(self, name: str) -> Joint:
        for j in self.joints:
            if j.name == name:
                return j
        raise KeyError(name)

    def _children(self) -> dict[str, list[Joint]]:
        out: dict[str, list[Joint]] = {n: [] for n in self.links}
        for j in self.joints:
            out.setdefault(j.parent, []).append(j)
        return out

    def fk(self, q: dict[str, float] | None = None) -> dict[str, np.ndarray]:
        """World transform (4, 4) float64 of every link for joint values ``q`` {joint name: value}.

        Missing movable joints are at 0. The world is the root link's frame (for PartNet the root is
        ``base`` and the world is Z-up thanks to the root joint's rpy).
        """
        q = q or {}
        children = self._children()
        out = {self.root: np.eye(4)}
        stack = [self.root]
        while stack:
            name = stack.pop()
            for j in children.get(name, []):
                T = out[name] @ j.origin
                if j.movable:
                    T = T @ j.motion(q.get(j.name, 0.0))
                out[j.child] = T
                stack.append(j.child)
        return out

    def joint_frames(self, q: dict[str, float] | None = None) -> dict[str, np.ndarray]:
        """World transform (4, 4) of each joint's frame *before* its own motion (parent @ origin)."""
        links = self.fk(q)
        return {j.name: links[j.parent] @ j.origin for j in self.joints}

    def part_groups(self) -> tuple[dict[str, int], list[Joint]]:
        """Rigid part groups: link name -> group index, and the movable joint of each group >= 1.

        Group 0 holds every link rigidly attached to the root (through fixed joints); each movable
        joint's child subtree (minus nested movable subtrees) is group ``1 + index`` in the
        returned joint list (file order).
        """
        movable = self.movable_joints
        gid = {j.name: i + 1 for i, j in enumerate(movable)}
        children = self._children()
        groups = {self.root: 0}
        stack = [self.root]
        while stack:
            name = stack.pop()
            for j in children.get(name, []):
                groups[j.child] = gid[j.name] if j.movable else groups[name]
                stack.append(j.child)
        return groups, movable


def _vec(elem: ET.Element | None, attr: str, default: str, path: Path) -> np.ndarray:
    text = default if elem is None else elem.get(attr, default)
    try:
        v = np.array([float(t) for t in text.split()], dtype=np.float64)
    except ValueError as exc:
        raise SceneError(f"{path}: bad {attr}={text!r}") from exc
    if v.shape != (3,):
        raise SceneError(f"{path}: {attr}={text!r} is not 3 numbers")
    return v


def parse_urdf(path: str | Path) -> URDFModel:
    """Parse a URDF file into a :class:`URDFModel`. Raises SceneError naming the file when bad."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: URDF file not found")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise SceneError(f"{path}: not valid XML ({exc})") from exc
    links: dict[str, Link] = {}
    for le in root.findall("link"):
        link = Link(le.get("name", ""))
        for ve in le.findall("visual"):
            me = ve.find("geometry/mesh")
            if me is None or not me.get("filename"):
                continue
            oe = ve.find("origin")
            link.visuals.append(Visual(me.get("filename"), _vec(oe, "xyz", "0 0 0", path),
                                       _vec(oe, "rpy", "0 0 0", path)))
        links[link.name] = link
    joints: list[Joint] = []
    for je in root.findall("joint"):
        jtype = je.get("type", "fixed")
        if jtype not in (*MOVABLE_TYPES, "fixed"):
            jtype = "fixed"
        pe, ce = je.find("parent"), je.find("child")
        if pe is None or ce is None:
            raise SceneError(f"{path}: joint {je.get('name')!r} lacks parent or child")
        oe, ae, le = je.find("origin"), je.find("axis"), je.find("limit")
        axis = _vec(ae, "xyz", "1 0 0", path)
        n = np.linalg.norm(axis)
        if jtype in MOVABLE_TYPES and n < 1e-12:
            raise SceneError(f"{path}: joint {je.get('name')!r} has a zero axis")
        axis = axis / n if n > 0 else np.array([1.0, 0.0, 0.0])
        lower = upper = None
        if le is not None and le.get("lower") is not None and le.get("upper") is not None:
            lower, upper = float(le.get("lower")), float(le.get("upper"))
        joints.append(Joint(je.get("name", f"joint_{len(joints)}"), jtype, pe.get("link"),
                            ce.get("link"), _vec(oe, "xyz", "0 0 0", path),
                            _vec(oe, "rpy", "0 0 0", path), axis, lower, upper))
    for j in joints:
        for ln in (j.parent, j.child):
            if ln not in links:
                raise SceneError(f"{path}: joint {j.name!r} names unknown link {ln!r}")
    child_names = {j.child for j in joints}
    roots = [n for n in links if n not in child_names]
    if len(roots) != 1:
        raise SceneError(f"{path}: expected one root link, found {roots}")
    return URDFModel(root.get("name", path.parent.name), links, joints, roots[0], path.parent)
