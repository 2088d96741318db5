"""ONNX reconstructors (VGGT-style): images -> per-pixel points, confidence and cameras.

``Reconstructor`` opens the model with onnxruntime, finds its ``pointmap-onnx/1`` contract
(:mod:`sparseart.lift.contract`), preprocesses images onto the model grid recording the exact pixel
mapping (:mod:`sparseart.lift.preprocess`), runs one forward pass and decodes the outputs back to
every frame's ORIGINAL pixel grid. :func:`lift_scene_with_model` does this for the frames of a
scene, both states in one pass ("joint") or one pass per state ("per_state").

Decoding, per frame s of a pass (first frame = reference):

* camera: VGGT ``pose_enc`` [t(3), quaternion (xyzw by default), fov_h, fov_w] -> camera-from-world
  ``[R | t]`` (OpenCV) and K in grid pixels (fx = (W/2)/tan(fov_w/2), principal point (W/2, H/2)
  or ((W-1)/2, (H-1)/2) per the contract); or extrinsic (w2c / c2w) + intrinsic matrices. Every
  pose is re-expressed relative to the first frame, so points are in the OpenCV frame of the
  pass's first camera whatever the model's own world frame is.
* points: depth (nearest-resampled to the original grid) unprojected with K mapped to the original
  grid (preferred, as upstream VGGT advises), else the point head, nearest-resampled.
* confidence mapped to [0, 1] (``expp1``: 1 - 1/c, ``logit``: sigmoid, ``prob``: clip); pixels
  below the threshold, outside the grid (crop), non-finite, with depth <= 0 or on depth edges
  (flying pixels, as for RGB-D) are invalid (NaN points).

Cost: one forward pass (model-dependent: VGGT-1B ~1e10-1e11 FLOP per frame, see models/README.md)
plus O(S H W) numpy for preprocessing and decoding.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .. import _onnx
from ..types import Camera, Pointmap, Scene
from .contract import Contract, ModelError, ModelIO, TensorInfo, resolve_contract
from .preprocess import PixelMap, SizeRule, prepare_frames
from .rgbd import flying_pixel_mask, pixel_rays

MODES = ("auto", "joint", "per_state")
DECODE_BYTES_PER_PIXEL = 200  # float64 working arrays of the decoder per original pixel
HEAD_REPROJECTION_PX = 4.0  # point head vs decoded camera: warn above max(this,
HEAD_REPROJECTION_DIAGONAL = 0.02  # this fraction of the image diagonal) median reprojection error
HEAD_CHECK_SAMPLES = 20000  # pixels (evenly strided) used by that check


@dataclass
class OnnxLiftOptions:
    """Options of :func:`lift_scene_with_model` / :class:`Reconstructor`.

    contract_path: explicit contract JSON (wins over sidecar, metadata and presets).
    mode: "joint" (all 2N frames in one pass; both states in the first start camera's frame),
        "per_state" (one pass per state; each state in its own first camera's frame, to be
        registered by the alignment stage), "auto" (joint when the model accepts 2N frames).
    confidence_threshold: pixels with confidence (mapped to [0, 1]) below it are invalid;
        None = the contract's default.
    confidence_percentile: additionally drop pixels below the p-th percentile (0-100) of the
        frame's valid confidences (VGGT demo's ``conf_thres``; ties at the percentile are kept).
    prefer: "depth_unproject" | "point_head" | None (contract's choice).
    long_side: override the contract's long side for models with a free input size.
    reject_flying_pixels: drop depth-edge pixels as the RGB-D path does.
    threads: onnxruntime intra-op threads (0 = its default, the physical cores).
    providers: execution providers in order; None = CUDA when available, then CPU.
    arena_off_above_bytes: disable the CPU memory arena for models larger than this.
    memory_limit_bytes: RAM budget for the memory checks; None = MemAvailable of the machine.
    """

    contract_path: str | Path | None = None
    mode: str = "auto"
    confidence_threshold: float | None = None
    confidence_percentile: float = 0.0
    prefer: str | None = None
    long_side: int | None = None
    reject_flying_pixels: bool = True
    threads: int = 0
    providers: tuple[str, ...] | None = None
    arena_off_above_bytes: int = 512 * 2**20
    memory_limit_bytes: int | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"OnnxLiftOptions.mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.confidence_threshold is not None and not 0.0 <= self.confidence_threshold <= 1.0:
            raise ValueError(f"OnnxLiftOptions.confidence_threshold must be in [0, 1], got {self.confidence_threshold!r}")
        if not 0.0 <= self.confidence_percentile < 100.0:
            raise ValueError(f"OnnxLiftOptions.confidence_percentile must be in [0, 100), got {self.confidence_percentile!r}")
        if self.prefer not in (None, "depth_unproject", "point_head"):
            raise ValueError(f"OnnxLiftOptions.prefer must be depth_unproject or point_head, got {self.prefer!r}")
        if self.long_side is not None and self.long_side < 1:
            raise ValueError(f"OnnxLiftOptions.long_side must be >= 1, got {self.long_side!r}")


@dataclass
class FrameGeometry:
    """One decoded frame, in its original pixel grid (H x W).

    points: (H*W, 3) float64, OpenCV frame of the pass's first camera, model units, NaN where invalid.
    valid: (H*W,) bool. confidence: (H*W,) float64 in [0, 1] (0 where invalid).
    camera: K (original grid) and cam_to_world = this camera -> first camera, or None when the
    model has no camera output. pixel_map: the model-grid mapping used.
    """

    points: np.ndarray
    valid: np.ndarray
    confidence: np.ndarray
    camera: Camera | None
    pixel_map: PixelMap


@dataclass
class OnnxLift:
    """Pointmaps of both states from an ONNX reconstructor (see :func:`lift_scene_with_model`).

    start / end: one :class:`Pointmap` per frame, original pixel grid, row-major, float64, NaN
        where invalid. start_cameras / end_cameras: estimated :class:`Camera` per frame (K in
        original pixels; cam_to_world maps the camera to the frame of the points) or None.
    frame: "joint" (both states in the OpenCV frame of start frame 0) or "per_state" (each state in
        the frame of its own first camera). scale: "relative" (arbitrary, differs between passes)
        or "metric".
    """

    start: list[Pointmap]
    end: list[Pointmap]
    start_cameras: list[Camera | None]
    end_cameras: list[Camera | None]
    frame: str
    scale: str
    contract: str
    seconds: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def pointmaps(self, state: str) -> list[Pointmap]:
        return self.start if state == "start" else self.end

    def cameras(self, state: str) -> list[Camera | None]:
        return self.start_cameras if state == "start" else self.end_cameras


# --------------------------------------------------------------------------- memory and session


def open_session(path: str | Path, options: OnnxLiftOptions):
    """The reconstructor's onnxruntime session (:func:`sparseart._onnx.open_session` with the RAM
    check, thread count, arena and providers of ``options``; failures are :class:`ModelError`)."""
    return _onnx.open_session(path, threads=options.threads, providers=options.providers,
                              memory_limit_bytes=options.memory_limit_bytes,
                              arena_off_above_bytes=options.arena_off_above_bytes, error_type=ModelError)


def model_io(session, path: Path) -> ModelIO:
    """The session's inputs, outputs and custom metadata as a :class:`ModelIO`."""
    def info(items):
        return tuple(TensorInfo(t.name, tuple(d if isinstance(d, int) else None for d in t.shape), t.type)
                     for t in items)

    metadata = dict(session.get_modelmeta().custom_metadata_map or {})
    return ModelIO(path=path, inputs=info(session.get_inputs()), outputs=info(session.get_outputs()),
                   metadata=metadata)


