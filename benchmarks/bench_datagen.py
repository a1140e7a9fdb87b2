"""Scene generation speed: seconds per scene by stage, scenes per hour, peak memory per worker.

    .venv/bin/python benchmarks/bench_datagen.py [--scenes 3] [--presets movi-e movi-f]
        [--resolution 256] [--frames 24] [--workers 2]

For each preset: one warm-up scene (EGL context, first asset loads), then the median over
`--scenes` scenes of wall seconds per stage (sample, physics, render, labels) and of the whole
scene, plus CPU seconds (all threads, Mesa's rasterizer included). Ratios are against the first
preset (movi-e) in the same run. The lit pass is also timed with pyrender's stock PBR shaders as
the baseline for datagen's own shaders. With `--workers` > 0, that many processes generate scenes
in parallel to give scenes per hour with all cores. Encoding is measured by the shard writer's
benchmark.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import statistics
import time

import numpy as np

from c4d_core.config import load_config
from datagen import render
from datagen.assets import load_asset_library
from datagen.generate import describe_and_simulate, generate_scene

STAGES = ("sample", "physics", "render", "labels")


def preset_config(preset: str, resolution: int, frames: int):
    return load_config("datagen", preset,
                       overrides=[f"resolution=[{resolution},{resolution}]", f"frames={frames}"])


def time_preset(preset: str, args) -> dict:
    cfg = preset_config(preset, args.resolution, args.frames)
    assets = load_asset_library(cfg)
    generate_scene(cfg, 10_000, assets)  # warm-up: EGL context, shader compilation
    rows = []
    for index in range(args.scenes):
        timings: dict = {}
        wall, cpu = time.perf_counter(), time.process_time()
        scene = generate_scene(cfg, index, assets, timings)
        timings["total"] = time.perf_counter() - wall
        timings["cpu"] = time.process_time() - cpu
        timings["blur_samples"] = scene.meta["blur_samples"]
        rows.append(timings)
    return {key: statistics.median(row[key] for row in rows) for key in rows[0]}


def time_lit_pass(args) -> dict:
    """Median ms per lit frame with datagen's shaders and with pyrender's stock shaders."""
    cfg = preset_config("movi-e", args.resolution, args.frames)
    assets = load_asset_library(cfg)
    description, sim = describe_and_simulate(cfg, 0, assets)
    renderer = render.SceneRenderer(description, sim.placed, assets, cfg)
    times = np.arange(description.num_frames, dtype=np.float64)
    poses, cameras = sim.poses_at(times), description.camera.pose_at(times, len(times))
    offscreen = renderer.renderer._renderer
    ours = offscreen._program_cache
    stock = render._pyrender().shader_program.ShaderProgramCache()
    result = {}
    for name, cache in (("pyrender stock shaders", stock), ("datagen shaders", ours)):
        offscreen._program_cache = cache
        renderer.render_rgb(poses[:, 0], cameras[0])
        frame_ms = []
        for t in range(len(times)):
            start = time.perf_counter()
            renderer.render_rgb(poses[:, t], cameras[t])
            frame_ms.append(1000 * (time.perf_counter() - start))
        result[name] = statistics.median(frame_ms)
    offscreen._program_cache = ours
    return result


def _worker(job) -> tuple[int, float]:
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=3)
    parser.add_argument("--presets", nargs="+", default=["movi-e", "movi-e-panning", "movi-f"])
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args()
    print(f"{args.resolution}x{args.resolution} x {args.frames} frames, median of {args.scenes} "
          f"scenes, one worker; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"{'preset':16s}" + "".join(f"{s:>9s}" for s in STAGES)
          + f"{'total s':>9s}{'cpu s':>8s}{'blur n':>8s}{'x movi-e':>10s}")
    baseline = None
    for preset in args.presets:
        row = time_preset(preset, args)
        baseline = baseline or row["total"]
        print(f"{preset:16s}" + "".join(f"{row[s]:9.3f}" for s in STAGES)
              + f"{row['total']:9.2f}{row['cpu']:8.2f}{row['blur_samples']:8.0f}"
              + f"{row['total'] / baseline:10.2f}")
    lit = time_lit_pass(args)
    stock = lit["pyrender stock shaders"]
    for name, ms in lit.items():
        print(f"lit pass, {name:24s} {ms:7.1f} ms/frame  (x{ms / stock:.2f} of stock)")
    if args.workers > 0:
        par = time_parallel(args.presets[0], args)
        print(f"{args.presets[0]} with {args.workers} workers: {par['scenes_per_hour']:.0f} "
              f"scenes/hour, peak memory per worker {par['peak_rss_mb']:.0f} MB")


if __name__ == "__main__":
    main()
