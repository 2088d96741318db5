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

:mod:`sparseart.view.data` reads OUT/ and computes the poses (no viser); :mod:`sparseart.view.page`
serves the page and imports viser only in :func:`start_viewer` (the ``view`` extra). Bad input
raises :class:`~sparseart.types.SceneError` with one line naming the file.
"""
from __future__ import annotations

from sparseart.view.data import (JointView, ObservedCloud, PartGeometry, ViewData, load_view_data, part_poses,
                                 slider_range)
from sparseart.view.page import Viewer, cone_mesh, serve, start_viewer

__all__ = ["JointView", "ObservedCloud", "PartGeometry", "ViewData", "Viewer", "cone_mesh", "load_view_data",
           "part_poses", "serve", "slider_range", "start_viewer"]
