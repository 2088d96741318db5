"""Scene-folder reading and validation (design section 2) and atomic result writing.

Every problem with the input raises :class:`sparseart.types.SceneError` whose message is one line
naming the offending file and what is wrong, so the CLI can print it and exit with code 2 before
any output is written. The checks themselves (regular files, size caps, headers before decoding,
JSON limits, numeric ranges) live in :mod:`sparseart.io.validate`, the one validation boundary.
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from sparseart.io import validate as check
from sparseart.types import STATES, Camera, Frame, Scene, SceneError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
MAX_VIEWS_PER_STATE = 4
RIGIDITY_TOLERANCE = 1e-3  # max |R^T R - I| and |det R - 1| accepted for cam_to_world
DEFAULT_DEPTH_SCALE = 1000.0


def load_scene(root: str | Path, require_depth: bool = True) -> Scene:
    """Read and validate a scene folder.

    Args:
        root: the scene folder (``start/``, ``end/``, optional ``cameras.json``).
        require_depth: when True, a scene without depth is an error (no reconstructor given).

    Returns:
        A :class:`Scene` whose frames hold rgb (H, W, 3) uint8, depth (H, W) float64 metres,
        masks (H, W) int64, depth confidence (H, W) float64 in [0, 1] and cameras (K and optional
        cam_to_world, float64).

    Depth confidence (``{state}/conf/NNN.npy``, optional): read when a state has a ``conf/``
    folder; then every image of that state needs one, and like depth and masks it is all or none
    over the scene (confidence for one state only would weigh the two states' points
    differently); it needs depth (``conf/`` without ``depth/`` is an error, not ignored).

    Raises:
        SceneError: one line naming the file and the problem.
    """
    root = Path(root)
    if not root.exists():
        raise check._fail(root, "scene folder does not exist")
    if not root.is_dir():
        raise check._fail(root, "not a folder (expected a scene folder with start/ and end/)")
    cameras = _read_cameras_json(root)
    depth_scale = cameras.get("depth_scale", DEFAULT_DEPTH_SCALE) if cameras else DEFAULT_DEPTH_SCALE
    warnings: list[str] = []
    budget = _PixelBudget()
    states: dict[str, list[Frame]] = {}
    for state in STATES:
        states[state] = _read_state(root, state, cameras, float(depth_scale), warnings, budget)
    scene = Scene(root=root, start=states["start"], end=states["end"], depth_scale=float(depth_scale),
                  warnings=warnings)
    _check_consistency(scene, require_depth)
    if scene.posed and scene.has_depth:
        scene.warnings.extend(check.check_posed_units(scene.all_frames, scene.depth_scale, root / "cameras.json"))
    return scene


class _PixelBudget:
    """Counts the pixels of every image read against ``validate.MAX_SCENE_PIXELS``."""

    def __init__(self) -> None:
        self.used = 0

    def take(self, path: Path, width: int, height: int) -> None:
        self.used += width * height
        if self.used > check.MAX_SCENE_PIXELS:
            raise check._fail(path, f"the scene's images hold more than {check.MAX_SCENE_PIXELS} pixels together "
                                    f"(the limit; downscale the images or use fewer views)")


# --------------------------------------------------------------------------- cameras.json


def _read_cameras_json(root: Path) -> dict[str, Any] | None:
    path = root / "cameras.json"
    if not check.is_present(path):
        return None
    data = check.load_json_file(path)
    if not isinstance(data, dict):
        raise check._fail(path, "expected a JSON object at top level")
    convention = data.get("convention", "opencv")
    if convention != "opencv":
        shown = convention if isinstance(convention, str) else check._type_name(convention)
        raise check._fail(path, f"convention '{shown[:80]}' not supported (use 'opencv')")
    if "depth_scale" in data:
        low, high = check.DEPTH_SCALE_RANGE
        if not check.is_number(data["depth_scale"]):
            raise check._fail(path, f"depth_scale must be a positive number, got {check._type_name(data['depth_scale'])}")
        scale = check.number(data["depth_scale"], "depth_scale", path)
        if scale <= 0:
            raise check._fail(path, f"depth_scale must be a positive number, got {scale:g}")
        check.number(scale, "depth_scale (PNG depth units per metre)", path, low, high)
    for state in STATES:
        entries = data.get(state, [])
        if not isinstance(entries, list):
            raise check._fail(path, f"'{state}' must be a list of camera entries")
        for i, entry in enumerate(entries):
            if not isinstance(entry, dict):
                raise check._fail(path, f"{state}[{i}] must be an object")
            if "image" in entry:
                check.text(entry["image"], f"{state}[{i}].image", path)
    return data


def _matrix(value: Any, shape: tuple[int, int], where: str, path: Path) -> np.ndarray:
    return check.matrix(value, shape, where, path)


def _camera_entry(entries: list[dict], image_rel: str, order: int, path: Path, state: str) -> dict | None:
    """The cameras.json entry for an image: matched by its "image" field, else by order."""
    named = [e for e in entries if "image" in e]
    if named:
        for entry in named:
            if Path(entry["image"]).as_posix() == image_rel:
                return entry
        return None
    return entries[order] if order < len(entries) else None


def _parse_camera(entry: dict, where: str, path: Path, width: int, height: int) -> Camera | None:
    if "K" not in entry:
        return None
    K = _matrix(entry["K"], (3, 3), f"{where} K", path)
    check.check_intrinsics(K, width, height, where, path)
    cam_to_world = None
    if entry.get("cam_to_world") is not None:
        cam_to_world = _matrix(entry["cam_to_world"], (4, 4), f"{where} cam_to_world", path)
        check.check_pose(cam_to_world, where, path, RIGIDITY_TOLERANCE)
    return Camera(K=K, width=width, height=height, cam_to_world=cam_to_world)


# --------------------------------------------------------------------------- images


def _read_image(path: Path, budget: "_PixelBudget | None" = None,
                match: tuple[Path, int, int] | None = None) -> np.ndarray:
    """Decode a PNG/JPEG after checking the file and its header (:mod:`validate`).

    match: (rgb path, width, height) the image must have; compared with the header, before decoding.
    """
    data = check.read_regular_file(path, check.MAX_IMAGE_FILE_BYTES, "image")
    header = check.image_header(data, path)
    if match is not None:
        _check_size(path, header.width, header.height, match)
    if budget is not None:
        budget.take(path, header.width, header.height)
    return check.decode_image(data, header, path)


def _check_size(path: Path, width: int, height: int, match: tuple[Path, int, int]) -> None:
    rgb_path, rgb_width, rgb_height = match
    if (width, height) != (rgb_width, rgb_height):
        raise check._fail(path, f"size {width}x{height} does not match image {rgb_path.name} "
                                f"({rgb_width}x{rgb_height})")


def _read_rgb(path: Path, budget: "_PixelBudget | None" = None) -> np.ndarray:
    image = _read_image(path, budget)
    if image.dtype != np.uint8:
        raise check._fail(path, f"RGB image must be 8-bit, got {image.dtype}")
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    elif image.shape[2] == 4:
        image = image[:, :, :3]
    elif image.shape[2] != 3:
        raise check._fail(path, f"RGB image must have 3 channels, got {image.shape[2]}")
    return np.ascontiguousarray(image[:, :, ::-1])


def _read_depth(path: Path, depth_scale: float, match: tuple[Path, int, int] | None = None) -> np.ndarray:
    if path.suffix == ".npy":
        depth = check.read_npy_file(path, kinds="f")
        if match is not None:
            _check_size(path, depth.shape[1], depth.shape[0], match)
    else:
        raw = _read_image(path, match=match)
        if raw.ndim != 2 or raw.dtype != np.uint16:
            raise check._fail(path, f"depth PNG must be single-channel uint16, got {raw.dtype} "
                                    f"with {1 if raw.ndim == 2 else raw.shape[2]} channels")
        depth = raw.astype(np.float64) / depth_scale
    return check.check_depth_metres(depth, path)


def _read_mask(path: Path, match: tuple[Path, int, int] | None = None) -> np.ndarray:
    raw = _read_image(path, match=match)
    if raw.ndim != 2 or raw.dtype not in (np.uint8, np.uint16):
        raise check._fail(path, "mask must be a single-channel uint8/uint16 label image")
    check.check_mask_ids(raw, path)
    return raw.astype(np.int64)


def _read_confidence(path: Path, depth_path: Path, depth_shape: tuple[int, int]) -> np.ndarray:
    confidence = check.read_npy_file(path, kinds="f")
    if confidence.shape != depth_shape:
        raise check._fail(path, f"depth confidence size {confidence.shape[1]}x{confidence.shape[0]} does not match "
                                f"depth {depth_path.name} ({depth_shape[1]}x{depth_shape[0]})")
    return check.check_depth_confidence(confidence, path)


def _find_companion(folder: Path, stem: str, suffixes: tuple[str, ...]) -> Path | None:
    for suffix in suffixes:
        candidate = folder / f"{stem}{suffix}"
        if check.is_present(candidate):   # a FIFO or broken link is reported, not skipped
            return candidate
    return None


def _read_state(root: Path, state: str, cameras: dict | None, depth_scale: float,
                warnings: list[str], budget: _PixelBudget | None = None) -> list[Frame]:
    state_dir = root / state
    if not state_dir.is_dir():
        raise check._fail(state_dir, "missing state folder (a scene needs start/ and end/)")
    rgb_dir = state_dir / "rgb"
    if not rgb_dir.is_dir():
        raise check._fail(rgb_dir, "missing rgb/ folder")
    image_paths = sorted(p for p in rgb_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not image_paths:
        raise check._fail(rgb_dir, "no images (.png/.jpg)")
    if len(image_paths) > check.MAX_IMAGES_PER_STATE:
        raise check._fail(rgb_dir, f"{len(image_paths)} images, more than the limit of "
                                   f"{check.MAX_IMAGES_PER_STATE} per state")
    if len(image_paths) > MAX_VIEWS_PER_STATE:
        warnings.append(f"{rgb_dir}: {len(image_paths)} images; 1-{MAX_VIEWS_PER_STATE} per state "
                        f"is the supported range, all are used")
    depth_dir, mask_dir, conf_dir = state_dir / "depth", state_dir / "mask", state_dir / "conf"
    camera_path = root / "cameras.json"
    entries = cameras.get(state, []) if cameras else []
    frames = []
    for index, rgb_path in enumerate(image_paths):
        rgb = _read_rgb(rgb_path, budget)
        height, width = rgb.shape[:2]
        frame = Frame(state=state, index=index, rgb_path=rgb_path, rgb=rgb)
        if depth_dir.is_dir():
            depth_path = _find_companion(depth_dir, rgb_path.stem, (".png", ".npy"))
            if depth_path is None:
                raise SceneError(f"{depth_dir}: no depth for {rgb_path.name} "
                                 f"(expected {rgb_path.stem}.png or {rgb_path.stem}.npy)")
            frame.depth = _read_depth(depth_path, depth_scale, (rgb_path, width, height))
            frame.depth_path = depth_path
            if frame.depth.shape != (height, width):
                raise SceneError(f"{depth_path}: size {frame.depth.shape[1]}x{frame.depth.shape[0]} "
                                 f"does not match image {rgb_path.name} ({width}x{height})")
        if conf_dir.is_dir():
            conf_path = _find_companion(conf_dir, rgb_path.stem, (".npy",))
            if conf_path is None:
                raise SceneError(f"{conf_dir}: no depth confidence for {rgb_path.name} (expected {rgb_path.stem}.npy)")
            if frame.depth is None:
                raise SceneError(f"{conf_path}: depth confidence without depth (add {state}/depth/ or remove "
                                 f"{state}/conf/)")
            frame.depth_confidence = _read_confidence(conf_path, frame.depth_path, frame.depth.shape)
            frame.confidence_path = conf_path
        if mask_dir.is_dir():
            mask_path = _find_companion(mask_dir, rgb_path.stem, (".png",))
            if mask_path is None:
                raise SceneError(f"{mask_dir}: no mask for {rgb_path.name} (expected {rgb_path.stem}.png)")
            frame.mask = _read_mask(mask_path, (rgb_path, width, height))
            frame.mask_path = mask_path
            if frame.mask.shape != (height, width):
                raise SceneError(f"{mask_path}: size {frame.mask.shape[1]}x{frame.mask.shape[0]} "
                                 f"does not match image {rgb_path.name} ({width}x{height})")
        image_rel = f"rgb/{rgb_path.name}"
        entry = _camera_entry(entries, image_rel, index, camera_path, state) if entries else None
        if entry is not None:
            frame.camera = _parse_camera(entry, f"{state} entry for {image_rel}", camera_path, width, height)
        if frame.depth is not None and frame.camera is None:
            raise SceneError(f"{frame.depth_path}: depth needs K for {state}/{image_rel} in "
                             f"{camera_path} (no camera entry with K)")
        frames.append(frame)
    return frames


def _check_consistency(scene: Scene, require_depth: bool) -> None:
    with_depth = [f for f in scene.all_frames if f.depth is not None]
    if with_depth and len(with_depth) != len(scene.all_frames):
        missing = next(f for f in scene.all_frames if f.depth is None)
        raise SceneError(f"{missing.rgb_path}: has no depth while other images do "
                         f"(give depth for every image or none)")
    if require_depth and not with_depth:
        raise SceneError(f"{scene.root}: no depth/ folders; an RGB-only scene needs a reconstructor "
                         f"model (--model)")
    with_conf = [f for f in scene.all_frames if f.depth_confidence is not None]
    if with_conf and len(with_conf) != len(scene.all_frames):
        missing = next(f for f in scene.all_frames if f.depth_confidence is None)
        raise SceneError(f"{missing.rgb_path}: has no depth confidence ({missing.state}/conf/{missing.rgb_path.stem}"
                         f".npy) while other images do (give conf/ for every image or none)")
    with_masks = [f for f in scene.all_frames if f.mask is not None]
    if with_masks and len(with_masks) != len(scene.all_frames):
        missing = next(f for f in scene.all_frames if f.mask is None)
        raise SceneError(f"{missing.rgb_path}: has no mask while other images do "
                         f"(give masks for every image or none)")
    posed = [f for f in scene.all_frames if f.camera is not None and f.camera.cam_to_world is not None]
    if posed and len(posed) != len(scene.all_frames):
        scene.warnings.append("cam_to_world is given for some images only: treating the scene as unposed")


# --------------------------------------------------------------------------- output


def write_json_atomic(path: str | Path, data: Any) -> None:
    """Write JSON to ``path`` atomically (temp file in the same folder, then rename)."""
    write_bytes_atomic(path, (json.dumps(data, indent=2) + "\n").encode())


def write_bytes_atomic(path: str | Path, payload: bytes) -> None:
    """Write bytes atomically: readers see either the old file or the complete new one. The file
    gets the permissions the umask allows (``0o666 & ~umask``), like a plainly created file."""
    from sparseart.io.outputs import file_mode

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as stream:
            stream.write(payload)
            stream.flush()
            os.fchmod(stream.fileno(), file_mode())
            os.fsync(stream.fileno())
        os.replace(temp_name, path)
    except BaseException:
        Path(temp_name).unlink(missing_ok=True)
        raise
