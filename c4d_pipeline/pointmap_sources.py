"""Pointmap sources by name: the registry `POINTMAP_SOURCES` and `build_pointmaps(spec, ...)`.

A spec is 'NAME' or 'NAME:ARG', as for `c4d_pipeline.flow.build_flow`:
  'gt'            the ground truth of a generated scene with noise, per-pair scale and static-world
                  bias (`c4d_pipeline.ground_truth.GroundTruthPointmaps`, the c4d config's
                  `gt_pointmaps` section; needs `scene=`)
  'dust3r:PATH'   a DUSt3R / MASt3R / MonST3R checkpoint file (`c4d_pipeline.dust3r_pointmaps.
                  Dust3rPointmaps`; the config's `pointmaps.batch` and `pointmaps.precision`)
A new network is one builder function and one entry of `POINTMAP_SOURCES`. The builders import
their source when called, so naming one loads only its code. This module sits above
`pointmaps.py` (the interface every source imports), which keeps the imports acyclic.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

from c4d_core.errors import UserError
from c4d_pipeline.pointmaps import PointmapSource
from datagen.scene import Scene


def _ground_truth(arg: str, cfg, scene: Scene | None, device, progress: bool) -> PointmapSource:
    from c4d_pipeline.ground_truth import GroundTruthPointmaps

    if arg:
        raise UserError(f"pointmap source 'gt' takes no argument, got 'gt:{arg}'")
    if scene is None:
        raise UserError("pointmap source 'gt' needs a generated scene (c4d datagen); for a plain "
                        "video use a network: 'dust3r:PATH'")
    return GroundTruthPointmaps.from_config(scene, cfg.gt_pointmaps)


def _dust3r(arg: str, cfg, scene: Scene | None, device, progress: bool) -> PointmapSource:
    from c4d_pipeline.dust3r_pointmaps import Dust3rPointmaps  # torch network: only when asked for

    if not arg:
        raise UserError("pointmap source 'dust3r' needs weights: write 'dust3r:PATH/TO/checkpoint.pth'")
    return Dust3rPointmaps.from_checkpoint(arg, device, cfg.pointmaps.batch, progress=progress,
                                           precision=cfg.pointmaps.precision)


class PointmapSourceKind(NamedTuple):
    """How a spec names the source (`usage`) and its builder: (arg, cfg, scene, device, progress)
    -> PointmapSource, `arg` the spec's text after ':' ('' without one)."""

    usage: str
    build: Callable[[str, Any, Scene | None, Any, bool], PointmapSource]


POINTMAP_SOURCES: dict[str, PointmapSourceKind] = {  # spec name (before ':') -> its kind
    "gt": PointmapSourceKind("gt", _ground_truth),
    "dust3r": PointmapSourceKind("dust3r:PATH", _dust3r),
}


def build_pointmaps(spec: str, cfg, scene: Scene | None = None, device=None,
                    progress: bool = False) -> PointmapSource:
    """The pointmap source named by `spec` ('gt', 'dust3r:PATH'; see the module doc).

    cfg: the c4d config; scene: the datagen `Scene` 'gt' reads (its frames are the ones later
    passed to `pointmaps`); device, progress: a network's torch device (default: cuda if
    available) and progress bar over the pairs.
    """
    name, _, arg = spec.partition(":")
    if name not in POINTMAP_SOURCES:
        known = ", ".join(repr(kind.usage) for kind in POINTMAP_SOURCES.values())
        raise UserError(f"unknown pointmap source {spec!r}; choose one of {known}")
    return POINTMAP_SOURCES[name].build(arg, cfg, scene, device, progress)
