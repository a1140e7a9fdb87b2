"""`c4d export kubric`: each scene as the folder Kubric's MOVi worker writes (movi_def_worker.py).

The scene folders go into OUT/scenes/ (`SCENES`), which holds nothing else once the export is
finished: that folder is the data path of Kubric's builders, which read every entry of their path
as a scene; OUT holds the ownership marker beside it (datagen/export/base.py).
Per scene, for frames i = 0..T-1 (docs/FORMAT.md, "Exports"):

- `rgba_{i:05d}.png`: 8-bit RGBA, alpha 255;
- `depth_{i:05d}.tiff`: float32 (H,W) Euclidean distance from the camera centre (ours is z-depth:
  times |K^-1 [u, v, 1]| at each pixel centre);
- `segmentation_{i:05d}.png`: 8-bit palette PNG of ids in Kubric's order: 0 background, 1..K' the
  objects visible in some frame, by total visible pixels, most first (never-visible objects are
  left out of every label, as Kubric does);
- `forward_flow_{i:05d}.png`, `backward_flow_{i:05d}.png`: 16-bit RGB PNG (R = drow, G = dcol,
  B = 0), (flow - min) * 65535 / (max - min) truncated, min/max over the video and both channels in
  `data_ranges.json`; backward flow in Kubric's time sense (motion from t-1 to t: minus ours);
- `normal_{i:05d}.png`: 16-bit RGB of (n + 1) / 2 * 65535, world-space normals;
- `object_coordinates_{i:05d}.png`: 16-bit RGB of the [0,1]^3 coordinates * 65535;
- `metadata.json` (flags, metadata, camera, instances) and `events.json` (collisions).

Kubric's conventions: resolution [W, H]; camera poses in Blender axes (x right, y up, looking
along -z: ours times diag(1, -1, -1)); K normalised with Blender's signs; image positions and 2D
boxes normalised to [0,1] with raster coordinates (pixel centres at +0.5); quaternions (w,x,y,z).

The folders are what Kubric's own TFDS builders (challenges/movi/) build unchanged: `movi_e.py`
and `panning_movi_e.py`, or for scenes of the movi-f preset `movi_f.py`, whose older worker's
conventions differ (`MOVI_F`). Those builders know an object only as one of the Google Scanned
Objects (GSO) of their tables, so each of our assets is written as a GSO stand-in of its kind
(`STAND_INS`), our own id kept beside it.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from c4d_core.errors import UserError
from c4d_core.files import write_json
from c4d_core.geometry import matrix_to_quat, pixel_grid
from datagen.export.base import ExportFormat, in_memory, write_member, write_png
from datagen.scene import Scene

BLENDER_AXES = np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes -> Blender's (right-multiplied)
LENS = ("focal_length", "sensor_width", "field_of_view")  # meta["camera"] keys Kubric's camera has
MOVI_F = "movi-f"  # scenes of this preset are written for movi_f.py, the others for movi_e.py
# movi_f.py multiplies data_ranges.json's flow ranges by 512: its worker stored flow in units of
# its 512-pixel frame. For it, the ranges are written in pixels / 512.
MOVI_F_FLOW_UNIT = 512.0
PROCEDURAL_BACKDROP = "procedural"  # `background` of a scene without a background image
SCENES = "scenes"  # OUT/scenes/: the scene folders, the data path of Kubric's builders


@dataclass(frozen=True)
class GsoAsset:
    """What Kubric's builders know of a GSO asset: movi_e.py's `asset_id_from_metadata` finds
    `asset_id` by (nr_faces, category, description[:15]) of an instance's metadata; movi_f.py's
    `get_scale_and_category` finds (scale_factor, category) by asset_id, and stores the
    instance's `scale` times scale_factor (its older worker's scale was relative to the raw GSO
    mesh, whose largest extent is scale_factor)."""

    asset_id: str
    nr_faces: int
    category: str  # one of the 17 GSO categories ("None" is one)
    description: str  # the first 15 characters of its GSO description, all the builders compare
    scale_factor: float


# Our assets -> the GSO asset written for each (our id is kept as `c4d_asset_id`): one of the same
# kind and category where GSO has one; every other asset (random_urdf/*, primitive/*, the other
# pybullet models, meshes of `assets_dir`) is a plain shape without a GSO category, written as
# `SHAPE`, a GSO asset of category "None". Facts of the builders' tables (kubric 0ee21e2).
STAND_INS = {
    "pybullet/teddy": GsoAsset("Lovable_Huggable_Cuddly_Boutique_Teddy_Bear_Beige", 97684,
                               "Stuffed Toys", "Lovable Huggabl", 0.370612),
    "pybullet/duck": GsoAsset("BIRD_RATTLE", 17104, "Toys", "BIRD RATTLE\nThi", 0.11119),
    "pybullet/soccerball": GsoAsset("HAMMER_BALL", 12474, "Toys", "HAMMER BALL\nThi", 0.28392),
    "pybullet/domino": GsoAsset("FRUIT_VEGGIE_DOMINO_GRADIENT", 12556, "Toys", "FRUIT & VEGGIE ",
                                0.347707),
    "pybullet/lego": GsoAsset("Android_Lego", 14214, "Legos", "Android Lego", 0.106349),
    "pybullet/jenga": GsoAsset("2_of_Jenga_Classic_Game", 8922, "Consumer Goods",
                               "2 of Jenga Clas", 0.292098),
    "pybullet/mug": GsoAsset("ACE_Coffee_Mug_Kristen_16_oz_cup", 11224, "Consumer Goods",
                             "ACE Coffee Mug,", 0.134936),
    "pybullet/tray": GsoAsset("Threshold_Tray_Rectangle_Porcelain", 2740, "None",
                              "Threshold Tray,", 0.314468),
}
SHAPE = GsoAsset("Closetmaid_Premium_Fabric_Cube_Red", 12158, "None", "Closetmaid Prem", 0.32167)


def euclidean_range(depth: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Euclidean distance from the camera centre, float32 (T,H,W), of the z-depth `depth` (T,H,W)
    seen through K `intrinsics` (T,3,3): z * |K^-1 [u, v, 1]| at each pixel centre (u, v)."""
    t, h, w = depth.shape
    pixels = np.concatenate([pixel_grid(h, w), np.ones((h, w, 1))], axis=-1)  # (H,W,3)
    rays = np.einsum("tij,hwj->thwi", np.linalg.inv(intrinsics.astype(np.float64)), pixels)
    return (depth * np.linalg.norm(rays, axis=-1)).astype(np.float32)


