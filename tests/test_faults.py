"""The fault suite: crashes, damaged data and bad output folders, each ending cleanly.

Every case runs real commands (in this process via `c4d.cli.main`, or as subprocesses where a
process must die) and checks the contract of a fault: one line on stderr naming the problem and
the fix, a non-zero exit, no traceback, nothing already written lost or torn. Kinds:
- damaged shards: a member deleted with `tar --delete`, a flipped byte inside rgb, a truncated
  shard, random bytes, a shard without checksums (older format: still read);
- output folders: read-only (a read-only bind mount; chmod does not stop root), an existing file
  as the output folder, a full disk (a 2 MB tmpfs filled up), for every writing command;
- processes: `kill -9` of datagen and of training, then resume with identical results; the
  parent of `c4d datagen --workers 2` killed (workers must exit), Ctrl-C to it alone; a torn
  log.jsonl line (a size limit, RLIMIT_FSIZE, during the append); a truncated newest checkpoint.
Mounts need root (or the right capability): those cases skip with the reason where not allowed.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import random
import resource
import shutil
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from c4d.cli import main
from datagen.codecs import CHECKSUMS
from datagen.shards import ShardWriter, decode_scene, iter_samples
from dynpt.checkpoint import save_checkpoint
from dynpt.model import build_model
from c4d_core.config import load_config
from tests.dynpt_testdata import synthetic_scene, synthetic_shards

pytestmark = pytest.mark.faults
ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
       "OMP_NUM_THREADS": "1", "PYOPENGL_PLATFORM": "egl"}
TINY_DATAGEN = ["--preset", "movi-e", "--resolution", "32x48", "--frames", "4", "--seed", "5",
                "tracks.num_points=16", "objects.num_static=[1,2]", "objects.num_tossed=[1,1]"]
TRAIN = ["--config", "tiny-cpu", "data.crop_size=[32,32]", "data.num_frames=6",
         "data.num_tracks=12", "train.total_batch=2", "train.batch_size=1", "train.log_every=1",
         "eval.every=0"]


def c4d(*args: str, **kwargs) -> subprocess.CompletedProcess:
    """`python -m c4d ARGS` in a subprocess (one torch thread)."""
    return subprocess.run([sys.executable, "-m", "c4d", *args], env=ENV, cwd=ROOT,
                          capture_output=True, text=True, timeout=240, **kwargs)


def assert_one_line_error(code: int, err: str, *words: str) -> str:
    """The contract of a fault: exit 2, one `c4d: error:` line naming it, no traceback."""
    assert code == 2, err[-2000:]
    assert "Traceback" not in err, err[-2000:]
    lines = [line for line in err.splitlines() if line.startswith("c4d: error:")]
    assert len(lines) == 1, err[-2000:]
    for word in words:
        assert word in lines[0], lines[0]
    if os.environ.get("C4D_SHOW_FAULTS"):
        print("FAULT-LINE", lines[0])
    return lines[0]


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def shard_copy(tmp_path: Path, num_scenes: int = 6) -> Path:
    """A fresh copy of the synthetic shards (3 scenes each) to damage."""
    out = tmp_path / "shards"
    shutil.copytree(synthetic_shards(num_scenes, 3), out)
    return out


# --- damaged shards -----------------------------------------------------------------------------


def delete_member(shard: Path, member: str) -> None:
    subprocess.run(["tar", "--delete", "-f", str(shard), member], check=True)


def flip_byte_in(shard: Path, member: str, offset: int = 200) -> None:
    with tarfile.open(shard) as tar:
        start = tar.getmember(member).offset_data
    with open(shard, "r+b") as f:
        f.seek(start + offset)
        byte = f.read(1)
        f.seek(start + offset)
        f.write(bytes([byte[0] ^ 0xFF]))


def without_checksums(shard: Path) -> None:
    """Rewrite `shard` as an older format (2) shard: the same members but no checksums.json."""
    samples = [{k: v for k, v in s.items() if k not in (CHECKSUMS, "__url__", "__members__")}
               for s in iter_samples(shard)]
    with ShardWriter(shard) as writer:
        for sample in samples:
            writer.write(sample)


def test_a_flipped_byte_in_rgb_is_caught_by_inspect_check(tmp_path, capsys):
    shards = shard_copy(tmp_path)
    flip_byte_in(shards / "train-000000.tar", "train-00000001.rgb.npy")
    assert main(["inspect", str(shards), "--check", "--no-progress"]) == 1
    out = capsys.readouterr().out
    assert "train-00000001" in out and "CRC-32" in out and "rgb.npy" in out
    assert "checked 6 scenes in 2 shards: 1 with problems" in out


def test_a_deleted_member_is_named_and_training_skips_the_sample(tmp_path, capsys, caplog):
    shards = shard_copy(tmp_path)
    delete_member(shards / "train-000001.tar", "train-00000004.tracks.npy.bsz")
    assert main(["inspect", str(shards), "--check", "--no-progress"]) == 1
    assert "lacks its member 'tracks.npy.bsz'" in capsys.readouterr().out
    # Training: skipped with a warning naming shard and sample, counted, reported at the end.
    run = tmp_path / "run"
    code = main(["train", *TRAIN, f"data.sources=[{shards}]", f"train.out_dir={run}",
                 "train.steps=4", "data.max_bad_fraction=0.05"])
    assert code == 0
    warned = [r.getMessage() for r in caplog.records if "skipping bad training data" in r.getMessage()]
    assert warned and "train-00000004" in warned[0] and "train-000001.tar" in warned[0]
    assert any("skipped" in r.getMessage() and "bad training samples" in r.getMessage()
               for r in caplog.records)
    # The limit: no bad sample allowed -> one line, the run stops (raised in a loader worker, so
    # in a subprocess: forking pytest, whose other threads may hold locks, can hang the worker).
    run = c4d("train", *TRAIN, f"data.sources=[{shards}]", f"train.out_dir={tmp_path / 'r0'}",
              "train.steps=8", "data.max_bad_fraction=0", "data.num_workers=1")
    assert_one_line_error(run.returncode, run.stderr, "data.max_bad_fraction", "train-00000004")


def test_eval_skips_damaged_scenes_and_counts_them_in_its_table(tmp_path, capsys):
    shards = shard_copy(tmp_path)
    delete_member(shards / "train-000000.tar", "train-00000002.tracks.npy.bsz")
    flip_byte_in(shards / "train-000001.tar", "train-00000003.rgb.npy")
    ckpt = save_checkpoint(tmp_path / "tiny.pt", build_model(load_config("dynpt", "tiny-cpu").model), 0)
    out = tmp_path / "eval"
    assert main(["eval", "--ckpt", str(ckpt), "--data", str(shards), "--out", str(out),
                 "--config", "tiny-cpu", "eval.resolution=[32,32]", "eval.num_tracks=8"]) == 0
    table = (out / "eval.md").read_text()
    assert "| checkpoint | 4 | 2 |" in table  # 4 videos evaluated, 2 skipped
    assert len(json.loads((out / "eval.json").read_text())["info"]["skipped"]) == 2


@pytest.mark.parametrize("damage", ["truncated", "random-bytes"])
def test_truncated_or_random_shards_are_one_line_for_every_reader(tmp_path, capsys, damage):
    shards = shard_copy(tmp_path)
    shard = shards / "train-000000.tar"
    data = shard.read_bytes()
    rng = random.Random(0)
    shard.write_bytes(data[: len(data) // 2] if damage == "truncated"
                      else bytes(rng.randrange(256) for _ in range(len(data) // 50)))
    assert main(["inspect", str(shards), "--check", "--no-progress"]) == 1
    assert "train-000000.tar" in capsys.readouterr().out
    ckpt = save_checkpoint(tmp_path / "tiny.pt", build_model(load_config("dynpt", "tiny-cpu").model), 0)
    code = main(["eval", "--ckpt", str(ckpt), "--data", str(shard), "--out", str(tmp_path / "e"),
                 "--config", "tiny-cpu", "eval.resolution=[32,32]"])
    if damage == "random-bytes":
        assert_one_line_error(code, capsys.readouterr().err, "no readable scene")
    else:  # the scene before the cut is evaluated, the rest counted as skipped
        assert code == 0 and "| checkpoint | 1 | 1 |" in (tmp_path / "e" / "eval.md").read_text()
    code = main(["train", *TRAIN, f"data.sources=[{shard}]", f"train.out_dir={tmp_path / 'r'}",
                 "train.steps=4"])
    assert_one_line_error(code, capsys.readouterr().err)


def test_shards_without_checksums_still_read_with_a_warning(tmp_path, capsys, caplog):
    shards = shard_copy(tmp_path)
    without_checksums(shards / "train-000000.tar")
    assert main(["inspect", str(shards), "--check", "--no-progress"]) == 0
    assert "checked 6 scenes in 2 shards: 0 with problems" in capsys.readouterr().out
    assert "3 scenes carry no checksums" in caplog.text


def test_webdataset_reads_the_shards_and_checksums_verify(tmp_path):
    import webdataset as wds

    shards = shard_copy(tmp_path)
    samples = list(wds.WebDataset(str(shards / "train-000000.tar"), shardshuffle=False))
    assert [s["__key__"] for s in samples] == [f"train-0000000{i}" for i in range(3)]
    assert decode_scene(samples[0]).rgb.shape == synthetic_scene(0).rgb.shape
    damaged = {**samples[1], "tracks.npy.bsz": samples[1]["tracks.npy.bsz"][:-1] + b"\0"}
    with pytest.raises(Exception, match="CRC-32"):
        decode_scene(damaged)


# --- output folders -----------------------------------------------------------------------------


@contextlib.contextmanager
def mounted(*args: str):
    """`mount ARGS` (and unmount afterwards), or skip the test with the reason it failed."""
    target = Path(args[-1])
    done = subprocess.run(["mount", *args], capture_output=True, text=True)
    if done.returncode:
        pytest.skip(f"cannot mount here ({done.stderr.strip() or 'not permitted'})")
    try:
        yield target
    finally:
        subprocess.run(["umount", "-l", str(target)], capture_output=True)


@pytest.fixture
def read_only_folder(tmp_path):
    """A folder that refuses writes, for root too (a read-only bind mount)."""
    source, target = tmp_path / "ro-source", tmp_path / "ro"
    source.mkdir(), target.mkdir()
    (source / "kept.txt").write_text("kept")
    if os.geteuid() != 0:
        target.rmdir()
        source.chmod(0o555)
        yield source
        source.chmod(0o755)
        return
    with mounted("--bind", str(source), str(target)):
        done = subprocess.run(["mount", "-o", "remount,bind,ro", str(target)], capture_output=True,
                              text=True)
        if done.returncode:
            pytest.skip(f"cannot remount read-only here ({done.stderr.strip()})")
        yield target


@pytest.fixture
def full_disk(tmp_path):
    """A 2 MB tmpfs filled to the last byte, holding one earlier file."""
    target = tmp_path / "full"
    target.mkdir()
    with mounted("-t", "tmpfs", "-o", "size=2m", "tmpfs", str(target)):
        (target / "kept.txt").write_text("kept")
        fd = os.open(target / "filler", os.O_WRONLY | os.O_CREAT)
        for block in (65536, 1):  # big blocks, then the last bytes
            with contextlib.suppress(OSError):
                while os.write(fd, b"\0" * block):
                    pass
        os.close(fd)
        yield target


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """What the writing commands read: shards, a tracker checkpoint, a video, a pointmap net."""
    from tests.test_c4d_run import ARGS, tiny_network
    import argparse
    from c4d_core.video import write_video

    folder = tmp_path_factory.mktemp("fault-inputs")
    shards = synthetic_shards(6, 3)
    ckpt = save_checkpoint(folder / "tiny.pt", build_model(load_config("dynpt", "tiny-cpu").model), 0)
    rng = np.random.default_rng(0)
    video = write_video(folder / "video.avi", rng.integers(0, 255, (4, 32, 32, 3), np.uint8), 12)
    net = folder / "dust3r_tiny.pth"
    torch.save({"model": tiny_network().state_dict(), "args": argparse.Namespace(model=ARGS)}, net)
    return {"shards": shards, "ckpt": ckpt, "video": video, "net": net}


def command(name: str, out: Path, inputs: dict) -> list[str]:
    """The arguments of command `name` writing into `out`."""
    return {
        "eval": ["eval", "--ckpt", str(inputs["ckpt"]), "--data", str(inputs["shards"]),
                 "--out", str(out), "--config", "tiny-cpu", "eval.resolution=[32,32]",
                 "eval.num_tracks=8", "eval.num_scenes=1"],
        "track": ["track", str(inputs["video"]), "--ckpt", str(inputs["ckpt"]), "--out", str(out)],
        "train": ["train", *TRAIN, f"data.sources=[{inputs['shards']}]", f"train.out_dir={out}",
                  "train.steps=3"],
        "inspect": ["inspect", str(inputs["shards"]), "--out", str(out), "--no-progress",
                    "--num-samples", "1"],
        "pretrain-pointmaps": ["pretrain-pointmaps", "--config", "tiny-cpu",
                               f"data.sources=[{inputs['shards']}]", f"train.out_dir={out}",
                               "train.steps=2", "model.patch_size=8"],
        "datagen": ["datagen", "--num-scenes", "1", "--out", str(out), "--workers", "1",
                    *TINY_DATAGEN],
        "run": ["run", str(inputs["video"]), "--pointmaps", str(inputs["net"]), "--out", str(out),
                "--size", "32", "graph.window=2", "optim.stage1_iters=2", "optim.stage2_iters=1",
                "pts.window=4", "pts.extend=1"],
    }[name]


COMMANDS = ["eval", "track", "train", "inspect", "pretrain-pointmaps", "datagen", "run"]


def no_temporaries(folder: Path) -> bool:
    return not [p for p in folder.rglob("*") if ".tmp" in p.name or p.name.endswith(".partial")]


@pytest.mark.parametrize("name", COMMANDS)
def test_an_existing_file_as_the_output_folder_is_one_line(tmp_path, capsys, inputs, name):
    target = tmp_path / "taken"
    target.write_text("kept")
    assert_one_line_error(main(command(name, target, inputs)), capsys.readouterr().err,
                          "taken", "is a file")
    assert target.read_text() == "kept"


@pytest.mark.parametrize("name", COMMANDS)
def test_a_read_only_output_folder_is_one_line(read_only_folder, capsys, inputs, name):
    out = read_only_folder / "out"
    assert_one_line_error(main(command(name, out, inputs)), capsys.readouterr().err,
                          "Read-only file system" if os.geteuid() == 0 else "ermission", str(out))
    assert (read_only_folder / "kept.txt").read_text() == "kept" and not out.exists()


@pytest.mark.parametrize("name", COMMANDS)
def test_a_full_disk_is_one_line_and_leaves_no_torn_file(full_disk, capsys, inputs, name):
    out = full_disk / "out"
    assert_one_line_error(main(command(name, out, inputs)), capsys.readouterr().err,
                          "no space left", str(out))
    assert (full_disk / "kept.txt").read_text() == "kept" and no_temporaries(full_disk)
    for config in out.rglob("config.yaml"):
        assert config.stat().st_size > 0  # written whole or not at all


# --- processes ----------------------------------------------------------------------------------


def wait_for(predicate, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.1)


def children(pid: int) -> list[int]:
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, ValueError, IndexError):
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(stat.parent.name))
    return found


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _interruptible() -> None:
    """In the child before exec: Ctrl-C's default action. A test run started in the background
    (CI) ignores SIGINT, and an ignored signal stays ignored across exec: the child would never
    see the Ctrl-C it is sent."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def datagen_process(out: Path, workers: int, num_scenes: int = 3) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "c4d", "datagen", "--num-scenes", str(num_scenes),
                             "--scenes-per-shard", "1", "--out", str(out), "--workers",
                             str(workers), *TINY_DATAGEN], env=ENV, cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_interruptible)


