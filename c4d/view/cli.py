"""`c4d view SOURCE`: the 4D view of a reconstruction or of a generated scene, in the browser.

SOURCE is the OUT folder of `c4d run` / `c4d demo` (its point clouds, cameras, motion masks and
3D tracks; `--gt DATA --scene-index I` draws that scene's ground-truth cameras beside them,
Sim(3)-aligned) or a shard set of `c4d datagen` (`--scene I` from its ground truth). The page is
one self-contained HTML file (c4d.view.page), a long video's points thinned alike in every frame
to keep it under `--max-page-mb` (scene_data.frame_selections): `--save FILE` writes it,
`--screenshot PNG` draws it in headless Chromium, and without either it is served on
127.0.0.1:`--port` and opened in the default browser (`--no-browser`: only print the address)
until Ctrl-C.
"""

from __future__ import annotations

import argparse
import errno
import logging
import math
import webbrowser
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from c4d.view import scene_data
from c4d_core.errors import UserError, refuse_unused
from c4d_core.ownership import check_file

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _size(text: str) -> tuple[int, int]:
    width, sep, height = text.partition("x")
    if not sep or not width.isdigit() or not height.isdigit() or min(int(width), int(height)) < 16:
        raise argparse.ArgumentTypeError(f"give WIDTHxHEIGHT in pixels (at least 16x16), got {text!r}")
    return int(width), int(height)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", metavar="SOURCE",
                        help="a reconstruction (the OUT folder of `c4d run` or `c4d demo`) or a "
                             "shard set of `c4d datagen` (a folder of .tar shards, a .tar, a glob)")
    parser.add_argument("--scene", type=int, metavar="I",
                        help="shard sets: the scene to show (0-based, reading order; default 0)")
    parser.add_argument("--gt", metavar="DATA",
                        help="reconstructions: the shard set holding the video's ground truth, "
                             "drawn beside it (the reconstruction Sim(3)-aligned onto it)")
    parser.add_argument("--scene-index", type=int, metavar="I",
                        help="reconstructions: which scene of --gt (0-based, reading order)")
    parser.add_argument("--stride", type=_positive, default=scene_data.DEFAULT_STRIDE, metavar="S",
                        help="draw every S-th pixel of every S-th row (default "
                             f"{scene_data.DEFAULT_STRIDE})")
    parser.add_argument("--max-points", type=_positive, default=scene_data.DEFAULT_MAX_POINTS,
                        metavar="N", help="at most N points per frame, evenly among those kept "
                                          f"(default {scene_data.DEFAULT_MAX_POINTS})")
    parser.add_argument("--max-page-mb", type=float, default=scene_data.DEFAULT_MAX_PAGE_MB,
                        metavar="MB", help="thin every frame's points alike so that the page stays "
                                           "under MB megabytes (default "
                                           f"{scene_data.DEFAULT_MAX_PAGE_MB:g}; 0: no limit)")
    parser.add_argument("--min-confidence", type=float, metavar="C",
                        help="reconstructions: draw points of confidence >= C "
                             f"(default {scene_data.DEFAULT_MIN_CONFIDENCE:g}: all)")
    parser.add_argument("--max-tracks", type=int, default=scene_data.DEFAULT_MAX_TRACKS, metavar="N",
                        help=f"at most N 3D tracks (default {scene_data.DEFAULT_MAX_TRACKS}; 0: none)")
    parser.add_argument("--save", type=Path, metavar="FILE.html",
                        help="write the page to this file (it opens offline) instead of serving it")
    parser.add_argument("--screenshot", type=Path, metavar="FILE.png",
                        help="draw the page in headless Chromium and write a PNG (needs Chromium)")
    parser.add_argument("--frame", type=int, metavar="T",
                        help="--screenshot: the frame shown, counted from 0 as the page's frame "
                             "label and the output's file names count (0..frames-1; default the "
                             "last, with the whole of every track drawn)")
    parser.add_argument("--size", type=_size, metavar="WxH",
                        help="--screenshot: the picture's size in pixels (default 1280x800)")
    parser.add_argument("--port", type=int,
                        help=f"serve on 127.0.0.1:PORT (default {DEFAULT_PORT}; 0: any free port)")
    parser.add_argument("--no-browser", action="store_true",
                        help="serve without opening a browser; only print the address")


