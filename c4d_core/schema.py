"""The settings schema: every key of every config group, with its type and valid range.

A group's schema has two halves that the loader (`c4d.config`) and `tests/test_schema.py` hold
together:
  - its root preset (`ROOTS`: configs/<group>/<root>.yaml) gives every key and its default, with
    a comment saying what it means; every other preset, `--config` file and `key=value` override
    may only set keys it has;
  - `RULES[group]` below gives every key's type and valid range, checked when a config is loaded,
    before any command creates a folder or writes a file. A wrong value is one `UserError` line
    naming the key, the value and the valid range. A rule `SECTION.*` covers every key of a
    section that code extends (`weights.*`: one per registered C4D objective).
The two list the same keys, a family rule standing for its section's keys (a test walks them). Code that keeps a section in a dataclass
takes the field names and defaults from the root preset (`section_defaults`), never its own.

To add a key: put it with its default and a comment into the root preset, and its rule here.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any, Callable, Mapping

from c4d_core.errors import UserError

# The preset of each group that holds every key with its default value.
ROOTS: dict[str, str] = {
    "datagen": "movi-e", "dynpt": "tiny-cpu", "c4d": "default", "demo": "default",
    "inspect": "default", "pointmaps": "tiny-cpu",
}

# The largest frame side anything here renders, crops or resizes to (pixels); the smallest.
MAX_SIDE, MIN_SIDE = 4096, 8
# The smallest frame side DynPT takes at its network resolution (training crop, model and eval
# resolution): its CNN's 1/16 features need more than one cell. The value of
# `dynpt.inference.MIN_SIDE`, written out because this floor module imports nothing of dynpt
# (tests/test_schema.py checks that the two agree).
TRACKER_MIN_SIDE = 17


@dataclass(frozen=True)
class Rule:
    """Type and range of one key.

    kind: 'int' | 'float' | 'bool' | 'str' | 'list' (of numbers, unless `item` says 'str');
    low/high: inclusive bounds of a number (of every number of a list); above: exclusive lower bound;
    shape: lengths of a list per nesting level (None = any length); ordered: a list's entries,
    or per coordinate the two rows of a (2, D) box, are non-decreasing;
    choices: the allowed values; nullable: null is allowed too (meaning given in the preset);
    zero: 0 is allowed too, besides the range (meaning given in the preset, e.g. 'all');
    pattern: a string must match this regular expression in full, `spelled` says so in words.
    """

    kind: str
    low: float | None = None
    high: float | None = None
    above: float | None = None
    shape: tuple = ()
    ordered: bool = False
    choices: tuple = ()
    nullable: bool = False
    zero: bool = False
    item: str = "float"
    pattern: str = ""
    spelled: str = ""

    def describe(self) -> str:
        """The valid values in words, e.g. 'an integer >= 2' or 'a list of 2 integers in [8, 4096]'."""
        number = {"int": "integer", "float": "number"}.get(self.kind if self.kind != "list" else self.item)
        if self.choices:
            text = "one of: " + ", ".join(str(c) for c in self.choices)
        elif self.pattern:
            text = self.spelled
        elif self.kind in ("bool", "str") or (self.kind == "list" and self.item == "str"):
            text = {"bool": "true or false", "str": "a string"}.get(self.kind, "a list of strings")
        else:
            text = number + ("s" if self.kind == "list" else "")
            bounds = []
            if self.low is not None and self.high is not None:
                bounds.append(f"in [{_num(self.low)}, {_num(self.high)}]")
            elif self.low is not None:
                bounds.append(f">= {_num(self.low)}")
            elif self.high is not None:
                bounds.append(f"<= {_num(self.high)}")
            if self.above is not None:
                bounds.append(f"> {_num(self.above)}")
            text = " ".join([text, *bounds])
            if self.kind == "list":
                if len(self.shape) > 1:
                    dims = "x".join("N" if n is None else str(n) for n in self.shape)
                    text = f"a {dims} list of {text}"
                else:
                    text = f"a list of {self.shape[0] if self.shape and self.shape[0] else ''} {text}"
                text = text.replace("  ", " ") + (", non-decreasing" if self.ordered else "")
            else:
                text = ("an " if text[0] in "aeiou" else "a ") + text
        return ("0 or " if self.zero else "") + text + (" (or null)" if self.nullable else "")

    def check(self, key: str, value: Any) -> None:
        """Raise `UserError` unless `value` is valid for `key`."""
        if value is None and self.nullable:
            return
        if not self.accepts(value):
            raise UserError(f"`{key}` = {_show(value)} is out of range: it must be {self.describe()}")

    def accepts(self, value: Any) -> bool:
        """Whether `value` (not null) is of the rule's type and in its range."""
        if self.choices:
            return value in self.choices and type(value) is type(self.choices[0])
        if self.kind == "list":
            if not isinstance(value, (list, tuple)):
                return False
            if self.item == "str":
                return all(isinstance(v, str) for v in value)
            return _shaped(value, self.shape) and all(self._number(v, self.item) for v in _flat(value)) \
                and (not self.ordered or _ordered(value))
        if self.pattern:
            return isinstance(value, str) and re.fullmatch(self.pattern, value) is not None
        if self.kind in ("int", "float"):
            return self._number(value, self.kind) or (self.zero and value == 0 and Rule(self.kind).accepts(value))
        return isinstance(value, {"bool": bool, "str": str}[self.kind])

    def _number(self, value: Any, kind: str) -> bool:
        if isinstance(value, bool) or not isinstance(value, int if kind == "int" else (int, float)):
            return False
        return not math.isnan(value) and (self.low is None or value >= self.low) \
            and (self.high is None or value <= self.high) and (self.above is None or value > self.above)


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else str(x)


