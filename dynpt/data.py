"""Training clips from datagen shards: a resumable, deterministic streaming pipeline.

Per scene: choose a clip (T frames at a random stride), augment it (dynpt.augment), then sample
N tracks that are visible at their query frame -- at their first visible frame, or (for a
`random_query_fraction` of them) at a random visible frame. A sample is a dict of numpy arrays:
`video` uint8 (T,H,W,3), `queries` float32 (N,3) as (t, x, y), `tracks` float32 (T,N,2),
`visible` bool (T,N), `moving` bool (T,N), and, from `ShardStream`, `key` (the scene's shard
key, e.g. `train-00000042`) and `position` int64 (the stream state after it).

`ShardStream` streams one or more sources mixed with weights: shard sets, and other projects'
Kubric data (TFDS MOVi records, CoTracker or Kubric worker folders: `datagen.foreign`), whose
scenes ("units") are listed once and shared out like shards, each one a sample (tracks drawn with
the training seed, mobility by `data.mobility_rule`, "point" unless set). A damaged unit stops
training with one line naming it, or with `data.foreign=skip` is skipped with a warning and
counted as bad. Every DDP rank and DataLoader
worker reads its own slice ("split") of the shards (or of the samples, when there are fewer
shards than splits). Per source and epoch, shards are permuted and samples pass a shuffle
buffer, all seeded by (seed, source, epoch, split). Per sample, the source choice and the
augmentation are seeded by (seed, split, sample counter). So the stream is a pure function of
the seed and the position; `position` lets `--resume` continue exactly: the worker re-reads (but
does not decode) the samples already taken from the current epoch of each source.

Bad data (webdataset's warn-and-continue): a corrupt or incomplete sample, or the unreadable rest
of a truncated shard, is skipped with a warning naming shard and sample and counted (the rest of a
shard as the scenes it lost, when the dataset file beside it tells; else as one); every sample
carries `counts` int64 [read, bad] of its loader split. A split stops with a `UserError` once
more than `data.max_bad_fraction` of its samples are bad (counted from 100 samples on).
Data of another dataset in a source folder (`datagen.shards.ForeignData`: a shard not of its
pattern or beyond its `num_shards`, a scene of another seed, size or config, a misplaced or
repeated key) stops training with one line, or with `data.foreign=skip` is skipped with a
warning (the rest of that shard; not counted as bad).

A scene whose clip has no track that is finite, visible in it and within `data.max_offscreen_px`
of the crop gives no sample and is passed over, not counted as bad: a random clip of good data
can miss every track. But where `FRUITLESS_IN_A_ROW` scenes of one source in a row give no sample
(bad ones included, so that not even data.max_bad_fraction=1 reads forever), the source has no
usable scene (its tracks all NaN, say): the split stops with a `UserError` naming the source
instead of drawing from it forever. A sample from the source starts the count again.
"""

from __future__ import annotations

import logging
import os
from typing import Iterator, Sequence

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from c4d_core.errors import UserError
from datagen.foreign import SHARDS, options_from, read_unit, source_kind, source_units
from datagen.scene import Scene
from datagen.shards import ForeignData, decode_scene, iter_samples, list_shards, lost_scenes
from dynpt.augment import augment_clip
from dynpt.device import pin_memory

log = logging.getLogger(__name__)

TRAIN_FIELDS = ("rgb", "tracks", "occluded", "moving", "query_frame")
MIN_COUNTED = 100  # the bad-sample limit is a fraction of at least this many samples
FRUITLESS_IN_A_ROW = 100  # scenes of one source in a row without a sample: it has no usable data


def too_many_bad(bad: int, read: int, max_fraction: float) -> bool:
    """True once `bad` of `read` samples exceed the allowed fraction (of at least MIN_COUNTED)."""
    return bad > max_fraction * max(read, MIN_COUNTED)


# --- one sample ---------------------------------------------------------------------------------


