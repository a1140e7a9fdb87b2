"""TFDS MOVi records read without TensorFlow (datagen/foreign/tfds_movi.py) and the source dispatch
(datagen/foreign/__init__.py), on small records that tests/foreign_writers.py writes from the
format's facts out of our own scenes: they must read back as those scenes (labels equal, depth
and flows within one uint16 step, cameras within 1e-5, tracks as TAP-Vid-Kubric's recipe draws
them on the original scene with the same seed); training, eval and inspect read them; bad input
is one line naming the problem.
"""

from __future__ import annotations

import logging
from dataclasses import replace
import struct

import numpy as np
import pytest

from c4d.cli import main
from c4d_core.config import load_config
from c4d_core.errors import UserError
from datagen.annotate import tapvid_kubric_tracks
from datagen.foreign import (ReadOptions, mobility_labels, object_moving, read_unit, source_kind,
                             source_units)
from datagen.foreign.tfds_movi import (feature_values, masked_crc, parse_example, scan_records,
                                       varints)
from tests.dynpt_testdata import synthetic_shards
from tests.foreign_writers import (damage_record, euclidean_distance, example_bytes,
                                   write_tfds_movi)
from tests.synthetic_scenes import make_box_scene

SEED = 7
H, W, T = 48, 64, 8  # non-square frames: the focal length must be f / sensor * W for both axes


def box_scene(index: int):
    """A box scene with Kubric's lens (35 mm on a 32 mm sensor, horizontal fit)."""
    scene = make_box_scene(num_frames=T, height=H, width=W, focal=35 / 32 * W, seed=index,
                           num_tracks=8)
    scene.meta.update(scene_index=index, mobility_threshold=0.01)
    return scene


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    """(root, scenes): 3 box scenes as split validation (2 files), 1 as split train."""
    root = tmp_path_factory.mktemp("tfds")
    scenes = [box_scene(i) for i in range(3)]
    write_tfds_movi(root, scenes, split="validation", num_files=2)
    write_tfds_movi(root, [box_scene(5)], split="train", num_files=1)
    return root, scenes


@pytest.fixture(scope="module")
def validation(records):
    root, scenes = records
    return f"{root}/movi_e/{H}x{W}/1.0.0:validation", scenes


def step(low: float, high: float) -> float:
    return (high - low) / 65535


def test_records_read_back_as_the_scenes_they_were_written_from(validation):
    source, scenes = validation
    units = source_units(source)
    assert [u.index for u in units] == [0, 1, 2] and "record 0" in units[0].name
    for unit, truth in zip(units, scenes):
        scene = read_unit(unit, ReadOptions(seed=SEED))
        assert np.array_equal(scene.rgb, truth.rgb)
        assert np.array_equal(scene.segmentation, truth.segmentation)
        distance = euclidean_distance(truth.depth.astype(np.float64), truth.intrinsics)
        assert np.abs(scene.depth - truth.depth).max() <= step(distance.min(), distance.max())
        for ours, flow in (("flow_fwd", truth.flow_fwd), ("flow_bwd", truth.flow_bwd)):
            assert np.abs(getattr(scene, ours) - flow).max() <= step(flow.min(), flow.max()) * 1.01
        assert np.abs(scene.intrinsics - truth.intrinsics).max() <= 1e-5
        assert np.abs(scene.cam_to_world - truth.cam_to_world).max() <= 1e-5
        assert np.abs(scene.object_to_world - truth.object_to_world).max() <= 1e-5
        assert [o["asset_id"] for o in scene.objects] == [o["asset_id"] for o in truth.objects]
        assert [o["tossed"] for o in scene.objects] == [o["tossed"] for o in truth.objects]
        # tracks: TAP-Vid-Kubric's recipe on the original scene with the same seed
        drawn = tapvid_kubric_tracks(truth, [SEED, unit.index])
        assert np.array_equal(scene.query_frame, drawn.query_frame)
        assert np.array_equal(scene.track_object, drawn.track_object)
        assert np.abs(scene.tracks - drawn.tracks).max() < 0.01  # px: depth's uint16 steps
        assert np.array_equal(scene.occluded, drawn.occluded)
        assert np.array_equal(scene.moving, drawn.moving)
        assert scene.meta["split"] == "validation" and scene.meta["preset"] == "movi_e"
        assert scene.meta["flow_fwd_valid"] == [True] * T  # Kubric renders beyond both ends


