"""`c4d demo`: the whole chain on a small generated dataset, in minutes on a CPU.

    data ─► train ─► eval ─► paper-eval ─► recon-data ─► reconstruct ─► pictures ─► OUT/summary.md

1. generate train and held-out val sets (configs/demo: movi-e and movi-e-panning, small size);
2. train the tiny DynPT config on the CPU;
3. evaluate D-ACC and TAP-Vid metrics on the val sets next to the zero-motion baseline
   ("everything static"), so the numbers mean something; then (paper-eval, unless
   `eval.paper_scenes` is 0) render the first val scenes again with 24 frames at 256x256 and score
   them by the paper's D-ACC protocol;
4. render the first `recon.num_scenes` val scenes of `recon.preset` again at `recon.resolution`
   (the same scenes: only the size changes; recon-data), reconstruct each there with C4D
   (ground-truth-source pointmaps with the static-world bias, DIS flow, the trained tracker) and
   with GA only, and score both against the truth;
5. draw the pictures (dataset report, track overlay, reconstruction report).
Each step writes OUT/<step>/ and a record OUT/<step>/done.json; a step whose record exists is
skipped, so re-running the command resumes (refused into a folder of another demo config, or past
reconstructions made with other C4D settings than `recon.config` gives now). OUT/summary.md gathers every number and file. The
records name files relative to OUT, so a moved or copied OUT resumes from its own files (an
older record's absolute or working-directory-relative paths are found inside OUT by their tail).
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import time
from itertools import islice
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from c4d.cli import run_subcommand
from c4d_core.config import changed_keys, load_config, to_dict, to_yaml
from c4d_core.errors import UserError
from c4d_core.files import write_json, write_text
from c4d_core.ownership import output_folder
from c4d_core.system import configure_threads

log = logging.getLogger("c4d.demo")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default: demo_out)")
    parser.add_argument("--quick", action="store_true",
                        help="toy sizes (configs/demo/quick.yaml): a few minutes, used by CI")
    parser.add_argument("--config", action="append", default=[], help="extra YAML merged over the preset")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="e.g. train.steps=200")


def _c4d(*argv) -> None:
    """Run one `c4d` subcommand in this process (its errors propagate), then take back this
    process's threads: a subcommand that starts workers leaves fewer (`c4d datagen --workers 2`:
    one, on which the paper-eval step's tracking after its rendering ran 1.7x slower)."""
    argv = [str(a) for a in argv]
    log.info("$ c4d %s", " ".join(argv))
    try:
        run_subcommand(argv)
    finally:
        configure_threads()


