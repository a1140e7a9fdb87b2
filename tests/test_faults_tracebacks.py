"""The fault suite, inputs that ended in a traceback (issue 44, item 3): each is now one line
naming the real cause, before anything is allocated or written where it can be known beforehand.

Cases: `c4d datagen` asked for a scene larger than the memory (frames, resolution, tracks,
physics steps; placement tries and blur samples past their schema range); `c4d run` and
`c4d track` on a GPU this machine lacks; a generated scene whose intrinsics are no camera's, in
`c4d view` and `c4d eval-recon`; a TAP-Vid entry whose points do not fit its video; a TAP-Vid
pickle whose array reconstructor names a shape larger than the file; a disk that fills up part
way through `c4d export cotracker`, `c4d export kubric` and `c4d run` (a small tmpfs: needs root,
skipped where mounting is not allowed).
"""

from __future__ import annotations

import contextlib
import os
import pickle
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from c4d.cli import main
from c4d_core.errors import UserError
from c4d_core.geometry import intrinsics_problem
from c4d_core.video import write_video
from datagen.shards import ShardWriter, encode_scene, read_scenes, scene_key
from dynpt.device import chosen_device
from tests.test_faults import (assert_one_line_error, command, inputs,  # noqa: F401  (module fixture)
                               mounted, no_temporaries)

pytestmark = pytest.mark.faults
DATAGEN = ["datagen", "--num-scenes", "1", "--workers", "1"]
# A GPU this machine lacks: any on a CPU-only torch, else the one past the last.
MISSING_GPU = f"cuda:{torch.cuda.device_count()}" if torch.cuda.is_available() else "cuda"


# --- memory: refused before anything is allocated or written -----------------------------------


@pytest.mark.parametrize("extra, words", [
    (["--frames", "100000000"], ("100000000 frames", "GiB", "available", "lower --frames")),
    (["--resolution", "4096", "--frames", "100000"], ("at 4096x4096", "--resolution")),
    (["tracks.num_points=1000000000"], ("1000000000 tracks", "(tracks ", "tracks.num_points")),
    (["physics.step_rate=1000000000"], ("(physics ", "physics.step_rate")),
    (["objects.placement_tries=100000000"], ("objects.placement_tries", "[1, 1000]")),
    (["blur.max_samples=100000000"], ("blur.max_samples", "[1, 256]")),
])
def test_datagen_beyond_the_memory_is_refused_before_anything_is_written(tmp_path, capsys, extra,
                                                                        words):
    out = tmp_path / "data"
    assert_one_line_error(main([*DATAGEN, "--out", str(out), *extra]), capsys.readouterr().err,
                          *words)
    assert not out.exists()


def test_the_presets_are_far_below_any_memory_and_the_estimate_reads_the_system(tmp_path):
    from c4d_core.config import available_presets, load_config
    from c4d_core.system import available_memory
    from datagen.generate import scene_memory

    for preset in available_presets("datagen"):
        assert sum(scene_memory(load_config("datagen", preset)).values()) < 2**30, preset
    meminfo, cgroup = tmp_path / "meminfo", tmp_path / "cgroup"
    meminfo.write_text("MemTotal:  8192 kB\nMemAvailable:  2048 kB\n")
    cgroup.mkdir()
    assert available_memory(meminfo, cgroup) == 2048 * 1024
    (cgroup / "memory.max").write_text("1000000\n")
    (cgroup / "memory.current").write_text("400000\n")
    assert available_memory(meminfo, cgroup) == 600000
    (cgroup / "memory.max").write_text("max\n")  # no limit
    assert available_memory(meminfo, cgroup) == 2048 * 1024
    assert available_memory(tmp_path / "none", tmp_path / "none") is None


# --- a GPU this machine lacks -------------------------------------------------------------------


@pytest.mark.parametrize("name", ["run", "track"])
def test_a_gpu_this_machine_lacks_is_one_line_before_anything_is_written(tmp_path, capsys, inputs,
                                                                        name):
    out = tmp_path / "out"
    device = [f"device={MISSING_GPU}"] if name == "run" else ["--device", MISSING_GPU]
    assert_one_line_error(main([*command(name, out, inputs), *device]), capsys.readouterr().err,
                          f"device {MISSING_GPU!r} requested", "use cpu" if MISSING_GPU == "cuda"
                          else "choose one of them or cpu")
    assert not out.exists() and not out.with_name("out.partial").exists()


def test_the_device_check_names_what_is_missing():
    assert chosen_device(None, 0, "2.13.0+cpu") == torch.device("cpu")
    assert chosen_device(None, 2, "2.13.0") == torch.device("cuda")
    assert chosen_device("cuda:1", 2, "2.13.0") == torch.device("cuda:1")
    for name, gpus, version, words in [
            ("cuda", 0, "2.13.0+cpu", "no CUDA GPU is available to torch 2.13.0+cpu (a CPU-only build)"),
            ("cuda:0", 0, "2.13.0", "no CUDA GPU is available to torch 2.13.0; use cpu"),
            ("cuda:1", 1, "2.13.0", "this machine has 1 CUDA GPU(s), cuda:0 to cuda:0"),
            ("tpu", 1, "2.13.0", "unknown device 'tpu'")]:
        with pytest.raises(UserError, match=re.escape(words)):
            chosen_device(name, gpus, version)


