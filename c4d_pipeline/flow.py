"""Optical flow behind one interface: OpenCV DIS (weight-free default), exact ground truth, RAFT.

Every estimator has one method:

    flow(frames, pairs) -> float32 (P,H,W,2)

`frames` is uint8 (T,H,W,3) RGB; `pairs` is a list of P (i, j) frame indices; entry p is the
(dx, dy) pixel displacement of the surface seen at each pixel of frame i to frame j (pixel
centres at integer coordinates, x the column), camera motion included, as in the contract.

`build_flow(spec, scene=None, device=None)` picks one from a string:
  'dis' or 'dis:PRESET'  OpenCV DIS, PRESET one of ultrafast | fast | medium (default medium);
  'dis:PRESET@Nx'         the same on frames upsampled N times (bicubic), the flow averaged back
                          to the frames' size and divided by N: finer patches on small frames
                          (2x at 256x256: motion-mask IoU 0.41 against 0.32 on the demo's 4
                          scenes, 0.52 against 0.40 on 4 others; ~3x the time; docs/RESULTS.md 1,
                          docs/results/masks.md)
  'dis...+chain'          (after any of the two above) a pair i -> j more than one frame apart takes,
                          per pixel, whichever of two flows matches the frames better (`fuse_flows`:
                          the colour difference over a 7x7 patch after warping frame j back): DIS's
                          own search of the pair, or the consecutive searches composed i -> i+1 ->
                          ... -> j (`compose_flows`). DIS's coarse-to-fine search loses large
                          displacements (on 256x256 MOVi-E its error on static pixels 9 frames apart
                          is 22-29 px mean, the composed flow's 4-13 px) and the composition drifts
                          where the search is right; CMA fed by either error pulls the cameras
                          (docs/results/cma_flow.md). Pairs of consecutive frames are unchanged.
  'gt'                    exact flow of a datagen `Scene` for ANY pair (i, j), from depth,
                          segmentation, camera and object poses (needs `scene=`;
                          `c4d_pipeline.ground_truth.GroundTruthFlow`, imported lazily)
  'raft:PATH'             RAFT weights at PATH (`c4d_pipeline.raft.RaftFlow`, imported lazily)
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Protocol, Sequence

import cv2
import numpy as np

from c4d_core.errors import UserError
from c4d_core.geometry import pixel_grid
from c4d_pipeline.flow_inputs import Pair, check_flow_inputs
from datagen.scene import Scene

DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


class FlowEstimator(Protocol):
    def flow(self, frames: np.ndarray, pairs: Sequence[Pair]) -> np.ndarray:
        """frames uint8 (T,H,W,3), pairs P x (i, j) -> float32 (P,H,W,2) (dx, dy) from i to j."""
        ...


def build_flow(spec: str, scene: Scene | None = None, device=None) -> FlowEstimator:
    """The flow estimator named by `spec` ('dis[:PRESET][@Nx][+chain]', 'gt', 'raft:PATH'); see
    the module doc.

    `scene` is required by 'gt' (its frames must be the frames later passed to `flow`, at any
    resolution); `device` is only used by 'raft'.
    """
    name, _, arg = spec.partition(":")
    if name.partition("+")[0] == "dis":
        search, _, option = spec.partition("+")
        if option not in ("", "chain"):
            raise UserError(f"flow {spec!r}: the only option after '+' is 'chain', e.g. 'dis:medium@3x+chain'")
        preset, _, factor = (search.partition(":")[2] or "medium").partition("@")
        if factor and not re.fullmatch(r"[1-8]x", factor):
            raise UserError(f"flow {spec!r}: the upsampling after '@' is 1x to 8x, e.g. 'dis:medium@2x'")
        return DISFlow(preset or "medium", int(factor[:-1]) if factor else 1, chain=option == "chain")
    if name == "gt":
        if scene is None:
            raise UserError("flow 'gt' needs a datagen scene; use flow 'dis' for a plain video")
        from c4d_pipeline.ground_truth import GroundTruthFlow  # the scene's labels: only when asked for

        return GroundTruthFlow(scene)
    if name == "raft":
        if not arg:
            raise UserError("flow 'raft' needs weights: write 'raft:PATH/TO/raft.pth'")
        if Path(arg).is_dir():
            raise UserError(f"RAFT weights {arg!r} is a folder, not a file; pass the .pth file inside it")
        if not Path(arg).is_file():
            raise UserError(f"RAFT weights {arg!r} do not exist; give the path of a local .pth file")
        from c4d_pipeline.raft import RaftFlow  # torch model: imported only when asked for

        return RaftFlow(arg, device)
    raise UserError(f"unknown flow {spec!r}; choose 'dis', 'dis:fast', 'dis:medium@2x', "
                    "'dis:medium@3x+chain', 'gt' or 'raft:PATH'")


REMAP_COLUMNS = 1024  # cv2.remap's maps are images of fewer than 32767 rows and columns


def sample_flow(flow: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear flow (H,W,2) at points xy (M,2) -> (M,2); points outside use the nearest edge."""
    count = len(xy)
    if count == 0:
        return np.zeros((0, 2))
    columns = min(count, REMAP_COLUMNS)
    rows = -(-count // columns)
    map_xy = np.zeros((rows * columns, 2), np.float32)
    map_xy[:count] = xy
    map_xy = map_xy.reshape(rows, columns, 2)  # the points as an image of rows x columns
    sampled = cv2.remap(flow.astype(np.float32), map_xy[..., 0], map_xy[..., 1], cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
    return sampled.reshape(-1, 2)[:count].astype(np.float64)  # (M,2)


FUSION_PATCH = 7  # pixels: the side of the patch whose colour difference picks a pixel's flow


def warp_back(image: np.ndarray, flow: np.ndarray, border: int = cv2.BORDER_REPLICATE) -> np.ndarray:
    """`image` (H,W) or (H,W,C) of frame j sampled where the flow i -> j (H,W,2) lands each pixel
    of frame i (bilinear; outside the image `border`, an OpenCV border mode: edges replicated, or
    cv2.BORDER_CONSTANT for 0): frame j seen from frame i, float32 of the image's shape."""
    height, width = flow.shape[:2]
    landing = (pixel_grid(height, width) + flow).astype(np.float32)  # (H,W,2) where the pixels land
    return cv2.remap(image.astype(np.float32), landing[..., 0], landing[..., 1], cv2.INTER_LINEAR,
                     borderMode=border)


def fuse_flows(source: np.ndarray, target: np.ndarray, candidates: Sequence[np.ndarray],
               patch: int = FUSION_PATCH) -> np.ndarray:
    """Per pixel, the candidate flow i -> j (each (H,W,2)) whose warp of frame j `target` (H,W,3)
    best matches frame i `source` (H,W,3): the least mean absolute colour difference over a
    patch x patch window; ties go to the later candidate. -> float32 (H,W,2)."""
    frame = source.astype(np.float32)
    costs = [cv2.boxFilter(np.abs(warp_back(target, flow) - frame).mean(-1), -1, (patch, patch))
             for flow in candidates]  # each (H,W)
    best = np.argmin(np.stack(costs[::-1]), axis=0)  # (H,W) index into the reversed list: ties -> later
    stacked = np.stack(candidates[::-1]).astype(np.float32)  # (K,H,W,2)
    return np.take_along_axis(stacked, best[None, ..., None], axis=0)[0]


def compose_flows(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """The flow i -> k (H,W,2) of the flows i -> j `first` (H,W,2) and j -> k `second` (H,W,2):
    first(x) + second(x + first(x)), the second sampled bilinearly where the first lands (edges
    replicated), summed in float64. With second = the flow j -> i it is the forward-backward
    residual."""
    return np.add(first, warp_back(second, first), dtype=np.float64)


class DISFlow:
    """OpenCV's Dense Inverse Search flow on grey-level frames (no weights, CPU), optionally on
    frames upsampled `upsample` times: the flow (Hu,Wu,2) there is averaged over each block of
    upsample x upsample pixels (a frame pixel) and divided by `upsample`. With `chain`, a pair more
    than one frame apart fuses its own search with the consecutive searches composed (at the
    upsampled size; see the module doc); each composition is made once for all the pairs from one
    frame, and a step is kept only while a pair still needs it, so memory does not grow with the
    video."""

    def __init__(self, preset: str = "medium", upsample: int = 1, chain: bool = False):
        if preset not in DIS_PRESETS:
            raise UserError(f"unknown DIS preset {preset!r}; choose one of {', '.join(DIS_PRESETS)}")
        self.preset, self.upsample, self.chain = preset, int(upsample), bool(chain)

    def flow(self, frames: np.ndarray, pairs: Sequence[Pair]) -> np.ndarray:
        check_flow_inputs(frames, pairs)
        dis = cv2.DISOpticalFlow_create(DIS_PRESETS[self.preset])
        height, width = frames.shape[1:3]
        n = self.upsample
        grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]  # T x (H,W) uint8
        if n > 1:
            grey = [cv2.resize(g, (width * n, height * n), interpolation=cv2.INTER_CUBIC) for g in grey]

        def to_frames(flow: np.ndarray) -> np.ndarray:  # (H*n,W*n,2) upsampled pixels -> (H,W,2)
            return flow if n == 1 else cv2.resize(flow, (width, height), interpolation=cv2.INTER_AREA) / n

        out = np.zeros((len(pairs), height, width, 2), np.float32)  # (P,H,W,2)
        if not self.chain:
            for p, (i, j) in enumerate(pairs):
                out[p] = to_frames(dis.calc(grey[int(i)], grey[int(j)], None))  # from (H*n,W*n,2)
            return out
        # chain: the pairs from one frame in one direction form a sweep, which composes the steps
        # once out to its farthest pair and fuses each pair on the way; sweeps run in the order of
        # the earliest frame they touch, so a step no later sweep needs is freed.
        sweeps: dict[tuple[int, int], dict[int, int]] = {}  # (start, +-1) -> {end: pair index}
        for p, (i, j) in enumerate(pairs):
            sweeps.setdefault((int(i), 1 if j > i else -1), {})[int(j)] = p
        steps: dict[tuple[int, int], np.ndarray] = {}  # (t, t +- 1) -> (H*n,W*n,2) step flow
        for (i, step), ends in sorted(sweeps.items(), key=lambda sweep: min(sweep[0][0], *sweep[1])):
            for key in [key for key in steps if min(key) < min(i, *ends)]:  # no later sweep needs it
                del steps[key]
            farthest = max(ends, key=lambda j: abs(j - i))
            chained = None  # (H*n,W*n,2) the flow i -> t, the steps composed
            for t in range(i, farthest, step):
                if (t, t + step) not in steps:
                    steps[(t, t + step)] = dis.calc(grey[t], grey[t + step], None)
                chained = steps[(t, t + step)] if chained is None else \
                    compose_flows(chained, steps[(t, t + step)]).astype(np.float32)
                j = t + step
                if j not in ends:
                    continue
                if j == i + step:  # consecutive frames: the search itself
                    out[ends[j]] = to_frames(chained)
                else:
                    searched = dis.calc(grey[i], grey[j], None)
                    out[ends[j]] = fuse_flows(frames[i], frames[j], [to_frames(searched), to_frames(chained)])
        return out
