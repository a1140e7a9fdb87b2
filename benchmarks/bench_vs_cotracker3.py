"""Speed and memory of DynPT built as CoTracker3 (no 3D encoder), for the side-by-side with CoTracker3.

Cases: 24 and 48 frames x 256 and 1024 points on one seeded 384x512 clip (CoTracker3's model
resolution; a textured pattern that translates), queries at seeded random frames and positions.
The model is `configs/dynpt/model/cotracker3-<offline|online>.yaml` with random weights (the cost
does not depend on the values), run as CoTracker3 runs: `--iters` refinement iterations (6, as its
predictor), float32, inference mode. Each case runs in a fresh process, so its peak resident
memory (ru_maxrss minus the same process's after-import baseline: weights, activations and
outputs) is its own; time is the median CPU time of `--repeats` forward passes (this process's
CPU seconds, which other load on a shared machine inflates less than wall time), with the wall
time alongside.

`--cotracker-repo DIR` times CoTracker3 on the same inputs in the same run, with
facebookresearch/co-tracker's code in DIR (a checkout outside this repository, which holds none of
its code; the commit is printed): `CoTrackerThreeOffline(stride=4, corr_radius=3, window_len=60)`
as its `CoTrackerPredictor` builds it (released sizes), random weights, called directly as DynPT's
model is (`model(video.float(), queries, iters=--iters)`: without the predictor's resize to
384x512, a no-op here, and its 6x6 support grid of extra queries), float32, inference mode, one
fresh process per case the same way. `--pairs K` runs each case K times per model, DynPT and
CoTracker3 interleaved (the order reversed every other pair), and prints the paired ratios (median
and range over the pairs) with the load average around every process. Offline windowing only.

`--save-inputs DIR` writes each case's clip and queries (case_T{T}_N{N}.npz: video uint8
(1,T,3,H,W), queries float32 (1,N,3) as (t, x, y)), so CoTracker3 can also be timed on the same
inputs by a script of its own.

    python benchmarks/bench_vs_cotracker3.py [--windowing offline|online] [--cases 24x256,48x1024]
        [--repeats 2] [--threads 1] [--iters 6] [--cotracker-repo DIR [--pairs 5]]
        [--save-inputs DIR] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from timing import git_commit, load_average, this_commit
from c4d_core.files import atomic_path

H, W = 384, 512
CASES = ("24x256", "24x1024", "48x256", "48x1024")


def clip_and_queries(T: int, N: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """The benchmark's inputs: video uint8 (1,T,3,H,W) and queries float32 (1,N,3) (t, x, y)."""
    g = torch.Generator().manual_seed(seed)
    base = F.interpolate(torch.rand(1, 3, H // 16, W // 16, generator=g) * 255, size=(H, W),
                         mode="bilinear", align_corners=False)
    frames = [torch.roll(base, shifts=(t, 2 * t), dims=(2, 3)) for t in range(T)]
    video = torch.cat(frames).round().clamp(0, 255).to(torch.uint8)[None]
    t = torch.randint(0, T, (N,), generator=g).float()
    queries = torch.stack([t, torch.rand(N, generator=g) * (W - 1), torch.rand(N, generator=g) * (H - 1)], -1)
    return video, queries[None]


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


def run_case(case: str, windowing: str, repeats: int, threads: int, iters: int) -> dict:
    """One case in this process: median CPU and wall seconds per forward pass, peak memory."""
    from c4d_core.config import load_config
    from dynpt.model import build_model

    torch.set_num_threads(threads)
    T, N = (int(v) for v in case.split("x"))
    video, queries = clip_and_queries(T, N)
    baseline = _peak_mib()
    torch.manual_seed(0)
    model = build_model(load_config("dynpt", f"model/cotracker3-{windowing}").model).eval()
    cpu, wall = [], []
    with torch.inference_mode():
        for _ in range(repeats):
            c0, w0 = time.process_time(), time.perf_counter()
            out = model(video, queries, iters=iters)
            cpu.append(time.process_time() - c0)
            wall.append(time.perf_counter() - w0)
            del out
    return {"model": f"dynpt-{windowing}", "T": T, "N": N, "H": H, "W": W, "iters": iters,
            "threads": threads, "params": sum(p.numel() for p in model.parameters()),
            "cpu_s": statistics.median(cpu), "wall_s": statistics.median(wall), "cpu_runs": cpu,
            "peak_mib": _peak_mib() - baseline}


def run_cotracker_case(repo: str, case: str, repeats: int, threads: int, iters: int) -> dict:
    """One case of CoTracker3 (co-tracker's `CoTrackerThreeOffline` from `repo`) in this process,
    measured as `run_case` measures DynPT."""
    sys.path.insert(0, str(Path(repo).resolve()))
    from cotracker.models.core.cotracker.cotracker3_offline import CoTrackerThreeOffline

    torch.set_num_threads(threads)
    T, N = (int(v) for v in case.split("x"))
    video, queries = clip_and_queries(T, N)
    baseline = _peak_mib()
    torch.manual_seed(0)
    model = CoTrackerThreeOffline(stride=4, corr_radius=3, window_len=60).eval()  # as its predictor
    cpu, wall = [], []
    with torch.inference_mode():
        for _ in range(repeats):
            c0, w0 = time.process_time(), time.perf_counter()
            out = model(video.float(), queries, iters=iters)
            cpu.append(time.process_time() - c0)
            wall.append(time.perf_counter() - w0)
            del out
    return {"model": "cotracker3-offline", "T": T, "N": N, "H": H, "W": W, "iters": iters,
            "threads": torch.get_num_threads(), "params": sum(p.numel() for p in model.parameters()),
            "cpu_s": statistics.median(cpu), "wall_s": statistics.median(wall), "cpu_runs": cpu,
            "peak_mib": _peak_mib() - baseline}


def _median_range(values: list[float]) -> str:
    return f"{statistics.median(values):.2f} ({min(values):.2f}-{max(values):.2f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--windowing", choices=("offline", "online"), default="offline")
    parser.add_argument("--cases", default=",".join(CASES), help="TxN, comma separated")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--iters", type=int, default=6)
    parser.add_argument("--cotracker-repo", metavar="DIR",
                        help="a facebookresearch/co-tracker checkout: time CoTracker3 offline on the "
                        "same inputs, interleaved with DynPT")
    parser.add_argument("--pairs", type=int, default=1,
                        help="with --cotracker-repo: processes per model and case, interleaved")
    parser.add_argument("--save-inputs", help="write each case's clip and queries here (.npz)")
    parser.add_argument("--json", help="write the results here")
    parser.add_argument("--only", help=argparse.SUPPRESS)  # child process mode: one case
    parser.add_argument("--only-cotracker", metavar="DIR", help=argparse.SUPPRESS)  # child: CoTracker3
    args = parser.parse_args()
    if args.only and args.only_cotracker:
        print(json.dumps(run_cotracker_case(args.only_cotracker, args.only, args.repeats, args.threads,
                                            args.iters)))
        return
    if args.only:
        print(json.dumps(run_case(args.only, args.windowing, args.repeats, args.threads, args.iters)))
        return
    if args.cotracker_repo and args.windowing != "offline":
        parser.error("--cotracker-repo compares offline windowing only")
    print(f"{time.strftime('%Y-%m-%d %H:%M')}, commit {this_commit()}, torch {torch.__version__}, "
          f"{args.threads} threads, load average {load_average()} on {os.cpu_count()} cores"
          + (f"; co-tracker {Path(args.cotracker_repo).resolve()} at "
             f"{git_commit(args.cotracker_repo, ('cotracker',))}" if args.cotracker_repo else ""), flush=True)
    results, table = [], []
    common = ["--windowing", args.windowing, "--repeats", str(args.repeats), "--threads",
              str(args.threads), "--iters", str(args.iters)]
    systems = {"dynpt": []} | ({"cotracker3": ["--only-cotracker", args.cotracker_repo]}
                               if args.cotracker_repo else {})
    for case in args.cases.split(","):
        if args.save_inputs:
            T, N = (int(v) for v in case.split("x"))
            video, queries = clip_and_queries(T, N)
            Path(args.save_inputs).mkdir(parents=True, exist_ok=True)
            np.savez(Path(args.save_inputs) / f"case_T{T}_N{N}.npz", video=video.numpy(), queries=queries.numpy())
        runs: dict[str, list[dict]] = {name: [] for name in systems}
        for pair in range(args.pairs if args.cotracker_repo else 1):
            for name in list(systems) if pair % 2 == 0 else list(systems)[::-1]:
                load_before = load_average()
                out = subprocess.run([sys.executable, __file__, "--only", case, *common, *systems[name]],
                                     capture_output=True, text=True)
                if out.returncode:
                    sys.exit(f"{name} {case} failed (exit {out.returncode}):\n{out.stderr[-3000:]}")
                r = json.loads(out.stdout.strip().splitlines()[-1])
                r["pair"], r["load"] = pair, [load_before, load_average()]
                runs[name].append(r)
                results.append(r)
                print(f"{r['model']} T={r['T']} N={r['N']} {H}x{W}: CPU {r['cpu_s']:.1f} s (runs "
                      f"{[round(v, 1) for v in r['cpu_runs']]}), wall {r['wall_s']:.1f} s, peak "
                      f"{r['peak_mib']:.0f} MiB, {r['params'] / 1e6:.2f}M params, {r['threads']} "
                      f"threads; load {load_before} -> {load_average()}", flush=True)
        if args.cotracker_repo:
            d, c = runs["dynpt"], runs["cotracker3"]
            time_ratio = [a["cpu_s"] / b["cpu_s"] for a, b in zip(d, c)]
            mem_ratio = [a["peak_mib"] / b["peak_mib"] for a, b in zip(d, c)]
            table.append(f"| {case} | {statistics.median(a['cpu_s'] for a in d):.1f} | "
                         f"{statistics.median(b['cpu_s'] for b in c):.1f} | {_median_range(time_ratio)} | "
                         f"{statistics.median(a['peak_mib'] for a in d):,.0f} | "
                         f"{statistics.median(b['peak_mib'] for b in c):,.0f} | {_median_range(mem_ratio)} |")
    if table:
        print(f"\n| frames x points | DynPT CPU s (median of {args.pairs}) | CoTracker3 CPU s | time "
              "ratio, paired (median; range) | DynPT peak MiB | CoTracker3 peak MiB | memory ratio, "
              "paired (median; range) |\n|---|---:|---:|---:|---:|---:|---:|\n" + "\n".join(table))
        print(f"\nload average at the end: {load_average()}")
    if args.json:
        with atomic_path(Path(args.json)) as tmp:
            Path(tmp).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
