"""Outputs of the networks users load from released files, against the official code's outputs.

The goldens in tests/fixtures/golden/ were made once, outside this repository, by running the
official code side by side with ours; no official code is needed to run these tests. How:

- Weights: each official model class was built in its release layout and its state dict's names,
  shapes and dtypes were taken in file order; `tests.golden.seeded_state` filled them from a seed
  (the rule is in tests/golden.py; tensors registered under two names get one value) and the
  official model was loaded with them. The golden file keeps the names, shapes and seed, so a test
  rebuilds the exact file the official code read, in its key layout, and loads it through the
  project's own loader.
- RAFT (raft_things.npz): princeton-vl/RAFT's `RAFT` (large; `small=False`, no mixed precision,
  no alternate correlation) wrapped in `DataParallel`, so every name has the `module.` prefix of
  raft-things.pth. Input: frames 0 and 2 of a 130x150 scene rendered by `c4d datagen` (preset
  movi-e-panning, seed 5), padded by the official `InputPadder` to 136x152; the official forward
  pass (20 iterations) gave the unpadded upsampled flow of iterations 1, 2, 5, 10 and 20.
- DUSt3R family (<name>.npz): tiny backbones (encoder 64 wide, 2 blocks, 4 heads; decoder 48 wide,
  3 heads, 12 blocks for DPT heads, which the official factory requires, else 2) with the released
  heads unchanged: naver/dust3r `AsymmetricCroCo3DStereo` with the 512 DPT head, with the 224
  linear head, and with the linear head and a model string that omits the head counts (encoder 48
  and decoder 64 wide, so CroCo's defaults of 12 and 16 heads apply); naver/mast3r
  `AsymmetricMASt3R` ('catmlp+dpt', desc24, two confidences); Junyi42/monst3r's
  `AsymmetricCroCo3DStereo` (freeze='encoder'). Each was saved as an official checkpoint
  ({'model', 'args': Namespace(model=<string>)}), read back with the official `load_model` and run
  with the official `load_images` (size 64: 64x48 landscape, 48x64 portrait) and `inference` on
  frames 0 and 2 of two rendered scenes (96x128 and 128x96, height x width; `c4d datagen`
  movi-e-panning, seeds 3 and 4). The golden keeps the preprocessed frames and pts3d / conf of
  both views (MASt3R's descriptors are not kept: this project does not use them).
- Preprocessing (preprocessing.npz): the official `load_images` at 512 and 224 on uniform-noise
  images (`tests.golden.noise_image`) of 16 sizes, among them exact .5 rounding ties at 224
  (402x384, 384x402, 192x393, width x height), and on the two rendered frames: the output size
  and the SHA-256 of its bytes.
"""

import argparse
import hashlib

import numpy as np
import pytest
import torch

from c4d_core.config import load_config
from c4d_core.errors import UserError
from c4d_pipeline.dust3r_pointmaps import Dust3rPointmaps
from c4d_pipeline.raft import RaftFlow
from c4d_pipeline.video_input import dust3r_resize
from tests.golden import golden, golden_state, noise_image

DUST3R_FAMILY = ["dust3r_dpt512", "dust3r_linear224", "dust3r_noheads", "mast3r_dpt512", "monst3r_dpt512"]


def test_raft_flow_equals_the_official_at_every_kept_iteration(tmp_path):
    data = golden("raft_things")
    state = golden_state(data)
    assert all(k.startswith("module.") for k in state)  # raft-things.pth's DataParallel names
    path = tmp_path / "raft-things.pth"
    torch.save({str(k): v for k, v in state.items()}, path)  # str names (not numpy's), as the release
    raft = RaftFlow(path, device="cpu")
    for iters, expected in zip(data["iters"], data["flow"]):
        raft.model.iters = int(iters)
        flow = raft.flow(data["frames"], [(0, 1)])[0]  # (H,W,2) px
        assert flow.shape == expected.shape
        err = np.abs(flow - expected).max()
        assert err < 5e-4, f"iteration {iters}: flow differs from the official by {err:.2e} px"
    assert np.abs(expected).max() > 10  # the random network moves pixels by tens of px


def write_official_checkpoint(data, path):
    args = argparse.Namespace(model=str(data["model"]))
    torch.save({"model": golden_state(data), "args": args, "epoch": 0}, path)


@pytest.mark.parametrize("name", DUST3R_FAMILY)
def test_pointmaps_equal_the_official_landscape_and_portrait(name, tmp_path):
    data = golden(name)
    path = tmp_path / f"{name}.pth"
    write_official_checkpoint(data, path)
    source = Dust3rPointmaps.from_checkpoint(path, device="cpu", batch_size=1)
    if name == "dust3r_noheads":
        assert (source.net.cfg.enc_num_heads, source.net.cfg.dec_num_heads) == (12, 16)
    for orient, hw in (("land", (48, 64)), ("port", (64, 48))):
        frames = data[f"{orient}_frames"]
        assert frames.shape == (2, *hw, 3)
        out = source.pointmaps(frames, np.array([[0, 1]]))
        for ours, theirs in (("pts_i", "pts1"), ("conf_i", "conf1"), ("pts_j", "pts2"), ("conf_j", "conf2")):
            expected = data[f"{orient}_{theirs}"]
            rel = np.abs(getattr(out, ours)[0] - expected).max() / np.abs(expected).max()
            assert rel < 1e-4, f"{name} {orient} {ours}: max error {rel:.1e} of the largest output"


def test_preprocessing_is_byte_identical_to_load_images():
    data = golden("preprocessing")
    for name, size, out_hw, sha in zip(data["name"], data["size"], data["out_hw"], data["sha256"]):
        if name.startswith("noise_"):
            h, w = (int(v) for v in name[len("noise_"):].split("x"))
            source = noise_image(h, w, seed=h * 10007 + w)
        else:
            source = data[name]
        frames, _ = dust3r_resize(source[None], int(size))
        assert frames.shape[1:3] == tuple(out_hw), f"{name} at {size}"
        assert hashlib.sha256(frames[0].tobytes()).hexdigest() == sha, f"{name} at {size}: pixels differ"


def test_pointmap_precision_defaults_to_fp32_and_bf16_is_explicit(tmp_path):
    assert load_config("c4d", "default").pointmaps.precision == "fp32"
    data = golden("dust3r_linear224")
    path = tmp_path / "linear224.pth"
    write_official_checkpoint(data, path)
    frames, pair = data["land_frames"], np.array([[0, 1]])
    fp32 = Dust3rPointmaps.from_checkpoint(path, "cpu").pointmaps(frames, pair)
    bf16 = Dust3rPointmaps.from_checkpoint(path, "cpu", precision="bf16").pointmaps(frames, pair)
    np.testing.assert_array_equal(bf16.pts_i, fp32.pts_i)  # bf16 autocast is for GPUs only
    with pytest.raises(UserError, match="pointmaps.precision"):
        Dust3rPointmaps.from_checkpoint(path, "cpu", precision="fp16")
