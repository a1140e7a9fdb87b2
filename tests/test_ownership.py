"""Every command owns its outputs (c4d_core.ownership): the data-lost cases of the fault campaign.

Each case runs the real commands: a command pointed at another command's output is refused with
one line and the other output is left byte for byte; `--overwrite` replaces it, and a replacement
that fails puts the old output back. Folders written before markers existed are recognised by the
files their kind writes.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest

from c4d.cli import main
from c4d_core.errors import UserError
from c4d_core.ownership import (MARKER, check_file, file_kind, folder_kind, mark_png,
                                output_folder)
from c4d_core.video import encode_image
from tests.test_faults import inputs  # noqa: F401 (a fixture)
from tests.test_faults import assert_one_line_error, command

pytestmark = pytest.mark.faults


def digest(folder: Path) -> dict[str, str]:
    """sha256 of every file below `folder`, by relative path."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def outputs(tmp_path_factory, inputs):
    """One output of each kind the cases need: a dataset, a DynPT run, a pointmap run, a
    reconstruction (made once; each test copies what it damages)."""
    root = tmp_path_factory.mktemp("owned")
    made = {"datagen": root / "data", "train": root / "run", "pretrain-pointmaps": root / "pm",
            "run": root / "recon"}
    for kind, folder in made.items():
        assert main(argv(kind, folder, inputs, made["datagen"])) == 0, kind
    return made


def argv(kind: str, out: Path, inputs: dict, data: Path | None = None) -> list[str]:
    """`command(kind, out, inputs)`; pretraining reads a generated dataset (it needs depth)."""
    args = command(kind, out, inputs)
    if kind == "pretrain-pointmaps":
        args = [f"data.sources=[{data}]" if a.startswith("data.sources=") else a for a in args]
    return args


def copy_of(outputs: dict, kind: str, tmp_path: Path) -> Path:
    target = tmp_path / kind
    shutil.copytree(outputs[kind], target)
    return target


def test_every_command_marks_its_output_folder(outputs):
    for kind, folder in outputs.items():
        assert json.loads((folder / MARKER).read_text()) == {"format": "c4d-output", "kind": kind}
        assert folder_kind(folder) == kind


@pytest.mark.parametrize("writer,victim", [("pretrain-pointmaps", "train"),
                                           ("train", "pretrain-pointmaps"),
                                           ("train", "run"), ("pretrain-pointmaps", "run"),
                                           ("run", "train"), ("datagen", "run"),
                                           ("inspect", "datagen"), ("track", "run"),
                                           ("eval", "train")])
def test_a_command_refuses_a_folder_another_kind_made(tmp_path, capsys, inputs, outputs, writer,
                                                      victim):
    folder = copy_of(outputs, victim, tmp_path)
    before = digest(folder)
    assert_one_line_error(main(argv(writer, folder, inputs, outputs["datagen"])),
                          capsys.readouterr().err,
                          str(folder), f"`c4d {victim}`", "--overwrite")
    assert digest(folder) == before


def test_a_folder_written_before_markers_is_still_recognised(tmp_path, capsys, inputs, outputs):
    for kind in outputs:
        folder = copy_of(outputs, kind, tmp_path)
        (folder / MARKER).unlink()
        assert folder_kind(folder) == kind
    before = digest(tmp_path / "train")
    assert_one_line_error(main(argv("pretrain-pointmaps", tmp_path / "train", inputs)),
                          capsys.readouterr().err, "DynPT training run", "--overwrite")
    assert digest(tmp_path / "train") == before
    # its own kind adopts it: training resumes and the folder gets its marker
    assert main([*command("train", tmp_path / "train", inputs), "--resume", "train.steps=4"]) == 0
    assert folder_kind(tmp_path / "train") == "train" and (tmp_path / "train" / MARKER).is_file()


def test_overwrite_replaces_another_kind_and_a_failure_puts_the_old_back(tmp_path, capsys, inputs,
                                                                         outputs):
    folder = copy_of(outputs, "run", tmp_path)
    before = digest(folder)
    # a replacement that fails (pretraining on no data) leaves the reconstruction as it was
    args = [*argv("pretrain-pointmaps", folder, inputs, outputs["datagen"]), "--overwrite"]
    bad = [a if not a.startswith("data.sources=") else "data.sources=[]" for a in args]
    assert_one_line_error(main(bad), capsys.readouterr().err, "data.sources")
    assert digest(folder) == before
    assert not [p for p in tmp_path.iterdir() if ".replaced" in p.name]
    # one that succeeds replaces it whole
    assert main(args) == 0
    assert folder_kind(folder) == "pretrain-pointmaps" and (folder / "pointmap_net.pth").is_file()
    assert not (folder / "poses_tum.txt").exists()
    assert not [p for p in tmp_path.iterdir() if ".replaced" in p.name]


