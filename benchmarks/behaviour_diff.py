"""Proof of "no change of behaviour" between two revisions: same shards, same training, same reconstruction.

    .venv/bin/python benchmarks/behaviour_diff.py REV_A REV_B [--scenes 4 --steps 50 --work /tmp/behaviour_diff]

Checks out both revisions as detached git worktrees under WORK and runs each with
`PYTHONPATH=WORKTREE` from the worktree root (`python -m c4d`, the venv's dependencies shared),
`OMP_NUM_THREADS=1`, at tiny sizes:

1. datagen: a seeded `c4d datagen` (movi-e, 64x64, 8 frames); the sha256 of every file written.
2. train: a `c4d train --config tiny-cpu` of `--steps` steps on REV_A's shards (both revisions train
   on the same bytes, so a datagen difference does not hide a training one): every log.jsonl line,
   and the final checkpoint's step and weights (tensor by tensor, exact).
3. run: `c4d run` at 64 pixels with few iterations (the overrides of tests/test_c4d_run.py) on a
   generated scene's video, with the tiny random-weight DUSt3R-layout network of that test and
   REV_A's trained tracker (same inputs for both): every array of the output (poses, intrinsics,
   depth, masks, pointmaps, 2-D and 3-D tracks, frames), exact.

Prints one Markdown table (check, equal?, detail). Exit status 0 when everything is equal, 1 otherwise.

Which revisions: any with `python -m c4d`, `c4d datagen/train/run` taking the options used here,
and tests/test_c4d_run.py's `make_inputs` and `FAST` (this project since the `c4d run` tests, at least
395b6b3 onwards). The presets are found in each worktree whichever way the revision looks for them:
older revisions read `configs/` next to their package; newer ones import the package `c4d_configs`,
which the editable install maps onto the main checkout, so a `c4d_configs -> configs` link is placed
in each worktree root (first on PYTHONPATH), and a sitecustomize.py drops the editable install's
finder, so no module of the main checkout can stand in for one the revision lacks. Before anything runs, each revision's
`c4d`, `c4d_pipeline`, `dynpt`, `datagen` and its preset folder are checked to come from its worktree.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

# On PYTHONPATH after the worktree: drops the editable install's finder, so a package the revision
# lacks (c4d_core before the layout step) is not found in the main checkout either.
ISOLATE = """import sys
sys.meta_path[:] = [f for f in sys.meta_path if "_EditableFinder" not in getattr(f, "__name__", type(f).__name__)]
"""

# Printed by each revision before anything runs: where its packages and presets come from.
PROVENANCE = """
import importlib, json, pathlib
files = {m: importlib.import_module(m).__file__ for m in ("c4d", "c4d_pipeline", "dynpt", "datagen")}
try:  # after the layout step
    config = importlib.import_module("c4d_core.config")
except ModuleNotFoundError:  # before it
    config = importlib.import_module("c4d.config")
files["presets"] = str(config.config_dir() if hasattr(config, "config_dir") else config.CONFIG_DIR)
print(json.dumps({k: str(pathlib.Path(v).resolve()) for k, v in files.items()}))
"""

# Run by REV_A once: the inputs of `c4d run` (a generated scene's video, a tiny DUSt3R-layout network).
MAKE_RUN_INPUTS = """
import sys
from pathlib import Path
from test_c4d_run import make_inputs
make_inputs(Path(sys.argv[1]), frames=8, size=64)
"""

# Read a checkpoint: its step, the sha256 of every weight tensor's bytes, and of the optimiser state's tensors.
READ_CHECKPOINT = """
import hashlib, json, sys, torch
payload = torch.load(sys.argv[1], map_location="cpu", weights_only=False)
print(json.dumps({"step": payload.get("step"), "format": payload.get("format"),
                  "weights": {k: [str(v.dtype), list(v.shape), hashlib.sha256(v.contiguous().numpy().tobytes()).hexdigest()]
                              for k, v in payload["model"].items()},
                  "optimizer": hashlib.sha256(b"".join(v.contiguous().numpy().tobytes() for state in
                      payload.get("extra", {}).get("optimizer", {}).get("state", {}).values()
                      for v in state.values() if torch.is_tensor(v))).hexdigest()}))
