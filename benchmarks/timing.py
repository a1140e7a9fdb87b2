"""Timing helpers shared by the benchmarks: medians over repeats, wall or CPU time."""

from __future__ import annotations

import statistics
import time
from typing import Callable


def median_seconds(fn: Callable[[], object], repeats: int, clock: Callable[[], float] = time.perf_counter) -> float:
    """Median seconds of `repeats` calls of `fn`, measured with `clock` (wall time by default;
    pass `time.process_time` for this process's CPU time, which a shared machine does not inflate)."""
    times = []
    for _ in range(repeats):
        start = clock()
        fn()
        times.append(clock() - start)
    return statistics.median(times)