def _show(value: Any) -> str:
    return "null" if value is None else str(value).replace("'", "").replace("True", "true").replace("False", "false")


def _flat(value) -> list:
    return [y for v in value for y in (_flat(v) if isinstance(v, (list, tuple)) else [v])]


def _shaped(value, shape: tuple) -> bool:
    if not shape:
        return all(not isinstance(v, (list, tuple)) for v in value)
    if not isinstance(value, (list, tuple)) or (shape[0] is not None and len(value) != shape[0]):
        return False
    return all(_shaped(v, shape[1:]) if len(shape) > 1 else not isinstance(v, (list, tuple)) for v in value)


def _ordered(value) -> bool:
    if value and isinstance(value[0], (list, tuple)):  # a (2, D) box: low corner <= high corner
        return all(a <= b for a, b in zip(value[0], value[1]))
    return all(a <= b for a, b in zip(value, value[1:]))


# --- short names for the rules -------------------------------------------------------------------
def integer(low: float | None = None, high: float | None = None, zero: bool = False) -> Rule:
    return Rule("int", low=low, high=high, zero=zero)


def number(low: float | None = None, high: float | None = None, above: float | None = None) -> Rule:
    return Rule("float", low=low, high=high, above=above)


def fraction() -> Rule:
    """A probability or share: a number in [0, 1]."""
    return number(0.0, 1.0)


def flag() -> Rule:
    return Rule("bool")


def text(*choices: str, nullable: bool = False) -> Rule:
    return Rule("str", choices=choices, nullable=nullable)


def device() -> Rule:
    """A torch device a command runs on: cpu, cuda or cuda:N (the names `torch.device` takes
    that this project runs on)."""
    return Rule("str", pattern=r"cpu|cuda(:[0-9]+)?", spelled="a torch device: cpu, cuda or cuda:N")


def texts() -> Rule:
    """A list of strings (paths, overrides, names)."""
    return Rule("list", item="str")


def size(nullable: bool = False, low: int = MIN_SIDE) -> Rule:
    """A frame size (H, W) in pixels that datagen renders and the tracker takes."""
    return Rule("list", shape=(2,), item="int", low=low, high=MAX_SIDE, nullable=nullable)


def tracker_size(nullable: bool = False) -> Rule:
    """A frame size (H, W) in pixels at DynPT's network resolution."""
    return size(nullable, low=TRACKER_MIN_SIDE)


