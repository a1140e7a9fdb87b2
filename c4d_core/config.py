"""YAML configs: presets in `configs/<group>/`, inheritance, and validated `key=value` overrides.

The presets ship inside the installed package (`configs/` of the source tree is installed as the
package `c4d_configs`, found with importlib.resources), so they work from a wheel, an sdist and an
editable install alike; a source checkout run without installing reads its `configs/` folder.

A config file may start with `_base_: other.yaml` (a path relative to itself), `_base_: c4d/tiny`
(a shipped preset by name: `<group>/<preset>`, no `.yaml`), or a list of them; the bases are
loaded first and the file's keys are merged over them. A config is the group's schema defaults
(its root preset, `c4d_core.schema.ROOTS`), then the preset, then extra files given with `--config`,
then command-line overrides; each may only set keys the root has, with values of the same type
(a misspelled key or a wrong type is a `UserError` that names the key), and the result must pass
the group's range rules (`c4d_core.schema.RULES`) before any command writes anything.
"""

from __future__ import annotations

import functools
import importlib.resources
import json
import re
from pathlib import Path
from typing import Any, Iterable, Mapping

import yaml
from omegaconf import DictConfig, ListConfig, OmegaConf

from c4d_core import schema
from c4d_core.errors import UserError
from c4d_core.files import check_regular_file

YAML_HINT = "give the path of a YAML file"  # what to do about a config path that is no file


@functools.lru_cache(maxsize=None)
def config_dir() -> Path:
    """The folder of the shipped presets: the installed package `c4d_configs`, or, in a source
    checkout run without installing (PYTHONPATH), the checkout's `configs/`."""
    try:
        return Path(str(importlib.resources.files("c4d_configs")))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[1] / "configs"


def available_presets(group: str) -> list[str]:
    """Names of the presets in `configs/<group>/` (file names without `.yaml`)."""
    return sorted(p.stem for p in (config_dir() / group).glob("*.yaml"))


def resolve_preset(group: str, name_or_path: str | Path) -> Path:
    """Path of a preset given by name (`movi-e`) or by path to a YAML file."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml"):
        if not path.is_file():
            check_regular_file(path, "config file", YAML_HINT)
            raise UserError(f"config file {str(path)!r} does not exist")
        return path
    preset = config_dir() / group / f"{name_or_path}.yaml"
    if not preset.is_file():
        names = ", ".join(available_presets(group)) or "(none)"
        raise UserError(f"unknown {group} preset {str(name_or_path)!r}; choose one of: {names}")
    return preset


def yaml_problem(exc: yaml.YAMLError) -> str:
    """PyYAML's error in one line: where (line:column, 1-based) and what, e.g. "not valid YAML at
    line 3, column 8: expected ',' or ']', but got ':'". Its full text (the quoted source and
    caret) stays on the exception, which `--verbose` prints."""
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    problem = getattr(exc, "problem", None) or getattr(exc, "context", None) or str(exc)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return f"not valid YAML{where}: {' '.join(str(problem).split())}"


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping (PyYAML would keep the
    last one without a word; YAML says keys are unique). Keys merged in with `<<` may repeat."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        lines: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                repeated = key in lines
            except TypeError:  # an unhashable key: the base class refuses it below
                continue
            if repeated:
                raise yaml.constructor.ConstructorError(
                    None, None, f"the key {key!r} is given twice in one mapping (also on line "
                    f"{lines[key]}); keep one", key_node.start_mark)
            lines[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep)


def _load_yaml(text: str) -> Any:
    """The value of YAML `text`, read as `yaml.safe_load` reads it but with unique keys."""
    return yaml.load(text, Loader=_UniqueKeyLoader)


def _read_yaml(path: Path, seen: tuple[Path, ...] = ()) -> DictConfig:
    """Load one YAML file with its `_base_` chain merged underneath it."""
    path = path.resolve()
    if path in seen:
        raise UserError(f"config {path} inherits from itself through `_base_`")
    check_regular_file(path, "config", YAML_HINT)  # a named pipe would never be read to its end
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise UserError(f"cannot read config {path}: {exc.strerror}") from exc
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise UserError(f"config {path} is not UTF-8 text (byte 0x{raw[exc.start]:02x} on line "
                        f"{line}); save it as UTF-8") from exc
    try:
        data = _load_yaml(text) or {}
    except yaml.YAMLError as exc:
        raise UserError(f"config {path}: {yaml_problem(exc)}") from exc
    if not isinstance(data, dict):
        raise UserError(f"config {path} must be a mapping of keys to values at its top level")
    bases = data.pop("_base_", [])
    merged = OmegaConf.create()
    for base in [bases] if isinstance(bases, str) else bases:
        merged = OmegaConf.merge(merged, _read_yaml(_base_path(path, str(base)), seen + (path,)))
    return OmegaConf.merge(merged, OmegaConf.create(data))


def _base_path(path: Path, base: str) -> Path:
    """The file a `_base_` entry of `path` names: a YAML path relative to `path`, or a shipped
    preset `<group>/<preset>`."""
    if Path(base).suffix in (".yaml", ".yml"):
        return path.parent / base
    group, _, name = base.rpartition("/")
    if not group:
        raise UserError(f"config {path}: `_base_: {base}` must be a YAML path or <group>/<preset>, "
                        "e.g. c4d/tiny")
    return resolve_preset(group, name)


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
            value = _load_yaml(raw) if raw.strip() else None
        except yaml.YAMLError as exc:
            raise UserError(f"override {item!r}: value is {yaml_problem(exc)}") from exc
        node = nested
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise UserError(f"override {item!r} conflicts with another override of {part}")
        node[parts[-1]] = value
    return nested


def refuse_override_as_positional(value: str, name: str, rest: Iterable[str], usage: str) -> None:
    """`UserError` where the positional argument `name` (VIDEO, SOURCE) holds a `key=value`
    override (argparse fills positionals in order): the overrides were put before it, or it was
    left out. `rest`: the overrides parsed after it (it is among them when it came later);
    `usage`: the command's form, e.g. `c4d run VIDEO --pointmaps CKPT --out DIR [key=value ...]`."""
    key, sep, _ = value.partition("=")
    if not sep or not re.fullmatch(r"[A-Za-z_][\w.]*", key) or Path(value).exists():
        return
    moved = next((item for item in rest if "=" not in item), None)
    where = (f"the override {value!r} stands before {name} {moved!r}" if moved else
             f"{name} is missing: {value!r} in its place is a key=value override")
    raise UserError(f"{where}; give {name} first and the overrides after it: {usage}")