def test_datagen_killed_then_rerun_gives_sha_identical_shards(tmp_path):
    reference = tmp_path / "reference"
    assert main(["datagen", "--num-scenes", "2", "--scenes-per-shard", "1", "--out",
                 str(reference), "--workers", "1", *TINY_DATAGEN]) == 0
    out = tmp_path / "killed"
    proc = datagen_process(out, workers=1, num_scenes=2)
    wait_for(lambda: (out / "train-000000.tar").exists() or proc.poll() is not None, 200,
             "the first shard")
    proc.kill()
    proc.wait()
    assert main(["datagen", "--num-scenes", "2", "--scenes-per-shard", "1", "--out", str(out),
                 "--workers", "1", *TINY_DATAGEN]) == 0
    names = sorted(p.name for p in reference.iterdir())
    assert names == sorted(p.name for p in out.iterdir())
    assert [sha(reference / n) for n in names] == [sha(out / n) for n in names]


def test_datagen_workers_exit_with_their_parent_and_ctrl_c_says_what_it_finishes(tmp_path):
    proc = datagen_process(tmp_path / "a", workers=2, num_scenes=6)
    wait_for(lambda: len(children(proc.pid)) >= 3 or proc.poll() is not None, 120, "the workers")
    spawned = children(proc.pid)  # 2 workers and the resource tracker
    time.sleep(1.0)
    proc.kill()  # the parent alone
    proc.wait()
    wait_for(lambda: not any(alive(pid) for pid in spawned), 20, "the orphaned workers to exit")

    proc = datagen_process(tmp_path / "b", workers=2, num_scenes=60)  # cannot finish before the signal
    wait_for(lambda: len(children(proc.pid)) >= 3 or proc.poll() is not None, 120, "the workers")
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)  # the parent alone, not its process group
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err and "interrupted: waiting for the 2 worker(s)" in err, err[-2000:]


