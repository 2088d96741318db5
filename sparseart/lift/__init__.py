"""Lifting images to per-pixel 3D points (pointmaps) and transferring 2D labels onto them."""
from .labels import build_labelled_cloud
from .rgbd import flying_pixel_mask, pointmap_from_depth

__all__ = ["build_labelled_cloud", "flying_pixel_mask", "pointmap_from_depth"]
