"""Benchmark of CPU threads on a busy machine: training steps and `c4d demo --quick`, with
`--hogs` CPU-bound processes running beside them, for two checkouts of the project.

    .venv/bin/python benchmarks/bench_threads.py --before /tmp/before [--after .] \
        [--repeats 3] [--budget 150] [--hogs 1] [--demo-budget 900] [--work /tmp/bench-threads]

`--before` is a checkout of the code to compare against (e.g. `git worktree add /tmp/before
<commit>`). Every run is a fresh process (`python -m c4d ...` with PYTHONPATH set to its
checkout and no OMP_* variables, so each checkout chooses its own threads).

1. Training: `c4d train --config tiny-cpu` (300 steps asked) runs for a fixed `--budget` of wall
   seconds and is then stopped; the figure is the steps it completed (log.jsonl lines), so a slow
   variant costs no more time than a fast one. Runs are interleaved (before, after, after,
   before, ...) so that both see the same background load; medians over `--repeats`.
2. The same for `after` without the hogs: the reference for "its share". With one hog on a
   2-core machine the command's fair share is half the machine, so about half the unloaded steps.
3. `c4d demo --quick` once per variant with the hogs, each stopped after `--demo-budget` seconds
   (the table then says it did not finish, and which step it was in).
Prints markdown tables.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path


def run_for(cmd: list[str], checkout: Path, log: Path, budget: float) -> tuple[float, bool]:
    """Run `cmd` from `checkout` for at most `budget` s; (wall s, finished)."""
    env = {**os.environ, "PYTHONPATH": str(checkout), "PYOPENGL_PLATFORM": "egl"}
    for name in ("OMP_NUM_THREADS", "OMP_WAIT_POLICY", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        env.pop(name, None)
    start = time.perf_counter()
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, cwd=checkout, env=env, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)
        try:
            code = proc.wait(timeout=budget)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, 9)  # the command and its workers
            proc.wait()
            return time.perf_counter() - start, False
    if code:
        raise SystemExit(f"{' '.join(cmd)} failed ({code}); see {log}")
    return time.perf_counter() - start, True


class Hogs:
    """`count` busy-looping processes beside the measured command."""

    def __init__(self, count: int):
        self.count, self.procs = count, []

    def __enter__(self):
        self.procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
                      for _ in range(self.count)]
        return self

    def __exit__(self, *exc):
        for proc in self.procs:
            proc.kill()
            proc.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", type=Path, required=True, help="checkout of the old code")
    parser.add_argument("--after", type=Path, default=Path(__file__).resolve().parents[1])
    parser.add_argument("--repeats", type=int, default=3, help="training runs per variant")
    parser.add_argument("--budget", type=float, default=150, help="wall seconds per training run")
    parser.add_argument("--demo-budget", type=float, default=900, help="wall seconds per demo run")
    parser.add_argument("--hogs", type=int, default=1, help="CPU-bound processes beside the runs")
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench-threads"))
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    python = [sys.executable, "-m", "c4d"]
    checkouts = {"before": args.before.resolve(), "after": args.after.resolve()}
    data = args.work / "data"
    if not data.exists():
        run_for([*python, "datagen", "--preset", "movi-e", "--num-scenes", "8", "--out", str(data),
                 "--resolution", "48x48", "--frames", "8", "--scenes-per-shard", "4", "--workers", "1"],
                checkouts["after"], args.work / "datagen.log", 3600)

    def train(variant: str, hogs: int, i: int) -> int:
        out = args.work / f"train-{variant}-{hogs}-{i}"
        shutil.rmtree(out, ignore_errors=True)
        run_for([*python, "train", "--config", "tiny-cpu", f"data.sources=[{data}]",
                 "train.steps=300", f"train.out_dir={out}", "eval.every=0"],
                checkouts[variant], out.with_suffix(".log"), args.budget)
        log = out / "log.jsonl"
        steps = len(log.read_text().splitlines()) if log.exists() else 0
        print(f"train {variant} hogs={hogs} #{i}: {steps} steps in {args.budget:.0f} s", flush=True)
        return steps

    steps: dict[str, list[int]] = {}
    for i in range(args.repeats):
        for variant in (("before", "after") if i % 2 == 0 else ("after", "before")):
            with Hogs(args.hogs):
                steps.setdefault(f"{variant}, {args.hogs} hog(s)", []).append(train(variant, args.hogs, i))
        steps.setdefault("after, no hog", []).append(train("after", 0, i))
    load = " ".join(f"{v:.1f}" for v in os.getloadavg())
    print(f"\ntraining, tiny-cpu, {args.budget:.0f} s per run; load average {load} on "
          f"{os.cpu_count()} cores\n")
    print("| variant | runs | steps done (median) | each run |")
    print("|---|---|---|---|")
    for variant, counts in steps.items():
        print(f"| {variant} | {len(counts)} | {statistics.median(counts):g} | "
              f"{', '.join(map(str, counts))} |")

    print("\n| demo --quick, with hogs | wall s | finished |")
    print("|---|---|---|")
    for variant in ("after", "before"):
        out = args.work / f"demo-{variant}"
        shutil.rmtree(out, ignore_errors=True)
        with Hogs(args.hogs):
            wall, finished = run_for([*python, "demo", "--quick", "--out", str(out)], checkouts[variant],
                                     args.work / f"demo-{variant}.log", args.demo_budget)
        done = sorted(p.parent.name for p in out.glob("*/done.json"))
        state = "yes" if finished else f"no (steps done: {', '.join(done) or 'none'})"
        print(f"| {variant} | {wall:.0f} | {state} |", flush=True)


if __name__ == "__main__":
    main()
