"""`c4d view`: the page's data against the reconstruction it shows, the page in headless
Chromium (ready, counts drawn, screenshots at two frames, no console errors, nothing fetched),
served, the screenshot command, a 1,000-frame reconstruction thinned to the page budget,
`c4d inspect`'s reports in the same browser, and bad input.

The browser tests (marker `browser`) need Chromium (`make test` installs or finds it, see the
README); where there is none they are skipped with the reason.
"""

from __future__ import annotations

import base64
import json
import re
import shutil
import socket
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from c4d.cli import main
from c4d.view import browser as chromium
from c4d.view import page as view_page
from c4d.view import scene_data
from c4d_core.errors import UserError
from c4d_pipeline.eval_metrics import rotation_angle_deg
from c4d_pipeline.ground_truth import ground_truth_motion_masks
from c4d_pipeline.outputs import read_reconstruction, tum_lines
from datagen import shards
from tests.synthetic_scenes import make_box_scene
from tests.test_inspect_recon import write_reconstruction

T, H, W, N = 8, 48, 64, 48
STRIDE, MAX_POINTS = 2, 500  # 32x24 = 768 grid pixels per frame: the cap thins them
BACKGROUND = (21, 24, 29)  # the page's background, #15181d
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def box_scene():
    return make_box_scene(num_frames=T, height=H, width=W, num_tracks=N, seed=3)


@pytest.fixture(scope="module")
def recon_dir(tmp_path_factory, box_scene) -> Path:
    return write_reconstruction(box_scene, tmp_path_factory.mktemp("view") / "recon")


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory, box_scene) -> Path:
    folder = tmp_path_factory.mktemp("view-data")
    with shards.ShardWriter(folder / "train-000000.tar") as writer:
        writer.write(shards.encode_scene(box_scene, "000000"))
        writer.write(shards.encode_scene(make_box_scene(num_frames=T, height=H, width=W,
                                                        num_tracks=N, seed=4), "000001"))
    return folder


def _moved_copy(recon_dir: Path, out: Path, scale: float, turn: np.ndarray, shift,
                cameras: np.ndarray | None = None) -> Path:
    """A copy of a reconstruction in a frame of its own, as another run's would be: its points and
    cameras (or `cameras` (T,4,4) in place of its own) mapped by x -> scale turn x + shift."""
    shutil.copytree(recon_dir, out)
    recon = read_reconstruction(out)
    poses = np.array(recon.cam_to_world if cameras is None else cameras, np.float64)
    poses[:, :3, :3] = turn @ poses[:, :3, :3]
    poses[:, :3, 3] = scale * poses[:, :3, 3] @ turn.T + shift
    (out / "poses_tum.txt").write_text(tum_lines(poses))
    points = scale * recon.points @ turn.T + np.asarray(shift)
    np.savez_compressed(out / "pointmaps.npz", points=points.astype(np.float32),
                        confidence=recon.confidence)
    return out


@pytest.fixture(scope="module")
def straight_path(tmp_path_factory):
    """(scene, its shard set, estimate, path): a generated movi-e scene, whose camera moves on a
    straight line `path` scene units long, and a reconstruction of it as an estimate comes out:
    every camera turned by about a degree, its centre off the line by about 2% of the path, all
    in a frame of its own (1/20 the size, turned and moved)."""
    folder = tmp_path_factory.mktemp("straight")
    assert main(["datagen", "--preset", "movi-e", "--num-scenes", "1", "--split", "val", "--out",
                 str(folder / "data"), "--resolution", str(W), "--frames", str(T)]) == 0
    scene = next(shards.read_scenes(folder / "data"))
    rng = np.random.default_rng(0)
    cameras = scene.cam_to_world.astype(np.float64)
    path = np.linalg.norm(np.diff(cameras[:, :3, 3], axis=0), axis=-1).sum()
    wobble = Rotation.from_rotvec(np.radians(rng.normal(0, 1, (T, 3)))).as_matrix()  # (T,3,3)
    cameras[:, :3, :3] = wobble @ cameras[:, :3, :3]
    cameras[:, :3, 3] += rng.normal(0, 0.02 * path, (T, 3))
    estimate = _moved_copy(write_reconstruction(scene, folder / "truth"), folder / "recon", 0.05,
                           Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix(), [4.0, -1.0, 2.0], cameras)
    return scene, folder / "data", estimate, path


