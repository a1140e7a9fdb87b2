"""Training DynPT on datagen shards: AdamW + OneCycle, gradient accumulation, bf16, DDP, resume.

One optimiser step uses `train.total_batch` clips: `train.batch_size` per process and forward
pass, accumulated over `total_batch / (batch_size * world_size)` micro-batches. Run on one
process (`c4d train ...`) or many (`torchrun ... -m dynpt.cli_train ...`, see docs/TRAINING.md).

Files in `train.out_dir`: `config.yaml`, `checkpoints/step_XXXXXXXX.pt` (the last
`keep_last`), `checkpoints/last.pt` (the newest of them), `checkpoints/best.pt` (best validation
`eval.best_metric`, only with `eval.source`), `log.jsonl` (one line
per step: losses, learning rate), `tb/` (TensorBoard). A checkpoint holds the model, optimiser,
scheduler, step, RNG states and the data-stream position, so `--resume` continues the same run.
`--resume` starts from the newest readable step checkpoint, else from a readable `last.pt` (a
damaged one is renamed to `*.pt.bad` with a warning, so pruning never keeps it instead of a good
one), drops log lines past its step (and a torn last line), and rebuilds the OneCycle annealing
to end at a changed `train.steps` (docs/TRAINING.md). Every run first deletes the temporary
files a killed checkpoint write left in `checkpoints/`.
"""

from __future__ import annotations

import gc
import hashlib
import json
import logging
import math
import os
import random
import re
import shutil
import sys
import threading
import time
import traceback
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from omegaconf import OmegaConf
from torch.nn.parallel import DistributedDataParallel

from c4d_core.config import to_dict
from c4d_core.errors import UserError
from c4d_core.files import DISK_ERRNOS, append_line, disk_error, write_text
from dynpt.checkpoint import CheckpointUnreadable, load_checkpoint, save_checkpoint
from dynpt.data import ShardStream, StreamPosition, make_loader, merge_positions
from dynpt.device import (apply_cudnn_flags, autocast, bf16_supported, cudnn_flags, ddp_backend,
                          ddp_device_ids, peak_memory, reset_peak_memory, training_autocast_dtype, training_device)
from dynpt.evaluate import evaluate_model, load_eval_scenes, track_image
from dynpt.losses import LossWeights, dynpt_loss
from dynpt.model import build_model

log = logging.getLogger(__name__)

DEBUG_DUMP_ENV = "DYNPT_DEBUG_DUMP"  # a folder: per-step weight digests of every rank (debugging)


# --- process set-up -----------------------------------------------------------------------------


