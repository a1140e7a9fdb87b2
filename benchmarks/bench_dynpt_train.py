"""Benchmark of DynPT training: data pipeline throughput, train step time and peak memory.

Usage:
    python benchmarks/bench_dynpt_train.py [--shards DIR] [--format1-shards DIR] [--workers 1,2]
        [--loader-config PRESET --loader-set KEY=VALUE ...] [--clips 120] [--repeats 3]
        [--models tiny,cnn-only,full] [--clip T,H,W,N] [--batch B] [--iters I] [--set KEY=VALUE ...]
        [--window-strides 4,8] [--before DIR] [--cotracker-repo DIR | --cotracker-step SCRIPT]
        [--cotracker-model online --cotracker-window S] [--malloc-variants] [--device cuda [--bf16]]

- Data: clips/s of the training pipeline (read, decode, clip choice, augmentation, track
  sampling, batching through a DataLoader) with each of `--workers` worker counts and with none
  (the main process), and the CPU ms per clip (0 workers: this process; with workers: the worker
  processes', from /proc: load independent). The loader's `data:` section is `--loader-config`
  (paper-gpu) with `--loader-set` overrides (default: 24 frames, 256x256 crops, 256 tracks);
  e.g. `--loader-config tiny-cpu-2x --loader-set data.shuffle_buffer=8` is the demo's loader.
  With --format1-shards the same scenes in format 1 (rgb as PNG; make them with an older
  `c4d datagen`) are read the old way (every member) and the new way (only the members training
  uses). Without --shards, 8 scenes are generated first with `c4d datagen`. `--clips 0` skips it.
- Train step: CPU seconds (and wall) per optimiser step as `dynpt.train.Trainer.train_step` takes
  it (forward, loss, backward, gradient clipping, AdamW, OneCycle), after one warm-up step, and
  the peak resident memory, of each model in `--models` on one seeded batch (`clip_inputs`:
  `--batch` clips of `--clip T,H,W,N`), each in a fresh process per repeat, the systems
  interleaved (the order reversed every other repeat); medians over `--repeats`, and each system's
  ratios to the last system paired by repeat (median and range over the repeats; the load average
  is printed with every process). `--window-strides 4,8` times each DynPT model once per window
  stride (`model.window_stride`; `cnn-only/s8`), in the same interleaved run. `--device cuda` runs
  the steps on the GPU instead: the times are then wall seconds per step between CUDA synchronisations
  and the memory is the peak GPU memory allocated by tensors (`--bf16`: forward and loss under
  bfloat16 autocast, as `train.bf16` trains; CoTracker3's script takes the same flags and wraps its
  forward as Lightning's bf16 precision does). `--set` overrides every
  model's config (`--iters` is `model.train_iters`). `--before DIR` times each model again with
  the `dynpt` package in DIR (`git archive COMMIT dynpt | tar -x -C DIR`): the code before a
  change, in the same run. `--cotracker-repo DIR` times CoTracker3's own train step on the same
  batch with facebookresearch/co-tracker's code in DIR (a checkout or `git archive` outside this
  repository, which holds none of its code; the commit used is printed when DIR is a git work tree):
  `CoTrackerThree{Online,Offline}` built as its `train_on_kubric.py` builds it (stride 4, radius 3,
  4 levels, 64 virtual tracks, `linear_layer_for_vis_conf`, window `--cotracker-window`), random
  weights, its own `fetch_optimizer` (AdamW 5e-4, weight decay 5e-4 as its launch script sets,
  OneCycle) and its own `forward_batch` (its query sampling from the visibility, its losses with the
  Huber term), then backward, `clip_grad_norm_` 1.0 and the two steps as its `Lite.run` loop takes
  them (float32 on the CPU; with `--bf16` on a GPU its model's forward under bfloat16 autocast, as
  Lightning's bf16 precision wraps it). `train_on_kubric.py`'s imports that the step does not use
  (Lightning, the visualiser, the evaluator, the dataset utilities) are replaced by empty stand-ins.
  `--cotracker-step SCRIPT` instead times it with a script of one's own on the same batch (saved
  as .npz): it is run as `SCRIPT --inputs NPZ --model online|offline --window S --iters I
  --steps K [--device cuda] [--bf16]` and prints one JSON line with step_cpu_s, step_s,
  peak_rss_gib, base_rss_gib (after its imports) and peak_gpu_gib (None on the CPU). CoTracker3
  runs with glibc's default allocator, as its script does. DynPT's steps run with the allocator
  `c4d train` sets (`prepare_allocator(every_size=True)`); `--malloc-variants` adds each model with glibc's
  defaults (`+glibc`) and CoTracker3 with `c4d train`'s allocator (`+kept`). Models: `tiny` (`tiny-cpu`),
  `tiny-2x` (`tiny-cpu-2x`: the clip at twice its height and width), `cnn-only`
  (`paper-gpu-cnn-only`), `full` (`paper-gpu`, frozen ViT-L with random weights: no DUSt3R file
  is needed to time it) and the fine-tuning recipes `ft-mobility`, `ft-mobility-fusion`,
  `ft-full` (the optimiser gets `train.lr_scale`'s groups: frozen parts take no gradient).
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
import numpy as np
import torch

from timing import git_commit, load_average, this_commit
from c4d_core.config import load_config
from c4d_core.system import allocator_environment

GLIBC, KEPT = "+glibc", "+kept"  # --malloc-variants: the other allocator (see step_times)
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


LOADER_DEFAULT = ["data.crop_size=[256,256]", "data.num_tracks=256", "data.num_frames=24",
                  "data.max_stride=1", "data.shuffle_buffer=4"]  # on the paper-gpu preset


def data_throughput(shards: str, workers: int, clips: int, repeats: int, preset: str = "paper-gpu",
                    overrides: list[str] = LOADER_DEFAULT, batch: int = 4) -> tuple[list, list]:
    """clips/s and CPU ms/clip of the training DataLoader over `shards` with the `data:` section
    of `preset` + `overrides` (default: 24 frames, 256x256 crops, 256 tracks).

    CPU ms/clip is this process's with 0 workers, and the worker processes' (from /proc, while
    timing) with workers: the load-independent cost.
    """
    from dynpt.data import ShardStream, make_loader

    cfg = load_config("dynpt", preset, overrides=overrides).data
    rates, cpu_ms = [], []
    for r in range(repeats):
        loader = make_loader(ShardStream([shards], [1.0], cfg, seed=r), batch, workers)
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


def clip_inputs(B: int, T: int, H: int, W: int, N: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A seeded batch as the training loader delivers it: video uint8 (B,T,H,W,3), queries
    float32 (B,N,3) as (t, x, y), tracks (B,T,N,2) (a random walk from each query point), visible
    (B,T,N) (always at the query frame, where a quarter of the queries are after frame 0) and
    moving (B,T,N) bool. Saved with `np.savez` it is also the input of `--cotracker-step`."""
    rng = np.random.default_rng(seed)
    t_q = np.where(rng.random((B, N)) < 0.25, rng.integers(0, T, (B, N)), 0)
    xy_q = rng.random((B, N, 2)) * [W - 1, H - 1]
    walk = rng.normal(0, 2.0, (B, T, N, 2)).cumsum(1)
    walk -= np.take_along_axis(walk, t_q[:, None, :, None], 1)
    visible = (rng.random((B, T, N)) > 0.2) | (np.arange(T)[None, :, None] == t_q[:, None])
    return {"video": rng.integers(0, 256, (B, T, H, W, 3), dtype=np.uint8),
            "queries": np.concatenate([t_q[..., None], xy_q], -1).astype(np.float32),
            "tracks": (xy_q[:, None] + walk).astype(np.float32), "visible": visible,
            "moving": rng.random((B, T, N)) > 0.8}


