"""The optimised variables of the 4D reconstruction, and the world pointmaps they define.

Per frame t (T frames, H x W pixels):
- depth D^t, parametrised as log-depth (T,H,W);
- camera-to-world pose [R^t | T^t]: unnormalised quaternion (w,x,y,z) (T,4) and translation (T,3);
- focal length f^t = fx^t, parametrised as `focal_break` * log f (DUSt3R's trick, so one
  Adam step moves f by ~lr/focal_break relative), or shared as one focal when `shared_focal`;
  fy^t = aspect^t f^t with the aspect ratio fy/fx a constant (1: square pixels) and the principal
  point (cx^t, cy^t) a constant (default the image centre ((W-1)/2, (H-1)/2); known intrinsics
  give both). With `fixed_focal` the focal is a constant too (known intrinsics, `intrinsics.mode`
  fixed): a buffer, so no optimiser sees it.
Per directed edge e: a similarity taking the pair's pointmaps into the world,
P_e(x) = sigma_e R_e x + t_e; the geometric mean of sigma_e is held at its initial value, which
removes the global-scale degeneracy of global alignment (all points collapsing to zero).

World pointmap: X^t(u, v) = R^t (D^t(u,v) K^-1 [u, v, 1]^T) + T^t.
"""

from __future__ import annotations

import torch
from torch import nn

from c4d_core.geometry import matrix_to_quat, quat_matrix_entries

FOCAL_BREAK = 20.0


def quat_to_rotation(quat: torch.Tensor) -> torch.Tensor:
    """(...,4) quaternions (w,x,y,z), any norm -> (...,3,3) rotation matrices (differentiable; the
    entries are `c4d_core.geometry.quat_matrix_entries`, the numpy `quat_to_matrix`'s formula)."""
    entries = quat_matrix_entries(*(quat / quat.norm(dim=-1, keepdim=True)).unbind(-1))
    return torch.stack(entries, dim=-1).reshape(quat.shape[:-1] + (3, 3))  # (...,9) -> (...,3,3)


def rotation_to_quat(rot: torch.Tensor) -> torch.Tensor:
    """(...,3,3) rotations -> (...,4) quaternions (w,x,y,z); computed by the numpy `matrix_to_quat`
    in float64 (initial values only, no gradient)."""
    return torch.as_tensor(matrix_to_quat(rot.detach().cpu().double().numpy()), dtype=rot.dtype)


def pixel_rays(height: int, width: int, focal: torch.Tensor, principal: torch.Tensor) -> torch.Tensor:
    """K^-1 [u, v, 1] for every pixel centre: focal (T,) (fx = fy) or (T,2) (fx, fy), principal
    (2,) (every frame's) or (T,2), pixels -> (T,H,W,3)."""
    fxy = focal[:, None].expand(-1, 2) if focal.ndim == 1 else focal  # (T,2)
    c = principal.expand(len(fxy), 2)  # (T,2)
    v, u = torch.meshgrid(
        torch.arange(height, dtype=focal.dtype, device=focal.device),
        torch.arange(width, dtype=focal.dtype, device=focal.device),
        indexing="ij",
    )  # (H,W) each
    x = (u[None] - c[:, 0, None, None]) / fxy[:, 0, None, None]  # (T,H,W)
    y = (v[None] - c[:, 1, None, None]) / fxy[:, 1, None, None]  # (T,H,W)
    return torch.stack([x, y, torch.ones_like(x)], dim=-1)  # (T,H,W,3)


