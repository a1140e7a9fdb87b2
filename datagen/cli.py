"""`c4d datagen`: generate scenes of a preset into webdataset shards, in parallel and resumably.

    c4d datagen --preset movi-e --num-scenes 1000 --out data/movi-e --workers 8

Scene i of seed S is the same whatever the worker count, task split or number of reruns. Each
shard is written under a temporary name and renamed when complete, so rerunning the same command
after a crash (or with more tasks of a job array) only generates the missing shards. The dataset's
identity (config, counts, generator version) is kept in `OUT/dataset-{split}.json`, the resolved
config also in `OUT/config-{split}.yaml`; a rerun into the same directory with a different
config is refused once a shard of the first is complete (before that the folder holds no data of
it and the new settings replace the old), also where the dataset file was deleted: each scene's
meta carries its seed and config digest. Every value is range-checked when the config loads,
before anything is created.
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing
import os
import signal
import threading
import time
from collections import deque
from contextlib import contextmanager
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from itertools import islice
from pathlib import Path
from typing import Any, Iterator

from tqdm import tqdm

import datagen
from c4d_core.config import available_presets, flag_overrides, load_config, to_dict, to_yaml
from c4d_core.errors import UserError
from c4d_core.files import make_folder, write_json, write_text
from c4d_core.ownership import output_folder
from c4d_core.schema import RULES
from c4d_core.system import (available_memory, configure_threads, gib, init_worker_threads,
                              require_egl)
from datagen.codecs import FORMAT_VERSION
from datagen.jobs import SHARD_PATTERN, ShardPlan, config_digest, resolve_task
from datagen.shards import (DATASET_FILE, KEY_PATTERN, ShardWriter, encode_scene, first_scene_meta,
                            scene_key)

log = logging.getLogger(__name__)

DATASET_FORMAT = "c4d-datagen-shards"


def usable_cpus() -> int:
    """CPU cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    presets = ", ".join(available_presets("datagen")) or "none yet"
    add = parser.add_argument
    add("--preset", default="movi-e", help=f"scene recipe ({presets}) or a YAML path")
    add("--num-scenes", type=int, required=True, metavar="N",
        help="scenes in the dataset (all tasks)")
    add("--out", type=Path, required=True, metavar="DIR", help="output directory of the shards")
    add("--seed", type=int, metavar="S", help="dataset seed (config key `seed`)")
    add("--workers", type=int, default=usable_cpus(), metavar="K",
        help="worker processes (default: all usable CPU cores)")
    add("--resolution", metavar="R", help="frame size: `256` (square) or `HxW` such as 384x512")
    add("--frames", type=int, metavar="T", help="frames per video (config key `frames`)")
    add("--scenes-per-shard", type=int, default=32, metavar="M",
        help="scenes per .tar shard (default: 32)")
    add("--split", choices=("train", "val", "test"), help="asset split and file prefix")
    add("--assets", metavar="DIR",
        help="folder of textured OBJ/GLB/GLTF meshes (config key `assets_dir`)")
    add("--config", action="append", default=[], metavar="FILE",
        help="YAML file merged over the preset (repeatable)")
    add("--task-index", type=int, metavar="I", help="this task's index in a job array (from 0)")
    add("--num-tasks", type=int, metavar="K",
        help="tasks in the job array; default from SLURM_ARRAY_TASK_ID/COUNT or RANK/WORLD_SIZE")
    add("overrides", nargs="*", metavar="key=value", help="config overrides")


def parse_resolution(text: str) -> list[int]:
    """`256` -> [256, 256]; `384x512` -> [384, 512] (height x width); the range is the schema's."""
    parts = text.lower().split("x")
    try:
        size = [int(p) for p in parts]
    except ValueError:
        size = []
    if len(parts) == 1:
        size = size * 2
    rule = RULES["datagen"]["resolution"]
    if len(size) != 2 or not rule.accepts(size):
        raise UserError(f"--resolution {text!r} must be `S` or `HxW` (e.g. 384x512), each side an "
                        f"integer in [{rule.low:.0f}, {rule.high:.0f}]")
    return size


def datagen_flag_overrides(args: argparse.Namespace) -> list[str]:
    """The `key=value` overrides the named flags stand for; a key set twice is an error."""
    return flag_overrides({
        "seed": args.seed,
        "frames": args.frames,
        "resolution": parse_resolution(args.resolution) if args.resolution else None,
        "split": args.split,
        "assets_dir": args.assets,
    }, args.overrides)


