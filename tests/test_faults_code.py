"""The fault suite, hostile files: no file given to any command can run code.

Every reader of a file a user gives (DynPT tracker, CoTracker3 weights, DUSt3R / MASt3R / MonST3R
checkpoints, RAFT weights, the pointmap network, its training state, `c4d eval`'s TAP-Vid pickles,
`c4d train --resume`) is fed files whose pickle, when unpickled, runs `touch MARKER`: in PyTorch's
zip format, its legacy format, a plain pickle, and (for the DUSt3R family, whose files hold an
`argparse.Namespace`) one hidden inside the allowed Namespace. Each must end in one line naming
the file, and the marker must never appear. A control proves the files do run code when
unpickled by the full unpickler.
"""

from __future__ import annotations

import argparse
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from c4d.cli import main
from c4d_core.errors import UserError
from c4d_core.video import write_image
from dynpt.checkpoint import FORMAT
from tests.test_faults import ENV, ROOT, assert_one_line_error
from tests.test_faults_training import POINTMAPS, depth_shards, pointmaps, train_args  # noqa: F401
from tests.test_faults_training import tracker_inputs  # noqa: F401  (module fixture)

pytestmark = pytest.mark.faults


class RunsCode:
    """An object whose unpickling calls `os.system("touch MARKER")`."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def hostile_file(path: Path, kind: str, marker: Path) -> Path:
    """Write a file at `path` whose unpickling creates `marker`, in the container `kind`."""
    evil = RunsCode(marker)
    if kind == "namespace":  # a DUSt3R-shaped file whose allowed Namespace carries the payload
        payload = {"model": {"w": torch.zeros(2)}, "args": argparse.Namespace(model="Net()", x=evil)}
    else:
        payload = {"format": FORMAT, "model": {"w": torch.zeros(2)}, "config": {}, "x": evil}
    if kind == "legacy":
        torch.save(payload, path, _use_new_zipfile_serialization=False)
    elif kind == "pickle":
        path.write_bytes(pickle.dumps(payload, protocol=2))
    else:
        torch.save(payload, path)
    return path


KINDS = ("zip", "legacy", "pickle", "namespace")


@pytest.fixture
def marker(tmp_path):
    path = tmp_path / "MARKER"
    yield path
    assert not path.exists(), "a file given to a command ran code"


def test_control_the_hostile_files_run_code_when_fully_unpickled(tmp_path):
    paths = [hostile_file(tmp_path / f"{kind}.pt", kind, tmp_path / f"ran-{kind}") for kind in KINDS]
    subprocess.run([sys.executable, "-c", "import pickle, sys, torch\n"
                    "for p in sys.argv[1:]:\n"
                    "    pickle.load(open(p, 'rb')) if p.endswith('pickle.pt') else "
                    "torch.load(p, weights_only=False)", *map(str, paths)],
                   env=ENV, cwd=ROOT, capture_output=True, check=True)
    assert all((tmp_path / f"ran-{kind}").exists() for kind in KINDS)


@pytest.mark.parametrize("kind", KINDS)
def test_no_library_reader_runs_code(tmp_path, marker, kind):
    from c4d_pipeline.raft import load_raft
    from dynpt.checkpoint import load_checkpoint
    from dynpt.cotracker3_weights import read_state
    from dynpt.dust3r.checkpoint import read_checkpoint
    from dynpt.dust3r.net import load_dust3r
    from dynpt.dust3r.vit_encoder import load_dust3r_encoder
    from dynpt.inference import load_tracker
    from dynpt.tapvid_data import read_tapvid

    path = hostile_file(tmp_path / "weights.pth", kind, marker)
    readers = {"tracker": load_checkpoint, "load_tracker": load_tracker,
               "cotracker3": lambda p: load_tracker(f"cotracker3:{p}"), "cotracker3-state": read_state,
               "dust3r": read_checkpoint, "dust3r-net": load_dust3r, "dust3r-encoder": load_dust3r_encoder,
               "raft": load_raft, "tapvid": lambda p: list(read_tapvid(p))}
    for name, read in readers.items():
        with pytest.raises(UserError) as caught:
            read(path)
        text = str(caught.value)
        assert str(path) in text and "\n" not in text, (name, text)
        assert "Weights only load failed" not in text and "\x1b[" not in text, (name, text)
    assert not marker.exists()


def test_a_dust3r_file_with_other_objects_is_refused_with_how_to_convert_a_trusted_one(tmp_path, marker):
    from dynpt.dust3r.checkpoint import read_checkpoint

    path = hostile_file(tmp_path / "dust3r.pth", "namespace", marker)
    with pytest.raises(UserError, match=r"holds Python objects other than tensors and plain values "
                                        r"\(posix.system\)\); if you trust the file, convert it once"):
        read_checkpoint(path)
    # the conversion the message gives, run on a trusted file, yields one the loader reads
    trusted = tmp_path / "trusted.pth"
    torch.save({"model": {"w": torch.ones(3)}, "args": argparse.Namespace(model="Net(a=1)"),
                "started": np.datetime64("2024-01-01")}, trusted)
    with pytest.raises(UserError, match="numpy"):
        read_checkpoint(trusted)
    hint = str(pytest.raises(UserError, read_checkpoint, trusted).value)
    command = hint[hint.index('python -c "') + len('python -c "'):hint.rindex('" IN OUT')]
    converted = tmp_path / "converted.pth"
    subprocess.run([sys.executable, "-c", command, str(trusted), str(converted)], env=ENV, cwd=ROOT,
                   check=True, capture_output=True)
    ckpt = read_checkpoint(converted)
    assert ckpt.constructor == "Net" and ckpt.kwargs == {"a": 1}
    torch.testing.assert_close(ckpt.state_dict["w"], torch.ones(3))


def test_a_dust3r_file_with_numpy_scalars_reads_under_numpy_1_and_2_names(tmp_path):
    """croco's save_model can store numpy scalars (a best_so_far float, numpy-string names)."""
    import zipfile

    from dynpt.dust3r.checkpoint import read_checkpoint

    path = tmp_path / "official.pth"
    torch.save({"model": {np.str_("module.w"): torch.ones(3)}, "args": argparse.Namespace(
        model="Net(a=1)"), "best_so_far": np.float64(0.25), "epoch": np.int64(7)}, path)
    old = tmp_path / "numpy1.pth"  # the same file as numpy 1.x writes it: numpy.core, not _core
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(old, "w") as dst:
        for item in src.infolist():
            data = src.read(item)
            if item.filename.endswith("data.pkl"):
                assert b"numpy._core.multiarray" in data
                data = data.replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
            dst.writestr(item, data)
    for file in (path, old):
        ckpt = read_checkpoint(file)
        assert ckpt.constructor == "Net" and list(ckpt.state_dict) == ["w"]