class Demo:
    """The demo's steps over one output folder; each returns the numbers it wants summarised."""

    def __init__(self, cfg, out: Path):
        self.cfg, self.out = cfg, out
        self.val_dirs = {p: out / "data" / "val" / p for p in cfg.data.presets}
        self.train_dirs = {p: out / "data" / "train" / p for p in cfg.data.presets}

    # -- bookkeeping
    def stored(self, path: Path) -> str:
        """`path` (inside OUT) as a record names it: relative to OUT, with '/'."""
        return Path(path).relative_to(self.out).as_posix()

    def located(self, stored: str) -> Path:
        """The file a record names: `stored` relative to OUT; in an older record (an absolute
        path, or one relative to the directory the demo ran in) the longest tail of it that
        exists inside OUT, never the original folder's file. None there: a `UserError` naming
        the record (the user never passed that path)."""
        parts = Path(stored).parts
        for start in range(1 if Path(stored).is_absolute() else 0, len(parts)):
            candidate = self.out.joinpath(*parts[start:])
            if candidate.exists():
                return candidate
        raise UserError(f"the demo's step records in {self.out} name {stored}, which is not in "
                        f"{self.out} (moved or deleted); delete the folder of the step that wrote "
                        "it (train/ or reconstruct/ there) and rerun the demo to redo that step")

    def render(self, preset: str, split: str, count: int, target: Path, resolution, frames: int) -> None:
        """`c4d datagen` of the first `count` scenes of `preset`'s `split` set into `target`, at
        `resolution` (H, W) with `frames` frames. The seed is the split's (the val sets use seed +
        1000), so a val scene rendered again at another size or length is the same scene there."""
        seed = self.cfg.seed + (1000 if split == "val" else 0)
        d = self.cfg.data
        _c4d("datagen", "--preset", preset, "--num-scenes", count, "--out", target, "--split", split,
             "--seed", seed, "--resolution", "x".join(str(v) for v in resolution), "--frames", frames,
             "--scenes-per-shard", d.scenes_per_shard, "--workers", d.workers)

    def claim_folder(self) -> None:
        """Refuse to resume into a folder made with another demo config."""
        record = self.out / "demo-config.yaml"
        if record.exists() and yaml.safe_load(record.read_text()) != to_dict(self.cfg):
            raise UserError(f"{self.out} holds a demo made with another config; use another --out "
                            f"or delete the folder (see {record})")
        write_text(record, to_yaml(self.cfg))

    def check_reconstruction_settings(self, record: dict) -> None:
        """Refuse to go on from a reconstruct step made with other C4D settings than
        `recon.config` gives now (a c4d config file, whose values `claim_folder`'s record does not
        hold; a newer checkout may ship others): the reconstructions, their pictures and the
        summary would describe settings the command no longer runs. Read from the C4D run's own
        report of the first scene, which every demo folder has."""
        r = self.cfg.recon
        report = self.located(record["outputs"]["scene-000"]["C4D"]) / "report.json"
        made = json.loads(report.read_text())["config"]
        now = json.loads(json.dumps(to_dict(self.recon_config("C4D"))))  # as report.json holds it
        changed = changed_keys(made, now)
        if changed:
            shown = ", ".join(f"{key} {_dotted(made, key)!r} -> {_dotted(now, key)!r}" for key in changed[:4])
            more = f" and {len(changed) - 4} more" if len(changed) > 4 else ""
            raise UserError(f"{self.out / 'reconstruct'} was made with other C4D settings than "
                            f"recon.config {r.config!r} gives now ({shown}{more}); delete "
                            f"{self.out / 'reconstruct'} and {self.out / 'pictures'} to redo those "
                            "steps with them, or use another --out")

    def recon_config(self, variant: str):
        """The c4d config of one reconstruction variant (a row of the ablation table: "C4D",
        "GA only"): `recon.config` with `recon.overrides`, then the variant's own."""
        from c4d_pipeline.ablation import RUNS

        r = self.cfg.recon
        return load_config("c4d", r.config, overrides=[*r.overrides, *RUNS[variant]])

    def run_step(self, name: str, step: Callable[[Path], dict]) -> dict:
        folder = self.out / name
        done = folder / "done.json"
        if done.exists():
            log.info("[%s] done before, skipped (delete %s to redo it)", name, folder)
            return json.loads(done.read_text())
        log.info("[%s] ...", name)
        folder.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        record = step(folder)
        record["seconds"] = round(time.perf_counter() - start, 1)
        write_json(done, record)
        log.info("[%s] finished in %.0f s", name, record["seconds"])
        return record

    # -- 1. data
    def data(self, folder: Path) -> dict:
        d = self.cfg.data
        for split, dirs, count in (("train", self.train_dirs, d.train_scenes),
                                   ("val", self.val_dirs, d.val_scenes)):
            for preset, target in dirs.items():
                self.render(preset, split, count, target, d.resolution, d.frames)
        return {"train": {p: self.stored(v) for p, v in self.train_dirs.items()},
                "val": {p: self.stored(v) for p, v in self.val_dirs.items()},
                "scenes_per_preset": {"train": d.train_scenes, "val": d.val_scenes},
                "resolution": list(d.resolution), "frames": d.frames}

    # -- 2. train
    def train(self, folder: Path) -> dict:
        from dynpt.train import latest_checkpoint

        t = self.cfg.train
        sources = "[" + ",".join(str(p) for p in self.train_dirs.values()) + "]"
        total_batch = load_config("dynpt", t.config, overrides=list(t.overrides)).train.total_batch
        args = ["train", "--config", t.config, f"data.sources={sources}", f"train.steps={t.steps}",
                f"train.out_dir={folder}", "eval.every=0", "--nproc-per-node", t.processes,
                f"train.batch_size={max(1, total_batch // t.processes)}", *t.overrides]
        if latest_checkpoint(folder) is not None:
            args.append("--resume")
        _c4d(*args)
        checkpoint = latest_checkpoint(folder)
        return {"checkpoint": self.stored(checkpoint), "config": t.config, "steps": t.steps,
                "processes": t.processes, "overrides": list(t.overrides),
                "log": self.stored(folder / "log.jsonl")}

    # -- 3. eval
    def eval(self, folder: Path, checkpoint: str) -> dict:
        """The tracker and the all-static baseline on the val sets at the demo's size, the
        scenes' own tracks queried at their first visible frame."""
        eval_cfg = load_config("dynpt", self.cfg.train.config, overrides=[
            f"eval.num_tracks={self.cfg.eval.num_tracks}", "eval.num_scenes=0",
            f"eval.resolution=[{self.cfg.data.resolution[0]},{self.cfg.data.resolution[1]}]",
            *self.cfg.eval.overrides, "eval.mobility=epipolar"]).eval  # last: the post-processed row always fuses
        results = _score(checkpoint, self.val_dirs, eval_cfg)
        write_json(folder / "eval.json", results)
        return {"results": results, "file": self.stored(folder / "eval.json"),
                "overrides": list(self.cfg.eval.overrides)}

    # -- 3b. the paper's D-ACC protocol
    def paper_eval(self, folder: Path, checkpoint: str) -> dict:
        """The first `eval.paper_scenes` val scenes of each preset rendered again with the
        paper's 24 frames at `eval.paper_resolution` (the same seeds and indices; 256x256 as the
        paper), scored as `c4d eval --protocol c4d-paper` scores them (dynpt/evaluate.py)."""
        from dynpt.evaluate import PAPER_FRAMES

        e, d = self.cfg.eval, self.cfg.data
        dirs = {p: folder / p for p in d.presets}
        for preset, target in dirs.items():
            self.render(preset, "val", e.paper_scenes, target, e.paper_resolution, PAPER_FRAMES)
        results = _score(checkpoint, dirs, paper_eval_config(self.cfg))
        write_json(folder / "eval.json", results)
        return {"results": results, "file": self.stored(folder / "eval.json"),
                "scenes_per_preset": e.paper_scenes, "resolution": list(e.paper_resolution),
                "overrides": list(e.paper_overrides)}

    # -- 4a. the reconstructed val scenes, rendered again at the reconstruction's size
    def recon_data(self, folder: Path) -> dict:
        """The first `recon.num_scenes` scenes of the `recon.preset` val set rendered again at
        `recon.resolution`: the data step's command with the same preset, split, seed and frames
        (a scene's content comes from the seed and its index alone, see datagen.generate), so
        they are the same scenes at another size. At the val set's own size: that set."""
        r, d = self.cfg.recon, self.cfg.data
        if list(r.resolution) == list(d.resolution):
            return {"source": self.stored(self.val_dirs[r.preset]), "resolution": list(d.resolution),
                    "rendered": False}
        target = folder / r.preset
        self.render(r.preset, "val", r.num_scenes, target, r.resolution, d.frames)
        return {"source": self.stored(target), "resolution": list(r.resolution), "rendered": True}

    # -- 4b. reconstruct
    def reconstruct(self, folder: Path, checkpoint: str, source: Path) -> dict:
        from c4d_pipeline.eval_recon import evaluate
        from c4d_pipeline.flow import build_flow
        from c4d_pipeline.outputs import read_reconstruction
        from c4d_pipeline.pipeline import Reused, reconstruct
        from c4d_pipeline.pointmap_sources import build_pointmaps
        from datagen.shards import read_scenes
        from dynpt.inference import load_tracker

        r = self.cfg.recon
        scenes = list(islice(read_scenes(source), r.num_scenes))
        if len(scenes) < r.num_scenes:
            raise UserError(f"recon.num_scenes={r.num_scenes} but {source} holds {len(scenes)} scenes; "
                            f"lower recon.num_scenes or raise data.val_scenes")
        tracker = load_tracker(checkpoint)
        metrics, outputs, seconds = {}, {}, {}
        for index, scene in enumerate(scenes):
            cpu = time.process_time()
            track_result = tracker.track(scene.rgb)
            name = f"scene-{index:03d}"
            metrics[name], outputs[name] = {}, {}
            base = load_config("c4d", r.config, overrides=list(r.overrides))
            # the same pointmaps and flow for both runs, computed once
            pointmaps, flow = Reused(build_pointmaps("gt", base, scene=scene)), Reused(build_flow(r.flow))
            for variant in ("C4D", "GA only"):  # rows of the ablation table (their overrides)
                cfg = self.recon_config(variant)
                target = folder / name / variant.lower().replace(" ", "-")
                reconstruct(scene.rgb, pointmaps, flow, track_result, cfg, target,
                            inputs={"scene": f"{source} #{index}",
                                    "pointmaps": "ground truth + noise + static-world bias",
                                    "tracker": checkpoint})
                metrics[name][variant] = evaluate(read_reconstruction(target), scene)
                outputs[name][variant] = self.stored(target)
            seconds[name] = round(time.process_time() - cpu, 1)
        write_json(folder / "metrics.json", metrics)
        return {"source": self.stored(source), "metrics": metrics, "outputs": outputs,
                "resolution": list(scenes[0].image_size), "frames": scenes[0].num_frames,
                "cpu_seconds": seconds, "flow": r.flow}

    # -- 5. pictures
    def pictures(self, folder: Path, recon_dir: str, checkpoint: str, recon_source: Path) -> dict:
        _c4d("inspect", recon_source, "--out", folder / "dataset")  # the scenes as reconstructed
        _c4d("inspect", recon_dir, "--out", folder / "reconstruction",
             "--gt", recon_source, "--scene-index", 0,
             "--compare", f"GA only={Path(recon_dir).parent / 'ga-only'}")
        _c4d("track", Path(recon_dir) / "frames", "--ckpt", checkpoint, "--out", folder / "tracks")
        readme = readme_pictures(folder)
        return {"dataset_report": self.stored(folder / "dataset" / "index.html"),
                "reconstruction_report": self.stored(folder / "reconstruction" / "index.html"),
                "track_overlay": self.stored(folder / "tracks" / "overlay.mp4"),
                "readme_pictures": f"{self.stored(readme)}/{{dataset_sheet,tracks,trajectory}}.png",
                "scene": f"{self.stored(recon_source)} #0 (the first reconstructed scene)"}