def dataset_record(cfg, plan: ShardPlan, preset: str) -> dict[str, Any]:
    """What identifies the dataset in OUT: reruns and other tasks must agree on all of it."""
    return {
        "format": DATASET_FORMAT,
        "format_version": FORMAT_VERSION,
        "generator_version": datagen.__version__,
        "preset": preset,
        "split": plan.split,
        "seed": int(cfg.seed),
        "num_scenes": plan.num_scenes,
        "scenes_per_shard": plan.scenes_per_shard,
        "num_shards": plan.num_shards,
        "shard_pattern": SHARD_PATTERN,
        "scene_key_pattern": KEY_PATTERN,
        "config": to_dict(cfg),
    }


def claim_directory(out: Path, record: dict[str, Any], plan: ShardPlan) -> None:
    """Create OUT and its dataset file (and the resolved config as YAML), or check that the
    existing one describes this dataset.

    A dataset file of other settings is only replaced while OUT holds no complete shard of it
    (a run that failed before its first shard claimed nothing); otherwise it is refused.
    """
    make_folder(out)
    path = out / DATASET_FILE.format(split=record["split"])
    holds_data = any(out.glob(f"{plan.split}-*.tar"))  # finished shards of SHARD_PATTERN
    if path.is_file() and holds_data:
        try:
            stored = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise UserError(f"cannot read {path} ({exc}); delete it or use a new --out") from exc
        ignore = {"preset"}  # the same config may be named by preset or by path
        differs = sorted(k for k in record.keys() | stored.keys()
                         if k not in ignore and record.get(k) != stored.get(k))
        if "config" in differs:
            old, new = stored.get("config", {}), record["config"]
            differs += [f"config.{k}" for k in sorted(new.keys() | old.keys())
                        if old.get(k) != new.get(k)]
        if differs:
            raise UserError(
                f"{out} already holds a different dataset ({path.name} differs in: "
                f"{', '.join(differs)}); rerun with the original settings to resume it, "
                "or choose a new --out"
            )
        return
    if holds_data:  # the dataset file was deleted: the shards' own scenes tell their dataset
        _check_shards_match(out, record, plan)
    write_json(path, record)
    write_text(out / f"config-{record['split']}.yaml", to_yaml(record["config"]))


def _check_shards_match(out: Path, record: dict[str, Any], plan: ShardPlan) -> None:
    """Refuse to resume shards in `out` whose first scene (its meta.json) was made by another
    generator version, or with another seed or config than `record`: they would pass as complete
    shards of this dataset and mix two generations."""
    digest, version = config_digest(record["config"]), record["generator_version"]
    for shard in sorted(out.glob(f"{plan.split}-*.tar")):
        meta = first_scene_meta(shard)
        how = "rerun with the shards' settings to resume them, or choose a new --out"
        if "generator_version" in meta and meta["generator_version"] != version:
            made = (f"by datagen {meta['generator_version']} (this is datagen {version}, whose "
                    "scenes differ)")
            how = "choose a new --out to generate the dataset with this version"
        elif "seed" in meta and meta["seed"] != record["seed"]:
            made = f"with seed {meta['seed']} (this run: seed {record['seed']})"
        elif "config_digest" in meta and meta["config_digest"] != digest:
            made = (f"with another config (config_digest {meta['config_digest']}, this run's "
                    f"{digest})")
        else:
            continue
        raise UserError(f"{shard} was generated {made} and "
                        f"{DATASET_FILE.format(split=plan.split)} is missing; {how}")


# --- scene generation, in this process or in spawned workers ------------------------------------

_worker: dict[str, Any] = {}

# Set by Ctrl-C (SIGINT) during a run. Python raises KeyboardInterrupt wherever the main thread
# happens to be, and where that is a finaliser (`__del__`, a weakref callback of the pool) the
# exception is printed and dropped: the run then went on to the end with exit 0. The flag keeps
# the interrupt, and the loops below check it between scenes and while waiting for a worker.
_interrupted = threading.Event()
# The pools of scene workers of this run, whose processes a second Ctrl-C kills.
_pools: list[ProcessPoolExecutor] = []


@contextmanager
def _interrupt_flag() -> Iterator[None]:
    """While inside: the first SIGINT sets `_interrupted` and raises KeyboardInterrupt (main
    thread only); the run then waits for the scenes its workers are rendering. A second SIGINT
    kills the workers (`_kill_workers`), which ends that wait, and raises nothing: the cleanup it
    would otherwise cut short (removing the partial shard) still runs.

    A process that ignores SIGINT (a job a shell started in the background) keeps ignoring it."""
    _interrupted.clear()
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is signal.SIG_IGN):
        yield
        return

    def on_sigint(signum, frame):
        if _interrupted.is_set():
            _kill_workers()
            return
        _interrupted.set()
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _check_interrupt() -> None:
    if _interrupted.is_set():
        raise KeyboardInterrupt


