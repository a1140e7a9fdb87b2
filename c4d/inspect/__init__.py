"""`c4d inspect`: reports, pictures and validation of shard sets and reconstructions.

- `dataset_report`: statistics, distributions and sample videos of datagen shards.
- `dataset_check`: the `--check` of datagen shards against the format.
- `recon_report`: videos, trajectory, 4D fly-through and file checks of a `c4d run` directory.
- `point_render`: the numpy point splatter behind the fly-throughs.
Drawing primitives (colour maps, track overlays, video files) live in `c4d_core.draw` and `c4d_core.video`.
"""
