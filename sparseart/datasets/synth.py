"""A procedural articulated cabinet built from boxes: a static body (open front, shelf, side and
back panels), a door hinged about a vertical edge (revolute, +Z axis, opens toward -X) and a
drawer (prismatic, slides along -X). Units are metres; the world is Z-up with the front at -X
(like PartNet objects after their root rpy). Rendering shares the PartNet code path.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sparseart.datasets.meshes import ArticulatedObject, RenderMesh
from sparseart.datasets.partnet import render_articulated_scene
from sparseart.datasets.urdf import Joint, Link, URDFModel

WIDTH, DEPTH, HEIGHT, THICK = 0.60, 0.45, 0.80, 0.02
SHELF_Z = 0.32  # top of the drawer compartment


def box_mesh(lo: tuple[float, float, float], hi: tuple[float, float, float],
             color: tuple[float, float, float]) -> RenderMesh:
    """Axis-aligned box from corner ``lo`` to ``hi`` (metres) with one RGB colour in [0, 1]."""
    from sparseart.geometry.o3d import open3d
    o3d = open3d()

    lo_a, hi_a = np.asarray(lo, float), np.asarray(hi, float)
    size = hi_a - lo_a
    m = o3d.geometry.TriangleMesh.create_box(float(size[0]), float(size[1]), float(size[2]))
    m.translate(lo_a)
    return RenderMesh.from_o3d(m, color)


def _shade(rng: np.random.Generator, base: tuple[float, float, float]) -> tuple[float, float, float]:
    c = np.clip(np.asarray(base) * rng.uniform(0.8, 1.1) + rng.uniform(-0.04, 0.04, 3), 0, 1)
    return tuple(float(x) for x in c)


def build_cabinet(seed: int = 0) -> ArticulatedObject:
    """The procedural cabinet as an :class:`ArticulatedObject` (links "body", "door", "drawer";
    joints "door_hinge" revolute [0, pi/2] and "drawer_slide" prismatic [0, 0.35 m]).

    Link meshes are in their link frames; the body frame is the world frame. Colours vary
    slightly with ``seed``; geometry does not.
    """
    rng = np.random.default_rng(seed)
    w2, d2, t = WIDTH / 2, DEPTH / 2, THICK
    wood, dark, light = (0.55, 0.35, 0.2), (0.3, 0.22, 0.15), (0.85, 0.8, 0.7)
    body = [
        box_mesh((-d2, -w2, 0.0), (d2, -w2 + t, HEIGHT), _shade(rng, wood)),     # left side
        box_mesh((-d2, w2 - t, 0.0), (d2, w2, HEIGHT), _shade(rng, wood)),       # right side
        box_mesh((d2 - t, -w2, 0.0), (d2, w2, HEIGHT), _shade(rng, light)),     # back
        box_mesh((-d2, -w2, HEIGHT - t), (d2, w2, HEIGHT), _shade(rng, dark)),   # top
        box_mesh((-d2, -w2, 0.0), (d2, w2, 0.06), _shade(rng, dark)),            # plinth/bottom
        box_mesh((-d2, -w2, SHELF_Z), (d2, w2, SHELF_Z + t), _shade(rng, light)),  # shelf
        box_mesh((-d2 + 0.05, -w2 + t, 0.55), (d2 - t, w2 - t, 0.55 + t), _shade(rng, light)),
        box_mesh((-d2 - 0.005, -w2, HEIGHT - 0.05), (-d2, w2, HEIGHT), (0.15, 0.35, 0.6)),
        box_mesh((-d2 - 0.005, -w2 + 0.01, 0.0), (-d2, w2 - 0.01, 0.06), (0.6, 0.15, 0.15)),
    ]
    # Door: closed in the plane just in front of the body, hinge on the left (-Y) front edge.
    hinge = np.array([-d2 - t, -w2, 0.0])
    door_z0, door_z1 = SHELF_Z + t, HEIGHT - 0.05
    door_world = [
        box_mesh((-d2 - t, -w2, door_z0), (-d2, w2, door_z1), _shade(rng, (0.2, 0.45, 0.3))),
        box_mesh((-d2 - t - 0.005, -w2 + 0.06, door_z0 + 0.06), (-d2 - t, w2 - 0.06, door_z1 - 0.06),
                 _shade(rng, (0.75, 0.75, 0.45))),
        box_mesh((-d2 - t - 0.04, w2 - 0.08, 0.5), (-d2 - t, w2 - 0.06, 0.65), (0.1, 0.1, 0.1)),
    ]
    door = [m.transformed(_translation(-hinge)) for m in door_world]
    # Drawer: open box with a front panel, in the lower compartment.
    dz0, dz1, dy = 0.08, SHELF_Z - 0.02, w2 - t - 0.01
    drawer = [
        box_mesh((-d2 - t, -w2 + 0.005, 0.065), (-d2, w2 - 0.005, SHELF_Z - 0.005),
                 _shade(rng, (0.7, 0.3, 0.2))),                                    # front panel
        box_mesh((-d2, -dy, dz0), (d2 - t - 0.02, -dy + 0.01, dz1), _shade(rng, light)),
        box_mesh((-d2, dy - 0.01, dz0), (d2 - t - 0.02, dy, dz1), _shade(rng, light)),
        box_mesh((d2 - t - 0.03, -dy, dz0), (d2 - t - 0.02, dy, dz1), _shade(rng, light)),
        box_mesh((-d2, -dy, dz0), (d2 - t - 0.02, dy, dz0 + 0.01), _shade(rng, (0.9, 0.9, 0.85))),
        box_mesh((-d2 - t - 0.04, -0.1, 0.18), (-d2 - t, 0.1, 0.2), (0.1, 0.1, 0.1)),  # handle
    ]
    z3 = np.zeros(3)
    links = {"body": Link("body"), "door": Link("door"), "drawer": Link("drawer")}
    joints = [
        Joint("door_hinge", "revolute", "body", "door", hinge.copy(), z3.copy(),
              np.array([0.0, 0.0, 1.0]), 0.0, np.pi / 2),
        Joint("drawer_slide", "prismatic", "body", "drawer", z3.copy(), z3.copy(),
              np.array([-1.0, 0.0, 0.0]), 0.0, 0.35),
    ]
    model = URDFModel("synth_cabinet", links, joints, "body")
    meshes = {"body": RenderMesh.concat(body), "door": RenderMesh.concat(door),
              "drawer": RenderMesh.concat(drawer)}
    return ArticulatedObject("synth_cabinet", model, meshes)


def _translation(v: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = v
    return T


def render_synth_scene(scene_dir: str | Path, views: int = 3, seed: int = 0,
                       door_angle: float | None = None, drawer_distance: float | None = None,
                       door_start: float = 0.0, drawer_start: float = 0.0, width: int = 320,
                       height: int = 240, posed: bool = True, scramble_masks: bool = False,
                       depth_noise: float = 0.0, write_masks: bool = True,
                       same_cameras: bool = True) -> dict:
    """Render the procedural cabinet in two states into ``scene_dir`` (+ gt.json); returns the gt.

    door_angle: radians the door opens start -> end (default seeded U(0.5, 1.2));
    drawer_distance: metres the drawer slides out (default seeded U(0.12, 0.3)).
    door_start / drawer_start: joint values at start. Mask labels: 1 body, 2 door, 3 drawer.
    """
    rng = np.random.default_rng(seed + 1)
    if door_angle is None:
        door_angle = float(rng.uniform(0.5, 1.2))
    if drawer_distance is None:
        drawer_distance = float(rng.uniform(0.12, 0.3))
    obj = build_cabinet(seed)
    q0 = {"door_hinge": float(door_start), "drawer_slide": float(drawer_start)}
    q1 = {"door_hinge": float(door_start + door_angle),
          "drawer_slide": float(drawer_start + drawer_distance)}
    return render_articulated_scene(obj, scene_dir, q0, q1, views=views, seed=seed, width=width,
                                    height=height, posed=posed, scramble_masks=scramble_masks,
                                    depth_noise=depth_noise, write_masks=write_masks,
                                    same_cameras=same_cameras)
