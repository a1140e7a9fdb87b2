"""Timing helpers shared by the benchmarks: medians over repeats, wall or CPU time, and what a
run reports beside its figures (the load, the commits measured)."""

from __future__ import annotations

import os
import statistics
import subprocess
import time
from pathlib import Path
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


def load_average() -> str:
    """The 1, 5 and 15 minute load averages, e.g. '3.1 2.7 2.2'."""
    return " ".join(f"{v:.1f}" for v in os.getloadavg())


def git_commit(repo: str | Path, code: tuple[str, ...] = ()) -> str:
    """The short commit of the git work tree `repo`, with whether its paths `code` (all tracked
    files where empty) differ from it, or why it is not known."""
    out = subprocess.run(["git", "-C", str(repo), "rev-parse", "--short", "HEAD"],
                         capture_output=True, text=True)
    top = subprocess.run(["git", "-C", str(repo), "rev-parse", "--show-toplevel"],
                         capture_output=True, text=True)
    if out.returncode or Path(top.stdout.strip()).resolve() != Path(repo).resolve():
        return "not a git work tree (say which commit was exported)"
    changed = subprocess.run(["git", "-C", str(repo), "diff", "--quiet", "HEAD", "--", *code]).returncode
    return out.stdout.strip() + (" with uncommitted changes" if changed else "")


def this_commit() -> str:
    """This checkout's commit, as the runs are reported."""
    return git_commit(Path(__file__).resolve().parent.parent)
