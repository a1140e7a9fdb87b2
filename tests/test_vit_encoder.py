"""DUSt3R ViT encoder: official key layout, 2-D RoPE, checkpoint reading without code execution."""

import argparse
import datetime
import math

import pytest
import torch

from c4d_core.errors import UserError
from dynpt.dust3r.checkpoint import parse_constructor, read_checkpoint
from dynpt.dust3r.vit_encoder import Dust3rEncoder, RoPE2D, load_dust3r_encoder, patch_positions

OFFICIAL_ARGS = ("AsymmetricCroCo3DStereo(pos_embed='RoPE100', patch_embed_cls='ManyAR_PatchEmbed', "
                 "img_size=(512, 512), head_type='dpt', output_mode='pts3d', "
                 "depth_mode=('exp', -inf, inf), conf_mode=('exp', 1, inf), enc_embed_dim={D}, "
                 "enc_depth={L}, enc_num_heads={H}, dec_embed_dim=768, dec_depth=12, dec_num_heads=12)")


def tiny_encoder(seed=0):
    torch.manual_seed(seed)
    return Dust3rEncoder(patch_size=4, embed_dim=32, depth=3, num_heads=2).eval()


def test_official_key_names_for_vit_large():
    names = set(Dust3rEncoder().state_dict().keys())
    per_block = {"norm1.weight", "norm1.bias", "attn.qkv.weight", "attn.qkv.bias", "attn.proj.weight",
                 "attn.proj.bias", "norm2.weight", "norm2.bias", "mlp.fc1.weight", "mlp.fc1.bias",
                 "mlp.fc2.weight", "mlp.fc2.bias"}
    expected = {f"enc_blocks.{i}.{k}" for i in range(24) for k in per_block}
    expected |= {"patch_embed.proj.weight", "patch_embed.proj.bias", "enc_norm.weight", "enc_norm.bias"}
    assert names == expected
    shapes = Dust3rEncoder(depth=1).state_dict()
    assert shapes["patch_embed.proj.weight"].shape == (1024, 3, 16, 16)
    assert shapes["enc_blocks.0.attn.qkv.weight"].shape == (3072, 1024)
    assert shapes["enc_blocks.0.mlp.fc1.weight"].shape == (4096, 1024)


