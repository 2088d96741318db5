"""URDF export of an :class:`~sparseart.types.Articulation`: a base link plus one link per movable
part, joints spanning the observed states, fused part meshes (OBJ) as visuals, convex pieces as
collision and inertia from them (built by :mod:`sparseart.sim.model`; the conventions below are
shared by the MJCF and USD exports).

Frames: the URDF root link ``base`` is the result's frame (world frame of a posed scene, else the
OpenCV frame of ``start/rgb/000.png``); lengths are the result's units (metres for RGB-D input).
Every link frame is parallel to the root frame. A movable part's link frame sits at its joint
``origin`` (revolute: a point on the axis; prismatic: the part centre at start) and joint position
0 is the START state: the end state is ``angle`` (radians) / ``distance`` along ``axis``. Limits
span both observed states: revolute ``[min(0, angle), max(0, angle)]``, prismatic likewise.
Visuals: each part's fused surface in its link frame, ``meshes/<link>.obj`` (vertex colours;
referenced by a relative path); collision: its coacd convex pieces ``meshes/collision/<link>_<k>.obj``;
inertial: mass and inertia of the pieces at a stated density (:mod:`sparseart.sim.physics`).
``effort`` and ``velocity`` limits are placeholders (1.0): images do not measure them.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sparseart.sim.links import PLACEHOLDER_EFFORT, PLACEHOLDER_VELOCITY
from sparseart.types import Articulation

if TYPE_CHECKING:
    from sparseart.sim.model import SimModel

def _fmt(values) -> str:
    return " ".join(f"{float(v):.9g}" for v in np.atleast_1d(np.asarray(values, dtype=np.float64)))


def urdf_tree(model: "SimModel") -> ET.ElementTree:
    """The URDF document of a :class:`~sparseart.sim.model.SimModel` (no files written): per link a
    visual (``meshes/<link>.obj``), one collision element per convex piece
    (``meshes/collision/<link>_<k>.obj``) and an inertial (mass, centre of mass, inertia tensor
    about it); per joint its origin (child link origin in the parent link frame), unit axis and
    limits spanning both observed states."""
    from sparseart.sim.model import collision_paths, visual_path

    robot = ET.Element("robot", name=model.name)
    for link in model.links:
        element = ET.SubElement(robot, "link", name=link.name)
        inertial = ET.SubElement(element, "inertial")
        ET.SubElement(inertial, "origin", xyz=_fmt(link.com), rpy="0 0 0")
        ET.SubElement(inertial, "mass", value=_fmt(link.mass))
        i = link.inertia
        ET.SubElement(inertial, "inertia", ixx=_fmt(i[0, 0]), ixy=_fmt(i[0, 1]), ixz=_fmt(i[0, 2]),
                      iyy=_fmt(i[1, 1]), iyz=_fmt(i[1, 2]), izz=_fmt(i[2, 2]))
        visual = ET.SubElement(element, "visual")
        ET.SubElement(visual, "origin", xyz="0 0 0", rpy="0 0 0")
        ET.SubElement(ET.SubElement(visual, "geometry"), "mesh", filename=visual_path(link))
        for path in collision_paths(link):
            collision = ET.SubElement(element, "collision")
            ET.SubElement(collision, "origin", xyz="0 0 0", rpy="0 0 0")
            ET.SubElement(ET.SubElement(collision, "geometry"), "mesh", filename=path)
    for joint in model.joints:
        element = ET.SubElement(robot, "joint", name=joint.name, type=joint.type)
        ET.SubElement(element, "parent", link=joint.parent)
        ET.SubElement(element, "child", link=joint.child)
        ET.SubElement(element, "origin", xyz=_fmt(joint.offset), rpy="0 0 0")
        ET.SubElement(element, "axis", xyz=_fmt(joint.axis))
        ET.SubElement(element, "limit", lower=_fmt(joint.lower), upper=_fmt(joint.upper),
                      effort=_fmt(PLACEHOLDER_EFFORT), velocity=_fmt(PLACEHOLDER_VELOCITY))
    ET.indent(robot)
    return ET.ElementTree(robot)


def write_urdf(result: Articulation, out_dir: str | Path, name: str = "object",
               model: "SimModel | None" = None) -> Path:
    """Write ``out_dir/<name>.urdf`` with the meshes it references (``meshes/<link>.obj`` in each
    link frame, ``meshes/collision/<link>_<k>.obj``, ``meshes/summary.json``; see
    :func:`sparseart.sim.model.write_meshes`). ``model``: an already built
    :class:`~sparseart.sim.model.SimModel` (else built here: surfaces, coacd, mass; seconds).
    Files are written atomically, the URDF last. Returns the URDF path.

    Raises:
        ValueError: a joint holds non-finite numbers, or the result has no labelled clouds.
    """
    from sparseart.sim.model import write_xml_export

    return write_xml_export(result, out_dir, f"{name}.urdf", model, name, urdf_tree, prolog='<?xml version="1.0"?>\n')