def test_focal_length_is_the_same_for_both_axes_on_non_square_frames(validation):
    """Section 8.4: fx = fy = f / sensor_width * W, the principal point at the centre; the height
    form (f / sw * H) would misplace tracks off the image centre by pixels."""
    scene = read_unit(source_units(validation[0])[0], ReadOptions(seed=SEED))
    K = scene.intrinsics[0]
    assert K[0, 0] == K[1, 1] == pytest.approx(35 / 32 * W)
    assert (K[0, 2], K[1, 2]) == ((W - 1) / 2, (H - 1) / 2)
    wrong = K.astype(np.float64).copy()
    wrong[1, 1] = 35 / 32 * H
    world = scene.tracks_world[:, 0]  # (N,3) the tracks' points at frame 0
    cam = np.linalg.inv(scene.cam_to_world[0].astype(np.float64))
    p = world @ cam[:3, :3].T + cam[:3, 3]
    off = np.abs((p[:, 1] / p[:, 2]) * (wrong[1, 1] - K[1, 1]))
    assert off.max() > 1.0  # the wrong focal length would move these tracks by pixels


def test_layers_of_a_generated_scene_read_back(tmp_path):
    """A real (tiny) generated scene, square, with normals and object coordinates."""
    from datagen.generate import generate_scene

    cfg = load_config("datagen", "movi-e", overrides=[
        "resolution=[32,32]", "frames=6", "objects.num_static=[2,2]", "objects.num_tossed=[1,1]",
        "layers.normal=true", "layers.object_coordinates=true", "layers.instances=true"])
    truth = generate_scene(cfg, 0)
    write_tfds_movi(tmp_path, [truth], num_files=1)
    scene = read_unit(source_units(tmp_path)[0], ReadOptions(seed=SEED))
    assert np.array_equal(scene.segmentation, truth.segmentation)
    assert np.abs(scene.normal - truth.normal).max() <= 2 / 65535 * 1.01
    assert np.abs(scene.object_coordinates - truth.object_coordinates).max() <= 1 / 65535 * 1.01
    assert np.abs(scene.cam_to_world - truth.cam_to_world).max() <= 1e-5
    for key in ("bbox_3d", "velocity", "angular_velocity", "is_dynamic", "visible_pixels"):
        np.testing.assert_array_equal(scene.instances[key], truth.instances[key], err_msg=key)
    np.testing.assert_array_equal(scene.instances["bbox_2d"], truth.instances["bbox_2d"])
    np.testing.assert_allclose(scene.instances["image_position"], truth.instances["image_position"],
                               atol=1e-4)
    drawn = tapvid_kubric_tracks(truth, [SEED, 0])
    assert np.array_equal(scene.query_frame, drawn.query_frame)
    assert np.array_equal(scene.track_object, drawn.track_object)
    assert np.abs(scene.tracks - drawn.tracks).max() < 0.01
    assert (scene.occluded == drawn.occluded).mean() > 0.99  # a point at a depth edge may flip
    fields = ("rgb", "tracks", "occluded", "moving", "query_frame")  # what training reads
    lean = read_unit(source_units(tmp_path)[0], ReadOptions(seed=SEED, fields=fields))
    assert lean.flow_fwd is None and lean.normal is None
    assert np.array_equal(lean.tracks, scene.tracks)


def test_reading_is_deterministic_by_seed(validation):
    unit = source_units(validation[0])[1]
    a, b = (read_unit(unit, ReadOptions(seed=SEED)) for _ in range(2))
    c = read_unit(unit, ReadOptions(seed=SEED + 1))
    assert np.array_equal(a.tracks, b.tracks) and np.array_equal(a.occluded, b.occluded)
    assert not np.array_equal(a.tracks, c.tracks)


