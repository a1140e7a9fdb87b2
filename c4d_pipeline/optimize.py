"""The two-stage correspondence-aided optimisation (paper sec. 3.4, supplement "Optimization").

Stage 1: GA + w_cma CMA + w_cts CTS over depth, poses, intrinsics and the per-edge similarities
(the focal only; with known intrinsics in `intrinsics.mode` fixed, not that either).
Stage 2: poses, intrinsics and edge similarities fixed; w_pts PTS over depth only.
Coarse-to-fine (`optim.coarse_factor` > 1, `optim.coarse_iters` > 0): the first coarse_iters of
stage 1's iterations run on pooled observations, the rest at full size (`coarse_to_fine`).
Units, so the paper's weights keep their meaning: the world is scaled as DUSt3R's (mean distance of
the points from their camera `optim.world_scale` = 0.5: pair pointmaps of unit mean distance, edge
scales of geometric mean 0.5), and CMA measures flow in pixels of a `cma.reference_size` = 512 image.
Both: Adam, lr 0.01 (decayed to `lr_min` by `schedule`), `stage1_iters` / `stage2_iters` steps
(stage 1's one schedule across its coarse and full-size iterations).

The terms are `objectives.OBJECTIVES` (name, weight key, stage, inputs); a stage iterates over the
registered terms of its stage whose weight is > 0 and whose inputs were given, so a new loss is one
registered function plus one `weights:` key.

Memory: per-edge terms (GA, CMA) are evaluated `edge_chunk` edges at a time. The per-frame and
per-edge quantities they share (world and camera points, edge similarities, ego projections) are
computed once per iteration (`StageState.shared`), the chunks back-propagate into detached copies
of them, and one final backward carries the summed gradients to the parameters; the result equals
the unchunked gradient while only one chunk's (e,3,H*W) temporaries are alive.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from tqdm import tqdm

from c4d_core.errors import UserError
from c4d_pipeline import coarse_to_fine, objectives
from c4d_pipeline.alignment import Initialisation, initialise
from c4d_pipeline.pointmaps import PairwisePointmaps
from c4d_pipeline.scene_params import SceneParams, pixel_rays

log = logging.getLogger(__name__)


@dataclass
class OptimisationResult:
    """Outputs of `optimise` (numpy, float32). T frames of H x W."""

    depth: np.ndarray  # (T,H,W) z-depth in the reconstruction's units (see `rescale_world`)
    cam_to_world: np.ndarray  # (T,4,4)
    intrinsics: np.ndarray  # (T,3,3)
    points: np.ndarray  # (T,H,W,3) world pointmaps
    confidence: np.ndarray  # (T,H,W) max raw confidence over the frame's pairs
    depth_stage1: np.ndarray  # (T,H,W) depth after stage 1 (before PTS)
    history: dict = field(default_factory=dict)  # wall and CPU seconds, per-iteration losses per stage


def learning_rate(iteration: int, total: int, lr: float, lr_min: float, schedule: str) -> float:
    """Learning rate at `iteration` of `total` for schedule 'constant' | 'linear' | 'cosine'."""
    frac = iteration / max(total, 1)
    if schedule == "constant":
        return lr
    if schedule == "linear":
        return lr + (lr_min - lr) * frac
    if schedule == "cosine":
        return lr_min + (lr - lr_min) * (1 + math.cos(math.pi * frac)) / 2
    raise UserError(f"optim.schedule must be constant, linear or cosine, got {schedule!r}")


class _Inputs:
    """The observations on the optimisation device, channels-first over P = H*W pixels.

    ei, ej (E,) the edges' frames; views: for view i and view j of every edge, (frames (E,),
    pointmaps (E,3,P) (a transposed view of the pair's (E,P,3) array: no copy), GA weights = log
    confidence (E,P)); with flow: target (E,2,P) pixel + flow i->j, static (E,P) static in frame i
    and finite flow, num_static, pixels (3,P) the homogeneous pixel grid [u, v, 1]. `available`:
    the observation names the objectives may ask for.
    """

    def __init__(self, pw, flows, static_masks, device):
        e = self.num_edges = pw.num_edges
        h, w = pw.image_size
        self.num_pixels = h * w
        self.ei = torch.from_numpy(pw.edges[:, 0]).to(device)
        self.ej = torch.from_numpy(pw.edges[:, 1]).to(device)
        self.views = [
            (frames, torch.from_numpy(pts).reshape(e, -1, 3).to(device).transpose(1, 2),
             torch.from_numpy(conf).reshape(e, -1).log().to(device))
            for frames, pts, conf in ((self.ei, pw.pts_i, pw.conf_i), (self.ej, pw.pts_j, pw.conf_j))
        ]
        self.available = {"pointmaps"}
        self.target = self.static = self.pixels = None
        if flows is not None:
            flow = torch.from_numpy(np.ascontiguousarray(flows, dtype=np.float32)).reshape(e, -1, 2)
            finite = torch.isfinite(flow).all(-1)  # (E,P)
            if static_masks is None:
                static = torch.ones_like(finite)
            else:
                per_frame = torch.from_numpy(np.asarray(static_masks, bool)).flatten(1)  # (T,P)
                static = per_frame[self.ei.cpu()]  # (E,P) static in frame i of each edge
            v, u = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
            pixels = torch.stack([u, v], -1).reshape(-1, 2).float()  # (P,2)
            target = pixels + torch.nan_to_num(flow, 0.0, 0.0, 0.0)  # (E,P,2)
            self.pixels = torch.cat([pixels.T, torch.ones(1, h * w)]).to(device)  # (3,P) [u, v, 1]
            self.target = target.transpose(1, 2).contiguous().to(device)  # (E,2,P)
            self.static = (static & finite).to(device)  # (E,P) static in frame i
            self.num_static = max(int(self.static.sum()), 1)
            self.available.add("flow")
            if int(self.static.sum()) == 0:
                log.warning("CMA: no static pixel with valid flow; the term contributes nothing")


def _check_inputs(pw: PairwisePointmaps, num_frames, flows, static_masks, tracks, visible):
    h, w = pw.image_size
    pw.validate(num_frames, (h, w))
    if flows is not None and tuple(flows.shape) != (pw.num_edges, h, w, 2):
        raise UserError(f"optical flow has shape {tuple(flows.shape)}, expected "
                        f"{(pw.num_edges, h, w, 2)} (one flow i->j per edge of the scene graph)")
    if static_masks is not None and tuple(static_masks.shape) != (num_frames, h, w):
        raise UserError(f"motion masks have shape {tuple(static_masks.shape)}, expected "
                        f"{(num_frames, h, w)}; compute them on the same frames")
    if tracks is not None:
        if tracks.ndim != 3 or tracks.shape[0] != num_frames or tracks.shape[2] != 2:
            raise UserError(f"tracks have shape {tuple(tracks.shape)}, expected (T={num_frames},N,2);"
                            " track the same frames the reconstruction uses")
        if visible is None or tuple(visible.shape) != tuple(tracks.shape[:2]):
            raise UserError("track visibility must be given with shape (T,N) matching the tracks")


def check_intrinsics(intrinsics: np.ndarray | None, num_frames: int) -> None:
    """`UserError` unless known intrinsics are None or (T,4) rows fx, fy, cx, cy."""
    if intrinsics is not None and np.shape(intrinsics) != (num_frames, 4):
        raise UserError(f"known intrinsics have shape {np.shape(intrinsics)}, expected (T={num_frames},4) "
                        "rows fx, fy, cx, cy")


def frame_confidence(pw: PairwisePointmaps, num_frames: int) -> np.ndarray:
    """(T,H,W) per-pixel maximum raw confidence over every pair the frame belongs to."""
    conf = np.ones((num_frames,) + pw.image_size, np.float32)
    for e, (i, j) in enumerate(pw.edges):
        np.maximum(conf[i], pw.conf_i[e], out=conf[i])
        np.maximum(conf[j], pw.conf_j[e], out=conf[j])
    return conf


def rescale_world(init: Initialisation, image_size: tuple[int, int], world_scale: float) -> Initialisation:
    """`init` with the world scaled so that the mean distance of every pixel's point from its own
    camera is `world_scale` (0: unchanged). Depth, camera and edge translations and edge scales
    scale together, so the world pointmaps and the edges' mapped pointmaps scale alike."""
    if world_scale <= 0:
        return init
    h, w = image_size
    ray_len = pixel_rays(h, w, init.focal_xy(), init.principal).norm(dim=-1)  # (T,H,W) distance per unit depth
    factor = world_scale / float((ray_len * init.depth).mean())
    pose = init.cam_to_world.clone()
    pose[:, :3, 3] *= factor
    return replace(init, depth=init.depth * factor, cam_to_world=pose,
                   edge_scale=init.edge_scale * factor, edge_translation=init.edge_translation * factor)