def load_config(
    group: str,
    preset: str | Path,
    config_files: Iterable[str | Path] = (),
    overrides: Iterable[str] = (),
) -> DictConfig:
    """Load preset `preset` of `configs/<group>/`, then extra files, then `key=value` overrides,
    over the group's schema defaults, and check every value against the group's rules.

    Returns a read-only `DictConfig` (attribute access: `cfg.camera.focal_mm`).
    """
    path = resolve_preset(group, preset)
    cfg = _read_yaml(path)
    if group in schema.ROOTS:
        root = _root(group)
        _check_against(root, OmegaConf.to_container(cfg), "", f"config {path}")
        cfg = OmegaConf.merge(root, cfg)
    for extra in config_files:
        extra_path = Path(extra)
        if not extra_path.is_file():
            check_regular_file(extra_path, "config file", YAML_HINT)
            raise UserError(f"config file {str(extra_path)!r} does not exist")
        update = OmegaConf.to_container(_read_yaml(extra_path))
        _check_against(cfg, update, "", f"config {extra_path}")
        cfg = OmegaConf.merge(cfg, update)
    update = parse_overrides(overrides)
    _check_against(cfg, update, "", "command line")
    cfg = OmegaConf.merge(cfg, update)
    if group in schema.ROOTS:
        schema.validate(group, OmegaConf.to_container(cfg, resolve=True))
    OmegaConf.set_readonly(cfg, True)
    return cfg


@functools.lru_cache(maxsize=None)
def _root(group: str) -> DictConfig:
    """The root preset of `group`: every key with its default (read once, read-only)."""
    cfg = _read_yaml(resolve_preset(group, schema.ROOTS[group]))
    OmegaConf.set_readonly(cfg, True)
    return cfg


def section_defaults(group: str, section: str) -> dict:
    """The defaults of one section of a group (`section_defaults("c4d", "motion_mask.c4d")`)."""
    node = _root(group)
    for part in section.split("."):
        node = node[part]
    return OmegaConf.to_container(node, resolve=True)


def defaults_from(group: str, section: str):
    """Class decorator, placed under `@dataclass`: the fields' defaults are the root preset's
    `section`, so the dataclass and the YAML cannot disagree; its fields must be exactly the
    section's keys (else `TypeError` at import)."""
    def apply(cls):
        values, names = section_defaults(group, section), list(cls.__annotations__)
        if set(names) != set(values):
            raise TypeError(f"{cls.__name__} fields {sorted(names)} differ from the keys of "
                            f"{group} `{section}` {sorted(values)}")
        for name in names:
            value = values[name]
            setattr(cls, name, tuple(value) if isinstance(value, list) else value)
        return cls
    return apply


