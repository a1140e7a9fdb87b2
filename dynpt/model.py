"""DynPT, the dynamic-aware point tracker: CoTracker3-style tracking plus a per-point mobility head.

Per frame, a CNN (and, when configured, DUSt3R's frozen 3D-aware ViT encoder, fused in) gives
L2-normalised stride-4 features. For each track, 4-D correlations between its query neighbourhood
and the neighbourhood of its current estimate in every frame, Fourier-encoded displacements and
the running visibility / confidence / mobility logits form one token per track and frame; a
transformer attending across time and across tracks refines positions and logits iteratively.

Videos longer than one window are processed in sliding windows (`window_len` frames, moved by
`window_stride`); each window starts from the previous window's predictions on the frames they
share. Tracking runs forward in time from each query frame (online, causal across windows):
`DynPTOutput.valid` is True from the query frame on. The `Tracker` in `dynpt.inference` adds
backward tracking for queries after the first frame by running the reversed video.

`windowing` picks how a video is cut into windows: "causal" (the above; the last window aligned
with the video's end), "cotracker3_online" (CoTracker3's online model: windows at multiples of
`window_stride`, the last one padded with the last frame) or "cotracker3_offline" (CoTracker3's
offline model: one window over the whole clip, every track predicted in every frame, `valid` all
True). With `time_embedding: cotracker3` and `sampling: cotracker3` as well, DynPT loaded from a
CoTracker3 file (`dynpt.cotracker3_weights`) reproduces CoTracker3's outputs.

All coordinates are (x, y) pixels of the input video, pixel centres at integers.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Mapping

import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf
from torch import nn

from c4d_core.errors import UserError
from dynpt.cnn_encoder import CNNEncoder
from dynpt.correlation import CorrelationEncoder, feature_pyramid
from dynpt.embeddings import fourier_dim, fourier_encode
from dynpt.update_transformer import UpdateTransformer

log = logging.getLogger(__name__)

# model keys added after the first checkpoints were written: their values there (old configs lack them)
COMPAT_DEFAULTS = {"time_embedding": "hidden", "time_emb_len": 16, "sampling": "centers",
                   "windowing": "causal", "init_from": "", "visibility_rule": "vis_conf"}
WINDOWINGS = ("causal", "cotracker3_online", "cotracker3_offline")


@dataclass
class DynPTOutput:
    """Predictions of one forward pass; every list has one entry per refinement iteration, the
    last being the final prediction. Shapes: coords (B,T,N,2) input pixels; vis_logits,
    conf_logits, moving_logits (B,T,N) logits (apply sigmoid for probabilities); valid (B,T,N)
    bool, True for frames at or after each track's query frame (the frames the model predicted).
    """

    coords: list[torch.Tensor]
    vis_logits: list[torch.Tensor]
    conf_logits: list[torch.Tensor]
    moving_logits: list[torch.Tensor]
    valid: torch.Tensor


class DynPT(nn.Module):
    """The tracker; build it with `build_model(model_cfg)`. `config` is the plain-dict model config
    (with the 3D encoder's sizes filled in), enough to rebuild the architecture."""

    def __init__(self, config: dict, encoder_3d: nn.Module | None = None):
        super().__init__()
        self.config = config
        c = config
        if c["windowing"] not in WINDOWINGS:
            raise UserError(f"model.windowing={c['windowing']!r}: choose one of {', '.join(WINDOWINGS)}")
        if c["sampling"] not in ("centers", "cotracker3"):
            raise UserError(f"model.sampling={c['sampling']!r}: choose centers or cotracker3")
        if c["time_embedding"] not in ("hidden", "cotracker3"):
            raise UserError(f"model.time_embedding={c['time_embedding']!r}: choose hidden or cotracker3")
        align = c["sampling"] == "cotracker3"
        self.stride = CNNEncoder.stride
        self.cnn = CNNEncoder(c["cnn_widths"], c["feature_dim"], align_corners=align)
        self.encoder_3d = encoder_3d
        self.encoder_layers = list(c["encoder_3d"]["layers"])
        if encoder_3d is not None:
            enc = c["encoder_3d"]
            encoder_3d.requires_grad_(False)
            encoder_3d.eval()
            # every requested block plus the final (normalised) output, projected to feature_dim
            self.vit_proj = nn.Linear(enc["embed_dim"] * (len(self.encoder_layers) + 1), c["feature_dim"])
            self.fuse = nn.Conv2d(2 * c["feature_dim"], c["feature_dim"], 1)
            self.patch_size = enc["patch_size"]
        self.corr = CorrelationEncoder(
            c["corr_levels"], c["corr_radius"], c["corr_hidden_dim"], c["corr_out_dim"], align_corners=align
        )
        input_dim = 3 + self.corr.out_dim + fourier_dim(4, c["fourier_freqs"])
        self.transformer = UpdateTransformer(
            input_dim, c["hidden_dim"], c["num_heads"], c["depth"], c["mlp_ratio"],
            c["num_virtual_tracks"], c["time_embedding"], c["time_emb_len"],
        )
        self.register_buffer(
            "displacement_scale", torch.tensor(c["displacement_scale"], dtype=torch.float32),
            persistent=False,
        )
        # padded sizes must suit the pyramid (and the ViT's patches)
        multiple = self.stride * 2 ** (c["corr_levels"] - 1)
        if encoder_3d is not None:
            multiple = math.lcm(multiple, self.patch_size)
        self.size_multiple = multiple

    def train(self, mode: bool = True) -> "DynPT":
        """Switch train/eval mode; the frozen 3D encoder always stays in eval mode."""
        super().train(mode)
        if self.encoder_3d is not None:
            self.encoder_3d.eval()
        return self

    def parameter_counts(self) -> dict[str, int]:
        """Parameters per part (the frozen 3D encoder reported separately)."""
        count = lambda m: sum(p.numel() for p in m.parameters())
        parts = {"cnn": count(self.cnn), "correlation_mlp": count(self.corr),
                 "transformer": count(self.transformer)}
        if self.encoder_3d is not None:
            parts["fusion"] = count(self.vit_proj) + count(self.fuse)
            parts["encoder_3d_frozen"] = count(self.encoder_3d)
        parts["trainable"] = sum(p.numel() for p in self.parameters() if p.requires_grad)
        return parts

    # -- features -----------------------------------------------------------------------------

    def encode_frames(self, frames: torch.Tensor) -> torch.Tensor:
        """frames (F,3,H,W) in [-1,1], H and W multiples of `size_multiple` -> L2-normalised
        features (F,C,H/4,W/4)."""
        fmap = self.cnn(frames)  # (F,C,h,w)
        if self.encoder_3d is not None:
            with torch.no_grad():
                tokens, _, blocks = self.encoder_3d(frames, return_layers=self.encoder_layers)
            feats = torch.cat([*blocks, tokens], dim=-1)  # (F,P,D*(k+1)), P row-major (y,x) patches
            feats = self.vit_proj(feats.to(fmap.dtype))  # (F,P,C)
            gh, gw = frames.shape[-2] // self.patch_size, frames.shape[-1] // self.patch_size
            grid = feats.transpose(1, 2).unflatten(-1, (gh, gw))  # (F,C,H/16,W/16)
            grid = F.interpolate(grid, size=fmap.shape[-2:], mode="bilinear", align_corners=False)
            fmap = self.fuse(torch.cat([fmap, grid], dim=1))  # (F,C,h,w)
        return fmap * fmap.square().sum(1, keepdim=True).clamp_min(1e-12).rsqrt()  # / max(norm, 1e-6)

    # -- tracking -----------------------------------------------------------------------------

    def window_len(self, T: int) -> int:
        """Frames per window for a T-frame video (the whole clip with `cotracker3_offline`)."""
        return T if self.config["windowing"] == "cotracker3_offline" else self.config["window_len"]

    def window_starts(self, T: int) -> list[int]:
        """First frames of the sliding windows for a T-frame video (T < window: one window).
        Frames past the video's end (padding) repeat its last frame."""
        S, step = self.window_len(T), self.config["window_stride"]
        if self.config["windowing"] == "cotracker3_online":  # CoTracker3's count, at least one
            return [k * step for k in range(max(1, (T - S + step - 1) // step + 1))]
        Tp = max(T, S)  # a video shorter than a window is padded with its last frame
        starts = list(range(0, Tp - S + 1, step))
        if starts[-1] + S < Tp:
            starts.append(Tp - S)  # last window aligned with the end of the video
        return starts

    def _tokens(self, coords: torch.Tensor, logits: torch.Tensor, corr: torch.Tensor) -> torch.Tensor:
        """coords (B,S,N,2) pixels, logits (B,S,N,3), corr (B,N,S,Dc) -> tokens (B,N,S,D_in)."""
        coords = coords.transpose(1, 2)  # (B,N,S,2)
        zero = torch.zeros_like(coords[:, :, :1])
        step = coords[:, :, 1:] - coords[:, :, :-1]
        fwd = torch.cat([step, zero], dim=2)  # P_{t+1} - P_t
        bwd = torch.cat([zero, step], dim=2)  # P_t - P_{t-1}
        disp = torch.cat([fwd, bwd], dim=-1) / self.displacement_scale.repeat(2)  # (B,N,S,4)
        return torch.cat([logits.transpose(1, 2), corr, fourier_encode(disp, self.config["fourier_freqs"])],
                         dim=-1)  # (B,N,S,D_in)

    def _refine(self, pyramid, query_feats, coords, logits, iters):
        """Iterative updates in one window; returns per-iteration [(coords, logits)]."""
        history = []
        targets = self.corr.target_maps(pyramid)
        for _ in range(iters):
            coords = coords.detach()  # gradients flow through each iteration's update only
            corr = self.corr(targets, query_feats, coords, self.stride)  # (B,N,S,Dc)
            delta_xy, delta_logits = self.transformer(self._tokens(coords, logits, corr))
            coords = coords + self.stride * delta_xy.transpose(1, 2)  # (B,S,N,2), stride-4 units
            logits = logits + delta_logits.transpose(1, 2)  # (B,S,N,3)
            history.append((coords, logits))
        return history

    @staticmethod
    def _initial_state(xy_q, t_q, S: int, start: int, prev: dict | None):
        """Starting coords (B,S,N,2) and logits (B,S,N,3) of the window beginning at `start`.

        Tracks not yet running start at their query point with zero logits. Tracks the previous
        window already covered (query frame before its end) continue from its final prediction
        on the shared frames; the last shared value is repeated over the new frames.
        """
        B, N = t_q.shape
        coords = xy_q[:, None].expand(B, S, N, 2).clone()
        logits = coords.new_zeros(B, S, N, 3)  # vis, conf, moving
        if prev is None:
            return coords, logits
        started = (t_q < prev["end"])[:, None, :, None]  # (B,1,N,1)
        shared = prev["end"] - start
        carried = []
        for x in (prev["coords"], prev["logits"]):
            x = x[:, S - shared:]  # (B,shared,N,D)
            carried.append(torch.cat([x, x[:, -1:].expand(-1, S - shared, -1, -1)], dim=1))  # (B,S,N,D)
        return torch.where(started, carried[0], coords), torch.where(started, carried[1], logits)

    def forward(self, video: torch.Tensor, queries: torch.Tensor, iters: int | None = None) -> DynPTOutput:
        """Track `queries` through `video`.

        video: (B,T,3,H,W), values 0..255 (float, or uint8 to save memory on long videos), any
            H, W (padded internally, bottom/right); frames are converted one window at a time.
        queries: float (B,N,3) as (t, x, y): frame index and input pixels.
        iters: refinement iterations per window; default `train_iters` in training mode,
            `eval_iters` in eval mode.
        Videos longer than `window_len` run in sliding windows; shorter ones are padded with
        their last frame to one window (`windowing`: see the module doc).
        """
        c = self.config
        B, T, _, H, W = video.shape
        N = queries.shape[1]
        iters = iters or (c["train_iters"] if self.training else c["eval_iters"])
        S = self.window_len(T)
        t_q = queries[..., 0].round().long()  # (B,N)
        xy_q = queries[..., 1:].float()  # (B,N,2)
        if T < 2 or N < 1 or t_q.min() < 0 or t_q.max() >= T:
            raise ValueError(f"need T >= 2, N >= 1 and query frames in [0, {T - 1}]")

        ph, pw = -H % self.size_multiple, -W % self.size_multiple
        starts = self.window_starts(T)

        def load_frames(first: int, last: int) -> torch.Tensor:
            """Frames [first, last) in [-1,1], padded: (B*(last-first),3,H+ph,W+pw)."""
            idx = torch.arange(first, last, device=video.device).clamp(max=T - 1)
            frames = 2 * (video[:, idx].flatten(0, 1).float() / 255.0) - 1
            return F.pad(frames, (0, pw, 0, ph), mode="replicate")

        levels = c["corr_levels"]
        query_feats = None  # per level (B,N,P,C); zero until the track's query frame is reached
        sampled = torch.zeros(B, N, dtype=torch.bool, device=video.device)
        fmaps, fmaps_start, prev, pieces = None, 0, None, []
        for k, start in enumerate(starts):
            end = start + S
            # this window owns its frames up to the next window's start (later windows overwrite)
            own = (starts[k + 1] if k + 1 < len(starts) else end) - start
            arriving = ~sampled & (t_q >= start) & (t_q < end)  # (B,N)
            if not (sampled | arriving).any():  # no track runs yet: nothing to compute
                init_xy = xy_q[:, None].expand(B, own, N, 2)
                pieces.append([(init_xy, init_xy.new_zeros(B, own, N, 3))] * iters)
                continue
            # features: reuse the frames shared with the previous computed window, encode the rest
            keep = 0 if fmaps is None else max(0, fmaps_start + S - start)
            new = self.encode_frames(load_frames(start + keep, end))
            new = new.unflatten(0, (B, end - start - keep))  # (B,S-keep,C,h,w)
            fmaps = new if keep == 0 else torch.cat([fmaps[:, S - keep:], new], dim=1)  # (B,S,C,h,w)
            fmaps_start = start
            pyramid = feature_pyramid(fmaps, levels)

            if arriving.any():
                local_t = (t_q - start).clamp(0, S - 1)
                feats = self.corr.query_features(pyramid, local_t, xy_q, self.stride)
                mask = arriving[:, :, None, None]
                query_feats = (
                    [f * mask for f in feats] if query_feats is None
                    else [torch.where(mask, f, q) for f, q in zip(feats, query_feats)]
                )
                sampled = sampled | arriving

            coords, logits = self._initial_state(xy_q, t_q, S, start, prev)
            history = self._refine(pyramid, query_feats, coords, logits, iters)
            pieces.append([(xy[:, :own], lg[:, :own]) for xy, lg in history])
            xy_last, lg_last = history[-1]
            prev = {"end": end, "coords": xy_last.detach(), "logits": lg_last.detach()}

        per_iter = [
            (torch.cat([p[i][0] for p in pieces], 1)[:, :T], torch.cat([p[i][1] for p in pieces], 1)[:, :T])
            for i in range(iters)
        ]
        valid = torch.arange(T, device=video.device)[None, :, None] >= t_q[:, None, :]  # (B,T,N)
        if c["windowing"] == "cotracker3_offline":  # one pass over the clip predicts every frame
            valid = torch.ones_like(valid)
        return DynPTOutput(
            coords=[xy for xy, _ in per_iter],
            vis_logits=[lg[..., 0] for _, lg in per_iter],
            conf_logits=[lg[..., 1] for _, lg in per_iter],
            moving_logits=[lg[..., 2] for _, lg in per_iter],
            valid=valid,
        )


def plain_config(model_cfg: Mapping) -> dict:
    """A mutable plain-dict copy of a `model:` config section (dict or DictConfig), the keys of
    `COMPAT_DEFAULTS` filled in where missing (configs written before they existed)."""
    if isinstance(model_cfg, DictConfig):
        cfg = OmegaConf.to_container(model_cfg, resolve=True)
    else:
        cfg = OmegaConf.to_container(OmegaConf.create(dict(model_cfg)), resolve=True)
    return {**COMPAT_DEFAULTS, **cfg}


def build_model(model_cfg: Mapping, *, weights_from_state_dict: bool = False) -> DynPT:
    """Build DynPT from the `model:` section of a config (plain dict or DictConfig).

    The 3D-aware encoder is built only when `encoder_3d.checkpoint` names an official DUSt3R /
    MASt3R / MonST3R checkpoint file (its sizes are read from the weights and recorded in the
    model's config), or when `encoder_3d.random_init` is true (tests and benchmarks only: a frozen
    random ViT is useless for tracking). Otherwise the model is CNN-only (the paper's "CE only").
    `weights_from_state_dict=True` builds the encoder from the recorded sizes without reading the
    file, for callers that load a full state dict right after (`dynpt.checkpoint`).
    """
    cfg = plain_config(model_cfg)
    enc = cfg["encoder_3d"]
    encoder = None
    if enc.get("checkpoint") and enc.get("random_init"):
        raise UserError("model.encoder_3d: set either `checkpoint` or `random_init`, not both")
    if enc.get("require_checkpoint") and not enc.get("checkpoint"):
        raise UserError("this DynPT preset needs DUSt3R's encoder weights: add "
                        "model.encoder_3d.checkpoint=/path/to/DUSt3R_or_MASt3R_or_MonST3R.pth, "
                        "or train without it: --config paper-gpu-cnn-only")
    if enc.get("checkpoint") or enc.get("random_init"):
        from dynpt.dust3r.vit_encoder import Dust3rEncoder, load_dust3r_encoder

        sizes = ("patch_size", "embed_dim", "depth", "num_heads", "mlp_ratio", "rope_freq")
        if enc.get("checkpoint") and not weights_from_state_dict:
            encoder = load_dust3r_encoder(enc["checkpoint"])
            block = encoder.enc_blocks[0]
            enc.update(patch_size=encoder.patch_size, embed_dim=encoder.embed_dim,
                       depth=len(encoder.enc_blocks), num_heads=block.attn.num_heads,
                       mlp_ratio=block.mlp.fc1.out_features / encoder.embed_dim,
                       rope_freq=float(encoder.rope.base))
        else:
            if enc.get("random_init") and not weights_from_state_dict:
                log.warning("DynPT: 3D encoder with RANDOM frozen weights (model.encoder_3d.random_init); "
                            "for tests and benchmarks only")
            encoder = Dust3rEncoder(**{k: enc[k] for k in sizes})
        bad = [i for i in enc["layers"] if not 0 <= i < enc["depth"]]
        if bad:
            raise UserError(f"model.encoder_3d.layers {bad} outside the encoder's {enc['depth']} blocks; "
                            f"choose block indices in [0, {enc['depth'] - 1}]")
    return DynPT(cfg, encoder)