def test_example_parser_agrees_with_protobuf():
    rng = np.random.default_rng(0)
    ints = np.concatenate([[0, 1, 127, 128, 16383, 16384, 65535, 2**31, 2**62, -1, -5,
                            np.iinfo(np.int64).min, np.iinfo(np.int64).max],
                           rng.integers(-2**40, 2**40, 500)])
    features = {"a/bytes": [b"", b"x" * 300, bytes(range(256))],
                "b/floats": rng.normal(size=1000).astype(np.float32),
                "c/ints": ints, "d/empty_ints": np.zeros(0, np.int64)}
    data = example_bytes(features)
    parsed = parse_example(data)
    assert set(parsed) == set(features)
    assert feature_values(data, parsed["a/bytes"]) == features["a/bytes"]
    assert np.array_equal(feature_values(data, parsed["b/floats"]), features["b/floats"])
    assert np.array_equal(feature_values(data, parsed["c/ints"]), ints)
    assert feature_values(data, parsed["d/empty_ints"]).size == 0
    # unpacked int64 lists (allowed by protobuf, written by some encoders)
    unpacked = b"".join(b"\x08" + bytes([v]) for v in (3, 5, 127))  # field 1, varint
    assert varints(np.frombuffer(b"\x03\x05\x7f", np.uint8)).tolist() == [3, 5, 127]
    feature = b"\x1a" + bytes([len(unpacked)]) + unpacked  # Feature.int64_list
    entry = b"\x0a\x01k\x12" + bytes([len(feature)]) + feature
    example = b"\x0a" + bytes([len(entry) + 2]) + b"\x0a" + bytes([len(entry)]) + entry
    assert feature_values(example, parse_example(example)["k"]).tolist() == [3, 5, 127]
    with pytest.raises(ValueError):
        varints(np.frombuffer(b"\x80\x80", np.uint8))  # ends inside a value


def test_record_checksums_are_tensorflows():
    """CRC-32C (Castagnoli, check value of "123456789": 0xe3069283), masked as TFRecord does."""
    import crc32c

    assert crc32c.crc32c(b"123456789") == 0xE3069283
    crc = crc32c.crc32c(b"abc")
    assert masked_crc(b"abc") == ((((crc >> 15) | (crc << 17)) & 0xFFFFFFFF) + 0xA282EAD8) % 2**32


def test_object_and_point_mobility():
    """The paper appendix's per-object rule against our per-point label."""
    poses = np.tile(np.eye(4), (3, 5, 1, 1))  # 3 objects, 5 frames
    poses[0, :, 0, 3] = 0.02 * np.arange(5)  # slides 0.02 a frame: moving
    poses[1, :, 0, 3] = 0.005 * np.arange(5)  # creeps 0.005 a frame: not moving
    angle = 0.2 * np.arange(5)  # spins in place about z: its position does not change
    poses[2, :, 0, 0], poses[2, :, 0, 1] = np.cos(angle), -np.sin(angle)
    poses[2, :, 1, 0], poses[2, :, 1, 1] = np.sin(angle), np.cos(angle)
    moving = object_moving(poses, 0.01)  # (K+1,T)
    assert moving.tolist() == [[False] * 5, [True] * 5, [False] * 5, [False] * 5]

    class Drawn:  # a point 1 unit off the spinning object's axis moves 0.2 a frame
        track_object = np.array([0, 3, 1])
        moving = np.array([[False] * 5, [True] * 5, [True] * 5])

    point = mobility_labels(Drawn, poses, ReadOptions(mobility_rule="point"))
    per_object = mobility_labels(Drawn, poses, ReadOptions(mobility_rule="object"))
    assert np.array_equal(point, Drawn.moving)
    assert per_object.tolist() == [[False] * 5, [False] * 5, [True] * 5]
    with pytest.raises(UserError, match="mobility_rule='some' is not a rule"):
        ReadOptions(mobility_rule="some")