@pytest.fixture(scope="module")
def browser():
    try:
        chromium.find_browser()
    except UserError as exc:
        pytest.skip(f"no browser for the browser tests: {exc}")
    with chromium.Browser(960, 640) as instance:
        yield instance


def _expected_counts(keep: np.ndarray, dynamic: np.ndarray) -> tuple[list[int], list[int]]:
    """Per frame (static, dynamic) counts by the documented rule, computed here from the
    arrays: the stride grid's kept pixels, at most MAX_POINTS evenly in row order."""
    static, moving = [], []
    for k, d in zip(keep, dynamic):
        kept = np.flatnonzero(k[::STRIDE, ::STRIDE])
        chosen = kept[np.arange(MAX_POINTS) * len(kept) // MAX_POINTS] if len(kept) > MAX_POINTS else kept
        flags = d[::STRIDE, ::STRIDE].reshape(-1)[chosen]
        static.append(int((~flags).sum()))
        moving.append(int(flags.sum()))
    return static, moving


def _expected_segments(valid: np.ndarray) -> list[int]:
    """Track segments ending at frame t or before: frames t-1 and t both valid (T,N)."""
    return [0, *np.cumsum((valid[:-1] & valid[1:]).sum(axis=1)).tolist()]


def _decode(page: str) -> tuple[dict, bytes]:
    header = json.loads(re.search(r'<script id="c4d-header" type="application/json">(.*?)</script>',
                                  page, re.S).group(1))
    payload = re.search(r'<script id="c4d-payload" type="application/octet-stream">(.*?)</script>',
                        page, re.S).group(1)
    return header, base64.b64decode(payload)


def _array(header: dict, data: bytes, name: str) -> np.ndarray:
    spec = header["arrays"][name]
    return np.frombuffer(data, np.dtype(spec["type"]), spec["length"], spec["offset"])


def test_page_data_is_the_reconstruction_after_the_documented_subsample(tmp_path, recon_dir):
    recon = read_reconstruction(recon_dir)
    out = tmp_path / "view.html"
    assert main(["view", str(recon_dir), "--save", str(out), "--stride", str(STRIDE),
                 "--max-points", str(MAX_POINTS)]) == 0
    text = out.read_text()
    header, data = _decode(text)
    keep = recon.confidence >= scene_data.DEFAULT_MIN_CONFIDENCE
    static, moving = _expected_counts(keep, recon.masks)
    assert header["points"]["static"] == static and header["points"]["dynamic"] == moving
    assert all(s + d == MAX_POINTS for s, d in zip(static, moving))  # the cap was reached
    assert sum(moving) > 0 and sum(static) > 0
    positions = _array(header, data, "positions").astype(np.float64).reshape(-1, 3) + header["centre"]
    colors = _array(header, data, "colors").reshape(-1, 3)
    for t in (0, T - 1):  # the frame's points, static first: the same set of points and colours
        start, count = header["points"]["start"][t], static[t] + moving[t]
        grid = recon.points[t, ::STRIDE, ::STRIDE].reshape(-1, 3)
        chosen = scene_data.frame_selection(keep[t], STRIDE, MAX_POINTS)
        order = np.argsort(recon.masks[t, ::STRIDE, ::STRIDE].reshape(-1)[chosen], kind="stable")
        expected = grid[chosen][order]  # float16 of the offset from the centre: half an ulp, 2^-11
        assert (np.abs(positions[start:start + count] - expected)
                <= 2.0 ** -11 * np.abs(expected - header["centre"]) + 1e-6).all()
        np.testing.assert_array_equal(colors[start:start + count],
                                      recon.frames[t, ::STRIDE, ::STRIDE].reshape(-1, 3)[chosen][order])
    valid = _array(header, data, "track_valid").reshape(T, N).astype(bool)
    np.testing.assert_array_equal(valid, recon.tracks_valid)  # N < --max-tracks: all of them
    track_points = _array(header, data, "track_points").astype(np.float64).reshape(T, N, 3) + header["centre"]
    expected = recon.tracks_world[valid]
    assert (np.abs(track_points[valid] - expected)
            <= 2.0 ** -11 * np.abs(expected - header["centre"]) + 1e-6).all()
    moving = _array(header, data, "track_moving").reshape(T, N).astype(bool)
    np.testing.assert_array_equal(moving, (recon.tracks_2d["moving"] > 0.5) & valid)
    assert len(header["cameras"]["cam_to_world"]) == T and header["gt_cameras"] is None
    assert header["thinned"] is None  # a short video is not thinned by the page's size budget
    # one file: no element loads anything from elsewhere, the scripts come inside it
    assert re.findall(r'<(?:script|link|img|iframe)[^>]*\b(?:src|href)="([^"]*)"', text) == ["data:,"]


def test_ground_truth_is_drawn_beside_the_sim3_aligned_reconstruction(tmp_path, box_scene, data_dir,
                                                                      recon_dir):
    view = scene_data.from_reconstruction(recon_dir, gt=box_scene)
    np.testing.assert_allclose(view.cam_to_world, box_scene.cam_to_world, atol=1e-4)  # same poses
    np.testing.assert_allclose(view.gt_cam_to_world, box_scene.cam_to_world, atol=1e-6)
    np.testing.assert_allclose(view.gt_intrinsics, box_scene.intrinsics, atol=1e-4)  # same size
    # a reconstruction 2.5x larger, turned and moved, comes back onto the ground truth
    moved = _moved_copy(recon_dir, tmp_path / "moved", 2.5, np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]),
                        [1.0, 2.0, 3.0])
    aligned = scene_data.from_reconstruction(moved, gt=box_scene)
    np.testing.assert_allclose(aligned.cam_to_world[:, :3, 3], box_scene.cam_to_world[:, :3, 3], atol=1e-3)
    np.testing.assert_allclose(aligned.points, view.points, atol=2e-3)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles in degrees between directions (...,3) and (...,3)."""
    cos = (a * b).sum(-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def test_cameras_on_a_straight_path_are_turned_onto_the_true_ones(straight_path):
    """A generated camera moves on a straight line, about which the centres alone leave the turn
    open (the Umeyama fit of the centres drew the truth 171 degrees from a movi-e estimate): the
    view turns the estimated cameras onto the true ones, then fits the centres. The title and
    notes name the scene, not the folders it was read from."""
    scene, data, estimate, path = straight_path
    centres = scene.cam_to_world[:, :3, 3]
    spread = np.linalg.svd(centres - centres.mean(axis=0), compute_uv=False)
    assert spread[1] < 1e-4 * spread[0]  # a straight line
    view = scene_data.from_reconstruction(estimate, gt=scene)
    turn = np.swapaxes(view.gt_cam_to_world[:, :3, :3], 1, 2) @ view.cam_to_world[:, :3, :3]
    assert rotation_angle_deg(turn).max() < 5
    assert np.linalg.norm(view.cam_to_world[:, :3, 3] - centres, axis=-1).max() < 0.1 * path
    assert view.title == "c4d view: reconstruction of movi-e val scene 0 (recon)"
    assert str(data.parent) not in " ".join([view.title, *view.notes])
    assert scene_data.from_scene(scene, str(data), 0).title == "c4d view: movi-e val scene 0"


def _canvas_pixels(page, image: np.ndarray) -> np.ndarray:
    """The screenshot's pixels outside the control panel, (M,3)."""
    box = page.evaluate("(() => { const r = document.getElementById('panel').getBoundingClientRect();"
                        " return [r.left, r.top, r.right, r.bottom].map(Math.ceil); })()")
    mask = np.ones(image.shape[:2], bool)
    mask[max(box[1] - 1, 0):box[3] + 1, max(box[0] - 1, 0):box[2] + 1] = False
    return image[mask].astype(np.int32)