def kubric_order(segmentation: np.ndarray, num_objects: int) -> np.ndarray:
    """Kubric's instance order (int (K',)): the objects (0-based) with a visible pixel in some
    frame, by total visible pixels, most first (ties: lower index first)."""
    counts = np.bincount(segmentation.ravel(), minlength=num_objects + 1)[1:num_objects + 1]
    order = np.argsort(-counts, kind="stable")
    return order[counts[order] > 0]


def visible_pixels(segmentation: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Kubric's `visibility`: int (K',T) pixels of each ordered object per frame."""
    return np.stack([(segmentation == k + 1).sum(axis=(1, 2)) for k in order]).reshape(len(order), -1)


def encode_flow(flow: np.ndarray) -> tuple[np.ndarray, dict[str, float]]:
    """Kubric's 16-bit flow frames: uint16 (T,H,W,3) of (flow - min) * 65535 / (max - min)
    truncated, the third channel 0, and {"min", "max"} over the whole video (T,H,W,2) and both
    channels (a constant flow is stored as 0 with min == max). Computed in float64: in float32
    the scaled value can round below an integer and truncate one code low, to decode more than
    one step below the flow."""
    flow = np.asarray(flow, np.float64)
    low, high = np.min(flow), np.max(flow)
    scaled = ((flow - low) * 65535 / (high - low) if high > low else np.zeros_like(flow))
    encoded = np.zeros(flow.shape[:-1] + (3,), np.uint16)
    encoded[..., :2] = scaled.astype(np.uint16)
    return encoded, {"min": float(low), "max": float(high)}


def unit_to_uint16(values: np.ndarray) -> np.ndarray:
    """[0,1] floats -> uint16 of clip(values, 0, 1) * 65535 truncated (Kubric's 16-bit layers)."""
    return (np.clip(values, 0.0, 1.0) * 65535).astype(np.uint16)


def hls_palette(count: int) -> np.ndarray:
    """Kubric's segmentation palette: black, then `count` hues evenly spaced from 0.01 at
    lightness 0.5 and saturation 0.7; uint8 (count+1, 3)."""
    hues = (np.linspace(0, 1, count + 1)[:-1] + 0.01) % 1
    colours = [(0.0, 0.0, 0.0)] + [colorsys.hls_to_rgb(h, 0.5, 0.7) for h in hues]
    return np.round(np.array(colours) * 255).astype(np.uint8)


def _normalised(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """Our pixel coordinates (...,2) (x, y) -> Kubric's [0,1] image coordinates (centres +0.5)."""
    return (np.asarray(pixels, np.float64) + 0.5) / np.array([width, height])


def _blender_pose(cam_to_world: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world (...,4,4) -> Blender camera axes (Kubric's `matrix_world`)."""
    pose = np.array(cam_to_world, np.float64)
    pose[..., :3, :3] = pose[..., :3, :3] @ BLENDER_AXES
    return pose


def normalised_intrinsics(k: np.ndarray, width: int, height: int) -> np.ndarray:
    """Kubric's `camera.K`: our pixel K (3,3) normalised by the image size with Blender's signs,
    [[fx/W, 0, -cx'/W], [0, -fy/H, -cy'/H], [0, 0, -1]], c' the raster principal point (c + 0.5)."""
    return np.array([[k[0, 0] / width, 0.0, -(k[0, 2] + 0.5) / width],
                     [0.0, -k[1, 1] / height, -(k[1, 2] + 0.5) / height],
                     [0.0, 0.0, -1.0]])


def camera_info(scene: Scene) -> dict[str, Any]:
    """metadata.json's `camera`: lens, per-frame positions and (w,x,y,z) quaternions in Blender
    axes, normalised K (of the first frame: datagen's lens is fixed per scene) and the last
    frame's `matrix_world` as R (Kubric's R is the camera's last pose)."""
    h, w = scene.image_size
    pose = _blender_pose(scene.cam_to_world)
    return {**{key: scene.meta["camera"][key] for key in LENS},
            "positions": pose[:, :3, 3], "quaternions": matrix_to_quat(pose[:, :3, :3]),
            "K": normalised_intrinsics(scene.intrinsics[0], w, h), "R": pose[-1]}


def for_movi_f(scene: Scene) -> bool:
    """Whether `scene` is written for movi_f.py (a scene of the movi-f preset) rather than for
    movi_e.py and panning_movi_e.py."""
    return scene.meta.get("preset") == MOVI_F


def gso_keys(obj: dict[str, Any], movi_f: bool) -> dict[str, Any]:
    """The keys of an instance that name its asset for Kubric's builders: the GSO stand-in's
    asset_id, nr_faces, category and description (`STAND_INS`), our asset id as c4d_asset_id,
    and `scale` (our largest extent, scene units; for movi_f.py divided by the stand-in's
    scale_factor, which the builder multiplies back)."""
    gso = STAND_INS.get(obj["asset_id"], SHAPE)
    return {"asset_id": gso.asset_id, "c4d_asset_id": obj["asset_id"], "nr_faces": gso.nr_faces,
            "category": gso.category, "description": gso.description,
            "scale": obj["scale"] / gso.scale_factor if movi_f else obj["scale"]}


def instance_info(scene: Scene, order: np.ndarray, visibility: np.ndarray) -> list[dict[str, Any]]:
    """metadata.json's `instances`, one per object of `order` (Kubric's order)."""
    h, w = scene.image_size
    inst = scene.instances
    result = []
    for j, k in enumerate(order):
        obj = scene.objects[k]
        box = np.asarray(inst["bbox_2d"][k], np.float64)  # (T,4), NaN where not visible
        frames = np.flatnonzero(np.isfinite(box).all(axis=1))
        pose = scene.object_to_world[k].astype(np.float64)
        result.append({
            **obj, **gso_keys(obj, for_movi_f(scene)), "is_dynamic": bool(inst["is_dynamic"][k]),
            "positions": pose[:, :3, 3], "quaternions": matrix_to_quat(pose[:, :3, :3]),
            "velocities": inst["velocity"][k], "angular_velocities": inst["angular_velocity"][k],
            "bboxes_3d": inst["bbox_3d"][k],
            "image_positions": _normalised(inst["image_position"][k], w, h),
            "bboxes": box[frames], "bbox_frames": frames, "visibility": visibility[j],
        })
    return result


def collisions(scene: Scene, order: np.ndarray) -> list[dict[str, Any]]:
    """events.json's `collisions`, instances as indices of `order` (-1: the floor or an object
    Kubric leaves out, never visible), image positions normalised, frames counted as Kubric does
    (its first rendered frame is frame 1: ours + 1)."""
    h, w = scene.image_size
    index = {int(k): j for j, k in enumerate(order)}
    columns = [scene.events[key].tolist()  # Python numbers, float32-exact
               for key in ("instances", "contact_normal", "frame", "force", "position")]
    pixels = _normalised(scene.events["image_position"], w, h).tolist()  # (E,2)
    return [{"instances": [index.get(i, -1) for i in instances], "contact_normal": normal,
             "frame": frame + 1, "force": force, "position": position, "image_position": pixel}
            for instances, normal, frame, force, position, pixel in zip(*columns, pixels)]


def write_scene(scene: Scene, folder: Path, name: str) -> None:
    """Write `scene` into `folder` in Kubric's worker layout (module docstring); `name` is not
    used (Kubric's files do not repeat the scene's name)."""
    missing = [key for key in LENS if key not in scene.meta.get("camera", {})]
    if missing:
        raise UserError(f"scene {scene.meta.get('scene_index')} has no camera {', '.join(missing)} "
                        "in its meta, which the kubric export needs; regenerate it with this "
                        "version of `c4d datagen`")
    h, w = scene.image_size
    order = kubric_order(scene.segmentation, len(scene.objects))
    if len(order) > 255:
        raise UserError(f"scene {scene.meta.get('scene_index')} shows {len(order)} objects; "
                        "Kubric's 8-bit segmentation holds at most 255")
    relabel = np.zeros(len(scene.objects) + 1, np.uint8)
    relabel[order + 1] = np.arange(1, len(order) + 1)
    segmentation = relabel[scene.segmentation]
    # Kubric's palette, padded to 256 entries: PIL writes a shorter one with fewer bits per pixel,
    # which Kubric's read_png (8 or 16 bits only) refuses
    palette = np.zeros((256, 3), np.uint8)
    colours = hls_palette(int(segmentation.max()) + 1)
    palette[:len(colours)] = colours
    depth = euclidean_range(scene.depth, scene.intrinsics)
    forward, forward_range = encode_flow(scene.flow_fwd[..., ::-1])  # (dx, dy) -> (drow, dcol)
    backward, backward_range = encode_flow(-scene.flow_bwd[..., ::-1])  # motion t-1 -> t
    normal = unit_to_uint16((scene.normal + 1.0) / 2.0)
    coordinates = unit_to_uint16(scene.object_coordinates)
    alpha = np.full((h, w, 1), 255, np.uint8)
    for t in range(scene.num_frames):
        write_png(folder / f"rgba_{t:05d}.png", np.concatenate([scene.rgb[t], alpha], axis=-1))
        write_member(folder / f"depth_{t:05d}.tiff",
                     in_memory(lambda fh: Image.fromarray(depth[t]).save(fh, format="TIFF")))
        image = Image.fromarray(segmentation[t])
        image.putpalette(palette.tobytes())
        write_member(folder / f"segmentation_{t:05d}.png",
                     in_memory(lambda fh: image.save(fh, format="PNG")))
        write_png(folder / f"forward_flow_{t:05d}.png", forward[t])
        write_png(folder / f"backward_flow_{t:05d}.png", backward[t])
        write_png(folder / f"normal_{t:05d}.png", normal[t])
        write_png(folder / f"object_coordinates_{t:05d}.png", coordinates[t])
    meta = scene.meta
    movi_f = for_movi_f(scene)
    unit = MOVI_F_FLOW_UNIT if movi_f else 1.0
    write_json(folder / "data_ranges.json", {
        layer: {key: value / unit for key, value in ranges.items()}
        for layer, ranges in (("backward_flow", backward_range), ("forward_flow", forward_range))})
    # compact JSON: Python's C encoder (indented JSON is encoded in Python, 5x slower)
    write_json(folder / "events.json", {"collisions": collisions(scene, order)}, indent=None)
    write_json(folder / "metadata.json", {
        "flags": {**{key: meta.get(key) for key in ("preset", "seed", "split", "scene_index",
                                                    "config_digest", "generator",
                                                    "generator_version")},
                  "tfds_builder": "movi_f.py" if movi_f else "movi_e.py"},
        "metadata": {"resolution": [w, h], "frame_rate": meta.get("fps"),
                     "step_rate": meta.get("physics", {}).get("step_rate"),
                     "num_frames": scene.num_frames, "seed": meta.get("seed"),
                     "background": meta.get("background") or PROCEDURAL_BACKDROP,
                     "num_instances": len(order), "motion_blur": meta.get("motion_blur"),
                     **({"height": h, "width": w} if movi_f else {})},
        "camera": camera_info(scene),
        "instances": instance_info(scene, order, visible_pixels(scene.segmentation, order)),
    }, indent=None)


FORMAT = ExportFormat(
    name="kubric",
    summary="Kubric's MOVi worker layout: in OUT/scenes/ (the data path of Kubric's TFDS "
            "builders) a folder per scene of rgba/depth/segmentation/flow/normal/"
            "object_coordinates frames, metadata.json, events.json, data_ranges.json",
    fields=None,
    layers=("depth", "segmentation", "flow_fwd", "flow_bwd", "object_to_world", "normal",
            "object_coordinates", "instances", "events"),
    write_scene=write_scene,
    subfolder=SCENES,
)