def fixed_camera_pts(params: SceneParams, targets: torch.Tensor, has_target: torch.Tensor) -> tuple:
    """Stage 2's PTS constants (poses and focals fixed there): the frames with targets (t,), their
    world rays R K^-1 [u, v, 1] (t,3,P) and offsets camera centre - target (t,3,P), from the
    targets (T,H,W,3) and has_target (T,) of `objectives.pts_targets`."""
    with torch.no_grad():
        frames = has_target.nonzero()[:, 0]  # (t,)
        rays = pixel_rays(*params.image_size, params.focals_xy(), params.principal)[frames]  # (t,H,W,3)
        rays = torch.bmm(params.rotations()[frames], rays.flatten(1, 2).transpose(1, 2))  # (t,3,P)
        offset = params.trans[frames, :, None] - targets[frames].flatten(1, 2).transpose(1, 2)  # (t,3,P)
    return frames, rays, offset.contiguous()


def _shared_cam(state):
    return (state.params.camera_points_channels_first(),)  # (T,3,P)


def _shared_depth(state):
    return (state.params.depth().flatten(1),)  # (T,P)


def _shared_rotations(state):
    return (state.params.rotations(),)  # (T,3,3) camera-to-world, shared by the terms of an iteration


def _shared_world(state):
    (cam,) = state.shared_value("cam")
    (rot,) = state.shared_value("rotations")
    return (torch.baddbmm(state.params.trans[..., None], rot, cam),)  # (T,3,P)