def _peak_rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # Linux: KiB


def step_times(model: str, steps: int, inputs: str, overrides: list[str], device: str = "cpu",
               bf16: bool = False, glibc_malloc: bool = False) -> dict:
    """CPU and wall seconds per optimiser step, peak RSS and (on a GPU) peak GPU memory of a fresh
    process (by `main`) on the batch saved at `inputs`, as `Trainer.train_step` does it: forward
    and loss (under bfloat16 autocast with `bf16` on a GPU), backward, gradient clipping, AdamW
    and OneCycle steps, with the allocator as `c4d train` sets it (`prepare_allocator(every_size=
    True)`) or, with `glibc_malloc`, glibc's defaults. On a GPU each step is timed between CUDA
    synchronisations."""
    from c4d_core.system import prepare_allocator
    from dynpt.device import (autocast, bf16_supported, peak_memory, reset_peak_memory,
                              training_autocast_dtype)
    from dynpt.losses import LossWeights, dynpt_loss
    from dynpt.model import build_model
    from dynpt.train import param_groups

    if not glibc_malloc:
        prepare_allocator(every_size=True)  # as `c4d train` (dynpt.cli_train) sets it
    base_rss = _peak_rss_gib()  # after the imports
    dev = torch.device(device)
    amp_dtype = training_autocast_dtype(dev.type, bf16, bf16_supported(dev))  # as the Trainer's
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    preset, preset_overrides, size_factor = MODELS[model]
    cfg = load_config("dynpt", preset, overrides=[*preset_overrides, *overrides])
    with np.load(inputs) as data:
        batch = {k: torch.from_numpy(data[k]).to(dev) for k in data.files}
    video = batch["video"].permute(0, 1, 4, 2, 3).float()  # (B,T,3,H,W)
    if size_factor != 1:  # the model tracks the clip at this multiple of its size
        B, T = video.shape[:2]
        video = torch.nn.functional.interpolate(video.flatten(0, 1), scale_factor=size_factor,
                                                mode="bilinear").unflatten(0, (B, T))
    queries = batch["queries"] * torch.tensor([1.0, size_factor, size_factor], device=dev)
    target = {"tracks": batch["tracks"] * size_factor, "visible": batch["visible"],
              "moving": batch["moving"]}
    torch.manual_seed(0)
    net = build_model(cfg.model).to(dev).train()
    tc = cfg.train
    groups = param_groups(net, tc.lr, tc.lr_scale)  # train.lr_scale's groups
    opt = torch.optim.AdamW(groups, lr=tc.lr, weight_decay=tc.weight_decay, eps=tc.adam_eps)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=[g["lr"] for g in groups],
                                                total_steps=steps + 101, cycle_momentum=False)
    weights = LossWeights.from_config(cfg.loss)
    times, cpu = [], []
    reset_peak_memory(dev)
    for _ in range(steps + 1):  # the first step warms up allocators (and chooses kernels)
        sync()
        start, cpu_start = time.perf_counter(), time.process_time()
        with autocast(dev.type, amp_dtype):
            loss, _ = dynpt_loss(net(video, queries), target, weights)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), tc.grad_clip)
        opt.step()
        sched.step()
        opt.zero_grad(set_to_none=True)
        sync()
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - cpu_start)
    B, T, _, H, W = video.shape
    peak_gpu = peak_memory(dev)  # bytes; None on a CPU
    return {"model": model, "B": B, "T": T, "HxW": f"{H}x{W}", "N": queries.shape[1],
            "threads": torch.get_num_threads(), "window": [cfg.model.window_len, cfg.model.window_stride],
            "trainable_params": sum(p.numel() for p in net.parameters() if p.requires_grad),
            "step_s": statistics.median(times[1:]), "all_step_s": times[1:],
            "step_cpu_s": statistics.median(cpu[1:]), "all_step_cpu_s": cpu[1:],
            "peak_rss_gib": _peak_rss_gib(), "base_rss_gib": base_rss,
            "peak_gpu_gib": None if peak_gpu is None else peak_gpu / 2**30}


