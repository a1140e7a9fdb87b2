"""DynPT from CoTracker3's weights: the mapping table against golden outputs of CoTracker3's own code.

tests/fixtures/cotracker3_golden.pt holds, for a reduced-size CoTracker3 offline and online model
built from facebookresearch/co-tracker's classes with random weights (heads scaled up so tracks
move), the state dicts, an 18-frame 48x64 video, 12 queries at frames 0..17 and CoTracker3's
tracks, visibility and confidence (3 iterations; online: windows of 8 moved by 4, the last one
padded), and under `offline_predictor` what CoTracker3's own `CoTrackerPredictor` returns for
the offline model on that video and those queries (tracks and visible flags, 6 iterations, at
the video's size, with and without backward tracking). Made by a scratch script outside the
repository.
"""

from pathlib import Path

import pytest
import torch

from c4d_core.config import load_config
from c4d_core.errors import UserError
from dynpt import cotracker3_weights as cw
from dynpt.model import build_model, plain_config

GOLDEN = Path(__file__).parent / "fixtures" / "cotracker3_golden.pt"


@pytest.fixture(scope="module")
def golden():
    return torch.load(GOLDEN, weights_only=True)


def _base() -> dict:
    return plain_config(load_config("dynpt", "model/cotracker3-offline").model)


def _dynpt(state, windowing, tmp_path):
    path = tmp_path / "ct3.pth"
    torch.save({"model": state}, path)  # as written by CoTracker3's training (under `model`)
    model = build_model(cw.config_from_state(state, _base(), windowing))
    fresh = cw.load_into(model, path)
    return model.eval(), fresh


@pytest.mark.parametrize("kind", ["offline", "online"])
def test_outputs_equal_cotracker3(golden, kind, tmp_path):
    g = golden[kind]
    model, fresh = _dynpt(g["state"], f"cotracker3_{kind}", tmp_path)
    assert fresh == ["transformer.mobility_head.weight", "transformer.mobility_head.bias"]
    q = golden["queries"]
    with torch.no_grad():
        out = model(golden["video"], q, iters=3)
    valid = out.valid[0]  # offline: every frame; online: from the query frame on
    assert valid.all() == (kind == "offline")
    err = (out.coords[-1][0] - g["tracks"]).norm(dim=-1)[valid]
    motion = (g["tracks"] - q[0, None, :, 1:]).norm(dim=-1)[valid]
    assert motion.mean() > 2.0  # the tracks move: a wrong mapping shows
    assert err.max() < 1e-3, err.max()
    vis, conf = torch.sigmoid(out.vis_logits[-1][0]), torch.sigmoid(out.conf_logits[-1][0])
    assert (vis - g["vis"]).abs()[valid].max() < 1e-4
    assert (conf - g["conf"]).abs()[valid].max() < 1e-4


@pytest.mark.parametrize("backward", [False, True])
def test_the_tracker_gives_cotracker3s_offline_predictor_flags(golden, backward):
    """DynPT's `Tracker` with CoTracker3's offline weights and config (model/cotracker3-offline:
    visible = sigmoid(vis) > 0.9, no confidence term) returns the visible flags and tracks of
    CoTracker3's `CoTrackerPredictor`, backward tracking included; the online rule on the same
    probabilities (vis x conf > 0.6) would not."""
    from dynpt.inference import Tracker, visibility

    g, expected = golden["offline"], golden["offline_predictor"]["backward" if backward else "forward"]
    cfg = {**cw.config_from_state(g["state"], _base(), "cotracker3_offline"), "resolution": None}
    assert (cfg["visibility_rule"], cfg["visibility_threshold"]) == ("vis", 0.9)
    model = build_model(cfg)
    model.load_state_dict(cw.map_state(g["state"], cfg, model.state_dict())[0], strict=False)
    video = golden["video"][0].permute(0, 2, 3, 1).numpy()  # (T,H,W,3) uint8
    queries = golden["queries"][0].numpy()  # (N,3) t, x, y at frames 0..17
    result = Tracker(model, "cpu").track(video, queries, backward=backward, support_grid=6)
    assert (result.visible == expected["visible"].numpy()).all()
    assert 0.3 < result.visible.mean() < 0.8  # both kinds of flag occur
    err = abs(result.tracks - expected["tracks"].numpy()).max()
    assert err < 1e-3, err
    with torch.no_grad():  # the online rule on the same network's probabilities disagrees
        out = model.eval()(golden["video"], golden["queries"], iters=6)
    online = visibility(torch.sigmoid(out.vis_logits[-1][0]), torch.sigmoid(out.conf_logits[-1][0]),
                        "vis_conf", 0.6)
    if not backward:
        assert (online.numpy() != expected["visible"].numpy()).any()


