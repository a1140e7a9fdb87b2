"""The fault suite, part "nothing hangs" (issue 44): inputs and signals that once made a command
wait forever now end it within seconds, with one line or exit 130.

- training data whose tracks are all NaN (checksums valid): no scene gives a sample, and the
  stream stops naming the source instead of drawing from it forever, with and without loader
  workers; a source with some such scenes still trains;
- a loader worker forked after OpenCV's thread pool ran in the parent (the hang of
  benchmarks/device_check.py's loader section) starts;
- Ctrl-C twice to `c4d datagen --workers 2` (to its process group, as a terminal sends it): the
  workers are killed at the second, exit 130, no traceback, finished shards kept, no temporaries;
- a named pipe or a character device where a shard, a checkpoint, a TAP-Vid pickle, a video or a
  config is read: refused before it is opened (opened, it blocks or never ends).
Every command that once hung runs in a subprocess with a timeout, so a regression fails.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from c4d_core.config import load_config
from datagen.shards import ShardWriter, encode_scene, iter_samples, scene_key
from dynpt.checkpoint import save_checkpoint
from dynpt.data import FRUITLESS_IN_A_ROW, ShardStream
from dynpt.model import build_model
from tests.dynpt_testdata import synthetic_scene, synthetic_shards
from tests.test_dynpt_data import DATA
from tests.test_faults import (ENV, ROOT, TINY_DATAGEN, TRAIN, alive, assert_one_line_error,
                               children, no_temporaries, shard_copy, wait_for)

pytestmark = pytest.mark.faults


def c4d(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """`python -m c4d ARGS` in a subprocess (one torch thread) that must end within `timeout` s."""
    return subprocess.run([sys.executable, "-m", "c4d", *args], env=ENV, cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


# --- training data without a usable track -------------------------------------------------------


def nan_track_shards(folder: Path, usable: tuple[int, ...] = (), num_scenes: int = 6) -> Path:
    """Shards (3 scenes each, checksums valid) of synthetic scenes whose tracks are all NaN, but
    for the scenes `usable`."""
    folder.mkdir()
    for shard, start in enumerate(range(0, num_scenes, 3)):
        with ShardWriter(folder / f"train-{shard:06d}.tar") as writer:
            for index in range(start, start + 3):
                scene = synthetic_scene(index)
                if index not in usable:
                    scene.tracks[:] = np.nan
                writer.write(encode_scene(scene, scene_key("train", index)))
    return folder


@pytest.mark.parametrize("workers", [0, 1])
def test_training_on_tracks_that_are_all_nan_stops_with_one_line(tmp_path, workers):
    shards = nan_track_shards(tmp_path / "nan")
    start = time.monotonic()
    run = c4d("train", *TRAIN, f"data.sources=[{shards}]", f"train.out_dir={tmp_path / 'run'}",
              "train.steps=4", f"data.num_workers={workers}")
    line = assert_one_line_error(run.returncode, run.stderr, "data.sources[0]", str(shards),
                                 "gives a training sample", f"none of {FRUITLESS_IN_A_ROW} in a row",
                                 "no track is finite", f"`c4d inspect {shards} --check`")
    assert "train-0000000" in line and time.monotonic() - start < 100


def test_a_source_with_some_scenes_without_tracks_still_trains(tmp_path):
    """A scene without a usable track is passed over, not counted as bad, and does not stop the
    stream while others of its source give samples."""
    shards = nan_track_shards(tmp_path / "some", usable=(1, 4))
    data = OmegaConf.merge(DATA, {"max_bad_fraction": 0.0, "foreign": "refuse"})
    stream = iter(ShardStream([shards], [1.0], data, seed=0))
    samples = [next(stream) for _ in range(FRUITLESS_IN_A_ROW)]  # ~2 without tracks drawn per sample
    assert {s["key"] for s in samples} == {"train-00000001", "train-00000004"}
    assert samples[-1]["counts"][1] == 0  # none counted as bad


# --- a loader worker forked after OpenCV's threads ran ------------------------------------------

OPENCV_THEN_FORK = """
import sys
import cv2
import numpy as np
from omegaconf import OmegaConf
from dynpt.data import ShardStream, make_loader
from tests.test_dynpt_data import DATA