# --------------------------------------------------------------------------- decoding (pure)


def to_canonical(array: np.ndarray, layout: str, target: str, name: str) -> np.ndarray:
    """Reorder an output from its contract ``layout`` to ``target`` axes (e.g. "SHW").

    B, and C when the target has no C, must have size 1 and are dropped; a trailing extra axis of
    size 1 is dropped; a missing S becomes one frame.
    """
    array = np.asarray(array)
    if array.ndim == len(layout) + 1 and array.shape[-1] == 1:
        array = array[..., 0]
    if array.ndim != len(layout):
        raise ModelError(f"output {name}: shape {list(array.shape)} does not fit layout {layout}")
    letters = list(layout)
    for letter in ("B", "C"):
        if letter in letters and letter not in target:
            axis = letters.index(letter)
            if array.shape[axis] != 1:
                raise ModelError(f"output {name}: axis {letter} of layout {layout} has size "
                                 f"{array.shape[axis]}, expected 1 (shape {list(array.shape)})")
            array = np.take(array, 0, axis=axis)
            letters.pop(axis)
    if "S" not in letters and "S" in target:
        array, letters = array[None], ["S", *letters]
    if sorted(letters) != sorted(target):
        raise ModelError(f"output {name}: layout {layout} cannot be read as {target}")
    return np.transpose(array, [letters.index(t) for t in target])