def choose_clip(scene: Scene, num_frames: int, max_stride: int, rng: np.random.Generator) -> dict:
    """A clip of `num_frames` frames at a random stride in [1, max_stride] and random start.

    Returns `rgb` (T,H,W,3), `tracks` (T,N,2), `occluded` (T,N), `moving` (T,N) (time first).
    """
    total = scene.num_frames
    if total < num_frames:
        raise UserError(
            f"scenes have {total} frames but data.num_frames={num_frames}; set "
            f"data.num_frames<={total} or generate longer scenes"
        )
    if scene.moving is None:
        raise UserError("scenes have no `moving` labels; generate them with a datagen preset that "
                        "computes 3-D tracks (tracks_world)")
    stride = int(rng.integers(1, max(1, min(max_stride, (total - 1) // max(num_frames - 1, 1))) + 1))
    start = int(rng.integers(0, total - (num_frames - 1) * stride))
    frames = slice(start, start + (num_frames - 1) * stride + 1, stride)  # T frames, views
    return {"rgb": scene.rgb[frames], **scene.tracks_time_major(frames)}


def sample_tracks(clip: dict, num_tracks: int, random_query_fraction: float,
                  rng: np.random.Generator, max_offscreen_px: float = np.inf,
                  moving_fraction: float = 0.0) -> dict | None:
    """Pick `num_tracks` tracks visible somewhere in the clip and a visible query frame for each.

    A fraction `random_query_fraction` of them is queried at a uniformly random visible frame,
    the rest at their first visible frame. Tracks are drawn without replacement when there are
    enough, else with replacement. Tracks that go more than `max_offscreen_px` outside the frame
    (e.g. behind the camera) are not drawn: their positions would dominate the occluded-point
    loss. `moving_fraction` > 0 balances the classes of the mobility head: up to that fraction
    of the tracks is drawn among those moving in some frame of the clip (as many as there are,
    without replacement), the rest among all. Returns the model sample, or None if no track
    qualifies.
    """
    visible = ~clip["occluded"]  # (T,N)
    h, w = clip["rgb"].shape[1:3]
    xy = clip["tracks"]  # (T,N,2)
    outside = np.maximum(np.maximum(-xy, xy - [w - 1, h - 1]), 0).max(axis=(0, 2))  # (N,) px
    near = np.isfinite(xy).all(axis=(0, 2)) & (outside <= max_offscreen_px)
    candidates = np.flatnonzero(visible.any(axis=0) & near)
    if candidates.size == 0:
        return None
    movers = candidates[clip["moving"][:, candidates].any(axis=0)]
    num_movers = min(int(round(moving_fraction * num_tracks)), movers.size)
    chosen_movers = rng.choice(movers, num_movers, replace=False) if num_movers else movers[:0]
    rest = np.setdiff1d(candidates, chosen_movers)
    if rest.size == 0:  # every candidate already drawn: the rest are repeats
        rest = candidates
    chosen = np.concatenate([chosen_movers, rng.choice(
        rest, num_tracks - num_movers, replace=rest.size < num_tracks - num_movers)])  # (N',)
    vis = visible[:, chosen]  # (T,N')
    first = vis.argmax(axis=0)  # (N',)
    random_pick = rng.random(num_tracks) < random_query_fraction
    # A uniformly random visible frame: the k-th visible one, k uniform in [0, count).
    kth = (rng.random(num_tracks) * vis.sum(axis=0)).astype(int)  # (N',)
    random_frame = np.argmax(np.cumsum(vis, axis=0) > kth, axis=0)  # (N',)
    query_t = np.where(random_pick, random_frame, first)  # (N',)
    tracks = clip["tracks"][:, chosen]  # (T,N',2)
    query_xy = tracks[query_t, np.arange(num_tracks)]  # (N',2)
    return {
        "video": np.ascontiguousarray(clip["rgb"]),
        "queries": np.concatenate([query_t[:, None], query_xy], axis=1).astype(np.float32),
        "tracks": np.ascontiguousarray(tracks, dtype=np.float32),
        "visible": vis,
        "moving": clip["moving"][:, chosen],
    }


def make_training_sample(scene: Scene, data_cfg, rng: np.random.Generator) -> dict | None:
    """Clip, augment and sample tracks from one scene, as configured in `data:`."""
    clip = choose_clip(scene, data_cfg.num_frames, data_cfg.max_stride, rng)
    clip = augment_clip(clip, data_cfg.augment, tuple(data_cfg.crop_size), rng)
    return sample_tracks(clip, data_cfg.num_tracks, data_cfg.random_query_fraction, rng,
                         data_cfg.max_offscreen_px, data_cfg.moving_track_fraction)


# --- the stream ---------------------------------------------------------------------------------


def _rng(*key: int) -> np.random.Generator:
    return np.random.default_rng([int(k) for k in key])


class ShardStream(IterableDataset):
    """An endless, seeded stream of training samples over weighted shard sets.

    sources: shard sources (anything `datagen.shards.list_shards` accepts), mixed by `weights`.
    rank, world_size: this DDP process. `start`: {split: position} from a checkpoint.
    A position is [n, epoch_0, taken_0, epoch_1, taken_1, ...]: the split's sample counter and,
    per source, its epoch and the samples already taken from that epoch.
    """

    def __init__(self, sources: Sequence, weights: Sequence[float], data_cfg, seed: int,
                 rank: int = 0, world_size: int = 1, start: dict[int, list[int]] | None = None):
        if len(sources) != len(weights) or not sources:
            raise UserError(f"data.sources ({len(sources)}) and data.weights ({len(weights)}) "
                            "must be non-empty lists of the same length")
        if min(weights) < 0 or sum(weights) <= 0:
            raise UserError(f"data.weights must be >= 0 with a positive sum, got {list(weights)}")
        self.names = [str(s) for s in sources]
        self.kinds = [source_kind(s) for s in sources]
        # per source: its shard paths, or the units (scenes) of another project's data
        self.shards = [[str(p) for p in list_shards(s)] if kind == SHARDS else source_units(s)
                       for s, kind in zip(sources, self.kinds)]
        self.options = options_from(data_cfg, seed, TRAIN_FIELDS)
        self.probs = np.asarray(weights, float) / float(sum(weights))
        self.cfg, self.seed = data_cfg, int(seed)
        self.rank, self.world_size = rank, world_size
        self.start = start or {}

    def _raw(self, source: int, epoch: int, split: int, num_splits: int) -> Iterator[dict]:
        """Raw (undecoded) samples of one epoch of one source for this split, shuffled."""
        if self.kinds[source] != SHARDS:
            yield from self._units(source, epoch, split, num_splits)
            return
        shards = self.shards[source]
        order = _rng(self.seed, source, epoch).permutation(len(shards))
        by_shard = len(shards) >= num_splits
        mine = order[split::num_splits] if by_shard else order
        buffer: list[dict] = []
        rng = _rng(self.seed, source, epoch, split, 1)
        index = 0
        for shard_id in mine:
            read = 0
            try:
                for sample in iter_samples(shards[shard_id], TRAIN_FIELDS):
                    index, read = index + 1, read + 1
                    if not by_shard and (index - 1) % num_splits != split:
                        continue
                    buffer.append(sample)
                    if len(buffer) >= self.cfg.shuffle_buffer:
                        yield buffer.pop(int(rng.integers(len(buffer))))
            except ForeignData as exc:  # not part of the dataset: refused, or skipped on request
                if self.cfg.foreign != "skip":
                    raise UserError(f"{exc} (or set data.foreign=skip to skip such shards with a "
                                    "warning)") from None
                log.warning("skipping the rest of a shard of another dataset: %s", exc)
            except UserError as exc:  # a truncated or damaged tar: its rest is lost
                lost = lost_scenes(shards[shard_id], read)
                mine_lost = lost if by_shard else sum(
                    i % num_splits == split for i in range(index, index + lost))
                index += lost  # the samples after the shard keep their splits
                self._counts[0] += mine_lost  # counted as read: they were due
                self._bad(exc, mine_lost)
        while buffer:
            yield buffer.pop(int(rng.integers(len(buffer))))

    def _units(self, source: int, epoch: int, split: int, num_splits: int) -> Iterator[dict]:
        """One epoch of a foreign source for this split: its units (scenes) in a seeded
        permutation, every `num_splits`-th from `split` on, each a raw sample naming its unit
        (read and decoded only when taken, so a resume passes over the taken ones unread)."""
        units = self.shards[source]
        for i in _rng(self.seed, source, epoch).permutation(len(units))[split::num_splits]:
            yield {"__key__": units[i].name, "__url__": units[i].path, "__unit__": units[i]}

    def _decode(self, raw: dict) -> Scene:
        """The Scene of a raw sample: a shard's members decoded, or a foreign unit read. A
        damaged unit is refused with one line unless `data.foreign=skip` (then it is counted as
        bad, as a damaged shard sample is)."""
        if "__unit__" not in raw:
            return decode_scene(raw, TRAIN_FIELDS)
        try:
            return read_unit(raw["__unit__"], self.options)
        except UserError as exc:
            if self.cfg.foreign != "skip":
                raise _Refused(f"{exc} (or set data.foreign=skip to skip such scenes with a "
                               "warning)") from None
            raise

    def _source(self, source: int, epoch: int, taken: int, split: int, num_splits: int,
                state: list[int]) -> Iterator[dict]:
        """Endless raw samples of one source from (epoch, taken); keeps `state` up to date."""
        while True:
            count = 0
            for count, sample in enumerate(self._raw(source, epoch, split, num_splits), 1):
                if count <= taken:
                    continue  # already consumed before the resume: read, not decoded
                state[1 + 2 * source: 3 + 2 * source] = [epoch, count]
                yield sample
            if count == 0:
                raise UserError(f"shard set {source} has no samples for split {split} of "
                                f"{num_splits}; use fewer workers/GPUs or more scenes")
            epoch, taken = epoch + 1, 0

    def _bad(self, exc: UserError, count: int = 1) -> None:
        """Count and report `count` bad samples (one, or the lost rest of an unreadable shard);
        stop past the limit."""
        if count == 0:  # the lost samples were another split's
            return
        read, bad = self._counts[0], self._counts[1] + count
        self._counts[1] = bad
        log.warning("skipping bad training data (%d of %d samples bad so far): %s", bad, read, exc)
        if too_many_bad(bad, read, float(self.cfg.max_bad_fraction)):
            raise UserError(
                f"{bad} of {read} training samples are bad, more than data.max_bad_fraction="
                f"{self.cfg.max_bad_fraction}; last: {exc} (check the data with `c4d inspect "
                "SOURCE --check`, or raise data.max_bad_fraction)")

    def _fruitless(self, source: int, raw: dict, why: str) -> None:
        """Count a scene of `source` that gave no sample (`why`); stop once FRUITLESS_IN_A_ROW
        scenes of it in a row gave none."""
        self._in_a_row[source] += 1
        if self._in_a_row[source] >= FRUITLESS_IN_A_ROW:
            name = self.names[source]
            raise UserError(
                f"no scene of data.sources[{source}] ({name}) gives a training sample: none of "
                f"{self._in_a_row[source]} in a row did (last: scene {raw['__key__']} of "
                f"{raw['__url__']}: {why}); check the data with `c4d inspect {name} --check`, "
                "or leave the source out")

    def __iter__(self) -> Iterator[dict]:
        self._counts = [0, 0]  # [read, bad] of this split, since this iterator started
        self._in_a_row = [0] * len(self.shards)  # per source: its last scenes without a sample
        info = get_worker_info()
        worker, num_workers = (info.id, info.num_workers) if info else (0, 1)
        num_splits = self.world_size * num_workers
        split = self.rank * num_workers + worker
        state = list(self.start.get(split, [0] + [0, 0] * len(self.shards)))
        streams = [self._source(s, state[1 + 2 * s], state[2 + 2 * s], split, num_splits, state)
                   for s in range(len(self.shards))]
        while True:
            n = state[0]
            source = int(_rng(self.seed, split, n, 0).choice(len(self.probs), p=self.probs))
            raw = next(streams[source])
            state[0] = n + 1
            self._counts[0] += 1
            try:
                scene = self._decode(raw)
            except _Refused:
                raise
            except UserError as exc:
                self._bad(exc)
                self._fruitless(source, raw, str(exc))
                continue
            try:
                sample = make_training_sample(scene, self.cfg, _rng(self.seed, split, n, 1))
            except UserError as exc:
                raise UserError(f"sample {raw['__key__']} of {raw['__url__']}: {exc}") from exc
            if sample is None:
                self._fruitless(source, raw, "no track is finite, visible in the clip and within "
                                f"data.max_offscreen_px={self.cfg.max_offscreen_px} of the crop")
                continue
            self._in_a_row[source] = 0
            yield {**sample, "key": raw["__key__"],
                   "position": np.array([split, num_splits] + state, np.int64),
                   "counts": np.array(self._counts, np.int64)}


class _Refused(UserError):
    """A damaged foreign unit, refused: it stops training instead of being counted as bad."""


def _init_worker(worker_id: int) -> None:
    """One thread per loader worker: the workers already use every core between them."""
    cv2.setNumThreads(1)
    torch.set_num_threads(1)


# OpenCV's thread pool (pthreads) is not fork-safe: a forked loader worker inherits the pool's
# list of threads but not the threads, and `_init_worker`'s `cv2.setNumThreads(1)` then joins
# threads that exist only in the parent: the worker waits forever with its CPU idle, and so does
# the loader (benchmarks/device_check.py's loader section, whose 0-worker row had started the
# pool, hung so). So before every fork of this process the pool is emptied (one thread: the
# caller's alone) and its size restored in the parent afterwards; the child starts with none.
_opencv_threads: list[int] = []  # the pool size of each fork under way


def _stop_opencv_threads() -> None:
    _opencv_threads.append(cv2.getNumThreads())
    cv2.setNumThreads(1)  # joins the pool's idle threads


def _restore_opencv_threads() -> None:
    cv2.setNumThreads(_opencv_threads.pop())


os.register_at_fork(before=_stop_opencv_threads, after_in_parent=_restore_opencv_threads)


def make_loader(stream: ShardStream, batch_size: int, num_workers: int,
                device_type: str = "cpu") -> DataLoader:
    """A DataLoader over `stream` for batches going to `device_type` (pinned memory on a GPU):
    batches come from workers in turn, so the order is fixed."""
    return DataLoader(stream, batch_size=batch_size, num_workers=num_workers,
                      persistent_workers=num_workers > 0, pin_memory=pin_memory(device_type),
                      prefetch_factor=2 if num_workers > 0 else None,
                      worker_init_fn=_init_worker if num_workers > 0 else None)


class StreamPosition:
    """The resume state of one rank's loader: the last consumed position of every split."""

    def __init__(self):
        self.splits: dict[int, list[int]] = {}
        self.num_splits: int | None = None

    def update(self, positions: torch.Tensor) -> None:
        """positions: (B, 2 + 1 + 2*S) int64 from a batch; rows are in stream order."""
        for row in positions.tolist():
            self.splits[row[0]] = row[2:]
            self.num_splits = row[1]

    def state_dict(self) -> dict:
        return {"splits": dict(self.splits), "num_splits": self.num_splits}


def merge_positions(states: Sequence[dict], num_splits: int) -> dict[int, list[int]]:
    """The `start` of a ShardStream from the positions of all ranks; {} if the layout changed."""
    merged: dict[int, list[int]] = {}
    for state in states:
        if state.get("num_splits") not in (None, num_splits):
            log.warning("data position was saved with %s loader splits, now %d: the data stream "
                        "restarts (training resumes, but not on the exact same samples)",
                        state["num_splits"], num_splits)
            return {}
        merged.update({int(k): list(v) for k, v in state["splits"].items()})
    return merged
