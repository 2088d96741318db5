"""The one link/joint description the URDF, MJCF and USD writers all read, so the same
articulation gives the same motion in every format.

Frames and conventions (shared by every export; also in docs/output.md):

* Root frame = the result's frame (world frame of a posed scene, else the OpenCV frame of
  ``start/rgb/000.png``); lengths in the result's units (metres for RGB-D input), angles in radians
  (USD: degrees, as UsdPhysics requires).
* Every link frame is parallel to the root frame. ``base`` (part 0) sits at the root origin; a
  movable part's link frame sits at its joint origin (revolute: a point on the axis; prismatic:
  the part centre at start). Meshes are stored in their link frame.
* Joint position 0 = the START state; the fitted end value (``angle`` radians / ``distance``)
  is the END state. Axis sign: a positive joint value turns the child right-handedly about
  ``axis`` (revolute) or moves it along ``+axis`` (prismatic), ``axis`` being the fitted unit axis
  in the root frame, written unchanged. Limits span both observed states:
  ``[min(0, end), max(0, end)]``. Effort and velocity limits are placeholders (images do not
  measure them): ``PLACEHOLDER_EFFORT`` / ``PLACEHOLDER_VELOCITY`` (N or N m; m/s or rad/s).
"""
from __future__ import annotations

import json
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sparseart.sim.links import PLACEHOLDER_EFFORT, PLACEHOLDER_VELOCITY, link_name
from sparseart.types import Articulation

__all__ = ["PLACEHOLDER_EFFORT", "PLACEHOLDER_VELOCITY", "SimLink", "SimJoint", "SimModel", "build_model",
           "write_meshes", "obj_text"]


@dataclass
class SimLink:
    """One rigid link.

    origin: (3,) float64 position of the link frame in the root frame (axes parallel to the root).
    vertices / faces / colors: the fused visual surface in the link frame ((V, 3) float64,
    (F, 3) int64, (V, 3) float64 RGB in [0, 1]). hulls: convex collision pieces in the link frame.
    mass (kg for metres), com (3,) link frame, inertia (3, 3) about the com, link axes.
    surface: method, seen share, points and views of the fusion (:class:`~sparseart.sim.surfaces.PartSurface`).
    """

    name: str
    part_id: int
    origin: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    hulls: list[tuple[np.ndarray, np.ndarray]]
    mass: float
    com: np.ndarray
    inertia: np.ndarray
    surface: dict = field(default_factory=dict)


@dataclass
class SimJoint:
    """One joint. offset: (3,) child link origin in the parent link frame. axis: (3,) unit, root
    (= every link's) axes. end: the fitted end value (radians | units); lower/upper: the limits."""

    name: str
    type: str
    parent: str
    child: str
    offset: np.ndarray
    axis: np.ndarray
    end: float
    lower: float
    upper: float


@dataclass
class SimModel:
    """Links (``base`` first, parents before children) and joints of an exportable object.
    seconds: wall time of each build step (surfaces, collision)."""

    name: str
    links: list[SimLink]
    joints: list[SimJoint]
    frame_kind: str
    frame_reference: str
    units: str
    density: float
    diagonal: float
    seconds: dict[str, float] = field(default_factory=dict)
    written_to: set[str] = field(default_factory=set)   # folders write_meshes already filled

    def link(self, name: str) -> SimLink:
        return next(link for link in self.links if link.name == name)

    def header(self) -> str:
        """The conventions line every export writes as a comment."""
        return (f"sparseart export: root frame = {self.frame_kind} frame ({self.frame_reference}); units = "
                f"{self.units} (angles radians; USD limits degrees); link frames parallel to the root, at "
                f"each joint origin; joint position 0 = start state, the fitted end value = end state; "
                f"axis sign: a positive value turns right-handed about the written axis / slides along "
                f"+axis; mass from the collision pieces at density {self.density:g} per cubic unit; "
                f"effort {PLACEHOLDER_EFFORT:g} and velocity {PLACEHOLDER_VELOCITY:g} are placeholders")


