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
normalise once (see `c4d_pipeline.optimize`).
"""

from __future__ import annotations

import logging

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


def apply_similarity(points: torch.Tensor, scale: torch.Tensor, rot: torch.Tensor,
                     trans: torch.Tensor) -> torch.Tensor:
    """sigma R x + t for points (e,P,3), scale (e,), rot (e,3,3), trans (e,3) -> (e,P,3)."""
    return affine(points, scale[:, None, None] * rot, trans)


def global_alignment_sum(world: torch.Tensor, ei: torch.Tensor, ej: torch.Tensor,
                         pts_i: torch.Tensor, pts_j: torch.Tensor, w_i: torch.Tensor,
                         w_j: torch.Tensor, scale: torch.Tensor, rot: torch.Tensor,
                         trans: torch.Tensor) -> torch.Tensor:
    """sum_e sum_p w ||X^{i_e}_p - P_e(pts_i)_p|| + (same for j). Divide by E*P for the GA loss.

    world (T,P,3); ei, ej (e,) frame indices; pts_i, pts_j (e,P,3); w_i, w_j (e,P) = log conf;
    scale (e,), rot (e,3,3), trans (e,3).
    """
    dist_i = (world[ei] - apply_similarity(pts_i, scale, rot, trans)).norm(dim=-1)  # (e,P)
    dist_j = (world[ej] - apply_similarity(pts_j, scale, rot, trans)).norm(dim=-1)  # (e,P)
    return (w_i * dist_i).sum() + (w_j * dist_j).sum()


# ----------------------------------------------------------------------------- CMA


def ego_flow(cam_points_i: torch.Tensor, cam_to_world_i: torch.Tensor,
             cam_to_world_j: torch.Tensor, k_j: torch.Tensor, pixels: torch.Tensor):
    """Pixel displacement of view i's points when the camera moves from i to j.

    cam_points_i (e,P,3) in camera i; poses (e,4,4) camera-to-world; k_j (e,3,3); pixels (P,2).
    Returns flow (e,P,2) and the depth of each point in camera j (e,P).
    """
    rel = torch.linalg.solve(cam_to_world_j, cam_to_world_i)  # (e,4,4) camera i -> camera j
    in_j = affine(cam_points_i, rel[:, :3, :3], rel[:, :3, 3])  # (e,P,3)
    proj = affine(in_j, k_j)  # (e,P,3)
    z = proj[..., 2]
    uv = proj[..., :2] / z.clamp_min(1e-6)[..., None]  # (e,P,2)
    return uv - pixels, in_j[..., 2]


def camera_motion_sum(cam_points: torch.Tensor, cam_to_world: torch.Tensor,
                      intrinsics: torch.Tensor, ei: torch.Tensor, ej: torch.Tensor,
                      flow: torch.Tensor, static: torch.Tensor, pixels: torch.Tensor,
                      max_px: float, px_scale: float = 1.0) -> torch.Tensor:
    """sum over static pixels of px_scale |F_ego^{i->j} - F^{i->j}|_1 (both channels). Divide by
    the number of static pixels (times 2) for the CMA loss.

    cam_points (T,P,3) own-camera points; cam_to_world (T,4,4); intrinsics (T,3,3); ei, ej (e,);
    flow (e,P,2) optical flow i->j; static (e,P) bool (static in frame i); pixels (P,2).
    `px_scale` converts this image's pixels to reference pixels (reference size / image size);
    errors and `max_px` are in reference pixels. Pixels whose error exceeds `max_px` (flow
    outliers, leaving the image) or that land behind camera j are ignored, as in MonST3R's flow loss.
    """
    ego, z_j = ego_flow(cam_points[ei], cam_to_world[ei], cam_to_world[ej], intrinsics[ej], pixels)
    err = px_scale * (ego - flow).abs()  # (e,P,2) reference pixels
    keep = static[..., None] & (z_j > 1e-6)[..., None] & (err < max_px).detach()
    return (err * keep).sum()


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


def point_smoothness(world: torch.Tensor, targets: torch.Tensor, has_target: torch.Tensor) -> torch.Tensor:
    """Mean L1 distance between world pointmaps (T,H,W,3) and PTS targets on frames with targets."""
    if not bool(has_target.any()):
        return world.sum() * 0.0
    return (world[has_target] - targets[has_target]).abs().mean()