def flag_overrides(flags: Mapping[str, Any], overrides: Iterable[str]) -> list[str]:
    """The `key=value` overrides that command-line flags stand for (`flags`: config key -> the
    flag's value, None when the flag was not given); a key set both ways is a `UserError`."""
    given = parse_overrides(overrides)
    result = []
    for key, value in flags.items():
        if value is None:
            continue
        if _has_key(given, key):
            raise UserError(f"`{key}` is set both by a flag and by `{key}=...`; give it once")
        result.append(f"{key}={json.dumps(value)}")
    return result


def _has_key(nested: dict, key: str) -> bool:
    *parents, last = key.split(".")
    for part in parents:
        nested = nested.get(part)
        if not isinstance(nested, dict):
            return False
    return last in nested


def add_training_arguments(parser, group: str, default: str | None = None) -> None:
    """`--config` (a preset of configs/<group> or a YAML path), `--resume` and key=value overrides,
    the arguments every training command takes (`training_config` reads them)."""
    parser.add_argument("--config", default=default,
                        help=f"a preset of configs/{group} ({', '.join(available_presets(group))}) or "
                        "a YAML path" + (f"; default {default}" if default else "; required unless "
                                         "--resume continues a run"))
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in train.out_dir where it stopped, with the config "
                        "saved there (--config is then not needed)")
    parser.add_argument("overrides", nargs="*", metavar="key=value",
                        help="config overrides, e.g. data.sources=[shards/train] train.steps=1000")


def to_dict(cfg: DictConfig) -> dict:
    """A plain, YAML-serialisable copy of a config (for checkpoints, meta and reports)."""
    return OmegaConf.to_container(cfg, resolve=True)


def training_config(group: str, args) -> DictConfig:
    """The config of a training command (`args` from `add_training_arguments`): the preset with the
    overrides; with `--resume`, the run folder's resolved `train.out_dir/config.yaml` with the
    command line's overrides over it, so `--resume train.out_dir=DIR` is enough to continue (the
    folder is `--config`'s `train.out_dir`, else the root preset's, unless an override sets it).

    A resumed run's `train.out_dir` is the folder its config.yaml was read from, whatever path
    the saved one names (a moved or copied run folder continues in itself). `--config` with
    `--resume` must agree with the saved config on the keys it sets (those it changes from the
    root preset, after the overrides): a `UserError` names those where it does not, as the saved
    config is the one used."""
    if not args.resume:
        if args.config is None:
            raise UserError(f"give --config: a preset of configs/{group} "
                            f"({', '.join(available_presets(group))}) or a YAML path "
                            "(or --resume train.out_dir=DIR to continue a run)")
        return load_config(group, args.config, overrides=args.overrides)
    chosen = load_config(group, args.config or schema.ROOTS[group], overrides=args.overrides)
    out_dir = chosen.train.out_dir
    saved = Path(out_dir) / "config.yaml"
    if not saved.is_file():
        raise UserError(f"no run in {out_dir} to resume (no config.yaml there); start one with "
                        f"--config PRESET_OR_YAML train.out_dir={out_dir} (without --resume)")
    resumed = load_config(group, saved, overrides=[*args.overrides,
                                                   f"train.out_dir={json.dumps(str(out_dir))}"])
    if args.config is not None:
        own = changed_keys(to_dict(_root(group)), to_dict(load_config(group, args.config)))
        ignored = set(changed_keys(to_dict(chosen), to_dict(resumed)))
        contradicted = [key for key in own if key in ignored]
        if contradicted:
            raise UserError(f"--resume continues the run in {out_dir} with its saved config.yaml, "
                            f"which --config {args.config} contradicts in "
                            f"{', '.join(contradicted[:5])}; drop --config to resume that run, or "
                            "start a new run with it in another train.out_dir")
    return resumed


def changed_keys(old: Any, new: Any, prefix: str = "") -> list[str]:
    """The dotted keys whose values differ between two plain configs (`to_dict`), sorted."""
    if isinstance(old, dict) and isinstance(new, dict):
        return [changed for key in sorted(old.keys() | new.keys(), key=str)
                for changed in changed_keys(old.get(key), new.get(key), f"{prefix}{key}.")]
    return [] if old == new else [prefix[:-1]]


def to_yaml(cfg: DictConfig | dict) -> str:
    """The resolved config (or its `to_dict` copy) as YAML text, keys in the order of the presets:
    what `c4d config show` prints and every run folder keeps."""
    return yaml.safe_dump(cfg if isinstance(cfg, dict) else to_dict(cfg), sort_keys=False)
