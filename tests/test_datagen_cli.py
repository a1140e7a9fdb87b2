"""`c4d datagen` end to end on tiny real scenes: shards, determinism, tasks, resume, bad input."""

import errno
import json
import os
import subprocess
import sys
import tarfile
import time

import numpy as np
import pytest
import yaml

from c4d.cli import main
from datagen import read_scenes
from datagen.cli import parse_resolution
from test_datagen_shards import assert_scenes_equal

NUM_SCENES = 4
TINY = ["--resolution", "48x64", "--frames", "6", "tracks.num_points=24",
        "objects.num_static=[2,3]", "objects.num_tossed=[1,1]"]


def datagen_args(out, *extra, num_scenes=NUM_SCENES, per_shard=2, workers=1):
    return ["datagen", "--preset", "movi-e", "--num-scenes", str(num_scenes), "--out", str(out),
            "--scenes-per-shard", str(per_shard), "--workers", str(workers), "--seed", "3",
            *TINY, *extra]


def shard_files(out):
    return sorted(p.name for p in out.iterdir() if p.name.endswith((".tar", ".partial")))


@pytest.fixture(scope="module", autouse=True)
def no_job_array():
    """Run as a single task even where the test suite itself runs inside SLURM or torchrun."""
    with pytest.MonkeyPatch.context() as patch:
        for name in ("SLURM_ARRAY_TASK_ID", "SLURM_ARRAY_TASK_COUNT", "SLURM_ARRAY_TASK_MIN",
                     "RANK", "WORLD_SIZE"):
            patch.delenv(name, raising=False)
        yield


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """4 scenes in 2 shards, one worker: the reference the other tests compare with."""
    out = tmp_path_factory.mktemp("dataset")
    assert main(datagen_args(out)) == 0
    return out


def test_writes_shards_metadata_and_contract_scenes(dataset):
    assert shard_files(dataset) == ["train-000000.tar", "train-000001.tar"]
    record = json.loads((dataset / "dataset-train.json").read_text())
    assert record["num_scenes"] == NUM_SCENES and record["num_shards"] == 2 and record["seed"] == 3
    assert record["config"]["resolution"] == [48, 64] and record["config"]["frames"] == 6
    scenes = list(read_scenes(dataset))
    assert [s.meta["scene_index"] for s in scenes] == list(range(NUM_SCENES))
    for scene in scenes:
        assert scene.rgb.shape == (6, 48, 64, 3) and scene.rgb.dtype == np.uint8
        assert scene.depth.dtype == np.float32 and scene.segmentation.dtype == np.int32
        assert scene.tracks.shape == (24, 6, 2) and scene.moving.dtype == bool
        assert len(scene.objects) == scene.object_to_world.shape[0]
    assert not np.array_equal(scenes[0].rgb, scenes[1].rgb)


def test_same_scenes_whatever_workers_sharding_and_tasks(dataset, tmp_path):
    # Three scenes per shard, two tasks: task 1 (shard 1, one worker) and task 0 (shard 0, two workers).
    assert main(datagen_args(tmp_path, "--task-index", "1", "--num-tasks", "2", per_shard=3)) == 0
    assert shard_files(tmp_path) == ["train-000001.tar"]
    assert main(datagen_args(tmp_path, "--task-index", "0", "--num-tasks", "2", per_shard=3, workers=2)) == 0
    assert shard_files(tmp_path) == ["train-000000.tar", "train-000001.tar"]
    reference, other = list(read_scenes(dataset)), list(read_scenes(tmp_path))
    assert len(other) == NUM_SCENES
    for a, b in zip(reference, other):
        assert_scenes_equal(a, b)  # every array bit-identical


