"""The two-stage optimisation: recovers a known trajectory, chunking is exact, stage 2, bad input."""

from pathlib import Path

import numpy as np
import pytest
import torch

from c4d_core.config import load_config
from c4d_core.errors import UserError
from c4d_pipeline import optimize as opt
from c4d_pipeline.alignment import initialise
from c4d_pipeline.eval_metrics import pose_metrics
from c4d_pipeline.flow import build_flow
from c4d_pipeline.ground_truth import GroundTruthPointmaps, ground_truth_motion_masks, oracle_tracks
from c4d_pipeline.scene_graph import graph_from_config, strided_window_pairs
from c4d_pipeline.scene_params import SceneParams
from tests.synthetic_scenes import make_box_scene

T, H, W = 8, 24, 32



@pytest.fixture(scope="module")
def case():
    scene = make_box_scene(num_frames=T, height=H, width=W, num_tracks=96, seed=1)
    edges = strided_window_pairs(T, window=3, stride=2)
    flows = build_flow("gt", scene=scene).flow(scene.rgb, [tuple(e) for e in edges])
    return scene, edges, flows


def tiny_cfg(*overrides):
    return load_config("c4d", "tiny", overrides=["graph.window=3", *overrides])


def test_recovers_known_trajectory_from_clean_inputs(case):
    scene, edges, flows = case
    pw = GroundTruthPointmaps(scene, depth_noise=0, smooth_noise=0, static_bias=False).pointmaps(scene.rgb, edges)
    tracks = oracle_tracks(scene)
    res = opt.optimise(pw, T, tiny_cfg(), flows=flows, static_masks=~ground_truth_motion_masks(scene),
                       tracks=tracks.tracks, visible=tracks.visible)
    metrics = pose_metrics(res.cam_to_world, scene.cam_to_world)
    assert metrics["ate"] < 0.01 and metrics["rpe_rot"] < 0.2  # scene is ~8 units across
    np.testing.assert_allclose(res.intrinsics[:, 0, 0], scene.intrinsics[:, 0, 0], rtol=0.01)
    scale = np.median(scene.depth / res.depth)
    assert np.median(np.abs(scale * res.depth / scene.depth - 1)) < 0.01
    assert set(res.history["seconds"]) >= {"init", "stage1", "stage2"}
    assert len(res.history["losses"]["stage1"]["ga"]) == 60


def test_global_alignment_converges_from_perturbed_poses(case):
    scene, edges, _ = case
    pw = GroundTruthPointmaps(scene, depth_noise=0, smooth_noise=0, static_bias=False).pointmaps(scene.rgb, edges)
    init = initialise(pw, T)
    g = torch.Generator().manual_seed(0)
    poses = init.cam_to_world.clone()
    poses[:, :3, 3] += 0.05 * torch.randn(T, 3, generator=g)  # 5 % of the median depth
    params = SceneParams(init.depth, poses, init.focal, init.edge_scale, init.edge_rotation, init.edge_translation)
    data = opt._Inputs(pw, None, None, "cpu")
    cfg = tiny_cfg("weights.cma=0", "weights.cts=0")
    state, terms = opt.StageState(params, data), opt.active_objectives(1, cfg.weights, data.available)
    assert [t.name for t in terms] == ["ga"]
    step = lambda: opt.stage_step(state, terms, cfg.weights, 0)  # noqa: E731
    before = pose_metrics(params.cam_to_world().detach().numpy(), scene.cam_to_world)["ate"]
    curves = opt._run_adam(opt.adam(list(params.parameters()), cfg.optim), range(150), 150, cfg.optim, step,
                           "test", False)
    after = pose_metrics(params.cam_to_world().detach().numpy(), scene.cam_to_world)["ate"]
    assert curves["ga"][-1] < 0.2 * curves["ga"][0]
    assert after < 0.3 * before


def test_rescale_world_sets_dustr_scale_and_scales_every_length_alike(case):
    scene, edges, _ = case
    pw = GroundTruthPointmaps(scene, seed=3).pointmaps(scene.rgb, edges)
    init = initialise(pw, T)
    scaled = opt.rescale_world(init, (H, W), 0.5)
    params = [SceneParams(i.depth, i.cam_to_world, i.focal, i.edge_scale, i.edge_rotation,
                          i.edge_translation) for i in (init, scaled)]
    cams = [p.camera_points().detach() for p in params]
    assert cams[1].norm(dim=-1).mean().item() == pytest.approx(0.5, rel=1e-5)
    factor = 0.5 / cams[0].norm(dim=-1).mean().item()
    worlds = [p.world_points().detach() for p in params]
    torch.testing.assert_close(worlds[1], factor * worlds[0], rtol=1e-4, atol=1e-5)
    data = opt._Inputs(pw, None, None, "cpu")
    weights = tiny_cfg("weights.cts=0").weights
    ga = [opt.stage_step(opt.StageState(p, data), opt.active_objectives(1, weights, data.available), weights, 0)["ga"]
          for p in params]
    assert ga[0] > 0 and ga[1] == pytest.approx(factor * ga[0], rel=1e-4)  # GA is in world units
    assert opt.rescale_world(init, (H, W), 0.0) is init