def train_process(out: Path, shards: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "c4d", "train", *TRAIN, f"data.sources=[{shards}]",
                             f"train.out_dir={out}", "train.ckpt_every=2", *extra],
                            env=ENV, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def log_lines(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]


def weights(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)["model"]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """An 8-step training run in one go, the reference of the resume test."""
    out = tmp_path_factory.mktemp("train") / "full"
    assert main(["train", *TRAIN, f"data.sources=[{synthetic_shards(12, 3)}]",
                 f"train.out_dir={out}", "train.ckpt_every=2", "train.steps=8"]) == 0
    return out


def assert_same_run(a: Path, b: Path) -> None:
    assert log_lines(a) == log_lines(b)  # bit-identical on one thread
    wa, wb = weights(a / "checkpoints/step_00000008.pt"), weights(b / "checkpoints/step_00000008.pt")
    assert all(torch.equal(wa[k], wb[k]) for k in wa)


def test_training_killed_then_resumed_is_bit_identical(tmp_path, uninterrupted, caplog, capsys):
    """kill -9 after the second checkpoint; the newest checkpoint is then cut short and the log
    ends in a torn line (as a crash inside the write leaves them): --resume falls back to the
    previous checkpoint, repairs the log and ends with the uninterrupted run's bytes."""
    shards = synthetic_shards(12, 3)
    out = tmp_path / "killed"
    proc = train_process(out, shards, "train.steps=8")
    ckpts = out / "checkpoints"
    wait_for(lambda: len(list(ckpts.glob("step_*.pt"))) >= 2 or proc.poll() is not None, 200,
             "two checkpoints")
    proc.kill()
    proc.wait()
    newest = sorted(ckpts.glob("step_*.pt"))[-1]
    newest.write_bytes(newest.read_bytes()[:5000])
    with open(out / "log.jsonl", "a") as f:
        f.write('{"step": 7, "lr": 0.00')
    assert main(["train", *TRAIN, f"data.sources=[{shards}]", f"train.out_dir={out}",
                 "train.ckpt_every=2", "train.steps=8", "--resume"]) == 0
    assert f"skipping {newest.name}" in caplog.text and "torn last line" in caplog.text
    assert "weights_only" not in caplog.text and "\x1b[" not in caplog.text
    assert_same_run(uninterrupted, out)