def _joint_values(result: Articulation) -> dict[int, tuple[np.ndarray, np.ndarray, float]]:
    values = {}
    for part, joint in result.joints:
        origin = np.asarray(joint.origin, dtype=np.float64)
        axis = np.asarray(joint.axis, dtype=np.float64)
        amount = joint.angle if joint.type == "revolute" else joint.distance
        quantity = "angle" if joint.type == "revolute" else "distance"
        if not (np.all(np.isfinite(origin)) and np.all(np.isfinite(axis)) and np.linalg.norm(axis) > 0):
            raise ValueError(f"part {part.spec.id} has a non-finite axis or origin")
        if amount is None or not np.isfinite(amount):
            raise ValueError(f"part {part.spec.id} has no finite {quantity}")
        values[part.spec.id] = (origin, axis / np.linalg.norm(axis), float(amount))
    return values


def build_model(result: Articulation, name: str = "object", seed: int = 0) -> SimModel:
    """Fuse the part surfaces, decompose them for collision, weigh them and lay out the links
    and joints (see the module docstring). Raises ValueError for a joint with non-finite numbers
    or a result without labelled clouds."""
    from sparseart.sim.physics import DENSITY, part_body
    from sparseart.sim.surfaces import fuse_parts, object_diagonal

    values = _joint_values(result)
    began = time.perf_counter()
    surfaces = fuse_parts(result)
    seconds = {"surfaces": time.perf_counter() - began}
    began = time.perf_counter()
    frame_origin = {0: np.zeros(3), **{part_id: origin for part_id, (origin, _, _) in values.items()}}
    links = []
    for part_id, surface in surfaces.items():
        origin = frame_origin[part_id]
        vertices = surface.vertices - origin
        body = part_body(vertices, surface.faces, seed=seed)
        links.append(SimLink(link_name(part_id), part_id, origin, vertices, surface.faces, surface.colors,
                             body.hulls, body.mass, body.com, body.inertia,
                             {"method": surface.method, "seen_share": surface.seen_share, "points": surface.points,
                              "views": surface.views, "triangles": int(len(surface.faces))}))
    _carve_parents(links, result, frame_origin, density=DENSITY)
    seconds["collision"] = time.perf_counter() - began
    joints = []
    for part, _ in result.joints:
        part_id = part.spec.id
        parent = part.spec.parent if part.spec.parent in frame_origin else 0
        origin, axis, amount = values[part_id]
        joints.append(SimJoint(f"joint_{part_id}", part.joint.type, link_name(parent), link_name(part_id),
                               origin - frame_origin[parent], axis, amount, min(0.0, amount), max(0.0, amount)))
    order = _parents_first(links, joints)
    return SimModel(name, order, joints, result.frame_kind, result.frame_reference, result.units, DENSITY,
                    object_diagonal(result), seconds)


def _carve_parents(links: list[SimLink], result: Articulation, frame_origin: dict[int, np.ndarray],
                   density: float) -> None:
    """Leave each child's rest box free in its parent's collision pieces
    (:func:`sparseart.sim.physics.carve`) and weigh the parent again, in place."""
    from sparseart.sim.physics import carve, mass_properties

    by_id = {link.part_id: link for link in links}
    for part, _ in result.joints:
        parent_id = part.spec.parent if part.spec.parent in frame_origin else 0
        child, parent = by_id.get(part.spec.id), by_id.get(parent_id)
        if child is None or parent is None or not child.hulls:
            continue
        rest = np.concatenate([v for v, _ in child.hulls]) + child.origin - parent.origin
        carved = carve(parent.hulls, rest)
        if carved:
            parent.hulls = carved
            mass, com, inertia = mass_properties(carved, density)
            if np.isfinite(mass) and mass > 0:
                parent.mass, parent.com, parent.inertia = mass, com, inertia