def _dotted(nested: dict, key: str):
    """The value at a dotted key of a plain config (None where it has no such key)."""
    for part in key.split("."):
        nested = nested.get(part) if isinstance(nested, dict) else None
    return nested


def readme_pictures(pictures: Path) -> Path:
    """The README's pictures of the first reconstructed val scene, into `pictures/readme/`
    (`make readme-pictures` copies them to docs/images/ and adds the 4D view, drawn by `c4d view
    --screenshot`): its contact sheet, three frames of the track overlay (first, middle, and of
    the others the frame with the most visible points predicted moving) and the camera trajectory."""
    from c4d_core.draw import MOVING_THRESHOLD, side_by_side
    from c4d_core.video import read_video, write_image

    out = pictures / "readme"
    out.mkdir(parents=True, exist_ok=True)
    sheet = sorted((pictures / "dataset" / "scenes").glob("*/sheet.png"))[0]  # the first val scene
    shutil.copyfile(sheet, out / "dataset_sheet.png")
    shutil.copyfile(pictures / "reconstruction" / "trajectory.png", out / "trajectory.png")
    overlay = read_video(pictures / "tracks" / "overlay.mp4")
    with np.load(pictures / "tracks" / "tracks.npz") as tracks:
        moving = ((tracks["moving"] > MOVING_THRESHOLD) & tracks["visible"]).sum(axis=1)  # (T,) red dots
    first, middle = 0, len(overlay) // 2
    moving[[first, middle]] = -1  # the third panel is a third frame even when one of these has the most
    most = int(moving.argmax())
    frames = sorted({first, middle, most})
    labels = [f"frame {t}" + (", most moving" if t == most else "") for t in frames]
    write_image(out / "tracks.png", side_by_side([overlay[t] for t in frames], labels))
    return out


