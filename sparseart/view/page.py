"""The viewer's page: a viser server drawing a :class:`~sparseart.view.data.ViewData` -- the parts,
the observed points of both states, each joint's axis with its 1-sigma cone, a slider per joint.

Drawn in the result's frame and units; the scene's up direction is -y for the OpenCV ``camera``
frame and +z for a ``world`` frame (the Z-up world of rendered scenes) unless given. viser is
imported only inside :func:`start_viewer` (the ``view`` extra).
"""
from __future__ import annotations

import contextlib
import io
import math
import socket
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from sparseart.geometry.transforms import apply_transform
from sparseart.io.ply import part_colour, part_colours
from sparseart.sim.links import link_name
from sparseart.io.validate import one_line
from sparseart.types import SceneError
from sparseart.view.data import JointView, ViewData, part_poses, slider_range

if TYPE_CHECKING:
    import viser

#: Points per drawn cloud at most (a deterministic subsample beyond): keeps the page responsive.
MAX_POINTS = 250_000
#: Observed points are drawn in their part's colour blended towards white (this much colour).
OBSERVED_TINT = 0.45
#: Widest uncertainty cone drawn (half-angle, degrees); a wider 1-sigma is drawn at this width.
MAX_CONE_DEG = 80.0


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
        host = self.server.get_host()
        host = {"0.0.0.0": "127.0.0.1", "": "127.0.0.1", "::": "::1"}.get(host, host)
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
        box = show_observed[state]
        box.on_update(lambda _, node=node, box=box: setattr(node, "visible", box.value))

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
