"""Scene generation cost: CPU seconds per scene by part, scenes per hour, peak memory per
worker; CPU seconds per scene against other commits, and the cost of the optional layers.

    .venv/bin/python benchmarks/bench_datagen.py [--scenes 3] [--presets movi-e movi-f]
        [--resolution 256] [--frames 24] [--workers 2] [--all-layers]
    .venv/bin/python benchmarks/bench_datagen.py --against /tmp/prev [--rounds 5] [--scenes 2]
    .venv/bin/python benchmarks/bench_datagen.py --against /tmp/old --cli --presets movi-f

Runs as `c4d datagen`'s workers do: one thread (`init_worker_threads`: llvmpipe's
LP_NUM_THREADS=1, OpenCV and torch 1). For each preset: every asset of the split is loaded first
(as a worker has after its first 100-200 scenes; the one-time cost is printed apart), one
warm-up scene (EGL context, shader compilation), then the median over
`--scenes` scenes of the CPU seconds (all threads, Mesa's rasterizer included) of each part of
`generate_scene` (`datagen.generate.PARTS`: sample, physics, render setup, the lit pass, the label
pass (with the normals and object coordinates when on), flow, tracks, instances, events) and of
encoding the scene into its shard members (`datagen.shards.encode_scene`), with the whole
scene's CPU and wall seconds. `--all-layers` turns every optional layer on (`layers.*=true`).
The lit pass is also timed through pyrender's own renderer with its stock PBR shaders, the
baseline for datagen's shaders and draw loop. With `--workers` > 0, that many processes generate
scenes in parallel to give scenes per hour with all cores.

`--against TREE...`: source trees of other commits (`git archive REV | tar -x -C TREE`, plus a
link `TREE/c4d_configs -> configs` for trees whose presets are installed as that package). Each
round runs every variant once, in a fresh process, in an order that alternates between rounds
(so a change in the machine's load hits all alike): this tree with the presets as they are,
this tree with every optional layer on (`layers.*=true`), and each TREE. Reported: the median
and the minimum over rounds of CPU seconds per scene, and the ratio to the first TREE (the
previous commit) as the median over rounds of the ratio within each round (on a shared machine
a round's load moves all its runs alike, so paired ratios scatter less than the seconds).
The process generates `--scenes` scenes after a warm-up scene (`generate_scene`, the same
indices everywhere). With `--cli` each run is instead a whole `c4d datagen --num-scenes
SCENES` (default `--workers`, so scenes run in spawned workers, shard writing included), timed
as the CPU seconds of the command and all its processes.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ALL_LAYERS = ["layers.normal=true", "layers.object_coordinates=true", "layers.instances=true",
              "layers.events=true"]


def _load_config(*args, **kwargs):
    """`load_config` of the tree on the path: c4d.config in trees before the floor package,
    else c4d_core.config (the `--against` children import whichever tree they run in; the
    older name is tried first, since c4d_core resolves to this checkout where a tree has none)."""
    try:
        from c4d.config import load_config
    except ImportError:
        from c4d_core.config import load_config
    return load_config(*args, **kwargs)


def preset_config(preset: str, resolution: int, frames: int, extra: list[str] = ()):
    return _load_config("datagen", preset, overrides=[
        f"resolution=[{resolution},{resolution}]", f"frames={frames}", *extra])


def time_preset(preset: str, args, extra: list[str] = ()) -> dict:
    """Median CPU seconds per part, wall and CPU seconds per scene of `args.scenes` scenes."""
    from datagen import shards
    from datagen.assets import load_asset_library
    from datagen.generate import generate_scene

    cfg = preset_config(preset, args.resolution, args.frames, extra)
    assets = load_asset_library(cfg)
    start = time.process_time()
    for asset_id in assets.object_ids:  # what a worker has loaded after its first 100-200 scenes
        assets.get(asset_id)
    assets_cpu = time.process_time() - start
    generate_scene(cfg, 10_000, assets)  # warm-up: EGL context, shader compilation
    rows = []
    for index in range(args.scenes):
        timings: dict = {}
        wall, cpu = time.perf_counter(), time.process_time()
        scene = generate_scene(cfg, index, assets, timings)
        timings["total"] = time.perf_counter() - wall
        timings["cpu"] = time.process_time() - cpu
        start = time.process_time()
        shards.encode_scene(scene, shards.scene_key(str(cfg.split), index))
        timings["encode"] = time.process_time() - start
        timings["blur_samples"] = scene.meta["blur_samples"]
        rows.append(timings)
    result = {key: statistics.median(row.get(key, 0.0) for row in rows) for key in rows[0]}
    return {**result, "assets": assets_cpu, "num_assets": len(assets.object_ids)}


def time_lit_pass(args) -> dict:
    """Median ms per lit frame: datagen's pass, and pyrender's renderer with its stock shaders."""
    from datagen import render
    from datagen.assets import load_asset_library
    from datagen.generate import describe_and_simulate

    cfg = preset_config("movi-e", args.resolution, args.frames)
    assets = load_asset_library(cfg)
    description, sim = describe_and_simulate(cfg, 0, assets)
    renderer = render.SceneRenderer(description, sim.placed, assets, cfg)
    times = np.arange(description.num_frames, dtype=np.float64)
    poses, cameras = sim.poses_at(times), description.camera.pose_at(times, len(times))
    pyrender = render._pyrender()
    offscreen = renderer.renderer._renderer
    ours = offscreen._program_cache

    def stock_frame(t):  # pyrender's own forward pass, shadow pass and PBR shaders
        renderer._set_poses(poses[:, t], cameras[t])
        renderer.renderer.render(renderer.scene, flags=pyrender.RenderFlags.SHADOWS_DIRECTIONAL)

    result = {}
    for name, frame in (("pyrender, stock shaders", stock_frame),
                        ("datagen", lambda t: renderer.render_rgb(poses[:, t], cameras[t]))):
        offscreen._program_cache = ours if name == "datagen" else \
            pyrender.shader_program.ShaderProgramCache()
        frame(0)
        frame_ms = []
        for t in range(len(times)):
            start = time.process_time()
            frame(t)
            frame_ms.append(1000 * (time.process_time() - start))
        result[name] = statistics.median(frame_ms)
    offscreen._program_cache = ours
    return result


def _worker(job) -> tuple[int, float]:
    from datagen.assets import load_asset_library
    from datagen.generate import generate_scene

    preset, resolution, frames, indices = job
    cfg = preset_config(preset, resolution, frames)
    assets = load_asset_library(cfg)
    for index in indices:
        generate_scene(cfg, index, assets)
    return len(indices), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def time_parallel(preset: str, args) -> dict:
    per_worker = max(args.scenes, 2)
    jobs = [(preset, args.resolution, args.frames,
             list(range(w * per_worker, (w + 1) * per_worker))) for w in range(args.workers)]
    start = time.perf_counter()
    with mp.get_context("spawn").Pool(args.workers) as pool:
        done = pool.map(_worker, jobs)
    wall = time.perf_counter() - start  # includes process start-up and one EGL context each
    return {"scenes_per_hour": 3600 * sum(n for n, _ in done) / wall,
            "peak_rss_mb": max(mb for _, mb in done)}


def _child_run(tree: Path, preset: str, args, extra: list[str]) -> float:
    """CPU seconds per scene of one fresh process of source tree `tree` (see the module doc)."""
    env = dict(os.environ, PYTHONPATH=str(tree), PYOPENGL_PLATFORM="egl")
    env.pop("OMP_NUM_THREADS", None)  # as a user's shell has it (the tests set it to 1)
    size = ["--resolution", str(args.resolution), "--frames", str(args.frames)]
    if not args.cli:
        command = [sys.executable, str(Path(__file__).resolve()), "--child", preset,
                   "--scenes", str(args.scenes), *size, *extra]
        out = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True)
        if out.returncode:
            raise SystemExit(f"{tree}: {out.stderr[-2000:]}")
        return float(out.stdout.split()[-1])
    with tempfile.TemporaryDirectory() as folder:
        command = [sys.executable, "-c", "import sys; from c4d.cli import main; sys.exit(main())",
                   "datagen", "--preset", preset, "--num-scenes", str(args.scenes), "--out",
                   str(Path(folder) / "out"), *size, *extra]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        out = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if out.returncode:
        raise SystemExit(f"{tree}: {out.stderr[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu / args.scenes


def compare_trees(args) -> None:
    """Interleaved rounds of this tree (as it is, and with every layer on) and each `--against`
    tree; prints the median CPU seconds per scene and the ratio to the first other tree."""
    variants = {"this tree": (ROOT, [])}
    if not args.cli:  # the layers' keys exist only here
        variants["this tree, all layers"] = (ROOT, ALL_LAYERS)
    for tree in args.against:
        variants[str(tree)] = (Path(tree).resolve(), [])
    reference = str(args.against[0])
    print(f"{args.resolution}x{args.resolution} x {args.frames} frames, {args.scenes} scenes per "
          f"{'c4d datagen run' if args.cli else 'process'}, {args.rounds} interleaved rounds; "
          f"CPU seconds per scene, median over rounds; load average {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} cores")
    print("| preset | variant | CPU s/scene (median) | min | runs | x " + reference
          + " (median of the rounds' ratios) |\n|---|---|---|---|---|---|")
    for preset in args.presets:
        runs: dict[str, list[float]] = {name: [] for name in variants}
        for round_index in range(args.rounds):
            names = list(variants) if round_index % 2 == 0 else list(variants)[::-1]
            for name in names:
                tree, extra = variants[name]
                runs[name].append(_child_run(tree, preset, args, extra))
                print(f"  {preset} round {round_index + 1}: {name} {runs[name][-1]:.2f} CPU-s/scene",
                      file=sys.stderr, flush=True)
        for name, values in runs.items():
            paired = statistics.median(v / r for v, r in zip(values, runs[reference]))
            print(f"| {preset} | {name} | {statistics.median(values):.2f} | {min(values):.2f} | "
                  f"{' '.join(f'{v:.2f}' for v in values)} | {paired:.3f} |", flush=True)
    print(f"load average at the end {os.getloadavg()[0]:.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=3)
    parser.add_argument("--presets", nargs="+", default=["movi-e", "movi-e-panning", "movi-f"])
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--against", nargs="+", metavar="TREE", help="source trees of other commits")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds with --against")
    parser.add_argument("--cli", action="store_true", help="with --against: time `c4d datagen` runs")
    parser.add_argument("--all-layers", action="store_true", help="every optional layer on")
    parser.add_argument("--child", metavar="PRESET", help=argparse.SUPPRESS)  # one --against run
    args, extra = parser.parse_known_args()
    if extra and not args.child:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    if not args.against:  # one thread, as `c4d datagen`'s workers run (before GL loads)
        from c4d_core.system import init_worker_threads

        init_worker_threads()
    if args.child:  # in the tree on PYTHONPATH: print CPU seconds per scene, last
        print(time_preset(args.child, args, extra)["cpu"])
        return
    if args.against:
        compare_trees(args)
        return
    from datagen.generate import PARTS

    extra = ALL_LAYERS if args.all_layers else []
    print(f"{args.resolution}x{args.resolution} x {args.frames} frames, median of {args.scenes} "
          f"scenes, one worker{', every optional layer on' if extra else ''}; CPU seconds per "
          f"scene by part; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    columns = [*PARTS, "encode"]
    print("| preset | " + " | ".join(columns) + " | scene CPU s | + encode | wall s | blur n |")
    print("|---" * (len(columns) + 5) + "|")
    for preset in args.presets:
        row = time_preset(preset, args, extra)
        print(f"| {preset} | " + " | ".join(f"{row.get(c, 0.0):.3f}" for c in columns)
              + f" | {row['cpu']:.2f} | {row['cpu'] + row['encode']:.2f} | {row['total']:.2f}"
              f" | {row['blur_samples']:.0f} |")
        print(f"  (loading the {row['num_assets']:.0f} assets of the split, once per worker: "
              f"{row['assets']:.1f} CPU-s, before the scenes timed)")
    lit = time_lit_pass(args)
    stock = lit["pyrender, stock shaders"]
    for name, ms in lit.items():
        print(f"lit pass, {name:24s} {ms:7.1f} CPU ms/frame  (x{ms / stock:.2f} of pyrender)")
    if args.workers > 0:
        par = time_parallel(args.presets[0], args)
        print(f"{args.presets[0]} with {args.workers} workers: {par['scenes_per_hour']:.0f} "
              f"scenes/hour, peak memory per worker {par['peak_rss_mb']:.0f} MB")


if __name__ == "__main__":
    main()