def _shared_edge_similarity(state):
    scale, rot, trans = state.params.edge_similarities()
    return scale[:, None, None] * rot, trans  # (E,3,3), (E,3)


def _shared_ego_projection(state):
    params, data = state.params, state.data
    (rot,) = state.shared_value("rotations")
    return objectives.ego_projection(rot, params.trans, params.intrinsics(), data.ei, data.ej)


_SHARED = {"cam": _shared_cam, "depth": _shared_depth, "rotations": _shared_rotations, "world": _shared_world,
           "edge_similarity": _shared_edge_similarity, "ego_projection": _shared_ego_projection}


class StageState:
    """What the objectives of one iteration see (`objectives.OBJECTIVES`): the parameters, the
    observations, the CMA settings, the PTS targets (stage 2) and `shared(name)`: the tensors of
    `_SHARED[name]` computed once per iteration and handed out as detached leaves, so that edge
    chunks accumulate their gradients there (`shared_frames(name)`: a per-frame (T,...) tensor as
    one leaf per frame, whose gradients add into one (T,...) buffer); `backward` carries them to
    the parameters."""

    def __init__(self, params: SceneParams, data: _Inputs, cma_max_px: float = 50.0,
                 cma_px_scale: float = 1.0, pts_targets=None):
        self.params, self.data = params, data
        self.cma_max_px, self.cma_px_scale = cma_max_px, cma_px_scale
        self.pts_targets = pts_targets
        self._shared: dict[str, tuple[tuple, tuple]] = {}
        self._frames: dict[str, tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]] = {}

    def shared_value(self, name: str) -> tuple:
        """The tensors of `name`, attached to the parameters' graph (for building other shared ones)."""
        if name not in self._shared:
            values = _SHARED[name](self)
            self._shared[name] = (values, tuple(v.detach().requires_grad_() for v in values))
        return self._shared[name][0]

    def shared(self, name: str) -> tuple:
        """The tensors of `name` as leaves (what per-edge terms differentiate)."""
        self.shared_value(name)
        return self._shared[name][1]

    def shared_frames(self, name: str) -> list[torch.Tensor]:
        """The one (T,...) tensor of `name` as T leaves of (...), one per frame, their gradients
        views of one (T,...) buffer (the GA and CMA kernels take them as they are)."""
        if name not in self._frames:
            (value,) = self.shared_value(name)
            grad = torch.zeros_like(value)
            leaves = [frame.detach().requires_grad_() for frame in value.detach()]
            for leaf, frame_grad in zip(leaves, grad):
                leaf.grad = frame_grad  # the backward adds in place: no (T,...) tensor per edge chunk
            self._frames[name] = (value, grad, leaves)
        return self._frames[name][2]

    def backward(self, losses: list[torch.Tensor]) -> None:
        """One backward of the accumulated leaf gradients and of `losses` to the parameters; clears."""
        pairs = [(v, leaf.grad) for values, leaves in self._shared.values()
                 for v, leaf in zip(values, leaves) if leaf.grad is not None]
        pairs += [(value, grad) for value, grad, _ in self._frames.values()]
        tensors = [v for v, _ in pairs] + losses
        if tensors:
            torch.autograd.backward(tensors, [g for _, g in pairs] + [torch.ones_like(x) for x in losses])
        self._shared.clear()
        self._frames.clear()