STOPPED_WORKER = """
import os, socket, sys, time
from multiprocessing import resource_sharer
from dynpt.train import _quiet_stopped_workers
if sys.argv[1] == "training":
    sys.excepthook = _quiet_stopped_workers(sys.excepthook)
read, _ = os.pipe()
resource_sharer.DupFd(read)  # a file descriptor offered to another process: the sharer's thread
client = socket.socket(socket.AF_UNIX)  # a loader worker stopped mid-handover
client.connect(resource_sharer._resource_sharer._address)
client.close()
time.sleep(1.0)
print("still running")
"""


@pytest.mark.parametrize("hook", ["training", "default"])
def test_a_worker_stopped_mid_handover_prints_no_traceback_while_training(hook):
    """The resource-sharer thread meets a connection closed by a stopped loader worker (as after
    Ctrl-C with workers): the training's excepthook prints nothing; Python's own prints the
    traceback (the control: the scenario is real)."""
    proc = subprocess.run([sys.executable, "-c", STOPPED_WORKER, hook], env=ENV, cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == "still running", proc.stderr
    assert ("Traceback" in proc.stderr) == (hook == "default"), proc.stderr


def test_training_with_loader_workers_ctrl_c_and_kill_leave_no_orphans(tmp_path):
    """Ctrl-C to a run with two DataLoader workers: exit 130 with how to go on, the workers gone,
    and --resume continues from the newest checkpoint; kill -9 of the trainer alone: its workers
    notice (PyTorch's parent watchdog) and exit."""
    shards = synthetic_shards(12, 3)

    def start(out: Path, *extra: str) -> tuple[subprocess.Popen, Path]:
        err = out.with_suffix(".err")
        with open(err, "w") as fh:  # a file, not a pipe: the per-step log must never block it
            proc = subprocess.Popen(
                [sys.executable, "-m", "c4d", "train", *TRAIN, f"data.sources=[{shards}]",
                 f"train.out_dir={out}", "train.ckpt_every=2", "train.steps=100000",
                 "data.num_workers=2", *extra], env=ENV, cwd=ROOT, stdout=subprocess.DEVNULL,
                stderr=fh, preexec_fn=_interruptible)
        return proc, err

    def running(proc: subprocess.Popen, out: Path) -> list[int]:
        wait_for(lambda: proc.poll() is not None or (
            len(list((out / "checkpoints").glob("step_*.pt"))) >= 2 and len(children(proc.pid)) >= 2),
            240, "two checkpoints with the loader workers running")
        assert proc.poll() is None
        return children(proc.pid)

    out = tmp_path / "interrupted"
    proc, err = start(out)
    workers = running(proc, out)
    proc.send_signal(signal.SIGINT)  # the trainer alone, not its process group
    assert proc.wait(timeout=120) == 130, err.read_text()[-2000:]
    text = err.read_text()
    assert "Traceback" not in text and "c4d: interrupted" in text, text[-2000:]
    assert f"`c4d train --resume train.out_dir={out}` continues from step_" in text, text[-2000:]
    wait_for(lambda: not any(alive(pid) for pid in workers), 30, "the workers to exit")
    done = log_lines(out)[-1]["step"]
    assert main(["train", *TRAIN, f"data.sources=[{shards}]", f"train.out_dir={out}",
                 "train.ckpt_every=2", f"train.steps={done + 2}", "data.num_workers=2",
                 "--resume"]) == 0
    steps = [line["step"] for line in log_lines(out)]
    assert steps == list(range(1, done + 3))  # no step twice, none lost

    out = tmp_path / "killed"
    proc, err = start(out)
    workers = running(proc, out)
    proc.kill()
    proc.wait()
    wait_for(lambda: not any(alive(pid) for pid in workers), 30, "the orphaned workers to exit")


def test_a_size_limit_during_training_leaves_whole_lines(tmp_path, capsys):
    """RLIMIT_FSIZE (EFBIG, SIGXFSZ ignored) cuts writes like a full disk, for this process only."""
    shards = synthetic_shards(12, 3)
    out = tmp_path / "run"
    args = [*TRAIN, f"data.sources=[{shards}]", f"train.out_dir={out}", "train.steps=40",
            "train.ckpt_every=100"]
    assert main(["train", *args, "train.stop_after=2"]) == 0
    size = (out / "config.yaml").stat().st_size + 100  # config.yaml is rewritten; the rest grows

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))

    run = c4d("train", *args, "--resume", preexec_fn=limit)
    assert_one_line_error(run.returncode, run.stderr, "file size limit exceeded", str(out))
    lines = (out / "log.jsonl").read_text()
    assert lines.endswith("\n") and [r["step"] for r in map(json.loads, lines.splitlines())][:2] == [1, 2]
    assert no_temporaries(out)


