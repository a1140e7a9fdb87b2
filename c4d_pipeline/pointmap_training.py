"""Training a DUSt3R-shaped pointmap network on generated scenes' exact pointmaps.

No DUSt3R weights can be downloaded here, yet DynPT's full design needs a frozen 3D-aware ViT
encoder taken from a DUSt3R-family network (paper sec. 3.2.1, "CE + 3E"). This module trains a
small `Dust3rNet` the way DUSt3R is trained, on pairs of frames of datagen shards whose pointmaps
are known exactly (depth, intrinsics, camera poses), and saves it in the official checkpoint
layout, so that `model.encoder_3d.checkpoint=...` (DynPT) and `pointmaps.checkpoint=...` (C4D)
load it exactly as they load a released file.

Pair (i, j) of one scene, frames at most `data.max_gap` apart, either order:
  target 1: view i's pixels with their true depth, in camera i's frame      (H,W,3) scene units
  target 2: view j's pixels at time j, moved into camera i's frame by the true relative pose
Loss (DUSt3R's confidence-aware regression): both the prediction and the target are divided by
their own mean distance to the origin over the pair's pixels; per pixel
  l = || pred / s_pred - gt / s_gt ||,   loss = mean(conf * l - alpha * log(conf)).

Files in `train.out_dir`: `config.yaml`, `last.pt` (training state, for --resume),
`log.jsonl` (one line per logged step) and `pointmap_net.pth`, the official-layout file:
`{'model': state_dict, 'args': Namespace(model="AsymmetricCroCo3DStereo(...)")}`. A run repairs
what a crash leaves, as `c4d train` does: temporaries of a killed write are deleted, log lines
past the checkpoint it starts from (and a torn last line) dropped; a damaged `last.pt` is a
one-line error.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from c4d_core.config import to_dict
from c4d_core.errors import UserError
from c4d_core.files import append_line, write_text
from c4d_pipeline.ground_truth import GroundTruthPointmaps
from datagen.shards import read_scenes
from dynpt.torch_files import read_tensor_file, save_atomic
from dynpt.dust3r.net import Dust3rConfig, Dust3rNet
from dynpt.train import remove_temporaries, repair_log

log = logging.getLogger(__name__)

PAIR_FIELDS = ("rgb", "depth", "intrinsics", "cam_to_world")


# --- data ---------------------------------------------------------------------------------------


def load_scenes(sources: list[str], max_scenes: int) -> list:
    """The scenes of every source (at most `max_scenes` per source; 0: all), with the fields a
    pair needs. Raises UserError when a source has no depth."""
    scenes = []
    for source in sources:
        for index, scene in enumerate(read_scenes(source, fields=PAIR_FIELDS)):
            if max_scenes and index >= max_scenes:
                break
            if scene.depth is None:
                raise UserError(f"{source!r} has no depth; pointmap training needs scenes generated "
                                "with depth (every datagen preset renders it)")
            scenes.append(scene)
    if not scenes:
        raise UserError(f"no scenes in {sources!r}; pass shard directories made by `c4d datagen`")
    return scenes


def exact_pair(scene, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
    """Pointmaps (H,W,3) float32 of views i and j, both in camera i's frame, without noise."""
    source = GroundTruthPointmaps(scene, depth_noise=0.0, smooth_noise=0.0, scale_range=1.0,
                                  static_bias=False)
    pair = source.pointmaps(scene.rgb, np.array([[i, j]]))
    return pair.pts_i[0], pair.pts_j[0]


