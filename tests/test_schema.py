"""The settings schema: one set of keys in YAML and code, range checks at load time, `c4d config show`."""

import dataclasses
import re
from pathlib import Path

import pytest
import yaml

from c4d.cli import main
from c4d_core.config import config_dir, load_config, section_defaults, to_dict, to_yaml
from c4d_core.errors import UserError
from c4d_core.schema import ROOTS, RULES, leaf_keys, rule_for, validate
from c4d_pipeline.motion_mask import MotionMaskConfig
from dynpt.losses import LossWeights

REPO = Path(__file__).resolve().parents[1]


def root_keys(group: str) -> set[str]:
    """Every key of `group`: the leaves of its root preset."""
    return set(leaf_keys(to_dict(load_config(group, ROOTS[group]))))


@pytest.mark.parametrize("group", sorted(ROOTS))
def test_every_schema_key_is_in_the_root_preset_and_its_default_is_valid(group):
    """The rules and the root preset list the same keys (a family rule `SECTION.*` standing for
    the keys of its section, at least one), and every default passes its rule."""
    keys = root_keys(group)
    assert sorted(k for k in keys if rule_for(group, k) is None) == []
    own = {k for k in RULES[group] if not k.endswith(".*")}
    assert sorted(own - keys) == []
    families = {k[:-1] for k in RULES[group] if k.endswith(".*")}
    assert all(any(k.startswith(f) for k in keys) for f in families), families
    validate(group, to_dict(load_config(group, ROOTS[group])))


def test_a_key_without_a_rule_is_refused_and_a_family_rule_covers_its_section():
    cfg = to_dict(load_config("c4d", "default"))
    cfg["weights"]["any_new_objective"] = 0.5
    validate("c4d", cfg)  # `weights.*`: a new objective's weight needs no rule of its own
    cfg["weights"]["any_new_objective"] = -1
    with pytest.raises(UserError, match="weights.any_new_objective.*-1"):
        validate("c4d", cfg)
    cfg["weights"]["any_new_objective"] = 0.5
    cfg["optim"]["nope"] = 1
    with pytest.raises(UserError, match="`optim.nope` has no rule"):
        validate("c4d", cfg)


@pytest.mark.parametrize("group", sorted(ROOTS))
def test_every_preset_sets_only_schema_keys_and_passes_the_rules(group):
    for path in sorted((config_dir() / group).rglob("*.yaml")):
        if path.parent.name == group:  # presets (model/ holds fragments of dynpt presets)
            cfg = to_dict(load_config(group, path.stem))
            assert set(leaf_keys(cfg)) == root_keys(group), path


@pytest.mark.parametrize("cls, group, section", [
    (MotionMaskConfig, "c4d", "motion_mask.c4d"), (LossWeights, "dynpt", "loss")])
def test_dataclasses_have_the_yaml_keys_and_defaults(cls, group, section):
    fields = {f.name: f.default for f in dataclasses.fields(cls)}
    assert fields == section_defaults(group, section)
    for name, value in fields.items():  # the field's type is the rule's
        kind = RULES[group][f"{section}.{name}"].kind
        assert isinstance(value, {"int": int, "float": float, "bool": bool}[kind]), name


def test_review_findings_of_the_motion_mask_section():
    # one Sampson threshold: the dataclass default is the YAML's (they were 0.5 and 1.0)
    assert MotionMaskConfig().sampson_threshold_px == load_config("c4d", "default").motion_mask.c4d.sampson_threshold_px
    # the fields missing from the YAML are keys now
    cfg = load_config("c4d", "default", overrides=["motion_mask.c4d.noise_sigmas=3", "motion_mask.c4d.max_pair_offset=1",
                                                   "motion_mask.c4d.judge_out_of_view=true"])
    mask = MotionMaskConfig(**to_dict(cfg.motion_mask.c4d))
    assert (mask.noise_sigmas, mask.max_pair_offset, mask.judge_out_of_view) == (3, 1, True)


