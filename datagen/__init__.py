"""datagen: Kubric-style synthetic videos with exact labels, on pybullet and pyrender.

Sample a scene, simulate it, render it, annotate it, write it. Reading gives `Scene` objects.
This package never imports torch, dynpt or c4d_pipeline.
"""

from datagen.scene import Scene
from datagen.shards import read_scenes

__version__ = "0.2.0"  # 0.2.0: camera paths drawn as Kubric's worker draws them (docs/FORMAT.md)
__all__ = ["Scene", "read_scenes"]
