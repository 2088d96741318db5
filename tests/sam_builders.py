"""Tiny, exact SAM-layout ONNX models built with onnx.helper, for testing sparseart.segment.onnx_sam.

* encoder ``x [1, 3, S, S] -> image_embeddings [1, 3, S, S]``: the identity, so the "embedding" is
  the normalised, padded image itself.
* decoder (SAM1 layout: image_embeddings, point_coords, point_labels, mask_input, has_mask_input,
  orig_im_size -> masks, iou_predictions). For the first point of every prompt it reads the
  embedding colour at that pixel and returns three masks at the original size:
    0. logits 10 * (0.5 - L1 colour distance): the pixels of exactly that colour (colours that
       differ by >= 60 per channel are >= 1 apart), predicted IoU 0.95, stable;
    1. the whole image (logits 5), predicted IoU 0.3 (dropped by the IoU filter);
    2. the same region with logits +-0.5, predicted IoU 0.99 but stability 0 (dropped by the
       stability filter).
  Like the official export it crops the prompt frame to the resized image (long side S) and
  resizes (nearest) to orig_im_size.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17


def _const(name: str, value) -> onnx.NodeProto:
    return helper.make_node("Constant", [], [name], value=numpy_helper.from_array(np.asarray(value), name))


def _save(graph: onnx.GraphProto, path: Path) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def build_encoder(path: Path, side: int = 64, output_name: str = "image_embeddings") -> Path:
    """Identity encoder ``x [1, 3, side, side] -> output_name``."""
    graph = helper.make_graph(
        [helper.make_node("Identity", ["x"], [output_name])], "tiny_sam_encoder",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, side, side])],
        [helper.make_tensor_value_info(output_name, TensorProto.FLOAT, [1, 3, side, side])])
    return _save(graph, path)


def build_decoder(path: Path, side: int = 64, batched: bool = True, embed_channels: int = 3,
                  names: dict[str, str] | None = None) -> Path:
    """Colour-matching decoder (module docstring). ``batched=False`` fixes the prompt batch to 1;
    ``names`` renames inputs (to test layout errors); ``embed_channels`` != 3 declares a
    mismatched embedding input."""
    n = {k: k for k in ("image_embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input",
                        "orig_im_size")}
    n.update(names or {})
    batch = "B" if batched else 1
    grid_y, grid_x = np.mgrid[0:side, 0:side].astype(np.float32)
    nodes = [
        _const("zero_i", np.array(0, dtype=np.int64)), _const("one_i", np.array(1, dtype=np.int64)),
        _const("grid_x", grid_x[None]), _const("grid_y", grid_y[None]),
        _const("half", np.array(0.5, np.float32)), _const("ten", np.array(10.0, np.float32)),
        _const("five", np.array(5.0, np.float32)), _const("neg_half", np.array(-0.5, np.float32)),
        _const("zero_f", np.array(0.0, np.float32)), _const("side_f", np.array(float(side), np.float32)),
        _const("axes_hw", np.array([2, 3], np.int64)), _const("axis1", np.array([1], np.int64)),
        _const("starts", np.array([0, 0], np.int64)), _const("iou_row", np.array([[0.95, 0.3, 0.99]], np.float32)),
        _const("three", np.array([3], np.int64)), _const("shape_b11", np.array([-1, 1, 1], np.int64)),
        _const("shape_b3_11", np.array([-1, embed_channels, 1, 1], np.int64)),
        # prompt pixel (first point of every prompt)
        helper.make_node("Gather", [n["point_coords"], "zero_i"], ["point"], axis=1),          # [B, 2]
        helper.make_node("Gather", ["point", "zero_i"], ["px"], axis=1),                        # [B]
        helper.make_node("Gather", ["point", "one_i"], ["py"], axis=1),
        helper.make_node("Floor", ["px"], ["px_f"]), helper.make_node("Floor", ["py"], ["py_f"]),
        helper.make_node("Reshape", ["px_f", "shape_b11"], ["px_b"]),
        helper.make_node("Reshape", ["py_f", "shape_b11"], ["py_b"]),
        helper.make_node("Equal", ["grid_x", "px_b"], ["on_x"]), helper.make_node("Equal", ["grid_y", "py_b"], ["on_y"]),
        helper.make_node("And", ["on_x", "on_y"], ["on_pixel"]),
        helper.make_node("Cast", ["on_pixel"], ["onehot"], to=TensorProto.FLOAT),                # [B, S, S]
        helper.make_node("Unsqueeze", ["onehot", "axis1"], ["onehot4"]),                        # [B, 1, S, S]
        helper.make_node("Mul", [n["image_embeddings"], "onehot4"], ["picked"]),                # [B, 3, S, S]
        helper.make_node("ReduceSum", ["picked", "axes_hw"], ["colour"], keepdims=0),           # [B, 3]
        helper.make_node("Reshape", ["colour", "shape_b3_11"], ["colour4"]),
        helper.make_node("Sub", [n["image_embeddings"], "colour4"], ["diff"]),
        helper.make_node("Abs", ["diff"], ["abs_diff"]),
        helper.make_node("ReduceSum", ["abs_diff", "axis1"], ["distance"], keepdims=1),         # [B, 1, S, S]
        helper.make_node("Sub", ["half", "distance"], ["margin"]),
        helper.make_node("Mul", ["margin", "ten"], ["match"]),
        helper.make_node("Mul", ["match", "zero_f"], ["zeros"]),
        helper.make_node("Add", ["zeros", "five"], ["whole"]),
        helper.make_node("Greater", ["match", "zero_f"], ["inside"]),
        helper.make_node("Where", ["inside", "half", "neg_half"], ["unstable"]),
        helper.make_node("Concat", ["match", "whole", "unstable"], ["prompt_masks"], axis=1),    # [B, 3, S, S]
        # crop to the resized image and resize to the original size
        helper.make_node("ReduceMax", [n["orig_im_size"]], ["long"], keepdims=1),
        helper.make_node("Div", ["side_f", "long"], ["scale"]),
        helper.make_node("Mul", [n["orig_im_size"], "scale"], ["scaled"]),
        helper.make_node("Add", ["scaled", "half"], ["scaled_r"]),
        helper.make_node("Floor", ["scaled_r"], ["pre_pad"]),
        helper.make_node("Cast", ["pre_pad"], ["ends"], to=TensorProto.INT64),
        helper.make_node("Slice", ["prompt_masks", "starts", "ends", "axes_hw"], ["cropped"]),
        helper.make_node("Shape", ["cropped"], ["cropped_shape"]),
        helper.make_node("Slice", ["cropped_shape", "starts_1", "ends_2"], ["bm"]),
        helper.make_node("Cast", [n["orig_im_size"]], ["orig_i"], to=TensorProto.INT64),
        helper.make_node("Concat", ["bm", "orig_i"], ["sizes"], axis=0),
        helper.make_node("Resize", ["cropped", "", "", "sizes"], ["masks"], mode="nearest",
                         nearest_mode="floor", coordinate_transformation_mode="asymmetric"),
        helper.make_node("Slice", ["cropped_shape", "starts_1", "ends_1"], ["batch"]),
        helper.make_node("Concat", ["batch", "three"], ["iou_shape"], axis=0),
        helper.make_node("Expand", ["iou_row", "iou_shape"], ["iou_predictions"]),
    ]
    nodes[:0] = [_const("starts_1", np.array([0], np.int64)), _const("ends_1", np.array([1], np.int64)),
                 _const("ends_2", np.array([2], np.int64))]
    inputs = [
        helper.make_tensor_value_info(n["image_embeddings"], TensorProto.FLOAT, [1, embed_channels, side, side]),
        helper.make_tensor_value_info(n["point_coords"], TensorProto.FLOAT, [batch, "N", 2]),
        helper.make_tensor_value_info(n["point_labels"], TensorProto.FLOAT, [batch, "N"]),
        helper.make_tensor_value_info(n["mask_input"], TensorProto.FLOAT, [batch, 1, 256, 256]),
        helper.make_tensor_value_info(n["has_mask_input"], TensorProto.FLOAT, [batch]),
        helper.make_tensor_value_info(n["orig_im_size"], TensorProto.FLOAT, [2]),
    ]
    outputs = [helper.make_tensor_value_info("masks", TensorProto.FLOAT, [batch, 3, "H", "W"]),
               helper.make_tensor_value_info("iou_predictions", TensorProto.FLOAT, [batch, 3])]
    return _save(helper.make_graph(nodes, "tiny_sam_decoder", inputs, outputs), path)