def test_edge_chunks_give_the_unchunked_gradient(case):
    scene, edges, flows = case
    pw = GroundTruthPointmaps(scene).pointmaps(scene.rgb, edges)
    init = initialise(pw, T)
    cfg = tiny_cfg()
    data = opt._Inputs(pw, flows, ~ground_truth_motion_masks(scene), "cpu")
    terms = opt.active_objectives(1, cfg.weights, data.available)
    assert [t.name for t in terms] == ["ga", "cma", "cts"]
    grads = []
    for chunk in (0, 5):
        params = SceneParams(init.depth, init.cam_to_world, init.focal, init.edge_scale,
                             init.edge_rotation, init.edge_translation)
        losses = opt.stage_step(opt.StageState(params, data), terms, cfg.weights, chunk)
        grads.append(([p.grad.clone() for p in params.parameters()], losses))
    for a, b in zip(grads[0][0], grads[1][0]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
    assert grads[0][1]["total"] == pytest.approx(grads[1][1]["total"], rel=1e-5)
    assert grads[0][1]["cma"] > 0 and grads[0][1]["cts"] > 0


def test_stage2_smooths_depth_and_keeps_cameras(case):
    scene, edges, flows = case
    pw = GroundTruthPointmaps(scene, seed=2).pointmaps(scene.rgb, edges)
    tracks = oracle_tracks(scene)
    res = opt.optimise(pw, T, tiny_cfg("optim.stage1_iters=20"), flows=flows, tracks=tracks.tracks,
                       visible=tracks.visible)
    pts = res.history["losses"]["stage2"]["pts"]
    assert pts[-1] < 0.6 * pts[0]  # 30 Adam steps of ~1 % on log-depth
    assert not np.allclose(res.depth, res.depth_stage1)


def test_bad_inputs_are_user_errors_or_ignored(case):
    scene, edges, flows = case
    pw = GroundTruthPointmaps(scene).pointmaps(scene.rgb, edges)
    cfg = tiny_cfg("optim.stage1_iters=2", "optim.stage2_iters=0")
    with pytest.raises(UserError, match="optical flow"):
        opt.optimise(pw, T, cfg, flows=flows[:-1])
    with pytest.raises(UserError, match="tracks"):
        opt.optimise(pw, T, cfg, tracks=np.zeros((T - 1, 4, 2)), visible=np.ones((T - 1, 4), bool))
    with pytest.raises(UserError, match="frames"):
        opt.optimise(pw, T - 2, cfg)
    nan_flows = flows.copy()
    nan_flows[:, :4] = np.nan
    res = opt.optimise(pw, T, cfg, flows=nan_flows, static_masks=np.zeros((T, H, W), bool))
    assert np.isfinite(res.cam_to_world).all()  # no static pixel at all: CMA contributes nothing


def test_ablation_runs_every_variant_on_one_scene():
    from c4d_pipeline.ablation import VARIANTS, ablate_scene, resize_scene

    scene = resize_scene(make_box_scene(num_frames=8, height=24, width=32, num_tracks=48, seed=2), 16, frames=6)
    assert scene.rgb.shape == (6, 12, 16, 3) and scene.tracks.shape[1] == 6
    out = ablate_scene(scene, "tiny", ["graph.window=2", "optim.stage1_iters=3", "optim.stage2_iters=2",
                                       "pts.window=3", "pts.extend=1"], True, "gt", "c4d")
    for variant in VARIANTS:
        assert np.isfinite(out[variant]["ate"]) and 0 < out[variant]["delta_1_25"] <= 1
    assert 0 <= out["mask_iou"] <= 1


def test_the_ablation_masks_and_pts_tracks_come_from_a_given_trained_tracker(tmp_path):
    """`--tracker CKPT`: the C4D masks are made from that tracker's tracks and mobility (here a
    tiny random-weight DynPT) and PTS follows its tracks, not the oracle's."""
    from c4d_pipeline.ablation import ablate_scene, resize_scene
    from c4d_pipeline.eval_metrics import mask_iou
    from c4d_pipeline.motion_mask import MotionMaskConfig, correspondence_motion_masks
    from dynpt.checkpoint import save_checkpoint
    from dynpt.inference import load_tracker
    from dynpt.model import build_model

    torch.manual_seed(0)
    ckpt = save_checkpoint(tmp_path / "dynpt_tiny.pt", build_model(load_config("dynpt/model", "tiny").model), step=0)
    tracker = load_tracker(ckpt)
    scene = resize_scene(make_box_scene(num_frames=6, height=24, width=32, num_tracks=48, seed=2), 32)
    fast = ["graph.window=2", "optim.stage1_iters=3", "optim.stage2_iters=2", "pts.window=3", "pts.extend=1"]
    out = ablate_scene(scene, "tiny", fast, True, "gt", "c4d", ("GA only", "C4D"), tracker)
    cfg = load_config("c4d", "tiny", overrides=fast)
    pairs = [tuple(map(int, e)) for e in graph_from_config(scene.num_frames, cfg.graph)]
    flows = build_flow("gt", scene=scene).flow(scene.rgb, pairs)
    expected = correspondence_motion_masks(tracker.track(scene.rgb), flows, pairs,
                                           MotionMaskConfig(**dict(cfg.motion_mask.c4d)), scene.rgb).masks
    oracle = ablate_scene(scene, "tiny", fast, True, "gt", "c4d", ("GA only", "C4D"))
    assert out["mask_iou"] == mask_iou(expected, ground_truth_motion_masks(scene))["iou"]
    assert out["GA only"] == oracle["GA only"]  # GA only reads neither masks nor tracks
    assert np.isfinite(out["C4D"]["ate"]) and out["C4D"] != oracle["C4D"]  # PTS smooths along the tracker's tracks


def test_a_resumed_ablation_refuses_other_settings(tmp_path):
    """The runs cached in OUT/runs/ were made with OUT/settings.json's settings; resuming with
    another flow, preset, tracker, ... is one clear error, not a table mixing both."""
    import argparse

    from c4d_pipeline.ablation import SETTINGS, check_settings

    args = argparse.Namespace(**{key: None for key in SETTINGS})
    args.flow, args.preset, args.overrides = "dis", "demo", ["cma.max_px=50"]
    check_settings(tmp_path, args)
    check_settings(tmp_path, args)  # the same settings: resumes
    args.overrides = []
    with pytest.raises(UserError, match=r"other settings \(overrides \['cma.max_px=50'\], now \[\]\)"):
        check_settings(tmp_path, args)


def test_the_ablation_takes_every_stride_th_frame_and_requeries_tracks_on_kept_frames():
    from c4d_pipeline.ablation import resize_scene

    scene = make_box_scene(num_frames=9, height=24, width=32, num_tracks=48, seed=2)
    scene.query_frame[:4] = [0, 3, 4, 8]
    out = resize_scene(scene, 32, frames=3, stride=3)  # frames 0, 3, 6 at the same size
    assert out.num_frames == 3 and out.image_size == (24, 32)
    np.testing.assert_array_equal(out.rgb, scene.rgb[[0, 3, 6]])
    np.testing.assert_array_equal(out.cam_to_world, scene.cam_to_world[[0, 3, 6]])
    usable = (~scene.occluded[:, [0, 3, 6]]).any(axis=1)
    np.testing.assert_allclose(out.tracks, scene.tracks[usable][:, [0, 3, 6]], atol=1e-6)
    first_visible = np.argmax(~out.occluded, axis=1)
    expected = {0: 0, 3: 1}  # kept frames map to their index; 4 and 8 are left out: first visible
    for i in np.flatnonzero(usable[:4]):
        n = int(np.flatnonzero(usable)[:i + 1].size - 1)
        q = int(scene.query_frame[i])
        assert out.query_frame[n] == expected.get(q, first_visible[n]), (q, out.query_frame[n])


def test_the_ablation_table_is_read_from_its_yaml_in_order_and_checked(tmp_path):
    """configs/c4d/ablation/objectives.yaml holds Table 6's rows in order; a malformed row or an
    override the c4d config lacks is one `UserError` at load."""
    from c4d_pipeline.ablation import RUNS, STAGE1_OF, VARIANTS, read_variants

    assert VARIANTS == ("GA only", "w/o CMA", "w/o CTS", "w/o PTS", "C4D")
    assert RUNS == {"GA only": ["weights.cma=0", "weights.cts=0", "weights.pts=0"],
                    "w/o CMA": ["weights.cma=0"], "w/o CTS": ["weights.cts=0"], "C4D": []}
    assert STAGE1_OF == {"w/o PTS": "C4D"}
    for text, message in (("A: {overrides: [weights.cma=0], stage1_of: A}\n", "exactly one of"),
                          ("A: {overrides: [weights.cmaa=0]}\n", "cmaa"),
                          ("A: {stage1_of: B}\n", "must name a row with overrides")):
        (tmp_path / "table.yaml").write_text(text)
        with pytest.raises(UserError, match=message):
            read_variants(tmp_path / "table.yaml")


REFERENCE = Path(__file__).parent / "data" / "c4d_optimise_reference.npz"


def reference_run():
    """The case of tests/data/c4d_optimise_reference.npz: 10 frames of 24x32, the default graph
    (50 edges), noisy biased pointmaps, exact flow and masks, oracle tracks, 150 + 150 iterations."""
    scene = make_box_scene(num_frames=10, height=24, width=32, num_tracks=128, seed=1)
    cfg = load_config("c4d", "default", overrides=["optim.stage1_iters=150", "optim.stage2_iters=150"])
    edges = graph_from_config(10, cfg.graph)
    pw = GroundTruthPointmaps(scene).pointmaps(scene.rgb, edges)
    flows = build_flow("gt", scene=scene).flow(scene.rgb, [tuple(map(int, e)) for e in edges])
    tracks = oracle_tracks(scene)
    return opt.optimise(pw, 10, cfg, flows=flows, static_masks=~ground_truth_motion_masks(scene),
                        tracks=tracks.tracks, visible=tracks.visible)


def test_result_equals_the_autograd_optimiser_within_rounding_drift():
    # The reference was written by the optimiser before the hand-written GA/CMA gradients (commit
    # 042ab8f: autograd over (e,P,3) temporaries, edge_chunk 64). The mathematics is the same, so the
    # results differ by float32 rounding, amplified over the Adam steps. Measured on this case: that
    # optimiser against itself with edge_chunk 7 (a pure rounding change) differs by depth 1.0e-2 max /
    # 8.5e-4 median relative, pose entries 1.4e-3, focal 1.5e-4; this one against it by 9.7e-3 /
    # 7.9e-4, 1.3e-3, 1.3e-4. Tolerances: about twice the rounding drift.
    torch.set_num_threads(1)
    ref, res = np.load(REFERENCE), reference_run()
    for key in ("depth", "depth_stage1"):
        rel = np.abs(getattr(res, key) / ref[key] - 1)
        assert rel.max() < 0.02 and np.median(rel) < 2e-3, (key, rel.max(), np.median(rel))
    assert np.abs(res.cam_to_world - ref["cam_to_world"]).max() < 3e-3
    np.testing.assert_allclose(res.intrinsics, ref["intrinsics"], rtol=1e-3)


def test_a_registered_objective_is_one_function_and_one_weight_key(case, monkeypatch, tmp_path):
    import shutil

    from c4d_core import config as config_module
    from c4d_pipeline import objectives

    scene, edges, flows = case
    pw = GroundTruthPointmaps(scene).pointmaps(scene.rgb, edges)
    calls = []

    def depth_prior(state):  # pulls log-depth towards 0: a toy stage-1 term
        calls.append(1)
        return state.params.log_depth.square().mean()

    monkeypatch.setattr(objectives, "OBJECTIVES", list(objectives.OBJECTIVES))
    objectives.objective("prior", weight="prior", stage=1)(depth_prior)
    with pytest.raises(UserError, match="weights.prior"):
        opt.optimise(pw, T, tiny_cfg("optim.stage1_iters=2", "optim.stage2_iters=0"))
    # the one YAML key, in the root preset (its range is the schema's `weights.*` rule)
    shutil.copytree(config_module.config_dir() / "c4d", tmp_path / "c4d")
    root = tmp_path / "c4d" / "default.yaml"
    root.write_text(root.read_text().replace("weights:\n", "weights:\n  prior: 0.5\n", 1))
    monkeypatch.setattr(config_module, "config_dir", lambda: tmp_path)
    config_module._root.cache_clear()
    try:
        res = opt.optimise(pw, T, tiny_cfg("optim.stage1_iters=3", "optim.stage2_iters=0"))
        assert len(calls) == 3 and len(res.history["losses"]["stage1"]["prior"]) == 3
        opt.optimise(pw, T, tiny_cfg("optim.stage1_iters=3", "optim.stage2_iters=0", "weights.prior=0"))
        assert len(calls) == 3  # weight 0: not evaluated
    finally:
        config_module._root.cache_clear()