def active_objectives(stage: int, weights, available: set[str]) -> list[objectives.Objective]:
    """The registered objectives of `stage` with weight > 0 whose inputs are `available`."""
    active = []
    for term in objectives.OBJECTIVES:
        if term.stage != stage:
            continue
        if term.weight not in weights:
            raise UserError(f"the config has no weights.{term.weight} (weight of the {term.name} objective)")
        if float(weights[term.weight]) > 0 and set(term.inputs) <= available:
            active.append(term)
    return active


def stage_step(state: StageState, terms: list[objectives.Objective], weights, edge_chunk: int) -> dict:
    """One forward/backward of the weighted `terms`, per-edge terms `edge_chunk` edges at a time
    (0 = all; module docstring). Leaves the gradients in the parameters; returns the losses."""
    values = {term.name: 0.0 for term in terms}
    per_edge = [t for t in terms if t.per_edge]
    num_edges = state.data.num_edges
    chunk = edge_chunk if edge_chunk > 0 else num_edges
    for start in range(0, num_edges if per_edge else 0, chunk):
        edges = slice(start, min(start + chunk, num_edges))
        loss = 0.0
        for term in per_edge:
            value = term.fn(state, edges)
            values[term.name] += float(value.detach())
            loss = loss + float(weights[term.weight]) * value
        loss.backward()
    once = []
    for term in terms:
        if not term.per_edge:
            value = term.fn(state)
            values[term.name] = float(value.detach())
            once.append(float(weights[term.weight]) * value)
    state.backward(once)
    values["total"] = sum(float(weights[t.weight]) * values[t.name] for t in terms)
    return values


class Stage1:
    """Stage 1 of `optimise` as a callable: built from the observations and the config (same
    arguments), `step()` makes one forward/backward of GA + CMA + CTS (gradients left in
    `params`) and returns its losses. Used by `optimise` and by timing scripts. `init`: initial
    values in the world's units (default: the spanning-tree initialisation, `rescale_world`ed).
    `intrinsics`: known (T,4) fx, fy, cx, cy in the pointmaps' pixels (None: estimated), held fixed
    when `intrinsics.mode` is fixed."""

    def __init__(self, pw: PairwisePointmaps, num_frames: int, cfg, flows=None, static_masks=None,
                 device: str = "cpu", init: Initialisation | None = None,
                 intrinsics: torch.Tensor | None = None):
        h, w = pw.image_size
        opt_cfg = cfg.optim
        if init is None:
            init = rescale_world(initialise(pw, num_frames, shared_focal=opt_cfg.shared_focal,
                                            intrinsics=intrinsics), (h, w), opt_cfg.world_scale)
        self.params = SceneParams(init.depth, init.cam_to_world, init.focal, init.edge_scale,
                                  init.edge_rotation, init.edge_translation,
                                  shared_focal=opt_cfg.shared_focal, principal=init.principal,
                                  aspect=init.aspect,
                                  fixed_focal=intrinsics is not None and cfg.intrinsics.mode == "fixed",
                                  ).to(device)
        wanted = {name for term in active_objectives(1, cfg.weights, {"pointmaps", "flow", "tracks"})
                  for name in term.inputs}  # flow is held on the device only if a term reads it
        self.data = _Inputs(pw, flows if "flow" in wanted else None, static_masks, device)
        px_scale = cfg.cma.reference_size / max(h, w) if cfg.cma.reference_size > 0 else 1.0
        self.state = StageState(self.params, self.data, float(cfg.cma.max_px), px_scale)
        self.weights, self.edge_chunk = cfg.weights, int(opt_cfg.edge_chunk)
        self.terms = active_objectives(1, cfg.weights, self.data.available)

    def step(self) -> dict:
        return stage_step(self.state, self.terms, self.weights, self.edge_chunk)


