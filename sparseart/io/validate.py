"""The one validation boundary: everything that enters sparseart is checked here, once.

Past this module the code may trust its inputs. Every failure raises
:class:`~sparseart.types.SceneError` with one line naming the file (or the argument) and the field.

What is checked, and the limits (module constants, so they can be quoted and tested):

* **Files** are opened only when they are regular files (a FIFO, a device such as ``/dev/zero``,
  a directory or a broken symlink in place of a file is an error, never a hang), with
  ``O_NONBLOCK`` and a size cap read *before* reading (``MAX_JSON_BYTES``,
  ``MAX_IMAGE_FILE_BYTES``, ``MAX_NPY_FILE_BYTES``).
* **JSON** (``cameras.json``): UTF-8, nesting depth <= ``MAX_JSON_DEPTH`` (checked on the raw
  text before parsing), no ``NaN``/``Infinity`` literals, no duplicate keys, integers too large for
  a float become ``inf`` and fail the finiteness checks. Numbers are ``int``/``float`` but never
  ``bool`` (``true`` is not 1).
* **Images** (PNG/JPEG, recognised by their magic bytes, not their suffix): width and height read
  from the header (PNG IHDR, JPEG SOF) before any decoding; at most ``MAX_IMAGE_PIXELS`` per image
  and ``MAX_SCENE_PIXELS`` over the scene; decoding is silenced (libpng/libjpeg and OpenCV print
  to the process's stderr otherwise) and its result checked against the header.
* **.npy depth**: magic and header parsed with :mod:`numpy.lib.format` before loading; an
  ``.npz`` (zip) or pickle is refused; dtype must be float16/32/64, shape 2-D, the header's size
  must fit ``MAX_IMAGE_PIXELS`` and match the file's length (a truncated or padded file is an
  error). The array is built from the bytes already read (``np.load`` is never called).
* **Numeric ranges**: ``depth_scale`` in ``DEPTH_SCALE_RANGE``; focal lengths within
  ``FOCAL_RANGE`` times the image's larger side; principal point within one image size of the
  image; positive depths and camera positions within ``DEPTH_RANGE_METRES`` / ``MAX_COORDINATE``.
* **Depth confidence** (``conf/NNN.npy``): a float ``.npy`` like depth, the depth's size, every
  value finite and in [0, 1] (:func:`check_depth_confidence`).
* **Masks**: at most ``MAX_MASK_IDS`` ids per image, and at least ``MIN_MASK_COVERAGE`` of the
  labelled pixels in ids of ``MIN_MASK_SEGMENT_PIXELS`` pixels or more (a mask cut into thousands
  of specks carries no part information).
* **Clouds given to** :func:`sparseart.run_clouds`: :func:`validate_clouds`.

Estimated memory of a run: about 80 bytes per input pixel on top of ~0.4 GB (measured: 3 views of
960x720 per state, 4.1 M pixels -> 0.67 GB peak), so ``MAX_SCENE_PIXELS`` keeps a scene under
~3 GB.
"""
from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
import stat
import struct
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from sparseart.geometry.budget import POINT_BUDGET, subsample_to_budget
from sparseart.types import LabelledCloud, SceneError

# ---------------------------------------------------------------------- limits (documented)

MAX_JSON_BYTES = 4 * 2**20            # cameras.json: 4 MiB holds thousands of camera entries
MAX_JSON_DEPTH = 16                   # cameras.json needs 5 levels ({start: [{K: [[...]]}]})
MAX_IMAGE_FILE_BYTES = 256 * 2**20    # one PNG/JPEG file
MAX_NPY_FILE_BYTES = 256 * 2**20      # one .npy depth (float64 4096 x 4096 = 128 MiB)
MAX_IMAGE_PIXELS = 4096 * 4096        # width x height of one image (a 12 MP phone photo fits)
MAX_SCENE_PIXELS = 32 * 2**20         # all images of both states together (~80 B/pixel: < 3 GB)
MAX_IMAGES_PER_STATE = 32             # more views than this is not a sparse-view scene
MAX_MASK_IDS = 1000                   # distinct ids in one mask image
MIN_MASK_SEGMENT_PIXELS = 30          # an id smaller than this is a speck (the labeler drops it)
MIN_MASK_COVERAGE = 0.5               # share of labelled pixels that must lie in non-speck ids
DEPTH_SCALE_RANGE = (1e-3, 1e9)       # PNG depth units per metre: 1 unit = 1 km ... 1 nm
DEPTH_RANGE_METRES = (1e-6, 1e7)      # a positive depth outside this is an error (0 = invalid)
MAX_COORDINATE = 1e7                  # |camera position| and |cloud coordinate| in scene units
FOCAL_RANGE = (0.05, 500.0)           # fx, fy / max(width, height): 175 deg ... 0.1 deg of view
MIN_CLOUD_POINTS = 10                 # per state (the labelers need at least this many)
CLOUD_POINT_BUDGET = POINT_BUDGET     # run_clouds: larger clouds are subsampled to this (seeded)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SIGNATURE = b"\xff\xd8"
NPZ_SIGNATURE = b"PK\x03\x04"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}   # colour type -> channels as decoded by OpenCV
_PNG_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


