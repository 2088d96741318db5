"""Scene-folder reading and validation (design section 2) and atomic result writing.

Every problem with the input raises :class:`sparseart.types.SceneError` whose message is one line
naming the offending file and what is wrong, so the CLI can print it and exit with code 2 before
any output is written.
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from sparseart.types import STATES, Camera, Frame, Scene, SceneError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
MAX_VIEWS_PER_STATE = 4
RIGIDITY_TOLERANCE = 1e-3  # max |R^T R - I| and |det R - 1| accepted for cam_to_world


def load_scene(root: str | Path, require_depth: bool = True) -> Scene:
    """Read and validate a scene folder.

    Args:
        root: the scene folder (``start/``, ``end/``, optional ``cameras.json``).
        require_depth: when True, a scene without depth is an error (no reconstructor given).

    Returns:
        A :class:`Scene` whose frames hold rgb (H, W, 3) uint8, depth (H, W) float64 metres,
        masks (H, W) int64 and cameras (K and optional cam_to_world, float64).

    Raises:
        SceneError: one line naming the file and the problem.
    """
    root = Path(root)
    if not root.exists():
        raise SceneError(f"{root}: scene folder does not exist")
    if not root.is_dir():
        raise SceneError(f"{root}: not a folder (expected a scene folder with start/ and end/)")
    cameras = _read_cameras_json(root)
    depth_scale = cameras.get("depth_scale", 1000.0) if cameras else 1000.0
    warnings: list[str] = []
    states: dict[str, list[Frame]] = {}
    for state in STATES:
        states[state] = _read_state(root, state, cameras, float(depth_scale), warnings)
    scene = Scene(root=root, start=states["start"], end=states["end"], depth_scale=float(depth_scale),
                  warnings=warnings)
    _check_consistency(scene, require_depth)
    return scene


# --------------------------------------------------------------------------- cameras.json


def _read_cameras_json(root: Path) -> dict[str, Any] | None:
    path = root / "cameras.json"
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as error:
        raise SceneError(f"{path}: cannot read file ({error})") from None
    except json.JSONDecodeError as error:
        raise SceneError(f"{path}: invalid JSON at line {error.lineno}: {error.msg}") from None
    if not isinstance(data, dict):
        raise SceneError(f"{path}: expected a JSON object at top level")
    convention = data.get("convention", "opencv")
    if convention != "opencv":
        raise SceneError(f"{path}: convention '{convention}' not supported (use 'opencv')")
    scale = data.get("depth_scale", 1000.0)
    if not isinstance(scale, (int, float)) or not np.isfinite(scale) or scale <= 0:
        raise SceneError(f"{path}: depth_scale must be a positive number, got {scale!r}")
    for state in STATES:
        entries = data.get(state, [])
        if not isinstance(entries, list):
            raise SceneError(f"{path}: '{state}' must be a list of camera entries")
        for i, entry in enumerate(entries):
            if not isinstance(entry, dict):
                raise SceneError(f"{path}: {state}[{i}] must be an object")
    return data


def _matrix(value: Any, shape: tuple[int, int], where: str, path: Path) -> np.ndarray:
    try:
        matrix = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise SceneError(f"{path}: {where} is not a numeric matrix") from None
    if matrix.shape != shape:
        raise SceneError(f"{path}: {where} must be {shape[0]}x{shape[1]}, got shape {matrix.shape}")
    if not np.all(np.isfinite(matrix)):
        raise SceneError(f"{path}: {where} has non-finite values")
    return matrix


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
    if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1.0) > 1e-6 or np.any(K[2, :2] != 0):
        raise SceneError(f"{path}: {where} K must be [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0")
    cam_to_world = None
    if entry.get("cam_to_world") is not None:
        cam_to_world = _matrix(entry["cam_to_world"], (4, 4), f"{where} cam_to_world", path)
        rotation = cam_to_world[:3, :3]
        orthogonality = np.abs(rotation.T @ rotation - np.eye(3)).max()
        if (orthogonality > RIGIDITY_TOLERANCE or abs(np.linalg.det(rotation) - 1.0) > RIGIDITY_TOLERANCE
                or np.abs(cam_to_world[3] - [0, 0, 0, 1]).max() > 1e-9):
            raise SceneError(f"{path}: {where} cam_to_world is not a rigid transform "
                             f"(rotation must be orthonormal with det +1, last row 0 0 0 1)")
    return Camera(K=K, width=width, height=height, cam_to_world=cam_to_world)


# --------------------------------------------------------------------------- images


def _read_image(path: Path, flags: int) -> np.ndarray:
    import cv2

    try:
        image = cv2.imread(str(path), flags)
    except cv2.error:
        image = None
    if image is None:
        raise SceneError(f"{path}: cannot read image (missing, empty or not a valid PNG/JPEG)")
    return image


def _read_rgb(path: Path) -> np.ndarray:
    import cv2

    image = _read_image(path, cv2.IMREAD_UNCHANGED)
    if image.dtype != np.uint8:
        raise SceneError(f"{path}: RGB image must be 8-bit, got {image.dtype}")
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    elif image.shape[2] == 4:
        image = image[:, :, :3]
    elif image.shape[2] != 3:
        raise SceneError(f"{path}: RGB image must have 3 channels, got {image.shape[2]}")
    return np.ascontiguousarray(image[:, :, ::-1])


def _read_depth(path: Path, depth_scale: float) -> np.ndarray:
    if path.suffix == ".npy":
        try:
            depth = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as error:
            raise SceneError(f"{path}: cannot read depth array ({error})") from None
        if depth.ndim != 2 or depth.dtype.kind != "f":
            raise SceneError(f"{path}: depth .npy must be a 2-D float array of metres, "
                             f"got {depth.dtype} with shape {depth.shape}")
        depth = depth.astype(np.float64)
        depth[~np.isfinite(depth)] = 0.0
    else:
        import cv2

        raw = _read_image(path, cv2.IMREAD_UNCHANGED)
        if raw.ndim != 2 or raw.dtype != np.uint16:
            raise SceneError(f"{path}: depth PNG must be single-channel uint16, got {raw.dtype} "
                             f"with {1 if raw.ndim == 2 else raw.shape[2]} channels")
        depth = raw.astype(np.float64) / depth_scale
    if np.any(depth < 0):
        raise SceneError(f"{path}: depth has negative values")
    if not np.any(depth > 0):
        raise SceneError(f"{path}: depth is all zero (no valid pixel)")
    return depth


def _read_mask(path: Path) -> np.ndarray:
    import cv2

    raw = _read_image(path, cv2.IMREAD_UNCHANGED)
    if raw.ndim != 2 or raw.dtype not in (np.uint8, np.uint16):
        raise SceneError(f"{path}: mask must be a single-channel uint8/uint16 label image")
    if not np.any(raw):
        raise SceneError(f"{path}: mask is empty (every pixel is 0 = background)")
    return raw.astype(np.int64)


def _find_companion(folder: Path, stem: str, suffixes: tuple[str, ...]) -> Path | None:
    for suffix in suffixes:
        candidate = folder / f"{stem}{suffix}"
        if candidate.exists():
            return candidate
    return None


def _read_state(root: Path, state: str, cameras: dict | None, depth_scale: float,
                warnings: list[str]) -> list[Frame]:
    state_dir = root / state
    if not state_dir.is_dir():
        raise SceneError(f"{state_dir}: missing state folder (a scene needs start/ and end/)")
    rgb_dir = state_dir / "rgb"
    if not rgb_dir.is_dir():
        raise SceneError(f"{rgb_dir}: missing rgb/ folder")
    image_paths = sorted(p for p in rgb_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not image_paths:
        raise SceneError(f"{rgb_dir}: no images (.png/.jpg)")
    if len(image_paths) > MAX_VIEWS_PER_STATE:
        warnings.append(f"{rgb_dir}: {len(image_paths)} images; 1-{MAX_VIEWS_PER_STATE} per state "
                        f"is the supported range, all are used")
    depth_dir, mask_dir = state_dir / "depth", state_dir / "mask"
    camera_path = root / "cameras.json"
    entries = cameras.get(state, []) if cameras else []
    frames = []
    for index, rgb_path in enumerate(image_paths):
        rgb = _read_rgb(rgb_path)
        height, width = rgb.shape[:2]
        frame = Frame(state=state, index=index, rgb_path=rgb_path, rgb=rgb)
        if depth_dir.is_dir():
            depth_path = _find_companion(depth_dir, rgb_path.stem, (".png", ".npy"))
            if depth_path is None:
                raise SceneError(f"{depth_dir}: no depth for {rgb_path.name} "
                                 f"(expected {rgb_path.stem}.png or {rgb_path.stem}.npy)")
            frame.depth = _read_depth(depth_path, depth_scale)
            frame.depth_path = depth_path
            if frame.depth.shape != (height, width):
                raise SceneError(f"{depth_path}: size {frame.depth.shape[1]}x{frame.depth.shape[0]} "
                                 f"does not match image {rgb_path.name} ({width}x{height})")
        if mask_dir.is_dir():
            mask_path = _find_companion(mask_dir, rgb_path.stem, (".png",))
            if mask_path is None:
                raise SceneError(f"{mask_dir}: no mask for {rgb_path.name} (expected {rgb_path.stem}.png)")
            frame.mask = _read_mask(mask_path)
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
    """Write bytes atomically: readers see either the old file or the complete new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as stream:
            stream.write(payload)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temp_name, path)
    except BaseException:
        Path(temp_name).unlink(missing_ok=True)
        raise
