"""SPLART-style refinement (optional; needs torch): 3D Gaussians with a per-Gaussian mobility,
seeded from the fitted joints, refined photometrically and geometrically.

Importing this package does not import torch; the functions do.
"""
from __future__ import annotations

__all__ = ["RefineOptions", "PartRefinement", "refine_part", "refine_parts", "write_refine_outputs", "rasterize"]


def __getattr__(name: str):
    if name in ("RefineOptions", "PartRefinement", "refine_part", "refine_parts"):
        from . import api

        return getattr(api, name)
    if name == "write_refine_outputs":
        from .outputs import write_refine_outputs

        return write_refine_outputs
    if name == "rasterize":
        from .render import rasterize

        return rasterize
    raise AttributeError(name)