def decode_vggt_pose_encoding(pose_enc: np.ndarray, width: int, height: int, quat_order: str = "xyzw",
                              principal_point: str = "half_size") -> tuple[np.ndarray, np.ndarray]:
    """VGGT ``absT_quaR_FoV`` (S, 9) -> (K (S, 3, 3) grid pixels, cam_from_world (S, 4, 4)), float64.

    pose_enc = [t (3), quaternion (4, ``quat_order``), fov_h, fov_w] (radians); OpenCV
    camera-from-world [R | t]; fx = (W/2)/tan(fov_w/2), fy = (H/2)/tan(fov_h/2); principal point
    (W/2, H/2) ("half_size", VGGT) or ((W-1)/2, (H-1)/2) ("center").
    """
    from scipy.spatial.transform import Rotation

    pose_enc = np.asarray(pose_enc, np.float64)
    if pose_enc.ndim != 2 or pose_enc.shape[1] != 9:
        raise ModelError(f"pose encoding must be (S, 9), got {list(pose_enc.shape)}")
    quaternion = pose_enc[:, 3:7] if quat_order == "xyzw" else pose_enc[:, [4, 5, 6, 3]]
    norms = np.linalg.norm(quaternion, axis=1)
    fov = pose_enc[:, 7:9]
    if not np.all(np.isfinite(pose_enc)) or np.any(norms < 1e-8) or np.any((fov <= 0) | (fov >= np.pi)):
        raise ModelError("pose encoding has a non-finite value, a zero quaternion or a field of view outside (0, pi)")
    cam_from_world = np.tile(np.eye(4), (len(pose_enc), 1, 1))
    cam_from_world[:, :3, :3] = Rotation.from_quat(quaternion / norms[:, None]).as_matrix()
    cam_from_world[:, :3, 3] = pose_enc[:, :3]
    K = np.tile(np.eye(3), (len(pose_enc), 1, 1))
    K[:, 0, 0] = (width / 2.0) / np.tan(fov[:, 1] / 2.0)
    K[:, 1, 1] = (height / 2.0) / np.tan(fov[:, 0] / 2.0)
    K[:, 0, 2], K[:, 1, 2] = ((width / 2.0, height / 2.0) if principal_point == "half_size"
                              else ((width - 1) / 2.0, (height - 1) / 2.0))
    return K, cam_from_world


def confidence_to_unit(raw: np.ndarray, kind: str) -> np.ndarray:
    """Map raw confidence to [0, 1] float64: expp1 (c >= 1) -> 1 - 1/c; logit -> sigmoid;
    prob -> clip; none -> 1. Non-finite values -> 0."""
    raw = np.asarray(raw, np.float64)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        if kind == "expp1":
            unit = 1.0 - 1.0 / np.maximum(raw, 1.0)
        elif kind == "logit":
            unit = 1.0 / (1.0 + np.exp(-raw))
        elif kind == "prob":
            unit = np.clip(raw, 0.0, 1.0)
        else:
            unit = np.ones_like(raw)
    return np.where(np.isfinite(raw), unit, 0.0)


def _matrices_to_4x4(matrices: np.ndarray, name: str) -> np.ndarray:
    if matrices.shape[1:] not in ((3, 4), (4, 4)):
        raise ModelError(f"output {name}: extrinsics must be 3x4 or 4x4 per frame, got {list(matrices.shape)}")
    full = np.tile(np.eye(4), (len(matrices), 1, 1))
    full[:, :3, :] = matrices[:, :3, :]
    return full


# --------------------------------------------------------------------------- the reconstructor