def init_distributed() -> tuple[int, int, torch.device]:
    """(rank, world_size, device) from torchrun's environment; a single process without it."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    device = training_device(torch.cuda.is_available(), local_rank)
    if device.type == "cuda":
        torch.cuda.set_device(device)
        apply_cudnn_flags(cudnn_flags(device.type))
    if world_size > 1 and not dist.is_initialized():
        dist.init_process_group(backend=ddp_backend(device.type))
    return (dist.get_rank() if world_size > 1 else 0), world_size, device


def accumulation_steps(total_batch: int, batch_size: int, world_size: int) -> int:
    """Micro-batches per optimiser step so that batch_size * world_size * steps == total_batch."""
    per_pass = batch_size * world_size
    if total_batch % per_pass:
        raise UserError(
            f"train.total_batch={total_batch} is not a multiple of train.batch_size={batch_size} "
            f"x {world_size} processes; choose total_batch as a multiple of {per_pass}"
        )
    return total_batch // per_pass


RANK_WAIT_S = 60.0  # s; how long a rank > 0 waits for rank 0's report of a schedule mistake


def check_schedule(tc, world_size: int) -> int:
    """Accumulation steps of the `train` section on `world_size` processes, or a UserError.

    Under torchrun every process finds the same mistake: only rank 0 says it (one line). The
    others wait for torchrun to stop them once rank 0 has exited (it stops every process at the
    first failure; a rank that exited first could have had rank 0 stopped before it spoke), and
    exit with the same status and no message if that does not come within `RANK_WAIT_S`.
    """
    try:
        return accumulation_steps(tc.total_batch, tc.batch_size, world_size)
    except UserError:
        if int(os.environ.get("RANK", "0")) > 0:
            time.sleep(RANK_WAIT_S)
            raise SystemExit(2) from None
        raise


def rng_state() -> dict:
    """Python, numpy, torch (and CUDA) RNG states in types `torch.load(weights_only=True)` reads."""
    kind, key, pos, has_gauss, gauss = np.random.get_state()
    state = {"python": random.getstate(), "torch": torch.get_rng_state(),
             "numpy": [kind, torch.from_numpy(key.astype(np.int64)), pos, has_gauss, gauss]}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    random.setstate(state["python"])
    kind, key, pos, has_gauss, gauss = state["numpy"]
    np.random.set_state((kind, key.numpy().astype(np.uint32), pos, has_gauss, gauss))
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


# --- checkpoints --------------------------------------------------------------------------------


def checkpoint_dir(out_dir: str | Path) -> Path:
    return Path(out_dir) / "checkpoints"


def latest_checkpoint(out_dir: str | Path) -> Path | None:
    """The step checkpoint with the highest step in `out_dir`, or None."""
    found = sorted(checkpoint_dir(out_dir).glob("step_*.pt"))
    return found[-1] if found else None


def load_latest_checkpoint(out_dir: str | Path, model_cfg, set_aside: bool = True
                           ) -> tuple[Path, dict]:
    """(path, checkpoint) of the newest readable step checkpoint, else of a readable `last.pt`.

    An unreadable one (cut by a crash or a full disk) is skipped with a warning and, with
    `set_aside`, renamed to `*.pt.bad`, so that pruning never keeps it in place of the good ones
    (it would sort as the newest). `UserError` if none is readable.
    """
    folder = checkpoint_dir(out_dir)
    found = sorted(folder.glob("step_*.pt"), reverse=True)
    found += [folder / "last.pt"] if (folder / "last.pt").is_file() else []
    if not found:
        raise UserError(f"--resume: no checkpoint in {folder}; start without --resume, or set "
                        "train.out_dir to the run to continue")
    for path in found:
        try:
            return path, load_checkpoint(path, model_cfg)
        except CheckpointUnreadable as exc:
            if not set_aside:
                continue
            bad = path.with_name(path.name + ".bad")
            try:
                os.replace(path, bad)
            except OSError as err:
                raise disk_error(bad, err) from err
            log.warning("warning: skipping %s (renamed to %s): %s", path.name, bad.name, exc)
    raise UserError(f"--resume: no readable checkpoint in {folder} (see the warnings above); run "
                    "again without --resume to start over, or in another train.out_dir")


def remove_temporaries(folder: Path) -> None:
    """Delete the temporary files that a killed writer left in `folder` (`.NAME.tmp<pid>.EXT` of
    `c4d_core.files.atomic_path`, `.last.pt.tmp` of `alias_last`), with a log line each."""
    for path in sorted(folder.glob(".*.tmp*")):
        if path.is_file() and re.fullmatch(r"\..+\.tmp\d*(\.\w+)?", path.name):
            log.warning("warning: removing %s, left by an interrupted write", path)
            path.unlink(missing_ok=True)


def repair_log(log_path: Path, step: int) -> None:
    """Drop the lines of the JSON-lines log `log_path` after `step` (written after the last
    checkpoint, before a crash) and a torn last line (a crash or a full disk inside the append);
    rewritten atomically. A broken line elsewhere is a `UserError` (the file was edited)."""
    if not log_path.exists():
        return
    text = log_path.read_text(errors="replace")
    lines, kept = text.splitlines(), []
    for number, line in enumerate(lines, 1):
        try:
            record = json.loads(line)
        except ValueError:
            if number < len(lines):
                raise UserError(f"{log_path} line {number} is not JSON (edited by hand?); "
                                "fix or delete that line, then resume") from None
            log.warning("warning: dropping the torn last line of %s", log_path)
            continue
        if record["step"] <= step:
            kept.append(line)
    if len(kept) != len(lines) or (text and not text.endswith("\n")):
        write_text(log_path, "".join(line + "\n" for line in kept))


def rebuild_annealing(scheduler, total_steps: int) -> None:
    """Make a OneCycleLR end at `total_steps` instead of its stored total (a resume with another
    `train.steps`): the warm-up is kept, the annealing phase ends at the new last step."""
    scheduler.total_steps = total_steps
    scheduler._schedule_phases[-1]["end_step"] = float(total_steps - 1)
    scheduler.last_epoch -= 1
    scheduler.step()  # the optimiser's rate for the next step, now on the new schedule


def _quiet_disk_errors(args) -> None:
    """`threading.excepthook` while training: a disk error in TensorBoard's writer thread prints
    no traceback (the training thread meets it too and reports it as one line)."""
    if not (isinstance(args.exc_value, OSError) and args.exc_value.errno in DISK_ERRNOS):
        threading.__excepthook__(args)


def _quiet_stopped_workers(hook):
    """`sys.excepthook` while training and after Ctrl-C: multiprocessing's resource-sharer thread
    (it hands a batch's file descriptors to the training process) reports through it what it
    meets when a loader worker stops mid-handover (Ctrl-C, the end of the run): the connection
    reset or closed by that worker. Those print nothing; everything else goes to `hook`."""
    def excepthook(kind, value, tb):
        sharer = os.path.join("multiprocessing", "resource_sharer.py")
        if not (issubclass(kind, (ConnectionError, EOFError)) and any(
                frame.f_code.co_filename.endswith(sharer) for frame, _ in traceback.walk_tb(tb))):
            hook(kind, value, tb)
    return excepthook


def next_batch(batches):
    """`next(batches)`, with a loader worker's `UserError` as its own one-line message (the
    DataLoader wraps it in "Caught UserError in DataLoader worker ..." and the traceback)."""
    try:
        return next(batches)
    except UserError as exc:
        text = str(exc)
        if not text.startswith("Caught UserError"):
            raise
        last = text.rstrip().splitlines()[-1]
        raise UserError(last.split("UserError: ", 1)[-1]) from None


def prune_checkpoints(out_dir: str | Path, keep_last: int) -> None:
    """Delete all but the newest `keep_last` step checkpoints (best.pt is never touched)."""
    for old in sorted(checkpoint_dir(out_dir).glob("step_*.pt"))[:-keep_last]:
        old.unlink(missing_ok=True)


def alias_last(path: Path) -> Path:
    """Point `checkpoints/last.pt` at the step checkpoint `path` (a hard link, a copy where links
    are not supported), replacing the previous alias atomically; returns the alias."""
    last, tmp = path.with_name("last.pt"), path.with_name(".last.pt.tmp")
    tmp.unlink(missing_ok=True)
    try:
        os.link(path, tmp)
    except OSError:
        shutil.copyfile(path, tmp)
    os.replace(tmp, last)
    return last


# --- parameter groups ---------------------------------------------------------------------------

# parts of DynPT by parameter-name prefix, for `train.lr_scale` (the mobility head before the
# transformer: the first matching prefix wins)
PARTS = {"mobility": ("transformer.mobility_head.",), "transformer": ("transformer.",),
         "cnn": ("cnn.",), "correlation": ("corr.",), "fusion": ("vit_proj.", "fuse.")}


def param_groups(model: torch.nn.Module, lr: float, lr_scale) -> list[dict]:
    """AdamW groups, one per part of `PARTS` with trainable parameters: learning rate
    `lr * lr_scale[part]`; a scale of 0 freezes the part (requires_grad False, not optimised).
    The frozen 3D encoder is never trained."""
    unknown = sorted(set(lr_scale) - set(PARTS))
    if unknown:
        raise UserError(f"train.lr_scale: unknown part(s) {unknown}; parts are {', '.join(PARTS)}")
    groups: dict[str, list] = {part: [] for part in PARTS}
    for name, p in model.named_parameters():
        if not p.requires_grad:
            continue
        part = next((k for k, prefixes in PARTS.items() if name.startswith(prefixes)), None)
        if part is None:
            raise UserError(f"parameter {name} belongs to no part of train.lr_scale")
        if lr_scale[part] == 0:
            p.requires_grad_(False)
        else:
            groups[part].append(p)
    out = [{"name": k, "params": v, "lr": lr * lr_scale[k]} for k, v in groups.items() if v]
    if not out:
        raise UserError("train.lr_scale freezes every part; give at least one part a scale > 0")
    return out


# --- the loop -----------------------------------------------------------------------------------


class Trainer:
    """Holds the model, optimiser, data and logs of one training run (`cfg`: the whole config)."""

    def __init__(self, cfg, resume: bool = False):
        self.cfg = cfg
        tc = cfg.train
        self.accum = check_schedule(tc, int(os.environ.get("WORLD_SIZE", "1")))
        self.rank, self.world_size, self.device = init_distributed()
        self.main = self.rank == 0
        self.out_dir = Path(tc.out_dir)
        random.seed(cfg.seed + self.rank)
        np.random.seed(cfg.seed + self.rank)
        torch.manual_seed(cfg.seed + self.rank)

        self.model = build_model(cfg.model)
        if cfg.model.init_from and not resume:  # the weights of the run's start (resume: from its checkpoint)
            from dynpt.cotracker3_weights import load_into, parse_init

            load_into(self.model, parse_init(cfg.model.init_from))
        self.model.to(self.device)
        self.amp_dtype = training_autocast_dtype(self.device.type, tc.bf16,
                                                 bf16_supported(self.device))
        groups = param_groups(self.model, tc.lr, tc.lr_scale)
        self.optimizer = torch.optim.AdamW(groups, lr=tc.lr, weight_decay=tc.weight_decay,
                                           eps=tc.adam_eps)
        self.scheduler = torch.optim.lr_scheduler.OneCycleLR(
            # warm-up of at least 2 steps: OneCycleLR divides by zero on a shorter phase (and
            # the schema's train.steps >= 3 leaves an annealing phase)
            self.optimizer, max_lr=[g["lr"] for g in groups], total_steps=tc.steps,
            pct_start=max(tc.pct_start, 2.0 / tc.steps),
            anneal_strategy="cos", cycle_momentum=False, div_factor=tc.div_factor,
            final_div_factor=tc.final_div_factor)
        self.loss_weights = LossWeights.from_config(cfg.loss)
        self.step, self.best = 0, None
        self.data_counts: dict[int, tuple[int, int]] = {}  # loader split -> (read, bad)
        start_positions: dict = {}
        if self.main:
            remove_temporaries(checkpoint_dir(self.out_dir))
        if resume:
            start_positions = self._resume()
        elif latest_checkpoint(self.out_dir) is not None:
            raise UserError(f"{self.out_dir} already holds checkpoints; add --resume to continue "
                            "that run, or set train.out_dir=... to a new folder")
        elif self.main:
            repair_log(self.out_dir / "log.jsonl", 0)  # lines of a run that crashed before its first checkpoint
        self.ddp = (DistributedDataParallel(self.model, device_ids=ddp_device_ids(self.device))
                    if self.world_size > 1 else self.model)
        sources = list(cfg.data.sources)
        weights = list(cfg.data.weights) or [1.0] * len(sources)
        stream = ShardStream(sources, weights, cfg.data, cfg.seed,
                             self.rank, self.world_size, start_positions)
        self.loader = make_loader(stream, tc.batch_size, cfg.data.num_workers, self.device.type)
        self.position = StreamPosition()
        self.val_scenes = (load_eval_scenes(cfg.eval.source, cfg.eval)
                           if self.main and cfg.eval.source else [])
        self.writer = None
        if self.main:
            from torch.utils.tensorboard import SummaryWriter

            write_text(self.out_dir / "config.yaml", OmegaConf.to_yaml(cfg))
            try:
                self.writer = SummaryWriter(str(self.out_dir / "tb"), purge_step=self.step + 1)
            except OSError as exc:
                raise disk_error(self.out_dir / "tb", exc) from exc

    # -- resume --

    def _resume(self) -> dict:
        # rank 0 first: it sets unreadable checkpoints aside, the others then find the same one
        if self.world_size > 1 and not self.main:
            dist.barrier()
        try:
            path, ckpt = load_latest_checkpoint(self.out_dir, self.cfg.model, set_aside=self.main)
        finally:
            if self.world_size > 1 and self.main:
                dist.barrier()
        extra = ckpt["extra"]
        self.model.load_state_dict(ckpt["model"])
        self.optimizer.load_state_dict(extra["optimizer"])
        self.scheduler.load_state_dict(extra["scheduler"])
        if self.scheduler.total_steps != self.cfg.train.steps:
            if self.cfg.train.steps <= int(ckpt["step"]):
                raise UserError(f"--resume: the run is at step {ckpt['step']}, so train.steps="
                                f"{self.cfg.train.steps} has nothing left to do; set it higher")
            log.info("train.steps changed from %d to %d: the learning-rate annealing now ends at "
                     "step %d", self.scheduler.total_steps, self.cfg.train.steps,
                     self.cfg.train.steps)
            rebuild_annealing(self.scheduler, self.cfg.train.steps)
        self.step, self.best = int(ckpt["step"]), extra.get("best")
        set_rng_state(extra["rng"][min(self.rank, len(extra["rng"]) - 1)])
        log.info("resumed %s at step %d", path, self.step)
        if self.main:
            repair_log(self.out_dir / "log.jsonl", self.step)
        num_splits = self.world_size * max(self.cfg.data.num_workers, 1)
        return merge_positions(extra["data"], num_splits)

    # -- checkpoints --

    def _gather(self, value):
        if self.world_size == 1:
            return [value]
        out = [None] * self.world_size
        dist.all_gather_object(out, value)
        return out

    def save(self, metrics: dict | None = None) -> None:
        """Write step_XXXXXXXX.pt (all ranks' RNG and data positions), prune, update best.pt."""
        rngs, positions = self._gather(rng_state()), self._gather(self.position.state_dict())
        if not self.main:
            return
        extra = {"optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(),
                 "rng": rngs, "data": positions, "best": self.best, "metrics": metrics or {},
                 "train_config": to_dict(self.cfg)}
        path = checkpoint_dir(self.out_dir) / f"step_{self.step:08d}.pt"
        path.parent.mkdir(parents=True, exist_ok=True)
        save_checkpoint(path, self.model, self.step, extra=extra)
        alias_last(path)
        prune_checkpoints(self.out_dir, self.cfg.train.keep_last)

    # -- one step --

    def _autocast(self):
        return autocast(self.device.type, self.amp_dtype)

    def train_step(self, batches) -> dict[str, float]:
        """One optimiser step over `accum` micro-batches; returns the mean weighted loss terms."""
        self.ddp.train()
        totals: dict[str, float] = {}
        scenes: list[str] = []
        for i in range(self.accum):
            batch = next_batch(batches)
            self.position.update(batch["position"])
            for split, counts in zip(batch["position"][:, 0].tolist(), batch["counts"].tolist()):
                self.data_counts[split] = tuple(counts)
            scenes += batch.get("key", [])
            video = batch["video"].to(self.device, non_blocking=True).permute(0, 1, 4, 2, 3).float()
            queries = batch["queries"].to(self.device)  # (B,N,3)
            target = {
                "tracks": batch["tracks"].to(self.device),  # (B,T,N,2)
                "visible": batch["visible"].to(self.device),  # (B,T,N)
                "moving": batch["moving"].to(self.device),  # (B,T,N)
            }
            sync = self.world_size == 1 or i == self.accum - 1
            with (nullcontext() if sync else self.ddp.no_sync()), self._autocast():
                output = self.ddp(video, queries)
                loss, terms = dynpt_loss(output, target, self.loss_weights)
            (loss / self.accum).backward()
            for key, value in {"total": loss, **terms}.items():
                totals[key] = totals.get(key, 0.0) + float(value.detach()) / self.accum
        grad_norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg.train.grad_clip)
        totals["lr"] = self.optimizer.param_groups[0]["lr"]  # the rate this step used
        self.optimizer.step()
        self.scheduler.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.step += 1
        totals["grad_norm"] = float(grad_norm)
        if DEBUG_DUMP_ENV in os.environ:
            self._debug_dump(Path(os.environ[DEBUG_DUMP_ENV]), scenes)
        return totals

    def _debug_dump(self, folder: Path, scenes: list[str]) -> None:
        """Append {step, weights (SHA-256 of every tensor's bytes), scenes read} to
        folder/rank_R.jsonl: `DYNPT_DEBUG_DUMP=DIR` lets tests/test_ddp.py compare the ranks."""
        digest = hashlib.sha256()
        for tensor in self.model.state_dict().values():
            digest.update(tensor.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy())
        folder.mkdir(parents=True, exist_ok=True)
        with open(folder / f"rank_{self.rank}.jsonl", "a") as f:
            f.write(json.dumps({"step": self.step, "weights": digest.hexdigest(),
                                "scenes": scenes}) + "\n")

    # -- validation --

    def validate(self) -> dict:
        if not self.val_scenes:
            return {}
        result = evaluate_model(self.model, self.val_scenes, self.cfg.eval, self.device)
        summary = result["summary"]
        for key, value in summary.items():
            if isinstance(value, float) and math.isfinite(value):
                self.writer.add_scalar(f"val/{key}", value, self.step)
        self.writer.add_image("val/tracks", track_image(result["example"]), self.step,
                              dataformats="HWC")
        return summary

    def _is_best(self, summary: dict) -> bool:
        value = summary.get(self.cfg.eval.best_metric)
        if value is None or not math.isfinite(value):
            return False
        if self.best is None or value > self.best:
            self.best = value
            return True
        return False

    # -- run --

    def fit(self) -> dict:
        """Train to `train.steps` (or `train.stop_after` more steps); returns the last summary."""
        tc = self.cfg.train
        stop = tc.steps if tc.stop_after <= 0 else min(tc.steps, self.step + tc.stop_after)
        batches = iter(self.loader)
        log_path = self.out_dir / "log.jsonl"
        summary: dict = {}
        window_start, window_clips = time.perf_counter(), 0
        reset_peak_memory(self.device)
        if self.main:
            log.info("training on %d process(es) x %d thread(s), %s", self.world_size,
                     torch.get_num_threads(), self.device)
        while self.step < stop:
            terms = self.train_step(batches)
            window_clips += tc.total_batch
            lr = terms.pop("lr")
            if self.main:
                append_line(log_path, json.dumps({"step": self.step, "lr": lr, **terms}))
            if self.main and (self.step % tc.log_every == 0 or self.step == stop):
                elapsed = time.perf_counter() - window_start
                for key, value in terms.items():
                    self.writer.add_scalar(f"loss/{key}" if key != "grad_norm" else "train/grad_norm",
                                           value, self.step)
                self.writer.add_scalar("train/lr", lr, self.step)
                self.writer.add_scalar("train/clips_per_s", window_clips / elapsed, self.step)
                if (peak := peak_memory(self.device)) is not None:
                    self.writer.add_scalar("train/gpu_mem_gib", peak / 2**30, self.step)
                log.info("step %d/%d  loss %.4f  lr %.2e  %.2f clips/s", self.step, tc.steps,
                         terms["total"], lr, window_clips / elapsed)
                window_start, window_clips = time.perf_counter(), 0
            is_last = self.step == stop
            if self.main and self.cfg.eval.every > 0 and (
                    self.step % self.cfg.eval.every == 0 or self.step == tc.steps):
                summary = self.validate()
                if summary:
                    log.info("step %d validation: %s", self.step, json.dumps(
                        {k: round(v, 4) for k, v in summary.items() if isinstance(v, float)}))
                if self._is_best(summary):
                    save_checkpoint(checkpoint_dir(self.out_dir) / "best.pt", self.model, self.step,
                                    extra={"metrics": summary, "train_config": to_dict(self.cfg)})
            if self.step % tc.ckpt_every == 0 or is_last:
                self.save(summary)
        if self.writer is not None:
            self.writer.flush()
        if self.world_size > 1:  # rank 0 may still validate or write the last checkpoint: no
            dist.barrier()       # rank leaves (and tears its half of the group down) before it
        read, bad = (sum(c[i] for c in self.data_counts.values()) for i in (0, 1))
        if bad:
            log.warning("warning: skipped %d bad training samples of %d read (see the warnings "
                        "above; `c4d inspect SOURCE --check` lists them)", bad, read)
        return summary

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        if self.world_size > 1 and dist.is_initialized():
            # DDP's reducer holds the gloo group and its last work items: release them while the
            # interpreter is whole, or the group's threads are torn down at interpreter exit
            # (gloo aborts there: 'terminate called without an active exception')
            self.ddp = self.model
            gc.collect()
            dist.destroy_process_group()