def _kill_workers() -> None:
    """Kill the processes of every pool in `_pools` (the scenes they render are lost; their shard
    is not written); each pool then counts as broken and stops waiting for them."""
    for pool in _pools:
        # the pool's own processes: no public way to reach them before Python 3.14 (kill_workers)
        for process in list((pool._processes or {}).values()):
            process.kill()


@contextmanager
def _stoppable(pool: ProcessPoolExecutor) -> Iterator[ProcessPoolExecutor]:
    """`pool`, shut down on leaving (waiting for its running scenes), its workers killed by a
    second Ctrl-C until then."""
    _pools.append(pool)
    try:
        with pool:
            yield pool
    finally:
        _pools.remove(pool)


@contextmanager
def _sigint_held() -> Iterator[None]:
    """SIGINT blocked in this thread while inside (one that comes is delivered on leaving). A
    process started inside inherits the blocked signal (the mask survives exec, as for CPython's
    own resource tracker): a terminal's Ctrl-C, sent to the whole process group, never reaches
    it, and only this process decides what Ctrl-C does."""
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def _exit_with_parent(parent: int) -> None:
    """Watch (in a daemon thread) for the parent process to die, then end this worker at once:
    an orphaned worker would otherwise sit idle holding its memory (and the resource tracker)."""
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def _init_worker(cfg, parent: int) -> None:
    """Worker initializer: keep the config (the assets load with the first scene); exit when the
    parent `parent` dies; one thread (the workers share the cores)."""
    import threading

    init_worker_threads()

    _worker["cfg"] = cfg
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()


def _make_sample(cfg, scene_index: int, assets) -> dict[str, Any]:
    from datagen.generate import generate_scene

    scene = generate_scene(cfg, scene_index, assets=assets)
    return encode_scene(scene, scene_key(cfg.split, scene_index))


def _worker_sample(scene_index: int) -> dict[str, Any]:
    """Generate and encode one scene in a worker; the asset library loads once per worker."""
    cfg = _worker["cfg"]
    if "assets" not in _worker:
        from datagen.assets import load_asset_library

        require_egl()
        _worker["assets"] = load_asset_library(cfg)
    return _make_sample(cfg, scene_index, _worker["assets"])


def generate_samples(cfg, indices: list[int], workers: int) -> Iterator[dict[str, Any]]:
    """Encoded samples of scenes `indices`, in that order, from `workers` processes.

    Workers are spawned (forking a process that may hold an EGL context is unsafe); at most two
    scenes per worker wait in memory, so a slow scene never lets results pile up. A worker that
    dies (out of memory, a crash in the GL driver) ends the run with a `UserError`, not a hang.
    Workers never see Ctrl-C (`_sigint_held`): at the first the run waits for the scenes they are
    rendering, at a second it kills them (`_interrupt_flag`).
    """
    from datagen.assets import load_asset_library

    if workers <= 1:
        assets = load_asset_library(cfg)
        for index in indices:
            yield _make_sample(cfg, index, assets)
        return
    context = multiprocessing.get_context("spawn")
    with _stoppable(ProcessPoolExecutor(workers, mp_context=context, initializer=_init_worker,
                                        initargs=(cfg, os.getpid()))) as pool:
        todo = iter(indices)
        with _sigint_held():  # the first `workers` submissions start the workers
            pending = deque(pool.submit(_worker_sample, i) for i in islice(todo, 2 * workers))
        try:
            while pending:
                future = pending.popleft()
                while True:  # wait in slices, so an interrupt lost in a finaliser still ends it
                    try:
                        sample = future.result(timeout=0.5)
                        break
                    except TimeoutError:
                        _check_interrupt()
                following = next(todo, None)
                if following is not None:
                    pending.append(pool.submit(_worker_sample, following))
                yield sample
        except BrokenProcessPool as exc:
            _check_interrupt()  # killed by a second Ctrl-C, not crashed
            raise UserError(
                "a worker process died while generating a scene (out of memory or a crash in the "
                "GL driver?); run the same command again with fewer --workers to resume"
            ) from exc
        finally:
            for future in pending:
                future.cancel()  # the pool then only waits for the scenes already running
            if _interrupted.is_set():
                log.warning("interrupted: waiting for the %d worker(s) to finish the scene each is "
                            "rendering (Ctrl-C again stops them at once); the shards already "
                            "written are kept and rerunning the same command continues", workers)


