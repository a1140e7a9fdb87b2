"""Speed of `c4d inspect`'s two inner loops: the statistics pass over shards and the point splatter.

    .venv/bin/python benchmarks/bench_inspect.py [--scenes 4] [--size 128] [--frames 12] [--repeats 3]

1. Statistics pass: seconds per scene to read a shard set decoding every field (the baseline of
   the ratio) versus only the fields the statistics need (`STATISTICS_FIELDS`), as
   `build_dataset_report` does for all scenes after the samples. Scenes are the analytic box
   scenes of tests/synthetic_scenes.py written with datagen's shard writer.
2. Point splatter: seconds per rendered view of `render_points` (z-buffer, 3x3 splats) for M
   points into a 256x341 image, against projecting the same points alone (the baseline).
Prints markdown tables of medians over `--repeats` runs.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from c4d.inspect import dataset_check, dataset_report, point_render
from c4d_core import geometry
from datagen import shards
from timing import median_seconds

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: tests.synthetic_scenes
from tests.synthetic_scenes import make_box_scene  # noqa: E402



def bench_statistics_pass(num_scenes: int, size: int, frames: int, repeats: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        with shards.ShardWriter(Path(tmp) / "train-000000.tar") as writer:
            for i in range(num_scenes):
                scene = make_box_scene(num_frames=frames, height=size, width=size, num_tracks=256, seed=i)
                writer.write(shards.encode_scene(scene, shards.scene_key("train", i)))

        def read(fields):
            for sample in dataset_check.iter_dataset(tmp, fields=fields):
                dataset_report.scene_statistics(sample.scene)

        full = median_seconds(lambda: read(None), repeats) / num_scenes
        subset = median_seconds(lambda: read(dataset_report.STATISTICS_FIELDS), repeats) / num_scenes
    print(f"\n{num_scenes} scenes of {frames} frames at {size}x{size}, 256 tracks\n")
    print("| statistics pass | s / scene | speed-up |")
    print("|---|---|---|")
    print(f"| decode every field (baseline) | {full:.4f} | 1.0x |")
    print(f"| decode STATISTICS_FIELDS only | {subset:.4f} | {full / subset:.1f}x |")


def bench_splatter(repeats: int) -> None:
    rng = np.random.default_rng(0)
    size = (256, 341)
    intrinsics = np.array([[375.0, 0, 170.0], [0, 375.0, 127.5], [0, 0, 1]])
    pose = geometry.look_at(np.array([0.0, -8.0, 4.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    print("\n| points M | project only (baseline), s | render_points, s | ratio | views / s |")
    print("|---|---|---|---|---|")
    for count in (20_000, 100_000, 400_000):
        points = rng.uniform(-4, 4, (count, 3))
        colors = rng.integers(0, 256, (count, 3), dtype=np.uint8)
        project = median_seconds(lambda: geometry.project(points, intrinsics, pose), repeats)
        render = median_seconds(
            lambda: point_render.render_points(points, colors, intrinsics, pose, size), repeats)
        print(f"| {count} | {project:.4f} | {render:.4f} | {render / project:.1f}x | {1 / render:.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=4)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    bench_statistics_pass(args.scenes, args.size, args.frames, args.repeats)
    bench_splatter(args.repeats)


if __name__ == "__main__":
    main()