def test_rope_matches_explicit_pairwise_rotation():
    """Channel pair (c, c+D/2) of the y half turns by y*100^(-2c/D); likewise x in the x half."""
    torch.manual_seed(0)
    B, heads, N, head_dim = 1, 2, 6, 8
    tokens = torch.randn(B, heads, N, head_dim)
    pos = torch.randint(0, 5, (B, N, 2))
    out = RoPE2D(100.0)(tokens, pos)
    half = head_dim // 2
    for n in range(N):
        for part, p in ((0, pos[0, n, 0]), (1, pos[0, n, 1])):
            chunk = tokens[0, :, n, part * half:(part + 1) * half]
            got = out[0, :, n, part * half:(part + 1) * half]
            for c in range(half // 2):
                angle = float(p) * 100.0 ** (-2 * c / half)
                a, b = chunk[:, c], chunk[:, c + half // 2]
                torch.testing.assert_close(got[:, c], a * math.cos(angle) - b * math.sin(angle))
                torch.testing.assert_close(got[:, c + half // 2], b * math.cos(angle) + a * math.sin(angle))


def test_rope_attention_scores_depend_only_on_relative_position():
    torch.manual_seed(1)
    q, k = torch.randn(2, 1, 1, 3, 16).unbind(0)
    pos = torch.tensor([[[0, 0], [1, 2], [3, 1]]])
    rope = RoPE2D()
    scores = rope(q, pos) @ rope(k, pos).transpose(-1, -2)
    shifted = rope(q, pos + 5) @ rope(k, pos + 5).transpose(-1, -2)
    torch.testing.assert_close(scores, shifted, atol=1e-5, rtol=1e-5)


def test_forward_shapes_positions_and_layers():
    enc = tiny_encoder()
    img = torch.rand(2, 3, 8, 12) * 2 - 1
    tokens, pos, layers = enc(img, return_layers=[0, 2])
    assert tokens.shape == (2, 6, 32) and pos.shape == (2, 6, 2) and pos.dtype == torch.long
    assert pos[0].tolist() == [[0, 0], [0, 1], [0, 2], [1, 0], [1, 1], [1, 2]]
    assert len(layers) == 2 and all(t.shape == (2, 6, 32) for t in layers)
    torch.testing.assert_close(enc.enc_norm(layers[1]), tokens)  # last block, then enc_norm
    assert torch.equal(patch_positions(1, 2, 3, torch.device("cpu")), pos[:1])
    with pytest.raises(ValueError, match="multiple of the patch size"):
        enc(torch.zeros(1, 3, 9, 12))


def test_images_are_encoded_independently_of_the_batch():
    enc = tiny_encoder()
    img = torch.rand(3, 3, 8, 8) * 2 - 1
    with torch.no_grad():
        batched = enc(img)[0]
        single = torch.cat([enc(img[i:i + 1])[0] for i in range(3)])
    torch.testing.assert_close(batched, single, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("args_as", ["namespace", "string"])
def test_official_file_round_trip(tmp_path, args_as):
    enc = tiny_encoder(seed=3)
    text = OFFICIAL_ARGS.format(D=32, L=3, H=2)
    args = argparse.Namespace(model=text, lr=1e-4) if args_as == "namespace" else text
    # An official file also carries decoder/head weights, which the encoder loader must skip.
    state = {**enc.state_dict(), "decoder_embed.weight": torch.zeros(8, 32), "mask_token": torch.zeros(1)}
    path = tmp_path / "dust3r.pth"
    torch.save({"model": state, "args": args, "epoch": 3}, path)
    loaded = load_dust3r_encoder(path)
    assert not loaded.training
    assert loaded.enc_blocks[0].attn.num_heads == 2 and loaded.patch_size == 4
    img = torch.rand(1, 3, 8, 8) * 2 - 1
    with torch.no_grad():
        torch.testing.assert_close(loaded(img)[0], enc(img)[0], atol=0, rtol=0)


def test_training_checkpoint_with_other_objects_is_refused_not_unpickled(tmp_path):
    enc = tiny_encoder(seed=4)
    path = tmp_path / "train.pth"
    torch.save({"model": enc.state_dict(), "args": argparse.Namespace(model="Net(enc_num_heads=2)"),
                "started": datetime.date(2024, 1, 1)}, path)  # not allowed by weights_only=True
    with pytest.raises(UserError, match=r"holds Python objects other than tensors and plain values "
                                        r"\(datetime.date\)\); if you trust the file, convert it once"):
        load_dust3r_encoder(path)


def test_bare_state_dict_with_module_prefix_loads(tmp_path):
    enc = tiny_encoder()
    path = tmp_path / "bare.pth"
    torch.save({f"module.{k}": v for k, v in enc.state_dict().items()}, path)
    loaded = load_dust3r_encoder(path)  # heads default to width/64 -> 1 head here
    assert loaded.patch_embed.proj.weight.shape == (32, 3, 4, 4)


def test_head_count_from_string_croco_default_or_width(tmp_path):
    """Given heads are used; a model string without them means CroCo's 12 (as the official code
    builds it); a bare state dict has no description, so width / 64."""
    torch.manual_seed(0)
    wide = Dust3rEncoder(patch_size=4, embed_dim=48, depth=1, num_heads=12).eval()
    for args, heads in (("Net(pos_embed='RoPE100', enc_num_heads=3)", 3), ("Net(pos_embed='RoPE100')", 12)):
        path = tmp_path / "enc.pth"
        torch.save({"model": wide.state_dict(), "args": argparse.Namespace(model=args)}, path)
        assert load_dust3r_encoder(path).enc_blocks[0].attn.num_heads == heads
    torch.save(wide.state_dict(), path)
    assert load_dust3r_encoder(path).enc_blocks[0].attn.num_heads == 1
    torch.save({"model": tiny_encoder().state_dict(), "args": argparse.Namespace(model="Net()")}, path)
    with pytest.raises(UserError, match="does not split into 12 attention heads"):
        load_dust3r_encoder(path)  # 32 channels, CroCo's 12 heads


def test_constructor_string_is_parsed_not_executed():
    name, kwargs = parse_constructor(OFFICIAL_ARGS.format(D=1024, L=24, H=16))
    assert name == "AsymmetricCroCo3DStereo"
    assert kwargs["depth_mode"] == ("exp", -math.inf, math.inf)
    assert kwargs["conf_mode"] == ("exp", 1, math.inf) and kwargs["img_size"] == (512, 512)
    assert parse_constructor("Net(a=float('inf'), b=[1, -2.5], c={'k': None})")[1] == {
        "a": math.inf, "b": [1, -2.5], "c": {"k": None}}
    for hostile in ("Net(a=__import__('os').system('echo hi'))", "Net(a=open('x'))",
                    "Net(a=1+2)", "Net(1)", "os.system('x')", "Net(**k)", "Net(a=x.y)"):
        with pytest.raises(ValueError):
            parse_constructor(hostile)


def test_bad_files_give_user_errors(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        load_dust3r_encoder(tmp_path / "missing.pth")
    no_encoder = tmp_path / "head_only.pth"
    torch.save({"model": {"downstream_head1.proj.weight": torch.zeros(4, 4)}, "args": "Net(a=1)"}, no_encoder)
    with pytest.raises(UserError, match="no DUSt3R encoder weights"):
        load_dust3r_encoder(no_encoder)
    hostile = tmp_path / "hostile.pth"
    torch.save({"model": tiny_encoder().state_dict(), "args": "Net(a=__import__('os'))"}, hostile)
    with pytest.raises(UserError, match="cannot parse"):
        read_checkpoint(hostile)
    good = tmp_path / "good.pth"
    torch.save({"model": tiny_encoder().state_dict(), "args": "Net(enc_num_heads=2)"}, good)
    truncated = tmp_path / "truncated.pth"
    truncated.write_bytes(good.read_bytes()[:200])
    with pytest.raises(UserError, match="cannot read checkpoint"):
        load_dust3r_encoder(truncated)