def test_files_c4d_did_not_write_are_never_replaced(tmp_path, capsys, inputs):
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "notes.txt").write_text("kept")
    for argv in (command("track", folder, inputs), [*command("track", folder, inputs), "--overwrite"]):
        assert_one_line_error(main(argv), capsys.readouterr().err, "holds files that c4d did not "
                              "write", "notes.txt")
    assert [p.name for p in folder.iterdir()] == ["notes.txt"]


def test_view_does_not_save_over_a_shard(tmp_path, capsys, outputs):
    data = copy_of(outputs, "datagen", tmp_path)
    shard = sorted(data.glob("*.tar"))[0]
    before = digest(data)
    assert_one_line_error(main(["view", str(data), "--scene", "0", "--save", str(shard)]),
                          capsys.readouterr().err, str(shard), "was not written by `c4d view`",
                          "--overwrite")
    # nor a new page into the dataset folder
    assert_one_line_error(main(["view", str(data), "--scene", "0", "--save",
                                str(data / "page.html")]),
                          capsys.readouterr().err, "dataset of shards", "--overwrite")
    assert digest(data) == before
    # its own page it replaces; it carries its kind
    page = tmp_path / "page.html"
    for _ in range(2):
        assert main(["view", str(data), "--scene", "0", "--save", str(page)]) == 0
    assert file_kind(page) == "view"


def test_eval_recon_does_not_write_over_the_poses(tmp_path, capsys, outputs):
    recon = copy_of(outputs, "run", tmp_path)
    data = outputs["datagen"]
    before = digest(recon)
    assert_one_line_error(main(["eval-recon", "--pred", str(recon), "--gt", str(data),
                                "--scene-index", "0", "--out", str(recon / "poses_tum.txt")]),
                          capsys.readouterr().err, "poses_tum.txt", "was not written by "
                          "`c4d eval-recon`")
    assert digest(recon) == before


def test_eval_recon_writes_its_companion_file_into_the_reconstruction(tmp_path, outputs):
    """`eval_recon.json` is the one file a reconstruction accepts from another command (its default
    place); rerunning replaces it, since it carries its kind."""
    from c4d_pipeline.outputs import read_reconstruction

    recon = copy_of(outputs, "run", tmp_path)
    for _ in range(2):
        check_file(recon / "eval_recon.json", "eval-recon")
        (recon / "eval_recon.json").write_text(json.dumps({"c4d_output": "eval-recon"}))
    assert file_kind(recon / "eval_recon.json") == "eval-recon"
    with pytest.raises(UserError, match="reconstruction made by `c4d run`"):
        check_file(recon / "other.json", "eval-recon")
    read_reconstruction(recon)  # still whole


def test_marked_files_are_told_from_others(tmp_path):
    png = tmp_path / "shot.png"
    data = encode_image(__import__("numpy").zeros((4, 5, 3), "uint8"), ".png")
    png.write_bytes(data)
    assert file_kind(png) is None
    png.write_bytes(mark_png(data, "view"))
    assert file_kind(png) == "view"
    import cv2

    assert cv2.imread(str(png)).shape == (4, 5, 3)  # still a valid PNG
    (tmp_path / "a.json").write_text('{"c4d_output": "eval-recon", "x": 1}')
    (tmp_path / "b.json").write_text('{"x": 1}')
    assert file_kind(tmp_path / "a.json") == "eval-recon" and file_kind(tmp_path / "b.json") is None
    with pytest.raises(UserError, match="was not written by `c4d eval-recon`"):
        check_file(tmp_path / "b.json", "eval-recon")
    assert check_file(tmp_path / "b.json", "eval-recon", overwrite=True) == tmp_path / "b.json"


def test_a_failed_command_leaves_no_folder_it_created(tmp_path):
    target = tmp_path / "a" / "b"
    with pytest.raises(RuntimeError):
        with output_folder(target, "inspect"):
            raise RuntimeError("failed before writing")
    assert not (tmp_path / "a").exists()
