"""The one place open3d is imported: lazily (it costs ~1 s), with its console warnings silenced
(registration fallbacks are reported through sparseart's own warnings instead), and the one switch
that makes its registration reproducible (:func:`serial`)."""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from types import ModuleType


@lru_cache(maxsize=1)
def open3d() -> ModuleType:
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


@contextmanager
def serial() -> Iterator[ModuleType]:
    """open3d limited to one thread inside the block (yields the module); the previous limit is
    restored on exit (nesting is fine).

    open3d parallelises with TBB, whose reductions (the 6x6 normal equations of every ICP step,
    RANSAC's best-model bookkeeping, fitness sums) add per-thread partial sums in an order that
    depends on the thread schedule: the same input then gives transforms that differ in the last
    bits (measured ~1e-16 per ICP call, enough to flip later discrete choices and the final joints).
    One thread makes every open3d call a pure function of its input. Registration works on at most
    a few thousand points, where the measured cost of one thread is within noise. The limit is
    process-wide, so other threads using open3d meanwhile also run on one thread.
    """
    o3d = open3d()
    previous = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        yield o3d
    finally:
        o3d.utility.set_max_threads(previous)
