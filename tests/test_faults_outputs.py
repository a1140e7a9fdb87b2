"""The fault suite, continued: failed last writes, odd output paths and shard sets that lie.

Like tests/test_faults.py, every case runs real commands and checks the contract of a fault: one
`c4d: error:` line, exit 2, no traceback, no torn or temporary file left. Kinds:
- a file size limit (RLIMIT_FSIZE) that strikes in the last flush of a shard;
- a full disk (a small tmpfs) while OpenCV writes a video: its writer ignores the failed
  writes, so the video is decoded again before it is renamed into place;
- a codec OpenCV lacks; output paths with a name too long, a dangling symbolic link, a folder
  that refuses new entries;
- shards against their dataset file (`dataset-train.json`): a shard cut at a scene boundary, a
  folder named like a shard, an unreadable shard counted as the scenes it held, a format 3
  scene without `checksums.json`, a listed shard that is absent.
Mounts need root (or the right capability): those cases skip with the reason where not allowed.
"""

from __future__ import annotations

import json
import logging
import re
import resource
import signal
import tarfile
from pathlib import Path

import pytest
from omegaconf import OmegaConf

import c4d_core.video
from c4d.cli import main
from c4d_core.errors import UserError
from datagen.shards import iter_samples
from dynpt.data import ShardStream
from tests.test_dynpt_data import DATA
from tests.test_faults import inputs  # noqa: F401 (a fixture)
from tests.test_faults import (COMMANDS, TINY_DATAGEN, assert_one_line_error, c4d, command,
                               delete_member, mounted, no_temporaries, shard_copy)

pytestmark = pytest.mark.faults


def test_a_size_limit_in_the_last_shard_flush_leaves_no_partial_file(tmp_path):
    reference = tmp_path / "reference"
    assert main(["datagen", "--num-scenes", "1", "--out", str(reference), "--workers", "1",
                 *TINY_DATAGEN]) == 0
    size = (reference / "train-000000.tar").stat().st_size  # the end blocks come with close()

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (size - 100, size - 100))

    out = tmp_path / "limited"
    run = c4d("datagen", "--num-scenes", "1", "--out", str(out), "--workers", "1", *TINY_DATAGEN,
              preexec_fn=limit)
    assert_one_line_error(run.returncode, run.stderr, "file size limit exceeded",
                          str(out / "train-000000.tar"))
    assert not list(out.glob("train-*")) and no_temporaries(out)


def test_a_full_disk_while_opencv_writes_a_video_is_one_line_and_leaves_no_video(
        tmp_path, capsys, inputs):
    reference = tmp_path / "reference"
    assert main(command("track", reference, inputs)) == 0
    tracks, video = ((reference / name).stat().st_size for name in ("tracks.npz", "overlay.mp4"))
    page = 4096
    room = -(-tracks // page) * page + max(video // 2 // page, 1) * page  # tracks, half the video
    (tmp_path / "small").mkdir()
    with mounted("-t", "tmpfs", "-o", f"size={room}", "tmpfs", str(tmp_path / "small")) as small:
        out = small / "out"
        capsys.readouterr()
        assert_one_line_error(main(command("track", out, inputs)), capsys.readouterr().err,
                              "no space left", str(out / "overlay.mp4"))
        assert (out / "tracks.npz").is_file() and not (out / "overlay.mp4").exists()
        assert no_temporaries(out)


def test_a_codec_opencv_lacks_is_one_line(tmp_path, capsys, inputs, monkeypatch):
    monkeypatch.setitem(c4d_core.video._VIDEO_CODECS, ".webm", "XXXX")  # no such encoder
    out = tmp_path / "report"
    code = main(["inspect", str(inputs["shards"]), "--out", str(out), "--no-progress",
                 "--num-samples", "1", "--video-format", ".webm"])
    assert_one_line_error(code, capsys.readouterr().err, "cannot encode .webm", ".gif or .avi")
    assert no_temporaries(out)


@pytest.mark.parametrize("name", COMMANDS)
def test_a_name_too_long_is_one_line(tmp_path, capsys, inputs, name):
    out = tmp_path / ("x" * 300)
    assert_one_line_error(main(command(name, out, inputs)), capsys.readouterr().err,
                          "name is too long", "shorter path")


def test_a_dangling_link_or_a_refusing_folder_as_the_output_is_one_line(tmp_path, capsys, inputs):
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "nowhere")
    assert_one_line_error(main(command("inspect", link, inputs)), capsys.readouterr().err,
                          str(link), "dangling symbolic link", str(tmp_path / "nowhere"))
    assert link.is_symlink() and not (tmp_path / "nowhere").exists()
    out = Path("/proc/c4d-test-output")  # procfs refuses new entries with ENOENT
    if not Path("/proc/self").exists():
        pytest.skip("no /proc here")
    assert_one_line_error(main(command("inspect", out, inputs)), capsys.readouterr().err,
                          str(out), "cannot be created in /proc")