@pytest.mark.parametrize("group, override, message", [
    ("datagen", "resolution=[7,7]", "`resolution` = [7, 7] is out of range: it must be a list of 2 integers in [8, 4096]"),
    ("datagen", "resolution=[0,0]", "`resolution` = [0, 0]"),
    ("datagen", "resolution=[64,64,3]", "`resolution` = [64, 64, 3]"),
    ("datagen", "frames=1", "`frames` = 1 is out of range: it must be an integer >= 2"),
    ("datagen", "split=dev", "must be one of: train, val, test"),
    ("datagen", "objects.num_static=[20,10]", "non-decreasing"),
    ("datagen", "objects.static_region=[[1,1,1],[0,0,0]]", "`objects.static_region`"),
    ("datagen", "lights.sun_elevation_deg=[30,100]", "in [0, 90]"),
    ("datagen", "camera.zfar=0.05", "`camera.znear` = 0.1 must be < `camera.zfar` = 0.05"),
    ("dynpt", "train.batch_size=0", "`train.batch_size` = 0 is out of range: it must be an integer >= 1"),
    ("dynpt", "data.num_frames=0", "`data.num_frames` = 0"),
    ("dynpt", "data.num_frames=1", "`data.num_frames` = 1 is out of range: it must be an integer >= 2"),
    ("dynpt", "data.crop_size=[100000,100000]", "`data.crop_size` = [100000, 100000]"),
    # the tracker's floor: 16 px crops ended in a torch ValueError after the run folder was made
    ("dynpt", "data.crop_size=[16,16]", "`data.crop_size` = [16, 16] is out of range: it must be a list of 2 integers in [17, 4096]"),
    ("dynpt", "model.resolution=[16,64]", "`model.resolution` = [16, 64]"),
    ("dynpt", "eval.resolution=[64,16]", "`eval.resolution` = [64, 16]"),
    ("dynpt", "train.steps=2", "`train.steps` = 2 is out of range: it must be an integer >= 3"),
    ("dynpt", "data.augment.hflip_prob=1.5", "in [0, 1]"),
    ("dynpt", "data.weights=[1.0]", "one entry per `data.sources`"),
    ("dynpt", "model.hidden_dim=33", "multiple of `model.num_heads`"),
    ("dynpt", "eval.query_mode=last", "one of: first, strided"),
    ("c4d", "motion_mask.c4d.sampson_threshold_px=-1", "`motion_mask.c4d.sampson_threshold_px` = -1"),
    ("c4d", "optim.betas=[0.9]", "a list of 2 numbers"),
    ("c4d", "video.stride=0", "`video.stride` = 0"),
    ("c4d", "video.max_frames=1", "`video.max_frames` = 1 is out of range: it must be 0 or an integer >= 2"),
    ("c4d", "video.max_frames=-1", "`video.max_frames` = -1"),
    ("c4d", "pointmaps.size=100000", "`pointmaps.size` = 100000 is out of range: it must be an integer in [0, 4096]"),
    ("demo", "recon.num_scenes=100", "must be <= `data.val_scenes`"),
    ("demo", "data.frames=1", "`data.frames` = 1"),
    ("demo", "train.steps=2", "`train.steps` = 2"),
    ("inspect", "samples=-1", "`samples` = -1"),
    ("pointmaps", "train.batch_size=0", "`train.batch_size` = 0"),
])
def test_out_of_range_values_are_one_line_errors(group, override, message):
    with pytest.raises(UserError) as error:
        load_config(group, ROOTS[group], overrides=[override])
    assert message in str(error.value) and "\n" not in str(error.value)


def test_the_tracker_floor_is_dynpts_own_and_zero_stays_valid_where_it_means_all():
    from c4d_core.schema import TRACKER_MIN_SIDE
    from dynpt.inference import MIN_SIDE

    assert TRACKER_MIN_SIDE == MIN_SIDE
    for override in ("data.crop_size=[17,17]", "model.resolution=[17,4096]", "model.resolution=null"):
        load_config("dynpt", "tiny-cpu", overrides=[override])
    cfg = load_config("c4d", "default", overrides=["video.max_frames=0", "pointmaps.size=0"])
    assert cfg.video.max_frames == 0 and cfg.pointmaps.size == 0


