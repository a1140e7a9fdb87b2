"""`c4d demo --quick`: the whole chain end to end (CI's integration test)."""

import json

import pytest

from c4d.cli import main


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--quick", "--out", str(out)]) == 0
    return out


def test_every_step_ran_and_the_summary_has_every_number(demo_out):
    for step in ("data", "train", "eval", "paper-eval", "recon-data", "reconstruct", "pictures"):
        assert json.loads((demo_out / step / "done.json").read_text())["seconds"] >= 0
    summary = (demo_out / "summary.md").read_text()
    assert "DynPT (trained here)" in summary and "zero motion, all static" in summary
    assert "| C4D |" in summary and "| GA only |" in summary and "nan" not in summary
    assert "DynPT above the baseline on D-ACC: **" in summary
    # the paper's protocol on the val scenes rendered again with 24 frames: 256 tracks at 256x256
    paper = json.loads((demo_out / "paper-eval" / "eval.json").read_text())
    assert set(paper) == {"movi-e", "movi-e-panning"}
    assert all(r["dynpt"]["num_videos"] == 1 and 0 <= r["dynpt"]["moving_ap"] <= 1 for r in paper.values())
    # the same tracking pass post-processed: at the demo's size the head fused with the tracks'
    # epipolar geometry (the same tracks, the same AJ), in the paper protocol on tracks refined
    # by Lucas-Kanade first (the demo config's eval.paper_overrides)
    small = json.loads((demo_out / "eval" / "eval.json").read_text())
    for r in small.values():
        assert r["dynpt_epipolar"]["average_jaccard"] == r["dynpt"]["average_jaccard"]
        assert len(r["dynpt_epipolar_d_acc_interval"]) == 2
    for r in paper.values():
        assert "dynpt_epipolar" not in r and len(r["dynpt_refined_d_acc_interval"]) == 2
        assert r["dynpt_refined"]["occlusion_accuracy"] == r["dynpt"]["occlusion_accuracy"]
    assert summary.count("| DynPT, head + epipolar mobility |") == 2  # 2 presets, demo's size
    assert summary.count("| DynPT, LK-refined tracks, head + epipolar mobility |") == 2  # paper protocol
    assert "Scored with `eval.epipolar.residual_sigmas=4` (demo config eval.overrides)." in summary
    assert ("Scored with `eval.refine=lk eval.epipolar.offset=1 eval.epipolar.residual_sigmas=0.55` "
            "(demo config "
            "eval.paper_overrides).") in summary
    assert "## Tracker, the paper's D-ACC protocol" in summary and "with 24 frames at 32x32" in summary
    for name in ("frames", "depth", "masks", "poses_tum.txt", "scene.ply", "report.json"):
        assert (demo_out / "reconstruct" / "scene-000" / "c4d" / name).exists()
    assert (demo_out / "pictures" / "dataset" / "index.html").exists()
    assert (demo_out / "pictures" / "tracks" / "overlay.mp4").stat().st_size > 0
    readme = demo_out / "pictures" / "readme"
    assert sorted(p.name for p in readme.glob("*.png")) == [
        "dataset_sheet.png", "tracks.png", "trajectory.png"]
    assert "trained 60 steps on 2 processes (overrides: `loss.mobility_pos_weight=1.0`)" in summary
    assert "the track overlay and the reconstruction report show recon-data/movi-e #0" in summary
    # the reconstructed val scene was rendered again at recon.resolution, and reconstructed there
    from datagen.shards import read_scenes

    scene = next(iter(read_scenes(demo_out / "recon-data" / "movi-e")))
    val = next(iter(read_scenes(demo_out / "data" / "val" / "movi-e")))
    assert scene.image_size == (64, 64) and val.image_size == (48, 48)
    assert (scene.cam_to_world == val.cam_to_world).all(), "the same scene at another size"
    assert "rendered again at 64x64" in summary and "for marking every pixel dynamic" in summary
    report = json.loads((demo_out / "pictures" / "reconstruction" / "summary.json").read_text())
    assert (demo_out / "pictures" / "reconstruction" / "mask_errors.png").exists()
    assert report["mask_vs_truth"]["iou"] == pytest.approx(
        json.loads((demo_out / "reconstruct" / "metrics.json").read_text())["scene-000"]["C4D"]["mask"]["iou"])


def test_rerun_resumes_and_skips_every_step(demo_out, caplog):
    caplog.set_level("INFO", logger="c4d.demo")
    assert main(["demo", "--quick", "--out", str(demo_out)]) == 0
    assert caplog.text.count("done before, skipped") == 7


def test_another_config_into_the_same_folder_is_refused(demo_out, capsys):
    assert main(["demo", "--quick", "--out", str(demo_out), "train.steps=7"]) == 2
    assert "another config" in capsys.readouterr().err


