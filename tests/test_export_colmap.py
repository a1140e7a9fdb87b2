"""`c4d export colmap RECON OUT`: a reconstruction as COLMAP's text model, read back by a reader
written here from COLMAP's format alone (docs: colmap.github.io/format.html), not ours."""

import logging

import numpy as np

from c4d.cli import main
from c4d_core import geometry
from c4d_core.ownership import folder_kind
from c4d_pipeline.colmap import MAX_POINTS, static_pixels
from c4d_pipeline.ground_truth import ground_truth_motion_masks
from c4d_pipeline.outputs import Reconstruction, write_reconstruction
from tests.synthetic_scenes import make_box_scene


def reconstruction(path, all_dynamic=False):
    """A generated scene's truth written as a reconstruction: 5 frames of 24 x 32 pixels, world
    pointmaps from its depth, poses and intrinsics (a different focal length in the last frame)."""
    scene = make_box_scene(num_frames=5, height=24, width=32, num_tracks=8, seed=3)
    intrinsics = scene.intrinsics.astype(np.float32).copy()
    intrinsics[-1, 0, 0] *= 1.25
    points = np.stack([geometry.unproject_depth_map(d, k, p) for d, k, p
                       in zip(scene.depth, intrinsics, scene.cam_to_world)]).astype(np.float32)
    masks = ground_truth_motion_masks(scene)
    rec = Reconstruction(
        frames=scene.rgb, depth=scene.depth.astype(np.float32),
        masks=np.ones_like(masks) if all_dynamic else masks,
        cam_to_world=scene.cam_to_world.astype(np.float32), intrinsics=intrinsics,
        points=points, confidence=np.ones(scene.depth.shape, np.float32))
    write_reconstruction(rec, path)
    return rec


def data_lines(path):
    """The lines of a COLMAP text file, comments left out (empty lines kept: POINTS2D may be)."""
    return [line.strip() for line in path.read_text().splitlines() if not line.startswith("#")]


def quaternion_matrix(qw, qx, qy, qz):
    """Hamilton unit quaternion -> 3x3 rotation, as COLMAP's Eigen::Quaterniond."""
    return np.array([
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
        [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
        [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)]])


def read_text_model(folder):
    """COLMAP's cameras.txt, images.txt and points3D.txt as dicts keyed by their 1-based ids."""
    cameras = {}
    for line in data_lines(folder / "cameras.txt"):
        cid, model, width, height, *params = line.split()
        cameras[int(cid)] = (model, int(width), int(height), [float(p) for p in params])
    images, lines = {}, data_lines(folder / "images.txt")
    for image_line, points_line in zip(lines[::2], lines[1::2]):
        iid, qw, qx, qy, qz, tx, ty, tz, cid, name = image_line.split()
        rest = points_line.split()
        images[int(iid)] = dict(
            rotation=quaternion_matrix(*map(float, (qw, qx, qy, qz))),
            translation=np.array([float(tx), float(ty), float(tz)]), camera=int(cid), name=name,
            points2d=[(float(x), float(y), int(p)) for x, y, p in zip(rest[::3], rest[1::3], rest[2::3])])
    points = {}
    for line in data_lines(folder / "points3D.txt"):
        pid, x, y, z, r, g, b, error, *track = line.split()
        points[int(pid)] = dict(xyz=np.array([float(x), float(y), float(z)]),
                                rgb=(int(r), int(g), int(b)), error=float(error),
                                track=[(int(i), int(j)) for i, j in zip(track[::2], track[1::2])])
    return cameras, images, points


