"""Benchmark of DynPT training: data pipeline throughput, train step time and peak memory.

Usage:
    python benchmarks/bench_dynpt_train.py [--shards DIR] [--format1-shards DIR] [--workers 2]
        [--clips 120] [--models tiny,full] [--steps 3] [--repeats 3]

- Data: clips/s of the training pipeline (read, decode, clip choice, augmentation, track
  sampling, batching through a DataLoader) with `--workers` worker processes, on 24-frame
  256x256 shards with 256 tracks per clip (target >= 50 clips/s, so the loader never starves a
  GPU step), and the CPU ms per clip of the same pipeline in the main process (0 workers; load
  independent: 50 clips/s from 2 workers needs <= 40 ms). Baselines in the same run: the main
  process (0 workers), and with --format1-shards the same scenes in format 1 (rgb as PNG; make
  them with an older `c4d datagen`), read the old way (every member) and the new way (only the
  members training uses). Without --shards, 8 scenes are generated first with `c4d datagen`.
- Train step: median seconds per optimiser step (forward, loss, backward, AdamW) and the peak
  resident memory of a fresh process, for the `tiny-cpu` model and the paper's `full` model
  (frozen ViT-L with random weights, as no DUSt3R file is needed to time it), both on the same
  clip `--clip T,H,W,N` with batch 1; ratio full / tiny. The paper's clip (24,384,512,384) is
  far beyond a 2-core CPU for the full model; the default is a reduced 8,128,128,64.
  `--models tiny,tiny-2x --clip 8,64,64,32` compares the demo's model with
  configs/dynpt/tiny-cpu-2x.yaml, which gets the clip at twice the height and width (it trains
  on 2x crops of the same videos). `--models ft-mobility,ft-mobility-fusion,ft-full` times the
  fine-tuning recipes from CoTracker3's weights (the optimiser gets `train.lr_scale`'s groups:
  frozen parts take no gradient).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import torch

from c4d_core.config import load_config

MODELS = {  # name -> (preset, overrides, frame size factor: the clip's H and W are multiplied by it)
    "tiny": ("tiny-cpu", [], 1),
    "tiny-2x": ("tiny-cpu-2x", [], 2),  # trains on crops twice the size of tiny's, same videos
    "cnn-only": ("paper-gpu-cnn-only", [], 1),
    "full": ("paper-gpu", ["model.encoder_3d.random_init=true",
                           "model.encoder_3d.require_checkpoint=false"], 1),
    # the fine-tuning recipes from CoTracker3's weights (random weights here: the cost is the same)
    "ft-mobility": ("finetune-mobility", [], 1),
    "ft-mobility-fusion": ("finetune-mobility-fusion", ["model.encoder_3d.random_init=true",
                                                        "model.encoder_3d.require_checkpoint=false"], 1),
    "ft-full": ("finetune-full", ["model.encoder_3d.random_init=true",
                                  "model.encoder_3d.require_checkpoint=false"], 1),
}


def _cpu_seconds(pids: list[int]) -> float:
    """User + system CPU seconds of these processes so far (Linux /proc)."""
    total = 0
    for pid in pids:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        total += int(fields[11]) + int(fields[12])  # utime, stime in clock ticks
    return total / os.sysconf("SC_CLK_TCK")


def data_throughput(shards: str, workers: int, clips: int, repeats: int) -> tuple[list, list]:
    """clips/s and CPU ms/clip of the training DataLoader over `shards`.

    24 frames, 256x256 crops, 256 tracks. CPU ms/clip is this process's with 0 workers, and the
    worker processes' (from /proc, while timing) with workers: the load-independent cost.
    """
    from dynpt.data import ShardStream, make_loader

    cfg = load_config("dynpt", "paper-gpu", overrides=[
        "data.crop_size=[256,256]", "data.num_tracks=256", "data.num_frames=24",
        "data.max_stride=1", "data.shuffle_buffer=4"]).data
    rates, cpu_ms = [], []
    for r in range(repeats):
        loader = make_loader(ShardStream([shards], [1.0], cfg, seed=r), 4, workers)
        it = iter(loader)
        next(it)  # worker start-up is not throughput
        pids = [w.pid for w in getattr(it, "_workers", [])]  # DataLoader internals, Linux only
        cpu = _cpu_seconds(pids) if pids else time.process_time()
        start, seen = time.perf_counter(), 0
        while seen < clips:
            seen += len(next(it)["video"])
        rates.append(seen / (time.perf_counter() - start))
        cpu_ms.append(((_cpu_seconds(pids) if pids else time.process_time()) - cpu) / seen * 1e3)
        del it, loader
    return rates, cpu_ms


def read_decode_ms(shards: str, repeats: int, only_training_members: bool) -> list[float]:
    """CPU ms per scene to read a scene's tar members and `decode_scene` its training fields."""
    from datagen.shards import decode_scene, iter_samples, list_shards
    from dynpt.data import TRAIN_FIELDS

    members = TRAIN_FIELDS if only_training_members else None
    times = []
    for _ in range(repeats):
        start, count = time.process_time(), 0
        for shard in list_shards(shards):
            for sample in iter_samples(shard, members):
                decode_scene(sample, TRAIN_FIELDS)
                count += 1
        times.append((time.process_time() - start) / count * 1e3)
    return times


