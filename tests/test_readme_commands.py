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
  TAP-Vid pickles are toy ones, `data.sources=[...]` is the first train set, CoTracker3's
  released file (`cotracker3:weights/scaled_offline.pth`) is one in its released layout and size
  with random weights (tests/cotracker3_layout.py);
- `[a|b]` optional groups are taken with their first alternative;
- not run here: the lines `NOT_RUN` matches, each with its reason (a fast test checks that every
  line is either run or listed, so a new line needs one or the other).
A line whose input a later line makes (the docs are not always in dependency order) is retried
after the others; what still fails is reported with its one-line error.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import pickle
import re
import shlex
import subprocess
import sys
from pathlib import Path

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
    "eval": ["eval.num_scenes=1", "eval.num_tracks=8", "eval.resolution=[32,32]"],
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
]


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


def _run(argv: list[str], folder: Path) -> tuple[int, str]:
    """(exit code, last stderr line) of one line, run in `folder`."""
    if argv[0] == "bash":
        (folder / "tmp").mkdir(exist_ok=True)
        proc = subprocess.run(argv, cwd=folder, capture_output=True, text=True, timeout=60)
        return proc.returncode, proc.stderr.strip()
    if argv[0] == sys.executable:  # torchrun
        env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
        proc = subprocess.run(argv, cwd=folder, env=env, capture_output=True, text=True, timeout=900)
        lines = [l for l in proc.stderr.splitlines() if "error" in l.lower()] or proc.stderr.splitlines()
        return proc.returncode, (lines[-1] if lines else "")
    err = io.StringIO()
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main(argv)
    finally:
        os.chdir(cwd)
    lines = [l for l in err.getvalue().splitlines() if l.startswith("c4d: ")]
    return code, (lines[-1] if lines else "")


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


RUN_DOCS = [doc for doc, sources in DOCS.items()
            if any(not_run_reason(line) is None for line in command_lines(ROOT / doc))]


@pytest.mark.slow
@pytest.mark.timeout(3600)
@pytest.mark.parametrize("doc", RUN_DOCS)
def test_documented_commands_run_as_written(doc, tmp_path):
    sources = DOCS[doc]
    pending = [(line, argv) for line in command_lines(ROOT / doc)
               if (argv := _toy_argv(line, sources)) is not None]
    assert len(pending) >= (10 if doc in ("README.md", "docs/TRAINING.md") else 1), \
        "the command extraction found too few lines"
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    failures: dict[str, str] = {}
    while pending:
        retry = []
        for line, argv in pending:
            _placeholders(tmp_path, line)
            code, message = _run(argv, tmp_path)
            if code:
                retry.append((line, argv))
                failures[line] = message
            else:
                failures.pop(line, None)
        if len(retry) == len(pending):
            break
        pending = retry
    assert not failures, "\n".join(f"{line}\n    -> {msg}" for line, msg in failures.items())
