"""Reading a ``sparseart run`` output folder for the viewer, and the parts' poses at given slider
values (no viser needed here; :mod:`sparseart.view` says what is read and in which frames).

A joint's slider value ``q`` is degrees (revolute) or frame units (prismatic), 0 = START, the
fitted angle / distance = END. A part's pose is its parent's pose composed with its own motion:
``T_part(q) = T_parent(q) @ T_joint(q_part)``, each a (4, 4) transform of root-frame START
coordinates (:func:`sparseart.geometry.transforms.transform_from_revolute` /
``transform_from_prismatic``). Bad input raises :class:`~sparseart.types.SceneError` with one line
naming the file.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sparseart.geometry.transforms import transform_from_prismatic, transform_from_revolute
from sparseart.io.articulation import SCHEMA
from sparseart.io.ply import part_colours
from sparseart.sim.links import link_name
from sparseart.io.validate import is_number, load_json_file, number, one_line
from sparseart.types import SceneError

if TYPE_CHECKING:
    import trimesh

#: How far the sliders reach beyond the observed states, as a share of the observed motion.
BEYOND = 0.5
#: Slider reach when a joint has no finite angle / distance: degrees, and shares of the object size.
UNKNOWN_ANGLE_DEG = 90.0
UNKNOWN_DISTANCE_SHARE = 0.5


def _fail(path: Path | str, problem: str) -> SceneError:
    return SceneError(one_line(f"{path}: {problem}"))


@dataclass
class JointView:
    """One joint of articulation.json. ``axis`` (3,) unit and ``origin`` (3,) are in the root frame
    at START; ``amount`` is the fitted START -> END angle (radians) or distance (frame units), None
    when not finite; ``axis_sigma_deg`` the axis 1-sigma in degrees (None: not stated)."""

    part: int
    parent: int
    type: str
    axis: np.ndarray
    origin: np.ndarray
    amount: float | None
    axis_sigma_deg: float | None
    amount_sigma: float | None
    confidence: float | None

    @property
    def link(self) -> str:
        """The URDF link of the part (:func:`sparseart.io.urdf.link_name`)."""
        return link_name(self.part)

    def transform(self, value: float) -> np.ndarray:
        """(4, 4) motion of the part at slider value ``value`` (degrees / frame units)."""
        if self.type == "revolute":
            return transform_from_revolute(self.axis, self.origin, math.radians(value))
        return transform_from_prismatic(self.axis, value)

    def end_value(self) -> float | None:
        """The END state in slider units (degrees / frame units), None when unknown."""
        if self.amount is None:
            return None
        return math.degrees(self.amount) if self.type == "revolute" else self.amount


@dataclass
class PartGeometry:
    """What is drawn for one part. ``points`` (V, 3) float64 in the root frame at START; ``faces``
    (F, 3) int for a mesh (None for points); ``colours`` (V, 3) in [0, 1], the file's own colours
    (None when it has none); ``mesh`` the loaded trimesh (root frame) for an OBJ, else None.
    ``source``: ``mesh`` (meshes/<link>.obj), ``points`` (meshes/<link>.ply) or ``labelled``
    (start_parts.ply)."""

    part: int
    source: str
    path: Path
    points: np.ndarray
    faces: np.ndarray | None = None
    colours: np.ndarray | None = None
    mesh: "trimesh.Trimesh | None" = None


@dataclass
class ObservedCloud:
    """A labelled cloud of one state: ``points`` (N, 3) float64 root frame, ``part`` (N,) int
    (-1 = unassigned)."""

    state: str
    path: Path
    points: np.ndarray
    part: np.ndarray


@dataclass
class ViewData:
    """Everything the viewer draws, read from one output folder."""

    out_dir: Path
    frame: dict[str, Any]
    part_ids: list[int]
    joints: dict[int, JointView]
    geometry: dict[int, PartGeometry]
    observed: dict[str, ObservedCloud] = field(default_factory=dict)

    def size(self) -> float:
        """Diagonal of the bounding box of everything drawn (frame units; 1.0 when empty)."""
        chunks = [g.points for g in self.geometry.values()] + [c.points for c in self.observed.values()]
        chunks = [c for c in chunks if len(c)]
        if not chunks:
            return 1.0
        points = np.concatenate(chunks)
        diagonal = float(np.linalg.norm(points.max(0) - points.min(0)))
        return diagonal if diagonal > 0 else 1.0

    def centre(self) -> np.ndarray:
        """Centre (3,) of the bounding box of the part geometry (origin when empty)."""
        chunks = [g.points for g in self.geometry.values() if len(g.points)]
        if not chunks:
            return np.zeros(3)
        points = np.concatenate(chunks)
        return (points.max(0) + points.min(0)) / 2.0


# ---------------------------------------------------------------------- reading OUT/


def _vector(value: Any, where: str, path: Path) -> np.ndarray:
    if not isinstance(value, list) or len(value) != 3:
        raise _fail(path, f"{where} must be a list of 3 numbers")
    return np.array([number(v, f"{where}[{k}]", path) for k, v in enumerate(value)])


def _optional(value: Any) -> float | None:
    return float(value) if is_number(value) and math.isfinite(float(value)) else None


def _read_joints(document: Any, path: Path) -> tuple[list[int], dict[int, JointView]]:
    if not isinstance(document, dict) or document.get("schema") != SCHEMA:
        raise _fail(path, f"not a {SCHEMA} document (its \"schema\" field differs)")
    parts, joints = document.get("parts", []), document.get("joints", [])
    if not isinstance(parts, list) or not isinstance(joints, list):
        raise _fail(path, "\"parts\" and \"joints\" must be lists")
    part_ids = sorted({0} | {int(number(p.get("id") if isinstance(p, dict) else None, f"parts[{k}].id", path))
                             for k, p in enumerate(parts)})
    views: dict[int, JointView] = {}
    for k, entry in enumerate(joints):
        where = f"joints[{k}]"
        if not isinstance(entry, dict):
            raise _fail(path, f"{where} must be an object")
        kind = entry.get("type")
        if kind not in ("revolute", "prismatic"):
            raise _fail(path, f"{where}.type must be revolute or prismatic, got {kind!r}"[:200])
        part = int(number(entry.get("part"), f"{where}.part", path, low=1))
        axis = _vector(entry.get("axis"), f"{where}.axis", path)
        if np.linalg.norm(axis) < 1e-12:
            raise _fail(path, f"{where}.axis is zero")
        uncertainty = entry.get("uncertainty") if isinstance(entry.get("uncertainty"), dict) else {}
        amount_key = "angle" if kind == "revolute" else "distance"
        views[part] = JointView(
            part=part, parent=int(_optional(entry.get("parent")) or 0), type=kind,
            axis=axis / np.linalg.norm(axis), origin=_vector(entry.get("origin"), f"{where}.origin", path),
            amount=_optional(entry.get(amount_key)), axis_sigma_deg=_optional(uncertainty.get("axis_deg")),
            amount_sigma=_optional(uncertainty.get(amount_key)), confidence=_optional(entry.get("confidence")))
        part_ids = sorted(set(part_ids) | {part})
    for joint in views.values():  # as the URDF does: a parent without a joint of its own is the base
        if joint.parent not in views or joint.parent == joint.part:
            joint.parent = 0
    return part_ids, views


def _read_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(points (N, 3) float64, colours (N, 3) in [0, 1] or None, part (N,) int or None) of a PLY."""
    import open3d as o3d

    from sparseart.io.validate import quiet_native_stderr

    if not path.is_file():
        raise _fail(path, "not a regular file")
    with quiet_native_stderr():
        cloud = o3d.t.io.read_point_cloud(str(path))
    if "positions" not in cloud.point:
        return np.zeros((0, 3)), None, None
    points = cloud.point["positions"].numpy().astype(np.float64)
    colours = part = None
    if "colors" in cloud.point:
        raw = cloud.point["colors"].numpy()
        colours = raw / 255.0 if raw.dtype == np.uint8 else raw.astype(np.float64)
    if "part" in cloud.point:
        part = cloud.point["part"].numpy().reshape(-1).astype(np.int64)
    if not np.all(np.isfinite(points)):
        raise _fail(path, "holds non-finite point coordinates")
    return points, colours, part


