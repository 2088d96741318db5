"""``sparseart view OUT/``: an interactive 3-D page (viser) of what ``sparseart run`` wrote.

What it reads from ``OUT/`` (see docs/viewer.md):

* ``articulation.json`` (required): the joints -- axis, origin, angle / distance, parent, and the
  axis 1-sigma ``uncertainty.axis_deg``.
* the part geometry, per link (``base``, ``part_<id>``; :func:`sparseart.io.urdf.link_name`), the
  first that exists: ``meshes/<link>.obj`` (a triangle mesh), ``meshes/<link>.ply`` (the points
  ``--urdf`` writes), else that part's points of ``start_parts.ply`` (``--ply``). Files under
  ``meshes/`` are in the link frame of :mod:`sparseart.io.urdf` (origin at the joint ``origin``,
  axes parallel to the root frame, joint position 0 = START state); they are shifted by the link
  origin into the root frame on loading.
* ``start_parts.ply`` / ``end_parts.ply`` (optional): the observed points of both states, drawn
  where they were observed and coloured by part.

Frames and units: everything is drawn in the result's frame (``frame`` of articulation.json) and
its units; the scene's up direction is -y for the OpenCV ``camera`` frame and +z for a ``world``
frame (the Z-up world of rendered scenes) unless given. A joint's slider value ``q`` is degrees
(revolute) or frame units (prismatic), 0 = START, the fitted angle / distance = END. A part's pose
is its parent's pose composed with its own motion: ``T_part(q) = T_parent(q) @ T_joint(q_part)``,
each a (4, 4) transform of root-frame START coordinates
(:func:`sparseart.geometry.transforms.transform_from_revolute` / ``transform_from_prismatic``).

The loading half (:func:`load_view_data`, :func:`part_poses`) needs no viser; :func:`start_viewer`
imports it (the ``view`` extra). Bad input raises :class:`~sparseart.types.SceneError` with one line
naming the file.
"""
from __future__ import annotations

import contextlib
import io
import math
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sparseart.geometry.transforms import apply_transform, transform_from_prismatic, transform_from_revolute
from sparseart.io.articulation import SCHEMA
from sparseart.io.ply import part_colour, part_colours
from sparseart.io.urdf import link_name
from sparseart.io.validate import is_number, load_json_file, number, one_line
from sparseart.types import SceneError

if TYPE_CHECKING:
    import trimesh
    import viser

#: Points per drawn cloud at most (a deterministic subsample beyond): keeps the page responsive.
MAX_POINTS = 250_000
#: How far the sliders reach beyond the observed states, as a share of the observed motion.
BEYOND = 0.5
#: Observed points are drawn in their part's colour blended towards white (this much colour).
OBSERVED_TINT = 0.45
#: Widest uncertainty cone drawn (half-angle, degrees); a wider 1-sigma is drawn at this width.
MAX_CONE_DEG = 80.0
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


# ---------------------------------------------------------------------- poses


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


def _subsample(count: int, limit: int = MAX_POINTS) -> np.ndarray:
    if count <= limit:
        return np.arange(count)
    return np.sort(np.random.default_rng(0).choice(count, limit, replace=False))


