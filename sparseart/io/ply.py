"""Labelled point clouds as binary PLY files (readable by open3d, MeshLab, CloudCompare, trimesh).

Each vertex has ``x y z`` (float64, the result's frame and units), ``red green blue`` (uint8) and
``part`` (int32 part id; -1 = unassigned). Colours show the part (:func:`part_colours`) unless the
caller asks for the image colours.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sparseart.io.scene import write_bytes_atomic
from sparseart.types import Articulation

UNASSIGNED_RGB = (0.1, 0.1, 0.1)
STATIC_RGB = (0.62, 0.62, 0.62)
MOVABLE_RGB = ((0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16),
               (0.58, 0.4, 0.74), (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.74, 0.74, 0.13), (0.09, 0.75, 0.81))


def part_colour(part_id: int) -> tuple[float, float, float]:
    """RGB in [0, 1] of a part id: grey for the static part 0, near-black for -1, else a palette."""
    if part_id < 0:
        return UNASSIGNED_RGB
    if part_id == 0:
        return STATIC_RGB
    return MOVABLE_RGB[(part_id - 1) % len(MOVABLE_RGB)]


def part_colours(part: np.ndarray) -> np.ndarray:
    """(N, 3) float64 RGB in [0, 1] for an (N,) int part-id array. O(N)."""
    part = np.asarray(part, dtype=np.int64)
    out = np.empty((len(part), 3))
    for part_id in np.unique(part):
        out[part == part_id] = part_colour(int(part_id))
    return out


def ply_bytes(points: np.ndarray, colours: np.ndarray, part: np.ndarray | None = None) -> bytes:
    """A binary little-endian PLY of (N, 3) float64 ``points``, (N, 3) ``colours`` in [0, 1] and
    optional (N,) int ``part``. Raises ValueError on mismatched or non-finite arrays."""
    points = np.asarray(points, dtype=np.float64)
    colours = np.asarray(colours, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or colours.shape != points.shape:
        raise ValueError(f"ply: points {points.shape} and colours {colours.shape} must both be (N, 3)")
    if not np.all(np.isfinite(points)):
        raise ValueError("ply: points contain non-finite values")
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if part is not None:
        part = np.asarray(part, dtype=np.int32).reshape(-1)
        if part.shape[0] != points.shape[0]:
            raise ValueError(f"ply: {part.shape[0]} part ids for {points.shape[0]} points")
        fields.append(("part", "<i4"))
    vertices = np.empty(len(points), dtype=fields)
    for k, name in enumerate("xyz"):
        vertices[name] = points[:, k]
    rgb = np.clip(np.round(colours * 255.0), 0, 255).astype(np.uint8)
    for k, name in enumerate(("red", "green", "blue")):
        vertices[name] = rgb[:, k]
    if part is not None:
        vertices["part"] = part
    types = {"<f8": "double", "u1": "uchar", "<i4": "int"}
    header = ["ply", "format binary_little_endian 1.0", "comment written by sparseart",
              f"element vertex {len(points)}", *(f"property {types[t]} {n}" for n, t in fields), "end_header"]
    return ("\n".join(header) + "\n").encode("ascii") + vertices.tobytes()


def write_ply(path: str | Path, points: np.ndarray, colours: np.ndarray, part: np.ndarray | None = None) -> Path:
    """Write :func:`ply_bytes` to ``path`` atomically and return the path."""
    path = Path(path)
    write_bytes_atomic(path, ply_bytes(points, colours, part))
    return path


def write_labelled_clouds(result: Articulation, out_dir: str | Path, image_colours: bool = False) -> list[Path]:
    """``out_dir/start_parts.ply`` and ``out_dir/end_parts.ply``: every lifted point of each state
    with its part id (``result.labels``), coloured by part (or by the images with ``image_colours``).
    Raises ValueError when the result carries no clouds or labels (e.g. built by hand)."""
    if result.start_cloud is None or result.end_cloud is None or result.labels is None:
        raise ValueError("--ply: the result carries no clouds/labels to write")
    written = []
    for state, cloud, part in (("start", result.start_cloud, result.labels.start_part),
                               ("end", result.end_cloud, result.labels.end_part)):
        colours = cloud.colors if image_colours else part_colours(part)
        written.append(write_ply(Path(out_dir) / f"{state}_parts.ply", cloud.points, colours, part))
    return written
