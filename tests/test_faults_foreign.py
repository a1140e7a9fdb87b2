"""The fault suite, foreign shards: a dataset folder is one dataset.

A shard that does not belong to the dataset its folder's `dataset-SPLIT.json` describes (another
seed, size or config with the same scene keys; scene keys of another shard; an index beyond
`num_shards`; a name not of `shard_pattern`) is refused by `c4d train`, `c4d eval` and
`c4d inspect --check` with one line naming the file, and skipped with a warning by train and eval
where the user asked for it (`data.foreign=skip`, `eval.foreign=skip`).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from c4d.cli import main
from tests.test_faults import TINY_DATAGEN, TRAIN, assert_one_line_error

pytestmark = pytest.mark.faults

TINY = [a for a in TINY_DATAGEN if a not in ("--seed", "5")]


def datagen(out: Path, *extra: str) -> Path:
    assert main(["datagen", "--num-scenes", "3", "--scenes-per-shard", "1", "--out", str(out),
                 "--workers", "1", *TINY, *extra]) == 0
    return out


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    """Three tiny datasets of 3 one-scene shards: seed 5, seed 6, and seed 5 with another config."""
    root = tmp_path_factory.mktemp("foreign")
    return {"own": datagen(root / "own", "--seed", "5"),
            "seed": datagen(root / "seed", "--seed", "6"),
            "config": datagen(root / "config", "--seed", "5", "camera.focal_mm=50")}


def spoiled(tmp_path: Path, datasets: dict, case: str) -> tuple[Path, Path]:
    """A copy of the own dataset with one foreign file put in; (folder, the foreign file)."""
    folder = tmp_path / "data"
    shutil.copytree(datasets["own"], folder)
    target = folder / "train-000001.tar"
    source = {"seed": datasets["seed"] / target.name, "config": datasets["config"] / target.name,
              "moved": folder / "train-000002.tar", "index": folder / "train-000002.tar",
              "name": folder / "train-000002.tar"}[case]
    target = {"index": folder / "train-000007.tar", "name": folder / "train-2.tar"}.get(case, target)
    shutil.copyfile(source, target)
    return folder, target


CASES = {"seed": "is from another dataset (seed 6, the dataset's 5)",
         "config": "is from another dataset (another config: config_digest",
         "moved": "scene 'train-00000002' does not belong to this shard",
         "index": "shard index 7 is beyond its num_shards=3",
         "name": "its name is not of the dataset's shard_pattern"}

EVAL = ["--config", "tiny-cpu", "eval.resolution=[32,32]", "eval.num_tracks=8"]


@pytest.fixture(scope="module")
def tracker(tmp_path_factory):
    from c4d_core.config import load_config
    from dynpt.checkpoint import save_checkpoint
    from dynpt.model import build_model

    path = tmp_path_factory.mktemp("tracker") / "tiny.pt"
    return save_checkpoint(path, build_model(load_config("dynpt", "tiny-cpu").model), 0)


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_foreign_shard_is_refused_by_train_eval_and_check(tmp_path, capsys, datasets, tracker, case):
    folder, foreign = spoiled(tmp_path, datasets, case)
    runs = {
        "train": ["train", *TRAIN, "data.num_frames=4", f"data.sources=[{folder}]",
                  f"train.out_dir={tmp_path / 'run'}", "train.steps=3"],
        "eval": ["eval", "--ckpt", str(tracker), "--data", str(folder), "--out", str(tmp_path / "e"),
                 *EVAL],
    }
    for name, argv in runs.items():
        code = main(argv)
        line = assert_one_line_error(code, capsys.readouterr().err, str(foreign), CASES[case])
        assert f"{'data' if name == 'train' else 'eval'}.foreign=skip" in line, line
    assert not (tmp_path / "e").exists()
    code = main(["inspect", str(folder), "--check", "--no-progress"])
    out = capsys.readouterr().out
    assert code == 1 and str(foreign) in out and CASES[case] in out, out
    # the own dataset as it was is clean
    assert main(["inspect", str(datasets["own"]), "--check", "--no-progress"]) == 0


def test_foreign_shards_are_skipped_with_a_warning_on_request(tmp_path, capsys, caplog, datasets, tracker):
    folder, foreign = spoiled(tmp_path, datasets, "seed")
    code = main(["train", *TRAIN, "data.num_frames=4", f"data.sources=[{folder}]",
                 f"train.out_dir={tmp_path / 'run'}", "train.steps=3", "data.foreign=skip"])
    assert code == 0, capsys.readouterr().err[-2000:]
    assert "skipping the rest of a shard of another dataset" in caplog.text and str(foreign) in caplog.text
    caplog.clear()
    code = main(["eval", "--ckpt", str(tracker), "--data", str(folder), "--out", str(tmp_path / "e"),
                 *EVAL, "eval.foreign=skip"])
    assert code == 0, capsys.readouterr().err[-2000:]
    assert "skipping the rest of a shard of another dataset" in caplog.text
    report = (tmp_path / "e" / "eval.json").read_text()
    assert '"num_videos": 2' in report or '"num_videos": 2.0' in report, report[:500]


def test_a_scene_key_that_repeats_inside_a_shard_is_refused(tmp_path, capsys, datasets):
    from datagen.shards import ShardWriter, iter_samples

    folder = tmp_path / "data"
    shutil.copytree(datasets["own"], folder)
    shard = folder / "train-000000.tar"
    (sample,) = list(iter_samples(shard))
    sample = {k: v for k, v in sample.items() if not k.startswith("__") or k == "__key__"}
    with ShardWriter(shard) as writer:
        writer.write(sample)
        writer.write(sample)
    code = main(["inspect", str(folder), "--check", "--no-progress"])
    out = capsys.readouterr().out
    assert code == 1 and "scene key 'train-00000000' repeats" in out and str(shard) in out, out