"""


class Revision:
    """One revision checked out as a detached worktree, with the environment that runs it."""

    def __init__(self, label: str, rev: str, work: Path):
        self.label = label
        self.sha = git("rev-parse", "--verify", f"{rev}^{{commit}}")
        self.root = work / f"{label}-{self.sha[:9]}"
        if not self.root.exists():
            git("worktree", "add", "--detach", str(self.root), self.sha)
        if (self.root / "configs" / "__init__.py").is_file() and not (self.root / "c4d_configs").exists():
            (self.root / "c4d_configs").symlink_to("configs")
        isolate = work / "isolate"
        isolate.mkdir(exist_ok=True)
        (isolate / "sitecustomize.py").write_text(ISOLATE)
        self.path = f"{self.root}{os.pathsep}{isolate}"
        self.env = {**os.environ, "PYTHONPATH": self.path, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                    "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl"), "PYTHONHASHSEED": "0"}

    def python(self, *args: str, extra_path: Path | None = None) -> str:
        env = dict(self.env)
        if extra_path is not None:
            env["PYTHONPATH"] = f"{self.path}{os.pathsep}{extra_path}"
        done = subprocess.run([sys.executable, *args], cwd=self.root, env=env, capture_output=True, text=True)
        if done.returncode != 0:
            raise SystemExit(f"{self.label} ({self.sha[:9]}): `python {' '.join(args)[:200]}` failed:\n"
                             f"{done.stderr[-3000:]}")
        return done.stdout

    def c4d(self, *args: str) -> str:
        return self.python("-m", "c4d", *args)

    def check_provenance(self) -> None:
        found = json.loads(self.python("-c", PROVENANCE))
        outside = {k: v for k, v in found.items() if not Path(v).is_relative_to(self.root.resolve())}
        if outside:
            raise SystemExit(f"{self.label}: these do not come from its worktree {self.root}: {outside}")


def git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=REPO, check=True, capture_output=True, text=True).stdout.strip()


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def files_under(folder: Path) -> dict[str, Path]:
    return {str(p.relative_to(folder)): p for p in sorted(folder.rglob("*")) if p.is_file()}


def compare_datagen(a: Revision, b: Revision, out: Path, scenes: int) -> list[tuple[str, bool, str]]:
    folders = {}
    for rev in (a, b):
        folders[rev.label] = out / rev.label / "data"
        rev.c4d("datagen", "--preset", "movi-e", "--num-scenes", str(scenes), "--out", str(folders[rev.label]),
                "--seed", "0", "--workers", "1", "--resolution", "64", "--frames", "8", "--scenes-per-shard", "2",
                "tracks.num_points=16")
    fa, fb = (files_under(folders[r.label]) for r in (a, b))
    rows = []
    for name in sorted(set(fa) | set(fb)):
        if name not in fa or name not in fb:
            rows.append((f"datagen {name}", False, f"only in {a.label if name in fa else b.label}"))
            continue
        ha, hb = sha256(fa[name]), sha256(fb[name])
        rows.append((f"datagen {name}", ha == hb, f"sha256 {ha[:16]}" + ("" if ha == hb else f" vs {hb[:16]}")))
    return rows


def compare_train(a: Revision, b: Revision, out: Path, steps: int) -> tuple[list[tuple[str, bool, str]], Path]:
    shards = out / a.label / "data"
    runs = {}
    for rev in (a, b):
        runs[rev.label] = out / rev.label / "run"
        rev.c4d("train", "--config", "tiny-cpu", f"data.sources=[{shards}]", f"train.out_dir={runs[rev.label]}",
                f"train.steps={steps}", f"train.ckpt_every={steps}", "eval.every=0")
    la, lb = ((runs[r.label] / "log.jsonl").read_text().splitlines() for r in (a, b))
    first_diff = next((i for i, (x, y) in enumerate(zip(la, lb)) if x != y), None)
    same_log = la == lb
    detail = f"{len(la)} lines" if same_log else (
        f"{len(la)} vs {len(lb)} lines" + ("" if first_diff is None else f"; first difference at line {first_diff + 1}"))
    rows = [("train log.jsonl", same_log, detail)]
    ckpts = {r.label: latest_checkpoint(runs[r.label]) for r in (a, b)}
    ca, cb = (json.loads(r.python("-c", READ_CHECKPOINT, str(ckpts[r.label]))) for r in (a, b))
    differing = sorted(k for k in set(ca["weights"]) | set(cb["weights"]) if ca["weights"].get(k) != cb["weights"].get(k))
    rows.append(("train checkpoint step", ca["step"] == cb["step"], f"{ca['step']} ({ckpts[a.label].name})"))
    rows.append(("train checkpoint weights", not differing,
                 f"{len(ca['weights'])} tensors" + (f"; differ: {', '.join(differing[:5])}" if differing else "")))
    rows.append(("train checkpoint optimizer state", ca["optimizer"] == cb["optimizer"], f"sha256 {ca['optimizer'][:16]}"))
    return rows, ckpts[a.label]


def latest_checkpoint(run: Path) -> Path:
    steps = sorted(run.glob("checkpoints/step_*.pt"), key=lambda p: int("".join(c for c in p.stem if c.isdigit())))
    if not steps:
        raise SystemExit(f"no step checkpoint under {run}/checkpoints")
    return steps[-1]


RUN_OVERRIDES = ["graph.window=2", "optim.stage1_iters=4", "optim.stage2_iters=2", "pts.window=4", "pts.extend=1"]


def compare_run(a: Revision, b: Revision, out: Path, tracker: Path) -> list[tuple[str, bool, str]]:
    inputs = out / "run_inputs"
    inputs.mkdir(parents=True, exist_ok=True)
    if not (inputs / "dust3r_tiny.pth").is_file():
        a.python("-c", MAKE_RUN_INPUTS, str(inputs), extra_path=a.root / "tests")
    recons = {}
    for rev in (a, b):
        recons[rev.label] = out / rev.label / "recon"
        rev.c4d("run", str(inputs / "video.mp4"), "--out", str(recons[rev.label]), "--pointmaps",
                str(inputs / "dust3r_tiny.pth"), "--tracker", str(tracker), "--size", "64", *RUN_OVERRIDES)
    ra, rb = recons[a.label], recons[b.label]
    rows = []
    for name, loader in [("poses_tum.txt", lambda p: np.loadtxt(p)), ("intrinsics.npy", np.load),
                         ("pointmaps.npz", np.load), ("tracks_2d.npz", np.load), ("tracks_3d.npz", np.load),
                         ("depth/*.npy", np.load), ("masks/*.png", read_png), ("frames/*.png", read_png)]:
        pa, pb = sorted(ra.glob(name)), sorted(rb.glob(name))
        if [p.name for p in pa] != [p.name for p in pb] or not pa:
            rows.append((f"run {name}", False, f"{len(pa)} vs {len(pb)} files"))
            continue
        equal, shapes = True, set()
        for x, y in zip(pa, pb):
            va, vb = loader(x), loader(y)
            arrays_a = dict(va) if hasattr(va, "files") else {"": va}
            arrays_b = dict(vb) if hasattr(vb, "files") else {"": vb}
            equal &= arrays_a.keys() == arrays_b.keys() and all(
                np.array_equal(arrays_a[k], arrays_b[k], equal_nan=arrays_a[k].dtype.kind == "f") for k in arrays_a)
            shapes |= {f"{k}{tuple(v.shape)}" if k else str(tuple(v.shape)) for k, v in arrays_a.items()}
        rows.append((f"run {name}", equal, f"{len(pa)} file(s), " + ", ".join(sorted(shapes))))
    return rows


def read_png(path: Path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(path))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("rev_a")
    parser.add_argument("rev_b")
    parser.add_argument("--scenes", type=int, default=4, help="generated scenes [4]")
    parser.add_argument("--steps", type=int, default=50, help="training steps [50]")
    parser.add_argument("--work", type=Path, default=Path("/tmp/behaviour_diff"), help="worktrees and outputs")
    args = parser.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    a, b = Revision("a", args.rev_a, args.work), Revision("b", args.rev_b, args.work)
    out = args.work / f"out-{a.sha[:9]}-{b.sha[:9]}"
    if out.exists():
        subprocess.run(["rm", "-rf", str(out)], check=True)
    for rev in (a, b):
        rev.check_provenance()
    rows = compare_datagen(a, b, out, args.scenes)
    train_rows, tracker = compare_train(a, b, out, args.steps)
    rows += train_rows + compare_run(a, b, out, tracker)
    print(f"A = {args.rev_a} ({a.sha[:9]}), B = {args.rev_b} ({b.sha[:9]}); {args.scenes} scenes, "
          f"{args.steps} training steps, OMP_NUM_THREADS=1\n")
    print("| check | equal? | detail |\n|---|---|---|")
    for check, equal, detail in rows:
        print(f"| {check} | {'yes' if equal else '**no**'} | {detail} |")
    return 0 if all(equal for _, equal, _ in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