# --- intrinsics that are no camera's ------------------------------------------------------------


@pytest.fixture(scope="module")
def layered_shards(tmp_path_factory) -> Path:
    """Two generated 64x64 scenes of 4 frames with every optional layer (what the Kubric export
    needs)."""
    out = tmp_path_factory.mktemp("layered") / "data"
    assert main(["datagen", "--num-scenes", "2", "--workers", "1", "--out", str(out), "--resolution",
                 "64", "--frames", "4", "--seed", "5", "tracks.num_points=16",
                 "objects.num_static=[1,2]", "objects.num_tossed=[1,1]", "layers.normal=true",
                 "layers.object_coordinates=true", "layers.instances=true",
                 "layers.events=true"]) == 0
    return out


@pytest.fixture(scope="module")
def reconstruction(tmp_path_factory, inputs) -> Path:
    out = tmp_path_factory.mktemp("recon") / "run"
    assert main(command("run", out, inputs)) == 0
    return out


INTRINSICS = {"zero": lambda K: np.zeros_like(K), "nan": lambda K: np.where(K == 0, np.nan, K),
              "negative-focal": lambda K: K * np.array([[-1.0], [1.0], [1.0]], np.float32)}


@pytest.mark.parametrize("kind", INTRINSICS)
def test_a_scene_whose_intrinsics_are_no_camera_is_one_line_naming_it(tmp_path, capsys,
                                                                      layered_shards, reconstruction,
                                                                      kind):
    scene = next(read_scenes(layered_shards))
    scene.intrinsics = INTRINSICS[kind](scene.intrinsics)
    bad = tmp_path / "bad"
    bad.mkdir()
    with ShardWriter(bad / "train-000000.tar") as writer:
        writer.write(encode_scene(scene, scene_key("train", 0)))
    words = ("scene 'train-00000000'", str(bad / "train-000000.tar"), "intrinsics", "fx, fy > 0",
             "regenerate this shard")
    assert_one_line_error(main(["view", str(bad), "--scene", "0", "--save", str(tmp_path / "v.html")]),
                          capsys.readouterr().err, *words)
    out = tmp_path / "score.json"
    assert_one_line_error(main(["eval-recon", "--pred", str(reconstruction), "--gt", str(bad),
                                "--out", str(out)]), capsys.readouterr().err, *words)
    assert not (tmp_path / "v.html").exists() and not out.exists()


def test_intrinsics_problem_accepts_pinhole_cameras_only():
    K = np.tile(np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 31.5], [0.0, 0.0, 1.0]]), (3, 1, 1))
    assert intrinsics_problem(K) is None
    assert "shape (3, 2, 2)" in intrinsics_problem(K[:, :2, :2])
    for row, col, value in [(0, 0, 0.0), (1, 1, -50.0), (2, 2, 0.0), (1, 0, 3.0), (0, 2, np.inf)]:
        bad = K.copy()
        bad[1, row, col] = value
        assert "of 1 of 3 frames (first frame 1:" in intrinsics_problem(bad)


# --- TAP-Vid files ------------------------------------------------------------------------------


def tapvid_eval(tmp_path: Path, inputs: dict, data: Path) -> list[str]:
    return ["eval", "--ckpt", str(inputs["ckpt"]), "--data", str(data), "--out", str(tmp_path / "ev"),
            "--config", "tiny-cpu", "eval.resolution=[32,32]"]


@pytest.mark.parametrize("points, occluded", [((5, 4, 2), (5, 4)), ((5, 6, 2), (3, 6)),
                                              ((5, 6), (5, 6))])
def test_a_tapvid_entry_whose_labels_do_not_fit_its_video_is_one_line(tmp_path, capsys, inputs,
                                                                      points, occluded):
    rng = np.random.default_rng(0)
    entry = {"video": rng.integers(0, 255, (6, 32, 32, 3), np.uint8), "points": rng.random(points),
             "occluded": np.zeros(occluded, bool)}
    data = tmp_path / "tapvid_davis.pkl"
    data.write_bytes(pickle.dumps({"bear": entry}))
    assert_one_line_error(main(tapvid_eval(tmp_path, inputs, data)), capsys.readouterr().err,
                          "TAP-Vid entry 'bear'", f"points of shape {points}",
                          f"occluded of shape {occluded}", "video of shape (6, 32, 32, 3)", "T = 6")
    assert not (tmp_path / "ev").exists()