def sample_batch(scenes: list, rng: np.random.Generator, batch: int, max_gap: int,
                 hflip_prob: float) -> dict[str, torch.Tensor]:
    """`batch` random pairs: img1, img2 (B,3,H,W) in [-1,1]; pts1, pts2 (B,H,W,3) in camera 1.

    A horizontal flip mirrors both images and negates x of both pointmaps (a mirrored world).
    """
    out = {k: [] for k in ("img1", "img2", "pts1", "pts2")}
    for _ in range(batch):
        scene = scenes[rng.integers(len(scenes))]
        T = scene.num_frames
        i = int(rng.integers(T))
        j = int(np.clip(i + rng.integers(-max_gap, max_gap + 1), 0, T - 1))
        pts1, pts2 = exact_pair(scene, i, j)
        img1, img2 = scene.rgb[i], scene.rgb[j]
        if rng.random() < hflip_prob:
            img1, img2 = img1[:, ::-1], img2[:, ::-1]
            pts1, pts2 = pts1[:, ::-1] * [-1, 1, 1], pts2[:, ::-1] * [-1, 1, 1]
        out["img1"].append(img1)
        out["img2"].append(img2)
        out["pts1"].append(pts1)
        out["pts2"].append(pts2)
    images = {k: torch.from_numpy(np.stack(out[k]).astype(np.float32)).permute(0, 3, 1, 2) / 127.5 - 1.0
              for k in ("img1", "img2")}  # (B,3,H,W)
    points = {k: torch.from_numpy(np.stack(out[k]).astype(np.float32)) for k in ("pts1", "pts2")}
    return images | points


# --- loss ---------------------------------------------------------------------------------------