def _read_obj(path: Path, origin: np.ndarray, part: int) -> PartGeometry:
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as error:  # noqa: BLE001 - any parser failure is bad input, named in one line
        raise _fail(path, f"cannot be read as a mesh ({type(error).__name__}: {error})"[:300]) from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise _fail(path, "holds no triangle mesh")
    mesh.apply_translation(origin)
    colours, visual = None, mesh.visual
    if visual is not None and visual.kind == "texture":
        visual = visual.to_color()  # the texture sampled at the vertices
    if visual is not None and visual.kind in ("vertex", "face"):
        colours = np.asarray(visual.vertex_colors, dtype=np.float64)[:, :3] / 255.0
        if len(colours) != len(mesh.vertices):
            colours = None
    return PartGeometry(part, "mesh", path, np.asarray(mesh.vertices, dtype=np.float64),
                        np.asarray(mesh.faces, dtype=np.int64), colours, mesh)


def _read_observed(out_dir: Path) -> dict[str, ObservedCloud]:
    observed = {}
    for state in ("start", "end"):
        path = out_dir / f"{state}_parts.ply"
        if not path.exists():
            continue
        points, _, part = _read_ply(path)
        if part is None or len(part) != len(points):
            raise _fail(path, "has no \"part\" vertex property (expected the labelled cloud of --ply)")
        if len(points) == 0:
            raise _fail(path, "holds no points (unreadable or empty PLY)")
        observed[state] = ObservedCloud(state, path, points, part)
    return observed