def _drawn_fraction(pixels: np.ndarray) -> float:
    return float((np.abs(pixels - BACKGROUND).max(axis=1) > 30).mean())


def _check_view_page(page, frames: tuple[int, int], static, moving, valid, cameras, gt_cameras):
    """Wait for the viewer, then at each of two frames: the counts drawn are the expected ones;
    the canvas is drawn on and differs between them; no error and no request off the page."""
    chromium.wait_for_view(page)
    shots = []
    for t in frames:
        page.evaluate(f"c4dView.setFrame({t})")
        page.next_frames()
        stats = page.evaluate("c4dView.stats")
        assert stats["frame"] == t
        assert (stats["staticPoints"], stats["dynamicPoints"]) == (static[t], moving[t])
        assert stats["points"] == static[t] + moving[t]
        assert (stats["cameras"], stats["gtCameras"]) == (cameras, gt_cameras)
        assert stats["trackSegments"] == _expected_segments(valid)[t]
        assert stats["trackHeads"] == int(valid[t].sum())
        shots.append(_canvas_pixels(page, page.screenshot()))
    assert all(_drawn_fraction(shot) > 0.02 for shot in shots)
    changed = (np.abs(shots[0] - shots[1]).max(axis=1) > 30).mean()
    assert changed > 0.002, f"frames {frames} look the same ({changed:.4f} of the pixels changed)"
    assert page.errors() == []
    urls = [p["request"]["url"] for p in page.events("Network.requestWillBeSent")]
    assert all(u.split(":")[0] in ("file", "data", "about", "http") for u in urls), urls
    assert not [u for u in urls if u.startswith("http") and "127.0.0.1" not in u], urls
    return shots