# ---------------------------------------------------------------------- messages


def one_line(text: str) -> str:
    """``text`` with control characters (newline, carriage return, escape ...) escaped, so that a
    message built from a hostile file name stays one line."""
    return "".join(c if c.isprintable() else c.encode("unicode_escape", "backslashreplace").decode("ascii")
                   for c in text)


def _fail(path: Path | str, problem: str) -> SceneError:
    return SceneError(one_line(f"{path}: {problem}"))


# ---------------------------------------------------------------------- files


def read_regular_file(path: Path, max_bytes: int, what: str = "file") -> bytes:
    """The bytes of ``path``, which must be a regular file of at most ``max_bytes`` bytes.

    Opened with ``O_NONBLOCK`` (a FIFO swapped in after a check cannot block) and checked with
    ``fstat`` on the open descriptor, so a FIFO, device, socket or directory is refused without
    reading. Symlinks to regular files are followed. O(size).

    Raises:
        SceneError: missing, not a regular file, too large, unreadable.
    """
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        handle = os.open(path, flags)
    except FileNotFoundError:
        if os.path.lexists(path):
            raise _fail(path, f"{what} is a broken symlink") from None
        raise _fail(path, f"{what} does not exist") from None
    except IsADirectoryError:
        raise _fail(path, f"{what} is a folder, expected a regular file") from None
    except OSError as error:
        raise _fail(path, f"cannot open {what} ({error.strerror})") from None
    try:
        info = os.fstat(handle)
        if not stat.S_ISREG(info.st_mode):
            raise _fail(path, f"{what} is not a regular file ({_file_kind(info.st_mode)}); refusing to read it")
        if info.st_size > max_bytes:
            raise _fail(path, f"{what} is {info.st_size} bytes, more than the limit of {max_bytes}")
        chunks, total = [], 0
        while True:
            try:
                chunk = os.read(handle, min(1 << 20, max_bytes + 1 - total))
            except BlockingIOError:  # pragma: no cover - regular files do not block
                raise _fail(path, f"{what} would block") from None
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
            if total > max_bytes:   # the file grew while being read
                raise _fail(path, f"{what} is larger than the limit of {max_bytes} bytes")
        return b"".join(chunks)
    except OSError as error:
        raise _fail(path, f"cannot read {what} ({error.strerror})") from None
    finally:
        os.close(handle)


def _file_kind(mode: int) -> str:
    for test, name in ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a folder")):
        if test(mode):
            return name
    return "not a file"


def is_present(path: Path) -> bool:
    """True when something (even a broken symlink, a FIFO) is at ``path``: present-but-bad files
    must be reported, not skipped as absent."""
    return os.path.lexists(path)


# ---------------------------------------------------------------------- JSON

_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)


def json_nesting_depth(data: bytes) -> int:
    """Maximum nesting depth of ``[``/``{`` in JSON text (strings skipped), without parsing.
    O(len(data)) in C-speed regex and numpy operations."""
    stripped = _JSON_STRING.sub(b'""', data)
    codes = np.frombuffer(stripped, dtype=np.uint8)
    steps = np.zeros(codes.shape, dtype=np.int32)
    steps[(codes == ord("[")) | (codes == ord("{"))] = 1
    steps[(codes == ord("]")) | (codes == ord("}"))] = -1
    return int(np.cumsum(steps).max(initial=0))


class _JsonProblem(ValueError):
    pass


def _reject_constant(name: str) -> Any:
    raise _JsonProblem(f"non-standard number {name} (JSON has no NaN or Infinity)")


def _parse_int(text: str) -> int | float:
    # Beyond 18 digits an int may not fit a float; as a float it is finite or inf (rejected later).
    return int(text) if len(text.lstrip("-")) <= 18 else float(text)


def _unique_object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    result: dict[str, Any] = {}
    for key, value in pairs:
        if key in result:
            raise _JsonProblem(f"duplicate key {key!r}")
        result[key] = value
    return result


