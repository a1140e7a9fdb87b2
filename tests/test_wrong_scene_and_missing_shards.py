"""Issue 46, items 3 and 4, through the real commands.

- A reconstruction scored or shown against a scene it was not made from is refused in one line by
  `c4d eval-recon`, `c4d inspect RECON --gt` and `c4d view RECON --gt`: by the scene its
  report.json records (`c4d demo`'s `inputs.scene`), else by its frames (`c4d run` records only
  the video it read).
- A dataset folder missing shards its dataset file lists is named in one warning line by every
  command that reads it; `c4d inspect --check` counts the missing shards apart from the scenes
  with problems.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from c4d.cli import main
from c4d_pipeline.outputs import write_reconstruction
from datagen.shards import ShardWriter, encode_scene, scene_key
from tests.synthetic_scenes import make_box_scene
from tests.test_c4d_eval_recon import reconstruction
from tests.test_faults import assert_one_line_error, command, inputs, shard_copy  # noqa: F401 (fixture)
from tests.test_faults_outputs import write_dataset_file

# --- item 3: the scene a reconstruction was made from ---------------------------------------------


@pytest.fixture(scope="module")
def truth(tmp_path_factory) -> tuple[Path, list]:
    """A shard set of two box scenes (scene indices 0 and 1, as `c4d datagen` numbers them)."""
    folder = tmp_path_factory.mktemp("truth") / "data"
    folder.mkdir()
    scenes = [make_box_scene(num_frames=6, height=24, width=32, num_tracks=16, seed=s) for s in (0, 1)]
    with ShardWriter(folder / "test-000000.tar") as writer:
        for index, scene in enumerate(scenes):
            scene.meta["scene_index"] = index
            writer.write(encode_scene(scene, scene_key("test", index)))
    return folder, scenes


def scoring(name: str, recon: Path, gt: Path, index: int, out: Path) -> list[str]:
    """The arguments of `name` scoring or showing `recon` against scene `index` of `gt`."""
    return {
        "eval-recon": ["eval-recon", "--pred", str(recon), "--out", str(out.with_suffix(".json"))],
        "inspect": ["inspect", str(recon), "--out", str(out), "--no-progress"],
        "view": ["view", str(recon), "--save", str(out.with_suffix(".html"))],
    }[name] + ["--gt", str(gt), "--scene-index", str(index)]


def scored(name: str, out: Path) -> float | None:
    """The ATE that `name` wrote into `out` (None: `c4d view`, whose page was written)."""
    if name == "view":
        assert out.with_suffix(".html").stat().st_size > 0
        return None
    if name == "eval-recon":
        return json.loads(out.with_suffix(".json").read_text())["pose"]["ate"]
    return json.loads((out / "summary.json").read_text())["pose_errors"]["ate"]


COMMANDS = ["eval-recon", "inspect", "view"]


@pytest.mark.parametrize("name", COMMANDS)
def test_the_scene_report_json_records_is_the_only_one_scored(truth, tmp_path, capsys, name):
    gt, scenes = truth
    made = reconstruction(scenes[0])  # as `c4d demo` reconstructs scene 0 of its folder
    made.report["inputs"]["scene"] = f"{gt} #0"
    recon = write_reconstruction(made, tmp_path / "recon")
    code = main(scoring(name, recon, gt, 1, tmp_path / "wrong"))
    line = assert_one_line_error(code, capsys.readouterr().err, f"made from scene 0 of {gt} (report.json",
                                 "not from scene 1", f"--gt {gt} --scene-index 0")
    assert "reconstructs another video" not in line  # refused by the record, before the frames
    assert not (tmp_path / "wrong").exists() and not (tmp_path / "wrong.json").exists()
    assert main(scoring(name, recon, gt, 0, tmp_path / "right")) == 0
    ate = scored(name, tmp_path / "right")
    assert ate is None or ate < 1e-4


@pytest.mark.parametrize("name", COMMANDS)
def test_without_a_recorded_scene_the_frames_tell_another_scene(truth, tmp_path, capsys, name):
    gt, scenes = truth
    recon = write_reconstruction(reconstruction(scenes[1]), tmp_path / "recon")  # `c4d run`: no scene
    code = main(scoring(name, recon, gt, 0, tmp_path / "wrong"))
    assert_one_line_error(code, capsys.readouterr().err, "differ from those of scene 0",
                          "reconstructs another video")
    assert main(scoring(name, recon, gt, 1, tmp_path / "right")) == 0


# --- item 4: incomplete datasets ------------------------------------------------------------------


@pytest.fixture
def incomplete(tmp_path) -> Path:
    """A dataset of 12 scenes in 4 shards whose shards 1 and 2 (scenes 3..8) are gone."""
    shards = shard_copy(tmp_path, num_scenes=12)
    write_dataset_file(shards, num_scenes=12)
    for index in (1, 2):
        (shards / f"train-{index:06d}.tar").unlink()
    return shards


WARNING = ("{} is an incomplete dataset: 2 of the 4 shards its dataset-train.json lists are missing "
           "(6 of its 12 scenes: 3..8), so they are not read; rerun the same `c4d datagen` command "
           "to write them")


def warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if "incomplete dataset" in r.getMessage()]


@pytest.mark.parametrize("name", ["inspect", "export", "train", "eval"])
def test_every_reader_names_an_incomplete_dataset_once(incomplete, tmp_path, caplog, inputs, name):
    args = (["export", "cotracker", str(incomplete), str(tmp_path / "out")] if name == "export"
            else command(name, tmp_path / "out", {**inputs, "shards": incomplete}))
    assert main(args) == 0
    assert warnings(caplog) == [WARNING.format(incomplete)]


def test_view_of_a_scene_names_an_incomplete_dataset(truth, tmp_path, caplog):
    data = tmp_path / "data"  # the two box scenes as the first of two planned shards
    shutil.copytree(truth[0], data)
    (data / "dataset-test.json").write_text(json.dumps({
        "format_version": 3, "split": "test", "num_scenes": 4, "scenes_per_shard": 2, "num_shards": 2}))
    assert main(["view", str(data), "--scene", "1", "--save", str(tmp_path / "scene.html")]) == 0
    assert warnings(caplog) == [
        f"{data} is an incomplete dataset: 1 of the 2 shards its dataset-test.json lists are missing "
        "(2 of its 4 scenes: 2..3), so they are not read; rerun the same `c4d datagen` command to "
        "write them"]


def test_check_counts_missing_shards_apart_from_scenes_with_problems(incomplete, tmp_path, capsys,
                                                                       caplog):
    assert main(["inspect", str(incomplete), "--check", "--no-progress", "--out",
                 str(tmp_path / "check")]) == 1
    out = capsys.readouterr().out
    assert (f"{incomplete / 'train-000001.tar'}: missing, though the dataset file beside it "
            "lists it (scenes 3..5)") in out
    assert out.splitlines()[-1] == ("checked 6 scenes in 2 shards: 0 with problems (0 problems); "
                                    "2 shards missing (scenes 3..8)")
    assert warnings(caplog) == [WARNING.format(incomplete)]
    report = json.loads((tmp_path / "check" / "check.json").read_text())
    assert report["scenes"] == 6 and report["shards"] == 2 and report["problems"] == []
    assert report["missing_shards"] == [str(incomplete / f"train-{i:06d}.tar") for i in (1, 2)]
    complete = shard_copy(tmp_path / "complete")  # 6 scenes, 2 shards, as its file plans them
    write_dataset_file(complete)
    assert main(["inspect", str(complete), "--check", "--no-progress"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == \
        "checked 6 scenes in 2 shards: 0 with problems (0 problems)"
