"""3D Gaussian Splatting PLY files (binary little-endian), as read by common splat viewers.

Vertex properties, all float32: x, y, z, nx, ny, nz (zeros), f_dc_0..2 (SH degree 0), opacity
(logit), scale_0..2 (log), rot_0..3 (quaternion w, x, y, z) and an extra ``mobility`` in [0, 1]
(viewers ignore unknown properties). Written with a numpy structured array, atomically.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sparseart.io.scene import write_bytes_atomic
from ..types import SceneError

PROPERTIES = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
              "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3", "mobility")


def gaussians_to_ply_bytes(means: np.ndarray, f_dc: np.ndarray, opacity_logits: np.ndarray,
                           log_scales: np.ndarray, quats: np.ndarray, mobility: np.ndarray | None = None) -> bytes:
    """The PLY file content for N Gaussians: means (N, 3) frame units, f_dc (N, 3),
    opacity_logits (N,), log_scales (N, 3), quats (N, 4) (w, x, y, z), mobility (N,) in [0, 1]
    (0 when None). Raises ValueError on mismatched shapes or non-finite values."""
    means = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    count = len(means)
    columns = {
        "xyz": means, "f_dc": np.asarray(f_dc, np.float64).reshape(count, 3),
        "opacity": np.asarray(opacity_logits, np.float64).reshape(count, 1),
        "scale": np.asarray(log_scales, np.float64).reshape(count, 3),
        "rot": np.asarray(quats, np.float64).reshape(count, 4),
        "mobility": (np.zeros((count, 1)) if mobility is None
                     else np.asarray(mobility, np.float64).reshape(count, 1)),
    }
    for name, column in columns.items():
        if not np.isfinite(column).all():
            raise ValueError(f"3DGS PLY: {name} has NaN or inf values")
    vertex = np.zeros(count, dtype=[(name, "<f4") for name in PROPERTIES])
    stacked = np.concatenate([columns["xyz"], np.zeros((count, 3)), columns["f_dc"], columns["opacity"],
                              columns["scale"], columns["rot"], columns["mobility"]], axis=1)
    for k, name in enumerate(PROPERTIES):
        vertex[name] = stacked[:, k]
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {count}\n" + \
        "".join(f"property float {name}\n" for name in PROPERTIES) + "end_header\n"
    return header.encode("ascii") + vertex.tobytes()


def write_gaussians_ply(path: str | Path, arrays: dict[str, np.ndarray]) -> Path:
    """Write ``GaussianSet.to_numpy()``-style arrays (means, f_dc, opacity_logits, log_scales,
    quats, mobility) to a 3DGS PLY atomically; returns the path."""
    payload = gaussians_to_ply_bytes(arrays["means"], arrays["f_dc"], arrays["opacity_logits"], arrays["log_scales"],
                                     arrays["quats"], arrays.get("mobility"))
    write_bytes_atomic(path, payload)
    return Path(path)


def read_gaussians_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Read a binary little-endian 3DGS PLY (float properties). Returns float64 arrays: means
    (N, 3), f_dc (N, 3), opacity_logits (N,), log_scales (N, 3), quats (N, 4), mobility (N,)
    (zeros when absent). Raises SceneError naming the file when it is not such a PLY."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise SceneError(f"{path}: cannot read ({error.strerror})") from None
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise SceneError(f"{path}: not a PLY file (no ply/end_header)")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise SceneError(f"{path}: only binary_little_endian 3DGS PLY files are supported")
    count, names, types = None, [], []
    for line in header:
        words = line.split()
        if words[:2] == ["element", "vertex"]:
            count = int(words[2])
        elif words[:1] == ["property"] and count is not None and len(words) == 3:
            types.append({"float": "<f4", "double": "<f8", "uchar": "u1", "int": "<i4"}.get(words[1]))
            names.append(words[2])
    if count is None or None in types:
        raise SceneError(f"{path}: no vertex element or an unsupported property type")
    dtype = np.dtype(list(zip(names, types)))
    body = data[end + len(b"end_header\n"):]
    if len(body) < count * dtype.itemsize:
        raise SceneError(f"{path}: truncated ({len(body)} bytes for {count} vertices of {dtype.itemsize})")
    vertex = np.frombuffer(body[:count * dtype.itemsize], dtype=dtype)
    needed = [n for n in PROPERTIES if n not in ("nx", "ny", "nz", "mobility")]
    missing = [n for n in needed if n not in names]
    if missing:
        raise SceneError(f"{path}: missing 3DGS properties {missing}")

    def columns(*keys):
        return np.stack([vertex[k].astype(np.float64) for k in keys], axis=1)

    return {"means": columns("x", "y", "z"), "f_dc": columns("f_dc_0", "f_dc_1", "f_dc_2"),
            "opacity_logits": vertex["opacity"].astype(np.float64),
            "log_scales": columns("scale_0", "scale_1", "scale_2"),
            "quats": columns("rot_0", "rot_1", "rot_2", "rot_3"),
            "mobility": (vertex["mobility"].astype(np.float64) if "mobility" in names else np.zeros(count))}
