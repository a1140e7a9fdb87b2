"""Everything GPU-bound, once, within a time budget (8 minutes) on one GPU; prints one Markdown table.

    python benchmarks/device_check.py [--out DIR] [--train-seconds 300] [--budget-s 480]  # CUDA
    python benchmarks/device_check.py --cpu                               # tiny sizes, ~1 minute
    python benchmarks/device_check.py --skip dust3r,c4d                   # leave sections out
    python benchmarks/device_check.py --section-limit-s 100 --section-limit-s loader=60

Sections, each through the project's own builders (configs, `dynpt.train.Trainer`,
`c4d_pipeline` DUSt3R network and pointmap source, `c4d_pipeline.optimize.optimise`):
1. shards: `c4d datagen` train and held-out val sets, generated fresh into --out;
2. DynPT `paper-gpu-cnn-only` training speed at the paper crop (384x512, 24 frames, 384 tracks,
   batch 1 per GPU), bf16 autocast and fp32: clips/s over timed optimiser steps after warm-up, on
   one real batch reused (data loading excluded), and peak GPU memory;
3. DUSt3R ViT-L 512 DPT (random weights saved and reloaded in the official checkpoint layout)
   pair forward through `Dust3rPointmaps` at 512x384, in float32 (the default) and, on a GPU, with
   `pointmaps.precision=bf16`: seconds per pair at batch 1 and at the batch it picks from free
   memory, peak memory;
4. C4D stage 1 (GA + CMA + CTS) seconds per iteration (median) at 24 and 90 frames, 512x288,
   ground-truth pointmaps and flow of an analytic box scene (`tests/synthetic_scenes.py`);
5. the DynPT training loader from the fresh shards (decode, clip, augment, track sampling) at the
   crop of section 2, clips/s with 0, 1, 2, 4 and 8 worker processes (--cpu: 0 and 1), against
   the bf16 step's clips/s of section 2, and the workers one GPU's step needs;
6. a real training run of a mid-sized config (the CNN-only model at a 256x256 crop, 16 frames,
   256 tracks, batch 4) on the fresh shards, data loading included; D-ACC and AJ on the val set
   before and after. It runs last and lasts --train-seconds (300; --cpu 8) or what the budget has
   left after the other sections, its own calibration and the final validation, if less (the
   number of steps is set from the calibration, so the OneCycle schedule completes).

Each section's seconds are printed as it ends; the table's last row is the total time against
--budget-s (480). A section that fails puts its one-line error in the table and the run goes on;
the exit status is then 1, as it is for a run over its budget. `--cpu` hides any GPU and shrinks
every size (CI runs it: tests/test_device_check.py).

Each section runs in a process of its own, in its own process group, under a time limit
(--section-limit-s: 150 s each, the training run 150 s beyond its --train-seconds; `KEY=S` sets
one section's). A section past its limit is killed with every process it started (loader and
datagen workers included), its row in the table reads "timed out after N s", and the check goes
on with the next section: a section that hangs costs its limit, never the GPU's whole lease.
This process itself never touches the GPU, so the sections are forked from it safely.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import signal
import sys
import tempfile
import time
from importlib.metadata import version
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: tests.synthetic_scenes

ROWS: list[tuple[str, str, str, str]] = []  # (check, setting, result, peak memory)
STEP_CLIPS_PER_S: dict[str, float] = {}  # section 2's training speed per precision, for section 5
SECTIONS = ("shards", "speed", "dust3r", "c4d", "loader", "run")  # --skip keys, in the run's order
BUDGET_MARGIN = 15.0  # seconds of the budget kept free (the run's start and checkpoint, rounding)
SECTION_LIMIT_S = 150.0  # a section's default time limit; the run's is this beyond --train-seconds
STOP_GRACE_S = 30.0  # seconds a section's process may take to exit after its last row
_TO_PARENT = None  # in a section's process: the pipe its rows and outcome go to


def log(message: str) -> None:
    print(f"[device_check] {message}", file=sys.stderr, flush=True)


def row(check: str, setting: str, result: str, memory: str = "-") -> None:
    """A row of the table (sent to the parent from a section's process, which prints the table)."""
    cells = (check, setting, result, memory)
    if _TO_PARENT is not None:
        _TO_PARENT.send(("row", cells))
    else:
        ROWS.append(cells)
    log(f"{check} | {setting} | {result} | {memory}")


def gib(nbytes: int | None) -> str:
    return "-" if nbytes is None else f"{nbytes / 2**30:.2f} GiB"


class Sizes:
    """Every size of the check: the real ones, or tiny ones for --cpu."""

    def __init__(self, cpu: bool, train_seconds: float | None):
        self.cpu = cpu
        self.scenes = (2, 1) if cpu else (48, 8)  # train, val
        self.resolution, self.frames = (64, 8) if cpu else (256, 24)
        self.workers = 1 if cpu else (os.cpu_count() or 1)  # datagen processes
        tiny = ["data.crop_size=[32,32]", "data.num_frames=6", "data.num_tracks=12"]
        self.speed_preset = "tiny-cpu" if cpu else "paper-gpu-cnn-only"
        self.speed = tiny if cpu else []  # the paper crop: the config's own sizes
        self.speed_steps = (1, 3) if cpu else (3, 10)  # warm-up, timed
        self.loader_workers, self.loader_clips = ((0, 1), 8) if cpu else ((0, 1, 2, 4, 8), 48)
        self.train_preset = "tiny-cpu" if cpu else "paper-gpu-cnn-only"
        self.train = tiny + ["data.num_workers=0", "eval.resolution=[64,64]", "eval.num_tracks=32"] if cpu else [
            "data.crop_size=[256,256]", "data.num_frames=16", "data.num_tracks=256",
            "train.batch_size=4", "train.total_batch=4", "data.num_workers=8",
            "eval.resolution=[256,256]", "eval.num_tracks=256"]
        self.train_seconds = train_seconds or (8.0 if cpu else 300.0)
        self.dust3r_hw = (48, 64) if cpu else (384, 512)
        self.c4d_hw, self.c4d_iters = ((24, 32), 3) if cpu else ((288, 512), 6)
        self.c4d_workers = 1 if cpu else (os.cpu_count() or 1)  # processes making C4D's inputs


# --- 1. shards ----------------------------------------------------------------------------------


def make_shards(out: Path, sizes: Sizes) -> tuple[Path, Path]:
    from c4d.cli import main

    start = time.perf_counter()
    dirs = []
    for split, count, seed in (("train", sizes.scenes[0], 0), ("val", sizes.scenes[1], 1)):
        folder = out / "shards" / split
        code = main(["datagen", "--num-scenes", str(count), "--out", str(folder), "--split", split,
                     "--seed", str(seed), "--resolution", str(sizes.resolution),
                     "--frames", str(sizes.frames), "--scenes-per-shard", "1",
                     "--workers", str(sizes.workers)])
        if code:
            raise RuntimeError(f"c4d datagen exited with {code}")
        dirs.append(folder)
    row("shards (c4d datagen)", f"{sizes.scenes[0]} train + {sizes.scenes[1]} val scenes, "
        f"{sizes.resolution}x{sizes.resolution}, {sizes.frames} frames",
        f"{time.perf_counter() - start:.1f} s")
    return dirs[0], dirs[1]


# --- 2. DynPT training speed --------------------------------------------------------------------


def _trainer(preset: str, overrides: list[str], train_dir: Path, out: Path, val_dir: Path | None = None):
    from c4d_core.config import load_config
    from dynpt.train import Trainer

    extra = [f"eval.source={val_dir}"] if val_dir else ["eval.every=0"]
    cfg = load_config("dynpt", preset, overrides=[f"data.sources=[{train_dir}]", f"train.out_dir={out}",
                                                  *overrides, *extra])
    return Trainer(cfg)


def training_speed(train_dir: Path, out: Path, sizes: Sizes) -> None:
    import itertools

    from dynpt.device import peak_memory, reset_peak_memory

    warm, timed = sizes.speed_steps
    for bf16 in (True, False):
        label = "bf16" if bf16 else "fp32"
        trainer = _trainer(sizes.speed_preset, [*sizes.speed, f"train.bf16={str(bf16).lower()}",
                                                f"train.steps={warm + timed + 3}", "train.total_batch=1",
                                                "train.batch_size=1"], train_dir, out / f"speed-{label}")
        try:
            d = trainer.cfg.data
            setting = (f"{sizes.speed_preset}, crop {d.crop_size[0]}x{d.crop_size[1]}, {d.num_frames} "
                       f"frames, {d.num_tracks} tracks, batch 1, {label}"
                       f"{'' if trainer.amp_dtype or not bf16 else ' (no autocast on this device)'}")
            batches = itertools.repeat(next(iter(trainer.loader)))
            for _ in range(warm):
                trainer.train_step(batches)
            _sync(trainer.device)
            reset_peak_memory(trainer.device)
            start = time.perf_counter()
            for _ in range(timed):
                trainer.train_step(batches)
            _sync(trainer.device)
            seconds = (time.perf_counter() - start) / timed
            STEP_CLIPS_PER_S[label] = 1 / seconds
            row("DynPT training speed", setting, f"{1 / seconds:.2f} clips/s ({seconds * 1e3:.0f} ms/step)",
                gib(peak_memory(trainer.device)))
        finally:
            trainer.close()


def _sync(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


# --- 5. the training loader ---------------------------------------------------------------------


def loader_speed(train_dir: Path, sizes: Sizes) -> None:
    """clips/s of `dynpt.data`'s loader (batch 1, as section 2) per worker count; the last row:
    the fewest worker processes that keep up with the bf16 step (at least one: with none, each
    clip is loaded between two steps instead of beside them), or the count extrapolated from the
    fastest per-worker rate when none of those measured does."""
    import math

    import torch

    from c4d_core.config import load_config
    from dynpt.data import ShardStream, make_loader

    data = load_config("dynpt", sizes.speed_preset, overrides=sizes.speed).data
    device = "cuda" if torch.cuda.is_available() else "cpu"
    step = STEP_CLIPS_PER_S.get("bf16")
    setting = (f"{sizes.speed_preset} data, crop {data.crop_size[0]}x{data.crop_size[1]}, "
               f"{data.num_frames} frames, {data.num_tracks} tracks, batch 1")
    rates = {}
    for workers in sizes.loader_workers:
        loader = make_loader(ShardStream([str(train_dir)], [1.0], data, seed=0), 1, workers, device)
        batches = iter(loader)
        next(batches)  # the workers' start
        start, clips = time.perf_counter(), 0
        while clips < sizes.loader_clips:
            clips += len(next(batches)["video"])
        rates[workers] = clips / (time.perf_counter() - start)
        del batches, loader
        versus = f", {rates[workers] / step:.1f}x the bf16 step's {step:.2f} clips/s" if step else ""
        row("DynPT loader", f"{setting}, {workers} workers", f"{rates[workers]:.1f} clips/s{versus}")
    if step:
        enough = [w for w, rate in rates.items() if w > 0 and rate >= step]
        per_worker = max(rate / w for w, rate in rates.items() if w > 0)
        need = min(enough) if enough else math.ceil(step / per_worker)
        how = "measured" if enough else f"extrapolated from {per_worker:.1f} clips/s per worker"
        row("DynPT loader workers per GPU", f"to feed {step:.2f} clips/s (bf16 step)", f"{need} ({how})")


# --- 6. a real training run ---------------------------------------------------------------------


def training_run(train_dir: Path, val_dir: Path, out: Path, sizes: Sizes, deadline: float) -> None:
    """The run trains for `sizes.train_seconds` or until `deadline` (a `time.perf_counter()` time)
    less the final validation (as long as the first) and `BUDGET_MARGIN`, whichever is sooner;
    at least 3 steps."""
    import math

    from dynpt.device import peak_memory, reset_peak_memory
    from dynpt.evaluate import evaluate_model

    # "before": the calibration trainer's fresh model, the run's first weights (same seed, same model)
    calib = _trainer(sizes.train_preset, [*sizes.train, "train.steps=100"], train_dir, out / "calibrate", val_dir)
    try:
        ev = calib.cfg.eval
        start = time.perf_counter()
        before = evaluate_model(calib.model, calib.val_scenes, ev, calib.device)["summary"]
        eval_seconds = time.perf_counter() - start
        batches = iter(calib.loader)
        calib.train_step(batches)  # warm-up (workers start, kernels are chosen)
        start = time.perf_counter()
        for _ in range(3):
            calib.train_step(batches)
        per_step = (time.perf_counter() - start) / 3
        del batches  # its loader workers stop before the run starts its own
    finally:
        calib.close()
    left = deadline - time.perf_counter() - eval_seconds - BUDGET_MARGIN
    seconds_wanted = min(sizes.train_seconds, left)
    steps = max(3, int(seconds_wanted / per_step))
    log(f"training run: {seconds_wanted:.0f} s wanted ({sizes.train_seconds:.0f} s asked, {left:.0f} s "
        f"left in the budget), {per_step:.2f} s per step -> {steps} steps")
    trainer = _trainer(sizes.train_preset, [*sizes.train, f"train.steps={steps}", f"eval.every={steps}",
                                            f"train.ckpt_every={steps}"], train_dir, out / "run", val_dir)
    try:
        reset_peak_memory(trainer.device)
        start = time.perf_counter()
        after = trainer.fit()
        seconds = time.perf_counter() - start
    finally:
        trainer.close()
    d, t = trainer.cfg.data, trainer.cfg.train
    setting = (f"{sizes.train_preset}, crop {d.crop_size[0]}x{d.crop_size[1]}, {d.num_frames} frames, "
               f"{d.num_tracks} tracks, batch {t.total_batch}, {steps} steps")
    row("DynPT training run", setting, f"{seconds:.0f} s ({steps * t.total_batch / seconds:.2f} clips/s "
        "incl. data and validation)", gib(peak_memory(trainer.device)))
    for key, name in (("d_acc", "D-ACC"), ("average_jaccard", "AJ")):
        b, a = before.get(key, math.nan), after.get(key, math.nan)
        row(f"DynPT {name} (val)", f"{len(trainer.val_scenes)} held-out scenes, before -> after training",
            f"{100 * b:.1f} -> {100 * a:.1f}")


# --- 3. DUSt3R pair forward ---------------------------------------------------------------------


def dust3r_forward(out: Path, sizes: Sizes) -> None:
    import numpy as np
    import torch

    from dynpt.dust3r.net import Dust3rConfig, Dust3rNet
    from c4d_pipeline.dust3r_pointmaps import Dust3rPointmaps
    from c4d_pipeline.pointmap_training import save_official
    from dynpt.device import peak_memory, reset_peak_memory

    torch.manual_seed(0)
    cfg = Dust3rConfig() if not sizes.cpu else Dust3rConfig(
        enc_embed_dim=32, enc_depth=2, enc_num_heads=2, dec_embed_dim=32, dec_depth=2, dec_num_heads=2,
        dpt_layer_dims=(8, 8, 16, 16), dpt_feature_dim=16, dpt_last_dim=8)
    h, w = sizes.dust3r_hw
    path = save_official(Dust3rNet(cfg), (h, w), out / "dust3r_random.pth")
    name = "ViT-L 512 DPT" if not sizes.cpu else "tiny DPT"
    frames = np.random.default_rng(0).integers(0, 256, (9, h, w, 3), dtype=np.uint8)
    edges = np.stack([np.arange(8), np.arange(1, 9)], axis=1)
    fp32 = Dust3rPointmaps.from_checkpoint(path)  # the default precision, as the official inference
    sources = [fp32] + ([Dust3rPointmaps(fp32.net, precision="bf16")] if fp32.device.type == "cuda" else [])
    for source in sources:
        for batch in (1, 0):
            source.batch_size = batch
            source.pointmaps(frames, edges[:1])  # warm-up
            _sync(source.device)
            reset_peak_memory(source.device)
            start = time.perf_counter()
            source.pointmaps(frames, edges)
            _sync(source.device)
            seconds = (time.perf_counter() - start) / len(edges)
            chosen = batch or source._auto_batch(h, w)
            dtype = str(source.amp_dtype).replace("torch.", "") if source.amp_dtype else "fp32"
            how = "" if batch else (f" (automatic: {chosen} from free memory, all {len(edges)} pairs "
                                    "at once)" if source.device.type == "cuda" else " (automatic)")
            row("DUSt3R pair forward", f"{name} ({path.name}, official layout), {w}x{h}, batch "
                f"{min(chosen, len(edges))}{how}, {dtype}", f"{seconds * 1e3:.0f} ms/pair",
                gib(peak_memory(source.device)))


# --- 4. C4D stage 1 -----------------------------------------------------------------------------

_SCENE = None  # the box scene of a C4D input worker (built once per worker, deterministic)


def _c4d_worker_init(frames: int, height: int, width: int) -> None:
    global _SCENE
    from tests.synthetic_scenes import make_box_scene

    _SCENE = make_box_scene(frames, height, width, num_tracks=256, seed=0)


def _c4d_inputs(edges):
    """Ground-truth pointmaps (pts_i, pts_j, conf_i, conf_j) and flow of `edges` (E,2) of the
    worker's scene: float32 (E,H,W,3) x 2, (E,H,W) x 2, (E,H,W,2)."""
    from c4d_pipeline.flow import build_flow
    from c4d_pipeline.ground_truth import GroundTruthPointmaps

    pw = GroundTruthPointmaps(_SCENE, static_bias=False).pointmaps(_SCENE.rgb, edges)
    flow = build_flow("gt", scene=_SCENE).flow(_SCENE.rgb, [tuple(map(int, e)) for e in edges])
    return pw.pts_i, pw.pts_j, pw.conf_i, pw.conf_j, flow


def c4d_stage1(sizes: Sizes) -> None:
    """Inputs from `sizes.c4d_workers` spawned processes (the ground truth of 850 edges at
    512x288 is minutes of one core; --cpu: this process), then `optimise` on the GPU."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    import numpy as np
    import torch

    from c4d_core.config import load_config
    from c4d_pipeline.optimize import optimise
    from c4d_pipeline.pointmaps import PairwisePointmaps
    from c4d_pipeline.scene_graph import graph_from_config
    from dynpt.device import peak_memory, reset_peak_memory

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    h, w = sizes.c4d_hw
    for frames in (24, 90):
        cfg = load_config("c4d", "default", overrides=[f"optim.stage1_iters={sizes.c4d_iters}",
                                                       "optim.stage2_iters=0", "weights.pts=0"])
        edges = graph_from_config(frames, cfg.graph)
        start = time.perf_counter()
        if sizes.c4d_workers == 1:
            _c4d_worker_init(frames, h, w)
            parts = [_c4d_inputs(edges)]
        else:
            with ProcessPoolExecutor(sizes.c4d_workers, mp_context=multiprocessing.get_context("spawn"),
                                     initializer=_c4d_worker_init, initargs=(frames, h, w)) as pool:
                parts = list(pool.map(_c4d_inputs, np.array_split(edges, sizes.c4d_workers)))
        pts_i, pts_j, conf_i, conf_j, flows = (np.concatenate(a) for a in zip(*parts))
        pw = PairwisePointmaps(edges=edges, pts_i=pts_i, pts_j=pts_j, conf_i=conf_i, conf_j=conf_j)
        inputs_s = time.perf_counter() - start
        reset_peak_memory(device)
        result = optimise(pw, frames, cfg, flows=flows, device=str(device))
        per_iter = float(np.median(result.history["losses"]["stage1"]["seconds"]))
        row("C4D stage 1 (GA+CMA+CTS)", f"{frames} frames, {w}x{h}, {len(edges)} edges, {device.type}, "
            f"median of {sizes.c4d_iters} iterations (inputs {inputs_s:.0f} s)",
            f"{per_iter * 1e3:.0f} ms/iter ({300 * per_iter:.0f} s for 300, extrapolated)",
            gib(peak_memory(device)))
        del pw, flows, result, parts


# --- each section in a process of its own, under a time limit ---------------------------------


def _section_process(section, to_parent) -> None:
    """The body of a section's process: run `section`, stream its rows and send its outcome
    ("done", its result, section 2's clips/s, the GPU's name) or ("failed", the one-line error)."""
    global _TO_PARENT
    os.setpgrp()  # a group of its own, before it starts any process: the parent kills the group
    _TO_PARENT = to_parent
    import torch

    torch.manual_seed(0)
    try:
        result = section()
    except Exception as exc:  # noqa: BLE001 -- one line in the table, then the next section
        message = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else ""
        to_parent.send(("failed", f"{type(exc).__name__}: {message}"))
        return
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none"
    to_parent.send(("done", result, dict(STEP_CLIPS_PER_S), gpu))


def _kill_group(pgid: int) -> None:
    """SIGKILL to process group `pgid` (a section's process and all it started), if any is left."""
    try:
        os.killpg(pgid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def run_section(section, limit_s: float) -> tuple:
    """Run `section` (no arguments) in a forked process of its own process group for at most
    `limit_s` seconds; its rows reach `ROWS` as they come. Returns ("done", result, clips/s, GPU),
    ("failed", message) or ("timed out",). Whatever the outcome, no process of the section is
    left when this returns: at the limit (or on Ctrl-C here) the whole group is killed."""
    context = multiprocessing.get_context("fork")  # this process holds no thread, no GPU context
    receive, send = context.Pipe(duplex=False)
    child = context.Process(target=_section_process, args=(section, send))
    child.start()
    send.close()  # the child's end: EOF here once the child is gone
    end = time.monotonic() + limit_s
    outcome: tuple = ("timed out",)
    try:
        while receive.poll(max(0.0, end - time.monotonic())):
            try:
                message = receive.recv()
            except EOFError:
                outcome = ("failed", f"the section's process died (exit status {child.exitcode})")
                break
            if message[0] != "row":
                outcome = message
                break
            ROWS.append(message[1])
        if outcome[0] != "timed out":
            child.join(STOP_GRACE_S)  # its own exit (a loader's workers stop, CUDA is released)
    finally:
        _kill_group(child.pid)  # the section's stragglers, or all of it past its limit
        child.kill()  # in case it was stopped before it had its own group
        child.join()
        receive.close()
    return outcome


def parse_limit(text: str) -> tuple[str | None, float]:
    """`--section-limit-s` values: `S` (every section) or `KEY=S` (one section)."""
    key, _, seconds = text.rpartition("=")
    if key and key not in SECTIONS:
        raise argparse.ArgumentTypeError(f"{key}: no such section; choose from {','.join(SECTIONS)}")
    try:
        value = float(seconds)
    except ValueError:
        value = -1.0
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: give positive seconds, S or KEY=S")
    return key or None, value


# --- main ---------------------------------------------------------------------------------------


def table() -> str:
    lines = ["| check | setting | result | peak memory |", "|---|---|---|---|"]
    lines += [f"| {' | '.join(cell.replace('|', '/') for cell in r)} |" for r in ROWS]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cpu", action="store_true", help="hide the GPU; tiny sizes (about a minute)")
    parser.add_argument("--out", type=Path, help="working folder (default: a temporary one, removed)")
    parser.add_argument("--train-seconds", type=float, help="length of the training run (300; --cpu 8); "
                        "less if the budget has less left")
    parser.add_argument("--budget-s", type=float, default=480.0,
                        help="seconds the whole check may take [480]; over it, the exit status is 1")
    parser.add_argument("--skip", type=lambda text: [k for k in text.split(",") if k], default=[],
                        metavar="KEYS", help=f"sections left out, comma-separated: {','.join(SECTIONS)} "
                        "(the DynPT sections need the shards)")
    parser.add_argument("--section-limit-s", type=parse_limit, action="append", default=[],
                        metavar="[KEY=]S", help=f"time limit of every section (S) or of one (KEY=S), "
                        f"repeatable [{SECTION_LIMIT_S:.0f}; the run: that beyond --train-seconds]; a "
                        "section past it is killed with its processes and reported as timed out")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.skip) - set(SECTIONS))
    if unknown:
        parser.error(f"--skip {','.join(unknown)}: no such section; choose from {','.join(SECTIONS)}")
    if args.budget_s <= 0:
        parser.error(f"--budget-s must be positive, got {args.budget_s:g}")
    if args.cpu:
        os.environ["CUDA_VISIBLE_DEVICES"] = ""  # before torch is imported (in the sections)
    sizes = Sizes(args.cpu, args.train_seconds)
    every = dict(args.section_limit_s).get(None, SECTION_LIMIT_S)
    limits = {key: every for key in SECTIONS} | {"run": every + sizes.train_seconds}
    limits |= {key: seconds for key, seconds in args.section_limit_s if key is not None}
    gpu = "unknown (no section finished)"
    with tempfile.TemporaryDirectory(prefix="device-check-") as tmp:
        out = args.out or Path(tmp)
        start, failed = time.perf_counter(), 0
        deadline = start + args.budget_s
        shards = None
        sections = [("shards (c4d datagen)", lambda: make_shards(out, sizes)),
                    ("DynPT training speed", lambda: training_speed(shards[0], out, sizes)),
                    ("DUSt3R pair forward", lambda: dust3r_forward(out, sizes)),
                    ("C4D stage 1 (GA+CMA+CTS)", lambda: c4d_stage1(sizes)),
                    ("DynPT loader", lambda: loader_speed(shards[0], sizes)),
                    ("DynPT training run", lambda: training_run(*shards, out, sizes, deadline))]
        sections = [(key, name, section) for key, (name, section) in zip(SECTIONS, sections)
                    if key not in args.skip]
        seconds = []
        for key, name, section in sections:
            section_start = time.perf_counter()
            if name.startswith("DynPT") and shards is None:
                failed += 1
                row(name, "SKIPPED", "no shards")
                continue
            outcome = run_section(section, limits[key])
            if outcome[0] == "done":
                result, step_rates, gpu = outcome[1:]
                shards = result if result is not None else shards
                STEP_CLIPS_PER_S.update(step_rates)
            elif outcome[0] == "failed":
                failed += 1
                row(name, "FAILED", outcome[1])
            else:
                failed += 1
                row(name, "TIMED OUT", f"timed out after {limits[key]:.0f} s (--section-limit-s); "
                    "its processes were killed")
            seconds.append(f"{name} {time.perf_counter() - section_start:.0f} s")
            log(f"section {seconds[-1]}")
        total = time.perf_counter() - start
    over = total > args.budget_s
    row("total", ", ".join(seconds), f"{total:.0f} s of the {args.budget_s:.0f} s budget"
        f"{' (OVER BUDGET)' if over else ''}")
    print(f"device_check: torch {version('torch')}, GPU {gpu}, {'--cpu, ' if args.cpu else ''}"
          f"{total:.0f} s in all (budget {args.budget_s:.0f} s{', exceeded' if over else ''}), "
          f"{failed} section(s) failed\n")
    print(table())
    return 1 if failed or over else 0


if __name__ == "__main__":
    sys.exit(main())