def _import_cotracker_training(repo: str):
    """facebookresearch/co-tracker's `train_on_kubric` module and model classes from the checkout
    in `repo` (outside this repository). The modules it imports for what the step does not use
    (Lightning, the visualiser, the evaluator, the datasets' loaders) are empty stand-ins, so
    neither Lightning nor torchvision is needed; `forward_batch`, `fetch_optimizer`, the models and
    the losses are its own code."""
    import types

    sys.path.insert(0, str(Path(repo).resolve()))

    def stand_in(name: str, **attrs) -> None:
        module = types.ModuleType(name)
        module.__dict__.update(attrs)
        sys.modules[name] = module

    unused = type("Unused", (), {})
    if "pytorch_lightning" not in sys.modules:
        stand_in("pytorch_lightning")
        stand_in("pytorch_lightning.lite", LightningLite=unused)
    stand_in("cotracker.utils.visualizer", Visualizer=unused)
    stand_in("cotracker.evaluation.core.evaluator", Evaluator=unused)
    stand_in("cotracker.utils.train_utils", **{n: unused for n in (
        "Logger", "get_eval_dataloader", "get_train_dataset", "sig_handler", "term_handler",
        "run_test_eval")})
    import train_on_kubric  # co-tracker's, from `repo`

    return train_on_kubric


