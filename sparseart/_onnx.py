"""The one place that opens onnxruntime sessions, and describes them in error messages.

:func:`open_session` checks the file, checks that the model's weights fit in the available RAM,
opens it on the CPU provider with the requested intra-op thread count and turns every failure into
a one-line :class:`~sparseart.types.SceneError` (or the subclass the caller passes) naming the
file. onnxruntime is imported lazily, inside the functions, so importing this module is free.

:func:`tensors` / :func:`describe_io` list a session's inputs and outputs (name, shape with symbolic
dimensions as None, element type) so that a "wrong model" error can show what the model is.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from sparseart.types import SceneError

# Weights larger than this are opened with the CPU memory arena off (it can double peak RAM).
ARENA_OFF_ABOVE_BYTES = 512 * 2**20


@dataclass(frozen=True)
class Tensor:
    """One model input or output: name, shape (int, or None for a symbolic/unknown dimension) and
    onnxruntime's type string (e.g. ``tensor(float)``)."""

    name: str
    shape: tuple[int | None, ...]
    type: str

    def describe(self) -> str:
        dims = ", ".join("?" if d is None else str(d) for d in self.shape)
        kind = self.type.removeprefix("tensor(").removesuffix(")")
        return f"{self.name} [{dims}] {kind}"


def available_memory_bytes() -> int | None:
    """MemAvailable from /proc/meminfo, else free physical pages from os.sysconf, else None."""
    try:
        with open("/proc/meminfo") as stream:
            for line in stream:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def model_bytes(path: Path) -> int:
    """Size of the model file plus external-data files beside it (``<stem>.data``, ``.bin``,
    ``.onnx_data``, ``<name>_data``): what loading keeps resident."""
    total = path.stat().st_size
    for sibling in path.parent.iterdir():
        if sibling != path and sibling.is_file() and sibling.name.startswith(path.stem) and (
                sibling.suffix in (".data", ".bin", ".onnx_data") or sibling.name.endswith("_data")):
            total += sibling.stat().st_size
    return total


def size_text(value: float) -> str:
    """Bytes as GB (MB below 0.1 GB), for error messages."""
    return f"{value / 1e9:.2f} GB" if value >= 1e8 else f"{value / 1e6:.3f} MB"


def _load_error(path: Path, what: str | None, error: Exception, error_type: type[SceneError]) -> SceneError:
    """One line for an onnxruntime load failure (IR / opset too new, corrupt file, missing data)."""
    import onnxruntime as ort

    text = str(error)
    version = ort.__version__
    head = f"{path}: {what}: " if what else f"{path}: "
    if match := re.search(r"Unsupported model IR version: (\d+), max supported IR version: (\d+)", text):
        return error_type(f"{head}model IR version {match[1]} is newer than onnxruntime {version} supports "
                          f"(max {match[2]}); upgrade onnxruntime or re-save the model with onnx after "
                          f"setting model.ir_version = {match[2]}")
    match = (re.search(r"Opset (\d+) is under development", text)
             or re.search(r"[Oo]pset (\d+)[^\n]*not (?:be )?supported", text))
    if match:
        till = re.search(r"till opset (\d+)", text)
        limit = f" (official support up to opset {till[1]})" if till else ""
        return error_type(f"{head}model opset {match[1]} is not supported by onnxruntime {version}{limit}; "
                          f"upgrade onnxruntime or re-export the model with a lower opset")
    if "Protobuf parsing failed" in text or "INVALID_PROTOBUF" in text:
        return error_type(f"{head}not a valid ONNX model (protobuf parsing failed: truncated or corrupt file?)")
    if match := re.search(r"[Ee]xternal data path does not exist: \"?([^\"\n]+)\"?", text):
        return error_type(f"{head}external data file {match[1]} not found (keep the .onnx file and its "
                          f"data file together in one folder, under the name the model references)")
    first = next((line.strip() for line in text.splitlines() if line.strip()), type(error).__name__)
    return error_type(f"{head}onnxruntime cannot load the model ({first[:300]})")


def open_session(path: str | Path, *, what: str | None = None, threads: int = 0,
                 providers: tuple[str, ...] | list[str] | None = None, memory_limit_bytes: int | None = None,
                 arena_off_above_bytes: int = ARENA_OFF_ABOVE_BYTES, error_type: type[SceneError] = SceneError):
    """An ``onnxruntime.InferenceSession`` (every model of the project is opened here).

    Args:
        path: the .onnx file (opened by path, so external data beside it is found).
        what: what the model is, for error messages (e.g. "XFeat detector"); None = say nothing.
        threads: intra-op threads (0 = onnxruntime's default, the physical cores).
        providers: execution providers, all of which must be available; None = CUDA when
            onnxruntime has it, then CPU.
        memory_limit_bytes: RAM budget for the check; None = MemAvailable of the machine.
        arena_off_above_bytes: weights larger than this are opened with the CPU memory arena off.
        error_type: the SceneError subclass to raise (e.g. lift's ModelError).

    Raises:
        SceneError (``error_type``), one line starting with the path: missing file, a folder,
        weights larger than the RAM budget, a missing provider, or a file onnxruntime cannot load.
    """
    path = Path(path)
    head = f"{path}: {what}: " if what else f"{path}: "
    if not path.exists():
        raise error_type(f"{path}: {what + ' ' if what else ''}model file not found")
    if not path.is_file():
        raise error_type(f"{head}not a file (expected an .onnx model)")
    if int(threads) < 0:
        raise error_type(f"{head}threads must be >= 0, got {threads}")
    size = model_bytes(path)
    budget = memory_limit_bytes if memory_limit_bytes is not None else available_memory_bytes()
    if budget is not None and size > budget:
        raise error_type(f"{head}the model's weights take {size_text(size)} but only {size_text(budget)} of RAM "
                         f"is available")
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    if threads > 0:
        options.intra_op_num_threads = int(threads)
    if size > arena_off_above_bytes:
        options.enable_cpu_mem_arena = False
    available = ort.get_available_providers()
    if providers is not None:
        missing = [p for p in providers if p not in available]
        if missing:
            raise error_type(f"{head}execution provider(s) {', '.join(missing)} not available "
                             f"(onnxruntime has {', '.join(available)})")
        chosen = list(providers)
    else:
        chosen = [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in available]
    try:
        return ort.InferenceSession(str(path), sess_options=options, providers=chosen)
    except Exception as error:  # onnxruntime raises private exception types
        raise _load_error(path, what, error, error_type) from None


def tensors(session) -> tuple[tuple[Tensor, ...], tuple[Tensor, ...]]:
    """(inputs, outputs) of a session as :class:`Tensor` tuples (symbolic dimensions -> None)."""
    def info(items) -> tuple[Tensor, ...]:
        return tuple(Tensor(t.name, tuple(d if isinstance(d, int) else None for d in t.shape), str(t.type))
                     for t in items)

    return info(session.get_inputs()), info(session.get_outputs())


def describe_io(session) -> str:
    """One line: ``inputs: a [1, ?, 2] float, ...; outputs: ...`` for error messages."""
    inputs, outputs = tensors(session)
    return (f"inputs: {', '.join(t.describe() for t in inputs) or 'none'}; "
            f"outputs: {', '.join(t.describe() for t in outputs) or 'none'}")


def run_error(path: Path, what: str, error: Exception, error_type: type[SceneError] = SceneError) -> SceneError:
    """One line for a failure of ``session.run`` (onnxruntime's first message line, shortened)."""
    first = next((line.strip() for line in str(error).splitlines() if line.strip()), type(error).__name__)
    return error_type(f"{path}: {what} failed to run ({first[:300]})")
