"""Shared benchmark helpers: timing by median of repeats, and result rows."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass
class Row:
    """One benchmark line. ``value`` and ``peer_value`` are in ``unit``; ``target`` is text."""

    name: str
    value: float
    unit: str
    target: str
    passed: bool
    peer: str = ""
    peer_value: float | None = None
    note: str = ""


def median_time_s(func: Callable[[], object], repeats: int, warmup: int = 1) -> float:
    """Median wall time of ``func()`` over ``repeats`` calls, after ``warmup`` calls."""
    for _ in range(warmup):
        func()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        func()
        samples.append(time.perf_counter() - start)
    return statistics.median(samples)