def cotracker_step_times(repo: str, model: str, window: int, iters: int, steps: int, inputs: str,
                         device: str = "cpu", bf16: bool = False) -> dict:
    """CoTracker3's own train step in this (fresh) process, on the batch saved at `inputs`, as its
    `train_on_kubric.py` takes it: the model built as there (`--model_stride 4 --corr_radius 3
    --num_virtual_tracks 64 --linear_layer_for_vis_conf`, window `window`, the clip's size as
    `crop_size`), random weights, its `fetch_optimizer` (lr 5e-4, `--wdecay 0.0005` as its launch
    script), then per step: `zero_grad`, its `forward_batch` (query sampling, forward with
    `is_train=True`, its losses; `--add_huber_loss` as its launch script), the loss terms summed,
    backward, `clip_grad_norm_(1.0)`, optimizer and scheduler steps. Its GradScaler is disabled
    there (no-op). `bf16` on a GPU: the model's forward under bfloat16 autocast (Lightning's bf16
    precision wraps the forward only; the losses run in float32). Timed as `step_times`."""
    import contextlib
    from types import SimpleNamespace

    from dynpt.device import peak_memory, reset_peak_memory

    with contextlib.redirect_stdout(sys.stderr):  # its prints (parameter counts) off the JSON line
        tok = _import_cotracker_training(repo)
    base_rss = _peak_rss_gib()  # after the imports
    dev = torch.device(device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    with np.load(inputs) as data:
        arrays = {k: data[k] for k in data.files}
    B, T, H, W, _ = arrays["video"].shape
    batch = SimpleNamespace(  # its CoTrackerData fields as its collate_fn_train delivers them
        video=torch.from_numpy(arrays["video"]).permute(0, 1, 4, 2, 3).float().to(dev),
        trajectory=torch.from_numpy(arrays["tracks"]).to(dev),
        visibility=torch.from_numpy(arrays["visible"]).float().to(dev),
        valid=torch.ones(arrays["visible"].shape, device=dev))
    args = SimpleNamespace(  # train_on_kubric's arguments as its online launch script sets them
        lr=5e-4, wdecay=5e-4, num_steps=steps + 1, train_iters=iters, sliding_window_len=window,
        offline_model=model == "offline", query_sampling_method=None, add_huber_loss=True,
        train_only_on_visible=False)
    cls = tok.CoTrackerThreeOffline if args.offline_model else tok.CoTrackerThreeOnline
    torch.manual_seed(0)
    net = cls(stride=4, corr_radius=3, corr_levels=4, window_len=window, num_virtual_tracks=64,
              model_resolution=(H, W), linear_layer_for_vis_conf=True).to(dev)
    if bf16 and dev.type == "cuda":
        forward = net.forward

        def forward_bf16(*a, **kw):
            with torch.autocast("cuda", dtype=torch.bfloat16):
                return forward(*a, **kw)

        net.forward = forward_bf16
    with contextlib.redirect_stdout(sys.stderr):
        optimizer, scheduler = tok.fetch_optimizer(args, net)
    net.train()
    times, cpu = [], []
    reset_peak_memory(dev)
    for _ in range(steps + 1):  # the first step warms up allocators, as in `step_times`
        sync()
        start, cpu_start = time.perf_counter(), time.process_time()
        optimizer.zero_grad(set_to_none=True)
        output = tok.forward_batch(batch, net, args)
        loss = sum(v["loss"] for v in output.values() if "loss" in v)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        optimizer.step()
        scheduler.step()
        sync()
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - cpu_start)
    peak_gpu = peak_memory(dev)
    return {"model": f"cotracker3-{model}", "B": B, "T": T, "HxW": f"{H}x{W}",
            "N": arrays["tracks"].shape[2], "threads": torch.get_num_threads(),
            "trainable_params": sum(p.numel() for p in net.parameters() if p.requires_grad),
            "step_s": statistics.median(times[1:]), "all_step_s": times[1:],
            "step_cpu_s": statistics.median(cpu[1:]), "all_step_cpu_s": cpu[1:],
            "peak_rss_gib": _peak_rss_gib(), "base_rss_gib": base_rss,
            "peak_gpu_gib": None if peak_gpu is None else peak_gpu / 2**30}