def test_resume_with_more_steps_continues_and_a_crash_before_the_first_checkpoint_reruns(tmp_path):
    shards = synthetic_shards(12, 3)
    out = tmp_path / "run"
    args = [*TRAIN, f"data.sources=[{shards}]", f"train.out_dir={out}", "train.ckpt_every=2"]
    assert main(["train", *args, "train.steps=4"]) == 0
    assert main(["train", *args, "train.steps=7", "--resume"]) == 0
    steps = [r["step"] for r in log_lines(out)]
    assert steps == list(range(1, 8))
    # The annealing is rebuilt to end at step 7: steps 5-7 use the rates of a 7-step schedule
    # (the same 2-step warm-up), though the 4-step run had already annealed to its end.
    opt = torch.optim.AdamW([torch.zeros(1, requires_grad=True)], lr=0.002)
    planned = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=0.002, total_steps=7,
                                                  pct_start=2 / 7, cycle_momentum=False,
                                                  div_factor=25.0, final_div_factor=10000.0)
    expected = []
    for _ in range(7):
        expected.append(opt.param_groups[0]["lr"])
        opt.step()
        planned.step()
    lrs = [r["lr"] for r in log_lines(out)]
    assert lrs[4:] == pytest.approx(expected[4:]) and lrs[3] < lrs[4]
    # A run that died before its first checkpoint: the rerun starts over without duplicate lines.
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    (fresh / ".c4d-output.json").write_text('{"format": "c4d-output", "kind": "train"}')
    (fresh / "log.jsonl").write_text('{"step": 1, "lr": 0.1}\n{"step": 2, "lr": 0.1}\n')
    assert main(["train", *TRAIN, f"data.sources=[{shards}]", f"train.out_dir={fresh}",
                 "train.steps=3"]) == 0
    assert [r["step"] for r in log_lines(fresh)] == [1, 2, 3]