def adam(params_list, cfg) -> torch.optim.Adam:
    """The optimiser of both stages (`optim.lr`, `optim.betas`; the schedule sets lr per iteration)."""
    return torch.optim.Adam(params_list, lr=cfg.lr, betas=tuple(cfg.betas))


def _run_adam(opt: torch.optim.Adam, steps: range, total: int, cfg, step_fn, stage: str,
              progress: bool) -> dict:
    """Iterations `steps` of a schedule of `total`; returns {loss name, 'seconds',
    'cpu_seconds': [per-iteration values]}."""
    curves: dict[str, list[float]] = {}
    for it in tqdm(steps, desc=stage, disable=not progress, leave=False):
        lr = learning_rate(it, total, cfg.lr, cfg.lr_min, cfg.schedule)
        for group in opt.param_groups:
            group["lr"] = lr
        opt.zero_grad(set_to_none=True)
        tic, cpu_tic = time.perf_counter(), time.process_time()
        losses = step_fn()
        if not math.isfinite(losses["total"]):
            raise FloatingPointError(f"{stage}: loss became non-finite at iteration {it}")
        opt.step()
        losses["seconds"] = time.perf_counter() - tic
        losses["cpu_seconds"] = time.process_time() - cpu_tic
        for name, value in losses.items():
            curves.setdefault(name, []).append(value)
    return curves


