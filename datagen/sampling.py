"""Scene descriptions: every random choice of a scene, drawn from a preset config and one RNG.

A `SceneDescription` says what is in the scene and how it looks, never how it moves after the
toss: `datagen.simulate` turns it into poses and `datagen.render` into images. Times are in frames:
frame f of the video is at time f, the toss happens at time -1 and the simulation runs to time T,
so sub-frame renders of a blurred shutter and both ends of the flow have poses (as Kubric does).

Objects get `placement_tries` candidate poses each (random rotation, position inside the region
with the rotated bounding box inside too); the simulator keeps the first candidate that touches
nothing already placed, as Kubric's `move_until_no_overlap` does.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from c4d_core import geometry
from datagen.assets import AssetLibrary


@dataclass
class ObjectSpec:
    asset_id: str
    scale: float  # largest extent, scene units
    tossed: bool
    candidates: np.ndarray  # float64 (tries,7): position (3) + quaternion (w,x,y,z)
    velocity: np.ndarray  # (3,) drawn velocity (units/s); tossed objects subtract (x, y, 0)
    mass: float
    friction: float
    restitution: float
    texture_seed: int  # procedural texture (ignored where the asset has its own)
    uv_tiles: float

    def summary(self) -> dict:
        return {"asset_id": self.asset_id, "scale": round(self.scale, 4), "tossed": self.tossed}


@dataclass
class CameraSpec:
    """A camera moving on a straight line from `start` (time -1) to `end` (time T)."""

    focal_mm: float
    sensor_mm: float
    start: np.ndarray  # (3,)
    end: np.ndarray  # (3,)
    lookat_start: np.ndarray  # (3,)
    lookat_end: np.ndarray  # (3,)

    def pose_at(self, times: np.ndarray, num_frames: int) -> np.ndarray:
        """OpenCV camera-to-world (...,4,4) at frame times (...) in [-1, T]."""
        alpha = (np.asarray(times, dtype=np.float64)[..., None] + 1.0) / (num_frames + 1.0)
        eye = self.start + alpha * (self.end - self.start)  # (...,3)
        target = self.lookat_start + alpha * (self.lookat_end - self.lookat_start)
        return geometry.look_at(eye, target)


@dataclass
class LightSpec:
    direction: np.ndarray  # (3,) unit vector the light travels along
    intensity: float
    color: np.ndarray  # (3,) in [0,1]
    shadows: bool  # the shadow-casting sun is directional; other lights are distant points


@dataclass
class SceneDescription:
    num_frames: int
    fps: int
    height: int
    width: int
    objects: list[ObjectSpec]
    camera: CameraSpec
    lights: list[LightSpec]
    ambient: float
    background_id: str | None  # a user background image, None: procedural backdrop
    backdrop_seed: int
    motion_blur: float  # shutter open time, frames
    meta: dict = field(default_factory=dict)  # JSON-friendly record of the random choices


def half_sphere_shell_point(rng: np.random.Generator, r_min: float, r_max: float,
                            min_height: float) -> np.ndarray:
    """A point uniform in volume in the upper half of a spherical shell, above `min_height`."""
    while True:
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        radius = np.cbrt(rng.uniform(r_min**3, r_max**3))
        point = radius * direction
        if point[2] > min_height:
            return point


def half_ball_point(rng: np.random.Generator, radius: float, max_height: float = np.inf):
    """A point uniform in the upper half ball of `radius`, below `max_height`."""
    while True:
        point = rng.uniform(-radius, radius, size=3)
        point[2] = abs(point[2])
        if np.linalg.norm(point) <= radius and point[2] < max_height:
            return point


def sample_camera(cfg, rng: np.random.Generator) -> CameraSpec:
    """Kubric's `linear_movement` (and `linear_movement_linear_lookat` when panning)."""
    c = cfg.camera
    r_min, r_max = c.shell_radius
    start = half_sphere_shell_point(rng, r_min, r_max, c.min_height)
    while True:
        direction = rng.random(3) - 0.5
        direction /= np.linalg.norm(direction)
        end = start + direction * rng.uniform(0.0, c.max_movement)
        if r_min <= np.linalg.norm(end) <= r_max and end[2] > c.min_height:
            break
    lookat_start = lookat_end = np.zeros(3)
    if c.moving_lookat:
        through = half_ball_point(rng, c.lookat_through_radius)
        lookat_start = half_ball_point(rng, c.lookat_start_radius, max_height=1.0)
        lookat_end = through + rng.uniform(0.0, c.lookat_extend) * (through - lookat_start)
        if rng.random() < 0.5:
            lookat_start, lookat_end = lookat_end, lookat_start
    return CameraSpec(float(c.focal_mm), float(c.sensor_mm), start, end, lookat_start, lookat_end)