def test_a_reconstruct_step_made_with_other_c4d_settings_is_refused(demo_out, tmp_path, capsys):
    """The C4D settings come from configs/c4d/<recon.config>.yaml, which the folder's demo config
    record does not hold: a checkout that ships other ones must not go on to pictures and a
    summary of reconstructions made with the old ones (read from the C4D run's report)."""
    import shutil

    out = tmp_path / "demo"
    shutil.copytree(demo_out, out)
    report = out / "reconstruct" / "scene-000" / "c4d" / "report.json"
    record = json.loads(report.read_text())
    record["config"]["cma"]["max_px"] = 50.0  # as made before ddab03d
    report.write_text(json.dumps(record))
    summary = (out / "summary.md").read_bytes()
    assert main(["demo", "--quick", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "other C4D settings" in err and "(cma.max_px 50.0 -> 20.0)" in err and "Traceback" not in err
    assert f"delete {out / 'reconstruct'} and {out / 'pictures'}" in err
    assert (out / "summary.md").read_bytes() == summary  # nothing rewritten


def test_verdict_says_yes_only_when_every_val_set_is_above_the_baseline():
    from c4d.demo import _tracker_verdict

    both = {"d_acc": 0.9, "d_acc_balanced": 0.6, "average_jaccard": 0.5}
    zero = {"d_acc": 0.91, "d_acc_balanced": 0.5, "average_jaccard": 0.4}
    results = {"movi-e": {"dynpt": both, "zero_motion": zero},
               "movi-e-panning": {"dynpt": dict(both, d_acc=0.95), "zero_motion": zero}}
    d_acc, balanced, aj = _tracker_verdict(results)
    assert d_acc == "- DynPT above the baseline on D-ACC: **no** (movi-e -1.0, movi-e-panning +4.0 points)"
    assert "**yes** (movi-e +10.0, movi-e-panning +10.0 points)" in balanced
    assert aj.startswith("- DynPT above the baseline on AJ: **yes**")
    # With the intervals of the D-ACC difference: "yes" only when every interval is above 0; one
    # that holds 0 makes it a difference within the variation, and nothing prints as "-0.0".
    results["movi-e"]["dynpt"] = dict(both, d_acc=0.92)
    results["movi-e"]["d_acc_interval"] = [-0.0004, 0.026]
    results["movi-e-panning"]["d_acc_interval"] = [0.01, 0.07]
    d_acc = _tracker_verdict(results)[0]
    assert d_acc == ("- DynPT above the baseline on D-ACC: **within the scene-to-scene variation** "
                     "(movi-e +1.0, movi-e-panning +4.0 points; 95 % interval over the val scenes: "
                     "movi-e +0.0 to +2.6, movi-e-panning +1.0 to +7.0)")
    results["movi-e"]["d_acc_interval"] = [0.002, 0.026]
    assert "D-ACC: **yes** (" in _tracker_verdict(results)[0]
    # the fused mobility's rows: its own intervals, no AJ line (the same tracks)
    for r in results.values():
        r["dynpt_epipolar"], r["dynpt_epipolar_d_acc_interval"] = dict(both, d_acc=0.8), [-0.2, -0.01]
    lines = _tracker_verdict(results, "dynpt_epipolar")
    assert len(lines) == 2 and lines[0].startswith(
        "- DynPT, head + epipolar mobility above the baseline on D-ACC: **no** (movi-e -11.0")


def test_every_run_folder_keeps_its_resolved_config(demo_out):
    """The demo, its training run and its datasets each keep the config they ran with, the YAML
    `c4d config show` prints."""
    import yaml

    from c4d_core.config import load_config, to_dict

    demo = load_config("demo", "quick")
    assert yaml.safe_load((demo_out / "demo-config.yaml").read_text()) == to_dict(demo)
    train = yaml.safe_load((demo_out / "train" / "config.yaml").read_text())
    assert train["train"]["steps"] == demo.train.steps and train["loss"]["mobility_pos_weight"] == 1.0
    assert train == to_dict(load_config("dynpt", demo_out / "train" / "config.yaml"))
    data = yaml.safe_load((demo_out / "data" / "train" / "movi-e" / "config-train.yaml").read_text())
    assert data["resolution"] == list(demo.data.resolution) and data["frames"] == demo.data.frames


def test_a_subcommand_that_starts_workers_leaves_the_demo_its_threads(tmp_path, monkeypatch):
    """`c4d datagen --workers 2` takes its threads down to leave the workers their cores; the
    demo's own work after it (the paper-eval step scores the scenes it rendered) gets them back."""
    import torch

    from c4d import demo
    from c4d_core import system

    monkeypatch.setattr(system, "_USER_OMP", None)  # as without OMP_NUM_THREADS (conftest sets it)
    monkeypatch.setattr(system, "available_cpus", lambda: 4)
    monkeypatch.setattr(system, "_override", {})
    try:
        assert system.configure_threads() == 4
        demo._c4d("datagen", "--preset", "movi-e", "--num-scenes", 2, "--out", tmp_path / "d",
                  "--resolution", "32x32", "--frames", 2, "--workers", 2)
        assert torch.get_num_threads() == 4
    finally:
        monkeypatch.undo()
        system.configure_threads()
