"""The one place open3d is imported: lazily (it costs ~0.8 s), without its plotly/dash drawing
helpers (another ~0.9 s, :func:`_defer_plotly`), with its console warnings silenced (registration
fallbacks are reported through sparseart's own warnings instead), and the one switch that makes
its registration reproducible (:func:`serial`)."""
from __future__ import annotations

import importlib
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import lru_cache
from types import ModuleType

PLOTLY_MODULE = "open3d.visualization.draw_plotly"
PLOTLY_NAMES = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


@lru_cache(maxsize=1)
def open3d() -> ModuleType:
    _defer_plotly()
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


def _defer_plotly() -> None:
    """Stand in for ``open3d.visualization.draw_plotly`` while open3d is imported, so ``import
    open3d`` does not load plotly, dash, IPython and requests for drawing helpers sparseart never
    calls (measured with ``python -X importtime``: 0.91 of the 1.70 s import, open3d 0.20). The
    stand-in's functions import the real module on first call and run it, and any other name
    asked of it loads the real module at once (an open3d that imports more from it still works),
    so a user of ``open3d.visualization``'s plotly helpers in the same process sees no
    difference. Nothing is done when open3d or the module is already imported. O(1)."""
    if "open3d" in sys.modules or PLOTLY_MODULE in sys.modules:
        return
    stand_in = ModuleType(PLOTLY_MODULE)
    stand_in._sparseart_stand_in = True   # the real module loads on the first call (_real_plotly)
    for name in PLOTLY_NAMES:
        setattr(stand_in, name, _deferred(name))

    def other(name: str):
        if name.startswith("__"):         # the import machinery's probes (__path__, __spec__, ...)
            raise AttributeError(name)
        return getattr(_real_plotly(), name)

    stand_in.__getattr__ = other
    sys.modules[PLOTLY_MODULE] = stand_in


def _deferred(name: str) -> Callable:
    """The stand-in for ``draw_plotly.<name>``: loads the real module (once) and calls it."""
    def call(*args, **kwargs):
        return getattr(_real_plotly(), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    return call


def _real_plotly() -> ModuleType:
    """The real ``open3d.visualization.draw_plotly``, imported on first use; its functions then
    replace the stand-ins on ``open3d.visualization`` (the import binds the module itself there,
    over the function of the same name)."""
    module = sys.modules.get(PLOTLY_MODULE)
    if module is None or getattr(module, "_sparseart_stand_in", False):
        sys.modules.pop(PLOTLY_MODULE, None)
        module = importlib.import_module(PLOTLY_MODULE)
        package = sys.modules.get("open3d.visualization")
        for name in PLOTLY_NAMES:
            if package is not None and hasattr(module, name):
                setattr(package, name, getattr(module, name))
    return module


_SERIAL_LOCK = threading.Lock()
_serial_holders = 0          # threads inside serial() now
_serial_previous = 0         # the thread limit before the first of them entered


@contextmanager
def serial() -> Iterator[ModuleType]:
    """open3d limited to one thread inside the block (yields the module); the previous limit is
    restored when the last block open in any thread closes (nesting and threads are fine).

    open3d parallelises with TBB, whose reductions (the 6x6 normal equations of every ICP step,
    RANSAC's best-model bookkeeping, fitness sums) add per-thread partial sums in an order that
    depends on the thread schedule: the same input then gives transforms that differ in the last
    bits (measured ~1e-16 per ICP call, enough to flip later discrete choices and the final joints).
    One thread makes every open3d call a pure function of its input. Registration works on at most
    a few thousand points, where the measured cost of one thread is within noise; independent
    registrations run side by side in Python threads instead (:func:`sparseart.parallel.
    in_parallel`). The limit is process-wide and counted over threads, so a thread leaving its
    block cannot lift it while another thread is still inside one; other threads using open3d
    meanwhile also run on one thread.
    """
    global _serial_holders, _serial_previous
    o3d = open3d()
    with _SERIAL_LOCK:
        if _serial_holders == 0:
            _serial_previous = o3d.utility.get_max_threads()
            o3d.utility.set_max_threads(1)
        _serial_holders += 1
    try:
        yield o3d
    finally:
        with _SERIAL_LOCK:
            _serial_holders -= 1
            if _serial_holders == 0:
                o3d.utility.set_max_threads(_serial_previous)


_RANDOM_LOCK = threading.Lock()


@contextmanager
def seeded(seed: int) -> Iterator[ModuleType]:
    """open3d on one thread (:func:`serial`) with its random generator seeded by ``seed``, held by
    one thread at a time (yields the module): the one home of open3d's randomness. Its generator
    is process-wide, so two Python threads running a seeded RANSAC at once draw from each other's
    sequence and the result depends on the thread schedule -- measured: of 16 FPFH RANSACs of one
    input and seed run from 4 threads, 4-8 differed from the same call alone; with this lock none.
    The labeler's pair registrations and the view graph's edges run side by side in threads
    (:func:`sparseart.parallel.in_parallel`), so a scene's answer could change with the machine's
    load. Read what the call returns inside the block. open3d takes a C int: seeds are reduced
    modulo 2**31 (a stage's derived seed, ``seed + 104729``, stays valid for every CLI seed)."""
    with _RANDOM_LOCK, serial() as o3d:
        o3d.utility.random.seed(int(seed) % 2**31)
        yield o3d