def interval(low: float | None = None, high: float | None = None, above: float | None = None,
             item: str = "float") -> Rule:
    """A [min, max] pair, min <= max, from which a value is drawn."""
    return Rule("list", shape=(2,), ordered=True, low=low, high=high, above=above, item=item)


def numbers(*shape: int | None, low: float | None = None, above: float | None = None,
            high: float | None = None, item: str = "float") -> Rule:
    return Rule("list", shape=shape, low=low, high=high, above=above, item=item)


def box() -> Rule:
    """[[x0, y0, z0], [x1, y1, z1]] with x0 <= x1, y0 <= y1, z0 <= z1."""
    return Rule("list", shape=(2, 3), ordered=True)


SEED = integer(0, 2**32 - 1)
COUNT, POSITIVE = integer(1), integer(0)  # at least one; zero or more
PIXELS = number(0.0)
ONE_CYCLE_STEPS = integer(3)  # DynPT's OneCycle schedule: a warm-up of 2 steps and an annealing one
# An object's candidate poses are drawn at once, (tries, hull vertices, 3) float64: 1000 tries of
# pybullet_data's largest hull (3,632 vertices) take 87 MB (Kubric tries 100).
PLACEMENT_TRIES = integer(1, 1000)
# Sub-frame renders averaged into one uint8 frame: from 256 on, one render moves the mean by less
# than one level.
BLUR_SAMPLES = integer(1, 256)

