"""The ``pointmap-onnx/1`` contract: what an ONNX reconstructor takes and returns, declaratively.

A contract is JSON (every field is documented in ``models/README.md``). It is found, in order:

1. an explicit contract file (``--contract FILE`` / ``OnnxLiftOptions.contract_path``);
2. a sidecar beside the model: ``<stem>.contract.json`` (``vggt.onnx`` -> ``vggt.contract.json``)
   or ``<file name>.contract.json`` (``vggt.onnx.contract.json``);
3. the model's own ``metadata_props`` under the key ``pointmap-onnx`` (``pointmap_contract`` is
   accepted too);
4. a built-in preset (``sparseart/lift/presets/*.json``) whose ``match`` input and output names
   are all present in the model (the preset naming the most tensors wins).

A model matching none of them fails with one message listing its inputs and outputs. The contract
never runs code: decoding maths lives in named decoders chosen by ``encoding`` / ``kind`` values.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any

from ..types import SceneError
from .preprocess import INTERPOLATIONS, RESIZE_RULES, SizeRule

SCHEMA = "pointmap-onnx/1"
METADATA_KEYS = ("pointmap-onnx", "pointmap_contract")
CONFIDENCE_KINDS = ("expp1", "logit", "prob", "none")
CAMERA_ENCODINGS = ("vggt_absT_quaR_FoV", "matrix_w2c", "matrix_c2w")
PRINCIPAL_POINTS = ("half_size", "center")
POINT_FRAMES = ("camera0", "world")
SCALES = {"relative": "relative", "normalized": "relative", "metric": "metric"}
PREFER = ("depth_unproject", "point_head")
# layout letters: B batch (size 1), S frames (N is a synonym), C channels, H, W; V vector (pose
# encoding), I, J matrix rows and columns.
INPUT_LETTERS, OUTPUT_LETTERS = set("BSNCHW"), set("BSNCHWVIJ")
FREE_TEXT_KEYS = {"description", "licence", "license", "license_note", "family", "comment", "source"}


class ModelError(SceneError):
    """Bad model or contract. ``str(error)`` is one line naming the file and the problem."""


@dataclass(frozen=True)
class TensorInfo:
    """One model input or output as onnxruntime reports it (shape entries: int or symbol/None)."""

    name: str
    shape: tuple
    type: str

    def describe(self) -> str:
        dims = ", ".join("?" if d is None else str(d) for d in self.shape)
        return f"{self.name} [{dims}] {self.type.replace('tensor(', '').rstrip(')')}"


@dataclass(frozen=True)
class ModelIO:
    """What the contract is checked against: the session's inputs, outputs and metadata."""

    path: Path
    inputs: tuple[TensorInfo, ...]
    outputs: tuple[TensorInfo, ...]
    metadata: dict[str, str] = field(default_factory=dict)

    def describe(self) -> str:
        return (f"inputs: {'; '.join(t.describe() for t in self.inputs)} | "
                f"outputs: {'; '.join(t.describe() for t in self.outputs)}")


@dataclass(frozen=True)
class OutputSpec:
    """One model output: its name, axis layout and how to read it.

    kind: confidence mapping (``expp1``: c >= 1 -> 1 - 1/c; ``logit``: sigmoid; ``prob``: clip to
    [0, 1]; ``none``: all 1), camera encoding for the camera output, ``K_pixels`` for intrinsics.
    """

    name: str
    layout: str
    kind: str = "none"
    optional: bool = False


