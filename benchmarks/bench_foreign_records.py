"""Benchmark of reading Kubric's TFDS MOVi records without TensorFlow (datagen/foreign/tfds_movi.py).

    .venv/bin/python benchmarks/bench_foreign_records.py [--shards DIR] [--scenes 6]
        [--repeats 5] [--workers 0,1] [--clips 24] [--loader-repeats 3] [--records DIR]

Records: the scenes of `--shards` (made by `c4d datagen --preset movi-e --split val ...
layers.normal=true layers.object_coordinates=true`; without it, `--scenes` such scenes of
256x256 x 24 frames are generated first) written as a TFDS MOVi validation split by the tests'
writer (tests/foreign_writers.py: every feature as Kubric's movi_e builder stores it: PNG frames,
int64 flow lists, float camera and object lists). `--records DIR` reads a TFDS folder instead
(real MOVi records, where one has them).

1. Decode: median CPU seconds per record over `--repeats` passes over the records, for the whole
   record (every layer, tracks drawn) and for what training reads (no flows, normals or object
   coordinates), and the parts of a whole decode: read + CRC-32C, Example parse, PNG frames, the
   two flows, the 256 TAP-Vid-Kubric tracks. Issue 43's target: <= 0.2 CPU-s a record.
2. Loader: clips/s and CPU ms per clip of dynpt's training DataLoader fed from the records at the
   paper crop (paper-gpu's `data:`: 24 frames, 384x512, 384 tracks, its augmentation), per
   `--workers` count (`bench_dynpt_train.data_throughput`; CPU ms from this process with 0
   workers, from the workers' /proc with some: load independent). Target: >= 2 clips/s a worker.
3. Mobility: over every record's 256 drawn tracks, the share of moving point-frames under our
   per-point label and under the paper appendix's per-object rule, and how often they agree.

Prints markdown tables, the load average and the commit.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from timing import load_average, this_commit

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: tests.*
from bench_dynpt_train import data_throughput  # noqa: E402
from c4d_core.config import load_config  # noqa: E402
from datagen.annotate import tapvid_kubric_tracks  # noqa: E402
from datagen.foreign import ReadOptions, mobility_labels, read_unit, source_units  # noqa: E402
from datagen.foreign.tfds_movi import (Record, decode_record, parse_example,  # noqa: E402
                                       read_record)
from dynpt.data import TRAIN_FIELDS  # noqa: E402


def make_records(shards: str | None, scenes: int, out: Path) -> Path:
    """A TFDS MOVi folder of the scenes of `shards` (or of `scenes` generated ones)."""
    from datagen import read_scenes
    from tests.foreign_writers import write_tfds_movi

    if shards is None:
        from c4d.cli import main

        shards = str(out / "shards")
        assert main(["datagen", "--preset", "movi-e", "--split", "val", "--num-scenes",
                     str(scenes), "--out", shards, "--workers", "1", "layers.normal=true",
                     "layers.object_coordinates=true"]) == 0
    folder = write_tfds_movi(out / "tfds", list(read_scenes(shards)), num_files=2)
    return folder


def cpu(fn) -> float:
    start = time.process_time()
    fn()
    return time.process_time() - start


def decode_costs(units, repeats: int) -> dict[str, list[float]]:
    """CPU seconds per record, one value per pass (the mean over the records of that pass)."""
    parts = ("whole record", "training fields", "read + CRC", "parse", "PNG frames", "flows",
             "tracks")
    costs: dict[str, list[float]] = {name: [] for name in parts}
    for _ in range(repeats):
        sums = dict.fromkeys(parts, 0.0)
        for unit in units:
            sums["whole record"] += cpu(lambda: read_unit(unit, ReadOptions()))
            sums["training fields"] += cpu(lambda: read_unit(unit, ReadOptions(fields=TRAIN_FIELDS)))
            data = []
            sums["read + CRC"] += cpu(lambda: data.append(read_record(unit.path, unit.where, unit.name)))
            sums["parse"] += cpu(lambda: parse_example(data[0]))
            record = Record(data[0], unit.name)
            sums["PNG frames"] += cpu(lambda: [record.frames(key, dtype, channels) for key, dtype, channels
                                               in (("video", np.uint8, 3), ("segmentations", np.uint8, 1),
                                                   ("depth", np.uint16, 1), ("normal", np.uint16, 3),
                                                   ("object_coordinates", np.uint16, 3))
                                               if record.has(key)])
            shape = record.frames("video", np.uint8, 3).shape[:3]
            sums["flows"] += cpu(lambda: [record.flow(key, shape, 1.0) for key in
                                          ("forward_flow", "backward_flow")])
            scene = decode_record(data[0], unit, ReadOptions(fields=()))
            sums["tracks"] += cpu(lambda: tapvid_kubric_tracks(scene, [0, unit.index]))
        for name in parts:
            costs[name].append(sums[name] / len(units))
    return costs


def mobility_agreement(units) -> dict[str, float]:
    """Moving point-frames (fractions) under each rule over every record's drawn tracks."""
    point, per_object = [], []
    for unit in units:
        scene = read_unit(unit, ReadOptions(fields=TRAIN_FIELDS))
        drawn = tapvid_kubric_tracks(scene, [0, unit.index])
        point.append(mobility_labels(drawn, scene.object_to_world, ReadOptions()).ravel())
        per_object.append(mobility_labels(drawn, scene.object_to_world,
                                          ReadOptions(mobility_rule="object")).ravel())
    point, per_object = np.concatenate(point), np.concatenate(per_object)
    return {"point-frames": point.size, "moving (point rule)": point.mean(),
            "moving (object rule)": per_object.mean(), "agreement": (point == per_object).mean(),
            "moving by points only": (point & ~per_object).mean(),
            "moving by objects only": (~point & per_object).mean()}


