"""The C4D objectives (paper sec. 3.1, 3.4 and supplement), vectorised over edges, CPU or GPU.

Shapes: T frames, E edges (directed pairs), P = H*W pixels, N tracks.
- GA  (global alignment): confidence-weighted unsquared Euclidean distance between the world
  pointmaps and each pair's pointmaps mapped by its similarity (DUSt3R).
- CMA (camera movement alignment): L1 between the ego-motion flow implied by depth, poses and
  intrinsics and the optical flow, on static pixels, in pixels of a reference image size (512, the
  DUSt3R/MonST3R resolution the paper's weight 0.01 was set at), so the weight means the same at
  any optimisation resolution.
- CTS (camera trajectory smoothness): sum_t ||R_t^T R_{t+1} - I||_F + ||T_{t+1} - T_t||_2.
- PTS (point trajectory smoothness): L1 between the world pointmaps and their smoothed version,
  built by smoothing lifted 3-D tracks with adaptive weights (kernel 5, lambda 1) and spreading
  the smoothing displacements to every pixel by Linear Blend Displacement (k = 4 nearest tracks),
  in non-overlapping windows of 20 frames extended by 5 frames on each side.
GA and CMA return *sums* over their edges so that callers may evaluate edges in chunks and
normalise once (see `c4d_pipeline.optimize`); GA takes channels-first (n,3,P) point layouts, CMA
the (T,P) depth and the pixel grid, and both carry hand-written gradients (the per-pixel work is a
few fused passes instead of an autograd graph of (n,P,3) temporaries). `OBJECTIVES` (bottom)
registers every term with its weight key, stage and inputs; the stage loops iterate over it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import torch
import torch.nn.functional as F

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- GA


def affine(points: torch.Tensor, mat: torch.Tensor, trans: torch.Tensor | None = None) -> torch.Tensor:
    """A x + t for points (e,P,3), mat (e,3,3), trans (e,3) or None -> (e,P,3) (one fused
    batched multiply-add; measured faster on CPU than einsum or broadcast products)."""
    if trans is None:
        return torch.bmm(points, mat.transpose(1, 2))
    return torch.baddbmm(trans[:, None], points, mat.transpose(1, 2))


def _norm3(vec: torch.Tensor) -> torch.Tensor:
    """Euclidean norm over dim 1 of (n,3,P) -> (n,P) (two fused multiply-adds; on CPU
    `linalg.vector_norm(dim=1)` of this layout was measured 60x slower)."""
    sq = torch.addcmul(torch.addcmul(vec[:, 0] * vec[:, 0], vec[:, 1], vec[:, 1]), vec[:, 2], vec[:, 2])
    return sq.sqrt_()


def _gather(frames: tuple, index: list[int]) -> torch.Tensor:
    """The per-frame tensors `frames[f]` (each (...)) for f in `index` (n,) stacked: (n,...) (one
    copy, which the kernels then work in place)."""
    return torch.stack([frames[f] for f in index])


def _per_frame_grads(rows: torch.Tensor, index: list[int], num_frames: int) -> list:
    """The gradients of the T per-frame inputs from the rows (n,...) of their gathered copy: row k
    is frame index[k]'s, a repeated frame's rows summed; frames not gathered get None (no (T,...)
    tensor is made: an edge chunk's gradient touches only its frames)."""
    frames, inverse = torch.tensor(index).unique(return_inverse=True)  # (u,) sorted, (n,)
    if len(frames) < len(index):  # sum the rows of each frame: row j of the sum is frames[j]'s
        rows = rows.new_zeros((len(frames),) + rows.shape[1:]).index_add_(0, inverse.to(rows.device), rows)
        index = frames.tolist()
    grads: list = [None] * num_frames
    for f, grad in zip(index, rows.unbind(0)):
        grads[f] = grad
    return grads


class _GlobalAlignment(torch.autograd.Function):
    """sum_k sum_p w_kp ||X^{f_k}_p - (A_k y_kp + b_k)||, gradient written out (see
    `global_alignment_sum`); the forward computes the gradient while its temporaries are alive."""

    @staticmethod
    def forward(ctx, mat, trans, pts, log_conf, index, *world):
        # in place on the gathered copy: an out-of-place baddbmm copies its input first
        res = _gather(world, index).baddbmm_(mat, pts, alpha=-1.0).sub_(trans[..., None])  # (n,3,P) X - A y - b
        dist = _norm3(res)  # (n,P)
        loss = torch.dot(log_conf.flatten(), dist.flatten())
        if any(ctx.needs_input_grad):
            unit = res.mul_((log_conf / dist.clamp_min(1e-30))[:, None])  # (n,3,P) w (X - A y - b) / |.|
            ctx.index, ctx.num_frames = index, len(world)
            ctx.save_for_backward(unit, torch.bmm(unit, pts.transpose(1, 2)).neg_(), unit.sum(-1).neg_())
        return loss

    @staticmethod
    def backward(ctx, grad):
        unit, grad_mat, grad_trans = ctx.saved_tensors
        return (grad_mat * grad, grad_trans * grad, None, None, None,
                *_per_frame_grads(unit.mul_(grad), ctx.index, ctx.num_frames))


def global_alignment_sum(world, frames: torch.Tensor, pts: torch.Tensor, log_conf: torch.Tensor,
                         mat: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """GA summed over n pointmap views: sum_k sum_p w_kp ||X^{f_k}_p - (A_k y_kp + b_k)||.

    Channels-first layout: world, the world pointmaps X: a (T,3,P) tensor or T tensors (3,P) (the
    optimiser's one leaf per frame: the gradient then touches only the frames read, no (T,3,P)
    tensor per call); frames (n,) the frame f_k of each view; pts (n,3,P) the views' pointmaps y
    in their pair's frame (any strides: a transposed (n,P,3) array is read in place); log_conf
    (n,P) the weights w;
    mat (n,3,3) A_k = sigma_e R_e and trans (n,3) b_k = t_e of the view's edge e. A pair gives two
    views (its pointmaps i and j, with the same similarity). Differentiable in world, mat and trans
    by a hand-written gradient (one pass, no autograd graph over the n*P points); divide by
    E*P for DUSt3R's GA loss.
    """
    return _GlobalAlignment.apply(mat, trans, pts, log_conf, frames.tolist(), *world)


# ----------------------------------------------------------------------------- CMA


def ego_projection(rotations: torch.Tensor, translations: torch.Tensor, intrinsics: torch.Tensor,
                   ei: torch.Tensor, ej: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per edge i->j the map of a pixel of view i and its depth to homogeneous pixels of view j:
    (H (e,3,3), c (e,3)) with [u' z, v' z, z] = d H [u, v, 1] + c, H = K_j R_j^T R_i K_i^-1 (the
    rotation homography), c = K_j R_j^T (T_i - T_j). Camera-to-world rotations (T,3,3) and
    translations (T,3), intrinsics (T,3,3) (fx, fy, cx, cy; no skew), ei, ej (e,)."""
    to_j = rotations[ej].transpose(1, 2)  # (e,3,3) world -> camera j
    k_to_j = intrinsics[ej] @ to_j
    k = intrinsics[ei]
    fx, fy = k[:, 0, 0], k[:, 1, 1]
    k_inv = torch.zeros_like(k)  # K_i^-1 = [[1/fx, 0, -cx/fx], [0, 1/fy, -cy/fy], [0, 0, 1]]
    k_inv[:, 0, 0], k_inv[:, 1, 1], k_inv[:, 2, 2] = 1.0 / fx, 1.0 / fy, 1.0
    k_inv[:, 0, 2], k_inv[:, 1, 2] = -k[:, 0, 2] / fx, -k[:, 1, 2] / fy
    return k_to_j @ rotations[ei] @ k_inv, (k_to_j @ (translations[ei] - translations[ej])[..., None])[..., 0]


class _CameraMotion(torch.autograd.Function):
    """sum of px_scale |F_ego - F| over kept static pixels, gradient written out (see
    `camera_motion_sum`)."""

    @staticmethod
    def forward(ctx, mat, offset, pixels, target, static, max_px, px_scale, index, *depth):
        n, num_pixels = len(index), pixels.shape[1]
        gathered = _gather(depth, index)[:, None]  # (n,1,P)
        rays = torch.bmm(mat, pixels.expand(n, 3, num_pixels))  # (n,3,P) H [u, v, 1]
        proj = torch.addcmul(offset[..., None], rays, gathered)  # (n,3,P) homogeneous pixels in view j
        z = proj[:, 2]
        valid = static & (z > 1e-6)  # (n,P)
        inv_z = z.clamp_min(1e-6).reciprocal_()  # (n,P)
        uv = proj[:, :2].mul_(inv_z[:, None])  # (n,2,P) pixels in view j
        diff = uv - target  # (n,2,P) F_ego - F in image pixels
        sign = diff.sign()
        keep = ((diff.abs_() < max_px / px_scale) & valid[:, None]).to(diff.dtype)  # (n,2,P) 1 = counted
        loss = torch.dot(diff.flatten(), keep.flatten()) * px_scale  # reference pixels
        if any(ctx.needs_input_grad):
            g_proj = torch.empty_like(proj)  # (n,3,P) d loss / d proj
            g_uv = g_proj[:, :2]
            torch.mul(sign, keep, out=g_uv).mul_((px_scale * inv_z)[:, None])  # at fixed z
            torch.mul(g_uv[:, 0], uv[:, 0], out=g_proj[:, 2])
            g_proj[:, 2].addcmul_(g_uv[:, 1], uv[:, 1]).neg_()  # d/dz = -(g_u u + g_v v) / z
            g_depth = torch.addcmul(torch.addcmul(g_proj[:, 0] * rays[:, 0], g_proj[:, 1], rays[:, 1]),
                                    g_proj[:, 2], rays[:, 2])  # (n,P) g . H [u, v, 1]
            g_mat = torch.mul(g_proj, gathered, out=rays).view(3 * n, num_pixels) @ pixels.T  # (3n,3)
            ctx.index, ctx.num_frames = index, len(depth)
            ctx.save_for_backward(g_depth, g_mat.view(n, 3, 3), g_proj.sum(-1))
        return loss

    @staticmethod
    def backward(ctx, grad):
        grad_depth, grad_mat, grad_offset = ctx.saved_tensors
        return (grad_mat * grad, grad_offset * grad, None, None, None, None, None, None,
                *_per_frame_grads(grad_depth.mul_(grad), ctx.index, ctx.num_frames))


def camera_motion_sum(depth, frames: torch.Tensor, mat: torch.Tensor, offset: torch.Tensor,
                      pixels: torch.Tensor, target: torch.Tensor, static: torch.Tensor,
                      max_px: float, px_scale: float = 1.0) -> torch.Tensor:
    """sum over static pixels of px_scale |F_ego^{i->j} - F^{i->j}|_1 (both channels). Divide by
    the number of static pixels (times 2) for the CMA loss.

    depth z-depth of every pixel: a (T,P) tensor or T tensors (P,) (as GA's world); frames (e,)
    the frame i of each edge; (mat (e,3,3),
    offset (e,3)) from `ego_projection`; pixels (3,P) the homogeneous pixel grid [u, v, 1];
    target (e,2,P) = pixel + optical flow i->j, i.e. where the flow puts each pixel of view i;
    static (e,P) bool (static in frame i). The ego-motion pixel is d H [u, v, 1] + c divided by its
    z: one depth gather per edge and one matrix product with the shared grid (no (e,3,P) camera
    points). `px_scale` converts this image's pixels to reference pixels (reference size / image
    size); errors and `max_px` are in reference pixels. Pixels whose error exceeds `max_px` (flow
    outliers, leaving the image) or that land behind camera j are ignored, as in MonST3R's flow
    loss. Differentiable in depth, mat and offset by a hand-written gradient.
    """
    return _CameraMotion.apply(mat, offset, pixels, target, static, float(max_px), float(px_scale),
                               frames.tolist(), *depth)


# ----------------------------------------------------------------------------- CTS


def camera_smoothness(rotations: torch.Tensor, translations: torch.Tensor) -> torch.Tensor:
    """sum_t ||R_t^T R_{t+1} - I||_F + ||T_{t+1} - T_t||_2 for rotations (T,3,3), translations (T,3)."""
    rel = rotations[:-1].transpose(1, 2) @ rotations[1:]  # (T-1,3,3)
    eye = torch.eye(3, dtype=rel.dtype, device=rel.device)
    rot_term = (rel - eye).flatten(1).norm(dim=-1)  # (T-1,)
    trans_term = (translations[1:] - translations[:-1]).norm(dim=-1)  # (T-1,)
    return (rot_term + trans_term).sum()


# ----------------------------------------------------------------------------- PTS


def smooth_trajectories(traj: torch.Tensor, kernel: int = 5, lam: float = 1.0) -> torch.Tensor:
    """Adaptive-weight 1-D smoothing of trajectories (T,N,C) along time -> (T,N,C).

    W_t = exp(-lam ||T_t - T_{t-1}||) for t >= 1 and W_0 = W_1; the result is
    conv(T * W, K) / conv(W, K) with the uniform kernel K = 1/k (zero padding, so the ends are
    averages over the frames that exist).
    """
    t, n, c = traj.shape
    if t < 2:
        return traj.clone()
    step = (traj[1:] - traj[:-1]).norm(dim=-1)  # (T-1,N)
    weight = torch.exp(-lam * step)
    weight = torch.cat([weight[:1], weight], dim=0)  # (T,N)
    box = torch.full((1, 1, kernel), 1.0 / kernel, dtype=traj.dtype, device=traj.device)
    num = (traj * weight[..., None]).permute(1, 2, 0).reshape(n * c, 1, t)  # (N*C,1,T)
    den = weight.T.reshape(n, 1, t)  # (N,1,T)
    num = F.conv1d(num, box, padding=kernel // 2).reshape(n, c, t)
    den = F.conv1d(den, box, padding=kernel // 2)  # (N,1,T)
    return (num / den).permute(2, 0, 1)  # (T,N,C)


def linear_blend_displacement(queries: torch.Tensor, controls: torch.Tensor,
                              displacements: torch.Tensor, k: int = 4, eps: float = 1e-12,
                              chunk: int = 65536) -> torch.Tensor:
    """Move queries (P1,3) by the inverse-squared-distance blend of the displacements (P2,3) of
    their k nearest controls (P2,3): x + sum_k w_k D_k / sum_k w_k, w_k = 1 / ||x - C_k||^2.
    Returns (P1,3). Queries are processed in chunks to bound the (chunk,P2) distance matrix."""
    k = min(k, controls.shape[0])
    out = []
    for start in range(0, queries.shape[0], chunk):
        q = queries[start:start + chunk]  # (p,3)
        d2 = torch.cdist(q, controls).square()  # (p,P2)
        d2_k, idx = d2.topk(k, dim=1, largest=False)  # (p,k)
        w = 1.0 / (d2_k + eps)
        w = w / w.sum(1, keepdim=True)
        out.append(q + (w[..., None] * displacements[idx]).sum(1))  # (p,3)
    return torch.cat(out)


def pts_windows(num_frames: int, window: int = 20, extend: int = 5) -> list[tuple[int, int, int, int]]:
    """Non-overlapping windows [start, end) and their extensions [ext_start, ext_end) (clipped)."""
    return [
        (s, min(s + window, num_frames), max(s - extend, 0), min(s + window + extend, num_frames))
        for s in range(0, num_frames, window)
    ]


def sample_points(world: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of world pointmaps (T,H,W,3) at pixels (T,N,2) (x, y) -> (T,N,3)."""
    t, h, w, _ = world.shape
    grid = torch.stack([pixels[..., 0] / (w - 1) * 2 - 1, pixels[..., 1] / (h - 1) * 2 - 1], -1)
    out = F.grid_sample(world.permute(0, 3, 1, 2), grid[:, :, None], mode="bilinear",
                        align_corners=True)  # (T,3,N,1)
    return out[..., 0].permute(0, 2, 1)


def pts_targets(world: torch.Tensor, tracks: torch.Tensor, visible: torch.Tensor,
                window: int = 20, extend: int = 5, kernel: int = 5, lam: float = 1.0,
                knn: int = 4) -> tuple[torch.Tensor, torch.Tensor]:
    """Smoothed pointmaps for PTS.

    world (T,H,W,3) (no gradient needed); tracks (T,N,2) pixels; visible (T,N) bool.
    Per window: tracks visible and inside the image over the whole extended window are lifted to
    3-D, smoothed, and their displacements blended onto every pixel of the window's frames.
    Returns targets (T,H,W,3) and has_target (T,) bool (False for frames of windows with fewer
    than `knn` usable tracks; those frames keep their own points and get no PTS loss).
    """
    num_frames, h, w, _ = world.shape
    world = world.detach()
    inside = (tracks[..., 0] >= 0) & (tracks[..., 0] <= w - 1) & (tracks[..., 1] >= 0) & (tracks[..., 1] <= h - 1)
    usable = visible & inside  # (T,N)
    targets = world.clone()
    has_target = torch.zeros(num_frames, dtype=torch.bool, device=world.device)
    for start, end, ext_start, ext_end in pts_windows(num_frames, window, extend):
        keep = usable[ext_start:ext_end].all(0)  # (N,)
        if int(keep.sum()) < knn:
            log.warning("PTS: frames %d-%d have %d tracks visible throughout (need %d); skipped",
                        start, end - 1, int(keep.sum()), knn)
            continue
        lifted = sample_points(world[ext_start:ext_end], tracks[ext_start:ext_end][:, keep])  # (t,n,3)
        smoothed = smooth_trajectories(lifted, kernel, lam)
        for t in range(start, end):
            c = t - ext_start
            targets[t] = linear_blend_displacement(
                world[t].reshape(-1, 3), lifted[c], smoothed[c] - lifted[c], knn
            ).reshape(h, w, 3)
        has_target[start:end] = True
    return targets, has_target


class _FixedCameraL1(torch.autograd.Function):
    """mean |rays * exp(log_depth) + offset| over (t,3,P), the gradient to log-depth by hand:
    sum_c sign(diff_c) rays_c * depth / n (one pass where autograd's world points take ~5)."""

    @staticmethod
    def forward(ctx, log_depth, rays, offset):  # (t,P), (t,3,P), (t,3,P)
        depth = log_depth.exp()[:, None]  # (t,1,P)
        diff = torch.addcmul(offset, rays, depth)  # (t,3,P) world point - target
        ctx.count = diff.numel()
        loss = diff.abs().sum() / ctx.count
        ctx.save_for_backward(diff.sign_().mul_(rays).sum(1).mul_(depth[:, 0]))  # (t,P)
        return loss

    @staticmethod
    def backward(ctx, grad):
        (slope,) = ctx.saved_tensors
        return grad * slope / ctx.count, None, None


def fixed_camera_point_smoothness(log_depth: torch.Tensor, frames: torch.Tensor, rays: torch.Tensor,
                                  offset: torch.Tensor) -> torch.Tensor:
    """PTS: the mean L1 distance between the world pointmaps and their targets on the frames with
    targets, with the cameras fixed (stage 2 optimises depth only): log_depth (T,H,W); frames (t,)
    the frames with targets, rays (t,3,P) their world rays R K^-1 [u, v, 1] and offset (t,3,P)
    camera centre - target, so that a world point minus its target is rays * depth + offset
    (`c4d_pipeline.optimize.fixed_camera_pts` builds them once per stage)."""
    if frames.numel() == 0:
        return log_depth.sum() * 0.0
    return _FixedCameraL1.apply(log_depth.flatten(1)[frames], rays, offset)


# ----------------------------------------------------------------------------- registry


@dataclass(frozen=True)
class Objective:
    """One C4D objective as the stage loops of `c4d_pipeline.optimize` see it.

    name: its loss name in the history; weight: its key under `weights:` in the config (the term is
    skipped at weight 0); stage: 1 (depth, poses, intrinsics, edge similarities) or 2 (depth only);
    inputs: the observations it needs ('pointmaps', 'flow', 'tracks'), skipped when one is missing;
    per_edge: True if `fn(state, edges)` returns a sum over the edges of the slice `edges` (the loop
    evaluates edge chunks and adds them up), False if `fn(state)` is called once per iteration.
    `fn` returns a scalar tensor, already normalised (the weighted sum of all terms is the loss).
    """

    name: str
    weight: str
    stage: int
    inputs: tuple[str, ...]
    per_edge: bool
    fn: Callable


OBJECTIVES: list[Objective] = []


def objective(name: str, weight: str, stage: int, inputs: tuple[str, ...] = (), per_edge: bool = False):
    """Decorator registering `fn` as an `Objective` (see its docstring); returns fn unchanged."""
    def register(fn):
        OBJECTIVES.append(Objective(name, weight, stage, tuple(inputs), per_edge, fn))
        return fn
    return register


# `state` is the loop's `c4d_pipeline.optimize.StageState`: `state.params` (SceneParams),
# `state.data` (the observations, channels-first), `state.shared(name)` (per-iteration per-edge
# tensors whose gradients the edge chunks accumulate), `state.shared_frames(name)` (the same for
# per-frame tensors, one leaf per frame, which GA and CMA take as they are),
# `state.shared_value(name)` (either, attached to the parameters' graph), `state.cma_max_px`,
# `state.cma_px_scale` and `state.pts_targets` (stage 2: `optimize.fixed_camera_pts`'s constants).


@objective("ga", weight="ga", stage=1, inputs=("pointmaps",), per_edge=True)
def _ga_term(state, edges: slice) -> torch.Tensor:
    world = state.shared_frames("world")  # T x (3,P)
    mat, trans = state.shared("edge_similarity")
    data = state.data
    total = sum(global_alignment_sum(world, frames[edges], pts[edges], log_conf[edges], mat[edges], trans[edges])
                for frames, pts, log_conf in data.views)  # views i and j of every edge
    return total / (data.num_edges * data.num_pixels)


@objective("cma", weight="cma", stage=1, inputs=("flow",), per_edge=True)
def _cma_term(state, edges: slice) -> torch.Tensor:
    depth = state.shared_frames("depth")  # T x (P,)
    mat, offset = state.shared("ego_projection")
    data = state.data
    total = camera_motion_sum(depth, data.ei[edges], mat[edges], offset[edges], data.pixels, data.target[edges],
                              data.static[edges], state.cma_max_px, state.cma_px_scale)
    return total / (2 * data.num_static)


@objective("cts", weight="cts", stage=1)
def _cts_term(state) -> torch.Tensor:
    return camera_smoothness(state.shared_value("rotations")[0], state.params.trans)


@objective("pts", weight="pts", stage=2, inputs=("tracks",))
def _pts_term(state) -> torch.Tensor:
    return fixed_camera_point_smoothness(state.params.log_depth, *state.pts_targets)