# --- inputs -------------------------------------------------------------------------------------


def test_bad_inputs_are_one_line(tmp_path, capsys, inputs):
    from c4d_core.video import write_image

    small = tmp_path / "small"  # a folder of 5x5 frames
    small.mkdir()
    for t in range(3):
        write_image(small / f"{t:03d}.png", np.full((5, 5, 3), 40 * t, np.uint8))
    code = main(["track", str(small), "--ckpt", str(inputs["ckpt"]), "--out", str(tmp_path / "t")])
    assert_one_line_error(code, capsys.readouterr().err, "5x5", "17x17")
    code = main(["track", str(inputs["video"]), "--ckpt", str(tmp_path), "--out", str(tmp_path / "t")])
    assert_one_line_error(code, capsys.readouterr().err, "is a folder")
    pickled = tmp_path / "pickled.pt"
    torch.save({"format": "dynpt-checkpoint-v1", "x": io.BytesIO()}, pickled)
    code = main(["track", str(inputs["video"]), "--ckpt", str(pickled), "--out", str(tmp_path / "t")])
    err = capsys.readouterr().err
    assert_one_line_error(code, err, "Python objects")
    assert "weights_only" not in err and "\x1b[" not in err
    backgrounds = tmp_path / "backgrounds"
    backgrounds.mkdir()
    for name in ("a.png", "b.jpg", "c.png"):
        (backgrounds / name).write_bytes(b"not an image")
    code = main(["datagen", "--num-scenes", "1", "--out", str(tmp_path / "d"), *TINY_DATAGEN,
                 f"backgrounds_dir={backgrounds}"])
    assert_one_line_error(code, capsys.readouterr().err, "3 background image(s)", "a.png", "c.png")