@pytest.mark.browser
def test_reconstruction_view_in_chromium(tmp_path, browser, recon_dir, data_dir):
    out = tmp_path / "view.html"
    assert main(["view", str(recon_dir), "--gt", str(data_dir), "--scene-index", "0", "--save",
                 str(out), "--stride", str(STRIDE), "--max-points", str(MAX_POINTS)]) == 0
    recon = read_reconstruction(recon_dir)
    static, moving = _expected_counts(recon.confidence >= 1.0, recon.masks)
    page = browser.open(out.as_uri())
    _check_view_page(page, (0, T - 1), static, moving, recon.tracks_valid, T, T)
    page.evaluate("document.getElementById('show-cameras').click()")  # the toggles change what is drawn
    page.evaluate("document.getElementById('show-points').click()")
    stats = page.evaluate("c4dView.stats")
    assert (stats["cameras"], stats["points"], stats["gtCameras"]) == (0, 0, T)
    page.evaluate("c4dView.setFrame(0); c4dView.play()")  # play steps through the frames
    page.wait_for("c4dView.stats.frame >= 2", timeout=20)
    page.evaluate("c4dView.pause()")
    assert page.errors() == []


@pytest.mark.browser
def test_ground_truth_frustums_are_drawn_on_the_estimated_ones(tmp_path, browser, straight_path):
    """The frustums as drawn, read back from the page: the true ones where the scene's cameras
    are, looking along their z axes, each where the matching estimated one is and looking the
    same way (its axis and its image's down direction); the panel names no folder."""
    scene, data, estimate, path = straight_path
    out = tmp_path / "view.html"
    assert main(["view", str(estimate), "--gt", str(data), "--scene-index", "0", "--save", str(out)]) == 0
    page = browser.open(out.as_uri())
    chromium.wait_for_view(page)
    drawn = page.evaluate("c4dView.frustums()")
    (apex, corners), (true_apex, true_corners) = (  # (T,3) and (T,4,3): the image's corners
        (np.array([f["apex"] for f in drawn[k]]), np.array([f["corners"] for f in drawn[k]]))
        for k in ("cameras", "truth"))
    forward, true_forward = corners.mean(axis=1) - apex, true_corners.mean(axis=1) - true_apex
    down, true_down = corners[:, 3] - corners[:, 0], true_corners[:, 3] - true_corners[:, 0]
    np.testing.assert_allclose(true_apex, scene.cam_to_world[:, :3, 3], atol=1e-4)
    assert _angle_deg(true_forward, scene.cam_to_world[:, :3, 2]).max() < 1
    assert _angle_deg(forward, true_forward).max() < 5 and _angle_deg(down, true_down).max() < 5
    assert np.linalg.norm(apex - true_apex, axis=-1).max() < 0.1 * path
    panel = page.evaluate("document.getElementById('panel').textContent")
    assert "reconstruction of movi-e val scene 0 (recon)" in panel and str(data.parent) not in panel
    assert page.errors() == []


