"""sparseart: how an articulated object moves, from 1-4 images of it in each of two states.

Python use (robot code)::

    import sparseart
    result = sparseart.run("scene/")            # an Articulation
    for part, joint in result.joints:
        print(part.spec.id, joint.type, joint.axis, joint.origin, joint.angle or joint.distance)

Heavy dependencies (open3d, onnxruntime, torch) are imported only by the stages that use them.
"""
from .pipeline import RunOptions, run, run_clouds
from sparseart.io.scene import load_scene
from .types import (Articulation, Camera, Frame, JointEstimate, LabelledCloud, PartLabels, PartResult,
                    PartSpec, Scene, SceneError)

__version__ = "0.1.0"

__all__ = ["Articulation", "Camera", "Frame", "JointEstimate", "LabelledCloud", "PartLabels", "PartResult",
           "PartSpec", "RunOptions", "Scene", "SceneError", "load_scene", "run", "run_clouds", "__version__"]