class _Reconstruct:
    """Pickles as numpy's array reconstructor called with `shape` and `dtype` (what numpy itself
    only ever calls with shape (0,))."""

    def __init__(self, shape: tuple, dtype):
        self.shape, self.dtype = shape, dtype

    def __reduce__(self):
        return np.empty(0).__reduce__()[0], (np.ndarray, self.shape, self.dtype)


@pytest.mark.parametrize("shape, dtype, words", [
    ((10**13,), b"b", ("an array of shape (10000000000000,) and dtype int8 (9313.2 GiB)",)),
    ((1,), np.dtype(("V", 2**31 - 1)), ("an array of shape (1,)", "(2.0 GiB)")),
])
def test_a_tapvid_pickle_asking_for_more_than_it_carries_is_one_line(tmp_path, capsys, inputs,
                                                                     shape, dtype, words):
    data = tmp_path / "tapvid_davis.pkl"
    data.write_bytes(pickle.dumps({"bear": {"video": _Reconstruct(shape, dtype)}}, protocol=4))
    assert_one_line_error(main(tapvid_eval(tmp_path, inputs, data)), capsys.readouterr().err,
                          f"TAP-Vid pickle {str(data)!r} asks for", *words,
                          f"more than its {data.stat().st_size} bytes can carry")


def test_an_honest_pickle_of_arrays_still_reads(tmp_path):
    from c4d_core.pickles import read_data_pickle

    arrays = {"video": np.arange(4 * 8 * 8 * 3, dtype=np.uint8).reshape(4, 8, 8, 3),
              "points": np.linspace(0, 1, 5 * 4 * 2).reshape(5, 4, 2)}
    for protocol in (2, 4, 5):
        path = tmp_path / f"p{protocol}.pkl"
        path.write_bytes(pickle.dumps(arrays, protocol=protocol))
        read = read_data_pickle(path, "TAP-Vid pickle", "")
        assert all(np.array_equal(read[k], v) and read[k].dtype == v.dtype for k, v in arrays.items())


# --- a disk that fills up part way --------------------------------------------------------------


@contextlib.contextmanager
def disk_with_room(folder: Path, kib: int):
    """A 4 MB tmpfs at `folder`, holding one earlier file, filled up to its last `kib` KiB."""
    folder.mkdir()
    with mounted("-t", "tmpfs", "-o", "size=4m", "tmpfs", str(folder)):
        (folder / "kept.txt").write_text("kept")
        stat = os.statvfs(folder)
        (folder / "filler").write_bytes(bytes(stat.f_bavail * stat.f_frsize - kib * 1024))
        yield folder


def files_of(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("fmt", ["cotracker", "kubric"])
def test_a_disk_full_during_an_export_is_one_line_naming_the_file(tmp_path, capfd, layered_shards,
                                                                  fmt):
    """Rooms that end the export in a frame's PNG (OpenCV's own write answered it with False, or
    an empty file), a depth TIFF, a flow PNG and the second scene: one line naming the file,
    no temporary left, the scenes finished before it kept whole."""
    reference = tmp_path / "reference"
    assert main(["export", fmt, str(layered_shards), str(reference)]) == 0
    for kib in (12, 20, 44, 68):
        with disk_with_room(tmp_path / f"disk{kib}", kib) as disk:
            out = disk / "out"
            code = main(["export", fmt, str(layered_shards), str(out)])
            err = capfd.readouterr().err
            line = assert_one_line_error(code, err, "no space left", str(out))
            assert "libpng" not in err and Path(line.split(" while writing ")[1].split(";")[0]).suffix
            assert (disk / "kept.txt").read_text() == "kept" and no_temporaries(disk)
            for record in out.rglob("c4d_export.json"):  # finished scenes: as in the reference
                scene = record.parent.relative_to(out)
                assert files_of(out / scene) == files_of(reference / scene), scene


@pytest.fixture(scope="module")
def video64(tmp_path_factory) -> Path:
    rng = np.random.default_rng(0)
    return write_video(tmp_path_factory.mktemp("video64") / "video.avi",
                       rng.integers(0, 255, (4, 64, 64, 3), np.uint8), 12)


def test_a_disk_full_during_run_is_one_line_naming_the_file(tmp_path, capfd, inputs, video64):
    """Rooms that end the reconstruction in its frames, depth maps (numpy's own write of a .npy
    raised an OSError without errno there) and masks: one line naming the file, nothing of the
    reconstruction left."""
    for kib in range(16, 80, 8):
        with disk_with_room(tmp_path / f"disk{kib}", kib) as disk:
            out = disk / "out"
            argv = [*command("run", out, {**inputs, "video": video64}), "--size", "64"]
            assert_one_line_error(main(argv), capfd.readouterr().err, "no space left",
                                  f"{out}.partial/")
            assert (disk / "kept.txt").read_text() == "kept" and no_temporaries(disk)
            assert not out.exists()
