"""The two-stage correspondence-aided optimisation (paper sec. 3.4, supplement "Optimization").

Stage 1: GA + w_cma CMA + w_cts CTS over depth, poses, intrinsics and the per-edge similarities.
Stage 2: poses, intrinsics and edge similarities fixed; w_pts PTS over depth only.
Units, so the paper's weights keep their meaning: the world is scaled as DUSt3R's (mean distance of
the points from their camera `optim.world_scale` = 0.5: pair pointmaps of unit mean distance, edge
scales of geometric mean 0.5), and CMA measures flow in pixels of a `cma.reference_size` = 512 image.
Both: Adam, lr 0.01 (decayed to `lr_min` by `schedule`), `stage1_iters` / `stage2_iters` steps.

Memory: GA and CMA are evaluated `edge_chunk` edges at a time. The per-frame quantities (world
points, camera points, poses, intrinsics, edge similarities) are computed once per iteration, the
chunks back-propagate into detached copies of them, and one final backward carries the summed
gradients to the parameters; the result equals the unchunked gradient while only one chunk's
(e,H*W,3) temporaries are alive.
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
from c4d_pipeline import objectives
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
    history: dict = field(default_factory=dict)  # seconds and per-iteration losses per stage


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
    """The observations on the optimisation device, flattened to P = H*W pixels."""

    def __init__(self, pw, flows, static_masks, device):
        e = pw.num_edges
        self.ei = torch.from_numpy(pw.edges[:, 0]).to(device)
        self.ej = torch.from_numpy(pw.edges[:, 1]).to(device)
        self.pts_i = torch.from_numpy(pw.pts_i).reshape(e, -1, 3).to(device)  # (E,P,3)
        self.pts_j = torch.from_numpy(pw.pts_j).reshape(e, -1, 3).to(device)
        self.w_i = torch.from_numpy(pw.conf_i).reshape(e, -1).log().to(device)  # (E,P)
        self.w_j = torch.from_numpy(pw.conf_j).reshape(e, -1).log().to(device)
        self.flow = self.static = None
        if flows is not None:
            flow = torch.from_numpy(np.ascontiguousarray(flows, dtype=np.float32)).reshape(e, -1, 2)
            finite = torch.isfinite(flow).all(-1)  # (E,P)
            if static_masks is None:
                static = torch.ones_like(finite)
            else:
                per_frame = torch.from_numpy(np.asarray(static_masks, bool)).flatten(1)  # (T,P)
                static = per_frame[self.ei.cpu()]  # (E,P) static in frame i of each edge
            self.flow = torch.nan_to_num(flow, 0.0, 0.0, 0.0).to(device)
            self.static = (static & finite).to(device)  # (E,P) static in frame i
            self.num_static = max(int(self.static.sum()), 1)
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
    principal = torch.tensor([(w - 1) / 2, (h - 1) / 2], dtype=init.focal.dtype)
    ray_len = pixel_rays(h, w, init.focal, principal).norm(dim=-1)  # (T,H,W) distance per unit depth
    factor = world_scale / float((ray_len * init.depth).mean())
    pose = init.cam_to_world.clone()
    pose[:, :3, 3] *= factor
    return replace(init, depth=init.depth * factor, cam_to_world=pose,
                   edge_scale=init.edge_scale * factor, edge_translation=init.edge_translation * factor)


@dataclass
class _StepCfg:
    edge_chunk: int  # edges per chunk, 0 = all
    cma_max_px: float  # CMA ignores flow errors above this many reference pixels
    cma_px_scale: float  # reference pixels per image pixel


def _stage1_step(params: SceneParams, data: _Inputs, weights, cfg: _StepCfg, pixels) -> dict:
    """One forward/backward of GA + CMA + CTS, edge-chunked (module docstring). Returns losses."""
    num_frames = params.num_frames
    num_edges, num_pix = data.pts_i.shape[:2]
    use_cma = weights.cma > 0 and data.flow is not None
    cam = params.camera_points()  # (T,H,W,3)
    world = params.world_points(cam).reshape(num_frames, num_pix, 3)
    pose, intr = params.cam_to_world(), params.intrinsics()
    scale, rot, trans = params.edge_similarities()
    shared = [world, scale, rot, trans] + ([cam.reshape(num_frames, num_pix, 3), pose, intr] if use_cma else [])
    leaves = [x.detach().requires_grad_() for x in shared]
    l_world, l_scale, l_rot, l_trans = leaves[:4]
    chunk = cfg.edge_chunk if cfg.edge_chunk > 0 else num_edges
    ga_total = cma_total = 0.0
    for start in range(0, num_edges, chunk):
        sl = slice(start, start + chunk)
        ga = objectives.global_alignment_sum(
            l_world, data.ei[sl], data.ej[sl], data.pts_i[sl], data.pts_j[sl], data.w_i[sl],
            data.w_j[sl], l_scale[sl], l_rot[sl], l_trans[sl]) / (num_edges * num_pix)
        loss = weights.ga * ga
        ga_total += float(ga.detach())
        if use_cma:
            l_cam, l_pose, l_intr = leaves[4:]
            cma = objectives.camera_motion_sum(
                l_cam, l_pose, l_intr, data.ei[sl], data.ej[sl], data.flow[sl], data.static[sl],
                pixels, cfg.cma_max_px, cfg.cma_px_scale) / (2 * data.num_static)
            loss = loss + weights.cma * cma
            cma_total += float(cma.detach())
        loss.backward()
    cts = objectives.camera_smoothness(params.rotations(), params.trans)
    pairs = [(x, leaf.grad) for x, leaf in zip(shared, leaves) if leaf.grad is not None]
    tensors = [x for x, _ in pairs] + ([weights.cts * cts] if weights.cts > 0 else [])
    grads = [g for _, g in pairs] + ([torch.ones_like(cts)] if weights.cts > 0 else [])
    torch.autograd.backward(tensors, grads)
    total = weights.ga * ga_total + weights.cma * cma_total + weights.cts * float(cts.detach())
    return {"total": total, "ga": ga_total, "cma": cma_total, "cts": float(cts.detach())}


def _run_adam(params_list, steps, cfg, step_fn, stage: str, progress: bool) -> dict:
    """Adam with the configured schedule; returns {loss name, 'seconds', 'cpu_seconds': [per-iteration values]}."""
    opt = torch.optim.Adam(params_list, lr=cfg.lr, betas=tuple(cfg.betas))
    curves: dict[str, list[float]] = {}
    for it in tqdm(range(steps), desc=stage, disable=not progress, leave=False):
        lr = learning_rate(it, steps, cfg.lr, cfg.lr_min, cfg.schedule)
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
) -> OptimisationResult:
    """Reconstruct depth, poses and intrinsics from pairwise pointmaps and correspondences.

    pw: pointmaps of the scene graph's E edges at (H,W); flows: float32 (E,H,W,2) optical flow
    i->j per edge (None: no CMA); static_masks: bool (T,H,W) True = static (None: all static);
    tracks: float (T,N,2) pixels and visible: bool (T,N) for PTS (None: no stage 2).
    cfg: a DictConfig/namespace with `optim`, `weights`, `cma`, `pts` sections (configs/c4d).
    """
    _check_inputs(pw, num_frames, flows, static_masks, tracks, visible)
    torch.manual_seed(int(cfg.seed))
    opt_cfg, weights = cfg.optim, cfg.weights
    history: dict = {"seconds": {}, "losses": {}}
    h, w = pw.image_size
    px_scale = cfg.cma.reference_size / max(h, w) if cfg.cma.reference_size > 0 else 1.0
    step_cfg = _StepCfg(opt_cfg.edge_chunk, cfg.cma.max_px, px_scale)

    start = time.perf_counter()
    init = rescale_world(initialise(pw, num_frames, shared_focal=opt_cfg.shared_focal),
                         (h, w), opt_cfg.world_scale)
    params = SceneParams(init.depth, init.cam_to_world, init.focal, init.edge_scale,
                         init.edge_rotation, init.edge_translation,
                         shared_focal=opt_cfg.shared_focal).to(device)
    data = _Inputs(pw, flows if weights.cma > 0 else None, static_masks, device)
    v, u = torch.meshgrid(torch.arange(h, device=device), torch.arange(w, device=device), indexing="ij")
    pixels = torch.stack([u, v], -1).reshape(-1, 2).float()  # (P,2)
    history["seconds"]["init"] = time.perf_counter() - start

    start = time.perf_counter()
    history["losses"]["stage1"] = _run_adam(
        list(params.parameters()), opt_cfg.stage1_iters, opt_cfg,
        lambda: _stage1_step(params, data, weights, step_cfg, pixels), "stage 1 (GA+CMA+CTS)", progress)
    history["seconds"]["stage1"] = time.perf_counter() - start
    depth_stage1 = params.depth().detach().cpu().numpy().astype(np.float32)

    run_pts = weights.pts > 0 and opt_cfg.stage2_iters > 0 and tracks is not None
    if weights.pts > 0 and tracks is None:
        log.warning("no tracks given: stage 2 (PTS) skipped")
    if run_pts:
        start = time.perf_counter()
        pc = cfg.pts
        with torch.no_grad():
            trk = torch.as_tensor(np.asarray(tracks, np.float32), device=device)
            vis = torch.as_tensor(np.asarray(visible, bool), device=device) & torch.isfinite(trk).all(-1)
            targets, has_target = objectives.pts_targets(
                params.world_points(), torch.nan_to_num(trk, -1.0), vis, pc.window, pc.extend,
                pc.kernel, pc.lam, pc.knn)
        history["seconds"]["pts_targets"] = time.perf_counter() - start
        history["pts_frames"] = int(has_target.sum())
        for p in params.parameters():
            p.requires_grad_(False)
        params.log_depth.requires_grad_(True)

        def stage2_step():
            pts = objectives.point_smoothness(params.world_points(), targets, has_target)
            (weights.pts * pts).backward()
            return {"total": weights.pts * float(pts.detach()), "pts": float(pts.detach())}

        start = time.perf_counter()
        history["losses"]["stage2"] = _run_adam([params.log_depth], opt_cfg.stage2_iters, opt_cfg,
                                                stage2_step, "stage 2 (PTS)", progress)
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
