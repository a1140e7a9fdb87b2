"""Shards: encodings, every Scene field round trip, source forms, corrupt shards, the shard plan."""

import json
import tarfile
import zlib

import cv2
import numpy as np
import pytest

from c4d_core.errors import UserError
from datagen import Scene, read_scenes
from datagen.codecs import (ARRAY_FIELDS, DECODE_ERRORS, JSON_FIELDS, QUANTISED, RECORD_FIELDS,
                            decode_array, dequantise, encode_array, quantise)
from datagen.scene import EVENT_KEYS
from datagen.jobs import ShardPlan, resolve_task
from datagen.shards import (
    ShardWriter, decode_scene, encode_scene, iter_samples, list_shards, scene_key,
)


def pinhole(entries: np.ndarray) -> np.ndarray:
    """Random (T,3,3) entries as the camera matrices `decode_scene` accepts:
    [[|a|, b, c], [0, |d|, e], [0, 0, 1]] (the other entries still at full entropy)."""
    cameras = np.triu(entries)
    cameras[:, [0, 1], [0, 1]] = np.abs(cameras[:, [0, 1], [0, 1]])
    cameras[:, 2] = [0, 0, 1]
    return cameras


def synthetic_scene(seed=0, frames=4, height=12, width=10, num_objects=3, num_tracks=7,
                    num_events=5):
    """A Scene with random values of the contract's dtypes and shapes (float labels at full
    entropy; the quantised layers on their 16-bit grid, so they too round-trip exactly)."""
    rng = np.random.default_rng(seed)
    t, h, w, k, n = frames, height, width, num_objects, num_tracks

    def f32(*shape):
        return (rng.standard_normal(shape) * 10).astype(np.float32)

    def grid(name):
        return dequantise(rng.integers(0, 65536, (t, h, w, 3)).astype(np.uint16), *QUANTISED[name])

    boxes = rng.random((k, t, 4)).astype(np.float32)
    boxes[0, 1] = np.nan  # object 0 hidden at frame 1
    instances = {"bbox_3d": f32(k, t, 8, 3), "bbox_2d": boxes,
                 "visible_pixels": rng.integers(0, 99, (k, t)).astype(np.int32),
                 "image_position": f32(k, t, 2), "velocity": f32(k, t, 3),
                 "angular_velocity": f32(k, t, 3), "is_dynamic": rng.random(k) < 0.5}
    events = {key: (rng.integers(-1, k, (num_events, *shape)) if dtype.kind == "i" else
                    rng.standard_normal((num_events, *shape)) * 10).astype(dtype)
              for key, (dtype, shape) in EVENT_KEYS.items()}

    return Scene(
        rgb=rng.integers(0, 256, (t, h, w, 3), dtype=np.uint8),
        depth=rng.uniform(0.5, 50, (t, h, w)).astype(np.float32),
        segmentation=rng.integers(0, k + 1, (t, h, w)).astype(np.int32),
        flow_fwd=f32(t, h, w, 2),
        flow_bwd=f32(t, h, w, 2),
        intrinsics=pinhole(f32(t, 3, 3)),
        cam_to_world=f32(t, 4, 4),
        object_to_world=f32(k, t, 4, 4),
        objects=[{"asset_id": f"primitive/box{i}", "scale": 1.5 + i, "mass": 2.0, "tossed": i == 0,
                  "color": [0.1, 0.2, 0.3]} for i in range(k)],
        tracks=f32(n, t, 2),
        occluded=rng.random((n, t)) < 0.3,
        query_frame=rng.integers(0, t, n).astype(np.int32),
        track_object=rng.integers(0, k + 1, n).astype(np.int32),
        tracks_world=f32(n, t, 3),
        displacement=np.abs(f32(n, t)),
        moving=rng.random((n, t)) < 0.5,
        normal=grid("normal"), object_coordinates=grid("object_coordinates"),
        instances=instances, events=events,
        meta={"preset": "movi-e", "seed": seed, "scene_index": 3, "fps": 12.0,
              "resolution": [h, w], "motion_blur": 0.0, "mobility_threshold": 0.01},
    )


def assert_scenes_equal(a: Scene, b: Scene):
    for name in Scene.field_names():
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert isinstance(y, np.ndarray) and x.dtype == y.dtype and x.shape == y.shape, name
            assert np.array_equal(x, y), name  # bit-exact, float labels included
        elif isinstance(x, dict) and name in ("instances", "events"):
            assert isinstance(y, dict) and list(x) == list(y), name
            for key in x:
                assert x[key].dtype == y[key].dtype and x[key].shape == y[key].shape, key
                assert x[key].tobytes() == y[key].tobytes(), key  # NaN where hidden included
        else:
            assert x == y, name


