"""Which Gaussian components are drawn for a given articulation state.

Every Gaussian of either state is split into a static component (opacity ``(1 - m) o``, never
moves) and a mobile component (opacity ``m o``, moves with the joint). For a rendering of state
``l`` (SPLART's cross renderings):

* ``own``: state l's own Gaussians with their full opacity ``o`` (static and mobile components
  coincide there, so they are drawn as one Gaussian);
* ``cross_static``: ``own`` + the other state's static components, unmoved;
* ``cross_mobile``: ``cross_static`` + the other state's mobile components moved by the joint
  (forward from start to end, inverse from end to start).

A novel state at fraction s of the motion draws start's static components + start's mobile
components moved by s of the motion, and the same for end (mobile moved back by 1 - s); at s = 0
and s = 1 this is exactly the ``cross_mobile`` rendering of start and end.
"""
from __future__ import annotations

from .gaussians import GaussianSet
from .joint import JointParams, move_gaussians
from .render import Camera, rasterize

MODES = ("own", "cross_static", "cross_mobile")


def _pack(gaussians: GaussianSet, opacities, means=None, quats=None) -> tuple:
    return (gaussians.means if means is None else means, gaussians.quats if quats is None else quats,
            gaussians.log_scales, opacities, gaussians.colors())


def _concat(pieces: list[tuple]) -> tuple:
    import torch

    return tuple(torch.cat([p[k] for p in pieces], dim=0) for k in range(5))


def components(state: str, sets: dict[str, GaussianSet], joint: JointParams | None, mode: str) -> tuple:
    """(means, quats, log_scales, opacities, colors) drawn for ``state`` in ``mode`` (see above)."""
    if mode not in MODES:
        raise ValueError(f"unknown composition mode {mode!r}; expected one of {MODES}")
    own = sets[state]
    pieces = [_pack(own, own.opacities())]
    other_name = "end" if state == "start" else "start"
    other = sets.get(other_name)
    if mode != "own" and other is not None:
        pieces.append(_pack(other, other.static_opacities()))
        if mode == "cross_mobile":
            if joint is None:
                raise ValueError("cross_mobile composition needs a joint")
            rotation, translation = joint.motion(1.0, inverse=(other_name == "end"))
            means, quats = move_gaussians(other.means, other.quats, rotation, translation)
            pieces.append(_pack(other, other.mobile_opacities(), means, quats))
    return _concat(pieces)


def novel_state_components(sets: dict[str, GaussianSet], joint: JointParams, fraction: float) -> tuple:
    """Components of the articulation state at ``fraction`` (0 = start, 1 = end) of the motion."""
    pieces = []
    for name, moved_by, inverse in (("start", fraction, False), ("end", 1.0 - fraction, True)):
        gaussians = sets.get(name)
        if gaussians is None:
            continue
        rotation, translation = joint.motion(moved_by, inverse=inverse)
        means, quats = move_gaussians(gaussians.means, gaussians.quats, rotation, translation)
        pieces.append(_pack(gaussians, gaussians.static_opacities()))
        pieces.append(_pack(gaussians, gaussians.mobile_opacities(), means, quats))
    return _concat(pieces)


def render_components(parts: tuple, camera: Camera, background) -> dict:
    """Rasterise a (means, quats, log_scales, opacities, colors) tuple into ``camera``."""
    means, quats, log_scales, opacities, colors = parts
    return rasterize(means, quats, log_scales, opacities, colors, camera, background=background)
