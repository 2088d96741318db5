"""Shared geometry: rigid/screw transforms and axis angles, the one robust ICP, point-cloud helpers
(spacing, extent, sub-sampling) and the lazy open3d import. No stage logic lives here."""