def test_nan_and_wrong_list_items_are_refused():
    for override in ("optim.lr=.nan", "resolution=[64.5,64]", "data.presets=[1]"):
        group = {"optim": "c4d", "resolution": "datagen", "data": "demo"}[override.split(".")[0].split("=")[0]]
        with pytest.raises(UserError, match="out of range"):
            load_config(group, ROOTS[group], overrides=[override])


@pytest.mark.parametrize("argv, message", [
    (["datagen", "--num-scenes", "1", "--resolution", "100000"], "--resolution '100000'"),
    (["datagen", "--num-scenes", "1", "resolution=[0,0]"], "`resolution` = [0, 0]"),
    (["datagen", "--num-scenes", "1", "resolution=[64,64,3]"], "`resolution` = [64, 64, 3]"),
    (["datagen", "--num-scenes", "1", "--frames", "0"], "`frames` = 0"),
    (["datagen", "--num-scenes", "0"], "--num-scenes must be at least 1"),
    (["train", "--config", "tiny-cpu", "train.batch_size=0"], "`train.batch_size` = 0"),
    (["train", "--config", "tiny-cpu", "data.num_frames=1"], "`data.num_frames` = 1"),
    (["train", "--config", "tiny-cpu", "data.crop_size=[100000,100000]"], "`data.crop_size`"),
    (["train", "--config", "tiny-cpu", "data.crop_size=[16,16]"], "`data.crop_size` = [16, 16]"),
    (["train", "--config", "tiny-cpu", "train.steps=2"], "`train.steps` = 2"),
    (["train", "--resume"], "to resume (no config.yaml there); start one with --config"),
    (["train"], "give --config"),
    (["pretrain-pointmaps", "train.batch_size=0"], "`train.batch_size` = 0"),
    (["demo", "--quick", "data.frames=1"], "`data.frames` = 1"),
])
def test_commands_refuse_bad_values_before_writing_anything(argv, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "out"
    flag = {"datagen": ["--out", str(out)], "demo": ["--out", str(out)]}.get(argv[0], [f"train.out_dir={out}"])
    assert main([*argv, *flag]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert list(tmp_path.iterdir()) == []


def test_resume_needs_only_the_run_folder(tmp_path, capsys):
    """`c4d train --resume train.out_dir=DIR` without --config (argparse required it) reads
    DIR/config.yaml: its data.sources get training as far as the missing checkpoint, where the
    root preset's empty sources would have stopped it with "no training data"."""
    run = tmp_path / "run"
    run.mkdir()
    saved = load_config("dynpt", "tiny-cpu", overrides=["data.sources=[shards/of-the-run]", f"train.out_dir={run}"])
    (run / "config.yaml").write_text(to_yaml(saved))
    assert main(["train", "--resume", f"train.out_dir={run}"]) == 2
    err = capsys.readouterr().err
    assert "--resume: no checkpoint in" in err and len(err.strip().splitlines()) == 1, err


def test_config_show_prints_what_runs(capsys, tmp_path):
    assert main(["config", "show", "c4d/tiny", "optim.lr=0.02", "motion_mask.c4d.noise_sigmas=3"]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert shown == to_dict(load_config("c4d", "tiny", overrides=["optim.lr=0.02", "motion_mask.c4d.noise_sigmas=3"]))
    assert shown["optim"]["stage1_iters"] == 60 and shown["optim"]["lr"] == 0.02  # tiny over the defaults
    mine = tmp_path / "mine.yaml"
    mine.write_text("_base_: datagen/movi-f\nframes: 6\n")  # a user's file over a shipped preset, by name
    assert main(["config", "show", f"datagen/{mine}"]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert shown["frames"] == 6 and shown["blur"]["max_shutter"] == 2.0 and shown["preset"] == "movi-f"
    assert main(["config", "show", "dynpt/tiny-cpu", "train.batch_size=0"]) == 2
    assert main(["config", "show", "nope/x"]) == 2
    assert "GROUP/PRESET" in capsys.readouterr().err


def test_base_by_name_must_name_a_group(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("_base_: tiny\n")
    with pytest.raises(UserError, match="<group>/<preset>"):
        load_config("c4d", bad)
    bad.write_text("_base_: c4d/nope\n")
    with pytest.raises(UserError, match="unknown c4d preset 'nope'"):
        load_config("c4d", bad)


# `key.sub=value` placeholders in prose, not settings
PLACEHOLDERS = {"key.sub", "a.b", "this.style.width"}  # the last: JavaScript in the inspect HTML
OVERRIDE = re.compile(r"(?<![\w.\-/$])([a-z][a-z0-9_]*(?:\.[a-z0-9_]+)+)=(?!=)")


def _documenting_files():
    files = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md")), *sorted((REPO / "configs").rglob("*.yaml"))]
    for package in ("c4d", "datagen", "dynpt", "c4d_pipeline", "benchmarks"):
        files += sorted((REPO / package).rglob("*.py"))
    return files


def _documented_keys():
    for path in _documenting_files():
        for key in OVERRIDE.findall(path.read_text()):
            if key not in PLACEHOLDERS:
                yield path.relative_to(REPO), key


def test_docs_and_code_name_only_real_keys():
    """Every `a.b=...` override in README, docs, presets and code names a key (or section) of
    some group's schema (docs/TRAINING.md once named `pointmaps.checkpoint=`, no key then)."""
    known = {prefix for group in ROOTS for key in root_keys(group)
             for prefix in (".".join(key.split(".")[:n]) for n in range(1, key.count(".") + 2))}
    found = list(_documented_keys())
    assert len(found) > 50  # the pattern finds the overrides
    assert [f"{path}: {key}" for path, key in found if key not in known] == []


# the config group each command's key=value overrides set (None: the command takes none);
# `c4d config show GROUP/PRESET` names its group itself
COMMAND_GROUPS = {"datagen": "datagen", "inspect": "inspect", "pretrain-pointmaps": "pointmaps",
                  "train": "dynpt", "eval": "dynpt", "run": "c4d", "demo": "demo", "track": None,
                  "eval-recon": None}
COMMAND = re.compile(r"(?:\bc4d +([a-z][a-z-]*)|-m +dynpt\.cli_train)([^`\n]*)")
COMMAND_END = re.compile(r"`|\s#|[|;)\"']|&&")  # a command line ends at these
TOKEN = re.compile(r"([a-z][a-z0-9_.]*)=")


def _documented_command_keys():
    """(file, command, group, key) of every key=value on a `c4d COMMAND ...` line of the docs,
    presets and code (backslash-continued lines joined)."""
    for path in _documenting_files():
        text = re.sub(r"\\\n\s*", " ", path.read_text())
        for match in COMMAND.finditer(text):
            command, tokens = match.group(1) or "train", COMMAND_END.split(match.group(2))[0].split()
            if command == "config":
                if len(tokens) < 2 or tokens[0] != "show" or tokens[1].split("/")[0] not in RULES:
                    continue  # prose, or GROUP/PRESET itself
                group = tokens[1].split("/")[0]
            elif command in COMMAND_GROUPS:
                group = COMMAND_GROUPS[command]
            else:
                continue  # prose: "c4d reconstructs ..."
            for token in tokens:
                if TOKEN.match(token):
                    yield path.relative_to(REPO), command, group, TOKEN.match(token).group(1)


def test_documented_commands_set_keys_of_their_own_group():
    """Each documented `c4d COMMAND` line's key=value overrides (dotted or not) are keys of that
    command's config group (`c4d run ... frames=6` names a datagen key: refused when run)."""
    found = list(_documented_command_keys())
    assert len(found) > 30 and {"train", "eval", "config"} <= {c for _, c, _, _ in found}
    keys = {group: root_keys(group) for group in ROOTS}
    wrong = [f"{path}: c4d {command} {key}=" for path, command, group, key in found
             if key not in keys.get(group, set())]
    assert wrong == []