def runs(values: list[float], scale: float = 1.0, digits: int = 3) -> str:
    return (f"{statistics.median(values) * scale:.{digits}f} "
            f"(runs {', '.join(f'{v * scale:.{digits}f}' for v in values)})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shards", help="our movi-e shards (with normals and object coordinates)")
    parser.add_argument("--records", help="a TFDS MOVi folder to read instead")
    parser.add_argument("--scenes", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--workers", default="0,1")
    parser.add_argument("--clips", type=int, default=24)
    parser.add_argument("--loader-repeats", type=int, default=3)
    args = parser.parse_args()

    print(f"load average at start {load_average()}; commit {this_commit()}")
    with tempfile.TemporaryDirectory(prefix="bench-records-") as tmp:
        folder = Path(args.records) if args.records else make_records(args.shards, args.scenes,
                                                                      Path(tmp))
        source = f"{folder}:validation" if not args.records else str(folder)
        units = source_units(source)
        first = read_unit(units[0], ReadOptions())
        size = sum(Path(p).stat().st_size for p in {u.path for u in units}) / len(units) / 1e6
        print(f"\n{len(units)} records of {first.num_frames} x {first.image_size[0]}x"
              f"{first.image_size[1]}, {size:.1f} MB each\n")

        costs = decode_costs(units, args.repeats)
        print("| decode, CPU s per record | median (runs) |\n|---|---|")
        for name, values in costs.items():
            print(f"| {name} | {runs(values)} |")

        cfg = load_config("dynpt", "paper-gpu").data
        print(f"\nloader at the paper crop ({cfg.num_frames} frames, {list(cfg.crop_size)}, "
              f"{cfg.num_tracks} tracks), load {load_average()}\n")
        print("| workers | clips/s | CPU ms per clip | clips/s per worker core |\n|---|---|---|---|")
        for workers in (int(w) for w in args.workers.split(",")):
            rates, cpu_ms = data_throughput(source, workers, args.clips, args.loader_repeats,
                                            "paper-gpu", [], batch=1)
            print(f"| {workers} | {runs(rates, digits=2)} | {runs(cpu_ms, digits=0)} | "
                  f"{1000 / statistics.median(cpu_ms):.1f} |")

        print("\n| mobility over the drawn tracks | value |\n|---|---|")
        for name, value in mobility_agreement(units).items():
            print(f"| {name} | {value if isinstance(value, int) else f'{100 * value:.1f} %'} |")
    print(f"\nload average at end {load_average()}")


if __name__ == "__main__":
    main()
