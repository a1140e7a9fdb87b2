"""The config loader: inheritance, validated overrides, clear errors."""

import pytest

from c4d_core.config import available_presets, load_config, parse_overrides, to_dict
from c4d_core.errors import UserError
from dynpt.model import build_model


@pytest.fixture
def preset(tmp_path):
    (tmp_path / "base.yaml").write_text(
        "seed: 0\nresolution: [256, 256]\ncamera:\n  focal_mm: 35.0\n  sensor_mm: 32.0\n"
        "lights:\n  shadows: false\npreset: base\n"
    )
    child = tmp_path / "child.yaml"
    child.write_text("_base_: base.yaml\npreset: child\ncamera:\n  focal_mm: 50.0\n")
    return child


def test_base_is_merged_under_the_child(preset):
    cfg = load_config("datagen", preset)
    assert cfg.preset == "child"
    assert cfg.camera.focal_mm == 50.0
    assert cfg.camera.sensor_mm == 32.0
    assert list(cfg.resolution) == [256, 256]


def test_overrides_set_nested_values_with_yaml_types(preset):
    cfg = load_config("datagen", preset, overrides=["camera.focal_mm=24", "resolution=[64,96]",
                                                    "lights.shadows=true", "seed=7"])
    assert cfg.camera.focal_mm == 24 and cfg.seed == 7 and cfg.lights.shadows is True
    assert to_dict(cfg)["resolution"] == [64, 96]


def test_misspelled_key_is_an_error_naming_the_key(preset):
    with pytest.raises(UserError, match=r"unknown config key `camera\.focal_m`"):
        load_config("datagen", preset, overrides=["camera.focal_m=3"])


@pytest.mark.parametrize("override, pattern", [
    ("seed=abc", r"`seed` must be int"),
    ("seed=1.5", r"`seed` must be an integer"),
    ("lights.shadows=1", r"`lights\.shadows` must be bool"),
    ("camera=3", r"`camera` is a section"),
    ("resolution=64", r"`resolution` must be list"),
])
def test_wrong_types_are_errors(preset, override, pattern):
    with pytest.raises(UserError, match=pattern):
        load_config("datagen", preset, overrides=[override])


def test_extra_config_file_is_validated_too(preset, tmp_path):
    extra = tmp_path / "extra.yaml"
    extra.write_text("camera:\n  focal_mm: 20.0\n")
    assert load_config("datagen", preset, config_files=[extra]).camera.focal_mm == 20.0
    extra.write_text("camra:\n  focal_mm: 20.0\n")
    with pytest.raises(UserError, match=r"unknown config key `camra`"):
        load_config("datagen", preset, config_files=[extra])


def test_config_is_read_only(preset):
    cfg = load_config("datagen", preset)
    with pytest.raises(Exception):
        cfg.seed = 3


@pytest.mark.parametrize("bad", ["novalue", "=3", "a.b"])
def test_malformed_override(bad):
    with pytest.raises(UserError, match="key=value"):
        parse_overrides([bad])


def test_unknown_preset_lists_the_known_ones():
    with pytest.raises(UserError, match=r"unknown datagen preset 'movi-z'"):
        load_config("datagen", "movi-z")


def test_missing_and_invalid_files(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        load_config("datagen", tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\n")
    with pytest.raises(UserError, match="not valid YAML"):
        load_config("datagen", bad)
    loop = tmp_path / "loop.yaml"
    loop.write_text("_base_: loop.yaml\n")
    with pytest.raises(UserError, match="inherits from itself"):
        load_config("datagen", loop)


@pytest.mark.parametrize("group", ["c4d", "datagen", "demo", "dynpt", "inspect", "pointmaps"])
def test_every_shipped_preset_loads(group):
    """A typo in a shipped YAML (or a key its code no longer has) fails here, not at run time."""
    names = available_presets(group)
    assert names, f"configs/{group} has no presets"
    for name in names:
        cfg = load_config(group, name)
        if group == "dynpt" and not cfg.model.encoder_3d.require_checkpoint:
            model = build_model(cfg.model)  # the architecture the preset describes builds
            assert model.parameter_counts()["trainable"] > 0