@pytest.mark.browser
def test_dataset_scene_view_in_chromium(tmp_path, browser, box_scene, data_dir):
    out = tmp_path / "scene.html"
    assert main(["view", str(data_dir), "--scene", "0", "--save", str(out), "--stride", str(STRIDE),
                 "--max-points", str(MAX_POINTS)]) == 0
    static, moving = _expected_counts(box_scene.depth > 0, ground_truth_motion_masks(box_scene))
    valid = np.isfinite(box_scene.tracks_world).all(-1).T  # (T,N)
    page = browser.open(out.as_uri())
    _check_view_page(page, (0, T - 1), static, moving, valid, T, 0)
    assert sum(moving) > 0  # the sliding box, in red


@pytest.mark.browser
def test_served_view_opens_in_chromium(browser, recon_dir):
    process = subprocess.Popen(
        [sys.executable, "-m", "c4d", "view", str(recon_dir), "--no-browser", "--port", "0",
         "--stride", str(STRIDE), "--max-points", str(MAX_POINTS)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
    try:
        line = process.stdout.readline()
        url = re.search(r"http://127\.0\.0\.1:\d+/", line)
        assert url, f"no address in {line!r}: {process.stderr.read() if process.poll() is not None else ''}"
        with pytest.raises(urllib.error.HTTPError, match="404"):
            urllib.request.urlopen(url.group(0) + "other.js", timeout=10)
        recon = read_reconstruction(recon_dir)
        static, moving = _expected_counts(recon.confidence >= 1.0, recon.masks)
        page = browser.open(url.group(0))
        _check_view_page(page, (1, T - 2), static, moving, recon.tracks_valid, T, 0)
    finally:
        process.terminate()
        process.wait(10)


@pytest.mark.browser
def test_screenshot_command_draws_the_view(tmp_path, recon_dir, browser):
    png = tmp_path / "shots" / "view.png"
    assert main(["view", str(recon_dir), "--screenshot", str(png), "--frame", "3", "--size", "640x400"]) == 0
    image = np.asarray(Image.open(png).convert("RGB"))
    assert image.shape == (400, 640, 3)
    assert _drawn_fraction(image.reshape(-1, 3).astype(np.int32)) > 0.05


@pytest.mark.browser
@pytest.mark.parametrize("kind", ["dataset", "reconstruction"])
def test_inspect_reports_open_without_errors_or_broken_images(tmp_path, browser, kind, data_dir, recon_dir):
    out = tmp_path / "report"
    argv = ([str(data_dir), "--num-samples", "1"] if kind == "dataset"
            else [str(recon_dir), "--gt", str(data_dir), "--scene-index", "0"])
    assert main(["inspect", *argv, "--out", str(out), "--no-progress"]) == 0
    page = browser.open((out / "index.html").as_uri())
    images = page.evaluate("[...document.images].map(i => [i.getAttribute('src'), i.complete, i.naturalWidth])")
    assert len(images) >= 2, images
    assert [src for src, complete, width in images if not complete or width == 0] == []
    assert page.errors() == []


LONG_T = 400  # frames of the long reconstruction, at 16x12: 48 points a frame at stride 2 (the
# page's size at 1,000 frames of 256x192 is measured by benchmarks/bench_view.py)


@pytest.fixture(scope="module")
def long_recon(tmp_path_factory) -> Path:
    scene = make_box_scene(num_frames=LONG_T, height=12, width=16, num_tracks=8, seed=5)
    return write_reconstruction(scene, tmp_path_factory.mktemp("long") / "recon")


@pytest.mark.browser
def test_a_long_reconstruction_is_thinned_to_the_page_budget_and_plays(tmp_path, browser, long_recon):
    """400 frames with a page budget that holds about 60 % of their points: the page stays
    under it, every frame is thinned alike (one cap for all) and the page says how
    many of how many points it draws; in Chromium the first frame is drawn and the slider
    reaches the last one."""
    full = tmp_path / "full.html"
    assert main(["view", str(long_recon), "--save", str(full), "--max-page-mb", "0"]) == 0
    header, _ = _decode(full.read_text())
    counts = np.add(header["points"]["static"], header["points"]["dynamic"])  # (T,) unthinned
    assert header["thinned"] is None and len(counts) == LONG_T
    budget_mb = round((full.stat().st_size - 0.4 * counts.sum() * scene_data.BYTES_PER_POINT) / 1e6, 3)
    out = tmp_path / "view.html"
    assert main(["view", str(long_recon), "--save", str(out), "--max-page-mb", str(budget_mb)]) == 0
    assert out.stat().st_size <= budget_mb * 1e6
    header, _ = _decode(out.read_text())
    thinned, drawn = header["thinned"], np.add(header["points"]["static"], header["points"]["dynamic"])
    np.testing.assert_array_equal(drawn, np.minimum(counts, thinned["cap"]))  # alike in every frame
    assert thinned["points"] == drawn.sum() and thinned["of"] == counts.sum()
    assert 0.5 * counts.sum() < drawn.sum() < 0.7 * counts.sum()

    page = browser.open(out.as_uri())
    chromium.wait_for_view(page)
    page.next_frames()
    stats = page.evaluate("c4dView.stats")
    assert (stats["frame"], stats["frames"], stats["points"]) == (0, LONG_T, drawn[0])
    assert _drawn_fraction(_canvas_pixels(page, page.screenshot())) > 0.01
    note = page.evaluate("document.getElementById('thinned').textContent")
    assert f"{thinned['points']:,} of {counts.sum():,} points drawn" in note
    assert f"for a page under {budget_mb} MB (--max-page-mb)" in note
    page.evaluate("(() => { const s = document.getElementById('frame'); s.value = s.max; "
                  "s.dispatchEvent(new Event('input')); })()")  # the slider to its end
    page.next_frames()
    stats = page.evaluate("c4dView.stats")
    assert (stats["frame"], stats["points"]) == (LONG_T - 1, drawn[-1])
    assert page.evaluate("document.getElementById('frame-label').textContent").startswith(
        f"frame {LONG_T - 1} of 0-{LONG_T - 1}")
    assert page.errors() == []


@pytest.mark.parametrize("value, words", [
    ("-1", "--max-page-mb must be a number of megabytes >= 0 (0: no limit), got -1"),
    ("nan", "--max-page-mb must be a number of megabytes >= 0"),
    ("0.5", "--max-page-mb 0.5 cannot hold this page: its HTML, three.js, cameras and tracks"),
])
def test_a_bad_page_budget_is_one_line(tmp_path, capsys, recon_dir, value, words):
    line = _one_error_line(capsys, ["view", str(recon_dir), "--save", str(tmp_path / "v.html"),
                                    "--max-page-mb", value])
    assert words in line
    assert not (tmp_path / "v.html").exists()


def _one_error_line(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("c4d: error: "), err
    return err[0]


def test_a_folder_that_is_no_reconstruction_is_one_line(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("not a reconstruction")
    line = _one_error_line(capsys, ["view", str(tmp_path), "--save", str(tmp_path / "v.html")])
    assert "neither a reconstruction" in line and "nor a shard set" in line
    assert not (tmp_path / "v.html").exists()
    line = _one_error_line(capsys, ["view", str(tmp_path / "nowhere"), "--gt", str(tmp_path)])
    assert "nowhere does not exist" in line


def test_a_missing_frame_file_is_one_line(tmp_path, capsys, recon_dir):
    broken = tmp_path / "recon"
    shutil.copytree(recon_dir, broken)
    (broken / "frames" / "000003.png").unlink()
    line = _one_error_line(capsys, ["view", str(broken), "--save", str(tmp_path / "v.html")])
    assert "frames/000003.png is missing" in line and f"{T} frames" in line


def test_a_port_in_use_is_one_line(capsys, recon_dir):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        line = _one_error_line(capsys, ["view", str(recon_dir), "--no-browser", "--port", str(port)])
    assert f"port {port} is in use" in line and "--port" in line


def test_no_browser_for_a_screenshot_is_one_line(tmp_path, capsys, monkeypatch, recon_dir):
    monkeypatch.delenv("C4D_BROWSER", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))  # a PATH with no browser on it
    line = _one_error_line(capsys, ["view", str(recon_dir), "--screenshot", str(tmp_path / "v.png")])
    assert "no Chromium or Chrome found" in line and "apt-get install chromium" in line
    monkeypatch.setenv("C4D_BROWSER", str(tmp_path / "nothing-here"))
    line = _one_error_line(capsys, ["view", str(recon_dir), "--screenshot", str(tmp_path / "v.png")])
    assert "C4D_BROWSER" in line and "not an executable" in line
    assert not (tmp_path / "v.png").exists()


def test_the_page_builder_ships_three_js_and_escapes_its_data():
    view = scene_data.ViewScene(
        title="c4d view: </script><b>", colors=np.zeros((2, 4, 4, 3), np.uint8),
        points=np.random.default_rng(0).normal(size=(2, 4, 4, 3)) + [0, 0, 5],
        keep=np.ones((2, 4, 4), bool), dynamic=None, cam_to_world=np.stack([np.eye(4)] * 2),
        intrinsics=np.stack([np.array([[4.0, 0, 1.5], [0, 4, 1.5], [0, 0, 1]])] * 2),
        notes=["</script>"])
    text = view_page.build_page(scene_data.encode(view, stride=1))
    assert text.count("</script>") == text.count("<script")  # the data cannot end a script early
    assert "&lt;/script&gt;&lt;b&gt;" in text  # the title is escaped
    header, _ = _decode(text)
    assert header["notes"] == ["</script>"] and header["tracks"] is None
    assert header["points"]["static"] == [16, 16] and header["points"]["dynamic"] == [0, 0]


@pytest.mark.browser
def test_the_page_checks_see_broken_images_and_console_errors(tmp_path, browser):
    page_file = tmp_path / "broken.html"
    page_file.write_text('<html><body><img src="missing.png"><img src="data:,">'
                         '<script>console.error("seen"); undefinedFunction();</script></body></html>')
    page = browser.open(page_file.as_uri())
    widths = page.evaluate("[...document.images].map(i => i.naturalWidth)")
    assert widths == [0, 0]
    errors = " | ".join(page.errors())
    assert "console: seen" in errors and "undefinedFunction" in errors and "missing.png" in errors


def test_make_looks_for_the_browsers_c4d_view_looks_for():
    makefile = (REPO / "Makefile").read_text()
    names = re.search(r"^BROWSERS := (.*)$", makefile, re.M).group(1).split()
    assert tuple(names) == chromium.BROWSER_NAMES
    assert re.search(r"^test: .*\bbrowser\b", makefile, re.M)  # `make test` finds or installs it
