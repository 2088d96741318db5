"""sparseart: how an articulated object moves, from 1-4 images of it in each of two states.

Python use (robot code)::

    import sparseart
    result = sparseart.run("scene/")            # an Articulation
    for part, joint in result.joints:
        print(part.spec.id, joint.type, joint.axis, joint.origin, joint.angle or joint.distance)

Heavy dependencies (open3d, onnxruntime, torch) are imported only by the stages that use them.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

# name -> module: resolved on first use (PEP 562), so ``import sparseart`` and ``sparseart --help``
# do not load the pipeline's stages (scipy, OpenCV) before a command needs them
_LAZY = {"RunOptions": ".pipeline", "run": ".pipeline", "run_clouds": ".pipeline", "load_scene": ".io.scene",
         **{name: ".types" for name in ("Articulation", "Camera", "Frame", "JointEstimate", "LabelledCloud",
                                        "PartLabels", "PartResult", "PartSpec", "Scene", "SceneError")}}

__all__ = sorted(_LAZY) + ["__version__"]

if TYPE_CHECKING:
    from .io.scene import load_scene
    from .pipeline import RunOptions, run, run_clouds
    from .types import (Articulation, Camera, Frame, JointEstimate, LabelledCloud, PartLabels, PartResult,
                        PartSpec, Scene, SceneError)


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module 'sparseart' has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name], __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