# --- the rules of every group, key by key --------------------------------------------------------
RULES: dict[str, dict[str, Rule]] = {
    "datagen": {
        "preset": text(), "seed": SEED, "frames": integer(2), "fps": number(above=0),
        "resolution": size(), "split": text("train", "val", "test"),
        "assets_dir": text(nullable=True), "backgrounds_dir": text(nullable=True),
        "mobility_threshold": number(0.0),
        "assets.split_seed": SEED, "assets.heldout_fraction": fraction(),
        "assets.texture_size": integer(1, MAX_SIDE),
        "objects.num_static": interval(0, item="int"), "objects.num_tossed": interval(0, item="int"),
        "objects.scale": interval(above=0), "objects.static_region": box(),
        "objects.tossed_region": box(), "objects.tossed_velocity": box(),
        "objects.placement_tries": PLACEMENT_TRIES, "objects.density": number(above=0),
        "objects.friction": number(0.0), "objects.restitution": fraction(),
        "objects.settle_friction": number(0.0), "objects.settle_restitution": fraction(),
        "objects.uv_tiles": interval(above=0),
        "physics.step_rate": COUNT, "physics.gravity": number(), "physics.settle_frames": POSITIVE,
        "physics.settle_speed": number(0.0), "physics.settle_damping": fraction(),
        "physics.resettle_frames": POSITIVE, "physics.resettle_hold_frames": COUNT,
        "physics.damping": fraction(), "physics.floor_friction": number(0.0),
        "physics.floor_restitution": fraction(),
        "camera.focal_mm": number(above=0), "camera.sensor_mm": number(above=0),
        "camera.shell_radius": interval(above=0), "camera.min_height": number(),
        "camera.max_movement": number(0.0), "camera.moving_lookat": flag(),
        "camera.lookat_through_radius": number(0.0), "camera.lookat_start_radius": number(0.0),
        "camera.lookat_extend": number(0.0), "camera.znear": number(above=0),
        "camera.zfar": number(above=0),
        "lights.sun_elevation_deg": interval(0.0, 90.0), "lights.sun_intensity": interval(0.0),
        "lights.fill_intensity": interval(0.0), "lights.ambient": interval(0.0),
        "lights.shadows": flag(), "lights.shadow_map_size": integer(1, 4 * MAX_SIDE),
        "lights.shadow_extent": number(above=0),
        "backdrop.dome_radius": number(above=0), "backdrop.floor_tile": number(above=0),
        "blur.max_shutter": number(0.0), "blur.samples_per_frame": BLUR_SAMPLES,
        "blur.max_samples": BLUR_SAMPLES,
        "layers.normal": flag(), "layers.object_coordinates": flag(), "layers.instances": flag(),
        "layers.events": flag(),
        "tracks.num_points": COUNT, "tracks.query_stride": COUNT, "tracks.grid_stride": COUNT,
        "tracks.max_sampled_fraction": number(high=1.0, above=0), "tracks.depth_tolerance": number(0.0),
    },
    "dynpt": {
        "seed": SEED, "threads": POSITIVE,  # 0: automatic (c4d_core.system.configure_threads)
        "model.cnn_widths": numbers(4, low=1, item="int"), "model.feature_dim": COUNT,
        "model.corr_levels": COUNT, "model.corr_radius": POSITIVE, "model.corr_hidden_dim": COUNT,
        "model.corr_out_dim": COUNT, "model.hidden_dim": COUNT, "model.num_heads": COUNT,
        "model.depth": COUNT, "model.mlp_ratio": number(above=0), "model.num_virtual_tracks": COUNT,
        "model.fourier_freqs": POSITIVE, "model.displacement_scale": numbers(2, above=0),
        "model.window_len": integer(2), "model.window_stride": COUNT, "model.train_iters": COUNT,
        "model.eval_iters": COUNT, "model.resolution": tracker_size(nullable=True),
        "model.visibility_threshold": fraction(),
        "model.visibility_rule": text("vis_conf", "vis"),
        "model.windowing": text("causal", "cotracker3_online", "cotracker3_offline"),
        "model.time_embedding": text("hidden", "cotracker3"), "model.time_emb_len": integer(2),
        "model.sampling": text("centers", "cotracker3"), "model.init_from": text(),
        "model.encoder_3d.checkpoint": text(), "model.encoder_3d.require_checkpoint": flag(),
        "model.encoder_3d.random_init": flag(), "model.encoder_3d.layers": numbers(None, low=0, item="int"),
        "model.encoder_3d.patch_size": COUNT, "model.encoder_3d.embed_dim": COUNT,
        "model.encoder_3d.depth": COUNT, "model.encoder_3d.num_heads": COUNT,
        "model.encoder_3d.mlp_ratio": number(above=0), "model.encoder_3d.rope_freq": number(above=0),
        "data.sources": texts(), "data.weights": numbers(None, low=0.0), "data.num_frames": integer(2),
        # a crop larger than the shards' frames is valid (augment scales them up to cover it, as
        # tiny-cpu-2x does), so it is not checked against the data
        "data.max_stride": COUNT, "data.crop_size": tracker_size(), "data.num_tracks": COUNT,
        "data.random_query_fraction": fraction(), "data.moving_track_fraction": fraction(),
        "data.max_offscreen_px": PIXELS, "data.shuffle_buffer": COUNT, "data.num_workers": POSITIVE,
        "data.max_bad_fraction": fraction(), "data.foreign": text("refuse", "skip"),
        "data.mobility_rule": text("point", "object"),
        "data.augment.scale_range": interval(above=0), "data.augment.hflip_prob": fraction(),
        "data.augment.vflip_prob": fraction(), "data.augment.jitter_prob": fraction(),
        "data.augment.brightness": number(0.0), "data.augment.contrast": number(0.0),
        "data.augment.saturation": number(0.0), "data.augment.hue": number(0.0, 0.5),
        "data.augment.blur_prob": fraction(), "data.augment.blur_sigma": interval(above=0),
        "data.augment.eraser_prob": fraction(), "data.augment.eraser_max_boxes": POSITIVE,
        "data.augment.eraser_size_px": interval(1, item="int"),
        "train.out_dir": text(), "train.steps": ONE_CYCLE_STEPS, "train.stop_after": POSITIVE,
        "train.total_batch": COUNT, "train.batch_size": COUNT, "train.lr": number(above=0),
        "train.weight_decay": number(0.0), "train.adam_eps": number(above=0),
        "train.pct_start": number(high=1.0, above=0), "train.div_factor": number(above=0),
        "train.final_div_factor": number(above=0), "train.grad_clip": number(above=0),
        "train.bf16": flag(), "train.log_every": COUNT, "train.ckpt_every": COUNT,
        "train.keep_last": COUNT,
        "train.lr_scale.cnn": number(0.0), "train.lr_scale.correlation": number(0.0),
        "train.lr_scale.transformer": number(0.0), "train.lr_scale.mobility": number(0.0),
        "train.lr_scale.fusion": number(0.0),
        "loss.track_visible": number(0.0), "loss.track_occluded": number(0.0),
        "loss.huber_delta_px": number(above=0), "loss.gamma": number(high=1.0, above=0),
        "loss.visibility": number(0.0), "loss.confidence": number(0.0),
        "loss.conf_radius_px": number(above=0), "loss.mobility": number(0.0),
        "loss.mobility_pos_weight": number(above=0),
        "eval.source": text(), "eval.every": POSITIVE, "eval.num_scenes": POSITIVE,
        "eval.num_tracks": COUNT, "eval.resolution": tracker_size(), "eval.seed": SEED,
        "eval.query_mode": text("first", "strided"), "eval.best_metric": text(),
        "eval.protocol": text("scene", "c4d-paper"), "eval.mobility_rule": text("point", "object"),
        "eval.foreign": text("refuse", "skip"),
        "eval.mobility": text("head", "epipolar"), "eval.epipolar.offset": integer(1),
        "eval.epipolar.window": integer(0), "eval.epipolar.quantile": number(0, 100),
        "eval.epipolar.head_weight": number(0), "eval.epipolar.residual_sigmas": number(above=0),
        "eval.refine": text("none", "lk"), "eval.lk.window": integer(3),
        "eval.lk.levels": integer(0), "eval.lk.max_backward_px": number(above=0),
    },
    "c4d": {
        "seed": SEED, "device": device(), "threads": POSITIVE, "flow": text(),
        "video.stride": COUNT, "video.max_frames": integer(2, zero=True),  # 0: all; 1 frame: no pair
        "intrinsics.known": text(), "intrinsics.mode": text("fixed", "init"),
        "pointmaps.checkpoint": text(), "pointmaps.size": integer(0, MAX_SIDE),  # 0: the checkpoint's
        "pointmaps.batch": POSITIVE,
        "pointmaps.precision": text("fp32", "bf16"),
        "tracker.checkpoint": text(), "tracker.grid_size": COUNT,
        "graph.window": COUNT, "graph.stride": COUNT, "graph.start": COUNT, "graph.symmetric": flag(),
        "window.frames": POSITIVE, "window.overlap": COUNT, "window.anchor": flag(),
        "window.joint_iters": POSITIVE,
        "gt_pointmaps.depth_noise": number(0.0), "gt_pointmaps.smooth_noise": number(0.0),
        "gt_pointmaps.smooth_cells": COUNT, "gt_pointmaps.scale_range": number(1.0),
        "gt_pointmaps.conf_max": number(1.0), "gt_pointmaps.static_bias": flag(),
        "gt_pointmaps.bias_fit": text("similarity", "rigid"), "gt_pointmaps.seed": SEED,
        "optim.stage1_iters": POSITIVE, "optim.stage2_iters": POSITIVE, "optim.lr": number(above=0),
        "optim.lr_min": number(0.0), "optim.schedule": text("constant", "linear", "cosine"),
        "optim.betas": numbers(2, low=0.0, high=0.999999), "optim.shared_focal": flag(),
        "optim.world_scale": number(0.0), "optim.edge_chunk": POSITIVE,
        "optim.coarse_factor": COUNT, "optim.coarse_iters": POSITIVE,
        "weights.*": number(0.0),  # every C4D objective's weight (c4d_pipeline.objectives)
        "cma.reference_size": POSITIVE, "cma.max_px": number(above=0),
        "pts.window": COUNT, "pts.extend": POSITIVE, "pts.kernel": COUNT, "pts.lam": number(0.0),
        "pts.knn": COUNT,
        "motion_mask.c4d.mobility_threshold": fraction(), "motion_mask.c4d.min_confidence": fraction(),
        "motion_mask.c4d.sampson_threshold_px": PIXELS, "motion_mask.c4d.min_static_points": integer(8),
        "motion_mask.c4d.fallback_grid_points": integer(8), "motion_mask.c4d.still_camera_px": PIXELS,
        "motion_mask.c4d.seed": SEED, "motion_mask.c4d.max_pair_offset": POSITIVE,
        "motion_mask.c4d.noise_sigmas": number(0.0), "motion_mask.c4d.judge_out_of_view": flag(),
        "motion_mask.c4d.forward_backward_px": number(0.0),
        "motion_mask.c4d.open_px": integer(0), "motion_mask.c4d.close_px": integer(0),
        "motion_mask.c4d.temporal_neighbours": integer(0), "motion_mask.c4d.guided_radius_px": integer(0),
        "motion_mask.c4d.guided_eps": number(above=0), "motion_mask.c4d.min_vote": number(above=0, high=1),
        "motion_mask.flow_only_threshold": fraction(),
        "outputs.ply_pixel_stride": COUNT, "outputs.ply_static_frame_stride": COUNT,
        "outputs.ply_min_confidence": number(0.0),
    },
    "demo": {
        "seed": integer(0, 2**32 - 1001),  # the val sets use seed + 1000
        "data.presets": texts(), "data.train_scenes": COUNT, "data.val_scenes": COUNT,
        "data.resolution": size(), "data.frames": integer(2), "data.scenes_per_shard": COUNT,
        "data.workers": COUNT,
        "train.config": text(), "train.steps": ONE_CYCLE_STEPS, "train.processes": COUNT,
        "train.overrides": texts(),
        "eval.num_tracks": COUNT, "eval.overrides": texts(), "eval.paper_scenes": integer(0),
        "eval.paper_resolution": size(), "eval.paper_overrides": texts(),
        "recon.preset": text(), "recon.num_scenes": COUNT, "recon.resolution": size(),
        "recon.config": text(),
        "recon.flow": text(), "recon.overrides": texts(),
    },
    "inspect": {
        "samples": POSITIVE, "fps": number(above=0), "sheet_frames": COUNT, "min_panel_height": COUNT,
        "track_radius": number(above=0), "track_curves": POSITIVE,
        "check.rotation_tolerance": number(0.0), "check.mobility_threshold": number(0.0),
        "flythrough.static_points": POSITIVE, "flythrough.dynamic_points": POSITIVE,
        "flythrough.keep_confident": number(high=1.0, above=0), "flythrough.min_height": COUNT,
        "flythrough.views_per_frame": COUNT, "flythrough.min_views": COUNT,
        "flythrough.sweep_deg": number(0.0, 360.0), "flythrough.view_back": number(above=0),
        "flythrough.view_up": number(), "flythrough.focal": number(above=0),
        "flythrough.splat_radius": POSITIVE, "flythrough.seed": SEED,
    },
    "pointmaps": {
        "seed": SEED, "threads": POSITIVE, "data.sources": texts(), "data.max_scenes": POSITIVE,
        "data.max_gap": COUNT,
        "data.hflip_prob": fraction(),
        "model.patch_size": COUNT, "model.enc_embed_dim": COUNT, "model.enc_depth": COUNT,
        "model.enc_num_heads": COUNT, "model.dec_embed_dim": COUNT, "model.dec_depth": COUNT,
        "model.dec_num_heads": COUNT,
        "loss.alpha": number(0.0),
        "train.out_dir": text(), "train.steps": COUNT, "train.stop_after": POSITIVE,
        "train.batch_size": COUNT, "train.lr": number(above=0), "train.weight_decay": number(0.0),
        "train.warmup_fraction": fraction(), "train.grad_clip": number(above=0),
        "train.log_every": COUNT, "train.ckpt_every": COUNT,
    },
}


