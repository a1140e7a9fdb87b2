"""Peak memory, wall time and pose error of C4D on long generated videos, in windows
(`window.frames`, issue 45 item 1) against the whole-video optimisation.

Inputs as the benchmarks of docs/RESULTS.md: one `c4d datagen --preset movi-e` scene per length
(`--frames N`, `--resolution HxW`, made once into DATA/fN), ground-truth-source pointmaps with the
usual noise, per-pair scale and static-world bias (the config's `gt_pointmaps`), DIS flow, and the
scene's own tracks and mobility labels as the tracker result (`oracle_tracks`), or with `--tracker
CKPT` a trained DynPT's tracks of a grid on frame 0 (as `c4d run` queries), tracked in the case's
process (its time in `track_s`, its memory in the peak). Every case is one subprocess (peak RSS is per process) that
reads the scene, calls `windows.reconstruct_windowed` (or `pipeline.reconstruct` for the whole
video) writing into a temporary folder, and reports wall and CPU seconds, the peak RSS, the RSS
once the inputs are read (the scene the ground-truth source reads: frames, depth, segmentation,
object poses, tracks; a video and a network would hold the frames only) and ATE / RPE against the
scene's cameras (Sim(3)-aligned, `eval_metrics.pose_metrics`).

Cases: C4D in windows at every `--frames`; at `--baseline-frames` (same run) also the whole-video
C4D (today's optimisation, the baseline), and GA only (DUSt3R-style: weights.cma=weights.cts=
weights.pts=0) whole and in windows. Ratios against the smallest windowed run and the whole-video
run. Medians over `--repeats` processes per case.

    .venv/bin/python benchmarks/bench_c4d_long.py [--frames 90 180 360] [--window 30] [--overlap 10]
        [--preset tiny] [--resolution 192x256] [--data DIR] [--tracker CKPT] [--json OUT.json] [--plot OUT.png]
        [key=value ...]
    .venv/bin/python benchmarks/bench_c4d_long.py --summarise --json OUT.json [--plot OUT.png]
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: benchmarks.timing

from benchmarks.timing import load_average, this_commit  # noqa: E402

ON_DISK = ("depth", "segmentation")  # (T,H,W) fields the gt source reads a frame at a time from DATA/fN/NAME.npy
SCENE_FIELDS = ("rgb", "intrinsics", "cam_to_world", "object_to_world", "tracks",
                "occluded", "query_frame", "track_object", "moving")  # held whole: a video's frames, small arrays
GA_ONLY = ["weights.cma=0", "weights.cts=0", "weights.pts=0"]


def make_scene(data: Path, frames: int, resolution: str) -> Path:
    """DATA/fN-HxW: one movi-e scene of `frames` frames (`c4d datagen`, made once), and its depth
    and segmentation as plain .npy beside the shard (`ON_DISK`, written once by another process)."""
    folder = data / f"f{frames}-{resolution}"
    if not list(folder.glob("*.tar")):
        subprocess.run([sys.executable, "-m", "c4d.cli", "datagen", "--preset", "movi-e", "--num-scenes", "1",
                        "--out", str(folder), "--resolution", resolution, "--frames", str(frames),
                        "--workers", "1", "--overwrite"], check=True)
    if not all((folder / f"{name}.npy").is_file() for name in ON_DISK):
        subprocess.run([sys.executable, __file__, "--unpack", str(folder)], check=True)
    return folder


def unpack(folder: str) -> None:
    """Write the scene's `ON_DISK` fields as FOLDER/NAME.npy (atomically)."""
    from c4d_pipeline.outputs import save_npy
    from datagen.shards import read_scenes

    scene = next(read_scenes(folder, fields=ON_DISK))
    for name in ON_DISK:
        save_npy(Path(folder) / f"{name}.npy", getattr(scene, name))


class FramesOnDisk:
    """A (T,H,W) array in an .npy file, read a frame at a time (`stack[t]`, a copy) and never held
    whole: what a network pointmap source holds of the scene's depth (nothing), where the
    ground-truth source that stands in for it needs depth and segmentation of the frames of each
    pair. The file is mapped for each read and unmapped after, so its pages do not stay in the
    process's resident memory."""

    def __init__(self, path: Path):
        import numpy as np

        self.path = path
        head = np.load(path, mmap_mode="r")
        self.shape, self.dtype = head.shape, head.dtype
        del head

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, t):
        import numpy as np

        if not isinstance(t, (int, np.integer)):
            raise TypeError("FramesOnDisk reads one frame at a time: index it with an int")
        return np.array(np.load(self.path, mmap_mode="r")[t])