def paper_eval_config(cfg):
    """The dynpt `eval` config the paper-eval step scores with, for demo config `cfg`: the paper's
    protocol, `eval.paper_overrides`, and the fused mobility last (so the post-processed row always
    fuses, whatever the overrides say). `benchmarks/mobility_cue.py` post-processes as it says."""
    return load_config("dynpt", cfg.train.config, overrides=[
        "eval.protocol=c4d-paper", "eval.num_scenes=0", *cfg.eval.paper_overrides,
        "eval.mobility=epipolar"]).eval


def _score(checkpoint: str, sources: dict[str, Path], eval_cfg) -> dict:
    """preset -> the summaries of the tracker as its network gives it ("dynpt"), post-processed
    as `eval_cfg` says (dynpt/postprocess.py, on the same tracking pass: "dynpt_epipolar" the
    head fused with the tracks' epipolar geometry, "dynpt_refined" that on tracks refined by
    Lucas-Kanade first) and of the all-static baseline on `sources[preset]`, and the 95 %
    intervals of the D-ACC differences from the baseline, evaluated as `eval_cfg` says."""
    from dynpt.baselines import ZeroMotionBaseline
    from dynpt.evaluate import (d_acc_difference_interval, evaluate_items, load_source,
                                protocol_query_mode, score_items, track_item)
    from dynpt.inference import load_tracker
    from dynpt.postprocess import Postprocess

    tracker, mode = load_tracker(checkpoint), protocol_query_mode(eval_cfg)
    post = Postprocess.from_config(eval_cfg)
    post_key = "dynpt_refined" if post.refinement is not None else "dynpt_epipolar"
    results = {}
    for preset, source in sources.items():
        items, _ = load_source(str(source), eval_cfg)
        tracked = [track_item(tracker, item, mode) for item in items]
        ours = score_items(items, tracked, mode)
        processed = score_items(items, [None if t is None else (*t[:2], post(t[2], item["video"]))
                                        for item, t in zip(items, tracked)], mode)
        baseline = evaluate_items(ZeroMotionBaseline(), items, mode)
        results[preset] = {"dynpt": ours["summary"], post_key: processed["summary"],
                           "zero_motion": baseline["summary"],
                           interval_key("dynpt"): d_acc_difference_interval(ours, baseline),
                           interval_key(post_key): d_acc_difference_interval(processed, baseline)}
    return results


