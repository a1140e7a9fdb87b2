"""Speed and memory of DynPT tracking (full-size model, CoTracker3 sizes) on this machine.

Tracking cost splits into per-frame feature encoding (every frame is encoded once, the sliding
windows reuse shared frames) and refinement iterations (`eval_iters` per window, each over the
whole 16-frame window and all points). This script times both parts separately (median of
`--repeats`), for 1,000 points at 256x256 and 384x512, CNN-only and with a ViT-L-sized DUSt3R
encoder (random frozen weights: the cost does not depend on the values), and combines them into
seconds per frame for a `--frames`-frame video:

    total = frames * encode_per_frame + windows * eval_iters * seconds_per_iteration

Each case runs in a fresh subprocess, so its peak resident memory (ru_maxrss, minus the
interpreter-and-imports baseline) is its own; it covers the weights, a 16-frame feature window and
one refinement iteration over 1,000 points (the largest step). With `--end-to-end` it also runs
`Tracker.track` once per case on a real `--frames`-frame video (slow on a CPU; checks the model).

    .venv/bin/python benchmarks/bench_dynpt_model.py [--repeats 3] [--points 1000] [--frames 24]
        [--cases cnn-256,cnn-384x512,vitl-256,vitl-384x512] [--end-to-end] [--device cpu] [--threads N]
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from c4d_core.config import load_config
from dynpt.inference import Tracker
from dynpt.model import build_model

CASES = {  # name -> (H, W, 3D encoder)
    "cnn-256": (256, 256, False),
    "cnn-384x512": (384, 512, False),
    "vitl-256": (256, 256, True),
    "vitl-384x512": (384, 512, True),
}


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


def _count_flops(fn) -> int:
    """Matmul/conv/attention FLOPs of one call (torch's FlopCounterMode; element-wise ops and
    grid_sample are not counted)."""
    with FlopCounterMode(display=False) as counter:
        fn()
    return counter.get_total_flops()


def _median_seconds(fn, repeats: int, sync) -> tuple[float, int]:
    """Median seconds of `repeats` calls, after an untimed warm-up call that counts the FLOPs."""
    flops = _count_flops(fn)  # also the warm-up: kernel selection and allocator
    times = []
    for _ in range(repeats):
        sync()
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return statistics.median(times), flops


def run_case(name: str, points: int, frames: int, repeats: int, device: str, end_to_end: bool,
             threads: int) -> dict:
    """One case in this process: parameter counts, timings, peak memory."""
    H, W, vit = CASES[name]
    if threads:
        torch.set_num_threads(threads)
    baseline = _peak_mib()
    torch.manual_seed(0)
    overrides = ["model.resolution=null"] + (["model.encoder_3d.random_init=true"] if vit else [])
    model = build_model(load_config("dynpt/model", "cnn-only", overrides=overrides).model).eval().to(device)
    cfg = model.config
    S, step, iters = cfg["window_len"], cfg["window_stride"], cfg["eval_iters"]
    cuda = device.startswith("cuda")
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    autocast = torch.autocast("cuda", dtype=torch.bfloat16, enabled=cuda)
    rng = torch.Generator().manual_seed(0)

    with torch.inference_mode(), autocast:
        m = model.size_multiple
        Hp, Wp = -(-H // m) * m, -(-W // m) * m
        frame = (torch.rand(1, 3, Hp, Wp, generator=rng) * 2 - 1).to(device)
        encode, encode_flops = _median_seconds(lambda: model.encode_frames(frame), repeats, sync)

        # one refinement iteration over a full window of points (features: random, unit norm)
        fmaps = torch.randn(1, S, cfg["feature_dim"], Hp // 4, Wp // 4, generator=rng).to(device)
        fmaps = fmaps / fmaps.norm(dim=2, keepdim=True)
        from dynpt.correlation import feature_pyramid

        pyramid = feature_pyramid(fmaps, cfg["corr_levels"])
        xy = torch.stack([torch.rand(1, points, generator=rng) * (W - 1),
                          torch.rand(1, points, generator=rng) * (H - 1)], -1).to(device)
        t0 = torch.zeros(1, points, dtype=torch.long, device=device)
        query_feats = model.corr.query_features(pyramid, t0, xy, model.stride)
        coords = xy[:, None].expand(1, S, points, 2).clone()
        logits = coords.new_zeros(1, S, points, 3)
        # the iteration costs the same with and without the ViT (same feature width): one timed
        # sample suffices there (it still counts for the case's peak memory)
        iteration, iteration_flops = _median_seconds(
            lambda: model._refine(pyramid, query_feats, coords, logits, 1), 1 if vit else repeats, sync)

    windows = len(model.window_starts(frames))
    total = frames * encode + windows * iters * iteration
    result = {
        "case": name, "H": H, "W": W, "points": points, "frames": frames, "repeats": repeats,
        "device": device, "threads": torch.get_num_threads(),
        "params": model.parameter_counts(), "iteration_samples": 1 if vit else repeats,
        "encode_s_per_frame": encode, "iteration_s": iteration,
        "encode_gflop_per_frame": encode_flops / 1e9, "iteration_gflop": iteration_flops / 1e9,
        "gflop_per_s": (encode_flops + iteration_flops) / (encode + iteration) / 1e9, "windows": windows, "iters": iters,
        "estimated_s_per_frame": total / frames,
        "steady_state_s_per_frame": encode + iters * iteration / step,  # long videos
        "peak_rss_mib": _peak_mib() - baseline,
    }
    if cuda:
        result["peak_cuda_mib"] = torch.cuda.max_memory_allocated() / 2**20
    if end_to_end:
        video = np.random.default_rng(0).integers(0, 256, (frames, H, W, 3), dtype=np.uint8)
        queries = np.stack([np.zeros(points), np.random.default_rng(1).uniform(0, W - 1, points),
                            np.random.default_rng(2).uniform(0, H - 1, points)], 1).astype(np.float32)
        tracker = Tracker(model, device)
        sync()
        start = time.perf_counter()
        tracker.track(video, queries)
        sync()
        result["end_to_end_s_per_frame"] = (time.perf_counter() - start) / frames
        result["peak_rss_mib"] = _peak_mib() - baseline
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--points", type=int, default=1000)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--end-to-end", action="store_true")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("--json", help="also write the results here")
    parser.add_argument("--one-case", help=argparse.SUPPRESS)  # internal: run one case, print JSON
    args = parser.parse_args()
    if args.one_case:
        print(json.dumps(run_case(args.one_case, args.points, args.frames, args.repeats, args.device,
                                  args.end_to_end, args.threads)))
        return

    results = []
    for name in args.cases.split(","):
        cmd = [sys.executable, __file__, "--one-case", name, "--repeats", str(args.repeats),
               "--points", str(args.points), "--frames", str(args.frames), "--device", args.device, "--threads", str(args.threads)]
        cmd += ["--end-to-end"] if args.end_to_end else []
        out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
        results.append(json.loads(out.strip().splitlines()[-1]))
        r = results[-1]
        print(f"{name:14s} encode {r['encode_s_per_frame']:8.3f} s/frame  iteration {r['iteration_s']:7.3f} s  "
              f"-> {r['estimated_s_per_frame']:7.2f} s/frame ({r['frames']} frames, {r['windows']} windows "
              f"x {r['iters']} iters), steady {r['steady_state_s_per_frame']:6.2f} s/frame, "
              f"peak RSS {r['peak_rss_mib']:7.0f} MiB; GFLOP encode {r['encode_gflop_per_frame']:.0f}/frame, "
              f"iteration {r['iteration_gflop']:.0f}, achieved {r['gflop_per_s']:.1f} GFLOP/s"
              + (f", end-to-end {r['end_to_end_s_per_frame']:.2f} s/frame" if "end_to_end_s_per_frame" in r else ""),
              flush=True)
    base = results[0]["estimated_s_per_frame"]
    print(f"\nratios against {results[0]['case']} (estimated s/frame):")
    for r in results:
        print(f"  {r['case']:14s} x{r['estimated_s_per_frame'] / base:6.2f}")
    print("\nparameters per part:")
    for r in results:
        print(f"  {r['case']:14s} " + ", ".join(f"{k} {v:,}" for k, v in r["params"].items()))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