def sample_lights(cfg, rng: np.random.Generator) -> tuple[list[LightSpec], float]:
    """A shadow-casting sun, a weaker fill light from the opposite side, and ambient light."""
    c = cfg.lights
    elevation = np.deg2rad(rng.uniform(*c.sun_elevation_deg))
    azimuth = rng.uniform(0, 2 * np.pi)
    to_sun = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                       np.sin(elevation)])
    to_fill = np.array([-to_sun[0], -to_sun[1], 0.8])
    to_fill /= np.linalg.norm(to_fill)
    warm = np.array([1.0, rng.uniform(0.9, 1.0), rng.uniform(0.8, 1.0)])
    lights = [
        LightSpec(-to_sun, float(rng.uniform(*c.sun_intensity)), warm,
                  bool(c.shadows)),
        LightSpec(-to_fill, float(rng.uniform(*c.fill_intensity)), np.ones(3),
                  False),
    ]
    return lights, float(rng.uniform(*c.ambient))


def _candidate_poses(rng: np.random.Generator, hull: np.ndarray, scale: float,
                     region: np.ndarray, tries: int) -> np.ndarray:
    """(tries,7) random poses whose rotated bounding box lies inside `region` (2,3)."""
    quats = geometry.quat_normalize(rng.normal(size=(tries, 4)))  # uniform on SO(3)
    quats *= np.where(quats[:, :1] < 0, -1.0, 1.0)
    points = np.einsum("nij,vj->nvi", geometry.quat_to_matrix(quats), hull * scale)  # (n,Vh,3)
    low, high = region[0] - points.min(axis=1), region[1] - points.max(axis=1)  # (n,3)
    # Where the object is larger than the region along an axis, centre it there.
    positions = np.where(low <= high, low + rng.random((tries, 3)) * (high - low), (low + high) / 2)
    return np.concatenate([positions, quats], axis=1)


def _config_array(rows) -> np.ndarray:
    """float64 (n,m) array of a config's list of lists (a region, a velocity range), made from
    plain lists: numpy probes an omegaconf list for array attributes, ~0.1 ms of raised errors."""
    return np.array([list(row) for row in rows], dtype=np.float64)


def _sample_objects(cfg, rng: np.random.Generator, assets: AssetLibrary) -> list[ObjectSpec]:
    c = cfg.objects
    regions = {False: _config_array(c.static_region), True: _config_array(c.tossed_region)}
    tossed_velocity = _config_array(c.tossed_velocity)
    num_static = int(rng.integers(c.num_static[0], c.num_static[1] + 1))
    num_tossed = int(rng.integers(c.num_tossed[0], c.num_tossed[1] + 1))
    specs = []
    for tossed in [False] * num_static + [True] * num_tossed:
        asset_id, asset = assets.draw(rng)  # skips broken assets, warning once for each
        scale = float(rng.uniform(*c.scale))
        specs.append(ObjectSpec(
            asset_id=asset_id,
            scale=scale,
            tossed=tossed,
            candidates=_candidate_poses(rng, asset.hull_vertices, scale, regions[tossed],
                                        int(c.placement_tries)),
            velocity=rng.uniform(*tossed_velocity) if tossed else np.zeros(3),
            mass=float(c.density) * asset.volume * scale**3,
            friction=float(c.friction),
            restitution=float(c.restitution),
            texture_seed=int(rng.integers(2**31)),
            uv_tiles=float(rng.uniform(*c.uv_tiles)),
        ))
    return specs


def sample_scene(cfg, rng: np.random.Generator, assets: AssetLibrary) -> SceneDescription:
    """Draw a whole scene description from the preset `cfg`."""
    height, width = (int(v) for v in cfg.resolution)
    objects = _sample_objects(cfg, rng, assets)
    camera = sample_camera(cfg, rng)
    lights, ambient = sample_lights(cfg, rng)
    background_id = (assets.background_ids[int(rng.integers(len(assets.background_ids)))]
                     if assets.background_ids else None)
    backdrop_seed = int(rng.integers(2**31))
    motion_blur = float(rng.uniform(0.0, cfg.blur.max_shutter)) if cfg.blur.max_shutter > 0 else 0.0
    meta = {
        "camera": {"start": camera.start.tolist(), "end": camera.end.tolist(),
                   "lookat_start": camera.lookat_start.tolist(),
                   "lookat_end": camera.lookat_end.tolist(),
                   "focal_mm": camera.focal_mm, "sensor_mm": camera.sensor_mm},
        "lights": [{"direction": l.direction.tolist(), "intensity": l.intensity,
                    "shadows": l.shadows} for l in lights],
        "ambient": ambient,
        "background": background_id,
        "sampled_objects": [o.summary() for o in objects],
    }
    return SceneDescription(int(cfg.frames), int(cfg.fps), height, width, objects, camera, lights,
                            ambient, background_id, backdrop_seed, motion_blur, meta)
