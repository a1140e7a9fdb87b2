"""The sha1 of every array and shard member of datagen's check scenes, to prove a change left
the labels (and, where it should, the images) bit-identical, against another commit's tree.

    PYTHONPATH=TREE .venv/bin/python benchmarks/datagen_digests.py OUT.json [--save DIR]
    .venv/bin/python benchmarks/datagen_digests.py --compare OLD.json NEW.json [--arrays OLD NEW]

The check scenes (every optional layer on): movi-e at 256x256 twice, movi-e-panning and
movi-f at 128x128, and movi-e at 128x128 with `lights.shadows=false`; 24 frames each.
Written: {scene: {field: sha1 of the array's bytes, "shard:<member>": sha1 of the encoded
member}}. `--save DIR` also keeps each scene's arrays (DIR/<scene>.npz), so `--compare` with
`--arrays` can report how far a field that moved moved (max |difference|, pixels changed).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

LAYERS = ["layers.normal=true", "layers.object_coordinates=true", "layers.instances=true",
          "layers.events=true"]
# name -> (preset, scene index, overrides)
SCENES = {
    "movi-e-256-a": ("movi-e", 0, ["resolution=[256,256]"]),
    "movi-e-256-b": ("movi-e", 1, ["resolution=[256,256]"]),
    "panning-128": ("movi-e-panning", 2, ["resolution=[128,128]"]),
    "movi-f-128": ("movi-f", 3, ["resolution=[128,128]"]),
    "no-shadows-128": ("movi-e", 4, ["resolution=[128,128]", "lights.shadows=false"]),
}


def scene_arrays(scene) -> dict[str, np.ndarray]:
    """Every array of a Scene by name (instances and events per key)."""
    from datagen.scene import Scene

    arrays = {}
    for name in Scene.field_names():
        value = getattr(scene, name)
        if isinstance(value, np.ndarray):
            arrays[name] = value
        elif name in ("instances", "events") and value is not None:
            arrays.update({f"{name}.{key}": v for key, v in value.items()})
    return arrays


def digests(save: Path | None) -> dict[str, dict[str, str]]:
    """{scene: {array name or "shard:<member>": sha1}} of the check scenes; arrays kept in
    save/<scene>.npz unless `save` is None."""
    from c4d_core.config import load_config
    from datagen import shards
    from datagen.generate import generate_scene

    out = {}
    for name, (preset, index, overrides) in SCENES.items():
        cfg = load_config("datagen", preset, overrides=[*overrides, "frames=24", *LAYERS])
        scene = generate_scene(cfg, index)
        arrays = scene_arrays(scene)
        out[name] = {key: hashlib.sha1(np.ascontiguousarray(a).tobytes()).hexdigest()
                     for key, a in arrays.items()}
        sample = shards.encode_scene(scene, shards.scene_key("train", index))
        out[name].update({f"shard:{member}": hashlib.sha1(data).hexdigest()
                          for member, data in sample.items() if member != "__key__"})
        if save is not None:
            save.mkdir(parents=True, exist_ok=True)
            np.savez(save / f"{name}.npz", **arrays)
        print(name, "done", file=sys.stderr, flush=True)
    return out


def compare(old_file: Path, new_file: Path, arrays: list[Path] | None) -> bool:
    """Print every digest that differs (with how far it moved, given saved arrays)."""
    old, new = json.loads(old_file.read_text()), json.loads(new_file.read_text())
    same = True
    for scene in old:
        for key in sorted(set(old[scene]) | set(new[scene])):
            if old[scene].get(key) == new[scene].get(key):
                continue
            same = False
            line = f"{scene} {key}: differs"
            if arrays and not key.startswith("shard:"):
                a = np.load(arrays[0] / f"{scene}.npz")[key]
                b = np.load(arrays[1] / f"{scene}.npz")[key]
                if a.shape == b.shape:
                    diff = np.abs(a.astype(np.float64) - b.astype(np.float64))
                    line += (f" (max |diff| {np.nanmax(diff):.3g}, "
                             f"{np.mean(diff > 0):.4%} of values)")
            print(line)
    print("all identical" if same else "some differ")
    return same


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", type=Path)
    parser.add_argument("--save", type=Path)
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("OLD", "NEW"))
    parser.add_argument("--arrays", nargs=2, type=Path, metavar=("OLD_DIR", "NEW_DIR"))
    args = parser.parse_args()
    if args.compare:
        sys.exit(0 if compare(*args.compare, args.arrays) else 1)
    args.out.write_text(json.dumps(digests(args.save), indent=1))


if __name__ == "__main__":
    main()
