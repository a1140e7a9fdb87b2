"""`c4d export cotracker`: each scene as the sequence folder CoTracker's Kubric training dataset
reads (co-tracker `cotracker/datasets/kubric_movif_dataset.py`, `KubricMovifDataset`).

OUT is that dataset's `data_root` (CoTracker3's `train_on_kubric.py` uses
`DATASET_ROOT/kubric/kubric_movi_f_120_frames_dense/movi_f`). Per scene NAME:

- `NAME/frames/{t:05d}.png`: 8-bit RGB frames, sorted by name = by time;
- `NAME/NAME.npy`: `np.save` of a dict (a pickled 0-d object array: `np.load(...,
  allow_pickle=True).item()`) with `coords` float32 (N,T,2) (x, y) pixels, pixel centres at
  integers (CoTracker's own coordinates: it marks x < 0 or x > W-1 out of view), `visibility`
  bool (N,T) holding the *occlusion* flags (True = occluded; the loader applies a logical NOT,
  as for CoTracker's released data), and our `moving` bool (N,T) (the point moved more than the
  mobility threshold in the world since the previous frame), which the loader ignores.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from datagen.export.base import ExportFormat, in_memory, write_member, write_png
from datagen.scene import Scene


def write_scene(scene: Scene, folder: Path, name: str) -> None:
    """Write `scene` as the sequence `name` into `folder` in CoTracker's Kubric layout (module
    docstring)."""
    frames = folder / "frames"
    frames.mkdir()
    for t, frame in enumerate(scene.rgb):
        write_png(frames / f"{t:05d}.png", frame)
    labels = {"coords": scene.tracks.astype(np.float32), "visibility": scene.occluded.astype(bool),
              "moving": scene.moving.astype(bool)}
    write_member(folder / f"{name}.npy", in_memory(lambda fh: np.save(fh, labels, allow_pickle=True)))


FORMAT = ExportFormat(
    name="cotracker",
    summary="CoTracker's Kubric training layout: a folder per scene with frames/*.png and "
            "NAME.npy {coords, visibility (= occluded), moving}",
    fields=("rgb", "tracks", "occluded", "moving"),
    layers=("moving",),
    write_scene=write_scene,
)