def one_case(folder: str, overrides: list[str], preset: str, tracker: str = "") -> dict:
    """One reconstruction (windowed if `window.frames` > 0 in `overrides`) in this process, with
    the tracks of the DynPT checkpoint `tracker` (queried as `c4d run` queries: a grid on frame 0,
    `tracker.grid_size`) or, for "", the scene's own (`oracle_tracks`)."""
    import numpy as np

    from c4d_core.config import load_config
    from c4d_pipeline.eval_metrics import pose_metrics
    from c4d_pipeline.flow import build_flow
    from c4d_pipeline.ground_truth import GroundTruthPointmaps, oracle_tracks
    from c4d_pipeline.pipeline import reconstruct
    from c4d_pipeline.windows import reconstruct_windowed
    from datagen.shards import read_scenes

    start, cpu_start = time.perf_counter(), time.process_time()
    scene = replace(next(read_scenes(folder, fields=SCENE_FIELDS)),
                    **{name: FramesOnDisk(Path(folder) / f"{name}.npy") for name in ON_DISK})
    cfg = load_config("c4d", preset, overrides=overrides)
    source, flow = GroundTruthPointmaps.from_config(scene, cfg.gt_pointmaps), build_flow("dis")
    rss_inputs = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # GiB (ru_maxrss in KiB)
    track_start = time.perf_counter()
    if tracker:
        from dynpt.inference import load_tracker

        tracks = load_tracker(tracker, "cpu").track(scene.rgb, grid_size=cfg.tracker.grid_size, seed=int(cfg.seed))
    else:
        tracks = oracle_tracks(scene)
    track_s = time.perf_counter() - track_start
    with tempfile.TemporaryDirectory() as out:
        run = reconstruct_windowed if cfg.window.frames else reconstruct
        rec = run(scene.rgb, source, flow, tracks, cfg, out)
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    metrics = pose_metrics(rec.cam_to_world.astype(np.float64), scene.cam_to_world.astype(np.float64))
    return {"frames": scene.num_frames, "size": f"{scene.image_size[1]}x{scene.image_size[0]}",
            "overrides": overrides, "tracker": tracker or "oracle", "track_s": track_s, "wall_s": wall, "cpu_s": cpu, "rss_inputs_gib": rss_inputs,
            "rss_peak_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
            "windows": len(rec.report.get("windows", [])) or 1, "stage_seconds": rec.report["seconds"],
            **metrics}


def case(folder: Path, overrides: list[str], preset: str, repeats: int, label: str, tracker: str = "") -> dict:
    """Medians over `repeats` subprocesses of `one_case`."""
    runs = []
    for _ in range(repeats):
        cmd = [sys.executable, __file__, "--one", str(folder), preset, tracker, *overrides]
        out = subprocess.run(cmd, capture_output=True, text=True)
        if out.returncode:
            raise RuntimeError(f"{label}: {out.stderr[-2000:]}")
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    numbers = {k: statistics.median(r[k] for r in runs) for k, v in runs[0].items() if isinstance(v, float)}
    row = {**runs[0], **numbers, "label": label, "repeats": repeats}
    print(f"{label:28s} {row['frames']:5d} f  {row['windows']:3d} win  wall {row['wall_s']:8.1f} s  "
          f"cpu {row['cpu_s']:8.1f} s  peak {row['rss_peak_gib']:.2f} GiB (inputs {row['rss_inputs_gib']:.2f})  "
          f"ATE {row['ate']:.4f}  RPE t {row['rpe_trans']:.4f} r {row['rpe_rot']:.3f}", flush=True)
    return row