def _num(value) -> str:
    return "n/a" if value is None else f"{value:.4f}"


def _recon_cells(m: dict) -> list:
    """ATE, RPE trans, RPE rot, Abs Rel, delta<1.25, mask IoU of one eval-recon result."""
    pose, depth = m["pose"], m.get("depth", {}).get("scale_shift", {})
    return [pose["ate"], pose["rpe_trans"], pose["rpe_rot"], depth.get("abs_rel"),
            depth.get("delta_1_25"), m.get("mask", {}).get("iou")]


def _pct(value) -> str:
    return "n/a" if value is None else f"{100 * value:.1f}"


TRACKER_ROWS = {"dynpt": "DynPT (trained here)",  # records' key -> row name
                "dynpt_epipolar": "DynPT, head + epipolar mobility",
                "dynpt_refined": "DynPT, LK-refined tracks, head + epipolar mobility"}


def interval_key(variant: str, metric: str = "d_acc") -> str:
    """The records' key of the 95 % interval of `variant`'s (a key of TRACKER_ROWS) `metric`
    difference from the baseline: 'd_acc_interval' for the head's, 'dynpt_epipolar_d_acc_interval'."""
    return f"{metric}_interval" if variant == "dynpt" else f"{variant}_{metric}_interval"


def _tracker_verdict(results: dict, variant: str = "dynpt") -> list[str]:
    """One line per metric saying, in points, whether the tracker (`variant`, a key of
    TRACKER_ROWS) beats the zero-motion baseline. Where the 95 % interval of the difference over
    the val scenes is known (D-ACC), "yes" only when every val set's interval is above 0, "no"
    when all are below, otherwise that the difference is within the scene-to-scene variation;
    without intervals, by the sign of the differences. AJ only for rows with their own tracks
    (not "dynpt_epipolar": the network's tracks)."""
    from dynpt.evaluate import interval_verdict, signed

    metrics = [("d_acc", "D-ACC"), ("d_acc_balanced", "balanced D-ACC")]
    metrics += [("average_jaccard", "AJ")] if variant != "dynpt_epipolar" else []
    lines = []
    for key, label in metrics:
        diffs = {p: 100 * (r[variant][key] - r["zero_motion"][key]) for p, r in results.items()}
        text = ", ".join(f"{p} {signed(d)}" for p, d in diffs.items()) + " points"
        intervals = {p: r[interval_key(variant, key)] for p, r in results.items()
                     if interval_key(variant, key) in r}
        if intervals:
            text += "; 95 % interval over the val scenes: " + ", ".join(
                f"{p} {signed(100 * low)} to {signed(100 * high)}" for p, (low, high) in intervals.items())
            verdicts = {interval_verdict(low, high) for low, high in intervals.values()}
            verdict = ("yes" if verdicts == {"above"} else "no" if verdicts == {"below"}
                       else "within the scene-to-scene variation")
        else:
            verdict = "yes" if all(d > 0 for d in diffs.values()) else "no"
        name = "DynPT" if variant == "dynpt" else TRACKER_ROWS[variant]
        lines.append(f"- {name} above the baseline on {label}: **{verdict}** ({text})")
    return lines