# --- rules between keys ----------------------------------------------------------------------
def _get(cfg: Mapping, key: str) -> Any:
    for part in key.split("."):
        cfg = cfg[part]
    return cfg


def _divides(cfg: Mapping, width: str, heads: str) -> str | None:
    if _get(cfg, width) % _get(cfg, heads):
        return f"`{width}` = {_get(cfg, width)} must be a multiple of `{heads}` = {_get(cfg, heads)}"
    return None


def _dynpt(cfg: Mapping) -> list[str | None]:
    weights, sources = _get(cfg, "data.weights"), _get(cfg, "data.sources")
    return [
        None if not weights or len(weights) == len(sources) else
        f"`data.weights` = {_show(list(weights))} must be [] or have one entry per `data.sources` "
        f"({len(sources)})",
        _divides(cfg, "model.hidden_dim", "model.num_heads"),
        _divides(cfg, "model.encoder_3d.embed_dim", "model.encoder_3d.num_heads"),
        None if _get(cfg, "model.window_stride") <= _get(cfg, "model.window_len") else
        f"`model.window_stride` = {_get(cfg, 'model.window_stride')} must be <= `model.window_len` "
        f"= {_get(cfg, 'model.window_len')}",
    ]


def _c4d(cfg: Mapping) -> list[str | None]:
    coarse, iters = _get(cfg, "optim.coarse_iters"), _get(cfg, "optim.stage1_iters")
    return [None if _get(cfg, "optim.lr_min") <= _get(cfg, "optim.lr") else
            f"`optim.lr_min` = {_get(cfg, 'optim.lr_min')} must be <= `optim.lr` = {_get(cfg, 'optim.lr')}",
            None if coarse == 0 or coarse < iters else
            f"`optim.coarse_iters` = {coarse} must be < `optim.stage1_iters` = {iters} (stage 1 ends at "
            "full size)",
            None if coarse == 0 or _get(cfg, "optim.coarse_factor") > 1 else
            f"`optim.coarse_iters` = {coarse} needs `optim.coarse_factor` >= 2 (1 is full size); "
            "set both, or coarse_iters=0"]


