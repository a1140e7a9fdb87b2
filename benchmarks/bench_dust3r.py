"""Speed of the DUSt3R pointmap network and of the `c4d run` stages on this machine.

Part 1: seconds per image pair for a ViT-L/ViT-B DPT network (official 512 sizes, random
weights) at 512x384 through `Dust3rPointmaps`, batch 1 and 2, with the 224 linear network as
baseline. Part 2: seconds per stage of `c4d run` on a 30-frame generated-looking video with a
small random-weight network (the stage split, not the absolute network cost, is what it shows).

    .venv/bin/python benchmarks/bench_dust3r.py [--repeats 3] [--frames 30] [--skip-large]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from c4d_pipeline.dust3r_pointmaps import Dust3rPointmaps
from dynpt.dust3r.net import Dust3rConfig, Dust3rNet


def seconds_per_pair(cfg: Dust3rConfig, hw: tuple[int, int], pairs: int, batch: int, repeats: int) -> float:
    torch.manual_seed(0)
    source = Dust3rPointmaps(Dust3rNet(cfg), device="cpu", batch_size=batch)
    frames = np.random.default_rng(0).integers(0, 256, (pairs + 1, *hw, 3), dtype=np.uint8)
    edges = np.stack([np.arange(pairs), np.arange(1, pairs + 1)], axis=1)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        source.pointmaps(frames, edges)
        times.append((time.perf_counter() - start) / pairs)
    return statistics.median(times)


def network_section(repeats: int, skip_large: bool) -> dict:
    results = {}
    base = Dust3rConfig(head_type="linear", img_size=224)
    results["vitl_224_linear_224x224_b1"] = seconds_per_pair(base, (224, 224), 2, 1, repeats)
    if not skip_large:
        dpt = Dust3rConfig(head_type="dpt")
        results["vitl_512_dpt_512x384_b1"] = seconds_per_pair(dpt, (384, 512), 1, 1, repeats)
        results["vitl_512_dpt_512x384_b2"] = seconds_per_pair(dpt, (384, 512), 2, 2, repeats)
    return results


def run_stage_section(frames: int) -> dict:
    """One `c4d run` on a synthetic video with tiny random networks; per-stage seconds from report.json."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_c4d_run import make_inputs  # the inputs of the end-to-end test

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        video, ckpt = make_inputs(tmp, frames=frames, size=64)
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "c4d", "run", str(video), "--out", str(tmp / "out"),
                        "--pointmaps", str(ckpt), "--size", "64", "--preset", "tiny"], check=True,
                       stderr=subprocess.DEVNULL)
        total = time.perf_counter() - start
        report = json.loads((tmp / "out" / "report.json").read_text())
    stages = {**report["inputs"].get("seconds_before_reconstruction", {}), **report["seconds"]}
    return {"total_wall_s": total, "stages_s": stages, "edges": report["inputs"]["edges"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--skip-large", action="store_true", help="skip the 512x384 ViT-L runs")
    args = parser.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, CPU, "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    net = network_section(args.repeats, args.skip_large)
    base = net["vitl_224_linear_224x224_b1"]
    for name, sec in net.items():
        print(f"{name:32s} {sec:8.2f} s/pair  (x{sec / base:.2f} vs 224 linear)")
    stages = run_stage_section(args.frames)
    print(f"c4d run, {args.frames} frames at 64x48 ({stages['edges']} pairs), tiny random networks, "
          f"no tracker, preset tiny: {stages['total_wall_s']:.1f} s wall")
    for name, sec in (stages["stages_s"] or {}).items():
        print(f"  {name:20s} {sec:8.2f} s")


if __name__ == "__main__":
    main()