def test_killed_run_resumes_and_rerun_only_fills_gaps(dataset, tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    process = subprocess.Popen([sys.executable, "-m", "c4d", *datagen_args(tmp_path)], env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while not (tmp_path / "train-000000.tar").exists() and process.poll() is None:
            assert time.monotonic() < deadline, "the first shard never appeared"
            time.sleep(0.05)
    finally:
        process.kill()  # SIGKILL: no cleanup code runs
        process.wait()
    assert not (tmp_path / "train-000001.tar").exists(), "the run finished before it was killed"
    for name in shard_files(tmp_path):  # whatever is there under a final name is complete
        if name.endswith(".tar"):
            assert len(list(read_scenes(tmp_path / name))) == 2

    assert main(datagen_args(tmp_path)) == 0  # resume
    assert shard_files(tmp_path) == shard_files(dataset)
    for name in shard_files(dataset):  # byte-identical to an uninterrupted run
        assert (tmp_path / name).read_bytes() == (dataset / name).read_bytes()

    kept = (tmp_path / "train-000000.tar").stat().st_mtime_ns
    (tmp_path / "train-000001.tar").unlink()
    (tmp_path / "train-000001.tar.partial").write_bytes(b"stale half-written shard")
    assert main(datagen_args(tmp_path)) == 0
    assert shard_files(tmp_path) == ["train-000000.tar", "train-000001.tar"]
    assert (tmp_path / "train-000000.tar").stat().st_mtime_ns == kept
    assert (tmp_path / "train-000001.tar").read_bytes() == (dataset / "train-000001.tar").read_bytes()

    before = {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()}
    assert main(datagen_args(tmp_path)) == 0  # complete: nothing is touched
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()} == before


def test_different_config_into_same_directory_is_refused(dataset, capsys):
    before = {p.name: p.stat().st_mtime_ns for p in dataset.iterdir()}
    assert main(datagen_args(dataset, "tracks.query_stride=2")) == 2
    message = capsys.readouterr().err
    assert "different dataset" in message and "config.tracks" in message and "--out" in message
    assert main(datagen_args(dataset, num_scenes=6)) == 2
    assert "num_scenes" in capsys.readouterr().err
    assert {p.name: p.stat().st_mtime_ns for p in dataset.iterdir()} == before


def test_shards_of_another_generator_version_are_not_resumed(tmp_path, monkeypatch, capsys):
    """With dataset-train.json gone, the shards' own meta.json tells their generator version: a
    datagen of another version (whose scenes differ) refuses to resume them, in one line."""
    import datagen

    assert main(datagen_args(tmp_path, num_scenes=2, per_shard=1)) == 0
    (tmp_path / "dataset-train.json").unlink()
    before = {p.name: p.read_bytes() for p in tmp_path.glob("*.tar")}
    made_by = datagen.__version__
    monkeypatch.setattr(datagen, "__version__", "9.9.9")
    capsys.readouterr()
    assert main(datagen_args(tmp_path, num_scenes=2, per_shard=1)) == 2
    message = capsys.readouterr().err.strip()
    assert len(message.splitlines()) == 1, message
    assert "train-000000.tar was generated by datagen " + made_by in message
    assert "this is datagen 9.9.9" in message and "dataset-train.json is missing" in message
    assert {p.name: p.read_bytes() for p in tmp_path.glob("*.tar")} == before
    assert not (tmp_path / "dataset-train.json").exists()
    monkeypatch.setattr(datagen, "__version__", made_by)
    assert main(datagen_args(tmp_path, num_scenes=2, per_shard=1)) == 0  # its own version resumes
    assert json.loads((tmp_path / "dataset-train.json").read_text())["generator_version"] == made_by


def test_disk_full_is_one_clear_error_and_leaves_no_partial_shard(tmp_path, monkeypatch, capsys):
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(tarfile.TarFile, "addfile", full)
    assert main(datagen_args(tmp_path, num_scenes=1)) == 2
    (message,) = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert message.startswith("c4d: error: no space left") and "run the same command again" in message
    assert shard_files(tmp_path) == []


def test_corrected_rerun_after_a_failed_one_works(tmp_path, monkeypatch, capsys):
    """A bad value claims nothing; a run that failed before its first shard leaves no dataset
    that would refuse the corrected settings; the folder keeps the resolved config."""
    out = tmp_path / "out"
    assert main(datagen_args(out, "--resolution", "100000", num_scenes=1)) == 2
    assert "--resolution '100000'" in capsys.readouterr().err and not out.exists()
    with monkeypatch.context() as patch:  # fails after the claim, before any shard is complete
        patch.setattr(tarfile.TarFile, "addfile", lambda *a, **k: (_ for _ in ()).throw(OSError(errno.ENOSPC, "full")))
        assert main(datagen_args(out, "--frames", "4", num_scenes=1)) == 2
    assert (out / "dataset-train.json").is_file() and shard_files(out) == []
    assert main(datagen_args(out, num_scenes=1)) == 0  # other settings: replaces the empty claim
    assert shard_files(out) == ["train-000000.tar"]
    assert main(datagen_args(out, "--frames", "4", num_scenes=1)) == 2  # now the folder holds data
    assert "different dataset" in capsys.readouterr().err
    kept = yaml.safe_load((out / "config-train.yaml").read_text())
    assert kept == json.loads((out / "dataset-train.json").read_text())["config"]
    assert main(["config", "show", "datagen/movi-e", "seed=3", "resolution=[48,64]", "frames=6",
                 "tracks.num_points=24", "objects.num_static=[2,3]", "objects.num_tossed=[1,1]"]) == 0
    assert yaml.safe_load(capsys.readouterr().out) == kept


@pytest.mark.parametrize("extra, expected", [
    (["--assets", "/nonexistent/meshes"], "asset folder '/nonexistent/meshes' does not exist"),
    (["--preset", "movi-z"], "unknown datagen preset 'movi-z'"),
    (["seed=5"], "`seed` is set both by a flag"),
    (["--resolution", "64x"], "--resolution '64x'"),
    (["--task-index", "2", "--num-tasks", "2"], "task index 2 is not in [0, 2)"),
    (["--workers", "0"], "--workers must be at least 1"),
    (["tracks.num_pointz=3"], "unknown config key `tracks.num_pointz`"),
])
def test_bad_input_is_a_user_error(tmp_path, capsys, extra, expected):
    assert main(datagen_args(tmp_path / "out", *extra)) == 2
    assert expected in capsys.readouterr().err
    assert not (tmp_path / "out").exists() or shard_files(tmp_path / "out") == []


def test_task_without_shards_does_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "5")
    monkeypatch.setenv("SLURM_ARRAY_TASK_COUNT", "6")
    assert main(datagen_args(tmp_path)) == 0  # 2 shards, 6 tasks: task 5 has none
    assert shard_files(tmp_path) == [] and (tmp_path / "dataset-train.json").is_file()