def test_a_tapvid_pickle_with_a_class_is_refused_and_a_real_one_reads(tmp_path, marker):
    from dynpt.tapvid_data import read_tapvid

    entry = {"video": np.zeros((3, 8, 8, 3), np.uint8), "points": np.full((2, 3, 2), 0.5),
             "occluded": np.zeros((2, 3), bool)}
    good = tmp_path / "good.pkl"
    good.write_bytes(pickle.dumps({"clip": entry}, protocol=4))
    (item,) = read_tapvid(good, size=(8, 8))
    assert item["tracks"].shape == (3, 2, 2) and np.allclose(item["tracks"], 3.5)
    bad = tmp_path / "bad.pkl"
    bad.write_bytes(pickle.dumps({"clip": {**entry, "video": RunsCode(marker)}}))
    with pytest.raises(UserError, match=r"holds Python objects other than arrays and plain values "
                                        r"\(posix.system\), which could run code"):
        list(read_tapvid(bad))


def test_no_command_runs_code_from_a_file(tmp_path, capsys, marker, tracker_inputs, depth_shards):
    frames = str(tracker_inputs["frames"])
    evil = hostile_file(tmp_path / "evil.pt", "zip", marker)
    evil_ns = hostile_file(tmp_path / "evil-ns.pth", "namespace", marker)
    evil_pkl = hostile_file(tmp_path / "evil.pkl", "pickle", marker)
    commands = {  # name -> (argv, the file the error must name)
        "track": (["track", frames, "--ckpt", str(evil), "--out", str(tmp_path / "t")], evil),
        "track cotracker3": (["track", frames, "--ckpt", f"cotracker3:{evil}", "--out",
                              str(tmp_path / "t")], evil),
        "eval": (["eval", "--ckpt", str(evil), "--data", str(tmp_path)], evil),
        "eval tapvid": (["eval", "--ckpt", str(tracker_inputs["ckpt"]), "--data", str(evil_pkl),
                         "--out", str(tmp_path / "e")], evil_pkl),
        "train init": (train_args(tmp_path / "r1", "train.steps=3",
                                  f"model.init_from=cotracker3:{evil}"), evil),
        "train encoder": (train_args(tmp_path / "r2", "train.steps=3",
                                     f"model.encoder_3d.checkpoint={evil_ns}"), evil_ns),
        "run pointmaps": (["run", frames, "--out", str(tmp_path / "o1"), "--pointmaps", str(evil_ns)],
                          evil_ns),
    }
    for name, (argv, culprit) in commands.items():
        code = main(argv)
        assert_one_line_error(code, capsys.readouterr().err, str(culprit))
        assert not marker.exists(), name
    # resuming a run whose checkpoints were replaced by hostile files
    run = tmp_path / "run"
    shutil.copytree(tracker_inputs["run"], run)
    for name in ("step_00000002.pt", "last.pt"):
        hostile_file(run / "checkpoints" / name, "zip", marker)
    code = main(train_args(run, "train.steps=4", "train.ckpt_every=2", "--resume"))
    assert_one_line_error(code, capsys.readouterr().err, "no readable checkpoint")
    # resuming pointmap training from a hostile state
    out = tmp_path / "pm"
    assert main(pointmaps(out, depth_shards, "train.steps=1")) == 0
    hostile_file(out / "last.pt", "zip", marker)
    code = main(pointmaps(out, depth_shards, "train.steps=2", "--resume"))
    assert_one_line_error(code, capsys.readouterr().err, str(out / "last.pt"))