def test_plain_rename_of_the_correlation_mlp_is_wrong(golden, tmp_path):
    """Without the column reorder the outputs differ: the golden data catches a plain rename."""
    g = golden["offline"]
    state = dict(g["state"])
    w = state["corr_mlp.fc1.weight"]
    state["corr_mlp.fc1.weight"] = cw._corr_columns(w, 1)  # undone by the mapping -> plain rename
    model, _ = _dynpt(state, "cotracker3_offline", tmp_path)
    with torch.no_grad():
        out = model(golden["video"], golden["queries"], iters=3)
    assert (out.coords[-1][0] - g["tracks"]).norm(dim=-1).max() > 0.05


def test_mapping_table_covers_the_released_layout():
    """Every tensor name of the released layout maps, and DynPT's fresh tensors are the mobility head."""
    base = _base()
    model = build_model(base)
    target = model.state_dict()
    names = [k for k in target if k != "transformer.mobility_head.weight" and k != "transformer.mobility_head.bias"]
    released = ["time_emb", "fnet.conv1.weight", "corr_mlp.fc1.weight", "updateformer.virual_tracks",
                "updateformer.space_virtual2point_blocks.2.cross_attn.to_kv.bias",
                "updateformer.space_point2virtual_blocks.0.norm_context.weight",
                "updateformer.time_blocks.1.mlp.fc2.weight", "updateformer.vis_conf_head.bias"]
    assert all(cw.dynpt_key(k) in names for k in released)
    assert cw.dynpt_key("updateformer.space_virtual_blocks.0.attn.to_q.weight") == \
        "transformer.virtual_blocks.0.attn.to_q.weight"
    assert cw.dynpt_key("fnet.layer2.0.downsample.0.weight") == "cnn.layer2.0.downsample.0.weight"
    assert cw.dynpt_key("not_cotracker.weight") is None


def test_token_columns():
    """Mobility column inserted at zero; forward-motion raw and sine columns negated (22 with 10 freqs)."""
    x = torch.arange(1, 1111, dtype=torch.float32)[None]  # CoTracker3's 1110 token inputs
    y = cw._token_columns(x, 2 + 1024, 10)[0]
    assert y.shape == (1111,) and y[2] == 0 and torch.equal(y[:2], x[0, :2])
    negated = (y[3:] == -x[0, 2:]).nonzero().flatten() + 2
    assert len(negated) == 22 and negated[:2].tolist() == [1026, 1027]


def test_single_head_file_is_split(golden, tmp_path):
    """A file with one 4-row flow head (linear_layer_for_vis_conf=False) maps onto both heads."""
    state = dict(golden["online"]["state"])
    state["updateformer.flow_head.weight"] = torch.cat(
        [state["updateformer.flow_head.weight"], state.pop("updateformer.vis_conf_head.weight")])
    state["updateformer.flow_head.bias"] = torch.cat(
        [state["updateformer.flow_head.bias"], state.pop("updateformer.vis_conf_head.bias")])
    model, _ = _dynpt(state, "cotracker3_online", tmp_path)
    assert torch.equal(model.transformer.vis_conf_head.bias, golden["online"]["state"]["updateformer.vis_conf_head.bias"])


