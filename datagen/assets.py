"""The asset library: object meshes and background images, with a fixed-seed train/test split.

Built in (nothing downloaded): pybullet_data's 1000 `random_urdfs` meshes, its textured and
untextured models (duck, soccer ball, tray, jenga, teddy, mug, ...) and trimesh primitives. Meshes
without a texture get a procedural one per scene (datagen.textures), and box-projected UVs where
they have none. Users may instead point `assets_dir` at a folder of textured OBJ/GLB/GLTF meshes
(e.g. Google Scanned Objects) and `backgrounds_dir` at equirectangular images or HDRIs.

Every asset is normalised once on load: centred on the centroid of its convex hull (the body
origin pybullet uses as centre of mass) and scaled so its largest axis-aligned extent is 1, so an
object's `scale` is its size in scene units, as in Kubric.

Split: ids are sorted, shuffled with `assets.split_seed` and the first `assets.heldout_fraction`
are held out. `split: train` uses the rest; `val` and `test` use the held-out assets, so they show
objects and backgrounds never seen in training.

Use `load_asset_library(cfg)` once per worker process and pass it to every
`datagen.generate.generate_scene(cfg, i, assets=library)` call; meshes are loaded lazily and cached.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import trimesh

from c4d_core.errors import UserError

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".glb", ".gltf")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".hdr", ".exr")

# pybullet_data models (path relative to pybullet_data); textured ones keep their own image.
PYBULLET_MODELS = {
    "duck": "duck.obj",
    "soccerball": "soccerball.obj",
    "textured_sphere": "textured_sphere_smooth.obj",
    "tray": "tray/tray_textured2.obj",
    "jenga": "jenga/jenga.obj",
    "domino": "domino/domino.obj",
    "torus": "torus/torus_textured.obj",
    "teddy": "teddy2_VHACD_CHs.obj",
    "mug": "objects/mug.obj",
    "lego": "lego/lego.obj",
    "bunny": "bunny.obj",
}
PRIMITIVES = ("box", "sphere", "cylinder", "capsule", "cone", "torus")
NUM_RANDOM_URDFS = 1000


@dataclass
class Asset:
    """A normalised mesh: centred on its hull centroid, largest extent 1."""

    asset_id: str
    vertices: np.ndarray  # float64 (V,3)
    faces: np.ndarray  # int64 (F,3)
    uv: np.ndarray | None  # float64 (V,2), None where the mesh has none
    texture: np.ndarray | None  # uint8 (h,w,3) the mesh's own texture, None: use a procedural one
    hull_vertices: np.ndarray  # float64 (Vh,3) convex hull, used as collision shape
    volume: float  # convex hull volume at scale 1 (units^3)

    def bounds(self, scale: float) -> np.ndarray:
        """float64 (2,3): the (min, max) corners of the render mesh's axis-aligned box in the
        object's own frame at `scale` (units), Kubric's `bounds` x scale."""
        return scale * np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])


def _pybullet_data_dir() -> Path:
    import pybullet_data

    return Path(pybullet_data.getDataPath())


def _primitive(name: str) -> trimesh.Trimesh:
    if name == "box":
        return trimesh.creation.box(extents=(1.0, 0.7, 0.5))
    if name == "sphere":
        return trimesh.creation.icosphere(subdivisions=3)
    if name == "cylinder":
        return trimesh.creation.cylinder(radius=0.5, height=1.0, sections=32)
    if name == "capsule":
        return trimesh.creation.capsule(height=1.0, radius=0.35, count=(24, 24))
    if name == "cone":
        return trimesh.creation.cone(radius=0.5, height=1.0, sections=32)
    if name == "torus":
        return trimesh.creation.torus(major_radius=0.5, minor_radius=0.18)
    raise KeyError(name)


def _to_image(image) -> np.ndarray | None:
    """A trimesh material image (PIL) -> uint8 (h,w,3), None if absent or degenerate."""
    if image is None:
        return None
    array = np.asarray(image.convert("RGB"), dtype=np.uint8)
    return array if min(array.shape[:2]) >= 8 else None


def _normalise(asset_id: str, mesh: trimesh.Trimesh, own_texture: bool) -> Asset:
    """Centre on the hull centroid, scale the largest extent to 1, keep UVs and texture."""
    if len(mesh.faces) == 0 or not np.isfinite(mesh.vertices).all():
        raise ValueError("mesh has no faces or non-finite vertices")
    hull = mesh.convex_hull
    centre = hull.center_mass if hull.volume > 1e-12 else mesh.bounds.mean(axis=0)
    extent = float(np.max(mesh.extents))
    if extent <= 0:
        raise ValueError("mesh is flat in every direction")
    vertices = (mesh.vertices - centre) / extent
    uv, texture = None, None
    visual = mesh.visual
    if isinstance(visual, trimesh.visual.TextureVisuals) and visual.uv is not None \
            and len(visual.uv) == len(mesh.vertices):
        uv = np.asarray(visual.uv, dtype=np.float64)
        if own_texture:
            material = visual.material
            image = getattr(material, "image", None)
            if image is None:
                image = getattr(material, "baseColorTexture", None)
            texture = _to_image(image)
    return Asset(
        asset_id=asset_id,
        vertices=vertices,
        faces=np.asarray(mesh.faces, dtype=np.int64),
        uv=uv,
        texture=texture,
        hull_vertices=(hull.vertices - centre) / extent,
        volume=float(hull.volume) / extent**3,
    )


def _load_mesh(path: Path) -> trimesh.Trimesh:
    mesh = trimesh.load(str(path), force="mesh", process=False)
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError("file holds no triangle mesh")
    return mesh


def split_ids(ids: list[str], split: str, seed: int, heldout_fraction: float) -> list[str]:
    """The ids of `split` (train, or val/test = held out) under a fixed-seed shuffle."""
    if split not in ("train", "val", "test"):
        raise UserError(f"unknown split {split!r}: use train, val or test")
    ordered = sorted(ids)
    perm = np.random.default_rng(seed).permutation(len(ordered))
    num_heldout = int(round(heldout_fraction * len(ordered)))
    if len(ordered) > 1:
        num_heldout = min(max(num_heldout, 1), len(ordered) - 1)
    heldout = {ordered[i] for i in perm[:num_heldout]}
    chosen = [i for i in ordered if (i in heldout) == (split != "train")]
    return chosen or ordered


def _list_folder(folder: str, suffixes: tuple[str, ...], what: str, key: str) -> list[Path]:
    path = Path(folder).expanduser()
    if not path.is_dir() or not os.access(path, os.R_OK | os.X_OK):
        raise UserError(f"{what} folder {str(path)!r} does not exist or is not readable: "
                        f"fix the path given as `{key}`")
    files = sorted(p for p in path.rglob("*") if p.suffix.lower() in suffixes and p.is_file())
    if not files:
        raise UserError(f"{what} folder {str(path)!r} holds no {'/'.join(suffixes)} files: "
                        f"point `{key}` at a folder that does")
    return files


class AssetLibrary:
    """Object assets and background images of one split. Meshes load lazily and are cached."""

    def __init__(self, object_sources: dict[str, tuple[str, object]],
                 background_paths: list[Path], split: str, seed: int, heldout_fraction: float):
        # object_sources: asset_id -> (kind, where): kind in {"file", "file_own", "primitive"}.
        self._sources = object_sources
        self.object_ids = split_ids(list(object_sources), split, seed, heldout_fraction)
        by_name = {str(p): p for p in background_paths}
        self.background_ids = (split_ids(list(by_name), split, seed, heldout_fraction)
                               if by_name else [])
        self._background_paths = by_name
        self._cache: dict[str, Asset | None] = {}
        self._images: dict[str, np.ndarray] = {}

    def get(self, asset_id: str) -> Asset | None:
        """The normalised asset, or None (with one warning) if its mesh is broken or untextured."""
        if asset_id not in self._cache:
            kind, where = self._sources[asset_id]
            try:
                if kind == "primitive":
                    asset = _normalise(asset_id, _primitive(str(where)), own_texture=False)
                else:
                    asset = _normalise(asset_id, _load_mesh(Path(where)),
                                       own_texture=kind in ("file_own", "user"))
                    if kind == "user" and asset.texture is None:
                        raise ValueError("it has no texture image with UV coordinates")
            except Exception as exc:  # a user's broken file must not end the run
                log.warning("skipping asset %s (%s): %s", asset_id, where, exc)
                asset = None
            self._cache[asset_id] = asset
        return self._cache[asset_id]

    def draw(self, rng: np.random.Generator) -> tuple[str, Asset]:
        """A uniformly random usable asset of the split; raises `UserError` if none is usable."""
        while True:
            asset_id = self.object_ids[int(rng.integers(len(self.object_ids)))]
            asset = self.get(asset_id)
            if asset is not None:
                return asset_id, asset
            if all(self._cache.get(i, 0) is None for i in self.object_ids):
                raise UserError("no usable mesh among the assets of this split (see the warnings "
                                "above): add textured OBJ/GLB/GLTF meshes to `assets_dir`")

    def check_backgrounds(self) -> None:
        """Decode every background image of the folder once (both splits); `UserError` listing
        all unreadable ones, so a bad file is found when the generator starts, not mid-run."""
        bad = [path for path in self._background_paths.values()
               if cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR) is None]
        if bad:
            names = ", ".join(repr(str(p)) for p in bad[:10]) + (" ..." if len(bad) > 10 else "")
            raise UserError(f"{len(bad)} background image(s) cannot be read: {names}; remove them "
                            "or convert them to PNG/JPEG/HDR")

    def background(self, background_id: str, max_width: int = 2048) -> np.ndarray:
        """An equirectangular background as uint8 (h,w,3); HDRIs are tone-mapped."""
        if background_id not in self._images:
            path = self._background_paths[background_id]
            image = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
            if image is None:
                raise UserError(f"cannot read background image {str(path)!r}: "
                                "remove it or convert it to PNG/JPEG/HDR")
            image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
            if image.dtype != np.uint8:  # HDR/EXR radiance: Reinhard tone map, then gamma 2.2
                radiance = np.maximum(image.astype(np.float32), 0)
                radiance *= 0.5 / max(float(np.median(radiance)), 1e-6)
                image = (np.power(radiance / (1 + radiance), 1 / 2.2) * 255).astype(np.uint8)
            if image.shape[1] > max_width:
                scale = max_width / image.shape[1]
                image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            self._images[background_id] = image
        return self._images[background_id]


def builtin_object_sources() -> dict[str, tuple[str, object]]:
    """Asset id -> source for everything built in."""
    data = _pybullet_data_dir()
    sources: dict[str, tuple[str, object]] = {}
    for i in range(NUM_RANDOM_URDFS):
        path = data / "random_urdfs" / f"{i:03d}" / f"{i:03d}.obj"
        if path.is_file():
            sources[f"random_urdf/{i:03d}"] = ("file", path)
    for name, rel in PYBULLET_MODELS.items():
        if (data / rel).is_file():
            sources[f"pybullet/{name}"] = ("file_own", data / rel)
    for name in PRIMITIVES:
        sources[f"primitive/{name}"] = ("primitive", name)
    return sources


def load_asset_library(cfg) -> AssetLibrary:
    """The library for `cfg.split`, from `cfg.assets_dir` / `cfg.backgrounds_dir` or built-ins.

    Raises `UserError` for an unreadable or empty folder. Cheap: meshes load on first use.
    """
    if cfg.assets_dir:
        root = Path(cfg.assets_dir).expanduser()
        sources = {str(p.relative_to(root)): ("user", p)
                   for p in _list_folder(cfg.assets_dir, MESH_SUFFIXES, "asset", "assets_dir")}
    else:
        sources = builtin_object_sources()
    backgrounds = (_list_folder(cfg.backgrounds_dir, IMAGE_SUFFIXES, "background",
                                "backgrounds_dir") if cfg.backgrounds_dir else [])
    return AssetLibrary(sources, backgrounds, cfg.split, int(cfg.assets.split_seed),
                        float(cfg.assets.heldout_fraction))