def _tracker_table(results: dict) -> list[str]:
    """The tracker's rows (as its network gives it, and post-processed where the records have
    it) and the baseline's per val set (percent), then the verdicts."""
    keys = ("d_acc", "d_acc_moving", "d_acc_static", "d_acc_balanced", "moving_ap",
            "average_jaccard", "average_pts_within_thresh", "occlusion_accuracy")
    lines = ["| val set | tracker | D-ACC | D-ACC moving | D-ACC static | D-ACC balanced | AP moving "
             "| AJ | <δ avg | OA |", "|---|---|---|---|---|---|---|---|---|---|"]
    variants = [v for v in TRACKER_ROWS if all(v in r for r in results.values())]
    for preset, result in results.items():
        for name, s in [*((TRACKER_ROWS[v], result[v]) for v in variants),
                        ("zero motion, all static", result["zero_motion"])]:
            lines.append(f"| {preset} | {name} | " + " | ".join(_pct(s.get(k)) for k in keys) + " |")
    verdicts = [line for v in variants for line in _tracker_verdict(results, v)]
    return [*lines, "", *verdicts]


def summary_markdown(records: dict) -> str:
    """OUT/summary.md: every number of the run and where each file is."""
    lines = ["# c4d demo summary", "", "Files are named relative to this folder.", "",
             "| step | seconds |", "|---|---|"]
    lines += [f"| {name} | {rec['seconds']} |" for name, rec in records.items()]
    data = records["data"]
    lines += ["", "## Data", "",
              f"{data['scenes_per_preset']['train']} train and {data['scenes_per_preset']['val']} "
              f"held-out val scenes per preset, {data['frames']} frames at "
              f"{data['resolution'][0]}x{data['resolution'][1]}: " +
              ", ".join(f"`{p}`" for p in (*data["train"].values(), *data["val"].values())), "",
              "## Tracker (held-out val scenes, 'first' queries)", "",
              *_tracker_table(records["eval"]["results"])]
    if records["eval"].get("overrides"):
        lines += ["", "Scored with `" + " ".join(records["eval"]["overrides"]) + "` (demo config "
                  "eval.overrides)."]
    paper = records.get("paper-eval")
    if paper:
        size = "x".join(str(v) for v in paper["resolution"])
        lines += ["", "## Tracker, the paper's D-ACC protocol", "",
                  f"The first {paper['scenes_per_preset']} val scenes of each preset rendered again "
                  f"with 24 frames at {size} (step paper-eval), scored as `c4d eval --protocol "
                  "c4d-paper` does: 256 tracks a video drawn as TAP-Vid-Kubric draws them, at "
                  "256x256 (docs/RESULTS.md section 4.1 puts the paper's figures beside these).", "",
                  *_tracker_table(paper["results"])]
        if paper.get("overrides"):
            lines += ["", "Scored with `" + " ".join(paper["overrides"]) + "` (demo config "
                      "eval.paper_overrides)."]
    rec = records["reconstruct"]
    train = records["train"]
    overrides = " ".join(train.get("overrides", [])) or "none"
    size = "x".join(str(v) for v in rec.get("resolution", ())) or "the val set's size"
    rendered = records.get("recon-data", {}).get("rendered")
    cpu = rec.get("cpu_seconds", {})
    processes = train.get("processes", 1)
    lines += ["", f"Tracker: `{train['config']}` trained {train['steps']} steps"
              f"{f' on {processes} processes' if processes > 1 else ''} (overrides: "
              f"`{overrides}`); checkpoint `{train['checkpoint']}`; training log `{train['log']}`.", "",
              f"## Reconstruction of the first {len(rec['metrics'])} scenes of {rec['source']}", "",
              (f"The first {len(rec['metrics'])} val scenes rendered again at {size} (the same scenes, "
               "only the size changed; step recon-data), " if rendered else f"At {size}, ") +
              f"{rec.get('frames', data['frames'])} frames. "
              "Pointmaps: ground truth with noise and the static-world bias (a stand-in for a "
              "DUSt3R-family network, see docs/RESULTS.md); flow: "
              f"`{rec.get('flow', 'dis')}` from the frames (c4d_pipeline/flow.py); tracker: the one "
              "trained above, on these frames." + (f" CPU seconds per scene (tracking, C4D and GA only): "
              + ", ".join(f"{v:.0f}" for v in cpu.values()) + "." if cpu else ""), "",
              "| scene | method | ATE | RPE trans | RPE rot (deg) | depth Abs Rel | δ<1.25 | mask IoU |",
              "|---|---|---|---|---|---|---|---|"]
    rows = {variant: [] for variant in ("C4D", "GA only")}
    for scene, by_variant in rec["metrics"].items():
        for variant, m in by_variant.items():
            rows[variant].append(_recon_cells(m))
            lines.append(f"| {scene} | {variant} | " + " | ".join(_num(c) for c in rows[variant][-1]) + " |")
    for variant, cells in rows.items():
        mean = [None if any(c[k] is None for c in cells) else sum(c[k] for c in cells) / len(cells)
                for k in range(len(cells[0]))]
        lines.append(f"| mean | {variant} | " + " | ".join(_num(c) for c in mean) + " |")
    wins = sum(c[0] < g[0] for c, g in zip(rows["C4D"], rows["GA only"]))
    lines += ["", f"C4D has the lower ATE than GA only in {wins} of {len(rows['C4D'])} scenes. Both "
              "runs write the same motion masks (from the tracker and the flow, computed before the "
              "optimisation, which GA only does not use), hence the same mask IoU."]
    masks = [m["C4D"].get("mask", {}) for m in rec["metrics"].values()]
    pairs = [(m["iou"], m["gt_dynamic_fraction"]) for m in masks if m.get("iou") is not None
             and m.get("gt_dynamic_fraction") is not None]
    if pairs:
        mean_iou, mean_share = (sum(v) / len(pairs) for v in zip(*pairs))
        verdict = ("near chance, so these masks say little yet; read ATE and depth instead"
                   if max(iou for iou, _ in pairs) < 0.2 else
                   f"{mean_iou / max(mean_share, 1e-9):.1f} times the baseline on average; "
                   "the reconstruction report's mask_errors.png shows where each mask errs")
        lines += ["", "Mask IoU " + ", ".join(f"{iou:.2f}" for iou, _ in pairs) + f" (mean {mean_iou:.2f})"
                  " against " + ", ".join(f"{share:.2f}" for _, share in pairs) + f" (mean {mean_share:.2f})"
                  f" for marking every pixel dynamic (the share of moving pixels): {verdict}."]
    lines += ["", f"Outputs: `{Path(rec['outputs']['scene-000']['C4D']).parent.parent}/scene-NNN/{{c4d,ga-only}}`", "",
              "## Pictures", ""]
    pictures = records["pictures"]
    lines += [f"- {k.replace('_', ' ')}: `{v}`" for k, v in pictures.items()
              if k not in ("seconds", "scene")]
    if "scene" in pictures:
        lines.append(f"- the track overlay and the reconstruction report show {pictures['scene']}")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    cfg = load_config("demo", "quick" if args.quick else "default", args.config, args.overrides)
    with output_folder(args.out, "demo", args.overwrite):
        return _run_demo(Demo(cfg, args.out))


