"""DynPT, the dynamic-aware point tracker: model, data, training, evaluation and inference.

The public names below are imported lazily (on first use), so `import dynpt` stays cheap and does
not import torch.

    tracker = dynpt.load_tracker("run/checkpoint.pt")       # eval mode, cuda if available
    result = tracker.track(video_uint8_THW3)                 # TrackResult (numpy)
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "load_tracker": "dynpt.inference",
    "Tracker": "dynpt.inference",
    "TrackResult": "dynpt.inference",
    "DynPT": "dynpt.model",
    "DynPTOutput": "dynpt.model",
    "build_model": "dynpt.model",
    "save_checkpoint": "dynpt.checkpoint",
    "load_checkpoint": "dynpt.checkpoint",
    "sample_queries": "dynpt.query_sampling",
    "read_video": "dynpt.video_io",
    "write_video": "dynpt.video_io",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'dynpt' has no attribute {name!r}")