def test_refusals(golden, tmp_path):
    state = golden["offline"]["state"]
    plain = tmp_path / "plain.pth"
    torch.save(state, plain)
    tiny = build_model(load_config("dynpt", "model/tiny").model)  # other sizes, DynPT's time embedding
    with pytest.raises(UserError, match="time_embedding=cotracker3"):
        cw.load_into(tiny, plain)
    wrong = build_model({**_base(), "corr_levels": 3})
    with pytest.raises(UserError, match="token inputs"):
        cw.load_into(wrong, plain)
    small_cfg = cw.config_from_state(state, _base(), "cotracker3_offline")
    wider = build_model({**small_cfg, "corr_hidden_dim": 64})
    with pytest.raises(UserError, match=r"corr.mlp.0.weight is \(32, 81\) in the file but \(64, 81\)"):
        cw.load_into(wider, plain)
    extra = tmp_path / "extra.pth"
    torch.save({**state, "updateformer.extra.weight": torch.zeros(1)}, extra)
    small = build_model(small_cfg)
    with pytest.raises(UserError, match="not part of CoTracker3's network"):
        cw.load_into(small, extra)
    partial = tmp_path / "partial.pth"
    torch.save({k: v for k, v in state.items() if not k.startswith("fnet.conv3")}, partial)
    with pytest.raises(UserError, match="no tensor 'fnet.conv3.weight'"):
        cw.load_into(small, partial)
    torch.save({k: v for k, v in state.items() if not k.startswith("fnet.layer2.1.")}, partial)
    with pytest.raises(UserError, match="no CoTracker3 tensor for DynPT's cnn.layer2.1"):
        cw.load_into(small, partial)
    other = tmp_path / "other.pth"
    torch.save({"weights": torch.zeros(1)}, other)
    with pytest.raises(UserError, match="not a CoTracker3 checkpoint"):
        cw.read_state(other)
    with pytest.raises(UserError, match="does not exist"):
        cw.read_state(tmp_path / "missing.pth")
    with pytest.raises(UserError, match="expected cotracker3:"):
        cw.parse_init("cotracker3:")


def test_default_presets_unchanged():
    """Existing presets keep DynPT's own windowing, embedding and sampling (old checkpoints load)."""
    cfg = plain_config(load_config("dynpt", "tiny-cpu").model)
    assert (cfg["windowing"], cfg["time_embedding"], cfg["sampling"]) == ("causal", "hidden", "centers")
    old = {k: v for k, v in cfg.items() if k not in ("windowing", "time_embedding", "time_emb_len",
                                                     "sampling", "init_from")}
    assert "transformer.time_emb" not in build_model(old).state_dict()


def test_load_tracker_reads_a_cotracker3_file(golden, tmp_path):
    import numpy as np

    import dynpt

    path = tmp_path / "scaled_online.pth"
    torch.save(golden["online"]["state"], path)
    tracker = dynpt.load_tracker(f"cotracker3:{path}", device="cpu")
    assert tracker.model.config["windowing"] == "cotracker3_online"  # 8-row time embedding
    video = golden["video"][0].permute(0, 2, 3, 1).numpy()
    q = golden["queries"][0].numpy()[:3]
    res = tracker.track(video, q, support_grid=2)
    assert res.tracks.shape == (18, 3, 2) and np.isfinite(res.tracks).all()


