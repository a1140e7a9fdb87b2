"""`c4d inspect` on reconstruction directories: reading, checks, pictures, fly-through, CLI."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from c4d.cli import main
from c4d.inspect import point_render, recon_report
from c4d_core import geometry
from c4d_pipeline import outputs
from c4d_pipeline.ground_truth import ground_truth_motion_masks
from tests.synthetic_scenes import make_box_scene
from datagen import shards
from datagen.scene import Scene


def write_reconstruction(scene: Scene, out: Path, masks: np.ndarray | None = None) -> Path:
    """A reconstruction directory written by `c4d run`'s writer, holding the scene's ground truth
    (or the motion `masks` (T,H,W) given)."""
    points = np.stack([geometry.unproject_depth_map(d, k, p) for d, k, p in
                       zip(scene.depth, scene.intrinsics, scene.cam_to_world)]).astype(np.float32)
    queries = np.concatenate([scene.query_frame[:, None],
                              scene.tracks[np.arange(scene.num_tracks), scene.query_frame]], -1)  # (N,3)
    rec = outputs.Reconstruction(
        frames=scene.rgb, depth=scene.depth,
        masks=ground_truth_motion_masks(scene) if masks is None else masks,
        cam_to_world=scene.cam_to_world, intrinsics=scene.intrinsics, points=points,
        confidence=np.ones(points.shape[:3], np.float32),
        tracks_2d={"tracks": scene.tracks.transpose(1, 0, 2), "visible": ~scene.occluded.T,
                   "moving": scene.moving.T.astype(np.float32), "queries": queries},
        tracks_world=scene.tracks_world.transpose(1, 0, 2), tracks_valid=~scene.occluded.T,
        report={"inputs": {"frame_indices": list(range(scene.num_frames))}, "seconds": {"optimise": 1.5}},
    )
    return outputs.write_reconstruction(rec, out, ply_pixel_stride=1)


@pytest.fixture(scope="module")
def box_scene() -> Scene:
    return make_box_scene(num_frames=8, height=48, width=64, num_tracks=48, seed=3)


@pytest.fixture(scope="module")
def recon_dir(tmp_path_factory, box_scene) -> Path:
    return write_reconstruction(box_scene, tmp_path_factory.mktemp("recon"))


def _not_blank(image: np.ndarray) -> bool:
    return image.std() > 5 and len(np.unique(image.reshape(-1, 3), axis=0)) > 10


def test_reading_a_complete_reconstruction_finds_no_problem(recon_dir, box_scene):
    recon = outputs.read_reconstruction(recon_dir, strict=False)
    assert recon.problems == []
    assert outputs.is_reconstruction(recon_dir)
    np.testing.assert_allclose(recon.cam_to_world, box_scene.cam_to_world, atol=1e-5)
    assert recon.frames.shape == box_scene.rgb.shape and recon.masks.any()
    assert len(recon.ply_points) > 1000 and recon.ply_colors.std() > 0


def test_broken_parts_become_problems_not_crashes(tmp_path, recon_dir):
    broken = tmp_path / "broken"
    broken.mkdir()
    for item in recon_dir.iterdir():
        target = broken / item.name
        if item.is_dir():
            target.mkdir()
            for f in item.iterdir():
                (target / f.name).write_bytes(f.read_bytes())
        else:
            target.write_bytes(item.read_bytes())
    (broken / "scene.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 9")
    np.save(broken / "depth/000003.npy", np.full((48, 64), np.nan, np.float32))
    (broken / "masks/000007.png").unlink()
    problems = " | ".join(outputs.read_reconstruction(broken, strict=False).problems)
    assert "scene.ply cannot be read" in problems
    assert "depth has" in problems and "NaN" in problems
    assert "frame counts disagree" in problems and "'masks': 7" in problems
    assert main(["inspect", str(broken), "--check"]) == 1
    assert main(["inspect", str(recon_dir), "--check"]) == 0


def test_point_splatter_keeps_the_nearest_point_and_projects_like_the_camera():
    k = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    pose = geometry.look_at(np.array([0.0, -5, 0]), np.zeros(3), np.array([0.0, 0, 1]))
    points = np.array([[0.0, 1, 0], [0.0, 0, 0], [1.0, 0, 0]])  # green behind red on one ray
    colors = np.array([[0, 255, 0], [255, 0, 0], [0, 0, 255]], np.uint8)
    image = point_render.render_points(points, colors, k, pose, (48, 64), radius=1)
    np.testing.assert_array_equal(image[23:26, 31:34].reshape(-1, 3).max(0), (255, 0, 0))
    uv, _ = geometry.project(points[2], k, pose)
    np.testing.assert_array_equal(image[int(round(uv[1])), int(round(uv[0]))], (0, 0, 255))
    assert (image == 255).all(-1).sum() > 48 * 64 - 3 * 9, "background stays white"
    assert not (image == (0, 255, 0)).all(-1).any()


def test_report_writes_videos_plots_and_a_page(tmp_path, recon_dir, box_scene):
    gt_dir = tmp_path / "gt"
    gt_dir.mkdir()
    with shards.ShardWriter(gt_dir / "test-000000.tar") as writer:
        writer.write(shards.encode_scene(box_scene, shards.scene_key("test", 0)))
    out = tmp_path / "report"
    assert main(["inspect", str(recon_dir), "flythrough.min_views=20", "flythrough.views_per_frame=1",
                 "--out", str(out), "--gt", str(gt_dir), "--no-progress",
                 "--compare", f"GA only={recon_dir}"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["problems"] == []
    assert summary["pose_errors"]["ate"] < 1e-3, "ground truth poses align onto themselves"
    assert summary["pose_errors_compared"]["GA only"]["ate"] < 1e-3  # the same folder, compared
    for name in ("overview.webm", "depth.webm", "masks.webm", "flythrough.webm", "trajectory.png",
                 "flythrough.png", "ply.png", "index.html"):
        assert (out / name).is_file(), name
    from c4d_core.video import read_video

    overview = read_video(out / "overview.webm")
    assert overview.shape[0] == 8 and overview.shape[1] >= 192 and _not_blank(overview[0])
    flythrough = read_video(out / "flythrough.webm")
    assert len(flythrough) == 20 and _not_blank(flythrough[0])
    assert not np.array_equal(flythrough[0], flythrough[5]), "the virtual camera moves"
    ply = cv2.imread(str(out / "ply.png"))
    assert ply.shape == (26 + 384, 384, 3) and _not_blank(ply)  # a title above the rendered points
    page = (out / "index.html").read_text()
    assert "flythrough.webm" in page and "trajectory.png" in page
    assert "Reconstruction of " in page and "scene 0" in page  # the title names the scene, not a path
    cells = re.findall(r"<td>(.*?)</td>", page)
    assert cells and not any("{" in c or "&#x27;" in c for c in cells), "formatted, not dict reprs"


def test_mask_errors_picture_shows_hits_false_alarms_and_misses_in_the_legend_colours(tmp_path, box_scene):
    """mask_errors.png paints each frame's true positives, false positives and false negatives in
    the key's colours, one pixel block per mask pixel, and its counts give the IoU that
    `c4d eval-recon` computes."""
    from c4d_pipeline.eval_metrics import mask_iou

    truth = ground_truth_motion_masks(box_scene)  # (T,H,W)
    assert truth.any()
    predicted = np.roll(truth, 3, axis=2)  # shifted right: misses on the left, false alarms on the right
    predicted[:, :6, :10] = True  # and a false block in a corner
    recon = write_reconstruction(box_scene, tmp_path / "recon", masks=predicted)
    gt_dir = tmp_path / "gt"
    gt_dir.mkdir()
    with shards.ShardWriter(gt_dir / "test-000000.tar") as writer:
        writer.write(shards.encode_scene(box_scene, shards.scene_key("test", 0)))
    out = tmp_path / "report"
    assert main(["inspect", str(recon), "--out", str(out), "--gt", str(gt_dir), "--no-progress",
                 "flythrough.min_views=4", "flythrough.views_per_frame=1"]) == 0
    summary = json.loads((out / "summary.json").read_text())["mask_vs_truth"]
    expected = {"true_positive": int((predicted & truth).sum()), "false_positive": int((predicted & ~truth).sum()),
                "false_negative": int((~predicted & truth).sum())}
    assert {k: summary[k] for k in expected} == expected and min(expected.values()) > 0
    assert summary["iou"] == pytest.approx(mask_iou(predicted, truth)["iou"])
    assert summary["iou"] == pytest.approx(expected["true_positive"] / sum(expected.values()))
    assert summary["dynamic_fraction"] == pytest.approx(truth.mean())

    picture = cv2.cvtColor(cv2.imread(str(out / "mask_errors.png")), cv2.COLOR_BGR2RGB)
    body, key = picture[:-26], picture[-26:]  # the colour key is the bottom strip
    factor = recon_report.draw.display_scale(box_scene.image_size[0], 192 // 2)
    legend = np.zeros(body.shape[:2], bool)
    for name, color in recon_report.MASK_ERROR_COLORS.items():
        painted = (body == color).all(-1)
        assert painted.sum() == factor**2 * expected[name.replace(" ", "_")], name
        assert (key == color).all(-1).any(), f"{name} is in the key"
        legend |= painted
    others = body[~legend]
    assert (others.max(-1) == others.min(-1)).all(), "everything else is grey"
    page = (out / "index.html").read_text()
    assert "mask_errors.png" in page and "false negative" in page
