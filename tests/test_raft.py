"""RAFT: weight loading in both public layouts, correlation lookup and upsampling by hand."""

import re

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from c4d_core.errors import UserError
from c4d_pipeline.flow import build_flow
from c4d_pipeline.raft import RAFT, RaftFlow, correlation_pyramid, load_raft, lookup, upsample_flow


@pytest.fixture(scope="module")
def raft_file(tmp_path_factory):
    torch.manual_seed(0)
    model = RAFT(iters=3).eval()
    with torch.no_grad():
        for name, buf in model.named_buffers():  # non-trivial batch-norm statistics
            if name.endswith("running_var"):
                buf.uniform_(0.5, 2.0)
            elif name.endswith("running_mean"):
                buf.normal_(0, 0.1)
    path = tmp_path_factory.mktemp("raft") / "raft-things.pth"
    torch.save({f"module.{k}": v for k, v in model.state_dict().items()}, path)  # DataParallel names
    return model, path


def test_released_key_names():
    keys = set(RAFT().state_dict())
    for key in ("fnet.conv1.weight", "fnet.layer2.0.downsample.0.weight", "cnet.norm1.running_var",
                "cnet.layer3.0.norm3.weight", "cnet.layer3.0.downsample.1.weight",
                "update_block.encoder.convc1.weight", "update_block.encoder.convf2.bias",
                "update_block.gru.convq2.weight", "update_block.flow_head.conv2.weight",
                "update_block.mask.2.weight"):
        assert key in keys, key
    sd = RAFT().state_dict()
    assert sd["update_block.encoder.convc1.weight"].shape == (256, 324, 1, 1)
    assert sd["update_block.gru.convz1.weight"].shape == (128, 384, 1, 5)
    assert sd["update_block.mask.2.weight"].shape == (576, 256, 1, 1)


def to_torchvision(state):
    """Original names -> torchvision raft_large names (independent of the loader's table)."""
    out = {}
    for k, v in state.items():
        if ".norm3." in k:
            continue
        k = k.replace("fnet.", "feature_encoder.", 1).replace("cnet.", "context_encoder.", 1)
        k = re.sub(r"^(feature_encoder|context_encoder)\.conv1\.", r"\1.convnormrelu.0.", k)
        k = re.sub(r"^(feature_encoder|context_encoder)\.norm1\.", r"\1.convnormrelu.1.", k)
        k = re.sub(r"^(feature_encoder|context_encoder)\.conv2\.", r"\1.conv.", k)
        k = re.sub(r"(layer\d\.\d)\.conv(\d)\.", r"\1.convnormrelu\2.0.", k)
        k = re.sub(r"(layer\d\.\d)\.norm(\d)\.", r"\1.convnormrelu\2.1.", k)
        k = re.sub(r"update_block\.encoder\.convc(\d)\.", r"update_block.motion_encoder.convcorr\1.0.", k)
        k = re.sub(r"update_block\.encoder\.convf(\d)\.", r"update_block.motion_encoder.convflow\1.0.", k)
        k = k.replace("update_block.encoder.conv.", "update_block.motion_encoder.conv.0.")
        k = re.sub(r"update_block\.gru\.conv([zrq])(\d)\.", r"update_block.recurrent_block.convgru\2.conv\1.", k)
        k = k.replace("update_block.mask.0.", "mask_predictor.convrelu.0.").replace(
            "update_block.mask.2.", "mask_predictor.conv.")
        out[k] = v
    return out


def test_both_layouts_round_trip(raft_file, tmp_path):
    model, path = raft_file
    img1, img2 = torch.rand(2, 1, 3, 64, 72) * 2 - 1
    with torch.no_grad():
        expected = model(img1, img2)
        assert expected.shape == (1, 2, 64, 72)
        torch.testing.assert_close(load_raft(path, iters=3)(img1, img2), expected, atol=0, rtol=0)
        tv_path = tmp_path / "raft_large_torchvision.pth"
        torch.save(to_torchvision(model.state_dict()), tv_path)
        torch.testing.assert_close(load_raft(tv_path, iters=3)(img1, img2), expected, atol=0, rtol=0)


def test_lookup_samples_correlations_in_the_released_order():
    torch.manual_seed(1)
    f1, f2 = torch.randn(2, 1, 8, 16, 16)
    pyramid = correlation_pyramid(f1, f2)
    coords = torch.zeros(1, 2, 16, 16)
    coords[0, 0, 5, 6], coords[0, 1, 5, 6] = 7.0, 9.0  # pixel (x=6, y=5) looks around (x=7, y=9)
    window = lookup(pyramid, coords)[0, :81, 5, 6].view(9, 9)  # level 0
    for a, dx in enumerate(range(-4, 5)):
        for b, dy in enumerate(range(-4, 5)):
            x, y = 7 + dx, 9 + dy
            want = (f1[0, :, 5, 6] @ f2[0, :, y, x]) / 8 ** 0.5 if 0 <= x < 16 and 0 <= y < 16 else 0.0
            assert window[a, b].item() == pytest.approx(float(want), abs=1e-5)


def test_convex_upsampling_of_a_constant_flow():
    flow = torch.tensor([1.5, -2.0]).view(1, 2, 1, 1).expand(1, 2, 3, 4)
    up = upsample_flow(flow, torch.randn(1, 576, 3, 4))
    assert up.shape == (1, 2, 24, 32)
    # Interior pixels average 8x the same flow; borders mix in the zero padding.
    torch.testing.assert_close(up[0, :, 8:16, 8:24], torch.tensor([12.0, -16.0]).view(2, 1, 1).expand(2, 8, 16))


def test_flow_for_requested_pairs_with_padding(raft_file):
    model, path = raft_file
    raft = build_flow(f"raft:{path}", device="cpu")
    assert isinstance(raft, RaftFlow)
    raft.model.iters = 3
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (3, 62, 69, 3), dtype=np.uint8)  # not multiples of 8
    out = raft.flow(frames, [(0, 1), (2, 0)])
    assert out.shape == (2, 62, 69, 2) and out.dtype == np.float32
    imgs = torch.from_numpy(frames).permute(0, 3, 1, 2).float() / 127.5 - 1
    padded = F.pad(imgs, (1, 2, 1, 1), mode="replicate")  # 64 x 72, centred
    with torch.no_grad():
        direct = model(padded[2:3], padded[0:1])[0, :, 1:63, 1:70].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(out[1], direct, atol=1e-4)


def test_wrong_weights_give_a_user_error(tmp_path):
    path = tmp_path / "small.pth"
    torch.save({"fnet.conv1.weight": torch.zeros(32, 3, 7, 7)}, path)
    with pytest.raises(UserError, match="not a RAFT-large checkpoint"):
        load_raft(path)
    with pytest.raises(UserError, match="do not exist"):
        build_flow(f"raft:{tmp_path / 'missing.pth'}")