@dataclass(frozen=True)
class Contract:
    """A validated ``pointmap-onnx/1`` contract. ``source`` says where it came from."""

    name: str
    source: str
    input_name: str
    input_layout: str
    input_dtype: str | None
    value_range: tuple[float, float]
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    pad_value: tuple[float, float, float]
    size: SizeRule
    min_frames: int
    max_frames: int | None
    camera: OutputSpec | None
    intrinsics: OutputSpec | None
    depth: OutputSpec | None
    depth_conf: OutputSpec | None
    points: OutputSpec | None
    points_conf: OutputSpec | None
    quat_order: str = "xyzw"
    principal_point: str = "half_size"
    points_frame: str = "camera0"
    prefer: str = "depth_unproject"
    scale: str = "relative"
    confidence_threshold: float = 0.0
    bytes_per_frame: float = 0.0
    bytes_per_frame_squared: float = 0.0
    match_inputs: tuple[str, ...] = ()
    match_outputs: tuple[str, ...] = ()

    def outputs(self) -> list[OutputSpec]:
        return [o for o in (self.camera, self.intrinsics, self.depth, self.depth_conf, self.points,
                            self.points_conf) if o is not None]


# --------------------------------------------------------------------------- parsing


class _Reader:
    """Typed access to a JSON object; every error names the source and the field path."""

    def __init__(self, data: Any, source: str, path: str = "") -> None:
        self.source, self.path = source, path
        if not isinstance(data, dict):
            self.fail(f"must be a JSON object, got {type(data).__name__}")
        self.data = data

    def fail(self, problem: str, key: str | None = None) -> None:
        where = ".".join(p for p in (self.path, key) if p) or "top level"
        raise ModelError(f"{self.source}: contract field '{where}' {problem}")

    def child(self, key: str, required: bool = True) -> "_Reader | None":
        if key not in self.data or self.data[key] is None:
            if required:
                self.fail("is missing", key)
            return None
        return _Reader(self.data[key], self.source, ".".join(p for p in (self.path, key) if p))

    def check_keys(self, allowed: set[str]) -> None:
        for key in self.data:
            if key not in allowed and key not in FREE_TEXT_KEYS and not str(key).startswith("x-"):
                self.fail(f"is not a known field (known: {', '.join(sorted(allowed))})", key)

    def text(self, key: str, default: Any = ..., choices: tuple[str, ...] | None = None) -> Any:
        if key not in self.data or self.data[key] is None:
            if default is ...:
                self.fail("is missing", key)
            return default
        value = self.data[key]
        if not isinstance(value, str) or not value:
            self.fail(f"must be a non-empty string, got {value!r}", key)
        if choices is not None and value not in choices:
            self.fail(f"must be one of {', '.join(choices)}, got {value!r}", key)
        return value

    def number(self, key: str, default: Any = ..., minimum: float | None = None,
               maximum: float | None = None, integer: bool = False) -> Any:
        if key not in self.data or self.data[key] is None:
            if default is ...:
                self.fail("is missing", key)
            return default
        value = self.data[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value:
            self.fail(f"must be a number, got {value!r}", key)
        if integer and int(value) != value:
            self.fail(f"must be an integer, got {value!r}", key)
        if (minimum is not None and value < minimum) or (maximum is not None and value > maximum):
            self.fail(f"must be in [{minimum}, {maximum if maximum is not None else 'inf'}], got {value!r}", key)
        return int(value) if integer else float(value)

    def triple(self, key: str, default: tuple, length: int = 3) -> tuple:
        value = self.data.get(key)
        if value is None:
            return default
        if (not isinstance(value, list) or len(value) != length
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
            self.fail(f"must be a list of {length} numbers, got {value!r}", key)
        return tuple(float(v) for v in value)

    def names(self, key: str) -> tuple[str, ...]:
        value = self.data.get(key, [])
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            self.fail("must be a list of tensor names", key)
        return tuple(value)


def _layout(reader: _Reader, key: str, letters: set[str], required: set[str]) -> str:
    layout = reader.text(key)
    normalised = layout.upper().replace("N", "S")
    if (set(normalised) - letters or len(set(normalised)) != len(normalised)
            or not required <= set(normalised)):
        reader.fail(f"{layout!r} is not a valid layout (distinct letters from {''.join(sorted(letters))}, "
                    f"needing {''.join(sorted(required))})", key)
    return normalised


def _output(reader: _Reader, key: str, required_letters: str, kinds: tuple[str, ...] | None,
            default_kind: str = "none") -> OutputSpec | None:
    spec = reader.child(key, required=False)
    if spec is None:
        return None
    spec.check_keys({"name", "layout", "kind", "encoding", "optional", "frame", "quat_order",
                     "principal_point", "convention"})
    kind_key = "encoding" if key == "camera" else "kind"
    optional = spec.data.get("optional", False)
    if not isinstance(optional, bool):
        spec.fail("must be true or false", "optional")
    return OutputSpec(name=spec.text("name"), layout=_layout(spec, "layout", OUTPUT_LETTERS, set(required_letters)),
                      kind=spec.text(kind_key, default_kind if kinds is None or default_kind in kinds else ...,
                                     choices=kinds),
                      optional=optional)


def parse_contract(data: Any, source: str) -> Contract:
    """Validate a decoded contract JSON object; ``source`` names where it came from (file path,
    model metadata or preset) and starts every error message."""
    top = _Reader(data, source)
    top.check_keys({"schema", "name", "inputs", "outputs", "geometry", "confidence", "memory", "match",
                    "postprocess"})
    if top.data.get("schema") != SCHEMA:
        top.fail(f"must be {SCHEMA!r}, got {top.data.get('schema')!r}", "schema")
    if top.data.get("postprocess") is not None:
        top.fail("is not supported by this version (only null)", "postprocess")
    images = top.child("inputs").child("images")
    top.child("inputs").check_keys({"images"})
    images.check_keys({"name", "layout", "dtype", "range", "mean", "std", "height", "width", "multiple_of",
                       "resize", "long_side", "interp", "pad_value", "frames", "color"})
    if images.data.get("color", "RGB") != "RGB":
        images.fail("must be 'RGB' (BGR models: reorder the channels in the export)", "color")
    value_range = images.triple("range", (0.0, 1.0), 2)
    std = images.triple("std", (1.0, 1.0, 1.0))
    if any(s == 0 for s in std):
        images.fail("must not contain 0", "std")
    frames = images.child("frames", required=False)
    min_frames = frames.number("min", 1, 1, integer=True) if frames else 1
    max_frames = frames.number("max", None, min_frames, integer=True) if frames else None
    size = SizeRule(height=images.number("height", None, 1, integer=True),
                    width=images.number("width", None, 1, integer=True),
                    long_side=images.number("long_side", None, 1, integer=True),
                    multiple_of=images.number("multiple_of", 1, 1, integer=True),
                    resize={"letterbox": "pad"}.get(images.data.get("resize"), images.data.get("resize", "pad")),
                    interpolation={"bicubic": "cubic", "bilinear": "linear"}.get(
                        images.data.get("interp"), images.data.get("interp", "cubic")))
    if size.resize not in RESIZE_RULES:
        images.fail(f"must be one of {', '.join(RESIZE_RULES)}, got {size.resize!r}", "resize")
    if size.interpolation not in INTERPOLATIONS:
        images.fail(f"must be one of {', '.join(INTERPOLATIONS)}, got {size.interpolation!r}", "interp")
    outputs = top.child("outputs")
    outputs.check_keys({"camera", "intrinsics", "depth", "depth_conf", "points", "points_conf"})
    camera = _output(outputs, "camera", "", CAMERA_ENCODINGS)
    intrinsics = _output(outputs, "intrinsics", "IJ", ("K_pixels",), "K_pixels")
    depth = _output(outputs, "depth", "HW", None)
    points = _output(outputs, "points", "HWC", None)
    depth_conf = _output(outputs, "depth_conf", "HW", CONFIDENCE_KINDS, "none")
    points_conf = _output(outputs, "points_conf", "HW", CONFIDENCE_KINDS, "none")
    camera_reader = outputs.child("camera", required=False)
    points_reader = outputs.child("points", required=False)
    if camera is not None:
        need = "V" if camera.kind == "vggt_absT_quaR_FoV" else "IJ"
        if not set(need) <= set(camera.layout):
            outputs.fail(f"layout {camera.layout!r} lacks {need} for encoding {camera.kind}", "camera.layout")
        if camera.kind != "vggt_absT_quaR_FoV" and intrinsics is None:
            outputs.fail(f"is required with camera encoding {camera.kind}", "intrinsics")
    if depth is None and points is None:
        outputs.fail("must name a depth or a points output", "depth")
    if depth is not None and camera is None and points is None:
        outputs.fail("is required to unproject depth (no points output either)", "camera")
    geometry = top.child("geometry", required=False) or _Reader({}, source, "geometry")
    geometry.check_keys({"prefer", "scale", "pixel_center"})
    if geometry.data.get("pixel_center", "integer") != "integer":
        geometry.fail("must be 'integer' (OpenCV pixel centres)", "pixel_center")
    scale = geometry.text("scale", "relative", tuple(SCALES))
    confidence = top.child("confidence", required=False) or _Reader({}, source, "confidence")
    confidence.check_keys({"threshold", "to01", "default"})
    memory = top.child("memory", required=False) or _Reader({}, source, "memory")
    memory.check_keys({"bytes_per_frame", "bytes_per_frame_squared"})
    match = top.child("match", required=False) or _Reader({}, source, "match")
    match.check_keys({"inputs", "outputs"})
    points_frame = points_reader.text("frame", "camera0", POINT_FRAMES) if points_reader else "camera0"
    if points_frame == "world" and camera is None:
        outputs.fail("'world' needs a camera output to express points in the first camera", "points.frame")
    return Contract(
        name=top.text("name"), source=source, input_name=images.text("name"),
        input_layout=_layout(images, "layout", INPUT_LETTERS, set("SCHW")),
        input_dtype=images.text("dtype", None, ("float32", "float16")),
        value_range=value_range, mean=images.triple("mean", (0.0, 0.0, 0.0)), std=std,
        pad_value=images.triple("pad_value", (value_range[0],) * 3), size=size,
        min_frames=min_frames, max_frames=max_frames, camera=camera, intrinsics=intrinsics, depth=depth,
        depth_conf=depth_conf, points=points, points_conf=points_conf,
        quat_order=camera_reader.text("quat_order", "xyzw", ("xyzw", "wxyz")) if camera_reader else "xyzw",
        principal_point=(camera_reader.text("principal_point", "half_size", PRINCIPAL_POINTS)
                         if camera_reader else "half_size"),
        points_frame=points_frame, prefer=geometry.text("prefer", "depth_unproject", PREFER),
        scale=SCALES[scale], confidence_threshold=confidence.number("threshold", 0.0, 0.0, 1.0),
        bytes_per_frame=memory.number("bytes_per_frame", 0.0, 0.0),
        bytes_per_frame_squared=memory.number("bytes_per_frame_squared", 0.0, 0.0),
        match_inputs=match.names("inputs"), match_outputs=match.names("outputs"))


def load_contract_file(path: str | Path) -> Contract:
    """Read and validate a contract JSON file (errors name the file, and the line for bad JSON)."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: contract file not found")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as error:
        raise ModelError(f"{path}: cannot read contract file ({error})") from None
    except json.JSONDecodeError as error:
        raise ModelError(f"{path}: invalid JSON at line {error.lineno}: {error.msg}") from None
    return parse_contract(data, str(path))


def builtin_presets() -> list[Contract]:
    """The contracts shipped in ``sparseart/lift/presets/*.json``, sorted by file name."""
    folder = resources.files("sparseart.lift") / "presets"
    presets = []
    for entry in sorted(folder.iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".json"):
            try:
                data = json.loads(entry.read_text())
            except json.JSONDecodeError as error:
                raise ModelError(f"preset {entry.name}: invalid JSON at line {error.lineno}: {error.msg}") from None
            presets.append(parse_contract(data, f"built-in preset {entry.name}"))
    return presets


def sidecar_paths(model_path: Path) -> list[Path]:
    """Where a sidecar contract may sit beside ``model_path``, in the order they are tried."""
    return [model_path.with_name(model_path.stem + ".contract.json"),
            model_path.with_name(model_path.name + ".contract.json")]


def resolve_contract(io: ModelIO, contract_path: str | Path | None = None) -> Contract:
    """Find the contract of a model (explicit file, sidecar, metadata, preset; module docstring)
    and check it against the model's inputs and outputs. Raises :class:`ModelError`."""
    if contract_path is not None:
        contract = load_contract_file(contract_path)
    else:
        contract = next((load_contract_file(p) for p in sidecar_paths(io.path) if p.is_file()), None)
    if contract is None:
        key = next((k for k in METADATA_KEYS if k in io.metadata), None)
        if key is not None:
            source = f"{io.path} (metadata '{key}')"
            try:
                data = json.loads(io.metadata[key])
            except json.JSONDecodeError as error:
                raise ModelError(f"{source}: invalid JSON at line {error.lineno}: {error.msg}") from None
            contract = parse_contract(data, source)
    if contract is None:
        input_names = {t.name for t in io.inputs}
        output_names = {t.name for t in io.outputs}
        matching = [p for p in builtin_presets() if p.match_inputs or p.match_outputs
                    if set(p.match_inputs) <= input_names and set(p.match_outputs) <= output_names]
        if not matching:
            raise ModelError(f"{io.path}: no pointmap-onnx contract (no --contract, no sidecar "
                             f"{sidecar_paths(io.path)[0].name}, no '{METADATA_KEYS[0]}' metadata) and no "
                             f"built-in preset matches the model's {io.describe()}")
        contract = max(matching, key=lambda p: len(p.match_inputs) + len(p.match_outputs))
    check_against_model(contract, io)
    return _without_absent_outputs(contract, io)


def _without_absent_outputs(contract: Contract, io: ModelIO) -> Contract:
    """The contract with its optional outputs that the model lacks set to None."""
    present = {t.name for t in io.outputs}
    absent = {key: None for key in ("camera", "intrinsics", "depth", "depth_conf", "points", "points_conf")
              if getattr(contract, key) is not None and getattr(contract, key).name not in present}
    contract = replace(contract, **absent)
    if contract.camera is not None and contract.camera.kind != "vggt_absT_quaR_FoV" and contract.intrinsics is None:
        contract = replace(contract, camera=None)  # extrinsics without intrinsics cannot unproject
    where = f"{io.path}: contract '{contract.name}' ({contract.source})"
    if contract.depth is None and contract.points is None:
        raise ModelError(f"{where}: the model has neither the depth nor the points output; it has {io.describe()}")
    if contract.points is None and contract.camera is None:
        raise ModelError(f"{where}: depth needs a camera output to be unprojected; the model has {io.describe()}")
    return contract


def check_against_model(contract: Contract, io: ModelIO) -> None:
    """Raise :class:`ModelError` when the contract's tensors are absent from the model or their
    ranks disagree with the layouts (an extra trailing axis of size 1 is tolerated on outputs)."""
    inputs = {t.name: t for t in io.inputs}
    outputs = {t.name: t for t in io.outputs}
    where = f"{io.path}: contract '{contract.name}' ({contract.source})"
    if contract.input_name not in inputs:
        raise ModelError(f"{where} names input '{contract.input_name}', but the model has {io.describe()}")
    shape = inputs[contract.input_name].shape
    if len(shape) != len(contract.input_layout):
        raise ModelError(f"{where}: input layout {contract.input_layout} has {len(contract.input_layout)} axes, "
                         f"the model's {inputs[contract.input_name].describe()} has {len(shape)}")
    channels = shape[contract.input_layout.index("C")]
    if isinstance(channels, int) and channels != 3:
        raise ModelError(f"{where}: input {contract.input_name} has {channels} channels, RGB needs 3")
    for spec in contract.outputs():
        if spec.name not in outputs:
            if spec.optional:
                continue
            raise ModelError(f"{where} names output '{spec.name}', but the model has {io.describe()}")
        rank = len(outputs[spec.name].shape)
        if rank not in (len(spec.layout), len(spec.layout) + 1):
            raise ModelError(f"{where}: output layout {spec.layout} has {len(spec.layout)} axes, the "
                             f"model's {outputs[spec.name].describe()} has {rank}")
