"""The labeler's per-part trust (PartLabels.confidence) survives the pairing diagnostics."""
from __future__ import annotations

import numpy as np

from sparseart.labelers.rules import _attach
from sparseart.types import PartLabels, PartSpec


def test_pairing_diagnostics_keep_the_lower_trust() -> None:
    parts = [PartSpec(id=0, role="static"), PartSpec(id=1, role="movable"), PartSpec(id=2, role="movable")]
    labels = PartLabels(parts=parts, start_part=np.zeros(3, np.int64), end_part=np.zeros(3, np.int64),
                        confidence={1: 0.25})
    _attach(labels, {"confidence": {1: 1.0, 2: 0.5}})
    assert labels.confidence == {1: 0.25, 2: 0.5}
    labels = PartLabels(parts=parts, start_part=np.zeros(3, np.int64), end_part=np.zeros(3, np.int64))
    _attach(labels, {"confidence": {2: 0.4}})
    assert labels.confidence == {2: 0.4}