# What lowers each part of `datagen.generate.scene_memory`.
MEMORY_KNOBS = {"frames": "--frames or --resolution", "tracks": "tracks.num_points or --frames",
                "physics": "--frames, physics.step_rate or objects.num_static/num_tossed",
                "placement": "objects.placement_tries or objects.num_static/num_tossed"}


def check_memory(cfg, workers: int) -> None:
    """`UserError` (before anything is allocated or written) where `workers` processes making
    one scene of `cfg` each would need more memory than is available: the estimate
    `scene_memory`, the biggest part and the knobs that lower it named."""
    from datagen.generate import scene_memory

    available = available_memory()
    parts = scene_memory(cfg)
    scene = sum(parts.values())
    if available is None or workers * scene <= available:
        return
    biggest = max(parts, key=parts.get)
    height, width = cfg.resolution
    total = f", {gib(workers * scene)} for {workers} workers" if workers > 1 else ""
    fewer = " (or fewer --workers)" if workers > 1 and scene <= available else ""
    raise UserError(f"a scene of {cfg.frames} frames at {height}x{width} with "
                    f"{cfg.tracks.num_points} tracks needs about {gib(scene)} of memory ({biggest} "
                    f"{gib(parts[biggest])}){total}, more than the {gib(available)} available; "
                    f"lower {MEMORY_KNOBS[biggest]}{fewer}")


def run(args: argparse.Namespace) -> int:
    overrides = list(args.overrides) + datagen_flag_overrides(args)
    cfg = load_config("datagen", args.preset, args.config, overrides)
    plan = ShardPlan(str(cfg.split), args.num_scenes, args.scenes_per_shard)
    task_index, num_tasks = resolve_task(args.task_index, args.num_tasks)
    if args.workers < 1:
        raise UserError(f"--workers must be at least 1, got {args.workers}")
    check_memory(cfg, min(args.workers, args.num_scenes))
    require_egl()
    configure_threads(workers=args.workers if args.workers > 1 else 0)
    from datagen.assets import load_asset_library

    load_asset_library(cfg).check_backgrounds()  # fails early on unreadable folders and images
    with output_folder(args.out, "datagen", args.overwrite):
        return _generate(args, cfg, plan, task_index, num_tasks)


def _generate(args: argparse.Namespace, cfg, plan: ShardPlan, task_index: int, num_tasks: int) -> int:
    """The shards of task `task_index` of `num_tasks` that OUT (claimed) does not hold yet."""
    claim_directory(args.out, dataset_record(cfg, plan, str(args.preset)), plan)

    shards = plan.shards_of_task(task_index, num_tasks)
    todo = plan.missing_shards(args.out, shards)
    indices = [i for shard in todo for i in plan.scenes_of(shard)]
    task = f"task {task_index} of {num_tasks}: " if num_tasks > 1 else ""
    if not shards:
        log.info("%sno shards to write: the dataset has only %d", task, plan.num_shards)
        return 0
    if not indices:
        log.info("%s%d of %d shards already complete in %s; nothing to do",
                 task, len(shards), len(shards), args.out)
        return 0
    workers = min(args.workers, len(indices))
    log.info("%sgenerating %d scenes into %d shards of %s (%d already complete), %d worker(s)",
             task, len(indices), len(todo), args.out, len(shards) - len(todo), workers)

    start = time.perf_counter()
    with _interrupt_flag():
        _write_shards(args.out, plan, todo, generate_samples(cfg, indices, workers), len(indices))
    seconds = time.perf_counter() - start
    log.info("wrote %d scenes in %d shards to %s in %.0f s (%.2f scenes/s)",
             len(indices), len(todo), args.out, seconds, len(indices) / seconds)
    return 0


def _write_shards(out: Path, plan: ShardPlan, todo: list[int], samples: Iterator[dict[str, Any]],
                  total: int) -> None:
    """Write the scenes `samples` yields into the shards `todo` of `plan` in `out`, in order."""
    try:
        with tqdm(total=total, unit="scene", desc="datagen", dynamic_ncols=True) as bar:
            for shard in todo:
                with ShardWriter(out / plan.shard_name(shard)) as writer:
                    for index in plan.scenes_of(shard):
                        sample = next(samples)
                        _check_interrupt()
                        assert sample["__key__"] == scene_key(plan.split, index), "out of order"
                        writer.write(sample)
                        bar.update()
    finally:
        samples.close()  # on an error or Ctrl-C: cancel queued scenes, shut the workers down
