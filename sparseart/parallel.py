"""Independent pure computations side by side in Python threads: :func:`in_parallel`.

The heavy steps that run many independent registrations (hypothesis refinements of
:func:`~sparseart.geometry.icp.register_rigid`, the edges of the geometric view fallback, the
labeler's pair registrations) spend their time in open3d, k-d tree searches and numpy, which
release the GIL, so threads use the machine's cores without copying the clouds to other
processes. Results come back in the order of the items whatever the schedule, and every open3d
call inside runs on one thread (:func:`sparseart.geometry.o3d.serial`), so the output is the same
bit for bit as a sequential run.
"""
from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor

PARALLEL_THREADS = max(1, os.cpu_count() or 1)   # threads for independent computations


def in_parallel(function: Callable, items: Iterable) -> list:
    """``[function(item) for item in items]``, evaluated on up to ``PARALLEL_THREADS`` threads; the
    results in the order of ``items``, the first exception raised. Only for functions whose result
    depends on their argument alone (no shared random generator, no order-dependent state).
    Sequential for one item or one thread; nested calls get threads of their own."""
    items = list(items)
    workers = min(PARALLEL_THREADS, len(items))
    if workers < 2:
        return [function(item) for item in items]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(function, items))
