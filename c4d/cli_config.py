"""`c4d config show GROUP/PRESET [key=value ...]`: print the fully resolved config, as it would run.

GROUP is one of the config groups (datagen, dynpt, c4d, demo, inspect, pointmaps) and PRESET a
preset of configs/GROUP (`c4d/tiny`) or a YAML path (`dynpt/runs/x/config.yaml`). The output is
the schema defaults, the preset, `--config` files and the overrides merged and range-checked,
the same YAML every run folder keeps.
"""

from __future__ import annotations

import argparse

from c4d_core.config import available_presets, load_config, to_yaml
from c4d_core.errors import UserError
from c4d_core.schema import ROOTS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=("show",), help="show: print the resolved config")
    parser.add_argument("preset", metavar="GROUP/PRESET",
                        help=f"a group ({', '.join(ROOTS)}) and a preset or YAML path, e.g. c4d/tiny")
    parser.add_argument("--config", action="append", default=[], metavar="YAML",
                        help="extra config file merged over the preset (repeatable)")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides")


def split_preset(text: str) -> tuple[str, str]:
    """`c4d/tiny` -> ('c4d', 'tiny'); `dynpt/runs/x/config.yaml` -> ('dynpt', 'runs/x/config.yaml')."""
    group, _, preset = text.partition("/")
    if group not in ROOTS or not preset:
        raise UserError(f"{text!r} must be GROUP/PRESET with GROUP one of {', '.join(ROOTS)}, "
                        f"e.g. c4d/{available_presets('c4d')[0]}")
    return group, preset


def run(args: argparse.Namespace) -> int:
    group, preset = split_preset(args.preset)
    print(to_yaml(load_config(group, preset, args.config, args.overrides)), end="")
    return 0
