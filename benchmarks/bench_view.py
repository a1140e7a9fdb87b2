"""`c4d view` of long reconstructions: the page's size, the time to its first drawn frame, and
`c4d view`'s own CPU time and peak memory, for N frames.

    .venv/bin/python benchmarks/bench_view.py [--frames 90 300 1000] [--size 256x192] [--repeats 3]
                                              [--keep DIR] [-- VIEW OPTIONS...]

The reconstructions are written with `c4d run`'s own writer (c4d_pipeline/outputs.py) without
running the optimiser: the analytic box scene of tests/synthetic_scenes.py (its ground-truth
depth unprojected, motion masks, 64 tracks; at most 90 frames of it) played forth and back
(0, 1, .., 89, 88, .., 0, 1, ..) up to N frames, so every frame holds a full frame's points.
`--keep DIR` keeps them there (and reuses them) between runs; VIEW OPTIONS after `--` are passed
to every `c4d view` (e.g. `-- --max-page-mb 0` for the page without a size budget).

Per N and run: `python -m c4d view RECON --save PAGE` in a fresh process (its CPU time, user +
system, and peak RSS, as a small launcher process sees them), then the page opened in a fresh tab
of one headless Chromium (c4d/view/browser.py, SwiftShader WebGL, 1280x800; one page opened first
and not counted, as the browser's first page also starts its GPU process): the wall time from
navigating to the page until it says it is ready and one more animation frame is drawn, the
page's own mark of its first drawn frame (`c4dView.timing.drawn`, ms since navigation), and the
wall time until the last frame is drawn after the slider is set to it. `--budgets` compares
`--max-page-mb` values, interleaved within each repeat. Prints a markdown table of medians over
`--repeats` runs, the load before and after, and the commit.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the repository root: tests.synthetic_scenes

from timing import load_average, this_commit  # noqa: E402
from c4d.view import browser as chromium  # noqa: E402
from c4d_pipeline import outputs  # noqa: E402
from c4d_pipeline.ground_truth import ground_truth_motion_masks  # noqa: E402
from c4d_core import geometry  # noqa: E402
from tests.synthetic_scenes import make_box_scene  # noqa: E402

BASE_FRAMES = 90  # frames of the box scene played forth and back


def forth_and_back(frames: int, base: int) -> np.ndarray:
    """(frames,) indices into `base` frames: 0, 1, .., base-1, base-2, .., 0, 1, .."""
    if base == 1:
        return np.zeros(frames, int)
    i = np.arange(frames) % (2 * base - 2)
    return np.where(i < base, i, 2 * base - 2 - i)


def write_long_reconstruction(out: Path, frames: int, width: int, height: int) -> Path:
    """A reconstruction folder of `frames` frames of `width` x `height` (see the module's doc)."""
    scene = make_box_scene(num_frames=min(frames, BASE_FRAMES), height=height, width=width,
                           num_tracks=64, seed=0)
    pick = forth_and_back(frames, scene.num_frames)
    points = np.stack([geometry.unproject_depth_map(d, k, p) for d, k, p in
                       zip(scene.depth, scene.intrinsics, scene.cam_to_world)]).astype(np.float32)
    rec = outputs.Reconstruction(
        frames=scene.rgb[pick], depth=scene.depth[pick], masks=ground_truth_motion_masks(scene)[pick],
        cam_to_world=scene.cam_to_world[pick], intrinsics=scene.intrinsics[pick], points=points[pick],
        confidence=np.ones((frames, height, width), np.float32),
        tracks_world=scene.tracks_world.transpose(1, 0, 2)[pick], tracks_valid=~scene.occluded.T[pick],
        report={"inputs": {"frame_indices": list(range(frames))}},
    )
    return outputs.write_reconstruction(rec, out)


# Runs `c4d view` as its own child and prints its CPU seconds and peak RSS: measured by wait4 from
# this process, the peak would include this benchmark's own (a child inherits its parent's peak).
LAUNCHER = ("import json, resource, subprocess, sys; code = subprocess.run(sys.argv[1:]).returncode; "
            "use = resource.getrusage(resource.RUSAGE_CHILDREN); print(json.dumps({'code': code, "
            "'cpu_s': use.ru_utime + use.ru_stime, 'peak_mib': use.ru_maxrss / 1024}))")


def run_view(recon: Path, page: Path, options: list[str]) -> dict:
    """One `c4d view RECON --save PAGE` in a fresh process: its CPU seconds and peak RSS (MiB)."""
    done = subprocess.run([sys.executable, "-c", LAUNCHER, sys.executable, "-m", "c4d", "view",
                           str(recon), "--save", str(page), "--overwrite", *options],
                          cwd=ROOT, capture_output=True, text=True)
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    if figures.pop("code"):
        raise SystemExit(f"c4d view failed: {done.stderr.strip()}")
    return figures


def open_page(browser: chromium.Browser, page_file: Path) -> dict:
    """Open the page in a fresh tab: seconds until it is ready and one more frame is drawn, the
    page's own mark of its first drawn frame (s), and seconds to show the last frame."""
    start = time.perf_counter()
    page = browser.open(page_file.as_uri())
    chromium.wait_for_view(page)
    page.next_frames(1)
    first = time.perf_counter() - start
    mark = page.evaluate("c4dView.timing.drawn") / 1000
    frames = page.evaluate("c4dView.stats.frames")
    start = time.perf_counter()
    page.evaluate(f"c4dView.setFrame({frames - 1})")
    page.next_frames(1)
    last = time.perf_counter() - start
    if page.evaluate("c4dView.stats.frame") != frames - 1 or page.errors():
        raise SystemExit(f"the page did not show its last frame: {page.errors()}")
    page.send("Page.close")
    return {"first_s": first, "mark_s": mark, "last_s": last}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[90, 300, 1000])
    parser.add_argument("--size", default="256x192", help="WIDTHxHEIGHT of the frames")
    parser.add_argument("--budgets", nargs="+", default=["default"],
                        help="--max-page-mb values, interleaved within each repeat (default: none given)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--keep", type=Path, help="write (and reuse) the reconstructions here")
    parser.add_argument("view_options", nargs="*", help="after --: options for every `c4d view`")
    args = parser.parse_args()
    width, height = map(int, args.size.split("x"))
    print(f"commit {this_commit()}; load before: {load_average()}; c4d view {' '.join(args.view_options)}")
    with tempfile.TemporaryDirectory(prefix="bench-view-") as tmp:
        folder = args.keep or Path(tmp)
        rows = []
        with chromium.Browser(1280, 800, timeout=600) as browser:
            for frames in args.frames:
                recon = folder / f"recon-{frames}-{width}x{height}"
                if not (recon / "report.json").is_file():
                    start = time.perf_counter()
                    write_long_reconstruction(recon, frames, width, height)
                    print(f"wrote {recon.name} in {time.perf_counter() - start:.0f} s", flush=True)
                page = Path(tmp) / f"view-{frames}.html"
                if frames == args.frames[0]:  # the browser's first page also starts its GPU process
                    run_view(recon, page, args.view_options)
                    open_page(browser, page)
                runs = {budget: [] for budget in args.budgets}
                for _ in range(args.repeats):
                    for budget, done in runs.items():
                        options = args.view_options + ([] if budget == "default" else ["--max-page-mb", budget])
                        done.append({**run_view(recon, page, options), **open_page(browser, page),
                                     "mb": page.stat().st_size / 1e6})
                        print(f"  {frames} frames, --max-page-mb {budget}: {done[-1]}", flush=True)
                for budget, done in runs.items():
                    rows.append((frames, budget, {key: statistics.median(r[key] for r in done) for key in done[0]}))
    print(f"\n{args.size} frames, medians of {args.repeats} runs; load after: {load_average()}\n")
    print("| frames | --max-page-mb | page, MB | first frame drawn, s (page's mark) | last frame shown, s "
          "| c4d view CPU-s | c4d view peak, MiB |")
    print("|---|---|---|---|---|---|---|")
    for frames, budget, m in rows:
        print(f"| {frames} | {budget} | {m['mb']:.1f} | {m['first_s']:.2f} ({m['mark_s']:.2f}) "
              f"| {m['last_s']:.2f} | {m['cpu_s']:.1f} | {m['peak_mib']:.0f} |")


if __name__ == "__main__":
    main()
