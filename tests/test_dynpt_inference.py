"""Tracker API, query sampling, video reading/writing and `c4d track` end to end."""

import math

import cv2
import numpy as np
import pytest
import torch

from c4d.cli import main
from c4d_core.errors import UserError
from dynpt.checkpoint import save_checkpoint
from dynpt.inference import Tracker, load_tracker
from dynpt.query_sampling import sample_queries
from dynpt.refine import TrackRefinement, refine_tracks
from c4d_core.video import read_video, write_video
from test_dynpt_model import make_model


def smooth_video(T=7, H=41, W=57, seed=0):
    """uint8 (T,H,W,3): a textured pattern drifting right by 1 px per frame."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    freqs = rng.uniform(0.1, 0.4, size=(3, 2))
    frames = [
        np.stack([np.sin(fx * (xx - t) + 2 * c) * np.cos(fy * yy) for c, (fx, fy) in enumerate(freqs)], -1)
        for t in range(T)
    ]
    return ((np.stack(frames) + 1) * 127.5).astype(np.uint8)


@pytest.fixture(scope="module")
def tracker():
    return Tracker(make_model(seed=1), "cpu")


def test_track_outputs_for_grid_sampling(tracker):
    video = smooth_video()
    result = tracker.track(video, grid_size=20, seed=3)
    N = 2 * 3 * 3  # 3 x 3 cells of 20 px on 41 x 57 (partial cells count), two points each
    assert result.queries.shape == (N, 3) and (result.queries[:, 0] == 0).all()
    assert result.tracks.shape == (7, N, 2) and result.tracks.dtype == np.float32
    assert result.visible.shape == (7, N) and result.visible.dtype == bool
    assert result.confidence.shape == result.moving.shape == (7, N)
    assert ((result.moving >= 0) & (result.moving <= 1)).all()
    np.testing.assert_array_equal(result.tracks[0], result.queries[:, 1:])  # exact at the query frame
    assert result.visible[0].all()
    again = tracker.track(video, grid_size=20, seed=3)
    np.testing.assert_array_equal(result.tracks, again.tracks)  # deterministic
    chunked = tracker.track(video, grid_size=20, seed=3, max_points=5)  # 4 groups tracked apart
    assert chunked.tracks.shape == result.tracks.shape
    np.testing.assert_array_equal(chunked.tracks[0], result.tracks[0])
    single = tracker.track(video, result.queries[5:10])
    np.testing.assert_allclose(chunked.tracks[:, 5:10], single.tracks, atol=1e-5)


def test_later_queries_are_tracked_both_ways(tracker):
    video = smooth_video(T=10)
    queries = np.array([[0, 10.0, 12.0], [6, 30.5, 20.0], [9, 56.0, 40.0]], np.float32)
    both = tracker.track(video, queries)
    assert np.isfinite(both.moving).all() and np.isfinite(both.tracks).all()
    for n, (t, x, y) in enumerate(queries):
        assert tuple(both.tracks[int(t), n]) == (x, y) and both.visible[int(t), n]
    forward = tracker.track(video, queries, backward=False)
    assert np.isnan(forward.moving[:6, 1]).all() and not forward.visible[:6, 1].any()
    after = np.arange(10)[:, None] >= queries[:, 0]  # (T,N) frames from each query frame on
    np.testing.assert_array_equal(forward.tracks[after], both.tracks[after])  # forward part unchanged
    assert not np.array_equal(forward.tracks[:6, 1], both.tracks[:6, 1])


def test_resizing_to_the_model_resolution_maps_coordinates_back():
    model = make_model("model.resolution=[32,48]", seed=1)
    result = Tracker(model, "cpu").track(smooth_video(T=5, H=64, W=96), np.array([[1, 50.0, 30.0]], np.float32))
    assert result.tracks.shape == (5, 1, 2)
    assert tuple(result.tracks[1, 0]) == (50.0, 30.0)
    assert np.abs(result.tracks[:, 0] - [50.0, 30.0]).max() < 20  # input pixels, not model pixels


@pytest.mark.parametrize(
    "video, queries, message",
    [
        (np.zeros((0, 20, 20, 3), np.uint8), None, "0 frame"),
        (np.zeros((1, 20, 20, 3), np.uint8), None, "at least 2"),
        (np.zeros((4, 20, 20), np.uint8), None, "RGB"),
        (np.zeros((4, 20, 20, 4), np.uint8), None, "RGB"),
        (np.zeros((4, 20, 20, 3), np.float32), None, "uint8"),
        (np.zeros((4, 20, 20, 3), np.uint8), [[0, 25.0, 5.0]], "outside"),
        (np.zeros((4, 20, 20, 3), np.uint8), [[0, 5.0, -3.0]], "outside"),
        (np.zeros((4, 20, 20, 3), np.uint8), [[4, 5.0, 5.0]], "frame index"),
        (np.zeros((4, 20, 20, 3), np.uint8), [[1.5, 5.0, 5.0]], "frame index"),
        (np.zeros((4, 20, 20, 3), np.uint8), [[1, 5.0]], r"\(N,3\)"),
    ],
)
def test_bad_input_is_a_user_error(tracker, video, queries, message):
    with pytest.raises(UserError, match=message):
        tracker.track(video, None if queries is None else np.array(queries, np.float32))


def test_query_sampling_finds_the_edge_and_is_seeded():
    frame = np.zeros((40, 60, 3), np.uint8)
    frame[:, 33:] = 255  # one vertical edge, in the middle cell column
    q = sample_queries(frame, grid_size=20, seed=0, frame_index=2)
    assert q.shape == (2 * 2 * 3, 3) and (q[:, 0] == 2).all()
    max_points, random_points = q[0::2, 1:], q[1::2, 1:]
    middle = max_points.reshape(2, 3, 2)[:, 1]
    assert np.all(np.abs(middle[:, 0] - 32.5) <= 1)  # the max-gradient point sits on the edge
    cells = (random_points // 20).reshape(2, 3, 2)
    assert np.array_equal(cells[..., 0], [[0, 1, 2]] * 2) and np.array_equal(cells[..., 1], [[0] * 3, [1] * 3])
    assert np.array_equal(q, sample_queries(frame, 20, seed=0, frame_index=2))
    assert not np.array_equal(q, sample_queries(frame, 20, seed=1, frame_index=2))


def test_video_round_trip_and_errors(tmp_path):
    video = smooth_video(T=6, H=40, W=56)
    path = write_video(tmp_path / "v.mp4", video, fps=10)
    back = read_video(path)
    assert back.shape == video.shape and back.dtype == np.uint8
    error = np.abs(back.astype(int) - video).mean()  # lossy codec at a tiny size, same content:
    assert error < 15 and error < 0.3 * np.abs(back.astype(int) - video[::-1]).mean()
    assert read_video(path, stride=2, max_frames=2).shape == (2, 40, 56, 3)
    folder = tmp_path / "frames"
    folder.mkdir()
    import cv2

    for t in range(6):  # names that sort wrongly as text: 2 < 10 only numerically
        cv2.imwrite(str(folder / f"f{t * 4}.png"), video[t][..., ::-1])
    np.testing.assert_array_equal(read_video(folder), video)  # lossless, natural order
    np.testing.assert_array_equal(read_video(folder, stride=3), video[::3])
    (tmp_path / "empty.mp4").write_bytes(b"")
    (tmp_path / "junk.mp4").write_bytes(np.random.default_rng(0).bytes(5000))
    (tmp_path / "truncated.mp4").write_bytes(path.read_bytes()[:300])
    (tmp_path / "nothing").mkdir()
    for bad, message in [("missing.mp4", "does not exist"), ("empty.mp4", "is not a video: it is an empty file"),
                         ("junk.mp4", "cannot open|no frame"), ("truncated.mp4", "cannot open|no frame"),
                         ("nothing", "no images")]:
        with pytest.raises(UserError, match=message):
            read_video(tmp_path / bad)


def test_c4d_track_end_to_end(tmp_path, capsys):
    video_path = write_video(tmp_path / "clip.mp4", smooth_video(T=6, H=40, W=56), fps=10)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", make_model(seed=2), step=5)
    out = tmp_path / "out"
    assert main(["track", str(video_path), "--ckpt", str(ckpt), "--out", str(out), "--grid-size", "20"]) == 0
    data = np.load(out / "tracks.npz")
    assert data["tracks"].shape == (6, 12, 2) and data["visible"].dtype == bool
    assert data["moving"].shape == data["confidence"].shape == (6, 12)
    overlay = read_video(out / "overlay.mp4")
    assert overlay.shape == (6, 280 + 26, 392, 3)  # enlarged 7x to at least 256 rows, + the key strip
    fused = tmp_path / "fused"  # the same tracks, the head fused with their epipolar geometry
    assert main(["track", str(video_path), "--ckpt", str(ckpt), "--out", str(fused), "--grid-size", "20",
                 "--mobility", "epipolar"]) == 0
    other = np.load(fused / "tracks.npz")
    np.testing.assert_array_equal(other["tracks"], data["tracks"])
    assert ((other["moving"] >= 0) & (other["moving"] <= 1)).all()  # fusion: tests/test_track_mobility.py
    refined = tmp_path / "refined"  # the tracks refined by Lucas-Kanade, the same visibility
    assert main(["track", str(video_path), "--ckpt", str(ckpt), "--out", str(refined), "--grid-size", "20",
                 "--refine", "lk"]) == 0
    other = np.load(refined / "tracks.npz")
    expected, _ = refine_tracks(read_video(video_path), data["tracks"], data["visible"],
                                data["queries"], TrackRefinement())  # how: tests/test_refine.py
    np.testing.assert_array_equal(other["tracks"], expected)
    np.testing.assert_array_equal(other["visible"], data["visible"])
    np.testing.assert_array_equal(other["moving"], data["moving"])
    queries = tmp_path / "q.txt"
    np.savetxt(queries, [[2, 10, 10], [0, 30, 20]])
    assert main(["track", str(video_path), "--ckpt", str(ckpt), "--out", str(out), "--queries", str(queries)]) == 0
    assert np.load(out / "tracks.npz")["tracks"].shape == (6, 2, 2)
    capsys.readouterr()
    assert main(["track", str(video_path), "--ckpt", str(tmp_path / "none.pt"), "--out", str(out)]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert load_tracker(ckpt).model.config["window_len"] == 8


def test_unknown_or_missing_device_is_a_user_error():
    with pytest.raises(UserError, match="unknown device"):
        Tracker(make_model(), "tpu:7")
    if not torch.cuda.is_available():
        with pytest.raises(UserError, match="no CUDA"):
            Tracker(make_model(), "cuda")


def test_track_sizes_point_budget_and_source_fps(tmp_path):
    """`--max-size` shrinks the working frames, tracks.npz stays in source pixels, `--points`
    widens the query grid, and the overlay keeps the source frame rate over the stride."""
    from dynpt.cli_track import grid_for_budget

    video_path = write_video(tmp_path / "clip.mp4", smooth_video(T=6, H=40, W=80), fps=10)
    ckpt = save_checkpoint(tmp_path / "tiny.pt", make_model(seed=2), step=5)
    out = tmp_path / "out"
    assert main(["track", str(video_path), "--ckpt", str(ckpt), "--out", str(out), "--max-size", "40",
                 "--grid-size", "5", "--points", "8", "--stride", "2"]) == 0
    data = np.load(out / "tracks.npz")
    assert data["tracks"].shape[0] == 3 and 0 < data["tracks"].shape[1] <= 8
    assert data["queries"][:, 1].max() > 40  # source pixels (80 wide), not working ones
    capture = cv2.VideoCapture(str(out / "overlay.mp4"))
    assert capture.get(cv2.CAP_PROP_FPS) == pytest.approx(5, abs=0.1)
    capture.release()
    assert grid_for_budget(720, 1296, 20, None) == 20
    cell = grid_for_budget(720, 1296, 20, 1000)
    def count(c):
        return 2 * math.ceil(720 / c) * math.ceil(1296 / c)
    assert count(cell) <= 1000 < count(cell - 1)
    assert main(["track", str(video_path), "--ckpt", str(ckpt), "--out", str(out), "--size", "4"]) == 2


def test_track_accepts_a_video_path(tmp_path):
    video_path = write_video(tmp_path / "clip.mp4", smooth_video(T=5, H=32, W=32), fps=10)
    result = Tracker(make_model()).track(str(video_path), grid_size=16)
    assert result.tracks.shape == (5, 8, 2)


def test_working_size_is_range_checked_and_optional():
    """--size/--max-size: unchanged without either, refused outside 8..4096 (a huge size once
    ended in an out-of-memory traceback), never enlarged by --max-size."""
    from c4d_core.video import resize_long_side

    video = np.zeros((2, 5, 6, 3), np.uint8)
    assert resize_long_side(video) is video  # the tracker names its own minimum frame size
    for size in (7, 100000):
        with pytest.raises(UserError, match=f"{size} is out of range; give 8 to 4096"):
            resize_long_side(video, size=size)
    assert resize_long_side(np.zeros((2, 20, 40, 3), np.uint8), size=20).shape == (2, 10, 20, 3)
    assert resize_long_side(np.zeros((2, 20, 40, 3), np.uint8), max_size=80).shape == (2, 20, 40, 3)
