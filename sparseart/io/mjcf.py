"""MuJoCo (MJCF) export: ``<name>.xml`` beside the URDF's ``meshes/``.

Same links, frames, units, axis sign and limits as the URDF (:mod:`sparseart.sim.model`): body
``base`` is fixed to the world at the root origin (no joint); each part is a body nested in its
parent at ``pos`` = its link origin in the parent frame, no rotation, with a ``hinge`` (revolute)
or ``slide`` (prismatic) joint at the body origin along the fitted ``axis``; joint position 0 is
the start state. Angles are radians (``<compiler angle="radian">``). Each body has an explicit
``inertial`` (mass, centre of mass, full inertia tensor from the collision pieces), its visual mesh
(group 1, no contacts) and one collision geom per convex piece (group 3). MuJoCo excludes contacts
between a body and its parent by default, as URDF simulators do between a link and its parent.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import TYPE_CHECKING

from sparseart.io.urdf import _fmt
from sparseart.types import Articulation

if TYPE_CHECKING:
    from sparseart.sim.model import SimModel

MJCF_JOINT = {"revolute": "hinge", "prismatic": "slide"}


def mjcf_tree(model: "SimModel") -> ET.ElementTree:
    """The MJCF document of a :class:`~sparseart.sim.model.SimModel` (mesh files relative to the
    XML's folder: ``meshes/...``)."""
    from sparseart.sim.model import collision_paths, visual_path

    root = ET.Element("mujoco", model=model.name)
    ET.SubElement(root, "compiler", angle="radian", meshdir=".", autolimits="true", balanceinertia="true",
                  inertiafromgeom="false")
    asset = ET.SubElement(root, "asset")
    for link in model.links:
        # "shell" inertia: a fused visual surface is open, MuJoCo's volume inertia would reject it;
        # the body inertia is given explicitly anyway.
        ET.SubElement(asset, "mesh", name=f"{link.name}_visual", file=visual_path(link), inertia="shell")
        for k, path in enumerate(collision_paths(link)):
            ET.SubElement(asset, "mesh", name=f"{link.name}_collision_{k}", file=path)
    world = ET.SubElement(root, "worldbody")
    joint_of = {joint.child: joint for joint in model.joints}
    bodies = {}
    for link in model.links:
        joint = joint_of.get(link.name)
        parent = world if joint is None else bodies[joint.parent]
        body = ET.SubElement(parent, "body", name=link.name,
                             pos=_fmt(link.origin if joint is None else joint.offset))
        bodies[link.name] = body
        i = link.inertia
        ET.SubElement(body, "inertial", pos=_fmt(link.com), mass=_fmt(link.mass),
                      fullinertia=_fmt([i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]]))
        if joint is not None:
            ET.SubElement(body, "joint", name=joint.name, type=MJCF_JOINT[joint.type], pos="0 0 0",
                          axis=_fmt(joint.axis), range=_fmt([joint.lower, joint.upper]), limited="true",
                          actuatorfrcrange=_fmt([-_effort(), _effort()]))
        ET.SubElement(body, "geom", name=f"{link.name}_visual", type="mesh", mesh=f"{link.name}_visual",
                      contype="0", conaffinity="0", group="1", rgba="0.7 0.7 0.7 1")
        for k in range(len(link.hulls)):
            ET.SubElement(body, "geom", name=f"{link.name}_collision_{k}", type="mesh",
                          mesh=f"{link.name}_collision_{k}", group="3", rgba="0.3 0.6 0.9 0.3")
    ET.indent(root)
    return ET.ElementTree(root)


def _effort() -> float:
    from sparseart.sim.links import PLACEHOLDER_EFFORT

    return PLACEHOLDER_EFFORT


def write_mjcf(result: Articulation, out_dir: str | Path, name: str = "object",
               model: "SimModel | None" = None) -> Path:
    """Write ``out_dir/<name>.xml`` and the meshes it references (as :func:`sparseart.io.urdf.
    write_urdf` does; ``model`` built here when not given), atomically, the XML last.

    Raises:
        ValueError: a joint holds non-finite numbers, or the result has no labelled clouds.
    """
    from sparseart.sim.model import write_xml_export

    return write_xml_export(result, out_dir, f"{name}.xml", model, name, mjcf_tree)