def _run_demo(demo: Demo) -> int:
    """Every step of `demo` (each resumed if done), then its summary."""
    demo.claim_folder()
    records = {"data": demo.run_step("data", demo.data)}
    records["train"] = demo.run_step("train", demo.train)
    checkpoint = str(demo.located(records["train"]["checkpoint"]))
    records["eval"] = demo.run_step("eval", lambda f: demo.eval(f, checkpoint))
    if demo.cfg.eval.paper_scenes:
        records["paper-eval"] = demo.run_step("paper-eval", lambda f: demo.paper_eval(f, checkpoint))
    records["recon-data"] = demo.run_step("recon-data", demo.recon_data)
    recon_source = demo.located(records["recon-data"]["source"])
    records["reconstruct"] = demo.run_step("reconstruct", lambda f: demo.reconstruct(f, checkpoint, recon_source))
    demo.check_reconstruction_settings(records["reconstruct"])
    recon_dir = str(demo.located(records["reconstruct"]["outputs"]["scene-000"]["C4D"]))
    records["pictures"] = demo.run_step("pictures", lambda f: demo.pictures(f, recon_dir, checkpoint, recon_source))
    summary = write_text(demo.out / "summary.md", summary_markdown(records))
    print(summary.read_text())
    print(f"wrote {summary}")
    return 0