def test_object_rule_on_records(validation):
    unit = source_units(validation[0])[0]
    scene = read_unit(unit, ReadOptions(seed=SEED, mobility_rule="object"))
    on_mover = scene.track_object == 3  # the sliding box
    assert scene.moving[on_mover].all() and not scene.moving[~on_mover].any()
    assert scene.meta["mobility_rule"] == "object"


def test_source_kinds_and_splits(records, tmp_path):
    root, _ = records
    version = root / "movi_e" / f"{H}x{W}" / "1.0.0"
    record = sorted(version.glob("*validation.tfrecord*"))[0]
    for source in (root, version, record, f"{version}/movi_e-validation.tfrecord*",
                   f"{version}:validation"):
        assert source_kind(source) == "tfds-movi", source
    assert source_kind(synthetic_shards(3, 3)) == "shards"
    assert len(source_units(f"{version}/movi_e-validation.tfrecord*")) == 3
    assert len(source_units(record)) == 2  # the first file holds 2 of the 3
    assert len(source_units(version, "train")) == 1
    with pytest.raises(UserError, match=r"holds the splits train, validation; name one, e\.g\. "
                                        r".*:validation"):
        source_units(root)
    with pytest.raises(UserError, match="has no split 'test'; its splits: train, validation"):
        source_units(version, "test")
    (tmp_path / "notes.txt").write_text("not data")
    with pytest.raises(UserError) as refused:
        source_kind(tmp_path)
    message = str(refused.value)
    assert "\n" not in message and "no shards" in message
    assert "TFDS MOVi records" in message and "c4d datagen" in message


def test_missing_feature_is_named(tmp_path):
    write_tfds_movi(tmp_path, [box_scene(0)], num_files=1, omit=("depth",))
    with pytest.raises(UserError, match=r"record 0 lacks the features depth, which MOVi records "
                                        "have"):
        read_unit(source_units(tmp_path)[0], ReadOptions())


@pytest.mark.parametrize("how, problem", [
    ("data", "record 1 is damaged: its data fails its CRC-32C checksum"),
    ("length", "is damaged: the length of record 1 fails its checksum"),
    ("cut", "is damaged: the file ends inside record 1"),
])
def test_a_damaged_record_is_named(tmp_path, how, problem):
    folder = write_tfds_movi(tmp_path, [box_scene(0), box_scene(1), box_scene(2)], num_files=1)
    record = next(folder.glob("*.tfrecord*"))
    damage_record(record, 1, how)
    units = source_units(folder)
    assert len(units) == (3 if how == "data" else 2)
    read_unit(units[0], ReadOptions())  # the record before it reads
    with pytest.raises(UserError, match=problem) as raised:
        read_unit(units[1], ReadOptions())
    assert str(record) in str(raised.value) and "\n" not in str(raised.value)


def test_a_file_cut_at_a_record_boundary_is_named_from_its_listed_length(tmp_path):
    folder = write_tfds_movi(tmp_path, [box_scene(0), box_scene(1)], num_files=1)
    record = next(folder.glob("*.tfrecord*"))
    raw = record.read_bytes()
    record.write_bytes(raw[:16 + struct.unpack_from("<Q", raw, 0)[0]])  # record 0 alone
    assert len(scan_records(record)[0]) == 1
    units = source_units(folder)
    with pytest.raises(UserError, match="holds 1 records where its dataset_info.json lists 2"):
        read_unit(units[1], ReadOptions())


@pytest.fixture
def damaged(tmp_path):
    """A validation split of 3 records whose second is damaged."""
    folder = write_tfds_movi(tmp_path, [box_scene(0), box_scene(1), box_scene(2)], num_files=1)
    damage_record(next(folder.glob("*.tfrecord*")), 1, "data")
    return folder


def eval_config(*overrides):
    cfg = load_config("dynpt", "tiny-cpu", overrides=[
        "eval.resolution=[32,32]", "eval.num_tracks=16", "eval.num_scenes=0", *overrides])
    return cfg.eval