def _rgb8(colours: np.ndarray | tuple[float, float, float]) -> np.ndarray:
    return np.clip(np.round(np.asarray(colours, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def _wxyz_position(transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial.transform import Rotation

    xyzw = Rotation.from_matrix(transform[:3, :3]).as_quat()
    return np.array([xyzw[3], *xyzw[:3]]), transform[:3, 3].copy()


def cone_mesh(apex: np.ndarray, direction: np.ndarray, half_angle_deg: float, height: float,
              sections: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """A cone (trimesh.creation.cone) with its apex at ``apex`` (3,) opening along ``direction``
    (3,) with ``half_angle_deg`` and ``height``: (vertices (V, 3) float64, faces (F, 3) int)."""
    import trimesh
    from scipy.spatial.transform import Rotation

    angle = min(max(half_angle_deg, 0.0), MAX_CONE_DEG)
    cone = trimesh.creation.cone(radius=height * math.tan(math.radians(angle)), height=height, sections=sections)
    local = np.asarray(cone.vertices, dtype=np.float64) * [1.0, -1.0, -1.0] + [0.0, 0.0, height]  # apex at 0
    turn = Rotation.align_vectors(np.asarray(direction, dtype=np.float64)[None], [[0.0, 0.0, 1.0]])[0]
    return turn.apply(local) + apex, np.asarray(cone.faces, dtype=np.int64)


# ---------------------------------------------------------------------- the page


class Viewer:
    """A running viser page of one :class:`ViewData`. ``sliders`` (part id -> slider handle),
    ``part_nodes`` (part id -> scene frame whose pose is the part's pose) and :meth:`set_joint`
    are the server-side API (tests, scripts); :meth:`close` stops the server."""

    def __init__(self, data: ViewData, server: "viser.ViserServer") -> None:
        self.data = data
        self.server = server
        self.sliders: dict[int, Any] = {}
        self.part_nodes: dict[int, Any] = {}
        self.joint_nodes: dict[int, Any] = {}
        self.values: dict[int, float] = {part: 0.0 for part in data.joints}

    @property
    def url(self) -> str:
        """The page's address (``0.0.0.0`` / ``::`` shown as this machine's loopback address)."""
        host = {"0.0.0.0": "127.0.0.1", "": "127.0.0.1", "::": "::1"}.get(self.server.get_host(), self.server.get_host())
        return f"http://{f'[{host}]' if ':' in host else host}:{self.server.get_port()}/"

    def set_joint(self, part: int, value: float) -> None:
        """Move joint ``part`` to ``value`` (degrees / frame units) as its slider would."""
        self.sliders[part].value = float(value)
        self._update(part, float(value))

    def poses(self) -> dict[int, np.ndarray]:
        """(4, 4) pose of every part at the current slider values (:func:`part_poses`)."""
        return part_poses(self.data, self.values)

    def _update(self, part: int, value: float) -> None:
        self.values[part] = value
        poses = self.poses()
        with self.server.atomic():
            for node_part, node in self.part_nodes.items():
                node.wxyz, node.position = _wxyz_position(poses[node_part])
            for joint_part, node in self.joint_nodes.items():
                node.wxyz, node.position = _wxyz_position(poses[self.data.joints[joint_part].parent])

    def close(self) -> None:
        """Stop the server (open pages lose their connection)."""
        self.server.stop()


def _summary(data: ViewData) -> str:
    frame = data.frame
    lines = [f"**{data.out_dir.name or data.out_dir}** · frame {frame.get('kind', '?')}, "
             f"units {frame.get('units', '?')}", ""]
    sources = sorted({g.source for g in data.geometry.values()})
    names = {"mesh": "meshes/*.obj", "points": "meshes/*.ply (points)", "labelled": "start_parts.ply"}
    lines.append("parts from " + ", ".join(names[s] for s in sources) + "; cones: axis 1σ")
    return "\n".join(lines)


def _joint_text(joint: JointView) -> str:
    unit = "°" if joint.type == "revolute" else ""
    end = joint.end_value()
    sigma = joint.amount_sigma
    if sigma is not None and joint.type == "revolute":
        sigma = math.degrees(sigma)
    amount = "unknown" if end is None else f"{end:.4g}{unit}" + ("" if sigma is None else f" ± {sigma:.2g}{unit}")
    axis = ", ".join(f"{v:+.3f}" for v in joint.axis)
    axis_sigma = "σ unknown" if joint.axis_sigma_deg is None else f"± {joint.axis_sigma_deg:.2g}°"
    confidence = "" if joint.confidence is None else f" · confidence {joint.confidence:.2f}"
    quantity = "angle" if joint.type == "revolute" else "distance"
    return f"axis [{axis}] {axis_sigma} · {quantity} at END {amount}{confidence}"


def start_viewer(data: ViewData, host: str = "127.0.0.1", port: int = 8080, up: str | None = None) -> Viewer:
    """Serve the page of ``data`` on ``host:port`` (0 = any free port; a busy port is passed over
    to the next) and return the :class:`Viewer`. ``up``: the scene's up direction (``+x`` ... ``-z``;
    None = -y for a camera frame, +z otherwise)."""
    import viser

    try:  # viser retries an address it cannot bind on every next port, for ever: check it first
        family, _, _, _, address = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
        socket.create_server(address[:2], family=family).close()
    except OSError as error:
        raise SceneError(one_line(f"--host {host}: cannot serve there ({error.strerror or error})")) from None
    with contextlib.redirect_stdout(io.StringIO()):  # viser's own address banner; serve() prints one line
        server = viser.ViserServer(host=host, port=port, verbose=False)
    viewer = Viewer(data, server)
    size, centre = data.size(), data.centre()
    up = up or ("-y" if data.frame.get("kind") == "camera" else "+z")
    server.scene.set_up_direction(up)
    up_vector = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0),
                 "+z": (0, 0, 1), "-z": (0, 0, -1)}[up]
    server.initial_camera.look_at = centre
    server.initial_camera.up = up_vector
    server.initial_camera.position = centre + _view_direction(data, np.asarray(up_vector, float)) * 1.1 * size
    point_size = size / 250.0
    gui = server.gui
    gui.add_markdown(_summary(data))
    show_parts = gui.add_checkbox("part geometry", True)
    by_part = gui.add_checkbox("part colours", True, hint="off: the meshes' / points' own colours")
    show_observed = {state: gui.add_checkbox(f"observed {state} points", True, disabled=state not in data.observed)
                     for state in ("start", "end")}
    show_axes = gui.add_checkbox("axes and 1σ cones", True)

    for state, cloud in data.observed.items():
        keep = _subsample(len(cloud.points))
        pale = OBSERVED_TINT * part_colours(cloud.part[keep]) + (1.0 - OBSERVED_TINT)  # ghosts beside the parts
        node = server.scene.add_point_cloud(
            f"/observed/{state}", cloud.points[keep], _rgb8(pale), point_size=0.6 * point_size,
            point_shape="circle" if state == "start" else "diamond", precision="float32")
        show_observed[state].on_update(lambda _, node=node, box=show_observed[state]: setattr(node, "visible", box.value))

    coloured: list[tuple[Any, Any]] = []  # (part-coloured node, own-coloured node or None)
    for part, geometry in data.geometry.items():
        viewer.part_nodes[part] = server.scene.add_frame(f"/part_{part}", show_axes=False)
        if len(geometry.points) == 0:  # e.g. an empty link PLY: nothing to draw
            continue
        colour = _rgb8(part_colour(part))
        own = None
        if geometry.faces is not None:
            flat = server.scene.add_mesh_simple(f"/part_{part}/part_colour", geometry.points, geometry.faces,
                                                color=tuple(int(c) for c in colour), side="double")
            if geometry.mesh is not None and geometry.colours is not None:
                own = server.scene.add_mesh_trimesh(f"/part_{part}/own_colour", geometry.mesh, visible=False)
        else:
            keep = _subsample(len(geometry.points))
            flat = server.scene.add_point_cloud(f"/part_{part}/part_colour", geometry.points[keep], colour,
                                                point_size=point_size * 1.3, precision="float32")
            if geometry.colours is not None:
                own = server.scene.add_point_cloud(f"/part_{part}/own_colour", geometry.points[keep],
                                                   _rgb8(geometry.colours[keep]), point_size=point_size * 1.3,
                                                   precision="float32", visible=False)
        coloured.append((flat, own))

    def recolour(_=None) -> None:
        for flat, own in coloured:
            flat.visible = show_parts.value and (by_part.value or own is None)
            if own is not None:
                own.visible = show_parts.value and not by_part.value

    show_parts.on_update(recolour)
    by_part.on_update(recolour)

    for part, joint in sorted(data.joints.items()):
        node = server.scene.add_frame(f"/joint_{part}", show_axes=False)
        viewer.joint_nodes[part] = node
        colour = _rgb8(part_colour(part))
        half = 0.6 * size
        ends = np.stack([joint.origin - half * joint.axis, joint.origin + half * joint.axis])[None]
        server.scene.add_arrows(f"/joint_{part}/axis", ends, colour, shaft_radius=size / 300.0,
                                head_radius=size / 80.0, head_length=size / 30.0)
        if joint.axis_sigma_deg is not None:
            for sign, name in ((1.0, "cone_plus"), (-1.0, "cone_minus")):
                vertices, faces = cone_mesh(joint.origin, sign * joint.axis, joint.axis_sigma_deg, 0.45 * size)
                server.scene.add_mesh_simple(f"/joint_{part}/{name}", vertices, faces,
                                             color=tuple(int(c) for c in colour), opacity=0.35, side="double",
                                             cast_shadow=False, receive_shadow=False)
        with gui.add_folder(f"{link_name(part)} · {joint.type}"):
            gui.add_markdown(_joint_text(joint))
            low, high, step = slider_range(joint, size)
            end = joint.end_value()
            marks = ((0.0, "start"),) + (() if end is None else ((end, "end"),))
            slider = gui.add_slider("angle (deg)" if joint.type == "revolute" else "distance", low, high, step, 0.0,
                                    marks=marks)
        slider.on_update(lambda _, part=part, slider=slider: viewer._update(part, float(slider.value)))
        viewer.sliders[part] = slider

    def toggle_axes(_=None) -> None:
        for node in viewer.joint_nodes.values():
            node.visible = show_axes.value

    show_axes.on_update(toggle_axes)
    return viewer


def _view_direction(data: ViewData, up: np.ndarray) -> np.ndarray:
    """Unit direction from the object's centre to the first camera: the side the movable parts move
    towards (a door swings and a drawer slides towards whoever opens it), turned 30 degrees about
    ``up`` to show depth and raised 40 degrees; else from the static part towards the movable ones;
    else a fixed diagonal (z-up: from +x -y; the y-down camera frame: from the camera's side)."""
    ends = {part: joint.end_value() or 0.0 for part, joint in data.joints.items()}
    poses = part_poses(data, ends)
    movable = {p: g.points.mean(0) for p, g in data.geometry.items() if p != 0 and len(g.points)}
    horizontal = sum((apply_transform(poses[p], c[None])[0] - c for p, c in movable.items()), np.zeros(3))
    horizontal = horizontal - (horizontal @ up) * up
    static = data.geometry.get(0)
    if np.linalg.norm(horizontal) < 1e-6 * data.size() and static is not None and len(static.points) and movable:
        horizontal = np.mean(list(movable.values()), axis=0) - static.points.mean(0)
        horizontal = horizontal - (horizontal @ up) * up
    if np.linalg.norm(horizontal) < 1e-6 * data.size():
        helper = np.array([1.0, -1.0, -1.0])
        horizontal = helper - (helper @ up) * up
    from scipy.spatial.transform import Rotation

    horizontal = Rotation.from_rotvec(up * math.radians(-30.0)).apply(horizontal / np.linalg.norm(horizontal))
    direction = math.cos(math.radians(40)) * horizontal + math.sin(math.radians(40)) * up
    return direction / np.linalg.norm(direction)


def serve(data: ViewData, host: str = "127.0.0.1", port: int = 8080, seconds: float | None = None,
          up: str | None = None) -> int:
    """``sparseart view``: serve the page of ``data`` (:func:`load_view_data`), print its address;
    run until Ctrl-C (or for ``seconds``, then stop). Returns 0."""
    viewer = start_viewer(data, host=host, port=port, up=up)
    print(f"sparseart view: {viewer.url} (Ctrl-C to stop)", flush=True)
    try:
        if seconds is None:
            while True:
                time.sleep(3600)
        time.sleep(max(seconds, 0.0))
    except KeyboardInterrupt:
        pass
    finally:
        viewer.close()
    return 0


__all__ = ["JointView", "ObservedCloud", "PartGeometry", "ViewData", "Viewer", "cone_mesh",
           "load_view_data", "part_poses", "serve", "slider_range", "start_viewer"]