def test_the_text_model_holds_the_poses_intrinsics_and_static_points(tmp_path, caplog):
    rec = reconstruction(tmp_path / "recon")
    with caplog.at_level(logging.INFO):
            assert main(["export", "colmap", str(tmp_path / "recon"), str(tmp_path / "colmap"),
                     "--stride", "3"]) == 0
    assert folder_kind(tmp_path / "colmap") == "export-colmap"
    cameras, images, points = read_text_model(tmp_path / "colmap")

    num_frames, height, width = rec.masks.shape
    assert sorted(images) == list(range(1, num_frames + 1))
    assert len(cameras) == 2  # the last frame's focal length differs
    for t in range(num_frames):
        image = images[t + 1]
        assert image["name"] == f"{t:06d}.png" and (tmp_path / "recon/frames" / image["name"]).is_file()
        world_to_cam = np.eye(4)
        world_to_cam[:3, :3], world_to_cam[:3, 3] = image["rotation"], image["translation"]
        np.testing.assert_allclose(np.linalg.inv(world_to_cam), rec.cam_to_world[t], atol=1e-6)
        model, cam_width, cam_height, (fx, fy, cx, cy) = cameras[image["camera"]]
        k = rec.intrinsics[t]
        assert (model, cam_width, cam_height) == ("PINHOLE", width, height)
        np.testing.assert_allclose([fx, fy, cx, cy], [k[0, 0], k[1, 1], k[0, 2] + 0.5, k[1, 2] + 0.5])

    static = int((~rec.masks).sum())
    assert 0 < len(points) == len(range(0, static, 3)) < static
    assert sorted(points) == list(range(1, len(points) + 1))
    for pid, point in points.items():
        (iid, idx), = point["track"]
        image = images[iid]
        x, y, seen = image["points2d"][idx]
        assert seen == pid and point["error"] == 0
        col, row = x - 0.5, y - 0.5  # COLMAP's pixel centres -> ours
        assert col == int(col) and row == int(row)
        t, row, col = iid - 1, int(row), int(col)
        assert not rec.masks[t, row, col], "a point on a dynamic pixel"
        np.testing.assert_allclose(point["xyz"], rec.points[t, row, col], rtol=1e-6)
        assert point["rgb"] == tuple(rec.frames[t, row, col])
        # COLMAP's projection of the point lands on its observation: conventions agree
        _, _, _, (fx, fy, cx, cy) = cameras[image["camera"]]
        cam = image["rotation"] @ point["xyz"] + image["translation"]
        np.testing.assert_allclose([fx * cam[0] / cam[2] + cx, fy * cam[1] / cam[2] + cy], [x, y],
                                   atol=1e-3)
    assert sum(len(image["points2d"]) for image in images.values()) == len(points)
    assert f"{len(points)} static points" in caplog.text


def test_the_default_stride_keeps_every_static_point_of_a_small_reconstruction(tmp_path):
    rec = reconstruction(tmp_path / "recon")
    assert main(["export", "colmap", str(tmp_path / "recon"), str(tmp_path / "colmap")]) == 0
    assert len(read_text_model(tmp_path / "colmap")[2]) == int((~rec.masks).sum())


def test_a_reconstruction_without_static_points_is_one_line(tmp_path, capsys):
    reconstruction(tmp_path / "recon", all_dynamic=True)
    assert main(["export", "colmap", str(tmp_path / "recon"), str(tmp_path / "colmap")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [err] and "no static points" in err
    assert not (tmp_path / "colmap").exists()


def test_the_output_folder_is_claimed_and_the_dataset_forms_stay_with_datagen(tmp_path, capsys):
    reconstruction(tmp_path / "recon")
    assert main(["export", "colmap", str(tmp_path / "recon"), str(tmp_path / "recon")]) == 2
    assert "is a reconstruction made by `c4d run`; `c4d export colmap` does not write into it" \
        in capsys.readouterr().err
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("kept")
    assert main(["export", "colmap", str(tmp_path / "recon"), str(mine), "--overwrite"]) == 2
    assert "files that c4d did not write" in capsys.readouterr().err
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]
    assert main(["export", "kubric", str(tmp_path / "recon"), str(tmp_path / "kubric")]) == 2
    assert "colmap" not in capsys.readouterr().err  # a dataset export: datagen's refusal


def test_the_default_stride_keeps_at_most_max_points():
    masks = np.zeros((3, 240, 320), bool)  # 230 400 static pixels
    masks[1, :120] = True  # less the top half of the middle frame: 192 000
    points = np.zeros((3, 240, 320, 3), np.float32)
    points[2, 0, :10] = np.nan  # 10 pixels without a point
    chosen = static_pixels(masks, points)
    assert len(chosen) == len(range(0, 192_000 - 10, 2)) <= MAX_POINTS
    assert not masks.reshape(-1)[chosen].any() and np.isfinite(points.reshape(-1, 3)[chosen]).all()
    assert len(static_pixels(masks, points, stride=1)) == 192_000 - 10


def test_a_bad_stride_is_one_line(tmp_path, capsys):
    assert main(["export", "colmap", str(tmp_path / "recon"), str(tmp_path / "colmap"),
                 "--stride", "0"]) == 2
    assert "--stride must be at least 1" in capsys.readouterr().err