def _system_command(name: str, inputs: Path, args) -> tuple[list[str], dict]:
    """The child command and environment of one system: `cotracker3[+kept]` (CoTracker3's step by
    `--cotracker-repo` or `--cotracker-step`) or a DynPT model `MODEL[/sSTRIDE][@before][+glibc]`."""
    env = dict(os.environ)
    device = ["--device", args.device] + ["--bf16"] * args.bf16
    if name.startswith("cotracker3"):
        common = ["--inputs", str(inputs), "--steps", str(args.steps), "--iters", str(args.iters or 4),
                  *device]
        if args.cotracker_repo:
            cmd = [sys.executable, __file__, "--only-cotracker", args.cotracker_repo, *common,
                   "--cotracker-model", args.cotracker_model, "--cotracker-window",
                   str(args.cotracker_window)]
        else:
            cmd = [sys.executable, args.cotracker_step, *common, "--model", args.cotracker_model,
                   "--window", str(args.cotracker_window)]
        if name.endswith(KEPT):  # c4d train's allocator, through glibc's variables
            env.update(allocator_environment(every_size=True))
        return cmd, env
    model, _, stride = name.split("@")[0].removesuffix(GLIBC).partition("/s")
    cmd = [sys.executable, __file__, "--only-steps", model, "--steps", str(args.steps), "--inputs",
           str(inputs), *[f"--set={o}" for o in args.set],
           *([f"--set=model.train_iters={args.iters}"] if args.iters else []),
           *([f"--set=model.window_stride={stride}"] if stride else []), *device,
           *["--glibc-malloc"] * name.endswith(GLIBC)]
    if name.endswith("@before"):  # the same model from the code in --before
        env["PYTHONPATH"] = os.pathsep.join([args.before, env.get("PYTHONPATH", "")])
    return cmd, env


def _paired(runs: dict[str, list[dict]], name: str, ref: str, key: str) -> list[float]:
    """Per repeat, `name`'s `key` over the reference's in the same repeat (a paired ratio)."""
    return [a[key] / b[key] for a, b in zip(runs[name], runs[ref])]


def _median_range(values: list[float]) -> str:
    return f"{statistics.median(values):.2f} ({min(values):.2f}-{max(values):.2f})"


def compare_steps(systems: list[str], args) -> None:
    """Each system's train step in a fresh process per repeat, the systems interleaved (a, b, c,
    then c, b, a, ...: the order reversed every other repeat, so no system always follows the same
    one); per system the median over repeats of each process's median CPU seconds (on a GPU: wall
    seconds) and its peak RSS (on a GPU: peak GPU memory), and its ratios to the last system
    (CoTracker3 when given) paired by repeat: median and range over the repeats. The load average
    is printed with every process."""
    B, (T, H, W, N) = args.batch, (int(v) for v in args.clip.split(","))
    inputs = Path(tempfile.mkdtemp(prefix="bench-dynpt-step-")) / "batch.npz"
    np.savez(inputs, **clip_inputs(B, T, H, W, N))
    runs: dict[str, list[dict]] = {name: [] for name in systems}
    if args.cotracker_repo:
        print(f"co-tracker: {Path(args.cotracker_repo).resolve()} at "
              f"{git_commit(args.cotracker_repo, ('cotracker', 'train_on_kubric.py'))}", flush=True)
    for repeat in range(args.repeats):
        for name in systems if repeat % 2 == 0 else systems[::-1]:
            cmd, env = _system_command(name, inputs, args)
            load_before = load_average()
            out = subprocess.run(cmd, capture_output=True, text=True, env=env)
            if out.returncode:
                sys.exit(f"{name} failed (exit {out.returncode}):\n{out.stderr[-3000:]}")
            r = json.loads(out.stdout.strip().splitlines()[-1])
            runs[name].append(r)
            print(f"repeat {repeat} {name:>12} (B={r['B']} T={r['T']} {r['HxW']} N={r['N']}, "
                  f"{r['trainable_params'] / 1e6:.2f}M trainable, {r.get('threads', '?')} threads"
                  + (f", window {r['window'][0]}/{r['window'][1]}" if r.get("window") else "")
                  + f"): CPU {r['step_cpu_s']:.2f} s/step "
                  f"(wall {r['step_s']:.2f} s), peak RSS {r['peak_rss_gib']:.2f} GiB "
                  f"(after imports {r['base_rss_gib']:.2f})"
                  + (f", peak GPU {r['peak_gpu_gib']:.2f} GiB" if r.get("peak_gpu_gib") else "")
                  + f"; load {load_before} -> {load_average()}", flush=True)
    if args.device != "cpu":
        _gpu_table(runs, args)
        return
    med = {name: {key: statistics.median(r[key] for r in rs)
                  for key in ("step_cpu_s", "step_s", "peak_rss_gib", "base_rss_gib")}
           for name, rs in runs.items()}
    ref = systems[-1]
    print(f"\n| system | CPU s/step (median of {args.repeats}; range) | peak RSS GiB (range) "
          f"| above imports GiB | time / {ref}, paired (median; range) "
          f"| memory / {ref}, paired (median; range) |\n|---|---:|---:|---:|---:|---:|")
    for name, m in med.items():
        cpu = [r["step_cpu_s"] for r in runs[name]]
        rss = [r["peak_rss_gib"] for r in runs[name]]
        print(f"| {name} | {m['step_cpu_s']:.2f} ({min(cpu):.2f}-{max(cpu):.2f}) | "
              f"{m['peak_rss_gib']:.2f} ({min(rss):.2f}-{max(rss):.2f}) | "
              f"{m['peak_rss_gib'] - m['base_rss_gib']:.2f} | "
              f"{_median_range(_paired(runs, name, ref, 'step_cpu_s'))} | "
              f"{_median_range(_paired(runs, name, ref, 'peak_rss_gib'))} |")
    print(f"\nload average at the end: {load_average()}")