def plot(rows: list[dict], path: Path) -> None:
    """Peak RSS, wall and CPU time against frames of the windowed C4D runs (and the whole-video runs)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (mem, wall) = plt.subplots(1, 2, figsize=(10, 4))
    for label, marker in (("C4D windows", "o-"), ("C4D whole video", "s")):
        sel = sorted((r for r in rows if r["label"] == label), key=lambda r: r["frames"])
        if sel:
            frames = [r["frames"] for r in sel]
            mem.plot(frames, [r["rss_peak_gib"] for r in sel], marker, label=f"{label}: peak RSS")
            wall.plot(frames, [r["wall_s"] / 60 for r in sel], marker, label=f"{label}: wall")
            wall.plot(frames, [r["cpu_s"] / 60 for r in sel], marker.replace("-", "--"), label=f"{label}: CPU")
            if label == "C4D windows":
                mem.plot(frames, [r["rss_peak_gib"] - r["rss_inputs_gib"] for r in sel], "o--",
                         label=f"{label}: peak RSS - inputs")
    mem.set(xlabel="frames", ylabel="GiB", title="peak memory", ylim=(0, None))
    wall.set(xlabel="frames", ylabel="minutes", title="time (2 CPU cores shared with other jobs)", ylim=(0, None))
    for ax in (mem, wall):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[90, 180, 360])
    parser.add_argument("--baseline-frames", type=int, default=90, help="frames of the whole-video and GA-only runs (0: none)")
    parser.add_argument("--window", type=int, default=30)
    parser.add_argument("--overlap", type=int, default=10)
    parser.add_argument("--preset", default="tiny", help="c4d preset of every run [tiny]")
    parser.add_argument("--resolution", default="192x256", help="HxW of the generated scenes")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--tracker", default="", help="a DynPT checkpoint: its tracks (grid on frame 0, as `c4d run` "
                        "queries) instead of the scene's own; its time and memory are in the case's")
    parser.add_argument("--data", type=Path, default=Path("runs/bench_c4d_long"))
    parser.add_argument("--json", type=Path, help="write the rows here")
    parser.add_argument("--plot", type=Path, help="write the memory / time plot here (PNG)")
    parser.add_argument("--cases", nargs="+", metavar="LABEL", help="run only these cases, e.g. 'GA only windows'")
    parser.add_argument("--summarise", action="store_true", help="run nothing: the ratios and plot of --json's rows")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="c4d config overrides of every run")
    parser.add_argument("--one", nargs="+", help=argparse.SUPPRESS)
    parser.add_argument("--unpack", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.unpack:
        unpack(args.unpack)
        return 0
    if args.one:
        print(json.dumps(one_case(args.one[0], args.one[3:], args.one[1], args.one[2])))
        return 0
    windows = [f"window.frames={args.window}", f"window.overlap={args.overlap}"]
    print(f"commit {this_commit()}, load average {load_average()}, preset {args.preset}, "
          f"windows of {args.window} overlapping by {args.overlap}", flush=True)
    rows = json.loads(args.json.read_text())["rows"] if args.summarise else []
    plan = [] if args.summarise else [
        *(((args.baseline_frames, overrides, label) for overrides, label in (
            ([], "C4D whole video"), (GA_ONLY, "GA only whole video"), ([*GA_ONLY, *windows], "GA only windows")))
          if args.baseline_frames else ()),
        *((frames, windows, "C4D windows") for frames in args.frames)]
    for frames, overrides, label in (c for c in plan if not args.cases or c[2] in args.cases):
        folder = make_scene(args.data, frames, args.resolution)
        rows.append(case(folder, [*overrides, *args.overrides], args.preset, args.repeats, label, args.tracker))
        if args.json:  # after every case: a long run that is stopped keeps what it measured
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps({"commit": this_commit(), "rows": rows}, indent=1))
    win = sorted((r for r in rows if r["label"] == "C4D windows"), key=lambda r: r["frames"])
    for r in win:
        first = win[0]
        print(f"windows, {r['frames']} frames against {first['frames']}: peak RSS {r['rss_peak_gib'] / first['rss_peak_gib']:.2f}x "
              f"(above the inputs {(r['rss_peak_gib'] - r['rss_inputs_gib']) / (first['rss_peak_gib'] - first['rss_inputs_gib']):.2f}x), "
              f"wall {r['wall_s'] / first['wall_s']:.2f}x, CPU {r['cpu_s'] / first['cpu_s']:.2f}x for "
              f"{r['frames'] / first['frames']:.2f}x the frames")
    whole = next((r for r in rows if r["label"] == "C4D whole video"), None)
    same = next((r for r in win if whole and r["frames"] == whole["frames"]), None)
    if same:
        print(f"at {whole['frames']} frames, windows / whole video: ATE {same['ate'] / whole['ate']:.3f}x, "
              f"peak RSS {same['rss_peak_gib'] / whole['rss_peak_gib']:.2f}x, wall {same['wall_s'] / whole['wall_s']:.2f}x")
    print(f"load average at the end {load_average()}")
    if args.plot:
        plot(rows, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
