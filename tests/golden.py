"""Seeded weights for the golden-output tests (tests/fixtures/golden/).

A golden file stores a network's tensor names, shapes and dtypes in the official release's order
and layout, plus a seed; `seeded_state` turns them back into the exact state dict the official
code was run with, so the fixtures hold a few hundred KB of inputs and outputs instead of the
weights. The rule (numpy PCG64, one stream over the tensors in file order, float32):
  - `*.running_var`: uniform(0.5, 1.5); `*.num_batches_tracked`: 0;
  - other 1-D `*.weight` (norm scales): 1 + 0.1 * N(0, 1); `*.bias`, `*.running_mean`: 0.1 * N(0, 1);
  - every other tensor: 0.8 * N(0, 1) / sqrt(fan_in), fan_in = product of all but the first dimension;
  - a tensor registered under two names (an alias) gets its first name's values.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

GOLDEN_DIR = Path(__file__).resolve().parent / "fixtures" / "golden"


def seeded_state(keys, shapes, alias, dtypes, seed: int) -> dict[str, torch.Tensor]:
    """The state dict described by parallel lists of names, shapes, alias targets ('' = none) and
    dtype names ('torch.float32', 'torch.int64'), filled by the module docstring's rule."""
    rng = np.random.default_rng(seed)
    state: dict[str, torch.Tensor] = {}
    for key, shape, target, dtype in zip(keys, shapes, alias, dtypes):
        shape = tuple(int(s) for s in shape)
        if target:
            state[key] = state[target]
            continue
        if dtype == "torch.int64":
            state[key] = torch.zeros(shape, dtype=torch.int64)
            continue
        if key.endswith("running_var"):
            value = rng.uniform(0.5, 1.5, shape)
        elif key.endswith((".bias", "running_mean")):
            value = 0.1 * rng.standard_normal(shape)
        elif key.endswith(".weight") and len(shape) == 1:
            value = 1 + 0.1 * rng.standard_normal(shape)
        else:
            fan_in = int(np.prod(shape[1:])) if len(shape) > 1 else 1
            value = 0.8 * rng.standard_normal(shape) / np.sqrt(fan_in)
        state[key] = torch.from_numpy(np.asarray(value, np.float32))
    return state


def golden(name: str) -> dict[str, np.ndarray]:
    """The arrays of tests/fixtures/golden/<name>.npz."""
    with np.load(GOLDEN_DIR / f"{name}.npz") as data:
        return {k: data[k] for k in data.files}


def golden_state(data: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """The seeded state dict a golden file describes (keys, shapes, alias, dtypes, seed)."""
    shapes = [tuple(int(s) for s in row.split(",") if s) for row in data["shapes"]]
    return seeded_state(data["keys"], shapes, data["alias"], data["dtypes"], int(data["seed"]))


def noise_image(height: int, width: int, seed: int) -> np.ndarray:
    """uint8 (height, width, 3) uniform noise (numpy PCG64 `integers`), a source image for the
    preprocessing goldens: any one-pixel shift of a crop changes its bytes."""
    return np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)
