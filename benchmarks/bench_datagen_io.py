"""Benchmark of datagen storage: size and speed of candidate encodings, and CLI throughput.

    .venv/bin/python benchmarks/bench_datagen_io.py [--preset movi-e] [--size 256] [--frames 24]
        [--repeats 5] [--cli-scenes 4] [--skip-cli] [--skip-codecs]

Part 1 generates one real scene and, per field, times every candidate encoding (median CPU time
of `--repeats` runs): MB stored, encode and decode MB/s (of the raw array), whether it is exact, and
the stored size relative to the raw .npy baseline. Then whole scenes: `encode_scene` and
`decode_scene` (all fields, and the fields training reads). Part 2 runs `c4d datagen` with one
worker and with all cores on a few scenes and reports scenes per hour. Prints markdown tables.
"""

from __future__ import annotations

import argparse
import bz2
import io
import lzma
import os
import resource
import subprocess
import sys
import tempfile
import time
import zlib

import cv2
import isal
import numpy as np
from isal import isal_zlib

from c4d_core.config import load_config
from c4d_core.system import require_egl
from datagen.cli import usable_cpus
from datagen.codecs import decode_array, encode_array, shuffled_npy
from datagen.shards import decode_scene, encode_scene, list_shards


def median_seconds(fn, repeats: int):
    """(last result, median CPU seconds) of `repeats` calls of `fn`.

    CPU time of this process, not wall time: the codecs are single-threaded and the machine may be
    shared, so CPU time is the reproducible cost (it equals wall time on an idle core).
    """
    times = []
    for _ in range(repeats):
        start = time.process_time()
        result = fn()
        times.append(time.process_time() - start)
    return result, float(np.median(times))


def _zlib_rle(data: bytes) -> bytes:
    """zlib level 1 with the run-length-only strategy (a standard zlib stream)."""
    compressor = zlib.compressobj(1, zlib.DEFLATED, 15, 8, zlib.Z_RLE)
    return compressor.compress(data) + compressor.flush()


# --- candidate encodings: name -> (encode(array) -> bytes, decode(bytes, like) -> array) --------


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def _from_npy(data: bytes, like: np.ndarray) -> np.ndarray:
    return np.load(io.BytesIO(data))


def _shuffled(array: np.ndarray) -> bytes:
    return np.ascontiguousarray(array.reshape(-1).view(np.uint8).reshape(-1, array.itemsize).T).tobytes()


def _unshuffled(data: bytes, like: np.ndarray) -> np.ndarray:
    planes = np.frombuffer(data, np.uint8).reshape(like.itemsize, -1)
    return np.ascontiguousarray(planes.T).view(like.dtype).reshape(like.shape)


def _image(ext: str, params: list[int]):
    """Encode (T,H,W[,C]) as one image of the frames stacked vertically."""
    def encode(array):
        ok, buf = cv2.imencode(ext, array.reshape(-1, *array.shape[2:]), params)
        assert ok, ext
        return buf.tobytes()

    def decode(data, like):
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED).reshape(like.shape)

    return encode, decode


def _frames(ext: str, params: list[int]):
    """Encode (T,H,W,3) as one image per frame (JPEG and WebP cap image height at 16383)."""
    def encode(array):
        return [cv2.imencode(ext, frame, params)[1].tobytes() for frame in array]

    def decode(frames, like):
        return np.stack([cv2.imdecode(np.frombuffer(f, np.uint8), cv2.IMREAD_UNCHANGED) for f in frames])

    return encode, decode


