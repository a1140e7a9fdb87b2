"""Speed and peak memory of the C4D optimisation (init, stage 1 GA+CMA+CTS, stage 2 PTS) on this CPU.

Every case runs in its own subprocess (peak RSS is per process) on an analytic box scene with
ground-truth pointmaps and flow (`tests/synthetic_scenes.py`), the default scene graph (offsets
1,3,5,7,9, symmetric) and the default config. Per stage it times `--iters` iterations and reports
the median seconds per iteration and that median x 300 (the paper's 300 iterations per stage:
EXTRAPOLATED from the measured iterations, labelled as such).

Baseline in the same run (`--baseline`, also part of the default run): on identical inputs
(16 frames of 64x64, 110 edges: the case C4D was compared with naver/dust3r's PointCloudOptimizer on),
CPU seconds per stage-1 iteration of C4D (GA + CMA + CTS, and GA only) against `plain_ga`, DUSt3R's
global alignment written the straightforward way (autograd over (E,P,3) tensors, all edges at
once, then Adam), so the suite tracks the ratio that docs/perf/c4d_optim.md measured against
DUSt3R's own code. Medians over iterations and repeats, every variant in its own process.

    .venv/bin/python benchmarks/bench_c4d_optim.py [--quick] [--threads 1] [--baseline]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: tests.synthetic_scenes


def one_case(frames: int, height: int, width: int, iters: int, threads: int, overrides: list[str]) -> dict:
    import numpy as np
    import torch

    from c4d_core.config import load_config
    from c4d_pipeline.flow import build_flow
    from c4d_pipeline.ground_truth import GroundTruthPointmaps, oracle_tracks
    from c4d_pipeline.optimize import optimise
    from c4d_pipeline.scene_graph import graph_from_config
    from tests.synthetic_scenes import make_box_scene

    torch.set_num_threads(threads)
    start, cpu_start = time.perf_counter(), time.process_time()
    scene = make_box_scene(frames, height, width, num_tracks=1024, seed=0)
    cfg = load_config("c4d", "default", overrides=[f"optim.stage1_iters={iters}",
                                                   f"optim.stage2_iters={iters}", *overrides])
    edges = graph_from_config(frames, cfg.graph)
    pw = GroundTruthPointmaps(scene, static_bias=False).pointmaps(scene.rgb, edges)
    flows = build_flow("gt", scene=scene).flow(scene.rgb, [tuple(map(int, e)) for e in edges])
    tracks = oracle_tracks(scene)
    inputs_s, inputs_cpu_s = time.perf_counter() - start, time.process_time() - cpu_start
    rss_inputs = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # GiB (ru_maxrss in KiB)
    res = optimise(pw, frames, cfg, flows=flows, tracks=tracks.tracks, visible=tracks.visible)
    rss_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    hist = res.history
    s1 = float(np.median(hist["losses"]["stage1"]["seconds"]))
    s2 = float(np.median(hist["losses"]["stage2"]["seconds"]))
    c1 = float(np.median(hist["losses"]["stage1"]["cpu_seconds"]))
    c2 = float(np.median(hist["losses"]["stage2"]["cpu_seconds"]))
    return {
        "frames": frames, "size": f"{width}x{height}", "edges": len(edges), "iters_measured": iters,
        "threads": threads, "overrides": overrides, "inputs_s": inputs_s, "inputs_cpu_s": inputs_cpu_s,
        "init_s": hist["seconds"]["init"], "init_cpu_s": hist["cpu_seconds"]["init"],
        "pts_targets_cpu_s": hist["cpu_seconds"]["pts_targets"], "stage1_s_per_iter": s1,
        "stage1_s_300_extrapolated": 300 * s1,
        "pts_targets_s": hist["seconds"]["pts_targets"], "stage2_s_per_iter": s2,
        "stage2_s_300_extrapolated": 300 * s2, "stage1_cpu_s_per_iter": c1, "stage2_cpu_s_per_iter": c2,
        "rss_after_inputs_gib": rss_inputs, "rss_peak_gib": rss_peak,
    }


def plain_ga(pw, num_frames: int, init) -> tuple[torch.nn.Module, Callable[[], torch.Tensor]]:
    """DUSt3R's GA loss written the straightforward way: depth, pose, focal and edge-similarity
    parameters, world points gathered per edge, similarity applied, weighted distances, mean over
    edges and pixels (both views); autograd for the gradient. Returns (params, loss function)."""
    from c4d_pipeline.objectives import affine
    from c4d_pipeline.scene_params import SceneParams

    params = SceneParams(init.depth, init.cam_to_world, init.focal, init.edge_scale, init.edge_rotation,
                         init.edge_translation)
    e = pw.num_edges
    ei, ej = torch.from_numpy(pw.edges[:, 0]), torch.from_numpy(pw.edges[:, 1])
    pts_i, pts_j = (torch.from_numpy(x).reshape(e, -1, 3) for x in (pw.pts_i, pw.pts_j))
    w_i, w_j = (torch.from_numpy(x).reshape(e, -1).log() for x in (pw.conf_i, pw.conf_j))

    def loss():
        world = params.world_points().reshape(num_frames, -1, 3)  # (T,P,3)
        scale, rot, trans = params.edge_similarities()
        sim = scale[:, None, None] * rot
        l_i = (w_i * (world[ei] - affine(pts_i, sim, trans)).norm(dim=-1)).mean()
        l_j = (w_j * (world[ej] - affine(pts_j, sim, trans)).norm(dim=-1)).mean()
        return l_i + l_j

    return params, loss


def baseline_case(variant: str, iters: int, threads: int) -> dict:
    """CPU s per stage-1 iteration (median) of `variant` on the 16x64x64 box scene: 'plain GA',
    'C4D stage 1' (default config) or 'C4D GA only'; and the process's peak RSS."""
    import numpy as np

    from c4d_core.config import load_config
    from c4d_pipeline.alignment import initialise
    from c4d_pipeline.flow import build_flow
    from c4d_pipeline.ground_truth import GroundTruthPointmaps, ground_truth_motion_masks
    from c4d_pipeline.optimize import Stage1, rescale_world
    from c4d_pipeline.scene_graph import graph_from_config
    from tests.synthetic_scenes import make_box_scene

    torch.set_num_threads(threads)
    frames, size = 16, 64
    scene = make_box_scene(frames, size, size, num_tracks=0, seed=0)
    overrides = ["weights.cma=0", "weights.cts=0"] if variant == "C4D GA only" else []
    cfg = load_config("c4d", "default", overrides=overrides)
    edges = graph_from_config(frames, cfg.graph)
    pw = GroundTruthPointmaps(scene).pointmaps(scene.rgb, edges)
    flows = build_flow("gt", scene=scene).flow(scene.rgb, [tuple(map(int, e)) for e in edges])
    if variant == "plain GA":
        init = rescale_world(initialise(pw, frames), (size, size), cfg.optim.world_scale)
        params, loss_fn = plain_ga(pw, frames, init)

        def step():
            loss_fn().backward()
    else:
        stage1 = Stage1(pw, frames, cfg, flows, ~ground_truth_motion_masks(scene))
        params, step = stage1.params, stage1.step
    opt = torch.optim.Adam(list(params.parameters()), lr=0.01, betas=(0.9, 0.9))
    times = []
    for _ in range(iters + 2):
        start = time.process_time()
        opt.zero_grad(set_to_none=True)
        step()
        opt.step()
        times.append(time.process_time() - start)
    return {"variant": variant, "edges": len(edges), "cpu_s_per_iter": float(np.median(times[2:])),
            "rss_peak_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}


BASELINE_VARIANTS = ("plain GA", "C4D stage 1", "C4D GA only")


def baseline(repeats: int, iters: int, threads: int) -> dict:
    """{variant: median CPU s per iteration over `repeats` processes}, the variants interleaved."""
    runs: dict[str, list[dict]] = {v: [] for v in BASELINE_VARIANTS}
    for _ in range(repeats):
        for variant in BASELINE_VARIANTS:
            cmd = [sys.executable, __file__, "--baseline-one", variant, str(iters), str(threads)]
            out = subprocess.run(cmd, capture_output=True, text=True, check=True)
            runs[variant].append(json.loads(out.stdout.strip().splitlines()[-1]))
    med = lambda xs: sorted(xs)[len(xs) // 2]  # noqa: E731
    return {v: {"cpu_s_per_iter": med([r["cpu_s_per_iter"] for r in rs]),
                "rss_peak_gib": med([r["rss_peak_gib"] for r in rs])} for v, rs in runs.items()}


def print_baseline(result: dict, repeats: int) -> None:
    ref = result["plain GA"]
    print(f"16 frames 64x64, 110 edges, CPU s per stage-1 iteration (median of {repeats} processes):")
    for variant, r in result.items():
        print(f"  {variant:12s} {r['cpu_s_per_iter']:.4f} s  {r['cpu_s_per_iter'] / ref['cpu_s_per_iter']:.2f}x plain GA"
              f"   peak RSS {r['rss_peak_gib']:.3f} GiB ({r['rss_peak_gib'] / ref['rss_peak_gib']:.2f}x)")


def run_subprocess(frames, height, width, iters, threads, overrides) -> dict:
    cmd = [sys.executable, __file__, "--one", str(frames), str(height), str(width), str(iters),
           str(threads), *overrides]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small sizes only")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3, help="runs of the small baseline pair")
    parser.add_argument("--cases", default=None,
                        help="only these cases, e.g. 24x96x128:5,24x384x512:1 (frames x H x W : iterations)")
    parser.add_argument("--baseline", action="store_true", help="only the plain-GA baseline comparison")
    parser.add_argument("--one", nargs="+", help=argparse.SUPPRESS)
    parser.add_argument("--baseline-one", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.baseline_one:
        variant, iters, threads = args.baseline_one
        print(json.dumps(baseline_case(variant, int(iters), int(threads))))
        return 0
    if args.baseline:
        result = baseline(args.repeats, 10, args.threads)
        print_baseline(result, args.repeats)
        print(json.dumps(result))
        return 0
    if args.one:
        frames, height, width, iters, threads = map(int, args.one[:5])
        print(json.dumps(one_case(frames, height, width, iters, threads, args.one[5:])))
        return 0
    rows = []
    if args.cases:
        for case in args.cases.split(","):
            dims, iters = case.split(":")
            frames, height, width = map(int, dims.split("x"))
            rows.append({**run_subprocess(frames, height, width, int(iters), args.threads, []), "label": "default"})
        print(json.dumps(rows))
        return 0
    # baseline comparison (same run): edge chunking on vs off, small case, several repeats
    pair = {}
    for label, ov in (("chunked (edge_chunk=64)", []), ("unchunked (edge_chunk=0)", ["optim.edge_chunk=0"])):
        runs = [run_subprocess(24, 96, 128, 5, args.threads, ov) for _ in range(args.repeats)]
        med = {k: sorted(r[k] for r in runs)[len(runs) // 2] for k in ("stage1_s_per_iter", "rss_peak_gib")}
        pair[label] = med
        rows.append({**runs[0], **med, "label": label})
    cases = [(24, 96, 128), (90, 96, 128)] + ([] if args.quick else [(24, 384, 512), (90, 384, 512)])
    for frames, height, width in cases:
        iters = 5 if height <= 96 else 2
        rows.append({**run_subprocess(frames, height, width, iters, args.threads, []), "label": "default"})
    print(f"{'case':34s} {'E':>4s} {'init s':>7s} {'st1 s/it':>9s} {'st1 cpu/it':>10s} {'st1 x300*':>9s} "
          f"{'PTS tgt s':>9s} {'st2 s/it':>9s} {'st2 cpu/it':>10s} {'RSS GiB':>8s}")
    for r in rows:
        print(f"{r['label'][:18]:18s} {r['frames']:3d}f {r['size']:>9s} {r['edges']:4d} {r['init_s']:7.2f} "
              f"{r['stage1_s_per_iter']:9.3f} {r['stage1_cpu_s_per_iter']:10.3f} "
              f"{r['stage1_s_300_extrapolated']:9.1f} {r['pts_targets_s']:9.2f} "
              f"{r['stage2_s_per_iter']:9.3f} {r['stage2_cpu_s_per_iter']:10.3f} {r['rss_peak_gib']:8.2f}")
    a, b = pair["chunked (edge_chunk=64)"], pair["unchunked (edge_chunk=0)"]
    print(f"* x300 = median measured seconds per iteration x 300 (extrapolated). threads={args.threads}")
    print(f"chunked / unchunked: stage-1 time {a['stage1_s_per_iter'] / b['stage1_s_per_iter']:.2f}x, "
          f"peak RSS {a['rss_peak_gib'] / b['rss_peak_gib']:.2f}x (medians of {args.repeats})")
    base = baseline(args.repeats, 10, args.threads)
    print_baseline(base, args.repeats)
    print(json.dumps({"cases": rows, "baseline": base}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
