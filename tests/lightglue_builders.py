"""A tiny LightGlue-ONNX pipeline stand-in built with onnx.helper (no download).

Same input/output contract as fabio-sim/LightGlue-ONNX's end-to-end export: ``images [2, C, H, W]``
float32 in [0, 1] -> ``keypoints [2, K, 2]`` (model-grid pixels), ``matches [M, 3]`` int64
(batch, idx0, idx1), ``mscores [M]`` float32. The keypoints and matches are constants baked in by the
test (correspondences it computed from the scene geometry: the model "knows" the scene it was built
for, as the reconstructor test models do); the keypoints depend on the input through ``+ 0 * mean``
so the graph really consumes the images.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper


def build_lightglue(path: Path, keypoints0: np.ndarray, keypoints1: np.ndarray, matches: np.ndarray,
                    scores: np.ndarray, *, height: int | None, width: int | None, channels: int = 1,
                    input_name: str = "images", float16: bool = False) -> Path:
    """Write the model. keypoints0/1: (K, 2) x, y model-grid pixels; matches (M, 3); scores (M,).
    height/width None = dynamic input size."""
    keypoints = np.stack([keypoints0, keypoints1]).astype(np.float32)
    elem = TensorProto.FLOAT16 if float16 else TensorProto.FLOAT
    images = helper.make_tensor_value_info(input_name, elem, [2, channels, height or "H", width or "W"])
    outputs = [helper.make_tensor_value_info("keypoints", TensorProto.FLOAT, [2, keypoints.shape[1], 2]),
               helper.make_tensor_value_info("matches", TensorProto.INT64, ["M", 3]),
               helper.make_tensor_value_info("mscores", TensorProto.FLOAT, ["M"])]
    nodes = [helper.make_node("Cast", [input_name], ["images32"], to=TensorProto.FLOAT),
             helper.make_node("ReduceMean", ["images32"], ["mean"], keepdims=0),
             helper.make_node("Mul", ["mean", "zero"], ["nothing"]),
             helper.make_node("Add", ["keypoints_table", "nothing"], ["keypoints"]),
             helper.make_node("Identity", ["matches_table"], ["matches"]),
             helper.make_node("Identity", ["scores_table"], ["mscores"])]
    inits = [numpy_helper.from_array(np.float32(0.0), "zero"),
             numpy_helper.from_array(keypoints, "keypoints_table"),
             numpy_helper.from_array(np.asarray(matches, np.int64).reshape(-1, 3), "matches_table"),
             numpy_helper.from_array(np.asarray(scores, np.float32).reshape(-1), "scores_table")]
    graph = helper.make_graph(nodes, "lightglue_standin", [images], outputs, inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def build_split_extractor(path: Path) -> Path:
    """An 'extractor' of the legacy split export: image [1, 1, H, W] -> keypoints, scores, descriptors."""
    image = helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 1, "H", "W"])
    outputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in ("keypoints", "scores", "descriptors")]
    nodes = [helper.make_node("Identity", ["image"], [n]) for n in ("keypoints", "scores", "descriptors")]
    model = helper.make_model(helper.make_graph(nodes, "split", [image], outputs),
                              opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path
