"""Initialisation of the global alignment from pairwise pointmaps (spanning-tree registration).

1. Score every frame pair by mean(conf_i) * mean(conf_j) and take the maximum spanning tree.
2. Seed the world with the strongest pair in its first view's camera frame, then walk the tree:
   each new frame's points come from a pair whose other frame is already placed, registered onto
   it with a confidence-weighted similarity (Umeyama) fit.
3. Per frame: the focal from its own-frame pointmap (weighted least squares + IRLS towards L1;
   with known intrinsics, the given fx, fy, cx, cy instead), the pose and depth scale from a
   similarity fit of that pointmap onto its world points.
4. Per edge: the similarity taking the pair's pointmaps onto the initial world points.
5. The world is rescaled so that the median depth is 1 (so fixed learning rates mean the same
   thing on every scene).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

from c4d_core.errors import UserError
from c4d_pipeline.pointmaps import PairwisePointmaps
from c4d_pipeline.procrustes import weighted_procrustes
from c4d_pipeline.scene_params import pixel_rays

log = logging.getLogger(__name__)


def estimate_focal(points: torch.Tensor, weights: torch.Tensor, principal: torch.Tensor,
                   irls_iters: int = 10) -> torch.Tensor:
    """Focal f (B,) of own-camera-frame pointmaps (B,H,W,3) with weights (B,H,W), pp (2,).

    Minimises sum w |(u,v) - pp - f (x/z, y/z)|, starting from the weighted least-squares solution
    and refining by iteratively reweighted least squares (Weiszfeld).
    """
    b, h, w_, _ = points.shape
    v, u = torch.meshgrid(torch.arange(h, dtype=points.dtype), torch.arange(w_, dtype=points.dtype),
                          indexing="ij")
    pix = torch.stack([u - principal[0], v - principal[1]], -1).reshape(1, -1, 2)  # (1,HW,2)
    z = points[..., 2:].reshape(b, -1, 1)
    valid = (z[..., 0] > 1e-6).to(points.dtype) * weights.reshape(b, -1)  # (B,HW)
    ray = points[..., :2].reshape(b, -1, 2) / z.clamp_min(1e-6)  # (B,HW,2)
    wts = valid
    focal = None
    for _ in range(irls_iters + 1):
        focal = (wts[..., None] * pix * ray).sum((1, 2)) / (wts[..., None] * ray * ray).sum((1, 2)).clamp_min(1e-12)
        residual = (pix - focal[:, None, None] * ray).norm(dim=-1)  # (B,HW)
        wts = valid / residual.clamp_min(1e-3)
    return focal


@dataclass
class Initialisation:
    """Initial values for `SceneParams` (float32 tensors)."""

    depth: torch.Tensor  # (T,H,W)
    cam_to_world: torch.Tensor  # (T,4,4)
    focal: torch.Tensor  # (T,) fx, pixels
    edge_scale: torch.Tensor  # (E,)
    edge_rotation: torch.Tensor  # (E,3,3)
    edge_translation: torch.Tensor  # (E,3)
    principal: torch.Tensor  # (T,2) cx, cy, pixels
    aspect: torch.Tensor  # (T,) fy / fx

    def focal_xy(self) -> torch.Tensor:
        return torch.stack([self.focal, self.focal * self.aspect], -1)  # (T,2) fx, fy


def spanning_tree_order(edges: np.ndarray, scores: np.ndarray, num_frames: int):
    """Maximum spanning tree of the frame graph; returns (seed pair, [(placed, new), ...] order)."""
    best: dict[tuple[int, int], float] = {}
    for (i, j), s in zip(edges.tolist(), scores.tolist()):
        key = (min(i, j), max(i, j))
        best[key] = max(best.get(key, -np.inf), s)
    keys = list(best)
    # scipy wants positive weights to minimise: strongest pair = smallest weight.
    top = max(best.values())
    weight = np.array([top - best[k] + 1.0 for k in keys])
    graph = coo_matrix((weight, ([k[0] for k in keys], [k[1] for k in keys])),
                       shape=(num_frames, num_frames)).tocsr()
    tree = minimum_spanning_tree(graph)
    tree = tree + tree.T
    seed = max(keys, key=lambda k: best[k])
    order, predecessors = breadth_first_order(tree, seed[0], directed=False)
    if len(order) != num_frames:
        raise UserError("the scene graph does not connect every frame; use a graph with offset 1")
    steps = [(int(predecessors[n]), int(n)) for n in order[1:] if int(n) != seed[1]]
    # the seed's partner is placed with the seed; every other frame follows its tree parent
    return seed, steps


def initialise(pw: PairwisePointmaps, num_frames: int, shared_focal: bool = False,
               chunk: int = 16, intrinsics: torch.Tensor | None = None) -> Initialisation:
    """Spanning-tree initialisation (module docstring). Needs every frame to be the first view of
    some edge (true for symmetric graphs). `intrinsics`: known (T,4) fx, fy, cx, cy in the
    pointmaps' pixels (None: the focal estimated, the principal point at the image centre)."""
    edges = pw.edges
    firsts = set(edges[:, 0].tolist())
    if len(firsts) != num_frames:
        missing = sorted(set(range(num_frames)) - firsts)
        raise UserError(f"frames {missing[:5]} are never the first view of a pair; use a symmetric "
                        "scene graph (graph.symmetric=true)")
    pts_i = torch.from_numpy(pw.pts_i)  # (E,H,W,3)
    pts_j = torch.from_numpy(pw.pts_j)
    w_i = torch.from_numpy(pw.conf_i).log()  # (E,H,W)
    w_j = torch.from_numpy(pw.conf_j).log()
    h, w = pw.image_size
    scores = pw.conf_i.reshape(len(edges), -1).mean(1) * pw.conf_j.reshape(len(edges), -1).mean(1)
    index = {(int(i), int(j)): e for e, (i, j) in enumerate(edges)}

    # 1-2. world points per frame, by walking the maximum spanning tree
    (a, b), steps = spanning_tree_order(edges, scores, num_frames)
    world: dict[int, torch.Tensor] = {}
    e = index.get((a, b), index.get((b, a)))
    first = int(edges[e, 0])
    world[first], world[a + b - first] = pts_i[e], pts_j[e]
    for placed, new in steps:
        if (placed, new) in index:
            e = index[(placed, new)]
            src, wt, target = pts_i[e], w_i[e], pts_j[e]
        else:
            e = index[(new, placed)]
            src, wt, target = pts_j[e], w_j[e], pts_i[e]
        s, r, t = weighted_procrustes(src.reshape(1, -1, 3), world[placed].reshape(1, -1, 3),
                                      wt.reshape(1, -1))
        world[new] = s[0] * target @ r[0].T + t[0]
    world_pts = torch.stack([world[n] for n in range(num_frames)])  # (T,H,W,3)

    # 3. per frame: own-frame pointmap from its most confident edge as first view
    own = torch.empty(num_frames, dtype=torch.long)
    for n in range(num_frames):
        cand = np.flatnonzero(edges[:, 0] == n)
        own[n] = int(cand[np.argmax(scores[cand])])
    cam_pts, cam_w = pts_i[own], w_i[own]  # (T,H,W,3), (T,H,W)
    if intrinsics is None:
        centre = torch.tensor([(w - 1) / 2, (h - 1) / 2])
        focal = estimate_focal(cam_pts.double(), cam_w.double(), centre.double()).float()  # (T,)
        if shared_focal:
            focal = focal.median().expand(num_frames).clone()
        principal, aspect = centre.expand(num_frames, 2).clone(), torch.ones(num_frames)
    else:
        known = intrinsics.float()
        focal, aspect, principal = known[:, 0], known[:, 1] / known[:, 0], known[:, 2:]
    s, r, t = weighted_procrustes(cam_pts.reshape(num_frames, -1, 3),
                                  world_pts.reshape(num_frames, -1, 3), cam_w.reshape(num_frames, -1))
    depth = (s[:, None, None] * cam_pts[..., 2]).clamp_min(1e-6)  # (T,H,W)
    floor = depth.median() * 1e-3
    depth = depth.clamp_min(floor)
    cam_to_world = torch.eye(4).repeat(num_frames, 1, 1)
    cam_to_world[:, :3, :3], cam_to_world[:, :3, 3] = r, t

    # 5. unit median depth
    norm = depth.median()
    depth, cam_to_world[:, :3, 3] = depth / norm, cam_to_world[:, :3, 3] / norm

    # 4. per-edge similarities onto the world points the initial parameters define
    rays = pixel_rays(h, w, torch.stack([focal, focal * aspect], -1), principal)  # (T,H,W,3)
    x_world = torch.einsum("tij,thwj->thwi", cam_to_world[:, :3, :3], rays * depth[..., None])
    x_world = x_world + cam_to_world[:, None, None, :3, 3]  # (T,H,W,3)
    fits = []
    for c in range(0, len(edges), chunk):  # chunks of edges bound the float64 temporaries
        sl = slice(c, c + chunk)
        ei, ej = torch.from_numpy(edges[sl, 0]), torch.from_numpy(edges[sl, 1])
        src = torch.cat([pts_i[sl], pts_j[sl]], dim=1).flatten(1, 2)  # (e,2HW,3)
        dst = torch.cat([x_world[ei], x_world[ej]], dim=1).flatten(1, 2)  # (e,2HW,3)
        wts = torch.cat([w_i[sl], w_j[sl]], dim=1).flatten(1)  # (e,2HW)
        fits.append(weighted_procrustes(src, dst, wts))
    es, er, et = (torch.cat(parts) for parts in zip(*fits))
    log.debug("initialised %d frames, median focal %.1f px", num_frames, float(focal.median()))
    return Initialisation(depth.float(), cam_to_world.float(), focal.float(), es.float(),
                          er.float(), et.float(), principal.float(), aspect.float())
