"""The one stage clock: every stage and sub-stage of a run as a :class:`StageRecord`."""
from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Iterator

from sparseart.types import StageRecord


class StageClock:
    """Collects :class:`StageRecord` entries (name, ran, wall seconds, why) in the order they end."""

    def __init__(self) -> None:
        self.records: list[StageRecord] = []

    @contextmanager
    def stage(self, name: str, why: str) -> Iterator[None]:
        began = time.perf_counter()
        try:
            yield
        finally:
            self.records.append(StageRecord(name, True, time.perf_counter() - began, why))

    def skip(self, name: str, why: str) -> None:
        self.records.append(StageRecord(name, False, 0.0, why))

    def add(self, name: str, seconds: float, why: str) -> None:
        """A sub-stage timed elsewhere (e.g. inside the lift)."""
        self.records.append(StageRecord(name, True, float(seconds), why))