def _parents_first(links: list[SimLink], joints: list[SimJoint]) -> list[SimLink]:
    parent_of = {j.child: j.parent for j in joints}

    def depth(name: str) -> int:
        return 0 if name not in parent_of else 1 + depth(parent_of[name])

    return sorted(links, key=lambda link: (depth(link.name), link.part_id))


def obj_text(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None, comment: str = "") -> str:
    """A Wavefront OBJ (``v x y z [r g b]`` with colours in [0, 1], 1-based ``f``), float64 kept
    to 9 significant digits."""
    lines = [f"# {comment}"] if comment else []
    if colors is None:
        lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in vertices]
    else:
        lines += [f"v {x:.9g} {y:.9g} {z:.9g} {r:.4f} {g:.4f} {b:.4f}"
                  for (x, y, z), (r, g, b) in zip(vertices, np.clip(colors, 0.0, 1.0))]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    return "\n".join(lines) + "\n"


def visual_path(link: SimLink) -> str:
    """Path of a link's visual OBJ, relative to the export folder."""
    return f"meshes/{link.name}.obj"


def collision_paths(link: SimLink) -> list[str]:
    """Paths of a link's convex collision OBJs, relative to the export folder."""
    return [f"meshes/collision/{link.name}_{k}.obj" for k in range(len(link.hulls))]


def write_xml_export(result: Articulation, out_dir: str | Path, file_name: str, model: SimModel | None,
                     name: str, tree_of: Callable[[SimModel], ET.ElementTree], prolog: str = "") -> Path:
    """The XML exports' common steps (URDF, MJCF): the model (built here when not given), its
    meshes (:func:`write_meshes`), then ``out_dir/<file_name>`` atomically: ``prolog``, the
    model's header as a comment, the tree. Returns the written path."""
    from sparseart.io.scene import write_bytes_atomic

    out_dir = Path(out_dir)
    model = model or build_model(result, name=name)
    tree = tree_of(model)
    write_meshes(model, out_dir)
    payload = prolog + "<!-- " + model.header() + " -->\n" + ET.tostring(tree.getroot(), encoding="unicode") + "\n"
    path = out_dir / file_name
    write_bytes_atomic(path, payload.encode())
    return path


def write_meshes(model: SimModel, out_dir: str | Path) -> list[Path]:
    """Write each link's visual ``meshes/<link>.obj`` (coloured, link frame), its convex pieces
    ``meshes/collision/<link>_<k>.obj`` and ``meshes/summary.json`` (:func:`write_summary`),
    each atomically; once per folder (the exports share them). Returns the written paths."""
    from sparseart.io.scene import write_bytes_atomic

    out_dir = Path(out_dir)
    key = str(out_dir.resolve())
    if key in model.written_to:
        return []
    written = []
    for link in model.links:
        note = f"{link.name}: link frame (root-parallel, origin {link.origin.tolist()} in the root frame), {model.units}"
        path = out_dir / visual_path(link)
        write_bytes_atomic(path, obj_text(link.vertices, link.faces, link.colors, note).encode())
        written.append(path)
        for (vertices, faces), relative in zip(link.hulls, collision_paths(link)):
            write_bytes_atomic(out_dir / relative, obj_text(vertices, faces, None, note + ", convex piece").encode())
            written.append(out_dir / relative)
    written.append(write_summary(model, out_dir))
    model.written_to.add(key)
    return written


def write_summary(model: SimModel, out_dir: str | Path) -> Path:
    """Write ``meshes/summary.json``: units, frame, density, object diagonal, the seconds of each
    build and export step, and per link the fusion method, seen share, points per state, views,
    triangles, collision pieces and mass. Returns its path."""
    from sparseart.io.scene import write_json_atomic

    summary = {"units": model.units, "frame": model.frame_kind, "density": model.density,
               "object_diagonal": model.diagonal, "seconds": model.seconds,
               "links": {link.name: {**link.surface, "collision_pieces": len(link.hulls), "mass": link.mass}
                         for link in model.links}}
    path = Path(out_dir) / "meshes" / "summary.json"
    write_json_atomic(path, json.loads(json.dumps(summary)))
    return path
