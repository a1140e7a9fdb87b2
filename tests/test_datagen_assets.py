"""Asset library: built-in split, user mesh folders (good, untextured, broken), backgrounds."""

import logging

import cv2
import numpy as np
import pytest
import trimesh
from PIL import Image

from c4d_core.config import load_config
from c4d_core.errors import UserError
from datagen import textures
from datagen.assets import load_asset_library
from datagen.generate import generate_scene


def textured_box(path):
    """A box with box-projected UVs and a noise texture, saved as a self-contained GLB."""
    box = trimesh.creation.box(extents=(1.0, 0.6, 0.4))
    vertices, faces, uv = textures.box_uv(box.vertices, box.faces)
    image = Image.fromarray(textures.procedural_texture(np.random.default_rng(0), 64))
    mesh = trimesh.Trimesh(vertices, faces, process=False,
                           visual=trimesh.visual.TextureVisuals(uv=uv % 1.0, image=image))
    mesh.export(path)


@pytest.fixture(scope="module")
def user_folders(tmp_path_factory):
    root = tmp_path_factory.mktemp("user_assets")
    meshes, backgrounds = root / "meshes", root / "backgrounds"
    meshes.mkdir()
    backgrounds.mkdir()
    for i in range(3):
        textured_box(meshes / f"box_{i}.glb")
    trimesh.creation.icosphere().export(meshes / "plain_sphere.obj")  # no texture
    (meshes / "broken.obj").write_text("v 0 0 nonsense\nf 1 2 9\n")
    sky = np.random.default_rng(1).random((32, 64, 3)).astype(np.float32) * 4
    cv2.imwrite(str(backgrounds / "sky.hdr"), sky)
    cv2.imwrite(str(backgrounds / "field.png"), (sky * 60).astype(np.uint8))
    return meshes, backgrounds


def test_builtin_split_is_fixed_and_held_out():
    train = load_asset_library(load_config("datagen", "movi-e"))
    test = load_asset_library(load_config("datagen", "movi-e", overrides=["split=test"]))
    val = load_asset_library(load_config("datagen", "movi-e", overrides=["split=val"]))
    assert not set(train.object_ids) & set(test.object_ids)
    assert val.object_ids == test.object_ids
    total = len(train.object_ids) + len(test.object_ids)
    assert total > 1000 and abs(len(test.object_ids) / total - 0.1) < 0.01
    again = load_asset_library(load_config("datagen", "movi-e"))
    assert again.object_ids == train.object_ids
    asset = train.get(train.object_ids[0])
    assert np.max(np.ptp(asset.vertices, axis=0)) == pytest.approx(1.0)
    assert asset.volume > 0


def test_user_meshes_broken_or_untextured_are_skipped_with_a_warning(user_folders, caplog):
    meshes, backgrounds = user_folders
    overrides = [f"assets_dir={meshes}", f"backgrounds_dir={backgrounds}"]
    libraries = [load_asset_library(load_config("datagen", "movi-e",
                                                overrides=overrides + [f"split={split}"]))
                 for split in ("train", "test")]
    ids = sorted(libraries[0].object_ids + libraries[1].object_ids)
    assert ids == ["box_0.glb", "box_1.glb", "box_2.glb", "broken.obj", "plain_sphere.obj"]
    library = libraries[0]
    with caplog.at_level(logging.WARNING, logger="datagen.assets"):
        good = [library.get(i) for i in library.object_ids if i.startswith("box")]
        bad = [library.get(i) for i in library.object_ids if not i.startswith("box")]
    assert all(a is not None and a.texture is not None for a in good)
    assert all(a is None for a in bad)
    assert len(caplog.records) == len(bad)
    for background in library.background_ids + libraries[1].background_ids:
        image = (library if background in library.background_ids
                 else libraries[1]).background(background)
        assert image.dtype == np.uint8 and image.shape == (32, 64, 3)


def test_scene_from_user_assets_and_backgrounds(user_folders):
    meshes, backgrounds = user_folders
    cfg = load_config("datagen", "movi-e", overrides=[
        f"assets_dir={meshes}", f"backgrounds_dir={backgrounds}", "resolution=[32,48]",
        "frames=3", "objects.num_static=[3,4]", "objects.num_tossed=[1,1]",
        "tracks.num_points=16"])
    scene = generate_scene(cfg, 0, load_asset_library(cfg))
    assert scene.rgb.shape == (3, 32, 48, 3)
    assert {o["asset_id"] for o in scene.objects} <= {"box_0.glb", "box_1.glb", "box_2.glb"}
    assert scene.meta["background"] is not None


def test_bad_asset_folders_are_user_errors(tmp_path):
    with pytest.raises(UserError, match="assets_dir"):
        load_asset_library(load_config("datagen", "movi-e",
                                       overrides=[f"assets_dir={tmp_path / 'missing'}"]))
    with pytest.raises(UserError, match="holds no"):
        load_asset_library(load_config("datagen", "movi-e", overrides=[f"assets_dir={tmp_path}"]))
    (tmp_path / "only_broken.obj").write_text("not a mesh\n")
    cfg = load_config("datagen", "movi-e", overrides=[f"assets_dir={tmp_path}"])
    library = load_asset_library(cfg)
    with pytest.raises(UserError, match="no usable mesh"):
        library.draw(np.random.default_rng(0))
