"""Shared test data for the dynpt training/evaluation tests (built once per test session).

- `synthetic_shards(n)`: shards of tiny hand-made scenes whose frames are filled with the scene
  index (so a test can tell which scene a sample came from); written with datagen's real writer.
- `generated_shards()`: a tiny real shard set made by `c4d datagen` (64x64, 10 frames).
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from functools import lru_cache
from pathlib import Path

import numpy as np

from datagen.scene import Scene
from datagen.shards import ShardWriter, encode_scene, scene_key

_ROOT = Path(tempfile.mkdtemp(prefix="dynpt-tests-"))
atexit.register(shutil.rmtree, _ROOT, ignore_errors=True)


def synthetic_scene(index: int, T: int = 10, H: int = 32, W: int = 32, N: int = 20) -> Scene:
    """Frames filled with value `index`; random tracks, some occluded, half of them moving."""
    rng = np.random.default_rng(index)
    tracks = rng.uniform(2, [W - 3, H - 3], size=(N, T, 2)).astype(np.float32)
    occluded = rng.random((N, T)) < 0.3
    occluded[:, 0] = False
    eye = np.tile(np.eye(4, dtype=np.float32), (T, 1, 1))
    return Scene(
        rgb=np.full((T, H, W, 3), index, np.uint8), depth=None, segmentation=None, flow_fwd=None,
        flow_bwd=None, intrinsics=np.tile(np.eye(3, dtype=np.float32), (T, 1, 1)),
        cam_to_world=eye, object_to_world=None, objects=[], tracks=tracks, occluded=occluded,
        query_frame=np.zeros(N, np.int32), track_object=np.zeros(N, np.int32), tracks_world=None,
        displacement=None, moving=np.repeat(np.arange(N)[:, None] % 2 == 0, T, axis=1),
        meta={"preset": "synthetic", "scene_index": index},
    )


@lru_cache(maxsize=None)
def synthetic_shards(num_scenes: int = 12, per_shard: int = 3, first: int = 0) -> Path:
    """A directory of shards holding synthetic scenes `first` .. `first + num_scenes - 1`."""
    out = _ROOT / f"synthetic-{first}-{num_scenes}-{per_shard}"
    out.mkdir()
    for k, start in enumerate(range(first, first + num_scenes, per_shard)):
        with ShardWriter(out / f"train-{k:06d}.tar") as writer:
            for i in range(start, min(start + per_shard, first + num_scenes)):
                writer.write(encode_scene(synthetic_scene(i), scene_key("train", i)))
    return out


@lru_cache(maxsize=None)
def generated_shards() -> Path:
    """4 real MOVi-E-style scenes at 64x64 with 10 frames, via the `c4d datagen` command."""
    from c4d.cli import main

    out = _ROOT / "movi-e-64"
    code = main(["datagen", "--num-scenes", "4", "--out", str(out), "--resolution", "64",
                 "--frames", "10", "--scenes-per-shard", "2", "--seed", "0"])
    assert code == 0, "c4d datagen failed"
    return out
