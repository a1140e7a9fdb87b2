"""YAML configs: presets in `configs/<group>/`, inheritance, and validated `key=value` overrides.

A config file may start with `_base_: other.yaml` (a path relative to itself, or a list of them);
the base is loaded first and the file's keys are merged over it. Everything merged after the
preset (extra config files given with `--config`, then command-line overrides) may only set keys
the preset already has, with values of the same type: a misspelled key or a wrong type is a
`UserError` that names the key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable

import yaml
from omegaconf import DictConfig, ListConfig, OmegaConf

from c4d_core.errors import UserError

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"


def available_presets(group: str) -> list[str]:
    """Names of the presets in `configs/<group>/` (file names without `.yaml`)."""
    return sorted(p.stem for p in (CONFIG_DIR / group).glob("*.yaml"))


def resolve_preset(group: str, name_or_path: str | Path) -> Path:
    """Path of a preset given by name (`movi-e`) or by path to a YAML file."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml"):
        if not path.is_file():
            raise UserError(f"config file {str(path)!r} does not exist")
        return path
    preset = CONFIG_DIR / group / f"{name_or_path}.yaml"
    if not preset.is_file():
        names = ", ".join(available_presets(group)) or "(none)"
        raise UserError(f"unknown {group} preset {str(name_or_path)!r}; choose one of: {names}")
    return preset


def _read_yaml(path: Path, seen: tuple[Path, ...] = ()) -> DictConfig:
    """Load one YAML file with its `_base_` chain merged underneath it."""
    path = path.resolve()
    if path in seen:
        raise UserError(f"config {path} inherits from itself through `_base_`")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except OSError as exc:
        raise UserError(f"cannot read config {path}: {exc.strerror}") from exc
    except yaml.YAMLError as exc:
        raise UserError(f"config {path} is not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise UserError(f"config {path} must be a mapping of keys to values at its top level")
    bases = data.pop("_base_", [])
    merged = OmegaConf.create()
    for base in [bases] if isinstance(bases, str) else bases:
        merged = OmegaConf.merge(merged, _read_yaml(path.parent / base, seen + (path,)))
    return OmegaConf.merge(merged, OmegaConf.create(data))


def _check_against(schema: Any, update: Any, prefix: str, origin: str) -> None:
    """Raise `UserError` if `update` sets a key `schema` lacks or changes a value's type."""
    if isinstance(update, dict):
        if not isinstance(schema, (dict, DictConfig)):
            raise UserError(f"{origin}: `{prefix}` is a value, not a section")
        for key, value in update.items():
            name = f"{prefix}.{key}" if prefix else str(key)
            if key not in schema:
                known = ", ".join(sorted(str(k) for k in schema.keys()))
                raise UserError(f"{origin}: unknown config key `{name}` (known here: {known})")
            _check_against(schema[key], value, name, origin)
        return
    if schema is None or update is None or isinstance(schema, (dict, DictConfig)):
        if isinstance(schema, (dict, DictConfig)):
            raise UserError(f"{origin}: `{prefix}` is a section; set one of its keys instead")
        return
    expected = list if isinstance(schema, (list, ListConfig)) else type(schema)
    numeric = (int, float)
    if expected is float and isinstance(update, int) and not isinstance(update, bool):
        return
    if isinstance(update, bool) != (expected is bool) or (
        not isinstance(update, expected) and not (expected in numeric and type(update) in numeric)
    ):
        raise UserError(
            f"{origin}: `{prefix}` must be {expected.__name__}, got {update!r} "
            f"({type(update).__name__})"
        )
    if expected is int and isinstance(update, float):
        raise UserError(f"{origin}: `{prefix}` must be an integer, got {update!r}")


def parse_overrides(overrides: Iterable[str]) -> dict:
    """Turn `a.b=1` strings into a nested dict; values are parsed as YAML (`x=[1,2]`, `y=true`)."""
    nested: dict = {}
    for item in overrides:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise UserError(f"override {item!r} is not of the form key=value")
        try:
            value = yaml.safe_load(raw) if raw.strip() else None
        except yaml.YAMLError as exc:
            raise UserError(f"override {item!r}: value is not valid YAML ({exc})") from exc
        node = nested
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise UserError(f"override {item!r} conflicts with another override of {part}")
        node[parts[-1]] = value
    return nested


def load_config(
    group: str,
    preset: str | Path,
    config_files: Iterable[str | Path] = (),
    overrides: Iterable[str] = (),
) -> DictConfig:
    """Load preset `preset` of `configs/<group>/`, then extra files, then `key=value` overrides.

    Returns a read-only `DictConfig` (attribute access: `cfg.camera.focal_mm`).
    """
    cfg = _read_yaml(resolve_preset(group, preset))
    for extra in config_files:
        extra_path = Path(extra)
        if not extra_path.is_file():
            raise UserError(f"config file {str(extra_path)!r} does not exist")
        update = OmegaConf.to_container(_read_yaml(extra_path))
        _check_against(cfg, update, "", f"config {extra_path}")
        cfg = OmegaConf.merge(cfg, update)
    update = parse_overrides(overrides)
    _check_against(cfg, update, "", "command line")
    cfg = OmegaConf.merge(cfg, update)
    OmegaConf.set_readonly(cfg, True)
    return cfg


def add_training_arguments(parser, group: str, default: str | None = None) -> None:
    """`--config` (a preset of configs/<group> or a YAML path), `--resume` and key=value overrides,
    the arguments every training command takes."""
    parser.add_argument("--config", required=default is None, default=default,
                        help=f"a preset of configs/{group} ({', '.join(available_presets(group))}) or "
                        "a YAML path" + (f"; default {default}" if default else ""))
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in train.out_dir where it stopped")
    parser.add_argument("overrides", nargs="*", metavar="key=value",
                        help="config overrides, e.g. data.sources=[shards/train] train.steps=1000")


def to_dict(cfg: DictConfig) -> dict:
    """A plain, YAML-serialisable copy of a config (for checkpoints, meta and reports)."""
    return OmegaConf.to_container(cfg, resolve=True)