class Reconstructor:
    """An opened ONNX reconstructor with its contract.

    Args:
        model_path: the .onnx file (external data, if any, beside it).
        options: :class:`OnnxLiftOptions` (contract file, providers, threads, memory budget ...).

    Attributes: ``contract`` (resolved), ``io`` (the model's inputs/outputs), ``warnings``.
    Raises :class:`~sparseart.lift.contract.ModelError` (a SceneError) naming the file.
    """

    def __init__(self, model_path: str | Path, options: OnnxLiftOptions | None = None) -> None:
        self.path = Path(model_path)
        self.options = options or OnnxLiftOptions()
        self.session = open_session(self.path, self.options)
        self.io = model_io(self.session, self.path)
        self.contract: Contract = resolve_contract(self.io, self.options.contract_path)
        self.warnings: list[str] = []
        self._input = next(t for t in self.io.inputs if t.name == self.contract.input_name)
        self.input_dtype = np.float16 if self._input.type == "tensor(float16)" else np.float32
        if self._input.type not in ("tensor(float)", "tensor(float16)"):
            raise ModelError(f"{self.path}: image input {self._input.describe()} must be float or float16")
        if self.input_dtype == np.float16:
            self.warnings.append(f"{self.path.name}: float16 input; on the CPU provider fp16 models usually run "
                                 f"slower than fp32 (onnxruntime inserts casts)")
        extra = [t.name for t in self.io.inputs if t.name != self.contract.input_name]
        if extra:
            raise ModelError(f"{self.path}: inputs {', '.join(extra)} are not described by contract "
                             f"'{self.contract.name}' (only one image input is supported)")
        self.size_rule = self._size_rule()

    def _size_rule(self) -> SizeRule:
        """The contract's size rule with the session's fixed H, W (they win over long_side)."""
        layout, shape = self.contract.input_layout, self._input.shape
        fixed_h, fixed_w = shape[layout.index("H")], shape[layout.index("W")]
        rule = self.contract.size
        for axis, fixed, declared in (("height", fixed_h, rule.height), ("width", fixed_w, rule.width)):
            if fixed is not None and declared is not None and fixed != declared:
                raise ModelError(f"{self.path}: contract '{self.contract.name}' says {axis} {declared}, the "
                                 f"model's input {self._input.describe()} has {fixed}")
        height, width = rule.height or fixed_h, rule.width or fixed_w
        if (height is None) != (width is None):
            raise ModelError(f"{self.path}: input {self._input.describe()} fixes only one of H and W")
        long_side = self.options.long_side or rule.long_side
        return replace(rule, height=height, width=width, long_side=long_side)

    def frame_limit(self) -> tuple[int, int | None]:
        """(min, max) frames per forward pass (max None = unbounded)."""
        fixed = self._input.shape[self.contract.input_layout.index("S")]
        if fixed is not None:
            return fixed, fixed
        return self.contract.min_frames, self.contract.max_frames

    def accepts(self, frames: int) -> bool:
        low, high = self.frame_limit()
        return frames >= low and (high is None or frames <= high)

    def _check_memory(self, frames: int, pixel_maps: list[PixelMap]) -> None:
        budget = (self.options.memory_limit_bytes if self.options.memory_limit_bytes is not None
                  else _onnx.available_memory_bytes())
        if budget is None:
            return
        grid = pixel_maps[0].grid_width * pixel_maps[0].grid_height
        item = np.dtype(self.input_dtype).itemsize
        inputs = frames * 3 * grid * (item + 4)
        outputs = frames * grid * 4 * sum(3 if o is self.contract.points else 1 for o in
                                          (self.contract.depth, self.contract.depth_conf, self.contract.points,
                                           self.contract.points_conf) if o is not None)
        model = self.contract.bytes_per_frame * frames + self.contract.bytes_per_frame_squared * frames ** 2
        decode = DECODE_BYTES_PER_PIXEL * sum(m.width * m.height for m in pixel_maps)
        need = inputs + outputs + model + decode
        if need > budget:
            raise ModelError(f"{self.path}: running {frames} frames at {pixel_maps[0].grid_width}x"
                             f"{pixel_maps[0].grid_height} needs about {_onnx.size_text(need)} (inputs {_onnx.size_text(inputs)}, "
                             f"outputs {_onnx.size_text(outputs)}, model activations {_onnx.size_text(model)}, decoding {_onnx.size_text(decode)}) "
                             f"but only {_onnx.size_text(budget)} of RAM is available; use fewer frames, a smaller "
                             f"long side or per_state mode")

    def infer(self, images: list[np.ndarray]) -> tuple[dict[str, np.ndarray], list[PixelMap]]:
        """Preprocess and run one forward pass over ``images`` ((H, W, 3) uint8 RGB each).

        Returns the raw outputs named in the contract (float32 arrays) and each frame's PixelMap.
        """
        contract = self.contract
        if not self.accepts(len(images)):
            low, high = self.frame_limit()
            raise ModelError(f"{self.path}: the model takes {low}-{high if high is not None else 'any'} frames "
                             f"per pass, got {len(images)}")
        tensor, maps = prepare_frames(images, self.size_rule, contract.value_range, contract.mean,
                                      contract.std, contract.pad_value)
        self._check_memory(len(images), maps)
        layout = contract.input_layout
        source = "BSCHW" if "B" in layout else "SCHW"
        feed = np.transpose(tensor[None] if "B" in layout else tensor, [source.index(a) for a in layout])
        names = [o.name for o in contract.outputs()]
        try:
            values = self.session.run(names, {contract.input_name: np.ascontiguousarray(feed, self.input_dtype)})
        except Exception as error:  # onnxruntime raises private exception types
            first = next((line for line in str(error).splitlines() if line.strip()), type(error).__name__)
            raise ModelError(f"{self.path}: inference failed on {len(images)} frames of "
                             f"{maps[0].grid_width}x{maps[0].grid_height} ({first[:300]})") from None
        return {n: np.asarray(v, np.float32) for n, v in zip(names, values)}, maps

    def reconstruct(self, images: list[np.ndarray]) -> list[FrameGeometry]:
        """One forward pass over ``images`` decoded to each image's pixel grid (module docstring);
        points are in the OpenCV frame of the first image's camera. O(S H W) besides the model."""
        raw, maps = self.infer(images)
        return self.decode(raw, maps)

    def decode(self, raw: dict[str, np.ndarray], maps: list[PixelMap]) -> list[FrameGeometry]:
        """Decode raw outputs (see :meth:`infer`) to :class:`FrameGeometry` per frame."""
        c, options = self.contract, self.options
        grid_w, grid_h = maps[0].grid_width, maps[0].grid_height
        frames = len(maps)
        K_grid = cam_from_model = None
        if c.camera is not None and c.camera.kind == "vggt_absT_quaR_FoV":
            K_grid, cam_from_model = decode_vggt_pose_encoding(
                to_canonical(raw[c.camera.name], c.camera.layout, "SV", c.camera.name), grid_w, grid_h,
                c.quat_order, c.principal_point)
        elif c.camera is not None:
            matrices = _matrices_to_4x4(to_canonical(raw[c.camera.name], c.camera.layout, "SIJ", c.camera.name)
                                        .astype(np.float64), c.camera.name)
            if not np.all(np.isfinite(matrices)):
                raise ModelError(f"{self.path}: output {c.camera.name} has non-finite values")
            cam_from_model = matrices if c.camera.kind == "matrix_w2c" else np.linalg.inv(matrices)
            K_grid = to_canonical(raw[c.intrinsics.name], c.intrinsics.layout, "SIJ", c.intrinsics.name).astype(np.float64)
        if cam_from_model is not None and len(cam_from_model) != frames:
            raise ModelError(f"{self.path}: camera output has {len(cam_from_model)} frames for {frames} inputs")
        prefer = options.prefer or c.prefer
        use_depth = c.depth is not None and cam_from_model is not None and (prefer == "depth_unproject" or c.points is None)
        grids = {}
        for key, spec, target in (("depth", c.depth, "SHW"), ("depth_conf", c.depth_conf, "SHW"),
                                  ("points", c.points, "SHWC"), ("points_conf", c.points_conf, "SHW")):
            if spec is not None:
                grids[key] = to_canonical(raw[spec.name], spec.layout, target, spec.name)
                if grids[key].shape[:3] != (frames, grid_h, grid_w):
                    raise ModelError(f"{self.path}: output {spec.name} has shape {list(raw[spec.name].shape)}, "
                                     f"expected {frames} frames of {grid_h}x{grid_w}")
        threshold = c.confidence_threshold if options.confidence_threshold is None else options.confidence_threshold
        result = []
        for s, pixel_map in enumerate(maps):
            result.append(self._decode_frame(s, pixel_map, grids, K_grid, cam_from_model, use_depth, threshold))
        return result

    def _decode_frame(self, s: int, pixel_map: PixelMap, grids: dict, K_grid, cam_from_model,
                      use_depth: bool, threshold: float) -> FrameGeometry:
        c = self.contract
        height, width = pixel_map.height, pixel_map.width
        camera, cam_to_ref = None, None
        if cam_from_model is not None:
            cam_to_ref = cam_from_model[0] @ np.linalg.inv(cam_from_model[s])
            cam_to_ref[3] = (0.0, 0.0, 0.0, 1.0)
            camera = Camera(K=pixel_map.K_to_image(K_grid[s]), width=width, height=height, cam_to_world=cam_to_ref)
        conf_key, conf_spec = ("depth_conf", c.depth_conf) if use_depth else ("points_conf", c.points_conf)
        row, col, inside = pixel_map.nearest_grid_index()  # once per frame: O(H W)
        head_points = None
        if c.points is not None:
            head_points = grids["points"][s][row, col].astype(np.float64)
            if c.points_frame == "world":
                head_points = head_points @ cam_from_model[0][:3, :3].T + cam_from_model[0][:3, 3]
        if use_depth:
            depth = grids["depth"][s][row, col].astype(np.float64)
            valid = inside & np.isfinite(depth) & (depth > 0)
            depth = np.where(valid, depth, 0.0)
            points = (pixel_rays(camera.K, height, width) * depth[:, None]) @ cam_to_ref[:3, :3].T + cam_to_ref[:3, 3]
            if head_points is not None:
                self._check_heads(head_points, valid, camera)
        else:
            points = head_points
            valid = inside & np.all(np.isfinite(points), axis=1)
            depth = None
            if cam_to_ref is not None:
                local = (points - cam_to_ref[:3, 3]) @ cam_to_ref[:3, :3]
                valid &= np.nan_to_num(local[:, 2]) > 0
                depth = np.where(valid, local[:, 2], 0.0)
        if self.options.reject_flying_pixels and depth is not None:
            valid &= ~flying_pixel_mask(depth.reshape(height, width)).reshape(-1)
        if conf_spec is not None:
            confidence = confidence_to_unit(grids[conf_key][s][row, col], conf_spec.kind)
        else:
            confidence = np.ones(height * width)
        if threshold > 0:
            valid &= confidence >= threshold
        if self.options.confidence_percentile > 0 and valid.any():
            valid &= confidence >= np.percentile(confidence[valid], self.options.confidence_percentile)
        points = np.where(valid[:, None], points, np.nan)
        return FrameGeometry(points=points, valid=valid, confidence=np.where(valid, confidence, 0.0),
                             camera=camera, pixel_map=pixel_map)

    def _check_heads(self, head_points: np.ndarray, valid: np.ndarray, camera: Camera) -> None:
        """Warn when the point head, projected with the decoded camera, misses its own pixels by
        more than max(4 px, 2 % of the image diagonal) (median): a wrong quat_order, camera
        encoding or principal point in the contract shows up here. O(H W) mask, O(20k) check."""
        both = valid & np.all(np.isfinite(head_points), axis=1)
        if both.sum() < 10:
            return
        pixel = np.flatnonzero(both)[::max(1, int(both.sum()) // HEAD_CHECK_SAMPLES)]
        to_ref = camera.cam_to_world
        local = (head_points[pixel] - to_ref[:3, 3]) @ to_ref[:3, :3]
        with np.errstate(divide="ignore", invalid="ignore"):
            projected = (local @ camera.K.T)[:, :2] / local[:, 2:3]
        grid = np.stack([pixel % camera.width, pixel // camera.width], axis=1)
        error = float(np.nanmedian(np.linalg.norm(projected - grid, axis=1)))
        limit = max(HEAD_REPROJECTION_PX, HEAD_REPROJECTION_DIAGONAL * math.hypot(camera.width, camera.height))
        message = (f"{self.path.name}: the point head lands {error:.1f} px (median) from its pixels through the "
                   f"decoded camera; check the contract's quat_order, camera encoding and principal_point")
        if not error <= limit and message not in self.warnings:
            self.warnings.append(message)


# --------------------------------------------------------------------------- scenes


def lift_scene_with_model(scene: Scene, model_path: str | Path | Reconstructor,
                          options: OnnxLiftOptions | None = None) -> OnnxLift:
    """Lift every frame of an (RGB-only) scene with an ONNX reconstructor.

    Args:
        scene: a loaded scene (``sparseart.io.scene.load_scene(path, require_depth=False)``); only
            the RGB images are used. cameras.json K, when given, is NOT used for geometry (the
            model's depth and cameras are consistent with its own K; mixing them would bend the
            surfaces); it is compared with the model's K and a warning is added when the focal
            lengths differ by more than 25 %. cameras.json poses are not used either (bringing
            the result into a posed scene's world frame is the alignment stage's job).
        model_path: the .onnx file, or an open :class:`Reconstructor` (reused across scenes).
        options: :class:`OnnxLiftOptions`; ``mode`` picks one pass over all 2N frames ("joint":
            both states in the OpenCV frame of start frame 0) or one pass per state ("per_state":
            each state in the frame of its own first camera; register them with a similarity).

    Returns:
        :class:`OnnxLift` with per-state Pointmaps ((H*W, 3) float64, original pixel grid,
        row-major, NaN where invalid) and Cameras; feed them to
        ``sparseart.lift.build_labelled_cloud(state, scene.frames(state), lift.pointmaps(state))``.

    Raises:
        ModelError (a SceneError): missing/corrupt model, unsupported IR/opset, no contract,
        frame count or RAM out of range — one line naming the file.
    """
    began = time.perf_counter()
    if isinstance(model_path, Reconstructor):
        reconstructor = model_path
        if options is not None:  # decoding options and long_side apply; contract/session ones were used at opening
            reconstructor.options = options
            reconstructor.size_rule = reconstructor._size_rule()
    else:
        reconstructor = Reconstructor(model_path, options)
    options = reconstructor.options
    loaded = time.perf_counter()
    frames = scene.all_frames
    mode = options.mode
    if mode == "auto":
        mode = "joint" if reconstructor.accepts(len(frames)) else "per_state"
    if mode == "joint":
        decoded = reconstructor.reconstruct([f.rgb for f in frames])
        per_state = {"start": decoded[:len(scene.start)], "end": decoded[len(scene.start):]}
    else:
        per_state = {state: reconstructor.reconstruct([f.rgb for f in scene.frames(state)])
                     for state in ("start", "end")}
    pointmaps: dict[str, list[Pointmap]] = {}
    warnings = list(reconstructor.warnings)
    for state in ("start", "end"):
        pointmaps[state] = [Pointmap(state=state, frame_index=f.index, height=g.pixel_map.height,
                                     width=g.pixel_map.width, points=g.points, valid=g.valid,
                                     confidence=g.confidence)
                            for f, g in zip(scene.frames(state), per_state[state])]
        for f, g in zip(scene.frames(state), per_state[state]):
            if f.camera is not None and g.camera is not None:
                ratio = g.camera.K[0, 0] / f.camera.K[0, 0]
                if not 0.8 <= ratio <= 1.25:
                    warnings.append(f"{f.rgb_path}: the model's focal length is {ratio:.2f} x the one in "
                                    f"cameras.json")
            if not g.valid.any():
                warnings.append(f"{f.rgb_path}: the reconstructor left no valid pixel")
    contract = reconstructor.contract
    return OnnxLift(start=pointmaps["start"], end=pointmaps["end"],
                    start_cameras=[g.camera for g in per_state["start"]],
                    end_cameras=[g.camera for g in per_state["end"]], frame=mode, scale=contract.scale,
                    contract=f"{contract.name} ({contract.source})",
                    seconds={"load": loaded - began, "reconstruct": time.perf_counter() - loaded},
                    warnings=warnings)