def write_shard(path, scenes, split="train", first_index=0):
    with ShardWriter(path) as writer:
        for i, scene in enumerate(scenes):
            writer.write(encode_scene(scene, scene_key(split, first_index + i)))
    return path


def test_array_codec_is_exact_for_every_dtype_and_special_values():
    rng = np.random.default_rng(0)
    special = np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 1e-45, 3.4e38], np.float32)
    arrays = [special, rng.standard_normal((3, 5, 7)).astype(np.float32), rng.random((4, 2)) < 0.5,
              rng.integers(-5, 5, (6,)).astype(np.int32), np.zeros((0, 3), np.float32),
              rng.standard_normal((2, 2))]
    for array in arrays:
        out = decode_array(encode_array(array))
        assert out.dtype == array.dtype and out.shape == array.shape
        assert out.tobytes() == array.tobytes()  # same bits, NaN and -0.0 included


def test_array_members_are_plain_zlib_streams_both_ways():
    """`.npy.bsz` is written by ISA-L's deflate, but the format is a zlib stream: Python's zlib
    (FORMAT.md's reader) reads what we write, and members written by zlib (shards made before
    ISA-L) decode to the same array."""
    rng = np.random.default_rng(1)
    depth = rng.uniform(1, 30, (4, 16, 16)).astype(np.float32)
    depth[:, :8] = 40.0  # runs, as the backdrop gives
    member = encode_array(depth)
    raw = zlib.decompress(member)  # the .npy v1 header, then the byte planes
    header = raw[:len(raw) - depth.nbytes]
    assert header.startswith(b"\x93NUMPY\x01\x00")
    planes = np.frombuffer(raw[len(header):], np.uint8).reshape(4, -1)  # (itemsize, n)
    assert planes.T.tobytes() == depth.tobytes()
    by_zlib = zlib.compress(raw, 1)
    assert by_zlib != member  # another deflate, another stream
    assert decode_array(by_zlib).tobytes() == depth.tobytes()
    with pytest.raises(DECODE_ERRORS):
        decode_array(member[:-7])  # truncated


def test_every_field_round_trips_exactly(tmp_path):
    scene = synthetic_scene()
    assert_scenes_equal(decode_scene(encode_scene(scene, "train-00000003")), scene)
    (read,) = read_scenes(write_shard(tmp_path / "train-000000.tar", [scene]))
    assert_scenes_equal(read, scene)


def test_segmentation_above_255_and_absent_fields(tmp_path):
    scene = synthetic_scene(num_objects=300)
    scene.segmentation[0, 0, 0] = 300
    for name in ("depth", "flow_fwd", "flow_bwd", "object_to_world", "tracks_world", "moving",
                 "normal", "object_coordinates", "instances", "events"):
        setattr(scene, name, None)
    out = decode_scene(encode_scene(scene, "k"))
    assert_scenes_equal(out, scene)
    assert out.depth is None and out.moving is None


def test_decode_only_requested_fields():
    scene = synthetic_scene()
    out = decode_scene(encode_scene(scene, "k"), fields=["rgb", "tracks", "occluded"])
    assert np.array_equal(out.rgb, scene.rgb) and np.array_equal(out.tracks, scene.tracks)
    assert out.depth is None and out.flow_fwd is None and out.meta is None
    with pytest.raises(UserError, match="unknown Scene fields"):
        decode_scene(encode_scene(scene, "k"), fields=["rgbd"])


def test_format_1_rgb_png_is_still_read_and_skipped_members_are_not_read(tmp_path):
    scene = synthetic_scene()
    sample = encode_scene(scene, "train-00000000")
    t, h, w, _ = scene.rgb.shape
    _, png = cv2.imencode(".png", scene.rgb.reshape(t * h, w, 3)[..., ::-1])  # stacked BGR frames
    format_1 = {("rgb.png" if k == "rgb.npy" else k): (png.tobytes() if k == "rgb.npy" else v)
                for k, v in sample.items() if k != "checksums.json"}  # format 1 had no checksums
    shard = tmp_path / "train-000000.tar"
    with ShardWriter(shard) as writer:
        writer.write(format_1)
        writer.write({**sample, "__key__": "train-00000001"})
    old, new = iter_samples(shard, fields=["rgb", "tracks"])
    assert set(old) == {"__key__", "__url__", "__members__", "rgb.png", "tracks.npy.bsz",
                        "intrinsics.npy.bsz", "meta.json"}  # skipped: depth, flow, ...
    assert set(new) == set(old) - {"rgb.png"} | {"rgb.npy", "checksums.json"}
    assert "depth.npy.bsz" in new["__members__"] and "depth.npy.bsz" not in new
    for raw in (old, new):
        out = decode_scene(raw, fields=["rgb", "tracks"])
        assert np.array_equal(out.rgb, scene.rgb) and np.array_equal(out.tracks, scene.tracks)
        assert out.rgb.flags.writeable and out.depth is None
    del sample["rgb.npy"], sample["checksums.json"]  # e.g. a future format's rgb member
    with pytest.raises(UserError, match="no rgb member"):
        decode_scene(sample, fields=["rgb"])
    assert decode_scene(sample, fields=["tracks"]).rgb is None