def resolve_options(args, reconstruction: bool) -> None:
    """Refuse (one `UserError`) an option given where it does nothing: for the other kind of
    SOURCE (`reconstruction` or shard set), without the option it refines, or for another output
    than the one asked for; then fill in the defaults of those left out."""
    serving = args.save is None and args.screenshot is None
    served = "serving the page (neither --save nor --screenshot)"
    refuse_unused([
        ("--scene", args.scene is not None and reconstruction, f"shard sets, and {args.source} "
         "is a reconstruction (its ground truth: --gt DATA --scene-index I)"),
        ("--min-confidence", args.min_confidence is not None and not reconstruction,
         f"reconstructions, and {args.source} is not one"),
        ("--scene-index", args.scene_index is not None and not args.gt,
         "--gt DATA (which of its scenes is the video's)"),
        ("--frame", args.frame is not None and args.screenshot is None, "--screenshot FILE.png"),
        ("--size", args.size is not None and args.screenshot is None, "--screenshot FILE.png"),
        ("--port", args.port is not None and not serving, served),
        ("--no-browser", args.no_browser and not serving, served),
    ])
    if args.min_confidence is not None and not math.isfinite(args.min_confidence):
        raise UserError(f"--min-confidence must be a finite number, got {args.min_confidence}")
    if not (math.isfinite(args.max_page_mb) and args.max_page_mb >= 0):
        raise UserError(f"--max-page-mb must be a number of megabytes >= 0 (0: no limit), got "
                        f"{args.max_page_mb:g}")
    defaults = {"scene": 0, "scene_index": 0, "size": (1280, 800), "port": DEFAULT_PORT,
                "min_confidence": scene_data.DEFAULT_MIN_CONFIDENCE}
    for name, value in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, value)


def load_view(args) -> scene_data.ViewScene:
    """The `ViewScene` of SOURCE: a reconstruction, or a scene of a shard set."""
    from c4d_pipeline.outputs import is_reconstruction

    if is_reconstruction(args.source):
        gt = None
        if args.gt:
            from c4d_pipeline.eval_recon import pick_scene

            gt = pick_scene(args.gt, args.scene_index)
        return scene_data.from_reconstruction(args.source, args.min_confidence, gt, args.scene_index)
    if not Path(args.source).exists() and not any(c in args.source for c in "*?["):
        raise UserError(f"{args.source} does not exist; give the --out folder of `c4d run` / "
                        "`c4d demo` or a shard set of `c4d datagen`")
    if args.gt:
        raise UserError(f"--gt is for reconstructions, and {args.source} is not one (no "
                        "poses_tum.txt, pointmaps.npz or report.json)")
    if Path(args.source).is_dir() and not any(Path(args.source).glob("*.tar")):
        raise UserError(f"{args.source} is neither a reconstruction (no poses_tum.txt, "
                        "pointmaps.npz or report.json) nor a shard set (no .tar shards); give the "
                        "--out folder of `c4d run` / `c4d demo` or of `c4d datagen`")
    from datagen.shards import not_a_shard

    if Path(args.source).is_file() and (kind := not_a_shard(args.source)):
        raise UserError(f"{args.source} is neither a reconstruction (a folder) nor a shard (a .tar): "
                        f"it is {kind}; give the --out folder of `c4d run` / `c4d demo` or a shard "
                        "set of `c4d datagen`")
    from c4d_pipeline.eval_recon import pick_scene

    if args.scene < 0:
        raise UserError(f"--scene must be >= 0, got {args.scene}")
    scene = pick_scene(args.source, args.scene)
    return scene_data.from_scene(scene, args.source, args.scene)


class _PageHandler(BaseHTTPRequestHandler):
    """Answers GET / (and /index.html) with the server's `page`; anything else is 404."""

    def do_GET(self):  # noqa: N802 -- the name http.server calls
        if self.path.split("?")[0] not in ("/", "/index.html"):
            self.send_error(404)
            return
        self.send_response(200)
        self.send_header("Content-Type", "text/html; charset=utf-8")
        self.send_header("Content-Length", str(len(self.server.page)))
        self.end_headers()
        self.wfile.write(self.server.page)

    def log_message(self, format, *args):  # noqa: A002 -- http.server's signature
        log.debug("%s %s", self.address_string(), format % args)