@pytest.mark.parametrize("preset,trained", [
    ("finetune-mobility", {"mobility"}),
    ("finetune-mobility-fusion", {"mobility", "fusion"}),
    ("finetune-full", {"cnn", "correlation", "transformer", "mobility", "fusion"}),
])
def test_finetune_recipes_train_their_parts(preset, trained):
    """Each recipe's parameter groups: the parts it trains, at lr x lr_scale; the rest frozen."""
    from dynpt.train import PARTS, param_groups

    over = ["model.encoder_3d.random_init=true", "model.encoder_3d.require_checkpoint=false",
            "model.encoder_3d.depth=2", "model.encoder_3d.embed_dim=64", "model.encoder_3d.num_heads=2",
            "model.encoder_3d.layers=[0]"] if preset != "finetune-mobility" else []
    cfg = load_config("dynpt", preset, overrides=over)
    assert cfg.model.windowing == "cotracker3_offline" and cfg.model.init_from == "cotracker3:"
    model = build_model(cfg.model)
    groups = param_groups(model, cfg.train.lr, cfg.train.lr_scale)
    assert {g["name"] for g in groups} == trained
    for g in groups:
        assert g["lr"] == pytest.approx(cfg.train.lr * cfg.train.lr_scale[g["name"]])
    for name, p in model.named_parameters():
        part = next((k for k, pre in PARTS.items() if name.startswith(pre)), "encoder_3d")
        assert p.requires_grad == (part in trained), name


def _cotracker2_like(state: dict) -> dict:
    """CoTracker2's layout from CoTracker3's tensors: no correlation MLP or visibility head, but
    a group norm, a track-feature updater and a visibility predictor (co-tracker's CoTracker2)."""
    kept = {k: v for k, v in state.items()
            if not k.startswith(("corr_mlp.", "updateformer.vis_conf_head."))}
    return {**kept, "norm.weight": torch.ones(16), "norm.bias": torch.zeros(16),
            "track_feat_updater.0.weight": torch.zeros(16, 48), "vis_predictor.0.weight": torch.zeros(1, 16)}


@pytest.mark.parametrize("fault,words", [
    ("no time_emb", ("no tensor 'time_emb'",)),
    ("no corr_mlp.fc1.weight", ("no tensor 'corr_mlp.fc1.weight'",)),
    ("no fnet.layer1.0.conv1.weight", ("no tensor 'fnet.layer1.0.conv1.weight'",)),
    ("no updateformer.virual_tracks", ("no tensor 'updateformer.virual_tracks'",)),
    ("cotracker2", ("is not part of CoTracker3's network", "CoTracker2?")),
    ("narrow input projection", ("updateformer.input_transform.weight has 109 token inputs",
                                 "2 + levels x 16")),
    ("narrow time embedding", ("time_emb is 109 wide", "input_transform.weight takes 118")),
])
def test_a_file_that_is_not_a_whole_cotracker3_is_one_line_naming_the_tensor(
        golden, tmp_path, capsys, fault, words):
    """`load_tracker("cotracker3:PATH")` and `c4d track --ckpt cotracker3:PATH` validate the file
    before reading any size from it; no KeyError, and the tensor at fault is the one named."""
    from c4d.cli import main
    from c4d_core.video import write_video
    from dynpt.inference import load_tracker
    from tests.test_faults import assert_one_line_error

    state = dict(golden["offline"]["state"])
    if fault.startswith("no "):
        del state[fault[3:]]
    elif fault == "cotracker2":
        state = _cotracker2_like(state)
    elif fault == "narrow input projection":
        state["updateformer.input_transform.weight"] = state["updateformer.input_transform.weight"][:, :109]
    else:
        state["time_emb"] = state["time_emb"][..., :109]
    path = tmp_path / "ct.pth"
    torch.save(state, path)
    with pytest.raises(UserError) as caught:
        load_tracker(f"cotracker3:{path}")
    assert str(path) in str(caught.value) and all(w in str(caught.value) for w in words), caught.value
    video = write_video(tmp_path / "v.avi", torch.zeros(4, 32, 32, 3, dtype=torch.uint8).numpy(), 12)
    code = main(["track", str(video), "--ckpt", f"cotracker3:{path}", "--out", str(tmp_path / "o")])
    assert_one_line_error(code, capsys.readouterr().err, str(path), *words)
    assert not (tmp_path / "o").exists()