def test_missing_egl_is_a_user_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PYOPENGL_PLATFORM", "osmesa")
    assert main(datagen_args(tmp_path)) == 2
    assert "PYOPENGL_PLATFORM" in capsys.readouterr().err


def test_pyopengl_too_old_for_the_python_is_a_user_error(tmp_path, monkeypatch, capsys):
    from c4d_core import system

    assert system.pyopengl_problem((3, 11), "3.1.0") is None
    assert system.pyopengl_problem((3, 12), "3.1.9") is None
    assert system.pyopengl_problem((3, 13), "3.1.10") is None
    assert system.pyopengl_problem((3, 12), None) is None
    assert "PyOpenGL>=3.1.7" in system.pyopengl_problem((3, 12), "3.1.0")
    # the command: one line naming the fix, exit 2, before anything is written
    real = system.pyopengl_problem  # this Python and PyOpenGL as if 3.12 with pyrender's pin
    monkeypatch.setattr(system, "pyopengl_problem", lambda python, version: real((3, 12), "3.1.0"))
    assert main(datagen_args(tmp_path)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "PyOpenGL 3.1.0 cannot render on Python 3.12" in err[0], err
    assert shard_files(tmp_path) == []


def test_resolution_forms():
    assert parse_resolution("256") == [256, 256]
    assert parse_resolution("384x512") == [384, 512]
    assert parse_resolution("384X512") == [384, 512]


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the dropped one
def test_ctrl_c_dropped_by_a_finaliser_still_stops_the_run():
    """A KeyboardInterrupt raised inside `__del__` is printed and dropped by Python; the run must
    still stop at its next check (it once went on to write every shard and exit 0)."""
    import gc
    import signal

    from datagen import cli as datagen_cli

    class SignalsWhenCollected:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)  # the handler runs here, inside the finaliser

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal
    try:
        with datagen_cli._interrupt_flag():
            datagen_cli._check_interrupt()  # nothing pending yet
            SignalsWhenCollected()  # collected at once: the KeyboardInterrupt is dropped
            gc.collect()
            with pytest.raises(KeyboardInterrupt):
                datagen_cli._check_interrupt()
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a background job keeps ignoring Ctrl-C
        with datagen_cli._interrupt_flag():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)
