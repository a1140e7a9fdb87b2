"""Benchmark of CPU threads on a busy machine: `c4d demo --quick` and a training run, with
`--hogs` CPU-bound processes running beside them, for two checkouts of the project.

    .venv/bin/python benchmarks/bench_threads.py --before /tmp/before [--after .] \
        [--repeats 3] [--demo-repeats 2] [--steps 300] [--hogs 1] [--work /tmp/bench-threads]

`--before` is a checkout of the code to compare against (e.g. `git worktree add /tmp/before
<commit>`). The runs are interleaved (before, after, before, after, ...) so that both see the same
background load; each is a fresh process (`python -m c4d ...` with PYTHONPATH set to its checkout)
timed in wall seconds and CPU seconds (user + system of the command and its children). One `after`
run without the hogs gives the reference the share is measured against: with one hog on a 2-core
machine, the command's share is half the machine, so about 2x its unloaded wall time is "its
share". Prints a markdown table of medians.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path


def timed(cmd: list[str], checkout: Path, log: Path) -> tuple[float, float]:
    """(wall s, CPU s) of `cmd` run from `checkout`; its output goes to `log`."""
    env = {**os.environ, "PYTHONPATH": str(checkout), "PYOPENGL_PLATFORM": "egl"}
    for name in ("OMP_NUM_THREADS", "OMP_WAIT_POLICY", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        env.pop(name, None)  # each checkout chooses its own threads
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    with open(log, "w") as out:
        subprocess.run(cmd, cwd=checkout, env=env, stdout=out, stderr=subprocess.STDOUT, check=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


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
    parser.add_argument("--demo-repeats", type=int, default=2, help="demo --quick runs per variant")
    parser.add_argument("--steps", type=int, default=300, help="training steps (tiny-cpu)")
    parser.add_argument("--hogs", type=int, default=1, help="CPU-bound processes beside the runs")
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench-threads"))
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    python = [sys.executable, "-m", "c4d"]
    data = args.work / "data"
    if not data.exists():
        timed([*python, "datagen", "--preset", "movi-e", "--num-scenes", "8", "--out", str(data),
               "--resolution", "48x48", "--frames", "8", "--scenes-per-shard", "4", "--workers", "1"],
              args.after, args.work / "datagen.log")

    def train(checkout: Path, run: str) -> list[str]:
        shutil.rmtree(args.work / run, ignore_errors=True)
        return [*python, "train", "--config", "tiny-cpu", f"data.sources=[{data}]",
                f"train.steps={args.steps}", f"train.out_dir={args.work / run}", "eval.every=0"]

    def demo(checkout: Path, run: str) -> list[str]:
        shutil.rmtree(args.work / run, ignore_errors=True)
        return [*python, "demo", "--quick", "--out", str(args.work / run)]

    checkouts = {"before": args.before.resolve(), "after": args.after.resolve()}
    results: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for job, make, repeats in (("train", train, args.repeats), ("demo --quick", demo, args.demo_repeats)):
        name = job.split()[0]
        for i in range(repeats):
            for variant in (("before", "after") if i % 2 == 0 else ("after", "before")):
                with Hogs(args.hogs):
                    res = timed(make(checkouts[variant], f"{name}-{variant}"), checkouts[variant],
                                args.work / f"{name}-{variant}-{i}.log")
                results.setdefault((job, f"{variant}, {args.hogs} hog(s)"), []).append(res)
                print(job, variant, i, f"{res[0]:.1f} s wall, {res[1]:.1f} CPU-s", flush=True)
        res = timed(make(checkouts["after"], f"{name}-alone"), checkouts["after"],
                    args.work / f"{name}-alone.log")
        results[(job, "after, no hog")] = [res]
        print(job, "after alone", f"{res[0]:.1f} s wall, {res[1]:.1f} CPU-s", flush=True)

    print(f"\nload average at the end {' '.join(f'{v:.1f}' for v in os.getloadavg())} on "
          f"{os.cpu_count()} cores; {args.steps} tiny-cpu steps; medians\n")
    print("| command | variant | runs | wall s | CPU s |")
    print("|---|---|---|---|---|")
    for (job, variant), runs in results.items():
        wall = statistics.median(r[0] for r in runs)
        cpu = statistics.median(r[1] for r in runs)
        print(f"| {job} | {variant} | {len(runs)} | {wall:.1f} | {cpu:.1f} |")


if __name__ == "__main__":
    main()