def test_encode_rejects_contract_violations():
    scene = synthetic_scene()
    scene.segmentation = scene.segmentation.astype(np.int64)
    with pytest.raises(ValueError, match="segmentation"):
        encode_scene(scene, "k")
    with pytest.raises(ValueError, match="key"):
        encode_scene(synthetic_scene(), "a.b")


def test_shards_are_byte_reproducible_and_webdataset_readable(tmp_path):
    import webdataset as wds

    scenes = [synthetic_scene(seed) for seed in range(3)]
    a = write_shard(tmp_path / "a.tar", scenes)
    b = write_shard(tmp_path / "b.tar", scenes)
    assert a.read_bytes() == b.read_bytes()
    samples = list(wds.WebDataset(str(a), shardshuffle=False, empty_check=False))
    assert [s["__key__"] for s in samples] == [scene_key("train", i) for i in range(3)]
    for sample, scene in zip(samples, scenes):
        assert_scenes_equal(decode_scene(sample), scene)


def test_source_forms_and_order(tmp_path):
    scenes = [synthetic_scene(seed) for seed in range(5)]
    write_shard(tmp_path / "train-000001.tar", scenes[3:], first_index=3)
    write_shard(tmp_path / "train-000000.tar", scenes[:3])
    (tmp_path / "train-000002.tar.partial").write_bytes(b"half a shard")
    expected = [s.meta["seed"] for s in scenes]

    def seeds(source, **kw):
        return [s.meta["seed"] for s in read_scenes(source, **kw)]

    assert seeds(tmp_path) == expected
    assert seeds(str(tmp_path / "train-*.tar")) == expected
    assert seeds([tmp_path / "train-000001.tar", tmp_path / "train-000000.tar"]) == expected[3:] + expected[:3]
    assert seeds(tmp_path / "train-000001.tar") == expected[3:]
    assert seeds(tmp_path, split="train") == expected
    write_shard(tmp_path / "val-000000.tar", scenes[:1], split="val")
    with pytest.raises(UserError, match="several splits"):
        list_shards(tmp_path)
    assert seeds(tmp_path, split="val") == expected[:1]
    with pytest.raises(UserError, match="does not exist"):
        list_shards(tmp_path / "nope")
    with pytest.raises(UserError, match="no shard matches"):
        list_shards(str(tmp_path / "x-*.tar"))