def normalise_pair(pts1: torch.Tensor, pts2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Divide both pointmaps (B,H,W,3) by the pair's mean distance to the origin (per sample)."""
    dist = torch.cat([pts1.norm(dim=-1).flatten(1), pts2.norm(dim=-1).flatten(1)], 1)  # (B,2HW)
    scale = dist.mean(1).clamp_min(1e-8)[:, None, None, None]  # (B,1,1,1)
    return pts1 / scale, pts2 / scale


def confidence_regression_loss(pred1, conf1, pred2, conf2, gt1, gt2, alpha: float
                               ) -> tuple[torch.Tensor, dict[str, float]]:
    """DUSt3R's loss for one batch of pairs: pred/gt (B,H,W,3), conf (B,H,W) >= 1.

    Returns the scalar loss and {'regression': mean l, 'loss': ...} for logging.
    """
    p1, p2 = normalise_pair(pred1, pred2)
    g1, g2 = normalise_pair(gt1, gt2)
    l1, l2 = (p1 - g1).norm(dim=-1), (p2 - g2).norm(dim=-1)  # (B,H,W)
    loss = torch.cat([(conf1 * l1 - alpha * conf1.log()).flatten(),
                      (conf2 * l2 - alpha * conf2.log()).flatten()]).mean()
    return loss, {"loss": loss.item(), "regression": torch.cat([l1, l2]).mean().item()}


# --- the official file --------------------------------------------------------------------------


def constructor_string(cfg: Dust3rConfig, image_size: tuple[int, int]) -> str:
    """`args.model` of an official file describing `cfg` (parsed back by dynpt.dust3r.checkpoint)."""
    return (f"AsymmetricCroCo3DStereo(pos_embed='RoPE{cfg.rope_freq:g}', img_size={tuple(image_size)}, "
            f"head_type='{cfg.head_type}', output_mode='pts3d', depth_mode=('exp', -inf, inf), "
            f"conf_mode=('exp', 1, inf), enc_embed_dim={cfg.enc_embed_dim}, enc_depth={cfg.enc_depth}, "
            f"enc_num_heads={cfg.enc_num_heads}, dec_embed_dim={cfg.dec_embed_dim}, "
            f"dec_depth={cfg.dec_depth}, dec_num_heads={cfg.dec_num_heads}, patch_size={cfg.patch_size})")


def save_official(net: Dust3rNet, image_size: tuple[int, int], path: Path) -> Path:
    """Write `net` as an official DUSt3R-layout checkpoint (temporary name, then rename)."""
    args = argparse.Namespace(model=constructor_string(net.cfg, image_size))
    return save_atomic(path, {"model": net.state_dict(), "args": args})


# --- training -----------------------------------------------------------------------------------


def network_config(model_cfg) -> Dust3rConfig:
    """Dust3rConfig from the `model` section (linear head: any patch size)."""
    keys = ("enc_embed_dim", "enc_depth", "enc_num_heads", "dec_embed_dim", "dec_depth",
            "dec_num_heads", "patch_size")
    return Dust3rConfig(head_type="linear", **{k: int(model_cfg[k]) for k in keys})


def train_pointmap_net(cfg, resume: bool = False) -> dict:
    """Train per `cfg` (configs/pointmaps/*.yaml); returns {'checkpoint' (None when stopped early
    by train.stop_after), 'steps'}."""
    if not cfg.data.sources:
        raise UserError("data.sources is empty; pass the shards to learn from, e.g. "
                        "\"data.sources=[shards/movi-e]\"")
    out = Path(cfg.train.out_dir)
    state_path = out / "last.pt"
    if state_path.exists() and not resume:
        raise UserError(f"{out} already holds a pointmap training run; pass --resume to continue "
                        "it or choose another train.out_dir")
    write_text(out / "config.yaml", OmegaConf.to_yaml(cfg))
    torch.manual_seed(int(cfg.seed))
    scenes = load_scenes(list(cfg.data.sources), int(cfg.data.max_scenes))
    image_size = scenes[0].image_size
    if any(s.image_size != image_size for s in scenes):
        raise UserError("pointmap training needs scenes of one size; generate them at one resolution")
    net_cfg = network_config(cfg.model)
    if image_size[0] % net_cfg.patch_size or image_size[1] % net_cfg.patch_size:
        raise UserError(f"frames of {image_size[0]}x{image_size[1]} are not a multiple of "
                        f"model.patch_size={net_cfg.patch_size}; pick a patch size that divides both")
    net = Dust3rNet(net_cfg)
    steps = int(cfg.train.steps)
    optimizer = torch.optim.AdamW(net.parameters(), lr=float(cfg.train.lr),
                                  weight_decay=float(cfg.train.weight_decay), betas=(0.9, 0.95))
    warmup = max(1, int(steps * float(cfg.train.warmup_fraction)))
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: min(1.0, (s + 1) / warmup)
                                                 * 0.5 * (1 + math.cos(math.pi * min(s, steps) / steps)))
    step, rng = 0, np.random.default_rng(int(cfg.seed))
    remove_temporaries(out)
    if resume and state_path.exists():
        state = read_tensor_file(state_path, "pointmap training", "run without --resume",
                                 "it cannot be resumed: delete it, then run the same command "
                                 "without --resume to start over")
        net.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        schedule.load_state_dict(state["schedule"])
        step, rng.bit_generator.state = state["step"], state["rng"]
        log.info("resumed pointmap training at step %d", step)
    repair_log(out / "log.jsonl", step)  # lines past the checkpoint, a torn last line
    net.train()
    started, recent = time.time(), []
    stop = min(steps, step + int(cfg.train.stop_after)) if int(cfg.train.stop_after) > 0 else steps
    while step < stop:
        batch = sample_batch(scenes, rng, int(cfg.train.batch_size), int(cfg.data.max_gap),
                             float(cfg.data.hflip_prob))
        pred1, conf1, pred2, conf2 = net(batch["img1"], batch["img2"])
        loss, stats = confidence_regression_loss(pred1, conf1, pred2, conf2, batch["pts1"],
                                                 batch["pts2"], float(cfg.loss.alpha))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), float(cfg.train.grad_clip))
        optimizer.step()
        schedule.step()
        step += 1
        recent.append(stats["regression"])
        if step % int(cfg.train.log_every) == 0 or step == stop:
            line = {"step": step, **stats, "lr": schedule.get_last_lr()[0],
                    "seconds": round(time.time() - started, 1)}
            append_line(out / "log.jsonl", json.dumps(line))
            log.info("pointmaps step %d/%d  loss %.4f  regression %.4f (this step, as in log.jsonl; "
                     "mean of the last %d steps %.4f)", step, steps, stats["loss"],
                     stats["regression"], len(recent), float(np.mean(recent)))
            recent = []
        if step % int(cfg.train.ckpt_every) == 0 or step == stop:
            state = {"model": net.state_dict(), "optimizer": optimizer.state_dict(),
                     "schedule": schedule.state_dict(), "step": step,
                     "rng": rng.bit_generator.state, "config": to_dict(cfg)}
            save_atomic(state_path, state)
    if step < steps:
        log.info("stopped at step %d of %d; continue with --resume", step, steps)
        return {"checkpoint": None, "steps": step}
    path = save_official(net.eval(), image_size, out / "pointmap_net.pth")
    log.info("pointmap network written to %s", path)
    return {"checkpoint": str(path), "steps": step}
