"""Speed of optical flow and motion masks per image pair, on the analytic box scene.

    .venv/bin/python benchmarks/bench_c4d_flow.py [--sizes 96x128,384x512] [--pairs 8] [--repeats 3]

Per frame size: seconds per pair (median of `--repeats` runs over `--pairs` pairs of offsets 1
and 3) of the flows 'dis' (medium, the baseline of the ratios), 'dis:fast' and 'gt', and of the
masks: C4D's correspondence-guided mask (oracle tracks, F by LMedS + refit, Sampson distance)
and the flow-only baseline (ego-flow from per-frame geometry, normalised error). Then, per size,
seconds per 12-frame video over the whole default scene graph (offsets 1,3,5,7,9 both ways: 70
pairs) of DIS searching every pair against DIS chained over consecutive frames ('+chain'), plain
and on frames upsampled 3x (the demo's). Prints markdown.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from c4d_core.config import load_config
from c4d_pipeline.flow import build_flow
from c4d_pipeline.ground_truth import oracle_tracks
from c4d_pipeline.motion_mask import correspondence_motion_masks, ego_flow, flow_only_motion_masks
from c4d_pipeline.scene_graph import graph_from_config
from timing import median_seconds

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: tests.synthetic_scenes
from tests.synthetic_scenes import make_box_scene  # noqa: E402



def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="96x128,384x512", help="comma-separated HxW")
    parser.add_argument("--pairs", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print("| size | step | s / pair | vs DIS medium |")
    print("|---|---|---|---|")
    for size in args.sizes.split(","):
        height, width = (int(v) for v in size.split("x"))
        scene = make_box_scene(num_frames=8, height=height, width=width, num_tracks=400)
        pairs = [(i, i + o) for o in (1, 3) for i in range(8 - o)][: args.pairs]
        flows = build_flow("gt", scene=scene).flow(scene.rgb, pairs)
        tracks = oracle_tracks(scene)
        sc = scene
        egos = np.stack([ego_flow(sc.depth[i], sc.intrinsics[i], sc.intrinsics[j], sc.cam_to_world[i], sc.cam_to_world[j]) for i, j in pairs])
        steps = {
            "flow dis (medium)": lambda: build_flow("dis").flow(sc.rgb, pairs),
            "flow dis:fast": lambda: build_flow("dis:fast").flow(sc.rgb, pairs),
            "flow gt (exact)": lambda: build_flow("gt", scene=sc).flow(sc.rgb, pairs),
            "mask C4D (LMedS + Sampson)": lambda: correspondence_motion_masks(tracks, flows, pairs),
            "mask flow-only (given ego-flow)": lambda: flow_only_motion_masks(flows, egos, pairs, sc.num_frames),
            "ego-flow from depth + poses": lambda: [ego_flow(sc.depth[i], sc.intrinsics[i], sc.intrinsics[j], sc.cam_to_world[i], sc.cam_to_world[j]) for i, j in pairs],
        }
        seconds = {name: median_seconds(fn, args.repeats) / len(pairs) for name, fn in steps.items()}
        base = seconds["flow dis (medium)"]
        for name, value in seconds.items():
            print(f"| {height}x{width} | {name} | {value:.4f} | {value / base:.2f}x |", flush=True)
    print("\n| size | flow over a 12-frame scene graph (70 pairs) | s / video | vs searching every pair |")
    print("|---|---|---|---|")
    graph = load_config("c4d", "default").graph
    for size in args.sizes.split(","):
        height, width = (int(v) for v in size.split("x"))
        scene = make_box_scene(num_frames=12, height=height, width=width, num_tracks=10)
        pairs = [tuple(map(int, e)) for e in graph_from_config(12, graph)]
        for search in ("dis", "dis:medium@3x"):
            plain = median_seconds(lambda: build_flow(search).flow(scene.rgb, pairs), args.repeats)
            chained = median_seconds(lambda: build_flow(search + "+chain").flow(scene.rgb, pairs), args.repeats)
            print(f"| {height}x{width} | {search} | {plain:.3f} | 1.00x |", flush=True)
            print(f"| {height}x{width} | {search}+chain | {chained:.3f} | {chained / plain:.2f}x |", flush=True)


if __name__ == "__main__":
    main()