def test_eval_refuses_a_damaged_record_unless_asked_to_skip(damaged, caplog):
    from dynpt.evaluate import load_source

    with pytest.raises(UserError, match=r"record 1 is damaged.*or set eval.foreign=skip"):
        load_source(str(damaged), eval_config())
    skipped: list[str] = []
    with caplog.at_level(logging.WARNING):
        items, kind = load_source(str(damaged), eval_config("eval.foreign=skip"), skipped)
    assert kind == "tfds-movi" and len(items) == 2 and len(skipped) == 1
    assert "record 1 is damaged" in caplog.text


def test_eval_scores_records(records, tmp_path, capsys):
    import json

    from dynpt.checkpoint import save_checkpoint
    from dynpt.model import build_model

    root, _ = records
    ckpt = tmp_path / "tiny.pt"
    save_checkpoint(ckpt, build_model(load_config("dynpt", "tiny-cpu").model), step=0)
    out = tmp_path / "eval"
    version = root / "movi_e" / f"{H}x{W}" / "1.0.0"
    assert main(["eval", "--ckpt", str(ckpt), "--data", f"{version}:validation", "--out",
                 str(out), "--config", "tiny-cpu", "eval.resolution=[32,32]"]) == 0
    report = json.loads((out / "eval.json").read_text())
    assert report["summary"]["num_videos"] == 3 and report["info"]["kind"] == "tfds-movi"
    assert 0 <= report["summary"]["d_acc"] <= 1
    part = tmp_path / "eval-2"  # the first 2, "of 3" counted from the listed records
    assert main(["eval", "--ckpt", str(ckpt), "--data", f"{version}:validation", "--out",
                 str(part), "--config", "tiny-cpu", "eval.resolution=[32,32]",
                 "eval.num_scenes=2"]) == 0
    assert f"scored 2 of 3 videos of {version}:validation (the first 2" in capsys.readouterr().out


def test_eval_items_of_records_under_both_protocols(validation, tmp_path):
    """`load_eval_scenes` (training's validation) and the paper's D-ACC protocol read records."""
    from dynpt.evaluate import load_eval_scenes, load_source

    items = load_eval_scenes(validation[0], eval_config())
    assert len(items) == 3 and items[0]["video"].shape == (T, 32, 32, 3)
    scene = make_box_scene(num_frames=24, height=H, width=W, focal=35 / 32 * W, seed=3,
                           num_tracks=8)
    scene.meta.update(scene_index=0, mobility_threshold=0.01)
    write_tfds_movi(tmp_path, [scene], num_files=1)
    paper, kind = load_source(str(tmp_path), eval_config("eval.protocol=c4d-paper"))
    assert kind == "tfds-movi" and paper[0]["video"].shape == (24, 256, 256, 3)
    assert paper[0]["tracks"].shape == (24, 256, 2) and len(paper[0]["query_frame"]) == 256
    by_object, _ = load_source(str(tmp_path), eval_config("eval.protocol=c4d-paper",
                                                          "eval.mobility_rule=object"))
    np.testing.assert_array_equal(by_object[0]["tracks"], paper[0]["tracks"])  # the same draw
    kinds = paper[0]["track_kind"]  # the sliding box is the one tossed object; it moves whole
    assert by_object[0]["moving"][:, kinds == 2].all() and not by_object[0]["moving"][:, kinds != 2].any()


