"""URDF export of an :class:`~sparseart.types.Articulation`: a base link plus one link per movable
part, joints spanning the observed states, part point clouds as visuals.

Frames: the URDF root link ``base`` is the result's frame (world frame of a posed scene, else the
OpenCV frame of ``start/rgb/000.png``); lengths are the result's units (metres for RGB-D input).
Every link frame is parallel to the root frame. A movable part's link frame sits at its joint
``origin`` (revolute: a point on the axis; prismatic: the part centre at start) and joint position
0 is the START state: the end state is ``angle`` (radians) / ``distance`` along ``axis``. Limits
span both observed states: revolute ``[min(0, angle), max(0, angle)]``, prismatic likewise.
Visuals: each part's start points, expressed in its link frame, as ``meshes/<link>.ply`` (a
vertex-only PLY with colours; referenced by a relative path). Collision geometry is omitted.
``effort`` and ``velocity`` limits are placeholders (1.0): images do not measure them.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from sparseart.io.ply import write_ply
from sparseart.io.scene import write_bytes_atomic
from sparseart.types import Articulation

PLACEHOLDER_EFFORT = 1.0
PLACEHOLDER_VELOCITY = 1.0


def _fmt(values) -> str:
    return " ".join(f"{float(v):.9g}" for v in np.atleast_1d(np.asarray(values, dtype=np.float64)))


def link_name(part_id: int) -> str:
    """``base`` for the static part 0, ``part_<id>`` otherwise."""
    return "base" if part_id == 0 else f"part_{part_id}"


def urdf_tree(result: Articulation, mesh_dir: str = "meshes", name: str = "sparseart_object",
              with_visuals: bool = True) -> ET.ElementTree:
    """The URDF document (no files written). Parts whose parent has no link (or whose joint failed)
    are attached to ``base``; movable parts without a joint get no link (they did not move
    measurably). Raises ValueError when a joint holds non-finite numbers."""
    robot = ET.Element("robot", name=name)
    joints = {part.spec.id: (part, joint) for part, joint in result.joints}
    frame_origin: dict[int, np.ndarray] = {0: np.zeros(3)}
    for part_id, (_, joint) in joints.items():
        origin = np.asarray(joint.origin, dtype=np.float64)
        if not np.all(np.isfinite(origin)) or not np.all(np.isfinite(joint.axis)):
            raise ValueError(f"--urdf: part {part_id} has a non-finite axis or origin")
        frame_origin[part_id] = origin

    def add_link(part_id: int) -> None:
        link = ET.SubElement(robot, "link", name=link_name(part_id))
        if with_visuals:
            visual = ET.SubElement(link, "visual")
            ET.SubElement(visual, "origin", xyz="0 0 0", rpy="0 0 0")
            geometry = ET.SubElement(visual, "geometry")
            ET.SubElement(geometry, "mesh", filename=f"{mesh_dir}/{link_name(part_id)}.ply")

    add_link(0)
    for part_id, (part, joint) in joints.items():
        parent = part.spec.parent if part.spec.parent in frame_origin else 0
        add_link(part_id)
        element = ET.SubElement(robot, "joint", name=f"joint_{part_id}", type=joint.type)
        ET.SubElement(element, "parent", link=link_name(parent))
        ET.SubElement(element, "child", link=link_name(part_id))
        ET.SubElement(element, "origin", xyz=_fmt(frame_origin[part_id] - frame_origin[parent]), rpy="0 0 0")
        axis = np.asarray(joint.axis, dtype=np.float64)
        ET.SubElement(element, "axis", xyz=_fmt(axis / np.linalg.norm(axis)))
        amount = joint.angle if joint.type == "revolute" else joint.distance
        if amount is None or not np.isfinite(amount):
            quantity = "angle" if joint.type == "revolute" else "distance"
            raise ValueError(f"--urdf: part {part_id} has no finite {quantity}")
        ET.SubElement(element, "limit", lower=_fmt(min(0.0, amount)), upper=_fmt(max(0.0, amount)),
                      effort=_fmt(PLACEHOLDER_EFFORT), velocity=_fmt(PLACEHOLDER_VELOCITY))
    ET.indent(robot)
    return ET.ElementTree(robot)


def write_urdf(result: Articulation, out_dir: str | Path, name: str = "sparseart_object") -> Path:
    """Write ``out_dir/<name>.urdf`` and ``out_dir/meshes/<link>.ply`` (each part's start points in
    its link frame; the base link gets the static points, unassigned points are left out).
    Files are written atomically, the URDF last. Returns the URDF path."""
    out_dir = Path(out_dir)
    tree = urdf_tree(result, name=name, with_visuals=result.start_cloud is not None and result.labels is not None)
    if result.start_cloud is not None and result.labels is not None:
        cloud, part_of = result.start_cloud, result.labels.start_part
        for link in tree.getroot().iter("link"):
            part_id = 0 if link.get("name") == "base" else int(link.get("name").split("_")[1])
            origin = np.zeros(3)
            for part, joint in result.joints:
                if part.spec.id == part_id:
                    origin = np.asarray(joint.origin, dtype=np.float64)
            keep = part_of == part_id
            write_ply(out_dir / "meshes" / f"{link.get('name')}.ply", cloud.points[keep] - origin,
                      cloud.colors[keep])
    comment = (f"<!-- sparseart export: frame {result.frame_kind} ({result.frame_reference}), units "
               f"{result.units}; joint position 0 = start state -->\n")
    payload = ('<?xml version="1.0"?>\n' + comment + ET.tostring(tree.getroot(), encoding="unicode") + "\n")
    path = out_dir / f"{name}.urdf"
    write_bytes_atomic(path, payload.encode())
    return path
