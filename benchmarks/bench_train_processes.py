"""Benchmark of `c4d train` on the CPU with its cores split into processes or into threads.

    .venv/bin/python benchmarks/bench_train_processes.py --shards DIR [DIR ...] \
        [--layouts 1x2,2x1] [--steps 150] [--repeats 3] [--config tiny-cpu-2x] [--set KEY=VALUE ...]
        [--work /tmp/bench-train-processes]

A layout PxT is `c4d train --nproc-per-node P` with `--threads T` in each process (1xT: one
process), `train.batch_size = train.total_batch / P`, so every layout takes the same optimiser
steps on the same total batch. Each run is the real command in a fresh process, from this
checkout, with no OMP_* variables set; the layouts are interleaved (the order reversed every other
repeat) so that they see the same background load. Figures per layout: the median over the
repeats of the clips/s the command logs, its last `(steps - 10) / log_every` windows (the first
window holds the start-up); each layout's ratio to the first one, paired by repeat; the load
average; and whether the repeats of a layout logged the same losses to the last digit (the
training is then bit-reproducible run to run). Defaults: `c4d demo`'s training (its config's
`train.config` and `train.overrides`: tiny-cpu-2x, lr 0.004, plain BCE on mobility), with
`--set` overrides after them. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

from timing import load_average, this_commit
from c4d_core.config import load_config

ROOT = Path(__file__).resolve().parents[1]
DEMO_TRAIN = load_config("demo", "default").train  # the training `c4d demo` runs
RATE = re.compile(r"step (\d+)/\d+ .* ([0-9.]+) clips/s")


def run(layout: str, args, out: Path) -> tuple[float, list[str]]:
    """(median logged clips/s after the first window, log.jsonl lines) of one `c4d train`."""
    processes, threads = (int(v) for v in layout.split("x"))
    env = {k: v for k, v in os.environ.items() if not k.startswith("OMP_")}
    env["PYTHONPATH"] = str(ROOT)
    sources = "[" + ",".join(args.shards) + "]"
    overrides = [*DEMO_TRAIN.overrides, *args.set]
    total = load_config("dynpt", args.config, overrides=overrides).train.total_batch
    command = [sys.executable, "-m", "c4d", "train", "--threads", str(threads),
               "--nproc-per-node", str(processes), "--config", args.config,
               f"data.sources={sources}", f"train.steps={args.steps}", f"train.out_dir={out}",
               "eval.every=0", f"train.batch_size={total // processes}", *overrides]
    shutil.rmtree(out, ignore_errors=True)
    done = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"{' '.join(command)} failed:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")
    rates = [float(m.group(2)) for m in RATE.finditer(done.stdout + done.stderr) if int(m.group(1)) > 10]
    return statistics.median(rates), (out / "log.jsonl").read_text().splitlines()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shards", nargs="+", required=True, help="shard sets (`c4d datagen` folders)")
    parser.add_argument("--layouts", default="1x2,2x1", help="PxT: P processes of T threads each")
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--config", default=DEMO_TRAIN.config)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--work", default="/tmp/bench-train-processes")
    args = parser.parse_args()
    layouts = args.layouts.split(",")
    rates = {layout: [] for layout in layouts}
    logs = {layout: [] for layout in layouts}
    loads = []
    for repeat in range(args.repeats):
        for layout in (layouts if repeat % 2 == 0 else layouts[::-1]):
            loads.append(load_average())
            rate, lines = run(layout, args, Path(args.work) / layout)
            rates[layout].append(rate)
            logs[layout].append(lines)
            print(f"repeat {repeat} {layout}: {rate:.2f} clips/s", file=sys.stderr)
    first = layouts[0]
    print(f"commit {this_commit()}; {args.config}, {args.steps} steps, {args.repeats} repeats; "
          f"load averages (1, 5, 15 min) at the runs' starts: {'; '.join(loads)}\n")
    print(f"| layout | clips/s (median) | runs | ratio to {first} (median, range) | same losses run to run |")
    print("|---|---|---|---|---|")
    for layout in layouts:
        ratios = [a / b for a, b in zip(rates[layout], rates[first])]
        same = all(lines == logs[layout][0] for lines in logs[layout])
        print(f"| {layout} | {statistics.median(rates[layout]):.2f} | "
              f"{[round(r, 2) for r in rates[layout]]} | {statistics.median(ratios):.2f} "
              f"({min(ratios):.2f} to {max(ratios):.2f}) | {'yes' if same else 'no'} |")


if __name__ == "__main__":
    main()
