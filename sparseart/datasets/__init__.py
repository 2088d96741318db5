"""Rendered two-state datasets with ground truth: PartNet-Mobility URDF objects and a procedural
cabinet. Heavy imports (open3d) happen inside the rendering functions' modules; importing this
package pulls numpy/scipy/cv2 only lazily via the submodules below."""
from __future__ import annotations

__all__ = ["render_partnet_scene", "render_synth_scene", "build_cabinet", "render_view",
           "parse_urdf", "load_articulated_object", "write_scene"]


def __getattr__(name: str):
    if name in ("render_partnet_scene",):
        from sparseart.datasets.partnet import render_partnet_scene
        return render_partnet_scene
    if name in ("render_synth_scene", "build_cabinet"):
        from sparseart.datasets import synth
        return getattr(synth, name)
    if name == "render_view":
        from sparseart.datasets.raycast import render_view
        return render_view
    if name == "parse_urdf":
        from sparseart.datasets.urdf import parse_urdf
        return parse_urdf
    if name == "load_articulated_object":
        from sparseart.datasets.meshes import load_articulated_object
        return load_articulated_object
    if name == "write_scene":
        from sparseart.datasets.scene_writer import write_scene
        return write_scene
    raise AttributeError(name)