# --- shards against their dataset file ----------------------------------------------------------


def write_dataset_file(shards: Path, num_scenes: int = 6, per_shard: int = 3) -> None:
    """What `c4d datagen` records beside its shards (the keys the readers use)."""
    (shards / "dataset-train.json").write_text(json.dumps({
        "format": "c4d-datagen-shards", "format_version": 3, "split": "train",
        "num_scenes": num_scenes, "scenes_per_shard": per_shard,
        "num_shards": -(-num_scenes // per_shard)}))


def test_a_shard_cut_at_a_scene_boundary_yields_its_last_complete_scene(tmp_path):
    shard = shard_copy(tmp_path) / "train-000000.tar"
    with tarfile.open(shard) as tar:
        cut = next(m.offset for m in tar.getmembers() if m.name.startswith("train-00000002."))
    shard.write_bytes(shard.read_bytes()[:cut])
    keys = []
    with pytest.raises(UserError, match="no end-of-archive marker"):
        for sample in iter_samples(shard):
            keys.append(sample["__key__"])
    assert keys == ["train-00000000", "train-00000001"]
    # A cut inside the last member of scene 1: scene 1 is incomplete, so not yielded.
    shard.write_bytes(shard.read_bytes()[:cut - 1024])
    keys.clear()
    with pytest.raises(UserError):
        for sample in iter_samples(shard):
            keys.append(sample["__key__"])
    assert keys == ["train-00000000"]


def test_a_folder_named_like_a_shard_is_named_as_a_folder(tmp_path, capsys):
    shards = shard_copy(tmp_path)
    (shards / "train-000002.tar").mkdir()
    assert main(["inspect", str(shards), "--check", "--no-progress"]) == 1
    out = capsys.readouterr().out
    assert "train-000002.tar" in out and "is a folder, not a shard" in out


def test_an_unreadable_shard_counts_as_the_scenes_it_held(tmp_path, caplog, inputs):
    shards = shard_copy(tmp_path)
    write_dataset_file(shards)
    (shards / "train-000001.tar").write_bytes(b"\x01" * 4096)  # 3 scenes per the dataset file
    data = OmegaConf.merge(DATA, {"max_bad_fraction": 1.0})  # count, never stop
    stream = iter(ShardStream([shards], [1.0], data, seed=5))
    with caplog.at_level(logging.WARNING, logger="dynpt.data"):
        samples = [next(stream) for _ in range(3)]
    warned = [m for m in caplog.messages if "skipping bad training data" in m]
    assert warned, caplog.text
    bad, read = map(int, re.search(r"\((\d+) of (\d+) samples bad so far\)", warned[0]).groups())
    assert bad == 3 and read >= 3  # never "1 bad of 0 samples"
    assert samples[-1]["counts"][1] % 3 == 0  # only whole shards are lost here
    # Evaluation counts them too: 3 scenes evaluated, 3 skipped.
    out = tmp_path / "eval"
    assert main(["eval", "--ckpt", str(inputs["ckpt"]), "--data", str(shards), "--out", str(out),
                 "--config", "tiny-cpu", "eval.resolution=[32,32]", "eval.num_tracks=8"]) == 0
    assert "| checkpoint | 3 | 3 |" in (out / "eval.md").read_text()


def test_a_format_3_scene_without_checksums_is_a_problem(tmp_path, capsys):
    shards = shard_copy(tmp_path)
    delete_member(shards / "train-000000.tar", "train-00000001.checksums.json")
    assert main(["inspect", str(shards), "--check", "--no-progress"]) == 0  # format unknown: 2
    capsys.readouterr()
    write_dataset_file(shards)
    assert main(["inspect", str(shards), "--check", "--no-progress"]) == 1
    out = capsys.readouterr().out
    assert "train-00000001" in out and "lacks its member 'checksums.json'" in out
    assert "checked 6 scenes in 2 shards: 1 with problems" in out


def test_check_names_a_shard_the_dataset_file_lists_but_the_folder_lacks(tmp_path, capsys):
    shards = shard_copy(tmp_path, num_scenes=9)
    write_dataset_file(shards, num_scenes=9)
    (shards / "train-000001.tar").unlink()
    assert main(["inspect", str(shards), "--check", "--no-progress"]) == 1
    out = capsys.readouterr().out
    assert re.search(r"train-000001\.tar: missing, though the dataset file beside it lists it "
                     r"\(scenes 3\.\.5\)", out), out
    assert ("checked 6 scenes in 2 shards: 0 with problems (0 problems); 1 shard missing "
            "(scenes 3..5)") in out
