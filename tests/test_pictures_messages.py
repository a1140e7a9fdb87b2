"""Issue 46, item 5: the pictures and messages say what is there, once, in the legend's colours.

Pictures: one depth colour range per video, no empty band under the report's depth video, track
dots in exactly the legend's colours, three panels in the README's tracks.png, ply.png with a
title and labelled axes, no negative ticks on the displacement plot, the trajectory named by its
method. Messages: the static-points fallback once and its list marked where cut, the pointmap
training line saying which value it prints, the view counting frames from 0 in --help and on the
page, the square-to-4:3 crop said, the demo's verdict only "yes" when the whole interval is
above 0 and never "-0.0", Ctrl-C on a 2-process training run ending in "c4d: interrupted"
with status 130 and no traceback.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from c4d.cli import main
from c4d.demo import readme_pictures
from c4d.inspect import plots, recon_report
from c4d_core import draw
from c4d_core.config import load_config
from c4d_core.video import read_video, write_image, write_video
from c4d_pipeline.outputs import write_reconstruction
from tests.synthetic_scenes import make_box_scene
from tests.test_c4d_outputs import random_reconstruction
from tests.test_inspect_recon import write_reconstruction as write_scene_reconstruction

GA_ONLY_LOSSES = {"stage1": {"ga": [0.3, 0.2], "total": [0.3, 0.2], "seconds": [0.1, 0.1]}}
QUICK_INSPECT = load_config("inspect", "default", overrides=["flythrough.min_views=8",
                                                             "flythrough.views_per_frame=1"])
C4D_LOSSES = {"stage1": {"ga": [0.3], "cma": [0.1], "cts": [0.1], "total": [0.5]},
              "stage2": {"pts": [0.2], "total": [0.2]}}


def _keeping(saved: list):
    """A stand-in for `plots._save` that saves as it does and keeps, in `saved`, each figure's
    axes and legend texts (ticks and legend as written to the PNG)."""
    save = plots._save

    def keep(fig, path):
        fig.canvas.draw()
        legend = [text.get_text() for lg in fig.legends for text in lg.get_texts()]
        saved.append({"axes": fig.axes, "legend": legend})
        return save(fig, path)

    return keep


@pytest.fixture()
def figures(monkeypatch):
    """What the report plots saved during the test (`_keeping`)."""
    saved = []
    monkeypatch.setattr(plots, "_save", _keeping(saved))
    return saved


@pytest.fixture(scope="module")
def box_scene():
    return make_box_scene(num_frames=8, height=64, width=64, num_tracks=48, seed=3)


@pytest.fixture(scope="module")
def report(tmp_path_factory, box_scene):
    """`c4d inspect` on a 64x64 reconstruction (the demo's size) and the figures it saved."""
    figures = []
    recon = write_scene_reconstruction(box_scene, tmp_path_factory.mktemp("recon") / "recon")
    out = tmp_path_factory.mktemp("report")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(plots, "_save", _keeping(figures))
        recon_report.build_recon_report(recon, out, QUICK_INSPECT, video_ext=".mp4")
    return out, figures


# --- pictures ------------------------------------------------------------------------------------


def test_depth_pngs_share_one_colour_range_over_the_video(tmp_path):
    rec = random_reconstruction(np.random.default_rng(0), t=2, h=8, w=10)
    rec.depth[0] = np.linspace(1.0, 2.0, 80).reshape(8, 10)  # a near frame ...
    rec.depth[1] = np.linspace(1.5, 9.0, 80).reshape(8, 10)  # ... and a far one
    rec.depth[0, 4, 5] = rec.depth[1, 4, 5] = 1.5  # the same depth in both
    out = write_reconstruction(rec, tmp_path / "out")
    first, second = (np.asarray(Image.open(out / "depth" / f"{t:06d}.png")) for t in (0, 1))
    np.testing.assert_array_equal(first[4, 5], second[4, 5])
    assert not np.array_equal(first[0, 0], second[-1, -1])  # 1 m and 9 m still differ


def test_the_report_depth_video_has_no_empty_band_of_rows(report):
    out, _ = report
    frame = read_video(out / "depth.mp4")[0].astype(np.int32)  # (H,W,3): depth over its colour key
    flat = np.ptp(frame.reshape(len(frame), -1), axis=1) < 12  # rows of one colour (codec noise)
    longest = run = 0
    for row_is_flat in flat:
        run = run + 1 if row_is_flat else 0
        longest = max(longest, run)
    assert longest < 0.05 * len(frame), f"{longest} of {len(frame)} rows hold nothing"


def test_track_dots_are_drawn_in_the_legend_colours():
    frames = np.full((2, 60, 200, 3), 128, np.uint8)  # wide enough for both keys
    tracks = np.array([[[20.0, 30.0], [60.0, 30.0]]] * 2, np.float32)  # (T,N,2)
    moving = np.array([[0.3, 0.7]] * 2)  # probabilities, as the tracker gives them
    out = draw.draw_tracks(frames, tracks, moving=moving, radius=4, legend=True)
    legend_colours = {tuple(c) for c in out[0, 60:].reshape(-1, 3)}  # the strip below the frames
    static_dot, moving_dot = tuple(out[0, 30, 20]), tuple(out[0, 30, 60])
    assert moving_dot == draw.TRACK_LEGEND["moving"] and moving_dot in legend_colours
    assert static_dot == draw.TRACK_LEGEND["static"] and static_dot in legend_colours


@pytest.mark.parametrize("most_moving", [0, 3, 5])  # the first, the middle, another frame
def test_the_readme_track_picture_has_three_panels(tmp_path, most_moving):
    T, H, W = 6, 64, 64
    (tmp_path / "dataset" / "scenes" / "000000").mkdir(parents=True)
    (tmp_path / "reconstruction").mkdir()
    (tmp_path / "tracks").mkdir()
    write_image(tmp_path / "dataset" / "scenes" / "000000" / "sheet.png", np.zeros((8, 8, 3), np.uint8))
    write_image(tmp_path / "reconstruction" / "trajectory.png", np.zeros((8, 8, 3), np.uint8))
    write_video(tmp_path / "tracks" / "overlay.mp4", np.full((T, H, W, 3), 40, np.uint8), 12.0)
    moving = np.zeros((T, 10), np.float32)
    moving[most_moving] = 1.0
    np.savez(tmp_path / "tracks" / "tracks.npz", moving=moving, visible=np.ones((T, 10), bool))
    picture = np.asarray(Image.open(readme_pictures(tmp_path) / "tracks.png").convert("RGB"))
    white = (picture == 255).all(axis=(0, 2))  # the gap columns between panels
    gaps = int((white[1:] & ~white[:-1]).sum())
    assert gaps + 1 == 3 and picture.shape[1] == 3 * W + 2 * 2


def test_ply_picture_has_a_title_and_labelled_world_axes(report):
    out, _ = report
    picture = np.asarray(Image.open(out / "ply.png").convert("RGB"))
    title = picture[:26]
    assert (title == title[0, 0]).mean() > 0.8 and (title.max(axis=-1) > 200).sum() > 100  # white text
    for colour in recon_report.AXIS_COLORS:  # each axis a line of its own colour
        assert (picture[26:] == colour).all(axis=-1).sum() >= 20, colour


def test_flythrough_caption_names_only_what_is_drawn(report):
    out, _ = report
    page = (out / "index.html").read_text()
    assert "orbiting virtual camera" in page and "dark dots" not in page


def test_displacement_axis_has_no_negative_ticks(tmp_path, figures, box_scene):
    plots.track_curves(tmp_path / "tracks.png", box_scene, 16)
    axis = figures[0]["axes"][0]
    low, high = axis.get_ylim()
    ticks = [t for t in axis.yaxis.get_majorticklocs() if low <= t <= high]
    assert low >= 0 and ticks and min(ticks) >= 0


def test_trajectory_is_labelled_with_the_method(report):
    _, figures = report
    legend = figures[0]["legend"]  # the trajectory plot, the report's one figure
    assert legend[0] == "C4D" and "estimated" not in legend
    assert recon_report.method_name({"losses": C4D_LOSSES}) == "C4D"
    assert recon_report.method_name({"losses": GA_ONLY_LOSSES}) == "GA only"
    without_cma = {"stage1": {"ga": [1.0], "cts": [1.0]}, "stage2": {"pts": [1.0]}}
    assert recon_report.method_name({"losses": without_cma}) == "GA + CTS + PTS"


def test_a_compared_ga_only_run_keeps_its_name_beside_c4d(tmp_path, figures, box_scene):
    recon = write_scene_reconstruction(box_scene, tmp_path / "c4d")
    rec_ga = random_reconstruction(np.random.default_rng(1), t=box_scene.num_frames)
    rec_ga.report = {"losses": GA_ONLY_LOSSES}
    ga = write_reconstruction(rec_ga, tmp_path / "ga")
    recon_report.build_recon_report(ga, tmp_path / "out", QUICK_INSPECT, compare={"C4D": recon})
    assert figures[-1]["legend"][:2] == ["C4D", "GA only"]  # the compared run, then this one
    assert "(GA only, red)" in (tmp_path / "out" / "index.html").read_text()


# --- messages ------------------------------------------------------------------------------------


def test_static_point_fallbacks_are_one_line_once_with_the_cut_marked(caplog):
    from c4d_pipeline.flow import build_flow
    from c4d_pipeline.ground_truth import oracle_tracks
    from c4d_pipeline.motion_mask import LISTED_PAIRS, correspondence_motion_masks

    scene = make_box_scene(num_frames=8, height=48, width=64, num_tracks=100, seed=11)
    pairs = [(i, j) for i in range(8) for j in range(8) if 0 < abs(i - j) <= 2]  # 26 pairs
    flows = build_flow("gt", scene=scene).flow(scene.rgb, pairs)
    tracks = oracle_tracks(scene)
    tracks.moving = np.ones_like(tracks.moving)  # no static point: every pair falls back
    with caplog.at_level(logging.WARNING, logger="c4d_pipeline.motion_mask"):
        correspondence_motion_masks(tracks, flows, pairs)
        correspondence_motion_masks(tracks, flows, pairs)  # a second run on the same video
        correspondence_motion_masks(tracks, flows[:3], pairs[:3])  # a short one: all listed
    lines = [r.getMessage() for r in caplog.records if "static points" in r.getMessage()]
    assert len(lines) == 2, lines
    assert lines[0].startswith(f"{len(pairs)} of {len(pairs)} pairs had fewer than 16 static points")
    assert lines[0].endswith(": " + ", ".join(map(str, pairs[:LISTED_PAIRS])) + ", ...")
    assert lines[1].endswith(": (0, 1), (0, 2), (1, 0)")


def test_pointmap_training_line_says_what_it_prints(tmp_path, caplog):
    from c4d_pipeline.pointmap_training import train_pointmap_net
    from tests.test_pointmap_training import _cfg, _log

    with caplog.at_level(logging.INFO, logger="c4d_pipeline.pointmap_training"):
        train_pointmap_net(_cfg(tmp_path, "train.steps=4", "train.log_every=2"))
    printed = [r.getMessage() for r in caplog.records if r.getMessage().startswith("pointmaps step")]
    logged = _log(tmp_path)
    assert [line["step"] for line in logged] == [2, 4] and len(printed) == 2
    for line, message in zip(logged, printed):
        assert f"regression {line['regression']:.4f} (this step, as in log.jsonl;" in message
        assert "mean of the last 2 steps" in message


def test_view_counts_frames_from_0_in_help(capsys):
    with pytest.raises(SystemExit):
        main(["view", "--help"])
    assert "counted from 0" in " ".join(capsys.readouterr().out.split())


@pytest.mark.browser
def test_view_page_counts_frames_from_0_as_frame_does(tmp_path, box_scene):
    from c4d.view import browser as chromium
    from c4d_core.errors import UserError

    try:
        chromium.find_browser()
    except UserError as exc:
        pytest.skip(f"no browser for the browser tests: {exc}")
    recon = write_scene_reconstruction(box_scene, tmp_path / "recon")
    assert main(["view", str(recon), "--save", str(tmp_path / "view.html")]) == 0
    with chromium.Browser(640, 480) as browser:
        page = browser.open((tmp_path / "view.html").as_uri())
        chromium.wait_for_view(page)
        page.evaluate("c4dView.setFrame(3)")
        label = page.evaluate("document.getElementById('frame-label').textContent")
    assert label.startswith(f"frame 3 of 0-{box_scene.num_frames - 1}"), label


def test_a_square_video_cropped_to_4_3_says_so(tmp_path, caplog):
    from c4d_pipeline.video_input import load_video_input

    frames = np.random.default_rng(0).integers(0, 256, (2, 64, 64, 3), dtype=np.uint8)
    for t, frame in enumerate(frames):
        write_image(tmp_path / f"{t:03d}.png", frame)
    with caplog.at_level(logging.INFO, logger="c4d_pipeline.video_input"):
        video = load_video_input(tmp_path, size=512)
        load_video_input(tmp_path, size=224)  # 224 keeps the centre square: nothing to say
    assert video.frames.shape[1:3] == (384, 512)
    lines = [r.getMessage() for r in caplog.records if "cropped" in r.getMessage()]
    assert lines == ["square 64x64 frames cropped to 4:3: the source's box x 0-64, y 8-56, network "
                     "frames 512x384 (DUSt3R's rule for a square input at size 512)"]


def test_eval_markdown_beats_all_static_only_above_the_interval(tmp_path):
    from dynpt.evaluate import signed, write_report

    assert [signed(v) for v in (-0.04, 0.0, -0.0, 0.04, -0.06)] == ["+0.0", "+0.0", "+0.0", "+0.0", "-0.1"]

    def run(rights, d_acc=None):
        per_video = [{"name": f"v{k}", "d_acc_right": r, "d_acc_counted": 10} for k, r in enumerate(rights)]
        return {"summary": {"d_acc": d_acc or sum(rights) / 30, "num_videos": 3}, "per_video": per_video}

    _, even = write_report(run([9, 5, 7], d_acc=0.7 - 1e-4), run([8, 6, 7]), tmp_path / "even", "val", {})
    text = even.read_text()  # a difference of -0.01 points, an interval around 0
    assert "-0.0" not in text and "all-static: +0.0 points" in text and "within the variation" in text
    _, better = write_report(run([9, 9, 9]), run([5, 6, 4]), tmp_path / "better", "val", {})
    assert "so it beats all-static" in better.read_text()


def test_ctrl_c_on_two_training_processes_ends_in_one_line_without_a_traceback(tmp_path):
    from tests.dynpt_testdata import synthetic_shards
    from tests.test_faults import ENV, ROOT, TRAIN, wait_for

    out = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "c4d", "train", "--nproc-per-node", "2", *TRAIN,
         f"data.sources=[{synthetic_shards(12, 3)}]", f"train.out_dir={out}", "train.steps=100000"],
        env=ENV, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=_own_group_with_ctrl_c)
    try:
        wait_for(lambda: (out / "log.jsonl").exists() or proc.poll() is not None, 200, "training")
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C in a terminal: the whole process group
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err and err.rstrip().splitlines()[-1] == "c4d: interrupted", err[-3000:]


def _own_group_with_ctrl_c() -> None:
    """In the child before exec: a process group of its own (the test signals it, not pytest) and
    Ctrl-C's default action (a run started in the background inherits SIGINT ignored)."""
    os.setpgrp()
    signal.signal(signal.SIGINT, signal.SIG_DFL)
