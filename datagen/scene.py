"""`Scene`: one labelled video, the unit that crosses package borders (see docs/FORMAT.md).

Shapes: T frames, H x W pixels, K objects, N tracks. Conventions (OpenCV camera, camera-to-world
poses, z-depth, pixel centres at integer coordinates, flow as (dx, dy)) are those of the
project's interface contract. A field a preset cannot produce is `None`, never silently wrong.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from c4d_core.geometry import swap_track_axes

# The optional layers: Scene fields made only where the config key `layers.<name>` is on.
OPTIONAL_LAYERS = ("normal", "object_coordinates", "instances", "events")
# `Scene.instances`: key -> (dtype, shape after the (K,T) axes; None: one value per object, (K,)).
INSTANCE_KEYS: dict[str, tuple[np.dtype, tuple[int, ...] | None]] = {
    "bbox_3d": (np.dtype(np.float32), (8, 3)),  # world corners, x slowest then y then z
    "bbox_2d": (np.dtype(np.float32), (4,)),  # [ymin,xmin,ymax,xmax] / (H,W,H,W), NaN: not visible
    "visible_pixels": (np.dtype(np.int32), ()),  # pixels of the object's segment
    "image_position": (np.dtype(np.float32), (2,)),  # (x, y) pixels of the object's origin
    "velocity": (np.dtype(np.float32), (3,)),  # world, units/s (pybullet's)
    "angular_velocity": (np.dtype(np.float32), (3,)),  # world, rad/s (pybullet's)
    "is_dynamic": (np.dtype(np.bool_), None),  # tossed (True) or a static distractor
}
# `Scene.events`, one row per collision: key -> (dtype, shape after the (E,) axis).
EVENT_KEYS: dict[str, tuple[np.dtype, tuple[int, ...]]] = {
    "instances": (np.dtype(np.int32), (2,)),  # indices into `objects`, -1: the floor
    "frame": (np.dtype(np.float32), ()),  # time in frames (frame f at f; -1 = the toss)
    "force": (np.dtype(np.float32), ()),  # normal force, N
    "position": (np.dtype(np.float32), (3,)),  # world, on the second instance's surface
    "image_position": (np.dtype(np.float32), (2,)),  # (x, y) pixels at the event's time
    "contact_normal": (np.dtype(np.float32), (3,)),  # world unit normal, second -> first
}


@dataclass
class Scene:
    rgb: np.ndarray  # uint8 (T,H,W,3), motion-blurred where the preset blurs
    depth: np.ndarray | None  # float32 (T,H,W) z-depth at the frame time
    segmentation: np.ndarray | None  # int32 (T,H,W): 0 background, k = objects[k-1]
    flow_fwd: np.ndarray | None  # float32 (T,H,W,2) (dx,dy) from t to t+1; last frame zero
    flow_bwd: np.ndarray | None  # float32 (T,H,W,2) (dx,dy) from t to t-1; first frame zero
    intrinsics: np.ndarray  # float32 (T,3,3) K in pixels
    cam_to_world: np.ndarray  # float32 (T,4,4) OpenCV camera-to-world
    object_to_world: np.ndarray | None  # float32 (K,T,4,4)
    objects: list[dict[str, Any]]  # K dicts: asset id, scale, mass, tossed, ...
    tracks: np.ndarray  # float32 (N,T,2) (x,y) pixels
    occluded: np.ndarray  # bool (N,T)
    query_frame: np.ndarray  # int32 (N,) frame where the track is sampled (visible there)
    track_object: np.ndarray  # int32 (N,) 0 background, k = objects[k-1]
    tracks_world: np.ndarray | None  # float32 (N,T,3) world position of the tracked point
    displacement: np.ndarray | None  # float32 (N,T) world distance moved since t-1 (t=0: to t+1)
    moving: np.ndarray | None  # bool (N,T) displacement > meta['mobility_threshold']
    # Optional layers (config `layers.*`; None where not generated), docs/FORMAT.md:
    normal: np.ndarray | None = None  # float32 (T,H,W,3) world-space unit shading normals
    object_coordinates: np.ndarray | None = None  # float32 (T,H,W,3) in [0,1]^3, 0 on background
    instances: dict[str, np.ndarray] | None = None  # INSTANCE_KEYS arrays, objects in `objects` order
    events: dict[str, np.ndarray] | None = None  # EVENT_KEYS arrays (E,...), one row per collision
    meta: dict[str, Any] = field(default_factory=dict)  # preset, seed, index, fps, version, ...

    @property
    def num_frames(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W) in pixels."""
        return int(self.rgb.shape[1]), int(self.rgb.shape[2])

    @property
    def num_tracks(self) -> int:
        return int(self.tracks.shape[0])

    def name(self, index: int) -> str:
        """The scene by what it is, for titles: its preset, split and index from its meta (e.g.
        "movi-e val scene 0"; `index`, its place in its shard set, where the meta has none), not
        the folder it was read from, which may be a machine's temporary one."""
        words = (self.meta.get("preset", "generated"), self.meta.get("split"), "scene",
                 self.meta.get("scene_index", index))
        return " ".join(str(word) for word in words if word is not None)

    def tracks_time_major(self, frames: slice = slice(None)) -> dict[str, np.ndarray | None]:
        """The tracker's layout of `frames`: `tracks` float32 (T,N,2), `occluded` bool (T,N) and
        `moving` bool (T,N) (None without the labels); views of the scene's arrays, no copies."""
        return {"tracks": swap_track_axes(self.tracks)[frames],
                "occluded": swap_track_axes(self.occluded)[frames],
                "moving": None if self.moving is None else swap_track_axes(self.moving)[frames]}

    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in fields(cls)]