def test_fusion_starts_as_identity(golden, tmp_path):
    """With the 3D encoder, the fusion conv starts as identity on the CNN features: CoTracker3's outputs."""
    g = golden["offline"]
    path = tmp_path / "ct3.pth"
    torch.save(g["state"], path)
    cfg = cw.config_from_state(g["state"], _base(), "cotracker3_offline")
    cfg["encoder_3d"].update(random_init=True, depth=1, embed_dim=32, num_heads=2, layers=[0])
    model = build_model(cfg)
    fresh = cw.load_into(model, path)
    assert {"vit_proj.weight", "fuse.weight", "transformer.mobility_head.weight"} <= set(fresh)
    with torch.no_grad():
        out = model.eval()(golden["video"], golden["queries"], iters=3)
    assert (out.coords[-1][0] - g["tracks"]).norm(dim=-1).max() < 1e-3


def test_param_groups_refuse_unknown_parts():
    from dynpt.train import param_groups

    model = build_model(load_config("dynpt", "model/tiny").model)
    with pytest.raises(UserError, match="unknown part"):
        param_groups(model, 1e-3, {"cnn": 1.0, "heads": 1.0})
    with pytest.raises(UserError, match="freezes every part"):
        param_groups(model, 1e-3, {k: 0.0 for k in ("cnn", "correlation", "transformer", "mobility", "fusion")})


# --- stand-ins for the released files (tests/cotracker3_layout.py) --------------------------------

# the DynPT sizes of cotracker3_golden.pt (what `config_from_state` reads from its shapes)
SMALL = ["model.cnn_widths=[8,12,16,16]", "model.feature_dim=16", "model.corr_levels=2",
         "model.corr_radius=1", "model.corr_hidden_dim=32", "model.corr_out_dim=16",
         "model.hidden_dim=48", "model.num_heads=1", "model.depth=1", "model.mlp_ratio=2.0",
         "model.num_virtual_tracks=4", "model.time_emb_len=8"]
TINY_3D = ["model.encoder_3d.random_init=true", "model.encoder_3d.require_checkpoint=false",
           "model.encoder_3d.depth=2", "model.encoder_3d.embed_dim=64", "model.encoder_3d.num_heads=2",
           "model.encoder_3d.layers=[0]"]


@pytest.mark.parametrize("kind", ["offline", "online"])
def test_stand_in_layout_is_cotracker3s(golden, kind):
    """tests/cotracker3_layout.py writes the names and shapes co-tracker's own classes write
    (the golden state dicts), and its transform oracle agrees with the loader on them."""
    from tests.cotracker3_layout import expected_dynpt, released_state

    state = golden[kind]["state"]
    cfg = cw.config_from_state(state, _base())
    made = released_state(cfg)
    assert {k: tuple(v.shape) for k, v in made.items()} == {k: tuple(v.shape) for k, v in state.items()}
    mapped, _ = cw.map_state(state, cfg, build_model(cfg).state_dict())
    expected = expected_dynpt(state, cfg)
    assert mapped.keys() == expected.keys()
    assert all(torch.equal(mapped[k], expected[k]) for k in mapped)
    released = released_state(_base())  # the released sizes: 188 tensors, 25.4 M values
    assert len(released) == 188 and sum(v.numel() for v in released.values()) == 25_452_300


def _checkpoint(run, step):
    return torch.load(run / "checkpoints" / f"step_{step:08d}.pt", weights_only=True)["model"]


@pytest.mark.parametrize("recipe, wrapped", [("finetune-mobility", False),
                                             ("finetune-mobility-fusion", True),
                                             ("finetune-full", False)])