def _datagen(cfg: Mapping) -> list[str | None]:
    near, far = _get(cfg, "camera.znear"), _get(cfg, "camera.zfar")
    return [None if near < far else f"`camera.znear` = {near} must be < `camera.zfar` = {far}"]


def _demo(cfg: Mapping) -> list[str | None]:
    preset, presets = _get(cfg, "recon.preset"), list(_get(cfg, "data.presets"))
    scenes, val = _get(cfg, "recon.num_scenes"), _get(cfg, "data.val_scenes")
    return [None if preset in presets else
            f"`recon.preset` = {preset} must be one of `data.presets` ({', '.join(presets)})",
            None if scenes <= val else
            f"`recon.num_scenes` = {scenes} must be <= `data.val_scenes` = {val}"]


def _pointmaps(cfg: Mapping) -> list[str | None]:
    return [_divides(cfg, "model.enc_embed_dim", "model.enc_num_heads"),
            _divides(cfg, "model.dec_embed_dim", "model.dec_num_heads")]


CROSS_RULES: dict[str, Callable[[Mapping], list[str | None]]] = {
    "datagen": _datagen, "dynpt": _dynpt, "c4d": _c4d, "demo": _demo, "pointmaps": _pointmaps,
}


def leaf_keys(cfg: Mapping, prefix: str = "") -> dict[str, Any]:
    """Every leaf of a nested mapping by dotted key: {'camera.focal_mm': 35.0, ...}."""
    leaves: dict[str, Any] = {}
    for key, value in cfg.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            leaves.update(leaf_keys(value, name + "."))
        else:
            leaves[name] = value
    return leaves


def rule_for(group: str, key: str) -> Rule | None:
    """The rule of `key` in `group`: its own, else that of its family `SECTION.*` (the keys of a
    section that code extends, such as `weights.*`: a new entry there needs no rule of its own)."""
    rules = RULES[group]
    if key in rules:
        return rules[key]
    section = key.rpartition(".")[0]
    return rules.get(f"{section}.*") if section else None


def validate(group: str, cfg: Mapping) -> None:
    """Raise `UserError` (one line: key, value, valid range) unless every value of `cfg`, a plain
    nested dict of group `group`'s keys, is valid."""
    for key, value in leaf_keys(cfg).items():
        rule = rule_for(group, key)
        if rule is None:
            raise UserError(f"`{key}` has no rule in the {group} settings schema; add one to "
                            "c4d_core/schema.py RULES")
        rule.check(key, value)
    for problem in CROSS_RULES.get(group, lambda _: [])(cfg):
        if problem:
            raise UserError(problem)