def test_truncated_shard_names_shard_and_scene(tmp_path):
    shard = write_shard(tmp_path / "train-000000.tar", [synthetic_scene(seed, height=64, width=64) for seed in range(3)])
    data = shard.read_bytes()
    with tarfile.open(shard) as tar:
        members = tar.getmembers()
    cut = next(m for m in members if m.name.startswith("train-00000001.rgb"))
    shard.write_bytes(data[: cut.offset_data + cut.size // 2])  # inside a member's data
    with pytest.raises(UserError, match=r"train-000000\.tar.*train-00000001"):
        list(read_scenes(shard))
    for end in (cut.offset, cut.offset + 100):  # at a scene boundary, inside a header
        shard.write_bytes(data[:end])
        with pytest.raises(UserError, match=r"train-000000\.tar.*train-00000000"):
            list(read_scenes(shard))


def test_corrupt_member_names_shard_and_scene(tmp_path):
    scene = synthetic_scene()
    sample = encode_scene(scene, "train-00000007")
    sample["depth.npy.bsz"] = sample["depth.npy.bsz"][:-20] + bytes(20)
    with pytest.raises(UserError, match=r"train-00000007.*rgb\.npy"):
        decode_scene({**sample, "rgb.npy": sample["rgb.npy"][:-3]})
    without_checksums = {k: v for k, v in sample.items() if k != "checksums.json"}  # format 2
    with pytest.raises(UserError, match=r"train-00000007.*depth\.npy\.bsz.* is corrupt"):
        decode_scene(without_checksums)  # the inflate's own error, as one line
    write_shard_path = tmp_path / "train-000000.tar"
    with ShardWriter(write_shard_path) as writer:
        writer.write(sample)
    with pytest.raises(UserError, match=r"train-00000007.*train-000000\.tar.*depth"):
        list(read_scenes(write_shard_path))
    not_a_tar = tmp_path / "junk.tar"
    not_a_tar.write_bytes(b"\x01" * 1500)
    with pytest.raises(UserError, match="junk.tar"):
        list(read_scenes(not_a_tar))


def test_failed_writer_leaves_no_shard_and_no_partial(tmp_path):
    path = tmp_path / "train-000000.tar"
    with pytest.raises(RuntimeError):
        with ShardWriter(path) as writer:
            writer.write(encode_scene(synthetic_scene(), "train-00000000"))
            raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []


def test_plan_and_tasks_cover_every_scene_exactly_once():
    plan = ShardPlan("train", num_scenes=23, scenes_per_shard=4)
    assert plan.num_shards == 6 and list(plan.scenes_of(5)) == [20, 21, 22]
    assert plan.shard_name(5) == "train-000005.tar"
    for num_tasks in (1, 2, 3, 7):
        covered = [i for task in range(num_tasks)
                   for shard in plan.shards_of_task(task, num_tasks) for i in plan.scenes_of(shard)]
        assert sorted(covered) == list(range(23))
    with pytest.raises(UserError):
        ShardPlan("train", 0, 4)
    with pytest.raises(UserError):
        ShardPlan("tr-ain", 5, 4)


def test_task_resolution_from_flags_and_environment():
    assert resolve_task(None, None, {}) == (0, 1)
    assert resolve_task(2, 4, {"RANK": "1", "WORLD_SIZE": "2"}) == (2, 4)
    slurm = {"SLURM_ARRAY_TASK_ID": "5", "SLURM_ARRAY_TASK_COUNT": "8", "SLURM_ARRAY_TASK_MIN": "1"}
    assert resolve_task(None, None, slurm) == (4, 8)
    assert resolve_task(None, None, {"RANK": "3", "WORLD_SIZE": "4"}) == (3, 4)
    for bad in ((4, 4, {}), (1, None, {}), (-1, 2, {})):
        with pytest.raises(UserError):
            resolve_task(*bad)
    with pytest.raises(UserError, match="RANK"):
        resolve_task(None, None, {"RANK": "x", "WORLD_SIZE": "2"})


def test_json_fields_accept_numpy_values():
    scene = synthetic_scene()
    scene.meta = {"seed": np.int64(3), "size": np.array([2, 3]), "blur": np.float32(0.5), "t": (1, 2)}
    out = decode_scene(encode_scene(scene, "k"))
    assert out.meta == {"seed": 3, "size": [2, 3], "blur": 0.5, "t": [1, 2]}
    assert json.dumps(out.meta)


def test_contract_table_matches_scene_fields():
    assert set(ARRAY_FIELDS) | set(JSON_FIELDS) | set(RECORD_FIELDS) == set(Scene.field_names())


def test_quantised_layers_are_within_half_a_step_and_stable():
    rng = np.random.default_rng(1)
    for name, (low, high) in QUANTISED.items():
        value = rng.uniform(low, high, (5, 4, 3, 3)).astype(np.float32)
        value[0, 0, 0] = [low, high, (low + high) / 2]
        steps = quantise(value, low, high)
        back = dequantise(steps, low, high)
        assert back.dtype == np.float32
        assert np.abs(back - value).max() <= (high - low) / 65535 / 2 * 1.02, name
        np.testing.assert_array_equal(quantise(back, low, high), steps)  # a re-encode is exact
        assert back[0, 0, 0].tolist() == [low, high, pytest.approx((low + high) / 2, abs=2e-5)]


def test_old_samples_without_the_optional_layers_read_them_as_none():
    """A sample written before the optional layers existed (no such members) still reads."""
    sample = encode_scene(synthetic_scene(), "train-00000000")
    optional = ("normal.u16.npy.bsz", "object_coordinates.u16.npy.bsz", "instances.npy.bsz",
                "events.npy.bsz")
    assert set(optional) <= set(sample)
    old = {k: v for k, v in sample.items() if k not in optional and k != "checksums.json"}
    out = decode_scene(old)
    assert out.normal is None and out.object_coordinates is None
    assert out.instances is None and out.events is None
    assert np.array_equal(out.tracks, synthetic_scene().tracks)


def test_instances_of_the_wrong_layout_are_refused():
    scene = synthetic_scene()
    scene.instances["velocity"] = scene.instances["velocity"].astype(np.float64)
    with pytest.raises(ValueError, match="velocity"):
        encode_scene(scene, "k")