def _runs(values: list[float], digits: int = 1) -> str:
    return f"{statistics.median(values):.{digits}f} (runs {[round(v, digits) for v in values]})"


def step_times(model: str, steps: int, clip: str) -> dict:
    """Seconds per train step and peak RSS on a (T,H,W,N) clip (a fresh process by `main`)."""
    from dynpt.losses import LossWeights, dynpt_loss
    from dynpt.model import build_model
    from dynpt.train import param_groups

    preset, overrides, size_factor = MODELS[model]
    cfg = load_config("dynpt", preset, overrides=overrides)
    net = build_model(cfg.model).train()
    opt = torch.optim.AdamW(param_groups(net, cfg.train.lr, cfg.train.lr_scale))  # train.lr_scale's groups
    T, H, W, N = (int(v) for v in clip.split(","))
    H, W, B = H * size_factor, W * size_factor, 1
    gen = torch.Generator().manual_seed(0)
    video = torch.rand(B, T, 3, H, W, generator=gen) * 255
    queries = torch.rand(B, N, 3, generator=gen) * torch.tensor([T - 1, W - 1, H - 1])
    queries[..., 0] = queries[..., 0].round()
    target = {"tracks": queries[:, None, :, 1:].expand(B, T, N, 2).contiguous(),
              "visible": torch.rand(B, T, N, generator=gen) > 0.3,
              "moving": torch.rand(B, T, N, generator=gen) > 0.8}
    weights = LossWeights.from_config(cfg.loss)
    times, cpu = [], []
    for _ in range(steps + 1):  # the first step warms up allocators
        start, cpu_start = time.perf_counter(), time.process_time()
        loss, _ = dynpt_loss(net(video, queries), target, weights)
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - cpu_start)
    return {"model": model, "B": B, "T": T, "HxW": f"{H}x{W}", "N": N,
            "trainable_params": sum(p.numel() for p in net.parameters() if p.requires_grad),
            "step_s": statistics.median(times[1:]), "all_step_s": times[1:],
            "step_cpu_s": statistics.median(cpu[1:]),
            "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shards", help="24-frame 256x256 shard set (default: generate 8 scenes)")
    parser.add_argument("--format1-shards", help="the same scenes in shard format 1 (rgb PNG)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--clips", type=int, default=120, help="clips timed per repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--models", default="tiny,cnn-only,full")
    parser.add_argument("--steps", type=int, default=3, help="timed train steps per model")
    parser.add_argument("--clip", default="8,128,128,64", help="T,H,W,N of the timed clip")
    parser.add_argument("--only-steps", help=argparse.SUPPRESS)  # child process mode
    args = parser.parse_args()
    if args.only_steps:
        print(json.dumps(step_times(args.only_steps, args.steps, args.clip)))
        return

    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, load average "
          f"{' '.join(f'{v:.1f}' for v in os.getloadavg())} on {os.cpu_count()} cores")
    if args.clips > 0:
        cv2.setNumThreads(1)  # as in the loader workers, so 0 workers measures one core's work
        shards = args.shards
        if not shards:
            from c4d.cli import main as c4d_main

            shards = str(Path(tempfile.mkdtemp(prefix="bench-dynpt-")) / "shards")
            c4d_main(["datagen", "--num-scenes", "8", "--out", shards, "--resolution", "256",
                      "--frames", "24", "--scenes-per-shard", "4"])
        sets = {"format 2": shards, "format 1": args.format1_shards}
        for name, path in sets.items():
            if not path:
                continue
            ways = [("training members", True)] + [("all members", False)] * (name == "format 1")
            for way, only in ways:
                print(f"read + decode_scene (training fields), {name}, {way}: "
                      f"{_runs(read_decode_ms(path, args.repeats, only))} CPU ms/scene")
            base, base_cpu = data_throughput(path, 0, args.clips // 4, args.repeats)
            rates, cpu = data_throughput(path, args.workers, args.clips, args.repeats)
            print(f"data pipeline, {name}, 24x256x256, 256 tracks, batch 4: 0 workers "
                  f"{_runs(base)} clips/s, {_runs(base_cpu)} CPU ms/clip; {args.workers} workers "
                  f"{_runs(rates)} clips/s, {_runs(cpu)} worker CPU ms/clip; ratio "
                  f"{statistics.median(rates) / statistics.median(base):.2f}x")
    results = []
    for model in [m for m in args.models.split(",") if m]:
        out = subprocess.run([sys.executable, __file__, "--only-steps", model, "--steps",
                              str(args.steps), "--clip", args.clip],
                             capture_output=True, text=True, check=True)
        results.append(json.loads(out.stdout.strip().splitlines()[-1]))
        r = results[-1]
        print(f"train step {r['model']:>4} (B={r['B']} T={r['T']} {r['HxW']} N={r['N']}, "
              f"{r['trainable_params'] / 1e6:.2f}M trainable): median {r['step_s']:.2f} s "
              f"(runs {[round(t, 2) for t in r['all_step_s']]}), CPU {r['step_cpu_s']:.2f} s, "
              f"peak RSS {r['peak_rss_gib']:.2f} GiB")
    for r in results[1:]:
        print(f"ratio {r['model']}/{results[0]['model']} step time: "
              f"{r['step_s'] / results[0]['step_s']:.1f}x")


if __name__ == "__main__":
    main()
