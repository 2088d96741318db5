"""The package's error for bad input (no heavy imports: the command line loads it first)."""
from __future__ import annotations


class SceneError(ValueError):
    """Bad input. ``str(error)`` is one line naming the offending file and the problem."""