def test_finetune_from_a_released_file(recipe, wrapped, tmp_path):
    """`c4d train --config finetune-* --init cotracker3:FILE`: every tensor of the file is in the
    step-1 checkpoint after the documented transforms; the frozen parts stay so at steps 2 and 3,
    the trained parts move; `--resume` continues from the run's checkpoint, not the (deleted) file."""
    from c4d.cli import main
    from dynpt.train import PARTS
    from tests.cotracker3_layout import expected_dynpt, write_released
    from tests.dynpt_testdata import synthetic_shards

    run = tmp_path / "run"
    over = [*SMALL, *(TINY_3D if recipe != "finetune-mobility" else []),
            f"data.sources=[{synthetic_shards(12, 3)}]", f"train.out_dir={run}", "data.crop_size=[32,32]",
            "data.num_frames=6", "data.num_tracks=12", "data.num_workers=0", "train.total_batch=1",
            "train.batch_size=1", "train.steps=3", "train.ckpt_every=1", "train.log_every=1",
            "train.keep_last=3", "eval.every=0"]
    cfg = load_config("dynpt", recipe, overrides=over)
    model_cfg = plain_config(cfg.model)
    file = tmp_path / "weights" / "scaled_offline.pth"
    expected = expected_dynpt(write_released(file, model_cfg, seed=3, wrapped=wrapped), model_cfg)
    init = ["--config", recipe, "--init", f"cotracker3:{file}", *over]
    assert main(["train", *init, "train.stop_after=2"]) == 0
    file.unlink()  # --resume must not need it
    assert main(["train", *init, "--resume"]) == 0
    steps = [_checkpoint(run, s) for s in (1, 2, 3)]
    params = dict(build_model(model_cfg).named_parameters())
    trained_parts = {p for p, scale in cfg.train.lr_scale.items() if scale > 0}

    def trained(name):
        part = next((k for k, pre in PARTS.items() if name.startswith(pre)), None)
        return name in params and part in trained_parts

    frozen = [n for n in expected if not trained(n)]
    assert "cnn.conv1.weight" in frozen or recipe == "finetune-full"
    for ckpt in steps:
        assert all(torch.equal(ckpt[n], expected[n]) for n in frozen)
    moved = {n for n in expected if trained(n) and not torch.equal(steps[0][n], expected[n])}
    for part in trained_parts & {"cnn", "correlation", "transformer"}:
        assert any(n.startswith(PARTS[part]) and not n.startswith(PARTS["mobility"]) for n in moved), part
    for name in params:  # the trained fresh parts (mobility head, fusion) keep learning after step 1
        if name.startswith(("transformer.mobility_head.", "vit_proj.", "fuse.")):
            assert trained(name) == (not torch.equal(steps[0][name], steps[2][name])), name


def test_c4d_track_reads_a_released_file(tmp_path):
    """`c4d track --ckpt cotracker3:FILE`: sizes read from the file's shapes; a file wrapped under
    `model` tracks the same as the plain one, another file's weights track differently."""
    import numpy as np

    from c4d.cli import main
    from c4d_core.video import write_video
    from tests.cotracker3_layout import write_released

    cfg = load_config("dynpt", "model/cotracker3-offline", overrides=SMALL).model
    rng = np.random.default_rng(0)
    video = write_video(tmp_path / "clip.mp4", rng.integers(0, 255, (6, 32, 40, 3), dtype=np.uint8), fps=10)
    tracks = {}
    for name, seed, wrapped in [("plain", 1, False), ("wrapped", 1, True), ("other", 2, False)]:
        file = tmp_path / f"{name}.pth"
        write_released(file, plain_config(cfg), seed=seed, wrapped=wrapped)
        out = tmp_path / name
        assert main(["track", str(video), "--ckpt", f"cotracker3:{file}", "--out", str(out),
                     "--grid-size", "16", "--no-backward"]) == 0
        tracks[name] = np.load(out / "tracks.npz")["tracks"]
    assert tracks["plain"].shape == (6, 12, 2) and np.isfinite(tracks["plain"]).all()
    np.testing.assert_array_equal(tracks["plain"], tracks["wrapped"])
    assert not np.array_equal(tracks["plain"], tracks["other"])