FLOAT_CODECS = {
    "npy (raw, baseline)": (_npy, _from_npy),
    "npy + zlib 1": (lambda a: zlib.compress(_npy(a), 1), lambda d, a: _from_npy(zlib.decompress(d), a)),
    "npy + zlib 6": (lambda a: zlib.compress(_npy(a), 6), lambda d, a: _from_npy(zlib.decompress(d), a)),
    "npy + lzma 0": (lambda a: lzma.compress(_npy(a), preset=0), lambda d, a: _from_npy(lzma.decompress(d), a)),
    "npy + bz2 9": (lambda a: bz2.compress(_npy(a), 9), lambda d, a: _from_npy(bz2.decompress(d), a)),
    "shuffle + ISA-L 1 (.npy.bsz, chosen)": (encode_array, lambda d, a: decode_array(d)),
    "shuffle + zlib 1 (.npy.bsz until ISA-L)": (lambda a: zlib.compress(shuffled_npy(a), 1),
                                                lambda d, a: decode_array(d)),
    "shuffle + ISA-L 3": (lambda a: isal_zlib.compress(shuffled_npy(a), 3), lambda d, a: decode_array(d)),
    "shuffle + zlib 1 RLE strategy": (lambda a: _zlib_rle(_shuffled(a)), lambda d, a: _unshuffled(zlib.decompress(d), a)),
    "shuffle + zlib 6": (lambda a: zlib.compress(_shuffled(a), 6), lambda d, a: _unshuffled(zlib.decompress(d), a)),
    "shuffle + lzma 0": (lambda a: lzma.compress(_shuffled(a), preset=0), lambda d, a: _unshuffled(lzma.decompress(d), a)),
    "TIFF deflate + float predictor": _image(".tiff", [
        cv2.IMWRITE_TIFF_COMPRESSION, cv2.IMWRITE_TIFF_COMPRESSION_ADOBE_DEFLATE,
        cv2.IMWRITE_TIFF_PREDICTOR, cv2.IMWRITE_TIFF_PREDICTOR_FLOATINGPOINT]),
    "float16 + shuffle + ISA-L 1 (lossy)": (lambda a: encode_array(a.astype(np.float16)),
                                           lambda d, a: decode_array(d).astype(np.float32)),
}
RGB_CODECS = {
    "npy (raw, baseline; chosen in format 2)": (_npy, _from_npy),
    "PNG level 1 (format 1)": _image(".png", [cv2.IMWRITE_PNG_COMPRESSION, 1]),
    "PNG level 6": _image(".png", [cv2.IMWRITE_PNG_COMPRESSION, 6]),
    "PNG per frame, level 1": _frames(".png", [cv2.IMWRITE_PNG_COMPRESSION, 1]),
    "WebP lossless per frame": _frames(".webp", [cv2.IMWRITE_WEBP_QUALITY, 101]),
    "JPEG q95 per frame (lossy)": _frames(".jpg", [cv2.IMWRITE_JPEG_QUALITY, 95]),
    "JPEG q90 per frame (lossy)": _frames(".jpg", [cv2.IMWRITE_JPEG_QUALITY, 90]),
}
SEGMENTATION_CODECS = {
    "npy int32 (raw, baseline)": (_npy, _from_npy),
    "uint8 PNG level 1 (chosen)": (lambda a: _image(".png", [cv2.IMWRITE_PNG_COMPRESSION, 1])[0](a.astype(np.uint8)),
                                   lambda d, a: _image(".png", [])[1](d, a).astype(np.int32)),
    "int32 shuffle + ISA-L 1 (.npy.bsz)": (encode_array, lambda d, a: decode_array(d)),
}


def _size(encoded) -> int:
    return sum(map(len, encoded)) if isinstance(encoded, list) else len(encoded)


def codec_rows(field: str, array: np.ndarray, codecs: dict, repeats: int) -> list[str]:
    rows, baseline = [], None
    for name, (encode, decode) in codecs.items():
        encoded, t_enc = median_seconds(lambda: encode(array), repeats)
        decoded, t_dec = median_seconds(lambda: decode(encoded, array), repeats)
        size = _size(encoded)
        baseline = baseline or size
        error = np.abs(decoded.astype(np.float64) - array.astype(np.float64))
        exact = "yes" if np.array_equal(decoded, array, equal_nan=True) else f"no (max err {error.max():.3g})"
        mb = array.nbytes / 1e6
        rows.append(f"| {field} | {name} | {size / 1e6:.3f} | {size / baseline:.2f} | "
                    f"{mb / t_enc:.0f} | {mb / t_dec:.0f} | {exact} |")
    return rows


def scene_rows(scene, repeats: int) -> list[str]:
    sample, t_enc = median_seconds(lambda: encode_scene(scene, "bench-00000000"), repeats)
    raw = sum(v.nbytes for v in vars(scene).values() if isinstance(v, np.ndarray))
    stored = sum(len(v) for k, v in sample.items() if not k.startswith("__"))
    rows = [f"| whole scene, encode_scene | {stored / 1e6:.2f} MB stored of {raw / 1e6:.2f} MB raw | "
            f"{t_enc * 1e3:.0f} ms CPU | {raw / 1e6 / t_enc:.0f} MB/s |"]
    for label, fields in (("all fields", None), ("training fields (rgb, tracks, occluded, query_frame, "
                                                 "track_object, moving)",
                                                 ["rgb", "tracks", "occluded", "query_frame", "track_object", "moving"])):
        _, t_dec = median_seconds(lambda: decode_scene(sample, fields), repeats)
        rows.append(f"| decode_scene, {label} | | {t_dec * 1e3:.0f} ms CPU | {raw / 1e6 / t_dec:.0f} MB/s |")
    return rows