def optimise(
    pw: PairwisePointmaps,
    num_frames: int,
    cfg,
    flows: np.ndarray | None = None,
    static_masks: np.ndarray | None = None,
    tracks: np.ndarray | None = None,
    visible: np.ndarray | None = None,
    device: str = "cpu",
    progress: bool = False,
    intrinsics: np.ndarray | None = None,
) -> OptimisationResult:
    """Reconstruct depth, poses and intrinsics from pairwise pointmaps and correspondences.

    pw: pointmaps of the scene graph's E edges at (H,W); flows: float32 (E,H,W,2) optical flow
    i->j per edge (None: no CMA); static_masks: bool (T,H,W) True = static (None: all static);
    tracks: float (T,N,2) pixels and visible: bool (T,N) for PTS (None: no stage 2);
    intrinsics: known (T,4) fx, fy, cx, cy in pixels of (H,W) (None: the focal estimated, the
    principal point at the image centre), fixed or a starting point per `intrinsics.mode`.
    cfg: a DictConfig/namespace with `optim`, `weights`, `cma`, `pts`, `intrinsics` sections
    (configs/c4d).
    """
    _check_inputs(pw, num_frames, flows, static_masks, tracks, visible)
    check_intrinsics(intrinsics, num_frames)
    known = None if intrinsics is None else torch.as_tensor(np.asarray(intrinsics), dtype=torch.float32)
    torch.manual_seed(int(cfg.seed))
    opt_cfg, weights = cfg.optim, cfg.weights
    history: dict = {"seconds": {}, "cpu_seconds": {}, "losses": {}}
    total = int(opt_cfg.stage1_iters)
    factor, coarse_iters = int(opt_cfg.coarse_factor), int(opt_cfg.coarse_iters)
    coarse_iters = coarse_iters if factor > 1 else 0

    init = None
    if coarse_iters:  # the first iterations of stage 1 on pooled observations (coarse_to_fine)
        coarse_to_fine.check_factor(pw.image_size, factor)
        start, cpu_start = time.perf_counter(), time.process_time()
        pooled, pooled_flows, pooled_static = coarse_to_fine.pooled_inputs(pw, factor, flows, static_masks)
        coarse = Stage1(pooled, num_frames, cfg, pooled_flows, pooled_static, device,
                        intrinsics=None if known is None else coarse_to_fine.pooled_intrinsics(known, factor))
        del pooled, pooled_flows, pooled_static
        history["seconds"]["init_coarse"] = time.perf_counter() - start
        history["cpu_seconds"]["init_coarse"] = time.process_time() - cpu_start
        start = time.perf_counter()
        coarse_adam = adam(list(coarse.params.parameters()), opt_cfg)
        history["losses"]["stage1_coarse"] = _run_adam(
            coarse_adam, range(coarse_iters), total, opt_cfg, coarse.step, f"stage 1 at 1/{factor} size",
            progress)
        history["seconds"]["stage1_coarse"] = time.perf_counter() - start
        init = coarse_to_fine.lift(coarse.params, pw, num_frames, factor, intrinsics=known)

    start, cpu_start = time.perf_counter(), time.process_time()
    stage1 = Stage1(pw, num_frames, cfg, flows, static_masks, device, init=init, intrinsics=known)
    params = stage1.params
    history["seconds"]["init"] = time.perf_counter() - start
    history["cpu_seconds"]["init"] = time.process_time() - cpu_start

    stage1_adam = adam(list(params.parameters()), opt_cfg)
    if coarse_iters:
        coarse_to_fine.lift_adam_state(coarse_adam, coarse.params, stage1_adam, params, factor)
        del coarse, coarse_adam
    start = time.perf_counter()
    history["losses"]["stage1"] = _run_adam(stage1_adam, range(coarse_iters, total), total, opt_cfg,
                                            stage1.step, "stage 1 (GA+CMA+CTS)", progress)
    history["seconds"]["stage1"] = time.perf_counter() - start
    depth_stage1 = params.depth().detach().cpu().numpy().astype(np.float32)

    available = {"pointmaps"} | ({"tracks"} if tracks is not None else set())
    terms = active_objectives(2, weights, available) if opt_cfg.stage2_iters > 0 else []
    if weights.pts > 0 and tracks is None:
        log.warning("no tracks given: stage 2 (PTS) skipped")
    if terms:
        pts_targets = None
        if tracks is not None:  # the PTS targets: smoothed tracks spread to every pixel, built once
            start, cpu_start = time.perf_counter(), time.process_time()
            pc = cfg.pts
            with torch.no_grad():
                trk = torch.as_tensor(np.asarray(tracks, np.float32), device=device)
                vis = torch.as_tensor(np.asarray(visible, bool), device=device) & torch.isfinite(trk).all(-1)
                targets, has_target = objectives.pts_targets(
                    params.world_points(), torch.nan_to_num(trk, -1.0), vis, pc.window, pc.extend,
                    pc.kernel, pc.lam, pc.knn)
                pts_targets = fixed_camera_pts(params, targets, has_target)
                del targets
            history["seconds"]["pts_targets"] = time.perf_counter() - start
            history["cpu_seconds"]["pts_targets"] = time.process_time() - cpu_start
            history["pts_frames"] = int(has_target.sum())
        for p in params.parameters():
            p.requires_grad_(False)
        params.log_depth.requires_grad_(True)
        state = StageState(params, stage1.data, pts_targets=pts_targets)
        start = time.perf_counter()
        history["losses"]["stage2"] = _run_adam(adam([params.log_depth], opt_cfg),
                                                range(opt_cfg.stage2_iters), opt_cfg.stage2_iters, opt_cfg,
                                                lambda: stage_step(state, terms, weights, 0),
                                                "stage 2 (PTS)", progress)
        history["seconds"]["stage2"] = time.perf_counter() - start

    with torch.no_grad():
        result = OptimisationResult(
            depth=params.depth().cpu().numpy().astype(np.float32),
            cam_to_world=params.cam_to_world().cpu().numpy().astype(np.float32),
            intrinsics=params.intrinsics().cpu().numpy().astype(np.float32),
            points=params.world_points().cpu().numpy().astype(np.float32),
            confidence=frame_confidence(pw, num_frames),
            depth_stage1=depth_stage1,
            history=history,
        )
    return result