def parse_json(data: bytes, path: Path | str, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """Parse JSON text with the limits of the module docstring.

    Raises:
        SceneError: not UTF-8, too deep, invalid JSON, NaN/Infinity, duplicate keys.
    """
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        raise _fail(path, f"not UTF-8 text (byte {error.start})") from None
    depth = json_nesting_depth(data)
    if depth > max_depth:
        raise _fail(path, f"JSON nested {depth} levels deep, more than the limit of {max_depth}")
    try:
        return json.loads(text, parse_constant=_reject_constant, parse_int=_parse_int,
                          object_pairs_hook=_unique_object)
    except json.JSONDecodeError as error:
        raise _fail(path, f"invalid JSON at line {error.lineno}: {error.msg}") from None
    except _JsonProblem as error:
        raise _fail(path, f"invalid JSON: {error}") from None
    except (ValueError, RecursionError) as error:
        raise _fail(path, f"invalid JSON: {type(error).__name__}") from None


def load_json_file(path: Path, max_bytes: int = MAX_JSON_BYTES, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """:func:`read_regular_file` + :func:`parse_json`."""
    return parse_json(read_regular_file(path, max_bytes, "JSON file"), path, max_depth)


# ---------------------------------------------------------------------- numbers


def is_number(value: Any) -> bool:
    """A JSON number: int or float, never bool."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def number(value: Any, where: str, path: Path | str, low: float | None = None, high: float | None = None,
           low_open: bool = False) -> float:
    """``value`` as a finite float within [low, high] (``low_open``: (low, high]).

    Raises:
        SceneError: not a number (bools are not numbers), not finite, out of range.
    """
    if not is_number(value):
        raise _fail(path, f"{where} must be a number, got {_type_name(value)}")
    try:
        result = float(value)
    except OverflowError:
        result = math.inf
    if not math.isfinite(result):
        raise _fail(path, f"{where} must be finite, got {value!r}"[:300])
    if low is not None and (result < low or (low_open and result == low)):
        raise _fail(path, f"{where} must be {'>' if low_open else '>='} {low:g}, got {result:g}")
    if high is not None and result > high:
        raise _fail(path, f"{where} must be <= {high:g}, got {result:g}")
    return result


def matrix(value: Any, shape: tuple[int, int], where: str, path: Path | str) -> np.ndarray:
    """A ``rows x cols`` matrix given as nested JSON lists of finite numbers (no bools)."""
    rows, cols = shape
    if not isinstance(value, list) or len(value) != rows or not all(isinstance(r, list) and len(r) == cols
                                                                      for r in value):
        raise _fail(path, f"{where} must be a {rows}x{cols} list of lists of numbers, got {_shape_of(value)}")
    result = np.empty(shape, dtype=np.float64)
    for i, row in enumerate(value):
        for j, item in enumerate(row):
            result[i, j] = number(item, f"{where}[{i}][{j}]", path)
    return result


def _type_name(value: Any) -> str:
    if isinstance(value, bool):
        return f"boolean {str(value).lower()}"
    if value is None:
        return "null"
    return {dict: "an object", list: "a list", str: "a string"}.get(type(value), type(value).__name__)


def _shape_of(value: Any) -> str:
    if isinstance(value, list):
        inner = {len(r) if isinstance(r, list) else "scalar" for r in value}
        return f"a list of {len(value)} rows ({', '.join(str(i) for i in sorted(inner, key=str))} wide)"
    return _type_name(value)


def text(value: Any, where: str, path: Path | str, max_chars: int = 4096) -> str:
    if not isinstance(value, str):
        raise _fail(path, f"{where} must be a string, got {_type_name(value)}")
    if len(value) > max_chars:
        raise _fail(path, f"{where} is longer than {max_chars} characters")
    return value


# ---------------------------------------------------------------------- cameras


def check_intrinsics(K: np.ndarray, width: int, height: int, where: str, path: Path | str) -> None:
    """Plausible pinhole intrinsics for a ``width x height`` image (``FOCAL_RANGE``; principal
    point within one image size of the image; K[1, 0] = 0; last row 0 0 1; |skew| <= fx)."""
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    if fx <= 0 or fy <= 0 or K[1, 0] != 0 or abs(K[2, 2] - 1.0) > 1e-6 or np.any(K[2, :2] != 0):
        raise _fail(path, f"{where} K must be [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0")
    side = max(width, height)
    low, high = FOCAL_RANGE[0] * side, FOCAL_RANGE[1] * side
    for name, value in (("fx", fx), ("fy", fy)):
        if not low <= value <= high:
            raise _fail(path, f"{where} K {name} = {value:g} px is implausible for a {width}x{height} image "
                              f"(expected {low:g} .. {high:g})")
    if not (-width <= cx <= 2 * width and -height <= cy <= 2 * height):
        raise _fail(path, f"{where} K principal point ({cx:g}, {cy:g}) lies far outside the {width}x{height} image")
    if abs(skew) > fx:
        raise _fail(path, f"{where} K skew {skew:g} is larger than fx")


def check_pose(cam_to_world: np.ndarray, where: str, path: Path | str, tolerance: float) -> None:
    """A rigid 4x4 transform (orthonormal rotation, det +1, last row 0 0 0 1) whose translation is
    within ``MAX_COORDINATE``."""
    rotation = cam_to_world[:3, :3]
    orthogonality = np.abs(rotation.T @ rotation - np.eye(3)).max()
    if (orthogonality > tolerance or abs(np.linalg.det(rotation) - 1.0) > tolerance
            or np.abs(cam_to_world[3] - [0, 0, 0, 1]).max() > 1e-9):
        raise _fail(path, f"{where} cam_to_world is not a rigid transform "
                          f"(rotation must be orthonormal with det +1, last row 0 0 0 1)")
    if np.abs(cam_to_world[:3, 3]).max() > MAX_COORDINATE:
        raise _fail(path, f"{where} cam_to_world translation {np.abs(cam_to_world[:3, 3]).max():g} is beyond "
                          f"the plausible range (|t| <= {MAX_COORDINATE:g} scene units)")


# ---------------------------------------------------------------------- images


@dataclass(frozen=True)
class ImageHeader:
    """What an image file's header declares. kind: "png" | "jpeg"; bit_depth per channel."""

    kind: str
    width: int
    height: int
    channels: int
    bit_depth: int


def image_header(data: bytes, path: Path | str) -> ImageHeader:
    """Width, height, channels and bit depth from a PNG IHDR or a JPEG SOF marker, without
    decoding; checks the size against ``MAX_IMAGE_PIXELS``. O(number of JPEG markers).

    Raises:
        SceneError: not a PNG/JPEG, a malformed header, an empty or too large image.
    """
    if data.startswith(PNG_SIGNATURE):
        header = _png_header(data, path)
    elif data.startswith(JPEG_SIGNATURE):
        header = _jpeg_header(data, path)
    elif not data:
        raise _fail(path, "cannot read image: the file is empty")
    else:
        raise _fail(path, "cannot read image: not a PNG or JPEG file")
    if header.width < 1 or header.height < 1:
        raise _fail(path, f"image header declares an empty image ({header.width}x{header.height})")
    if header.width * header.height > MAX_IMAGE_PIXELS:
        raise _fail(path, f"image header declares {header.width}x{header.height} pixels, more than the limit of "
                          f"{MAX_IMAGE_PIXELS} pixels per image (downscale it)")
    return header


def _png_header(data: bytes, path: Path | str) -> ImageHeader:
    if len(data) < 33 or data[12:16] != b"IHDR" or struct.unpack(">I", data[8:12])[0] != 13:
        raise _fail(path, "cannot read image: PNG without a valid IHDR header (truncated?)")
    width, height, bit_depth, colour = struct.unpack(">IIBB", data[16:26])
    if colour not in _PNG_CHANNELS or bit_depth not in _PNG_DEPTHS[colour]:
        raise _fail(path, f"cannot read image: PNG colour type {colour} with bit depth {bit_depth} is not valid")
    return ImageHeader("png", width, height, _PNG_CHANNELS[colour], 16 if bit_depth == 16 else 8)


def _jpeg_header(data: bytes, path: Path | str) -> ImageHeader:
    offset = 2
    while offset + 4 <= len(data):
        if data[offset] != 0xFF:
            raise _fail(path, "cannot read image: malformed JPEG (bad marker)")
        marker = data[offset + 1]
        if marker == 0xFF:          # fill byte
            offset += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):   # markers without a length
            offset += 2
            continue
        length = struct.unpack(">H", data[offset + 2:offset + 4])[0]
        if length < 2:
            raise _fail(path, "cannot read image: malformed JPEG (bad segment length)")
        if marker in _JPEG_SOF:
            if offset + 10 > len(data):
                break
            precision, height, width, components = struct.unpack(">BHHB", data[offset + 4:offset + 10])
            if components not in (1, 3, 4):
                raise _fail(path, f"cannot read image: JPEG with {components} components is not supported")
            if data.rfind(b"\xff\xd9") < offset:
                raise _fail(path, "cannot read image: JPEG is truncated (no end-of-image marker)")
            return ImageHeader("jpeg", width, height, 1 if components == 1 else 3, precision)
        if marker == 0xDA:           # start of scan before any frame header
            break
        offset += 2 + length
    raise _fail(path, "cannot read image: JPEG without a frame header (truncated?)")


_QUIET_LOCK = threading.Lock()


@contextlib.contextmanager
def quiet_native_stderr() -> Iterator[None]:
    """Silence what native libraries (libpng, libjpeg, OpenCV's logger) print to file descriptor 2
    while the block runs; Python's ``sys.stderr`` is untouched. Process-wide: other threads'
    native stderr output is lost meanwhile (this wraps only short decode calls)."""
    import cv2

    with _QUIET_LOCK:
        try:
            level = cv2.utils.logging.getLogLevel()
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
        except AttributeError:  # pragma: no cover - very old OpenCV
            level = None
        saved = None
        try:
            try:
                sys.stderr.flush()
            except (AttributeError, ValueError, OSError):
                pass
            try:
                saved = os.dup(2)
                with open(os.devnull, "wb") as sink:
                    os.dup2(sink.fileno(), 2)
            except OSError:
                saved = None
            yield
        finally:
            if saved is not None:
                os.dup2(saved, 2)
                os.close(saved)
            if level is not None:
                cv2.utils.logging.setLogLevel(level)


def decode_image(data: bytes, header: ImageHeader, path: Path | str) -> np.ndarray:
    """Decode checked image bytes (OpenCV, ``IMREAD_UNCHANGED``; BGR channel order), silently.

    Raises:
        SceneError: corrupt data, or a decoded size that disagrees with the header.
    """
    import cv2

    with quiet_native_stderr():
        try:
            image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        except cv2.error:
            image = None
    if image is None:
        raise _fail(path, f"cannot read image: corrupt {header.kind.upper()} data")
    if image.shape[:2] != (header.height, header.width):
        raise _fail(path, f"decoded image is {image.shape[1]}x{image.shape[0]}, its header says "
                          f"{header.width}x{header.height}")
    return image


def read_image_file(path: Path) -> tuple[np.ndarray, ImageHeader]:
    """:func:`read_regular_file` + :func:`image_header` + :func:`decode_image`."""
    data = read_regular_file(path, MAX_IMAGE_FILE_BYTES, "image")
    header = image_header(data, path)
    return decode_image(data, header, path), header


# ---------------------------------------------------------------------- .npy


def read_npy_file(path: Path, kinds: str = "f", max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """A 2-D array from a ``.npy`` file, its header checked before anything is allocated.

    kinds: allowed dtype kinds (``"f"`` = float16/32/64). Pickles and ``.npz`` archives are
    refused; the header's shape must fit ``max_pixels`` and its byte count the file's length.

    Raises:
        SceneError: one line naming the file and the problem.
    """
    from numpy.lib import format as npy

    data = read_regular_file(path, MAX_NPY_FILE_BYTES, ".npy file")
    if data.startswith(NPZ_SIGNATURE):
        raise _fail(path, "is a zip archive (.npz saved as .npy); save a single array with numpy.save")
    stream = io.BytesIO(data)
    try:
        version = npy.read_magic(stream)
        reader = {(1, 0): npy.read_array_header_1_0, (2, 0): npy.read_array_header_2_0}.get(version)
        if reader is None:
            raise ValueError(f"unsupported .npy format version {version}")
        shape, fortran, dtype = reader(stream, max_header_size=10000)
    except Exception as error:  # noqa: BLE001 - numpy's header parser raises ValueError, SyntaxError,
        # tokenize.TokenError, MemoryError ... on hostile headers; all mean "not a valid .npy"
        raise _fail(path, f"not a valid .npy file ({type(error).__name__}: {one_line(str(error))[:120]})") from None
    if dtype.hasobject or dtype.kind not in kinds or dtype.itemsize > 8 or dtype.fields is not None:
        raise _fail(path, f".npy dtype {dtype} is not allowed (expected a float array)")
    if len(shape) != 2:
        raise _fail(path, f".npy must be a 2-D array, got shape {shape}")
    if shape[0] < 1 or shape[1] < 1 or shape[0] * shape[1] > max_pixels:
        raise _fail(path, f".npy header declares shape {shape}: outside 1 .. {max_pixels} elements")
    expected = shape[0] * shape[1] * dtype.itemsize
    remaining = len(data) - stream.tell()
    if remaining != expected:
        raise _fail(path, f".npy header declares {expected} bytes of data, the file holds {remaining} "
                          f"({'truncated' if remaining < expected else 'trailing bytes'})")
    array = np.frombuffer(data, dtype=dtype, count=shape[0] * shape[1], offset=stream.tell())
    return array.reshape(shape, order="F" if fortran else "C")


# ---------------------------------------------------------------------- depth and masks


def check_depth_metres(depth: np.ndarray, path: Path | str) -> np.ndarray:
    """Depth in metres: non-finite values and positive values below ``DEPTH_RANGE_METRES[0]``
    (sub-micron: rounding residue, not a measurement) become 0 (invalid); negatives, values above
    ``DEPTH_RANGE_METRES[1]`` and a map without any valid pixel are errors. Returns (H, W)
    float64. O(H W)."""
    low, high = DEPTH_RANGE_METRES
    with np.errstate(all="ignore"):
        depth = np.asarray(depth, dtype=np.float64)
        depth = np.where(np.isfinite(depth), depth, 0.0)
        if np.any(depth < 0):
            raise _fail(path, "depth has negative values")
        positive = depth > 0
        if not np.any(positive):
            raise _fail(path, "depth is all zero (no valid pixel)")
        largest = float(depth.max())
        if largest > high:
            raise _fail(path, f"depth values up to {largest:g} m lie beyond the plausible range (<= {high:g} m; "
                              f"check depth_scale and the depth unit)")
        tiny = positive & (depth < low)
        if np.any(tiny):
            if np.all(tiny[positive]):
                raise _fail(path, f"every depth value is below {low:g} m (largest {largest:g} m; check depth_scale "
                                  f"and the depth unit)")
            depth = np.where(tiny, 0.0, depth)
    return depth


def check_depth_confidence(confidence: np.ndarray, path: Path | str) -> np.ndarray:
    """A depth confidence map (``conf/NNN.npy``): every value finite and within [0, 1] (a NaN or a
    value outside is an error, not clipped: the map is not what the contract says, so no value in
    it can be trusted). Returns (H, W) float64. O(H W)."""
    with np.errstate(all="ignore"):
        confidence = np.asarray(confidence, dtype=np.float64)
        finite = np.isfinite(confidence)
        if not finite.all():
            raise _fail(path, f"depth confidence has {int((~finite).sum())} non-finite values (NaN or inf); "
                              f"values must lie in [0, 1]")
        low, high = float(confidence.min()), float(confidence.max())
        if low < 0.0 or high > 1.0:
            raise _fail(path, f"depth confidence values must lie in [0, 1], got {low:g} .. {high:g}")
    return confidence


def check_mask_ids(mask: np.ndarray, path: Path | str) -> None:
    """A label image's ids: not all background, at most ``MAX_MASK_IDS`` ids, and at least
    ``MIN_MASK_COVERAGE`` of the labelled pixels in ids of ``MIN_MASK_SEGMENT_PIXELS`` pixels or
    more. O(H W)."""
    counts = np.bincount(mask.reshape(-1).astype(np.int64, copy=False))
    counts[0] = 0
    labelled = int(counts.sum())
    if labelled == 0:
        raise _fail(path, "mask is empty (every pixel is 0 = background)")
    n_ids = int(np.count_nonzero(counts))
    if n_ids > MAX_MASK_IDS:
        raise _fail(path, f"mask has {n_ids} ids, more than the limit of {MAX_MASK_IDS} "
                          f"(is it a label image? use --segmenter none to ignore masks)")
    covered = int(counts[counts >= MIN_MASK_SEGMENT_PIXELS].sum())
    if covered < MIN_MASK_COVERAGE * labelled:
        raise _fail(path, f"mask is fragmented: only {covered / labelled:.0%} of its labelled pixels lie in ids of "
                          f"at least {MIN_MASK_SEGMENT_PIXELS} pixels ({n_ids} ids); use --segmenter none to "
                          f"ignore masks")


# ---------------------------------------------------------------------- clouds (run_clouds)

_CLOUD_FIELDS = ("points", "colors", "segment", "frame_index", "pixel_index", "confidence")


def validate_clouds(start: Any, end: Any, budget: int = CLOUD_POINT_BUDGET,
                    seed: int = 0) -> tuple[LabelledCloud, LabelledCloud]:
    """Check the clouds given to :func:`sparseart.run_clouds`; return them (subsampled to
    ``budget`` points each when larger, :func:`sparseart.geometry.budget.subsample_to_budget`, so
    10 million points behave like ``budget``).

    Checks per cloud: a :class:`LabelledCloud`; every field a numpy array (not a list) of one
    length N >= ``MIN_CLOUD_POINTS``; ``points`` (N, 3) real and finite with
    |coordinate| <= ``MAX_COORDINATE`` and a non-zero extent; ``colors`` (N, 3) finite in [0, 1];
    ``segment`` / ``frame_index`` / ``pixel_index`` (N,) integers (not bool), segment >= -1,
    the others >= 0; ``confidence`` (N,) finite in [0, 1]; ``segment_source`` a dict.
    Integer or float32 arrays are converted to the documented dtypes (new arrays; the caller's
    clouds are not modified). O(N).

    Raises:
        SceneError: one line naming the state and the field, e.g. ``start.points: row 17 is not finite``.
    """
    checked = [_validate_cloud(name, cloud) for name, cloud in (("start", start), ("end", end))]
    return subsample_to_budget(checked[0], budget, seed), subsample_to_budget(checked[1], budget, seed + 1)


def _validate_cloud(name: str, cloud: Any) -> LabelledCloud:
    if not isinstance(cloud, LabelledCloud):
        raise SceneError(f"{name}: expected a sparseart.types.LabelledCloud, got {type(cloud).__name__}")
    arrays = {}
    for field in _CLOUD_FIELDS:
        value = getattr(cloud, field, None)
        if not isinstance(value, np.ndarray):
            raise SceneError(f"{name}.{field}: expected a numpy array, got {type(value).__name__}")
        arrays[field] = value
    points = arrays["points"]
    if points.ndim != 2 or points.shape[1] != 3:
        raise SceneError(f"{name}.points: expected shape (N, 3), got {points.shape}")
    n = points.shape[0]
    if n < MIN_CLOUD_POINTS:
        raise SceneError(f"{name}.points: {n} points, at least {MIN_CLOUD_POINTS} are needed")
    for field in _CLOUD_FIELDS[1:]:
        want = (n, 3) if field == "colors" else (n,)
        if arrays[field].shape != want:
            raise SceneError(f"{name}.{field}: expected shape {want} (one row per point), got {arrays[field].shape}")
    real = {"points": points, "colors": arrays["colors"], "confidence": arrays["confidence"]}
    converted = {}
    with np.errstate(all="ignore"):
        for field, value in real.items():
            if value.dtype.kind not in "fiu":
                raise SceneError(f"{name}.{field}: expected real numbers, got dtype {value.dtype}")
            value = value.astype(np.float64, copy=False)
            finite = np.isfinite(value) if value.ndim == 1 else np.isfinite(value).all(axis=1)
            if not finite.all():
                row = int(np.flatnonzero(~finite)[0])
                raise SceneError(f"{name}.{field}: row {row} is not finite ({int((~finite).sum())} such rows; "
                                 f"drop them first, e.g. cloud.subset(np.isfinite(cloud.points).all(axis=1)))")
            converted[field] = value
        if np.abs(converted["points"]).max() > MAX_COORDINATE:
            raise SceneError(f"{name}.points: coordinates up to {np.abs(converted['points']).max():g}, beyond the "
                             f"plausible range |x| <= {MAX_COORDINATE:g} (wrong unit?)")
        if float(np.ptp(converted["points"], axis=0).max()) <= 0:
            raise SceneError(f"{name}.points: every point is the same point")
        for field in ("colors", "confidence"):
            value = converted[field]
            if value.min() < 0 or value.max() > 1:
                raise SceneError(f"{name}.{field}: values must lie in [0, 1], got {value.min():g} .. {value.max():g}")
    for field, lowest in (("segment", -1), ("frame_index", 0), ("pixel_index", 0)):
        value = arrays[field]
        if value.dtype.kind not in "iu":
            raise SceneError(f"{name}.{field}: expected integers, got dtype {value.dtype}")
        value = value.astype(np.int64, copy=False)
        if value.size and value.min() < lowest:
            raise SceneError(f"{name}.{field}: values must be >= {lowest}, got {int(value.min())}")
        converted[field] = value
    if not isinstance(cloud.segment_source, dict):
        raise SceneError(f"{name}.segment_source: expected a dict, got {type(cloud.segment_source).__name__}")
    if all(converted[field] is arrays[field] for field in _CLOUD_FIELDS):
        return cloud
    return LabelledCloud(state=cloud.state, segment_source=dict(cloud.segment_source), **converted)


# ---------------------------------------------------------------------- posed scenes: one unit

UNIT_CHECK_SAMPLES = 2000              # depth pixels per view used by the unit check
UNIT_CHECK_RADIUS_SPACINGS = 3.0       # "overlaps": within this many sample spacings of another view
UNIT_CHECK_FACTORS = (1e-6, 1e-3, 1e-2, 1e2, 1e3, 1e6)   # unit slips tried when views do not overlap
UNIT_CHECK_MIN_OVERLAP = 0.2           # below this median overlap the alternatives are tried ...
UNIT_CHECK_CLEAR_OVERLAP = 0.4         # ... and one that reaches this (and doubles it) is an error


def _camera_points(K: np.ndarray, width: int, pixels: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(S, 3) camera-frame points of row-major pixel indices with their depths (the unprojection of
    :func:`sparseart.lift.rgbd.pixel_rays`, skew included)."""
    u, v = (pixels % width).astype(np.float64), (pixels // width).astype(np.float64)
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return np.stack([x, y, np.ones_like(x)], axis=1) * depth[:, None]


def view_overlap(views: list[tuple[np.ndarray, np.ndarray]], factor: float = 1.0) -> float | None:
    """Median over views of the share of a view's sampled points that lie within
    ``UNIT_CHECK_RADIUS_SPACINGS`` sample spacings of a view taken from another camera position,
    with every depth multiplied by ``factor``.

    views: per view ((S, 3) camera-frame points, (4, 4) cam_to_world). None when no two views
    have different camera positions. O(V S log S) for V views.
    """
    from scipy.spatial import cKDTree

    centres = [pose[:3, 3] for _, pose in views]
    worlds = [(factor * points) @ pose[:3, :3].T + pose[:3, 3] for points, pose in views]
    trees = [cKDTree(w) for w in worlds]
    spacing = max(float(np.median(tree.query(w, k=2)[0][:, 1])) for tree, w in zip(trees, worlds))
    radius = UNIT_CHECK_RADIUS_SPACINGS * max(spacing, 1e-300)
    shares = []
    for i, world in enumerate(worlds):
        scale = float(np.ptp(world, axis=0).max()) or 1.0
        others = [j for j in range(len(views)) if j != i and np.linalg.norm(centres[j] - centres[i]) > 1e-6 * scale]
        if not others:
            continue
        near = np.zeros(len(world), dtype=bool)
        for j in others:
            distance, _ = trees[j].query(world, distance_upper_bound=radius)
            near |= np.isfinite(distance)
        shares.append(float(near.mean()))
    return float(np.median(shares)) if shares else None


def check_posed_units(frames: list, depth_scale: float, cameras_path: Path | str, seed: int = 0) -> list[str]:
    """Posed RGB-D scenes: do depth and the cam_to_world translations share one unit?

    A depth unit that disagrees with the poses' (``depth_scale: 1`` for millimetre PNGs with poses
    in metres) scales every view about its own camera, so views from different positions stop
    overlapping and each yields its own copy of the object (measured: one door became three
    revolute joints at confidence 0.8). When the views overlap less than
    ``UNIT_CHECK_MIN_OVERLAP`` as given but at least ``UNIT_CHECK_CLEAR_OVERLAP`` (and twice as
    much) with depth scaled by one of ``UNIT_CHECK_FACTORS``, that is an error naming the factor;
    views that overlap under no factor give a warning. O(V S log S); a no-op for scenes with
    fewer than two camera positions.

    frames: every :class:`~sparseart.types.Frame` of the scene (depth, K, cam_to_world set).
    Returns warnings. Raises SceneError on a clear unit slip.
    """
    rng = np.random.default_rng(seed)
    views = []
    for frame in frames:
        if frame.depth is None or frame.camera is None or frame.camera.cam_to_world is None:
            return []
        flat = frame.depth.reshape(-1)
        valid = np.flatnonzero(flat > 0)
        if len(valid) < 10:
            continue
        pick = valid[rng.choice(len(valid), min(len(valid), UNIT_CHECK_SAMPLES), replace=False)]
        views.append((_camera_points(frame.camera.K, frame.depth.shape[1], pick, flat[pick]),
                      frame.camera.cam_to_world))
    if len(views) < 2:
        return []
    with np.errstate(all="ignore"):
        given = view_overlap(views)
        if given is None or given >= UNIT_CHECK_MIN_OVERLAP:
            return []
        scores = {factor: view_overlap(views, factor) or 0.0 for factor in UNIT_CHECK_FACTORS}
    factor, best = max(scores.items(), key=lambda item: item[1])
    if best >= UNIT_CHECK_CLEAR_OVERLAP and best >= 2 * given:
        raise _fail(cameras_path, f"depth and cam_to_world disagree in unit: the posed views overlap {given:.0%} "
                                  f"as given but {best:.0%} with depth x{factor:g}; check depth_scale (now "
                                  f"{depth_scale:g}; {depth_scale / factor:g} would fit) or the unit of the "
                                  f"cam_to_world translations")
    return [f"{cameras_path}: the posed views barely overlap ({given:.0%} of sampled points near another view); "
            f"check the cam_to_world poses"]
