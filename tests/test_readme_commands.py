"""Every command line of README.md, docs/*.md and docs/results/*.md runs as written, at toy sizes,
or is listed in `NOT_RUN` with the reason.

The lines come from the documents' ```bash blocks (backslash continuations joined, comments
dropped) and run in document order in an empty folder per document holding only a link to the
repository's `configs/` (so `--config configs/dynpt/tiny-cpu.yaml` resolves as in a clone's
root); `.venv/bin/c4d` is `c4d`, paths under `/tmp/` are under that folder, and a `printf ... >
FILE` line runs in bash. The documented mapping from "as written" to "at toy sizes here":

- sizes: `c4d datagen` gets `--num-scenes 4 --workers 1 --resolution 32x32 --frames 12`;
  training, evaluation and reconstruction lines get the key=value overrides of `TOY` appended
  (later overrides win, so the line's own keys are still parsed and checked);
- `torchrun --nproc_per_node 8` runs 2 processes (`python -m torch.distributed.run`);
- placeholders for the user's own files (`_placeholders`): `video.mp4` is the first val scene as
  a video, a DUSt3R checkpoint is a tiny official-layout network whose points lie in front of the
  camera (`test_c4d_run.tiny_network`; a few steps of `c4d pretrain-pointmaps` do not give one),
  TAP-Vid pickles are toy ones, Kubric's TFDS records (`tfds/NAME/CONFIG/VERSION:SPLIT`) are
  records of the first two toy movi-e-64 scenes written from the format's facts
  (tests/foreign_writers.py), `data.sources=[...]` is the first train set, CoTracker3's
  released file (`cotracker3:weights/scaled_offline.pth`) is one in its released layout and size
  with random weights (tests/cotracker3_layout.py);
- `[a|b]` optional groups are taken with their first alternative;
- not run here: the lines `NOT_RUN` matches, each with its reason (a fast test checks that every
  line is either run or listed, so a new line needs one or the other).
A line whose input a later line makes (the docs are not always in dependency order) is retried
after the others; what still fails is reported with its one-line error.

README.md's lines are also held to what the README says they give: `OUTCOMES` maps a pattern of
a README line to a check of what that line wrote or printed in the toy run (the files it names,
`c4d eval` scoring every video of the toy data into --out, a checkpoint continued by --resume),
and a line the README shows being refused (`Refused`) must end in exit code 2 with the one line
that says why; those run after all the others, so the folder they would write into exists. A
fast test fails if a README line that is run here has no check: a new line needs one or an entry
in `NO_OUTCOME` with the reason. What the README states that a toy run cannot show (time, disk,
memory and scores at full size) is measured in docs/PERFORMANCE.md, "README lines: what they
cost", not here; the figures README.md and docs/RESULTS.md give for `make demo` are held to that
run's records (docs/results/demo/) by tests/test_docs_figures.py.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import pickle
import re
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import pytest
import torch

from c4d.cli import SUBCOMMANDS, main
from test_c4d_run import ARGS, tiny_network

ROOT = Path(__file__).resolve().parents[1]

TOY = {
    "train": ["train.steps=4", "train.stop_after=2", "train.ckpt_every=2", "train.log_every=1",
              "train.total_batch=2", "train.batch_size=1", "data.num_frames=4",
              "data.crop_size=[32,32]", "model.resolution=[32,32]", "data.num_tracks=8",
              "data.num_workers=0", "eval.every=2", "eval.num_scenes=1", "eval.num_tracks=8",
              "eval.resolution=[32,32]", "model.encoder_3d.layers=[0,1]"],
    "pretrain-pointmaps": ["train.steps=4", "train.batch_size=2", "train.ckpt_every=2",
                           "train.log_every=1"],
    "eval": ["eval.num_tracks=8", "eval.resolution=[32,32]"],  # every video, as the README says
    "run": ["--size", "64", "graph.window=2", "optim.stage1_iters=3", "optim.stage2_iters=3"],
}
DATAGEN_TOY = ["--num-scenes", "4", "--workers", "1", "--resolution", "32x32", "--frames", "12"]
DUST3R = ("DUSt3R_ViTLarge_BaseDecoder_512_dpt.pth", "weights/DUSt3R_ViTLarge_BaseDecoder_512_dpt.pth")
# the documents and the `data.sources=[...]` each one's lines get
DOCS = {"README.md": "data/movi-e", "docs/TRAINING.md": "data/movi-e/train",
        **{str(p.relative_to(ROOT)): "data/movi-e" for p in sorted(ROOT.glob("docs/*.md"))
           if p.name != "TRAINING.md"},
        **{str(p.relative_to(ROOT)): "data/movi-e" for p in sorted(ROOT.glob("docs/results/*.md"))}}
# (regular expression searched in a line, why such lines are not run here); the first match wins
NOT_RUN = [
    (r"^make ", "make demo / make test: tests/test_demo.py and this suite"),
    (r"^sbatch ", "a Slurm cluster's job array"),
    (r"benchmarks/device_check\.py", "tests/test_device_check.py runs it (--cpu)"),
    (r"benchmarks/", "a measurement or evaluation script: minutes at its documented sizes (its "
     "tables are in docs/PERFORMANCE.md, docs/perf/, docs/results/)"),
    (r"-m c4d_pipeline\.ablation", "C4D ablations over several scenes: minutes even at 32x32 (their "
     "times are in docs/results/c4d.md); the optimiser itself: tests/test_c4d_optimize.py"),
    (r"^\S*c4d demo\b|demo_out/", "`c4d demo` or its output (make demo): tests/test_demo.py"),
    (r"^git ", "changes the clone itself (a worktree of an old commit, for bench_threads.py --before)"),
    (r"\$", "needs shell variables: a loop's, a line's above (not run) or a cluster's ($NODE_RANK)"),
    (r"data256/", "its input is made by a shell loop above (not run)"),
    (r"--protocol c4d-paper", "the paper's protocol fixes 256 tracks at 256x256 on 24-frame videos, "
     "which the toy sizes here contradict; tests/test_foreign_tfds.py and "
     "tests/test_eval_protocol.py run it on records written from the format's facts"),
]


TOY_SCENES = int(DATAGEN_TOY[1])  # scenes of each dataset a toy datagen line makes


class Ran(NamedTuple):
    """A README line that ran at toy sizes: the folder it ran in, the line, what it printed."""
    folder: Path
    line: str
    stdout: str


def _flag(line: str, flag: str, default: str | None = None) -> str | None:
    """The value of `flag` in `line` (`--out DIR`), else `default`."""
    found = re.search(rf"(?:^|\s){re.escape(flag)}[ =](\S+)", line)
    return found[1] if found else default


def _key(line: str, key: str) -> str:
    """The value of the key=value override `key` in `line`."""
    return re.search(rf"(?:^|\s){re.escape(key)}=(\S+)", line)[1]


def _positional(line: str, index: int) -> str:
    """The `index`-th word after `c4d SUBCOMMAND` of a line without options (`c4d export`'s)."""
    return shlex.split(line)[2:][index]


def _files(folder: Path, *names: str) -> None:
    missing = [name for name in names if not (folder / name).exists()]
    assert not missing, f"{folder} lacks {missing} (has {sorted(p.name for p in folder.iterdir())})"


def shards_written(ran: Ran) -> None:
    """datagen: the dataset file's plan (all the scenes asked for), its shards and the config."""
    out, split = ran.folder / _flag(ran.line, "--out"), _flag(ran.line, "--split", "train")
    _files(out, f"dataset-{split}.json", f"config-{split}.yaml")
    plan = json.loads((out / f"dataset-{split}.json").read_text())
    assert plan["num_scenes"] == TOY_SCENES, plan
    assert len(list(out.glob(f"{split}-*.tar"))) == plan["num_shards"], plan


def layers_written(ran: Ran) -> None:
    """datagen with the optional layers the Kubric export needs: they are in the scenes."""
    from datagen.shards import read_scenes

    shards_written(ran)
    scene = next(iter(read_scenes(ran.folder / _flag(ran.line, "--out"))))
    assert scene.normal is not None and scene.object_coordinates is not None and scene.events is not None


def scene_folders(out: Path) -> list[Path]:
    folders = sorted(p for p in out.iterdir() if p.is_dir())
    assert len(folders) == TOY_SCENES, f"{out}: {[p.name for p in folders]}"
    return folders


def kubric_written(ran: Ran) -> None:
    """OUT/scenes/ holding one Kubric worker folder per scene and nothing else (the builders' data
    path), with the layers and JSON files the README names; OUT holds it and the marker."""
    out = ran.folder / _positional(ran.line, 2)
    assert sorted(p.name for p in out.iterdir()) == [".c4d-output.json", "scenes"], list(out.iterdir())
    assert all(p.is_dir() for p in (out / "scenes").iterdir())
    for scene in scene_folders(out / "scenes"):
        _files(scene, "metadata.json", "events.json", "data_ranges.json", "rgba_00000.png",
               "segmentation_00000.png", "forward_flow_00000.png", "normal_00000.png",
               "object_coordinates_00000.png")


def cotracker_written(ran: Ran) -> None:
    """CoTracker's Kubric folders: frames and NAME.npy, with our mobility labels as `moving`."""
    for scene in scene_folders(ran.folder / _positional(ran.line, 2)):
        _files(scene, "frames/00000.png", f"{scene.name}.npy")
        assert "moving" in np.load(scene / f"{scene.name}.npy", allow_pickle=True).item()


def tapvid_written(ran: Ran) -> None:
    """One TAP-Vid pickle laid out as tapvid_davis.pkl: every scene a video with its labels."""
    data = pickle.loads((ran.folder / _positional(ran.line, 2)).read_bytes())
    assert len(data) == TOY_SCENES and all({"video", "points", "occluded"} <= set(v) for v in data.values())


def report_written(ran: Ran) -> None:
    """c4d inspect --out: index.html (a --scene report names its scene)."""
    out = ran.folder / _flag(ran.line, "--out")
    _files(out, "index.html")
    if scene := _flag(ran.line, "--scene"):
        assert f"Scene {scene}:" in (out / "index.html").read_text()


def dataset_checked(ran: Ran) -> None:
    """c4d inspect --check: every scene decoded, none with problems."""
    assert f"checked {TOY_SCENES} scenes in" in ran.stdout and ": 0 with problems" in ran.stdout, ran.stdout


def page_saved(ran: Ran) -> None:
    """c4d view --save: one HTML page, marked as c4d view's output."""
    page = (ran.folder / _flag(ran.line, "--save")).read_text()
    assert page.startswith("<!") and 'name="c4d-output"' in page and len(page) > 10_000


def checkpoints_written(ran: Ran) -> None:
    """c4d train: runs/NAME/checkpoints/last.pt, and best.pt where eval.source is set."""
    out = ran.folder / _key(ran.line, "train.out_dir") / "checkpoints"
    _files(out, "last.pt", *(["best.pt"] if "eval.source=" in ran.line else []))


def resumed(ran: Ran) -> None:
    """--resume continues the stopped run to its last step (toy: stopped at 2 of 4 steps)."""
    from dynpt.checkpoint import load_checkpoint

    checkpoints_written(ran)
    last = ran.folder / _key(ran.line, "train.out_dir") / "checkpoints" / "last.pt"
    assert load_checkpoint(last)["step"] == int(_key(" ".join(TOY["train"]), "train.steps"))


def pointmap_net_written(ran: Ran) -> None:
    """c4d pretrain-pointmaps: pointmap_net.pth in the official DUSt3R layout (the next line
    loads it as DynPT's 3D encoder)."""
    from dynpt.dust3r.checkpoint import read_checkpoint

    official = read_checkpoint(ran.folder / _key(ran.line, "train.out_dir") / "pointmap_net.pth")
    assert official.constructor and official.state_dict, official.constructor


def every_video_scored(ran: Ran) -> None:
    """c4d eval: eval.json and eval.md in --out, every video of --data scored, and said so."""
    out = ran.folder / _flag(ran.line, "--out")
    _files(out, "eval.json", "eval.md")
    report = json.loads((out / "eval.json").read_text())
    total = report["info"]["videos_in_data"]
    assert report["summary"]["num_videos"] == total, report["summary"]
    assert total == (TOY_SCENES if report["info"]["kind"] == "shards" else 1), report["info"]
    assert f"scored {total} of {total} videos of {_flag(ran.line, '--data')}" in ran.stdout, ran.stdout
    assert f"wrote {Path(_flag(ran.line, '--out')) / 'eval.json'}" in ran.stdout, ran.stdout


def tracks_written(ran: Ran) -> None:
    """c4d track: tracks.npz (at most --points points) and the overlay video."""
    out = ran.folder / _flag(ran.line, "--out")
    _files(out, "tracks.npz", "overlay.mp4")
    with np.load(out / "tracks.npz") as tracks:
        assert 0 < tracks["tracks"].shape[1] <= int(_flag(ran.line, "--points"))


def reconstruction_written(ran: Ran) -> None:
    """c4d run: every file and folder the README lists."""
    _files(ran.folder / _flag(ran.line, "--out"), "frames", "depth", "masks", "poses_tum.txt",
           "intrinsics.npy", "pointmaps.npz", "tracks_2d.npz", "tracks_3d.npz", "scene.ply",
           "report.json", "config.yaml")


def reconstruction_scored(ran: Ran) -> None:
    """c4d eval-recon: the scores in PRED/eval_recon.json, ATE among them."""
    scores = (ran.folder / _flag(ran.line, "--pred") / "eval_recon.json").read_text()
    assert '"ate"' in scores.lower(), scores[:300]


class Refused(NamedTuple):
    """A line the README shows being refused: exit code 2 and one line holding `says`."""
    says: str


# (pattern searched in a README line, its check, or `Refused`); the first match wins
OUTCOMES: list[tuple[str, Callable[[Ran], None] | Refused]] = [
    (r"^c4d view \S+ .*--save data/", Refused("`c4d view` does not write into it")),
    (r"^c4d train .*train\.out_dir=recon", Refused("`c4d train` does not write into it")),
    (r"^c4d datagen .*layers\.normal=true", layers_written),
    (r"^c4d datagen ", shards_written),
    (r"^c4d export kubric ", kubric_written),
    (r"^c4d export cotracker ", cotracker_written),
    (r"^c4d export tapvid ", tapvid_written),
    (r"^c4d inspect .*--check", dataset_checked),
    (r"^c4d inspect .*--out ", report_written),
    (r"^c4d view .*--save ", page_saved),
    (r"^c4d train .*--resume", resumed),
    (r"^(c4d train|torchrun) ", checkpoints_written),
    (r"^c4d pretrain-pointmaps ", pointmap_net_written),
    (r"^c4d eval ", every_video_scored),
    (r"^c4d track ", tracks_written),
    (r"^c4d run ", reconstruction_written),
    (r"^c4d eval-recon ", reconstruction_scored),
]
# README lines run here whose outcome a toy run cannot check: (pattern, why); none at present
NO_OUTCOME: list[tuple[str, str]] = []


def outcome(line: str) -> Callable[[Ran], None] | Refused | None:
    """The check of README line `line` (`OUTCOMES`), or None."""
    return next((check for pattern, check in OUTCOMES if re.search(pattern, line)), None)


def command_lines(doc: Path) -> list[str]:
    """The shell command lines of `doc`'s ```bash blocks."""
    lines = []
    for block in re.findall(r"```bash\n(.*?)```", doc.read_text(), re.S):
        for line in re.sub(r"\\\n\s*", " ", block).splitlines():
            line = re.sub(r"\s+#.*$", "", line).strip()
            if line and not line.startswith("#"):
                lines.append(line)
    return lines


def not_run_reason(line: str) -> str | None:
    """Why `line` is not run here (`NOT_RUN`), or None if it is."""
    return next((why for pattern, why in NOT_RUN if re.search(pattern, line)), None)


def _toy_argv(line: str, sources: str) -> list[str] | None:
    """argv of `line` at toy sizes (see the module docstring), or None if it is not run here;
    `sources` replaces the `[...]` of `data.sources=[...]`."""
    if not_run_reason(line):
        return None
    line = line.replace("/tmp/", "tmp/")
    if line.startswith("printf "):
        return ["bash", "-c", line]
    line = re.sub(r"^\.venv/bin/c4d ", "c4d ", line)
    line = re.sub(r"\[(--[^\]]*)\]", lambda m: m.group(1).split("|")[0], line)  # [--flow dis|raft:..]
    line = line.replace("data.sources=[...]", f"data.sources=[{sources}]")
    argv = shlex.split(line)
    if argv[0] == "torchrun":
        argv[argv.index("--nproc_per_node") + 1] = "2"
        argv = [sys.executable, "-m", "torch.distributed.run", *argv[1:], *TOY["train"]]
        return argv
    assert argv[0] == "c4d", line
    argv = argv[1:]
    if argv[0] == "datagen":
        for flag in ("--num-scenes", "--workers", "--resolution", "--frames"):
            if flag in argv:
                i = argv.index(flag)
                del argv[i:i + 2]
        return argv + DATAGEN_TOY
    return argv + TOY.get(argv[0], [])


def _placeholders(folder: Path, line: str) -> None:
    """Make the files that stand for the user's own, once their sources exist."""
    released = re.search(r"cotracker3:(\S+)", line)
    if released and not (folder / released[1]).exists():
        from c4d_core.config import load_config
        from dynpt.model import plain_config
        from tests.cotracker3_layout import write_released

        write_released(folder / released[1], plain_config(load_config("dynpt", "model/cotracker3-offline").model))
    for name in DUST3R:
        if not (folder / name).exists():
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            torch.save({"model": tiny_network().state_dict(), "args": argparse.Namespace(model=ARGS)},
                       folder / name)
    toy = folder / "data" / "movi-e-64"
    for records in re.finditer(r"\btfds/(\w+)/([\w.]+)/([\w.]+):(\w+)", line):
        name, config, version, split = records.groups()
        if not (folder / records[0].partition(":")[0]).exists() and list(toy.glob("*.tar")):
            from datagen.shards import read_scenes
            from tests.foreign_writers import write_tfds_movi

            scenes = [scene for scene, _ in zip(read_scenes(toy), range(2))]
            write_tfds_movi(folder / "tfds", scenes, name, config, split, num_files=1,
                            version=version)
    val = folder / "data" / "val"
    if not (folder / "video.mp4").exists() and list(val.glob("*.tar")):
        from datagen.shards import read_scenes
        from c4d_core.video import write_video

        write_video(folder / "video.mp4", next(iter(read_scenes(val))).rgb, fps=10)
    rng = np.random.default_rng(0)

    def entry():
        occluded = rng.random((5, 8)) < 0.2
        return {"video": rng.integers(0, 255, (8, 24, 32, 3), dtype=np.uint8),
                "points": rng.random((5, 8, 2)).astype(np.float32), "occluded": occluded}

    for name in ("tapvid_davis.pkl", "tapvid/tapvid_davis.pkl"):
        if not (folder / name).exists():
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            (folder / name).write_bytes(pickle.dumps({"bear": entry()}))
    kinetics = folder / "tapvid" / "kinetics" / "0000_of_0010.pkl"
    if not kinetics.exists():
        kinetics.parent.mkdir(parents=True, exist_ok=True)
        kinetics.write_bytes(pickle.dumps([entry()]))


def _run(argv: list[str], folder: Path) -> tuple[int, str, str]:
    """(exit code, last stderr line, stdout) of one line, run in `folder`."""
    if argv[0] == "bash":
        (folder / "tmp").mkdir(exist_ok=True)
        proc = subprocess.run(argv, cwd=folder, capture_output=True, text=True, timeout=60)
        return proc.returncode, proc.stderr.strip(), proc.stdout
    if argv[0] == sys.executable:  # torchrun
        env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
        proc = subprocess.run(argv, cwd=folder, env=env, capture_output=True, text=True, timeout=900)
        lines = [l for l in proc.stderr.splitlines() if "error" in l.lower()] or proc.stderr.splitlines()
        return proc.returncode, (lines[-1] if lines else ""), proc.stdout
    err, out = io.StringIO(), io.StringIO()
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            code = main(argv)
    finally:
        os.chdir(cwd)
    lines = [l for l in err.getvalue().splitlines() if l.startswith("c4d: ")]
    return code, (lines[-1] if lines else ""), out.getvalue()


def test_every_line_is_run_or_listed():
    """Each documented line maps to a toy command or has a `NOT_RUN` reason; every reason is used."""
    used = set()
    for doc, sources in DOCS.items():
        for line in command_lines(ROOT / doc):
            reason = not_run_reason(line)
            used.add(reason)
            if reason is None:  # a c4d subcommand, torchrun or printf (_toy_argv refuses others)
                assert _toy_argv(line, sources)[0] in (*SUBCOMMANDS, sys.executable, "bash"), (doc, line)
    assert {why for _, why in NOT_RUN} <= used, "a NOT_RUN reason no line needs any more"


def test_every_readme_line_run_here_has_its_outcome_checked():
    """A README line that is run at toy sizes has a check of what the README says it gives
    (`OUTCOMES`) or a reason in `NO_OUTCOME`; every pattern of both is used by some line."""
    lines = [line for line in command_lines(ROOT / "README.md") if not_run_reason(line) is None]
    unchecked = [line for line in lines if outcome(line) is None
                 and not any(re.search(pattern, line) for pattern, _ in NO_OUTCOME)]
    assert not unchecked, "README lines without an outcome check (OUTCOMES) or a NO_OUTCOME reason:\n" \
        + "\n".join(unchecked)
    unused = [pattern for pattern, _ in [*OUTCOMES, *NO_OUTCOME]
              if not any(re.search(pattern, line) for line in lines)]
    assert not unused, f"OUTCOMES / NO_OUTCOME patterns no README line matches: {unused}"
    assert any(isinstance(outcome(line), Refused) for line in lines), "no refused line is checked"


RUN_DOCS = [doc for doc, sources in DOCS.items()
            if any(not_run_reason(line) is None for line in command_lines(ROOT / doc))]


@pytest.mark.slow
@pytest.mark.timeout(3600)
@pytest.mark.parametrize("doc", RUN_DOCS)
def test_documented_commands_run_as_written(doc, tmp_path):
    sources = DOCS[doc]
    checks = {line: outcome(line) if doc == "README.md" else None for line in command_lines(ROOT / doc)}
    runs = [(line, argv) for line in checks if (argv := _toy_argv(line, sources)) is not None]
    pending = [(line, argv) for line, argv in runs if not isinstance(checks[line], Refused)]
    assert len(pending) >= (10 if doc in ("README.md", "docs/TRAINING.md") else 1), \
        "the command extraction found too few lines"
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    failures: dict[str, str] = {}
    while pending:
        retry = []
        for line, argv in pending:
            _placeholders(tmp_path, line)
            code, message, stdout = _run(argv, tmp_path)
            if code:
                retry.append((line, argv))
                failures[line] = message
                continue
            failures.pop(line, None)
            if checks[line] is not None:
                try:
                    checks[line](Ran(tmp_path, line, stdout))
                except AssertionError as exc:  # ran, but not what the README says it gives
                    failures[line] = f"ran, but: {exc}"
        if len(retry) == len(pending):
            break
        pending = retry
    for line, argv in runs:  # the refusals, once every folder they would write into exists
        if isinstance(checks[line], Refused):
            code, message, _ = _run(argv, tmp_path)
            if code != 2 or checks[line].says not in message:
                failures[line] = f"not refused as the README says (exit {code}): {message}"
    assert not failures, "\n".join(f"{line}\n    -> {msg}" for line, msg in failures.items())