def open_server(port: int) -> ThreadingHTTPServer:
    """A server bound to 127.0.0.1:`port` (0: any free port), before any work is done; a port in
    use is one `UserError`. Set its `page` (bytes) before `serve`."""
    if not 0 <= port <= 65535:
        raise UserError(f"--port must be 0..65535, got {port}")
    try:
        return ThreadingHTTPServer(("127.0.0.1", port), _PageHandler)
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise UserError(f"port {port} is in use on 127.0.0.1; choose another with --port "
                            "(--port 0 picks a free one)") from None
        raise UserError(f"cannot serve on 127.0.0.1:{port}: {exc.strerror or exc}") from None


def serve(server: ThreadingHTTPServer, open_browser: bool) -> None:
    """Serve the server's page until Ctrl-C, printing its address first."""
    url = f"http://127.0.0.1:{server.server_address[1]}/"
    print(f"serving the view on {url} (Ctrl-C to stop)", flush=True)
    if open_browser:
        webbrowser.open(url)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        print("stopped", flush=True)


def point_budget(view: scene_data.ViewScene, max_page_mb: float, max_tracks: int) -> int | None:
    """The most points a page of at most `max_page_mb` megabytes (1e6 bytes) holds beside its
    HTML, three.js, cameras and tracks (None: no limit); a `UserError` where that leaves fewer
    than one point per frame."""
    from c4d.view.page import page_overhead

    if not max_page_mb:
        return None
    other = page_overhead(view.title) + scene_data.page_other_bytes(view, max_tracks)
    budget = (int(max_page_mb * 1e6) - other) // scene_data.BYTES_PER_POINT
    if budget < view.num_frames:
        raise UserError(f"--max-page-mb {max_page_mb:g} cannot hold this page: its HTML, three.js, "
                        f"cameras and tracks of {view.num_frames} frames take {other / 1e6:.1f} MB "
                        "before any point; give more (0: no limit)")
    return budget


def run(args) -> int:
    from c4d.view.page import build_page
    from c4d_pipeline.outputs import is_reconstruction

    resolve_options(args, is_reconstruction(args.source))
    if args.max_tracks < 0:
        raise UserError(f"--max-tracks must be >= 0, got {args.max_tracks}")
    if args.screenshot is not None:
        from c4d.view.browser import find_browser

        if args.screenshot.suffix.lower() != ".png":
            raise UserError(f"--screenshot {args.screenshot}: give a .png file name")
        check_file(args.screenshot, "view", args.overwrite)
        find_browser()  # no browser: said before the scene is read
    if args.save is not None:
        check_file(args.save, "view", args.overwrite)
    server = open_server(args.port) if args.save is None and args.screenshot is None else None
    try:
        view = load_view(args)
        if args.frame is not None and not 0 <= args.frame < view.num_frames:
            raise UserError(f"--frame must be 0..{view.num_frames - 1}, got {args.frame}")
        if args.max_tracks == 0:
            view.tracks = None
        payload = scene_data.encode(view, args.stride, args.max_points, args.max_tracks,
                                    point_budget(view, args.max_page_mb, args.max_tracks))
        if payload.header["thinned"]:
            payload.header["thinned"]["max_page_mb"] = args.max_page_mb
        page = build_page(payload).encode("utf-8")
        points = sum(payload.header["points"]["static"]) + sum(payload.header["points"]["dynamic"])
        log.info("%d frames, %d points, page of %.1f MB", view.num_frames, points, len(page) / 1e6)
        if payload.header["thinned"]:
            log.info("thinned to at most %d points per frame for a page under %g MB (--max-page-mb)",
                     payload.header["thinned"]["cap"], args.max_page_mb)
        if server is not None:
            server.page = page
            serve(server, not args.no_browser)
            return 0
    finally:
        if server is not None:
            server.server_close()
    from c4d_core.files import write_bytes

    if args.save is not None:
        write_bytes(args.save, page)
        log.info("wrote %s", args.save)
    if args.screenshot is not None:
        import tempfile

        from c4d.view.browser import screenshot_file

        with tempfile.TemporaryDirectory(prefix="c4d-view-") as folder:
            html = args.save or write_bytes(Path(folder) / "view.html", page)
            frame = view.num_frames - 1 if args.frame is None else args.frame
            screenshot_file(html, args.screenshot, frame, *args.size)
        log.info("wrote %s", args.screenshot)
    return 0