def test_object_tracks_of_records_are_lifted_through_their_boxes(tmp_path):
    """Kubric's records hold an object point's place exactly in its object coordinates and 3-D
    box, its depth only to 16 bits over the scene's range: the reader and the paper protocol lift
    object queries through the box, as TAP-Vid-Kubric does, so their tracks are those of the
    original scene within 1e-3 px (from the 16-bit depth they are not)."""
    from datagen.generate import generate_scene
    from dynpt.evaluate import PAPER_FIELDS, PAPER_TRACKS, load_source

    cfg = load_config("datagen", "movi-e", overrides=[
        "resolution=[64,64]", "frames=24", "objects.num_static=[3,3]", "objects.num_tossed=[2,2]",
        "layers.object_coordinates=true", "layers.instances=true"])
    truth = generate_scene(cfg, 1)
    write_tfds_movi(tmp_path, [truth], num_files=1)
    exact = tapvid_kubric_tracks(truth, [SEED, 0], PAPER_TRACKS)
    on_object = exact.track_object > 0
    assert on_object.sum() > 100
    for fields in (None, ("rgb", "tracks", "moving")):  # the layer whole, or its query frames
        scene = read_unit(source_units(tmp_path)[0], ReadOptions(seed=SEED, fields=fields))
        np.testing.assert_array_equal(scene.track_object, exact.track_object)
        assert np.abs(scene.tracks[on_object] - exact.tracks[on_object]).max() < 1e-3
    from_depth = replace(scene, object_coordinates=None, instances=None)  # the 16-bit depth lift
    coarse = tapvid_kubric_tracks(from_depth, [SEED, 0], PAPER_TRACKS)
    assert np.abs(coarse.tracks[on_object] - exact.tracks[on_object]).max() > 1e-3
    unread = read_unit(source_units(tmp_path)[0], ReadOptions(seed=SEED, fields=PAPER_FIELDS))
    assert unread.tracks.shape[0] == 0  # the protocol draws its own: the reader draws none
    paper, _ = load_source(str(tmp_path), eval_config("eval.protocol=c4d-paper", f"eval.seed={SEED}"))
    scale = 256 / 64  # the protocol's 256x256 from the record's 64x64, pixel centres kept
    expected = (exact.tracks[on_object] + 0.5) * scale - 0.5  # (n,T,2)
    got = paper[0]["tracks"].transpose(1, 0, 2)[on_object]
    assert np.abs(got - expected).max() < 1e-3 * scale


def data_config(*overrides):
    return load_config("dynpt", "tiny-cpu", overrides=[
        "data.num_frames=4", "data.crop_size=[32,32]", "data.num_tracks=8",
        "data.shuffle_buffer=2", *overrides]).data


def test_training_mixes_records_with_shards(validation):
    from dynpt.data import ShardStream

    sources = [str(synthetic_shards(6, 3)), validation[0]]
    keys = []
    for _ in range(2):
        stream = iter(ShardStream(sources, [1.0, 1.0], data_config(), seed=0))
        keys.append([next(stream)["key"] for _ in range(12)])
    assert keys[0] == keys[1]  # deterministic by seed
    assert any("record" in k for k in keys[0]) and any(k.startswith("train-") for k in keys[0])
    sample = next(iter(ShardStream([validation[0]], [1.0], data_config(), seed=0)))
    assert sample["video"].shape == (4, 32, 32, 3) and sample["moving"].shape == (4, 8)


def test_training_refuses_a_damaged_record_unless_asked_to_skip(damaged, caplog):
    from dynpt.data import ShardStream

    with pytest.raises(UserError, match=r"record 1 is damaged.*or set data.foreign=skip"):
        stream = iter(ShardStream([str(damaged)], [1.0], data_config(), seed=0))
        for _ in range(3):
            next(stream)
    stream = iter(ShardStream([str(damaged)], [1.0], data_config("data.foreign=skip",
                                                                  "data.max_bad_fraction=1"),
                              seed=0))
    with caplog.at_level(logging.WARNING):
        keys = [next(stream)["key"] for _ in range(4)]
    assert not any(k.endswith("record 1") for k in keys)
    assert "record 1 is damaged" in caplog.text


def test_inspect_checks_and_reports_records(validation, damaged, tmp_path, capsys):
    assert main(["inspect", validation[0], "--check", "--no-progress"]) == 0
    assert "checked 3 scenes in 2 shards: 0 with problems" in capsys.readouterr().out
    assert main(["inspect", str(damaged), "--check", "--no-progress"]) == 1
    assert "record 1 is damaged" in capsys.readouterr().out
    out = tmp_path / "report"
    assert main(["inspect", validation[0], "--out", str(out), "--num-samples", "1",
                 "--no-progress"]) == 0
    assert (out / "index.html").is_file()