def load_view_data(out_dir: str | Path) -> ViewData:
    """Read an output folder of ``sparseart run`` (see the module docstring).

    Raises:
        SceneError: ``articulation.json`` is missing or malformed, no part geometry exists
            (neither ``meshes/`` nor ``start_parts.ply``), or a file cannot be read.
    """
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise _fail(out_dir, "not a folder (expected the --out folder of sparseart run)")
    path = out_dir / "articulation.json"
    if not path.exists():
        raise _fail(path, "not found (expected the --out folder of sparseart run)")
    document = load_json_file(path)
    part_ids, joints = _read_joints(document, path)
    observed = _read_observed(out_dir)
    origins = {part: joints[part].origin if part in joints else np.zeros(3) for part in part_ids}
    geometry: dict[int, PartGeometry] = {}
    for part in part_ids:
        obj, ply = out_dir / "meshes" / f"{link_name(part)}.obj", out_dir / "meshes" / f"{link_name(part)}.ply"
        if obj.exists():
            geometry[part] = _read_obj(obj, origins[part], part)
        elif ply.exists():
            points, colours, _ = _read_ply(ply)
            geometry[part] = PartGeometry(part, "points", ply, points + origins[part], None, colours)
        elif "start" in observed:
            cloud = observed["start"]
            keep = cloud.part == part
            geometry[part] = PartGeometry(part, "labelled", cloud.path, cloud.points[keep], None,
                                          part_colours(cloud.part[keep]))
    if not geometry:
        raise _fail(out_dir / "start_parts.ply", "not found, nor meshes/<link>.obj|.ply: no part geometry to "
                    "show (run sparseart run with --ply or --urdf)")
    frame = document.get("frame") if isinstance(document.get("frame"), dict) else {}
    return ViewData(out_dir, frame, part_ids, joints, geometry, observed)


def part_poses(data: ViewData, values: dict[int, float]) -> dict[int, np.ndarray]:
    """(4, 4) pose of every part at the slider ``values`` (part id -> degrees / frame units; a
    missing joint is at 0 = START): the transform taking the part's root-frame START coordinates to
    where the joints put it, composed down the chain of parents."""
    poses: dict[int, np.ndarray] = {0: np.eye(4)}

    def pose(part: int, depth: int = 0) -> np.ndarray:
        if part not in poses:
            joint = data.joints.get(part)
            if joint is None or depth > len(data.joints):  # a part without a joint does not move
                poses[part] = np.eye(4)
            else:
                poses[part] = pose(joint.parent, depth + 1) @ joint.transform(values.get(part, 0.0))
        return poses[part]

    for part in data.part_ids:
        pose(part)
    return poses


def slider_range(joint: JointView, size: float) -> tuple[float, float, float]:
    """(low, high, step) of a joint's slider in its units: both observed states (0 and the END
    value) plus :data:`BEYOND` of the motion on either side; ``size`` (frame units) sets the reach
    of a prismatic joint whose distance is unknown."""
    end = joint.end_value()
    if end is None or end == 0.0:
        reach = UNKNOWN_ANGLE_DEG if joint.type == "revolute" else UNKNOWN_DISTANCE_SHARE * size
        low, high = -reach, reach
    else:
        low, high = min(0.0, end) - BEYOND * abs(end), max(0.0, end) + BEYOND * abs(end)
    if joint.type == "revolute":
        low, high = max(low, -360.0), min(high, 360.0)
    return low, high, (high - low) / 400.0
