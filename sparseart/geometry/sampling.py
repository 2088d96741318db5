"""Random sub-sampling shared by every stage that caps its work at a number of points."""
from __future__ import annotations

import numpy as np


def random_subset(total: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted indices of ``min(count, total)`` distinct rows out of ``total``, drawn with ``rng``.

    Returns (min(count, total),) int64; all rows (in order) when ``total <= count``. O(total).
    """
    if total <= count:
        return np.arange(total)
    return np.sort(rng.choice(total, count, replace=False))