def _gpu_table(runs: dict[str, list[dict]], args) -> None:
    """The GPU comparison: wall s/step and peak GPU memory, medians over repeats, ratios to the
    last system."""
    med = {name: {key: statistics.median(r[key] for r in rs) for key in ("step_s", "peak_gpu_gib")}
           for name, rs in runs.items()}
    ref = list(runs)[-1]
    precision = "bf16 autocast" if args.bf16 else "fp32"
    print(f"\n| system ({args.device}, {precision}) | s/step (median of {args.repeats}) | peak GPU GiB "
          f"| time / {ref} | memory / {ref} |\n|---|---:|---:|---:|---:|")
    for name, m in med.items():
        print(f"| {name} | {m['step_s']:.3f} | {m['peak_gpu_gib']:.2f} | "
              f"{m['step_s'] / med[ref]['step_s']:.2f} | {m['peak_gpu_gib'] / med[ref]['peak_gpu_gib']:.2f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shards", help="24-frame 256x256 shard set (default: generate 8 scenes)")
    parser.add_argument("--format1-shards", help="the same scenes in shard format 1 (rgb PNG)")
    parser.add_argument("--workers", default="2", help="loader worker counts compared with 0, e.g. 1,2")
    parser.add_argument("--loader-config", default="paper-gpu", help="the dynpt preset of the loader's data:")
    parser.add_argument("--loader-set", action="append", metavar="KEY=VALUE",
                        help="data: overrides of the loader (default: 24 frames, 256x256 crops, 256 "
                        "tracks, stride 1)")
    parser.add_argument("--loader-batch", type=int, default=4)
    parser.add_argument("--clips", type=int, default=120, help="clips timed per repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--models", default="tiny,cnn-only,full",
                        help="DynPT models (keys of MODELS) whose train step is timed")
    parser.add_argument("--steps", type=int, default=3, help="timed train steps per process")
    parser.add_argument("--clip", default="8,128,128,64", help="T,H,W,N of the timed clip")
    parser.add_argument("--batch", type=int, default=1, help="clips per train step")
    parser.add_argument("--iters", type=int, default=0, help="refinement iterations (0: the preset's)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="config override for every DynPT model, e.g. model.window_stride=8")
    parser.add_argument("--window-strides", default="", metavar="S1,S2",
                        help="time each DynPT model once per window stride (model.window_stride), "
                        "interleaved, e.g. 4,8: the preset's and CoTracker3's (S/2) at window 16")
    parser.add_argument("--cotracker-repo", metavar="DIR",
                        help="a facebookresearch/co-tracker checkout (outside this repository): times "
                        "CoTracker3's own train step (its train_on_kubric.forward_batch, losses, "
                        "optimiser) on the same batch, in the same interleaved run, as the reference")
    parser.add_argument("--cotracker-step", metavar="SCRIPT",
                        help="a script timing CoTracker3's own train step on the same batch (not part "
                        "of this repository): run as SCRIPT --inputs NPZ --model M --window S --iters I "
                        "--steps K, it prints one JSON line with step_cpu_s, step_s, peak_rss_gib, "
                        "base_rss_gib")
    parser.add_argument("--before", metavar="DIR", help="a folder holding an earlier `dynpt` package "
                        "(e.g. `git archive COMMIT dynpt | tar -x -C DIR`): each model is also timed "
                        "with it, interleaved")
    parser.add_argument("--cotracker-model", default="online", choices=("online", "offline"))
    parser.add_argument("--cotracker-window", type=int, default=16)
    parser.add_argument("--device", default="cpu", help="where the train steps run: cpu or cuda")
    parser.add_argument("--bf16", action="store_true", help="on a GPU: bfloat16 autocast (train.bf16)")
    parser.add_argument("--malloc-variants", action="store_true",
                        help="also time each DynPT model with glibc's default allocator (+glibc) and "
                        "CoTracker3 with the one `c4d train` sets (+kept): how much of a ratio is the "
                        "allocator")
    parser.add_argument("--only-steps", help=argparse.SUPPRESS)  # child process mode
    parser.add_argument("--only-cotracker", metavar="DIR", help=argparse.SUPPRESS)  # child mode
    parser.add_argument("--glibc-malloc", action="store_true", help=argparse.SUPPRESS)  # child mode
    parser.add_argument("--inputs", help=argparse.SUPPRESS)  # child process mode: the batch
    args = parser.parse_args()
    if args.only_steps:
        print(json.dumps(step_times(args.only_steps, args.steps, args.inputs, args.set, args.device,
                                    args.bf16, args.glibc_malloc)))
        return
    if args.only_cotracker:
        print(json.dumps(cotracker_step_times(args.only_cotracker, args.cotracker_model,
                                              args.cotracker_window, args.iters or 4, args.steps,
                                              args.inputs, args.device, args.bf16)))
        return
    if args.cotracker_repo and args.cotracker_step:
        parser.error("--cotracker-repo or --cotracker-step, not both")

    print(f"{time.strftime('%Y-%m-%d %H:%M')}, commit {this_commit()}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, load average "
          f"{load_average()} on {os.cpu_count()} cores")
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
            loader = (args.loader_config, args.loader_set or LOADER_DEFAULT, args.loader_batch)
            cfg = load_config("dynpt", loader[0], overrides=loader[1]).data
            setting = (f"{loader[0]} {cfg.num_frames}x{cfg.crop_size[0]}x{cfg.crop_size[1]}, "
                       f"{cfg.num_tracks} tracks, batch {loader[2]}")
            base, base_cpu = data_throughput(path, 0, args.clips // 4, args.repeats, *loader)
            print(f"data pipeline, {name}, {setting}: 0 workers {_runs(base)} clips/s, "
                  f"{_runs(base_cpu)} CPU ms/clip", flush=True)
            for workers in [int(w) for w in args.workers.split(",") if int(w) > 0]:
                rates, cpu = data_throughput(path, workers, args.clips, args.repeats, *loader)
                print(f"data pipeline, {name}, {setting}: {workers} workers {_runs(rates)} clips/s, "
                      f"{_runs(cpu)} worker CPU ms/clip; ratio to 0 workers "
                      f"{statistics.median(rates) / statistics.median(base):.2f}x", flush=True)
    models = [m for m in args.models.split(",") if m]
    strides = [int(v) for v in args.window_strides.split(",") if v]
    models = [f"{m}/s{v}" for m in models for v in strides] if strides else models
    systems = models + [f"{m}@before" for m in models if args.before]
    cotracker = ["cotracker3"] * bool(args.cotracker_step or args.cotracker_repo)
    if args.malloc_variants:
        systems += [f"{m}{GLIBC}" for m in models]
        cotracker = [f"{c}{KEPT}" for c in cotracker] + cotracker
    systems += cotracker  # the reference last: CoTracker3 as its own script runs
    if systems:
        compare_steps(systems, args)


if __name__ == "__main__":
    main()
