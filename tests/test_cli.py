"""The `c4d` command shell: help, subcommand list, one-line errors."""

import subprocess
import sys

from c4d.cli import SUBCOMMANDS, main


def run_c4d(*args):
    return subprocess.run([sys.executable, "-m", "c4d", *args], capture_output=True, text=True)


def test_help_lists_every_subcommand():
    result = run_c4d("--help")
    assert result.returncode == 0
    for name in SUBCOMMANDS:
        assert name in result.stdout


def test_every_subcommand_has_help():
    for name in SUBCOMMANDS:
        result = run_c4d(name, "--help")
        assert result.returncode == 0, (name, result.stderr)
        assert "usage: c4d " + name in result.stdout


def test_unknown_subcommand_fails():
    result = run_c4d("frobnicate")
    assert result.returncode != 0
    assert "invalid choice" in result.stderr


def test_user_error_is_one_line_without_traceback(tmp_path):
    result = run_c4d("datagen", "--preset", "movi-z", "--num-scenes", "1", "--out", str(tmp_path))
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [result.stderr.strip()]
    assert "unknown datagen preset 'movi-z'" in result.stderr
    assert "Traceback" not in result.stderr


def test_verbose_shows_the_traceback(tmp_path):
    result = run_c4d("--verbose", "datagen", "--preset", "movi-z", "--num-scenes", "1",
                     "--out", str(tmp_path))
    assert result.returncode == 2
    assert "Traceback" in result.stderr


def test_main_returns_exit_code_in_process(tmp_path, capsys):
    code = main(["datagen", "--preset", "movi-z", "--num-scenes", "1", "--out", str(tmp_path)])
    assert code == 2
    assert "c4d: error:" in capsys.readouterr().err


def test_overrides_may_follow_options():
    from c4d.cli import parse_arguments

    args = parse_arguments(["train", "--config", "tiny-cpu", "train.steps=3", "--resume", "seed=2"])
    assert args.overrides == ["train.steps=3", "seed=2"] and args.resume
    args = parse_arguments(["inspect", "data", "--out", "report", "samples=2"])
    assert args.source == "data" and args.overrides == ["samples=2"]


def test_stray_arguments_are_still_rejected():
    result = run_c4d("train", "--config", "tiny-cpu", "--bogus")
    assert result.returncode == 2 and "unrecognized arguments: --bogus" in result.stderr
