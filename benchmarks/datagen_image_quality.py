"""How close datagen's lit frames come to a 16x supersampled reference of the same scene, to
show that a renderer change which moves RGB leaves the images no worse (docs/perf/datagen.md).

    PYTHONPATH=TREE .venv/bin/python benchmarks/datagen_image_quality.py render OUT.npz
    .venv/bin/python benchmarks/datagen_image_quality.py compare OLD.npz NEW.npz

`render`: movi-e scenes 0-2 at 256x256, 24 frames, as the tree on PYTHONPATH renders them
(4x multisampled) and its reference: the same scene at 4x the resolution, single-sampled,
averaged over 4x4 pixel blocks (16 samples a pixel). `compare`: per scene, each tree's frames
against each tree's reference: PSNR (dB), max |error| and the 99.9th percentile of a pixel's
largest channel error (levels of 255), and the mean error at the pixels where the two trees'
frames differ.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

SCENES = (0, 1, 2)
SUPERSAMPLE = 4  # the reference's resolution factor per axis: 16 samples a pixel


def render_frames(out: Path) -> None:
    """Write out (.npz): frames_<scene> and reference_<scene>, float64 (T,256,256,3) levels."""
    from c4d_core.config import load_config
    from datagen import render
    from datagen.assets import load_asset_library
    from datagen.generate import describe_and_simulate

    pyrender = render._pyrender()
    multisample = pyrender.renderer.glRenderbufferStorageMultisample
    single = {"sampled": False}  # pyrender makes its framebuffers again when the size changes

    def storage(target, samples, fmt, width, height):  # the reference: single-sampled buffers
        if single["sampled"]:
            return pyrender.renderer.glRenderbufferStorage(target, fmt, width, height)
        return multisample(target, samples, fmt, width, height)

    pyrender.renderer.glRenderbufferStorageMultisample = storage
    cfg = load_config("datagen", "movi-e", overrides=["resolution=[256,256]", "frames=24"])
    assets = load_asset_library(cfg)
    arrays = {}
    for index in SCENES:
        description, sim = describe_and_simulate(cfg, index, assets)
        times = np.arange(description.num_frames, dtype=np.float64)
        poses, cameras = sim.poses_at(times), description.camera.pose_at(times, len(times))
        for name, factor in (("frames", 1), ("reference", SUPERSAMPLE)):
            single["sampled"] = factor > 1
            scaled = dataclasses.replace(description, height=256 * factor, width=256 * factor)
            renderer = render.SceneRenderer(scaled, sim.placed, assets, cfg)
            frames = np.stack([renderer.render_rgb(poses[:, t], cameras[t])
                               for t in range(len(times))]).astype(np.float64)  # (T,h,w,3)
            arrays[f"{name}_{index}"] = frames.reshape(
                len(times), 256, factor, 256, factor, 3).mean(axis=(2, 4))
    np.savez(out, **arrays)


def compare(old_file: Path, new_file: Path) -> None:
    """Print the figures of the module docstring for two `render` outputs."""
    old, new = np.load(old_file), np.load(new_file)
    for index in SCENES:
        print(f"scene {index}:")
        for tree, data in (("old", old), ("new", new)):
            for ref_tree, ref in (("old", old), ("new", new)):
                error = data[f"frames_{index}"] - ref[f"reference_{index}"]  # (T,H,W,3)
                psnr = 10 * np.log10(255**2 / np.mean(error**2))
                worst = np.percentile(np.abs(error).max(axis=-1), 99.9)
                print(f"  {tree} frames vs {ref_tree} reference: PSNR {psnr:.3f} dB, "
                      f"max |error| {np.abs(error).max():.1f}, p99.9 {worst:.1f}")
        changed = np.any(old[f"frames_{index}"] != new[f"frames_{index}"], axis=-1)  # (T,H,W)
        for ref_tree, ref in (("old", old), ("new", new)):
            errors = [np.abs(data[f"frames_{index}"][changed]
                             - ref[f"reference_{index}"][changed]).mean() for data in (old, new)]
            print(f"  {changed.sum()} pixels differ; their mean |error| against the {ref_tree} "
                  f"reference: old {errors[0]:.1f}, new {errors[1]:.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mode", choices=("render", "compare"))
    parser.add_argument("files", nargs="+", type=Path)
    args = parser.parse_args()
    if args.mode == "render":
        render_frames(args.files[0])
    else:
        compare(*args.files)


if __name__ == "__main__":
    main()
