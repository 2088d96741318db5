"""Tiny, geometrically exact reconstructor ONNX models built with onnx.helper (no download).

The test images carry depth in their pixels: R = depth_mm // 256, G = depth_mm % 256 (the scene's
uint16 depth PNG value), B = 255 where depth is valid. The models decode that exactly
(``Round(255 R) * 256 + Round(255 G)``, times ``depth_unit`` metres), and emit it in a known
reconstructor layout together with cameras they were built with:

* ``vggt``: input ``[S, 3, H, W]`` in [0, 1]; outputs ``pose_enc [1, S, 9]`` (t, quaternion xyzw,
  fov_h, fov_w of the given K in grid pixels), ``depth [1, S, H, W, 1]``, ``depth_conf [1, S, H, W]``
  = 1 + 10 B (VGGT's expp1 form), ``world_points [1, S, H, W, 3]`` = R_s^T (z ray_K - t_s)
  computed in the graph, ``world_points_conf`` = depth_conf.
* ``da3``: input ``[1, S, 3, H, W]`` ImageNet-normalised on the host (the graph undoes it);
  outputs ``depth [1, S, H, W]``, ``depth_conf``, ``extrinsics [1, S, 3, 4]`` (w2c),
  ``intrinsics [1, S, 3, 3]``.

Per-frame cameras come from tables of ``max_frames`` entries sliced to the batch's S, so the model
"knows" the cameras of the scene it was built for. Large constants are initializers, so the model
can be saved with external data.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper
from scipy.spatial.transform import Rotation

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def encode_depth_rgb(depth_u16: np.ndarray) -> np.ndarray:
    """(H, W) uint16 depth -> (H, W, 3) uint8 RGB: R high byte, G low byte, B 255 where > 0."""
    depth_u16 = np.asarray(depth_u16, np.uint16)
    return np.stack([(depth_u16 >> 8).astype(np.uint8), (depth_u16 & 255).astype(np.uint8),
                     np.where(depth_u16 > 0, 255, 0).astype(np.uint8)], axis=2)


def vggt_pose_encoding(cam_from_world: np.ndarray, K_grid: np.ndarray, width: int, height: int) -> np.ndarray:
    """(9,) VGGT absT_quaR_FoV of one camera: t, quaternion xyzw, fov_h, fov_w (radians)."""
    quat = Rotation.from_matrix(cam_from_world[:3, :3]).as_quat()
    fov_h = 2.0 * np.arctan((height / 2.0) / K_grid[1, 1])
    fov_w = 2.0 * np.arctan((width / 2.0) / K_grid[0, 0])
    return np.concatenate([cam_from_world[:3, 3], quat, [fov_h, fov_w]])


def _init(name: str, value: np.ndarray) -> onnx.TensorProto:
    return numpy_helper.from_array(np.asarray(value), name)


def _slice_frames(table: str, out: str, axis: int) -> onnx.NodeProto:
    return helper.make_node("Slice", [table, "zero1", "S1", f"axis{axis}"], [out])


def build_reconstructor(path: Path, *, width: int, height: int, K_grid: np.ndarray,
                        cam_from_world: list[np.ndarray], layout: str = "vggt",
                        input_name: str | None = None, output_names: dict[str, str] | None = None,
                        fixed_frames: int | None = None, float16: bool = False, depth_unit: float = 0.001,
                        ir_version: int = 8, opset: int = 17, metadata: dict[str, str] | None = None,
                        external_data: bool = False) -> Path:
    """Write a depth-decoding reconstructor (module docstring) for a ``width`` x ``height`` grid.

    K_grid: (3, 3) intrinsics in grid pixels (the rays of the point head; the pose encoding carries
        only its focal lengths). cam_from_world: per frame index, (4, 4) camera-from-world.
    output_names: rename outputs (keys: the vggt/da3 names). fixed_frames: fix the S axis.
    metadata: metadata_props (e.g. {"pointmap-onnx": json}). external_data: weights in
        ``<name>.data`` beside the model.
    """
    names = {k: k for k in ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf",
                            "extrinsics", "intrinsics")}
    names.update(output_names or {})
    frames_dim = fixed_frames if fixed_frames is not None else "S"
    elem = TensorProto.FLOAT16 if float16 else TensorProto.FLOAT
    input_name = input_name or ("input_images" if layout == "vggt" else "image")
    in_shape = [frames_dim, 3, height, width] if layout == "vggt" else [1, frames_dim, 3, height, width]
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([(cols - K_grid[0, 2]) / K_grid[0, 0], (rows - K_grid[1, 2]) / K_grid[1, 1],
                     np.ones_like(cols)], axis=2)[None].astype(np.float32)
    poses = np.asarray(cam_from_world, np.float64)
    inits = [
        _init("rays", rays), _init("rot", poses[:, :3, :3].astype(np.float32)),
        _init("trans", poses[:, None, :3, 3].astype(np.float32)),
        _init("pose_table", np.stack([vggt_pose_encoding(p, K_grid, width, height) for p in poses])[None]
              .astype(np.float32)),
        _init("extr_table", poses[None, :, :3, :].astype(np.float32)),
        _init("intr_table", np.tile(K_grid, (len(poses), 1, 1))[None].astype(np.float32)),
        _init("mean", np.asarray(IMAGENET_MEAN, np.float32).reshape(1, 3, 1, 1)),
        _init("std", np.asarray(IMAGENET_STD, np.float32).reshape(1, 3, 1, 1)),
    ]
    consts = {"zero1": np.array([0], np.int64), "one1": np.array([1], np.int64), "two1": np.array([2], np.int64),
              "three1": np.array([3], np.int64), "axis0": np.array([0], np.int64), "axis1": np.array([1], np.int64),
              "flat_shape": np.array([0, -1, 3], np.int64), "c255": np.array(255.0, np.float32),
              "c256": np.array(256.0, np.float32), "unit": np.array(depth_unit, np.float32),
              "c1": np.array(1.0, np.float32), "c10": np.array(10.0, np.float32)}
    nodes = [helper.make_node("Constant", [], [k], value=numpy_helper.from_array(v, k)) for k, v in consts.items()]
    x = input_name
    if float16:
        nodes.append(helper.make_node("Cast", [x], ["x32"], to=TensorProto.FLOAT))
        x = "x32"
    if layout == "da3":
        nodes += [helper.make_node("Squeeze", [x, "axis0"], ["x4n"]),
                  helper.make_node("Mul", ["x4n", "std"], ["x4s"]),
                  helper.make_node("Add", ["x4s", "mean"], ["x4"])]
        x = "x4"
    nodes += [
        helper.make_node("Shape", [x], ["shape4"]),
        helper.make_node("Slice", ["shape4", "zero1", "one1", "axis0"], ["S1"]),
        helper.make_node("Slice", [x, "zero1", "one1", "axis1"], ["r"]),
        helper.make_node("Slice", [x, "one1", "two1", "axis1"], ["g"]),
        helper.make_node("Slice", [x, "two1", "three1", "axis1"], ["b"]),
        helper.make_node("Mul", ["r", "c255"], ["r255"]), helper.make_node("Round", ["r255"], ["r_int"]),
        helper.make_node("Mul", ["g", "c255"], ["g255"]), helper.make_node("Round", ["g255"], ["g_int"]),
        helper.make_node("Mul", ["r_int", "c256"], ["high"]), helper.make_node("Add", ["high", "g_int"], ["depth_raw"]),
        helper.make_node("Mul", ["depth_raw", "unit"], ["z"]),                                # [S, 1, H, W]
        helper.make_node("Mul", ["b", "c10"], ["b10"]), helper.make_node("Add", ["b10", "c1"], ["conf4"]),
        helper.make_node("Squeeze", ["conf4", "axis1"], ["conf3"]),                          # [S, H, W]
        helper.make_node("Unsqueeze", ["conf3", "axis0"], ["conf_out"]),                     # [1, S, H, W]
        helper.make_node("Transpose", ["z"], ["z_hw1"], perm=[0, 2, 3, 1]),                  # [S, H, W, 1]
    ]
    outputs = []
    if layout == "vggt":
        nodes += [
            helper.make_node("Mul", ["rays", "z_hw1"], ["cam_pts"]),                         # [S, H, W, 3]
            helper.make_node("Reshape", ["cam_pts", "flat_shape"], ["cam_flat"]),
            _slice_frames("rot", "rot_s", 0), _slice_frames("trans", "trans_s", 0),
            helper.make_node("Sub", ["cam_flat", "trans_s"], ["centred"]),
            helper.make_node("MatMul", ["centred", "rot_s"], ["world_flat"]),
            helper.make_node("Shape", ["cam_pts"], ["pts_shape"]),
            helper.make_node("Reshape", ["world_flat", "pts_shape"], ["world_pts"]),
            helper.make_node("Unsqueeze", ["world_pts", "axis0"], [names["world_points"]]),
            helper.make_node("Unsqueeze", ["z_hw1", "axis0"], [names["depth"]]),
            helper.make_node("Identity", ["conf_out"], [names["depth_conf"]]),
            helper.make_node("Identity", ["conf_out"], [names["world_points_conf"]]),
            _slice_frames("pose_table", names["pose_enc"], 1),
        ]
        outputs = [(names["pose_enc"], [1, frames_dim, 9]), (names["depth"], [1, frames_dim, height, width, 1]),
                   (names["depth_conf"], [1, frames_dim, height, width]),
                   (names["world_points"], [1, frames_dim, height, width, 3]),
                   (names["world_points_conf"], [1, frames_dim, height, width])]
    else:
        nodes += [
            helper.make_node("Squeeze", ["z", "axis1"], ["z3"]),
            helper.make_node("Unsqueeze", ["z3", "axis0"], [names["depth"]]),
            helper.make_node("Identity", ["conf_out"], [names["depth_conf"]]),
            _slice_frames("extr_table", names["extrinsics"], 1),
            _slice_frames("intr_table", names["intrinsics"], 1),
        ]
        outputs = [(names["depth"], [1, frames_dim, height, width]),
                   (names["depth_conf"], [1, frames_dim, height, width]),
                   (names["extrinsics"], [1, frames_dim, 3, 4]), (names["intrinsics"], [1, frames_dim, 3, 3])]
    graph = helper.make_graph(nodes, f"tiny_{layout}_reconstructor",
                              [helper.make_tensor_value_info(input_name, elem, in_shape)],
                              [helper.make_tensor_value_info(n, TensorProto.FLOAT, s) for n, s in outputs], inits)
    return save_model(graph, path, ir_version=ir_version, opset=opset, metadata=metadata, external_data=external_data)


def build_passthrough(path: Path, input_name: str = "foo", output_name: str = "bar", side: int = 14) -> Path:
    """A model that matches no preset: ``input_name [S, 3, side, side] -> output_name`` (Identity)."""
    graph = helper.make_graph([helper.make_node("Identity", [input_name], [output_name])], "passthrough",
                              [helper.make_tensor_value_info(input_name, TensorProto.FLOAT, ["S", 3, side, side])],
                              [helper.make_tensor_value_info(output_name, TensorProto.FLOAT, ["S", 3, side, side])])
    return save_model(graph, path)


def save_model(graph: onnx.GraphProto, path: Path, ir_version: int = 8, opset: int = 17,
               metadata: dict[str, str] | None = None, external_data: bool = False) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])
    model.ir_version = ir_version
    if metadata:
        helper.set_model_props(model, metadata)
    if ir_version <= onnx.IR_VERSION and opset <= onnx.defs.onnx_opset_version():
        onnx.checker.check_model(model)
    path = Path(path)
    if external_data:
        onnx.save_model(model, str(path), save_as_external_data=True, all_tensors_to_one_file=True,
                        location=path.name + ".data", size_threshold=0)
    else:
        onnx.save(model, str(path))
    return path


def contract_json(name: str, *, input_name: str = "images", layout: str = "vggt", resize: str = "pad",
                  interp: str = "nearest", long_side: int | None = None, principal_point: str = "center",
                  output_names: dict[str, str] | None = None, scale: str = "metric",
                  threshold: float = 0.5, **extra) -> dict:
    """A pointmap-onnx/1 contract for :func:`build_reconstructor` models."""
    n = {k: k for k in ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf",
                        "extrinsics", "intrinsics")}
    n.update(output_names or {})
    if layout == "vggt":
        images = {"name": input_name, "layout": "SCHW", "range": [0, 1], "pad_value": [1, 1, 1]}
        outputs = {"camera": {"name": n["pose_enc"], "layout": "BSV", "encoding": "vggt_absT_quaR_FoV",
                              "principal_point": principal_point},
                   "depth": {"name": n["depth"], "layout": "BSHWC"},
                   "depth_conf": {"name": n["depth_conf"], "layout": "BSHW", "kind": "expp1"},
                   "points": {"name": n["world_points"], "layout": "BSHWC", "frame": "camera0"},
                   "points_conf": {"name": n["world_points_conf"], "layout": "BSHW", "kind": "expp1"}}
    else:
        images = {"name": input_name, "layout": "BSCHW", "range": [0, 1], "mean": list(IMAGENET_MEAN),
                  "std": list(IMAGENET_STD), "pad_value": list(IMAGENET_MEAN)}
        outputs = {"camera": {"name": n["extrinsics"], "layout": "BSIJ", "encoding": "matrix_w2c"},
                   "intrinsics": {"name": n["intrinsics"], "layout": "BSIJ"},
                   "depth": {"name": n["depth"], "layout": "BSHW"},
                   "depth_conf": {"name": n["depth_conf"], "layout": "BSHW", "kind": "expp1"}}
    images.update({"multiple_of": 14, "resize": resize, "interp": interp, "long_side": long_side})
    contract = {"schema": "pointmap-onnx/1", "name": name, "inputs": {"images": images}, "outputs": outputs,
                "geometry": {"prefer": "depth_unproject", "scale": scale}, "confidence": {"threshold": threshold}}
    contract.update(extra)
    return contract


def write_json(path: Path, data: dict) -> Path:
    Path(path).write_text(json.dumps(data, indent=1))
    return Path(path)
