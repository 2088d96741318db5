"""The one place open3d is imported: lazily (it costs ~1 s), with its console warnings silenced
(registration fallbacks are reported through sparseart's own warnings instead)."""
from __future__ import annotations

from functools import lru_cache
from types import ModuleType


@lru_cache(maxsize=1)
def open3d() -> ModuleType:
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d
