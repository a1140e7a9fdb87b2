"""Which scenes go into which shard, which task writes which shard, and what is left to do.

Shard k of a split holds scenes k*M .. k*M+M-1 (M scenes per shard; the last shard may be
shorter) and is named `{split}-{k:06d}.tar`. Tasks of a job array split the shards round-robin
(task i writes the shards k with k % num_tasks == i), so any number of independent processes,
with no coordinator, write one dataset; a finished shard is never written again.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

from c4d_core.errors import UserError

SHARD_PATTERN = "{split}-{shard:06d}.tar"


def config_digest(config: Mapping) -> str:
    """16 hex digits identifying a resolved datagen config (a plain dict): every scene's
    `meta["config_digest"]`, checked against the dataset file's `config` when the scene is read."""
    text = json.dumps(config, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]

# (index variable, count variable, first-index variable or None), in order of preference.
TASK_ENVIRONMENTS = (
    ("SLURM_ARRAY_TASK_ID", "SLURM_ARRAY_TASK_COUNT", "SLURM_ARRAY_TASK_MIN"),
    ("RANK", "WORLD_SIZE", None),
)


@dataclass(frozen=True)
class ShardPlan:
    """The fixed assignment of `num_scenes` scenes of `split` to shards of `scenes_per_shard`."""

    split: str
    num_scenes: int
    scenes_per_shard: int

    def __post_init__(self) -> None:
        if self.num_scenes < 1:
            raise UserError(f"--num-scenes must be at least 1, got {self.num_scenes}")
        if self.scenes_per_shard < 1:
            raise UserError(f"--scenes-per-shard must be at least 1, got {self.scenes_per_shard}")
        if not re.fullmatch(r"[A-Za-z0-9_]+", self.split):
            raise UserError(
                f"split {self.split!r} must be letters, digits or '_', such as train, val or test"
            )

    @property
    def num_shards(self) -> int:
        return -(-self.num_scenes // self.scenes_per_shard)

    def shard_name(self, shard: int) -> str:
        return SHARD_PATTERN.format(split=self.split, shard=shard)

    def scenes_of(self, shard: int) -> range:
        """Scene indices of shard `shard`, in the order they are stored."""
        start = shard * self.scenes_per_shard
        return range(start, min(start + self.scenes_per_shard, self.num_scenes))

    def shards_of_task(self, task_index: int, num_tasks: int) -> list[int]:
        """The shards task `task_index` of `num_tasks` writes (round-robin: balanced tasks)."""
        return list(range(task_index, self.num_shards, num_tasks))

    def missing_shards(self, out_dir: str | Path, shards: list[int]) -> list[int]:
        """Those of `shards` without a finished file in `out_dir` (a `.partial` one is not)."""
        return [k for k in shards if not (Path(out_dir) / self.shard_name(k)).is_file()]


def _parse_int(name: str, text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise UserError(f"environment variable {name}={text!r} is not an integer") from None


def resolve_task(
    task_index: int | None, num_tasks: int | None, environ: Mapping[str, str] = os.environ
) -> tuple[int, int]:
    """(task index, number of tasks) from the flags, else from SLURM or torch-style variables.

    With neither flags nor variables, the single task (0, 1) does everything.
    """
    if task_index is None and num_tasks is None:
        for index_var, count_var, min_var in TASK_ENVIRONMENTS:
            if index_var in environ and count_var in environ:
                task_index = _parse_int(index_var, environ[index_var])
                if min_var and min_var in environ:  # e.g. --array=1-8 numbers tasks from 1
                    task_index -= _parse_int(min_var, environ[min_var])
                num_tasks = _parse_int(count_var, environ[count_var])
                break
        else:
            return 0, 1
    if task_index is None or num_tasks is None:
        raise UserError("give both --task-index and --num-tasks, or neither")
    if num_tasks < 1 or not 0 <= task_index < num_tasks:
        raise UserError(
            f"task index {task_index} is not in [0, {num_tasks}); the task index counts from 0 "
            "and must be smaller than the number of tasks"
        )
    return task_index, num_tasks