class SceneParams(nn.Module):
    """Depth, poses, focals and per-edge similarities as `nn.Parameter`s (see module docstring).

    Initial values: depth (T,H,W) > 0, cam_to_world (T,4,4) rigid, focal (T,) fx, edge_scale (E,),
    edge_rotation (E,3,3), edge_translation (E,3); constants: principal (T,2) pixels (None: the
    image centre), aspect (T,) fy/fx (None: 1), and with `fixed_focal` the focal.
    """

    def __init__(
        self,
        depth: torch.Tensor,
        cam_to_world: torch.Tensor,
        focal: torch.Tensor,
        edge_scale: torch.Tensor,
        edge_rotation: torch.Tensor,
        edge_translation: torch.Tensor,
        shared_focal: bool = False,
        principal: torch.Tensor | None = None,
        aspect: torch.Tensor | None = None,
        fixed_focal: bool = False,
    ):
        super().__init__()
        num_frames, height, width = depth.shape
        self.image_size = (height, width)
        self.shared_focal = shared_focal and not fixed_focal
        if principal is None:
            principal = torch.tensor([(width - 1) / 2, (height - 1) / 2]).expand(num_frames, 2)
        self.register_buffer("principal", principal.clone().float())  # (T,2)
        self.register_buffer("aspect", torch.ones(num_frames) if aspect is None else aspect.clone().float())
        self.log_depth = nn.Parameter(depth.clamp_min(1e-6).log())  # (T,H,W)
        self.quat = nn.Parameter(rotation_to_quat(cam_to_world[:, :3, :3]))  # (T,4)
        self.trans = nn.Parameter(cam_to_world[:, :3, 3].clone())  # (T,3)
        log_f = focal.log() * FOCAL_BREAK  # (T,)
        if fixed_focal:
            self.register_buffer("focal_param", log_f)
        else:
            self.focal_param = nn.Parameter(log_f.mean(0, keepdim=True) if shared_focal else log_f)
        self.edge_quat = nn.Parameter(rotation_to_quat(edge_rotation))  # (E,4)
        self.edge_trans = nn.Parameter(edge_translation.clone())  # (E,3)
        self.edge_log_scale = nn.Parameter(edge_scale.log())  # (E,)
        self.register_buffer("mean_log_scale", edge_scale.log().mean())
        self.num_frames = num_frames

    # -- derived quantities
    def depth(self) -> torch.Tensor:
        return self.log_depth.exp()  # (T,H,W)

    def rotations(self) -> torch.Tensor:
        return quat_to_rotation(self.quat)  # (T,3,3)

    def focals(self) -> torch.Tensor:
        return (self.focal_param / FOCAL_BREAK).exp().expand(self.num_frames)  # (T,) fx

    def focals_xy(self) -> torch.Tensor:
        f = self.focals()
        return torch.stack([f, f * self.aspect], -1)  # (T,2) fx, fy

    def intrinsics(self) -> torch.Tensor:
        k = torch.zeros(self.num_frames, 3, 3, dtype=self.trans.dtype, device=self.trans.device)
        f = self.focals_xy()
        k[:, 0, 0], k[:, 1, 1] = f[:, 0], f[:, 1]
        k[:, 0, 2], k[:, 1, 2], k[:, 2, 2] = self.principal[:, 0], self.principal[:, 1], 1.0
        return k  # (T,3,3)

    def cam_to_world(self) -> torch.Tensor:
        pose = torch.zeros(self.num_frames, 4, 4, dtype=self.trans.dtype, device=self.trans.device)
        pose[:, :3, :3] = self.rotations()
        pose[:, :3, 3] = self.trans
        pose[:, 3, 3] = 1.0
        return pose  # (T,4,4)

    def camera_points(self) -> torch.Tensor:
        """(T,H,W,3) every pixel in its own camera frame."""
        rays = pixel_rays(*self.image_size, self.focals_xy(), self.principal)  # (T,H,W,3)
        return rays * self.depth()[..., None]

    def camera_points_channels_first(self) -> torch.Tensor:
        """(T,3,H*W) the same points as `camera_points`, channels-first (the layout of the stage-1
        kernels; built without channels-last temporaries, whose backward is slow on CPU)."""
        height, width = self.image_size
        v, u = torch.meshgrid(torch.arange(height, dtype=self.trans.dtype, device=self.trans.device),
                              torch.arange(width, dtype=self.trans.dtype, device=self.trans.device), indexing="ij")
        offsets = torch.stack([u.flatten(), v.flatten()])[None] - self.principal[:, :, None]  # (T,2,P)
        depth = self.depth().flatten(1)[:, None]  # (T,1,P)
        xy = offsets / self.focals_xy()[:, :, None] * depth  # (T,2,P)
        return torch.cat([xy, depth], 1)

    def world_points(self, cam_points: torch.Tensor | None = None) -> torch.Tensor:
        """(T,H,W,3) the global pointmaps X^t (from `camera_points()` unless given)."""
        from c4d_pipeline.objectives import affine

        cam = self.camera_points() if cam_points is None else cam_points  # (T,H,W,3)
        return affine(cam.flatten(1, 2), self.rotations(), self.trans).reshape(cam.shape)

    def edge_similarities(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per-edge (scale (E,), rotation (E,3,3), translation (E,3)); mean log-scale held fixed."""
        log_s = self.edge_log_scale - self.edge_log_scale.mean() + self.mean_log_scale
        return log_s.exp(), quat_to_rotation(self.edge_quat), self.edge_trans
