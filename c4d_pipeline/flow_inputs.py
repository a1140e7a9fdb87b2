"""What every optical-flow estimator checks first: uint8 RGB frames (T,H,W,3) and in-range pairs.

Shared by `c4d_pipeline.flow` (DIS, ground truth) and `c4d_pipeline.raft`, which import it rather
than each other.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from c4d_core.errors import UserError

Pair = tuple[int, int]


def check_flow_inputs(frames: np.ndarray, pairs: Sequence[Pair]) -> None:
    """Raise `UserError` unless frames is uint8 (T,H,W,3) and every pair indexes a frame."""
    if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3:
        raise UserError(
            f"flow needs uint8 RGB frames of shape (T,H,W,3), got {frames.dtype} {frames.shape}; "
            "convert the video to 8-bit RGB first"
        )
    num_frames = frames.shape[0]
    for i, j in pairs:
        if not (0 <= i < num_frames and 0 <= j < num_frames):
            raise UserError(
                f"flow pair ({i}, {j}) is outside the video of {num_frames} frames; "
                "build the pairs from the same frames"
            )
