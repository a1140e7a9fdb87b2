"""c4d_core.draw and c4d_core.video: colour maps, track overlays, layouts and video files."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from c4d_core import draw as vis
from c4d_core import video


def _gray_video(t=4, h=40, w=50, value=128):
    return np.full((t, h, w, 3), value, np.uint8)


def test_draw_tracks_colours_visible_points_by_mobility_and_leaves_input_alone():
    frames = _gray_video()
    tracks = np.zeros((4, 2, 2), np.float32)
    tracks[:, 0] = (10, 10)  # static point
    tracks[:, 1] = (35, 25)  # moving point
    moving = np.array([[False, True]] * 4)
    out = vis.draw_tracks(frames, tracks, moving=moving, radius=3)
    assert out.shape == frames.shape and out.dtype == np.uint8
    assert (frames == 128).all()
    np.testing.assert_array_equal(out[2, 10, 10], vis.STATIC_COLOR)
    np.testing.assert_array_equal(out[2, 25, 35], vis.MOVING_COLOR)
    # probabilities are drawn in the legend's two colours, never a blend of them
    probability = vis.draw_tracks(frames, tracks, moving=np.array([[0.5, 0.6]] * 4), radius=3)
    np.testing.assert_array_equal(probability[0, 10, 10], vis.STATIC_COLOR)
    np.testing.assert_array_equal(probability[0, 25, 35], vis.MOVING_COLOR)


def test_enlarged_tracks_land_on_the_centre_of_their_enlarged_pixel():
    frames = _gray_video()  # (4,H,W,3)
    H, W = frames.shape[1:3]
    tracks = np.zeros((4, 1, 2), np.float32)
    tracks[:, 0] = (7, 5)  # x, y
    out = vis.draw_tracks_enlarged(frames, tracks, moving=np.ones((4, 1)), min_height=3 * H + 1, radius=2)
    assert out.shape == (4, 4 * H, 4 * W, 3)  # factor 4: the smallest reaching 3H+1 rows
    np.testing.assert_array_equal(out[0, 4 * 5 + 1, 4 * 7 + 2], vis.MOVING_COLOR)  # centre 29.5, 21.5
    assert (out[0, 0, 0] == 128).all()
    same = vis.draw_tracks_enlarged(frames, tracks, moving=np.ones((4, 1)), min_height=H, radius=2)
    np.testing.assert_array_equal(same, vis.draw_tracks(frames, tracks, moving=np.ones((4, 1)), radius=2))


def test_occluded_points_are_hollow_rings_or_hidden():
    frames = _gray_video()
    tracks = np.full((4, 1, 2), 20.0, np.float32)
    visible = np.zeros((4, 1), bool)
    ring = vis.draw_tracks(frames, tracks, visible, np.zeros((4, 1)), radius=6)
    assert (ring[1, 20, 20] == 128).all(), "the centre of an occluded point stays empty"
    assert (ring[1, 20, 26] != 128).any(), "the ring is drawn at the radius"
    hidden = vis.draw_tracks(frames, tracks, visible, np.zeros((4, 1)), show_occluded=False)
    np.testing.assert_array_equal(hidden, frames)


def test_trails_and_subpixel_positions():
    frames = _gray_video(t=5)
    tracks = np.stack([np.linspace(5, 45, 5), np.full(5, 20.0)], -1)[:, None].astype(np.float32)
    out = vis.draw_tracks(frames, tracks, trail=4, radius=1.5)
    # the trail at frame 4 passes through x=15..35 on row 20, long after the dot left it
    assert (out[4, 20, 15:36] != 128).any(axis=-1).all()
    assert (out[0, 20, 15:36] == 128).all()
    # a half-pixel shift moves the drawn dot: sub-pixel positions are honoured
    shifted = vis.draw_tracks(frames, tracks + 0.5, radius=3)
    assert not np.array_equal(shifted[0], vis.draw_tracks(frames, tracks, radius=3)[0])


def test_draw_tracks_rejects_point_major_layout():
    with pytest.raises(ValueError, match=r"\(T=4,N,2\)"):
        vis.draw_tracks(_gray_video(), np.zeros((3, 4, 2)))


def test_colorize_depth_near_is_red_invalid_is_black_and_range_is_shared():
    depth = np.full((2, 8, 8), 10.0, np.float32)
    depth[0, :, :4] = 1.0
    depth[1, 0, 0] = 0.0
    depth[1, 0, 1] = np.nan
    rgb = vis.colorize_depth(depth)
    assert rgb.shape == (2, 8, 8, 3) and rgb.dtype == np.uint8
    near, far = rgb[0, 4, 0].astype(int), rgb[0, 4, 7].astype(int)
    assert near[0] > near[2] and far[2] > far[0]
    np.testing.assert_array_equal(rgb[1, 0, :2], 0)
    np.testing.assert_array_equal(rgb[1, 4, 4], rgb[0, 4, 7])  # same depth, same colour over time


def test_colorize_flow_follows_the_standard_wheel():
    flow = np.zeros((1, 4, 2), np.float32)
    flow[0, 1] = (5, 0)  # right
    flow[0, 2] = (-5, 0)  # left
    flow[0, 3] = (2.5, 0)  # right, half as long
    rgb = vis.colorize_flow(flow).astype(int)[0]
    np.testing.assert_array_equal(rgb[0], (255, 255, 255))  # no motion is white
    assert rgb[1, 0] == 255 and rgb[1, 1] < 50 and rgb[1, 2] < 50  # right is red
    assert rgb[2, 0] < 50 and rgb[2, 1] > 200 and rgb[2, 2] > 200  # left is cyan
    assert rgb[3, 1] > rgb[1, 1]  # shorter vectors are paler
    assert vis.colorize_flow(np.full((2, 2, 2), np.nan)).max() == 0


def test_segmentation_palette_is_stable_and_distinct():
    seg = np.array([[0, 1, 2, 3]], np.int32)
    rgb = vis.colorize_segmentation(seg)
    np.testing.assert_array_equal(rgb[0, 0], vis.BACKGROUND_SEGMENT_COLOR)
    assert len({tuple(c) for c in rgb[0]}) == 4
    bigger = vis.colorize_segmentation(np.array([[3, 17]], np.int32))
    np.testing.assert_array_equal(bigger[0, 0], rgb[0, 3])
    assert len({tuple(c) for c in vis.segment_palette(32)}) == 32


def test_layout_helpers_shapes():
    a = np.zeros((3, 20, 30, 3), np.uint8)
    b = np.zeros((3, 10, 10, 3), np.uint8)  # scaled up to height 20 -> width 20
    row = vis.side_by_side([a, b], labels=["a", "b"], gap=2)
    assert row.shape == (3, 20, 30 + 2 + 20, 3)
    assert (row[:, :, 30:32] == 255).all()
    assert (row[:, :, :30] != 0).any(), "labels are written"
    sheet = vis.contact_sheet([np.zeros((8, 12, 3), np.uint8)] * 5, gap=1)
    assert sheet.shape == (2 * 8 + 1, 3 * 12 + 2, 3)


@pytest.mark.parametrize("suffix", [".mp4", ".webm", ".avi", ".gif"])
def test_write_video_round_trip(tmp_path, suffix):
    t = np.arange(5)[:, None, None, None]
    frames = np.broadcast_to(t * 50, (5, 31, 40, 3)).astype(np.uint8).copy()
    frames[:, :, :20, 0] = 255
    path = video.write_video(tmp_path / f"clip{suffix}", frames, fps=5)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"clip{suffix}"]
    decoded = video.read_video(path)
    assert decoded.shape[0] == 5 and decoded.shape[1:3] in ((31, 40), (32, 40))
    np.testing.assert_allclose(
        decoded[:, :31].astype(float).mean(axis=(1, 2, 3)), frames.astype(float).mean(axis=(1, 2, 3)),
        atol=12,
    )


def test_write_user_video_turns_failures_into_one_user_error(tmp_path):
    import dynpt
    from c4d_core.errors import UserError

    with pytest.raises(ValueError, match="unknown video extension '.mov'"):
        video.write_video(tmp_path / "clip.mov", _gray_video())
    with pytest.raises(UserError, match=r"cannot write video '.*clip\.mov': unknown video extension"):
        video.write_user_video(tmp_path / "clip.mov", _gray_video())
    with pytest.raises(UserError, match=r"cannot write video '.*clip\.gif': frames must be uint8"):
        video.write_user_video(tmp_path / "clip.gif", _gray_video().astype(np.float32))
    assert dynpt.write_video is video.write_user_video and dynpt.read_video is video.read_video
    assert list(tmp_path.iterdir()) == []


def test_write_image_rgb_order(tmp_path):
    image = np.zeros((4, 6, 3), np.uint8)
    image[..., 0] = 200
    path = video.write_image(tmp_path / "red.png", image)
    np.testing.assert_array_equal(np.asarray(Image.open(path))[0, 0], (200, 0, 0))
