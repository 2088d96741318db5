"""What every export names the same way and cannot measure: link names and the limit placeholders.

Images measure neither a joint's effort nor its velocity: the exports write these placeholders.
"""
from __future__ import annotations

PLACEHOLDER_EFFORT = 1.0      # N·m (revolute) or N (prismatic): a placeholder, not a measurement
PLACEHOLDER_VELOCITY = 1.0    # rad/s or units/s: a placeholder, not a measurement


def link_name(part_id: int) -> str:
    """``base`` for the static part 0, ``part_<id>`` otherwise."""
    return "base" if part_id == 0 else f"part_{part_id}"