def measure_codecs(scene, repeats: int) -> None:
    t, h, w, _ = scene.rgb.shape
    print(f"\n### Encodings of one scene, {h}x{w} x {t} frames, {scene.num_tracks} tracks "
          f"(median of {repeats})\n")
    print("| field | encoding | MB | size vs raw | encode MB/s | decode MB/s | exact |")
    print("|---|---|---|---|---|---|---|")
    rows = codec_rows("rgb", scene.rgb, RGB_CODECS, repeats)
    rows += codec_rows("depth", scene.depth, FLOAT_CODECS, repeats)
    flow_codecs = {k: v for k, v in FLOAT_CODECS.items() if not k.startswith("TIFF")}  # 2 channels
    rows += codec_rows("flow_fwd", scene.flow_fwd, flow_codecs, repeats)
    rows += codec_rows("segmentation", scene.segmentation, SEGMENTATION_CODECS, repeats)
    small = {k: FLOAT_CODECS[k] for k in ("npy (raw, baseline)", "npy + zlib 1",
                                          "shuffle + ISA-L 1 (.npy.bsz, chosen)",
                                          "shuffle + zlib 1 (.npy.bsz until ISA-L)")}
    rows += codec_rows("tracks_world", scene.tracks_world, small, repeats)
    print("\n".join(rows))
    print("\n| what | size | time | throughput |\n|---|---|---|---|")
    print("\n".join(scene_rows(scene, repeats)))


def measure_cli(preset: str, size: int, frames: int, num_scenes: int) -> None:
    """Wall-clock scenes/hour of `c4d datagen`, and its CPU seconds per scene (all processes).

    CPU time (of the command and its workers, from `getrusage`) gives the rate an idle machine
    would reach, `cores * 3600 / cpu_per_scene`, when other jobs share the cores.
    """
    cores = usable_cpus()
    print(f"\n### `c4d datagen` throughput, {preset} {size}x{size} x {frames} frames, {num_scenes} scenes "
          f"(load average {os.getloadavg()[0]:.1f} before)\n")
    print("| workers | wall s | scenes/hour (wall) | CPU s per scene | scenes/hour per idle core | "
          "MB per scene | wall rate vs 1 worker |\n|---|---|---|---|---|---|---|")
    base = None
    for workers in sorted({1, cores}):
        with tempfile.TemporaryDirectory() as out:
            cpu_before = resource.getrusage(resource.RUSAGE_CHILDREN)
            start = time.perf_counter()
            subprocess.run(
                [sys.executable, "-m", "c4d", "datagen", "--preset", preset, "--num-scenes", str(num_scenes),
                 "--out", out, "--workers", str(workers), "--resolution", str(size), "--frames", str(frames),
                 "--scenes-per-shard", str(num_scenes)],
                check=True, stderr=subprocess.DEVNULL,
            )
            seconds = time.perf_counter() - start
            cpu_after = resource.getrusage(resource.RUSAGE_CHILDREN)
            megabytes = sum(p.stat().st_size for p in list_shards(out)) / 1e6 / num_scenes
        cpu = (cpu_after.ru_utime + cpu_after.ru_stime - cpu_before.ru_utime - cpu_before.ru_stime) / num_scenes
        rate = num_scenes / seconds * 3600
        base = base or rate
        print(f"| {workers} | {seconds:.1f} | {rate:.0f} | {cpu:.2f} | {3600 / cpu:.0f} | {megabytes:.2f} | "
              f"{rate / base:.2f}x |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="movi-e")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--cli-scenes", type=int, default=4)
    parser.add_argument("--skip-cli", action="store_true")
    parser.add_argument("--skip-codecs", action="store_true")
    args = parser.parse_args()

    require_egl()
    from datagen.generate import generate_scene

    cfg = load_config("datagen", args.preset, overrides=[f"resolution=[{args.size},{args.size}]",
                                                          f"frames={args.frames}"])
    print(f"machine: {usable_cpus()} usable cores, load average {os.getloadavg()[0]:.1f}; "
          f"numpy {np.__version__}, OpenCV {cv2.__version__}, zlib {zlib.ZLIB_RUNTIME_VERSION}, "
          f"isal {isal.__version__}")
    if not args.skip_codecs:
        measure_codecs(generate_scene(cfg, 0), args.repeats)
    if not args.skip_cli:
        measure_cli(args.preset, args.size, args.frames, args.cli_scenes)


if __name__ == "__main__":
    main()
