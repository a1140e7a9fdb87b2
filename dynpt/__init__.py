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
    "read_video": "c4d_core.video",
    "write_video": "c4d_core.video:write_user_video",  # module:name where the names differ
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        module, _, attr = _EXPORTS[name].partition(":")
        return getattr(importlib.import_module(module), attr or name)
    raise AttributeError(f"module 'dynpt' has no attribute {name!r}")
