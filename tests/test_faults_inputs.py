"""The fault suite, arguments and config files: each mistake is one line before anything is written.

Cases: a config file that is not UTF-8 and one that is malformed YAML (for `--config` and
`c4d config show`), `c4d track` with a negative seed or a frame rate of 0 or NaN, `device=tpu`
for `c4d run` (and `--device tpu` for track and eval), `c4d inspect` failing on its arguments
(no empty `--out` left), `c4d run` into a folder that already holds a reconstruction or other
files, and a real reconstruction scored against another ground-truth scene.
"""

from __future__ import annotations

import resource
import signal
from pathlib import Path

import pytest

from c4d.cli import main
from c4d_core.video import write_video
from datagen.shards import read_scenes
from tests.dynpt_testdata import generated_shards
from tests.test_faults import assert_one_line_error, c4d, command, inputs  # noqa: F401  (module fixture)

pytestmark = pytest.mark.faults


@pytest.fixture
def bad_yaml(tmp_path) -> dict[str, Path]:
    latin1 = tmp_path / "latin1.yaml"
    latin1.write_bytes("# réglages\ntrain:\n  steps: 3\n".encode("latin-1"))
    malformed = tmp_path / "malformed.yaml"
    malformed.write_text("train:\n  steps: [1, 2\n  lr: 3\n")
    return {"latin1": latin1, "malformed": malformed}


@pytest.mark.parametrize("how", ["config show", "--config", "train --config"])
def test_a_config_file_that_is_not_utf8_is_one_line(tmp_path, capsys, bad_yaml, how):
    path = bad_yaml["latin1"]
    argv = {"config show": ["config", "show", f"dynpt/{path}"],
            "--config": ["config", "show", "dynpt/tiny-cpu", "--config", str(path)],
            "train --config": ["train", "--config", str(path), f"train.out_dir={tmp_path / 'r'}"]}[how]
    assert_one_line_error(main(argv), capsys.readouterr().err, str(path), "not UTF-8",
                          "byte 0xe9 on line 1", "save it as UTF-8")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("how", ["config show", "--config"])
def test_malformed_yaml_is_one_line_with_its_line_and_column(capsys, bad_yaml, how):
    path = bad_yaml["malformed"]
    argv = {"config show": ["config", "show", f"dynpt/{path}"],
            "--config": ["config", "show", "dynpt/tiny-cpu", "--config", str(path)]}[how]
    line = assert_one_line_error(main(argv), capsys.readouterr().err, str(path),
                                 "not valid YAML at line 3, column 5", "expected ',' or ']'")
    assert "^" not in line and '"<unicode string>"' not in line  # PyYAML's quoted source is not shown
    code = main([*argv, "--verbose"])  # the whole of PyYAML's text, with the traceback
    assert code == 2 and "in \"<unicode string>\", line 3, column 5" in capsys.readouterr().err


@pytest.mark.parametrize("flag,value,words", [
    ("--seed", "-1", ("--seed must be 0 or more",)),
    ("--fps", "0", ("--fps must be a positive number",)),
    ("--fps", "nan", ("--fps must be a positive number", "nan")),
    ("--device", "tpu", ("`--device` = tpu", "cpu, cuda or cuda:N")),
])
def test_track_checks_its_numbers_before_writing(tmp_path, capsys, inputs, flag, value, words):
    out = tmp_path / "t"
    argv = [*command("track", out, inputs), flag, value]
    assert_one_line_error(main(argv), capsys.readouterr().err, *words)
    assert not out.exists()


def test_a_device_that_does_not_exist_is_one_line_for_run_and_eval(tmp_path, capsys, inputs):
    out = tmp_path / "r"
    assert_one_line_error(main([*command("run", out, inputs), "device=tpu"]), capsys.readouterr().err,
                          "`device` = tpu", "cpu, cuda or cuda:N")
    assert not out.exists() and not out.with_name("r.partial").exists()
    assert_one_line_error(main([*command("eval", out, inputs), "--device", "tpu"]),
                          capsys.readouterr().err, "`--device` = tpu")
    assert not out.exists()


def test_inspect_leaves_no_empty_output_folder_when_its_arguments_fail(tmp_path, capsys, inputs):
    empty = tmp_path / "no-shards"
    empty.mkdir()
    for source in (tmp_path / "missing", empty):
        out = tmp_path / "new" / "report"
        assert_one_line_error(main(["inspect", str(source), "--out", str(out), "--no-progress"]),
                              capsys.readouterr().err, str(source))
        assert not (tmp_path / "new").exists()
    kept = tmp_path / "kept"  # a folder that was there before is left as it was
    kept.mkdir()
    assert main(["inspect", str(empty), "--out", str(kept), "--no-progress"]) == 2
    assert kept.is_dir()


def test_run_into_a_reconstruction_or_a_full_folder_and_scoring_another_scene(tmp_path, capsys,
                                                                              inputs):
    shards = generated_shards()  # real scenes: the frames tell them apart
    scene = next(iter(read_scenes(shards)))
    video = write_video(tmp_path / "scene0.avi", scene.rgb, 12)
    out = tmp_path / "recon"
    argv = [*command("run", out, {**inputs, "video": video}), "graph.window=3"]
    assert main(argv) == 0
    first = (out / "report.json").read_bytes()
    # scored against its own scene, and against another one: the other is refused in one line
    assert main(["eval-recon", "--pred", str(out), "--gt", str(shards), "--scene-index", "0"]) == 0
    assert_one_line_error(main(["eval-recon", "--pred", str(out), "--gt", str(shards),
                                "--scene-index", "1"]), capsys.readouterr().err,
                          "reconstructs another video")
    # into the same folder again: refused unless --overwrite; nothing of the first is touched
    assert_one_line_error(main(argv), capsys.readouterr().err, str(out),
                          "already holds a reconstruction", "--overwrite")
    assert (out / "report.json").read_bytes() == first
    # --overwrite with fewer frames: the new reconstruction replaces the old one whole
    assert main([*argv, "--overwrite", "video.max_frames=3", "graph.window=2"]) == 0
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["000000.png", "000001.png",
                                                                  "000002.png"]
    assert not out.with_name("recon.partial").exists()
    # an --overwrite that fails while writing (a file size limit, as a full disk) keeps the old one
    kept = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))

    run = c4d(*argv, "--overwrite", preexec_fn=limit)
    assert_one_line_error(run.returncode, run.stderr, "file size limit exceeded", str(out))
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == kept
    assert not out.with_name("recon.partial").exists()
    # a folder of other files is never written into
    other = tmp_path / "notes"
    other.mkdir()
    (other / "notes.txt").write_text("kept")
    assert_one_line_error(main([*command("run", other, inputs), "--overwrite"]),
                          capsys.readouterr().err, str(other), "files that c4d did not write")
    assert [p.name for p in other.iterdir()] == ["notes.txt"]