def train(cfg, resume: bool = False) -> dict:
    """Run (or resume) the training described by `cfg`; returns the last validation summary."""
    if not cfg.data.sources:
        raise UserError("no training data: set data.sources=[DIR_OR_GLOB,...] (and data.weights) "
                        "to shard sets made with `c4d datagen`")
    trainer = Trainer(cfg, resume=resume)
    hook, threading.excepthook = threading.excepthook, _quiet_disk_errors
    sys_hook, sys.excepthook = sys.excepthook, _quiet_stopped_workers(sys.excepthook)
    interrupted = False
    try:
        try:
            return trainer.fit()
        finally:
            trainer.close()
    except KeyboardInterrupt:  # Ctrl-C: every file is whole (atomic writes); say how to go on
        interrupted = True
        if trainer.main:
            saved = latest_checkpoint(trainer.out_dir)
            log.warning("interrupted at step %d; %s", trainer.step,
                        f"`c4d train --resume train.out_dir={trainer.out_dir}` continues from "
                        f"{saved.name}" if saved else "no checkpoint yet: the same command starts over")
        raise
    except OSError as exc:  # TensorBoard's event file on a full disk (its own thread writes it)
        if exc.errno not in DISK_ERRNOS:
            raise
        raise disk_error(exc.filename or trainer.out_dir / "tb", exc) from exc
    finally:
        threading.excepthook = hook
        if not interrupted:  # after Ctrl-C the process ends, and stopped workers may still be met
            sys.excepthook = sys_hook