cv2.setNumThreads(2)  # the pool device_check's 0-worker row started (all cores by default)
image = np.zeros((512, 512, 3), np.uint8)
for _ in range(20):
    cv2.GaussianBlur(image, (5, 5), 1.0)
data = OmegaConf.merge(DATA, {"max_bad_fraction": 0.0, "foreign": "refuse"})
loader = make_loader(ShardStream([sys.argv[1]], [1.0], data, seed=0), 1, 1)
print(next(iter(loader))["key"][0])
"""


def test_a_loader_worker_forked_after_opencv_threads_ran_starts():
    """The hang of device_check's loader section: a worker forked from a process whose OpenCV pool
    had threads joined them in `cv2.setNumThreads(1)` (threads of the parent only) forever."""
    proc = subprocess.Popen([sys.executable, "-c", OPENCV_THEN_FORK, str(synthetic_shards(6, 3))],
                            env=ENV, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=120)
    finally:  # a hung worker waits in C and never notices its parent gone: end the whole group
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert proc.returncode == 0 and out.startswith("train-"), err[-2000:]


# --- Ctrl-C twice to datagen --------------------------------------------------------------------


def _own_group_interruptible() -> None:
    """In the child before exec: a process group of its own (the terminal's Ctrl-C goes to a
    whole group, and this test must not send it to pytest) and Ctrl-C's default action (see
    tests/test_faults.py `_interruptible`)."""
    os.setpgid(0, 0)
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_datagen_ctrl_c_twice_to_its_group_kills_the_workers_and_exits_130(tmp_path):
    out = tmp_path / "data"
    # scenes of a few seconds each (the later flags win), so that the second Ctrl-C comes while
    # the workers still render: one Ctrl-C waits for them (~6 s here), the second kills them
    args = [*TINY_DATAGEN, "--frames", "24", "--resolution", "96x128"]
    proc = subprocess.Popen([sys.executable, "-m", "c4d", "datagen", "--num-scenes", "40",
                             "--scenes-per-shard", "1", "--out", str(out), "--workers", "2", *args],
                            env=ENV, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, preexec_fn=_own_group_interruptible)
    err: list[str] = []  # stderr as it comes, read in a thread
    reader = threading.Thread(target=lambda: err.extend(iter(proc.stderr.readline, "")), daemon=True)
    reader.start()
    try:
        wait_for(lambda: (out / "train-000001.tar").exists() or proc.poll() is not None, 200,
                 "two finished shards")
        workers = children(proc.pid)  # 2 workers and the resource tracker
        assert proc.poll() is None and len(workers) >= 2
        os.killpg(proc.pid, signal.SIGINT)
        # as a user does: the second Ctrl-C after the first is acknowledged (two signals that
        # come before Python runs its handler are one, on a loaded machine even 0.5 s apart)
        wait_for(lambda: "Ctrl-C again stops them at once" in "".join(err) or proc.poll() is not None,
                 60, "the first Ctrl-C to be acknowledged")
        os.killpg(proc.pid, signal.SIGINT)
        start = time.monotonic()
        proc.wait(timeout=60)
        reader.join(10)
        assert time.monotonic() - start < 20, "".join(err)[-2000:]
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    text = "".join(err)
    assert proc.returncode == 130, text[-2000:]
    assert "Traceback" not in text and "Ctrl-C again stops them at once" in text, text[-2000:]
    assert "c4d: interrupted" in text, text[-2000:]
    wait_for(lambda: not any(alive(pid) for pid in workers), 10, "the workers to be gone")
    assert no_temporaries(out)
    finished = sorted(out.glob("train-*.tar"))
    assert len(finished) >= 2
    for shard in finished:  # whole shards, one scene each
        assert len(list(iter_samples(shard))) == 1


# --- named pipes and devices as input files -----------------------------------------------------


@pytest.fixture
def fifo_inputs(tmp_path):
    """A shard folder whose second shard is a named pipe, a checkpoint, and named pipes as a
    checkpoint, a TAP-Vid pickle, a video and a config."""
    shards = shard_copy(tmp_path)
    (shards / "train-000001.tar").unlink()
    os.mkfifo(shards / "train-000001.tar")
    for name in ("pipe.pt", "pipe.pkl", "pipe.mp4", "pipe.yaml"):
        os.mkfifo(tmp_path / name)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", build_model(load_config("dynpt", "tiny-cpu").model), 0)
    return {"shards": shards, "ckpt": ckpt, "dir": tmp_path}


EVAL = ["--config", "tiny-cpu", "eval.resolution=[32,32]", "eval.num_tracks=8"]


def test_a_named_pipe_among_the_shards_is_named_and_nothing_waits_for_it(fifo_inputs):
    shards, pipe = fifo_inputs["shards"], fifo_inputs["shards"] / "train-000001.tar"
    named = f"{pipe} is a named pipe, not a regular file"
    run = c4d("inspect", str(shards), "--check", "--no-progress", timeout=60)
    assert run.returncode == 1 and named in run.stdout, run.stdout[-2000:] + run.stderr[-2000:]
    assert "checked 4 scenes in 2 shards: 1 with problems" in run.stdout  # the 3 of shard 0, the pipe
    run = c4d("inspect", str(shards), "--no-progress", "--out", str(fifo_inputs["dir"] / "report"),
              timeout=60)
    assert run.returncode == 0 and "1 samples could not be read" in run.stdout + run.stderr, run.stderr
    run = c4d("inspect", str(pipe), "--check", "--no-progress", timeout=60)
    assert_one_line_error(run.returncode, run.stderr, named, "give a directory, a .tar shard")
    out = fifo_inputs["dir"] / "eval"
    run = c4d("eval", "--ckpt", str(fifo_inputs["ckpt"]), "--data", str(shards), "--out", str(out),
              *EVAL)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "| checkpoint | 3 | 1 |" in (out / "eval.md").read_text()  # the pipe: skipped
    run = c4d("eval", "--ckpt", str(fifo_inputs["ckpt"]), "--data", str(pipe), "--out", str(out),
              *EVAL)
    assert_one_line_error(run.returncode, run.stderr, named)


@pytest.mark.parametrize("flag, path, words", [
    ("--ckpt", "pipe.pt", ("checkpoint", "is a named pipe, not a regular file")),
    ("--ckpt", "/dev/zero", ("checkpoint /dev/zero is a character device, not a regular file",)),
    ("--data", "pipe.pkl", ("TAP-Vid pickle", "is a named pipe, not a regular file")),
    ("--config", "pipe.yaml", ("config file", "is a named pipe, not a regular file")),
])
def test_a_named_pipe_or_a_device_as_an_input_file_of_eval_is_one_line(fifo_inputs, flag, path,
                                                                        words):
    given = {"--ckpt": str(fifo_inputs["ckpt"]), "--data": str(fifo_inputs["shards"]),
             "--config": "tiny-cpu"} | {flag: str(fifo_inputs["dir"] / path)}
    run = c4d("eval", *(a for item in given.items() for a in item), "--out",
              str(fifo_inputs["dir"] / "e"), "eval.resolution=[32,32]", timeout=60)
    assert_one_line_error(run.returncode, run.stderr, *words)


@pytest.mark.parametrize("video", ["pipe.mp4", "/dev/zero"])
def test_a_named_pipe_or_a_device_as_the_video_is_one_line(fifo_inputs, video):
    path = str(fifo_inputs["dir"] / video)  # an absolute `video` stays itself
    run = c4d("track", path, "--ckpt", str(fifo_inputs["ckpt"]), "--out",
              str(fifo_inputs["dir"] / "t"), timeout=60)
    kind = "a character device" if video == "/dev/zero" else "a named pipe"
    assert_one_line_error(run.returncode, run.stderr, f"video {path} is {kind}, not a regular file")
