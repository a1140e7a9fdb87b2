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
    """A camera moving on a straight line, as Kubric's MOVi worker keyframes it: at frame time t
    of a T-frame video the eye is at `start` + (t + 1) / (T + 2) x (`end` - `start`), so it leaves
    `start` at time -1 and would reach `end` at time T + 1 (the worker's keyframes 0..T+1 at
    interp = frame / (T + 2): the rendered frames 0..T-1 cover T / (T + 2) of the segment, 23/26
    at 24 frames). The look-at point moves from `lookat_start` to `lookat_end` alike."""

    focal_mm: float
    sensor_mm: float
    start: np.ndarray  # (3,) eye at time -1
    end: np.ndarray  # (3,) eye at time T + 1
    lookat_start: np.ndarray  # (3,)
    lookat_end: np.ndarray  # (3,)

    def pose_at(self, times: np.ndarray, num_frames: int) -> np.ndarray:
        """OpenCV camera-to-world (...,4,4) at frame times (...) in [-1, T]."""
        alpha = (np.asarray(times, dtype=np.float64)[..., None] + 1.0) / (num_frames + 2.0)
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
                            offset: float) -> np.ndarray:
    """A point (3,) of the upper half of the spherical shell r_min <= |p| <= r_max, drawn as
    Kubric's `sample_point_in_half_sphere_shell` draws it: a standard normal 3-vector, redrawn
    while its own (unnormalised) z is below `offset`, normalised and put at radius
    cbrt(U(r_min^3, r_max^3)), uniform in volume. The test on the raw normal draw, not on the
    point, is Kubric's: it keeps fewer points near the floor than a test of the point's height."""
    while True:
        normal = rng.normal(size=3)
        if normal[2] >= offset:
            break
    return np.cbrt(rng.uniform(r_min**3, r_max**3)) * normal / np.linalg.norm(normal)


def sample_camera(cfg, rng: np.random.Generator) -> CameraSpec:
    """Kubric's `linear_movement` (and `linear_movement_linear_lookat` when panning), drawn as
    `movi_def_worker.py` draws it (units: scene units).

    The travel distance is drawn once, U(0, `max_movement`); then a shell point
    (`half_sphere_shell_point` of `shell_radius`, offset `min_height`) and a direction
    (U[0,1)^3 - 0.5, normalised) are redrawn together until the moved point, shell point +
    distance x direction, lies in the shell with z > `min_height`. The worker's camera leaves the
    moved point for the shell point (its keyframes are interp x shell point + (1 - interp) x
    moved point), so the moved point is our `start`. Panning: the look-at path passes through a
    point of the upper half ball of radius `lookat_through_radius`; one end is a point of the
    upper half ball of radius `lookat_start_radius` below height `lookat_through_radius`, the
    other continues through the first by U(0, `lookat_extend`) of their difference; the ends are
    swapped with probability 1/2 and, as for the eye, the worker's second end is where it starts.
    """
    c = cfg.camera
    r_min, r_max = (float(r) for r in c.shell_radius)
    min_height = float(c.min_height)  # plain floats: a config read is slow inside the loop
    distance = rng.uniform(0.0, c.max_movement)
    while True:
        shell_point = half_sphere_shell_point(rng, r_min, r_max, min_height)
        direction = rng.random(3) - 0.5
        moved = shell_point + direction / np.linalg.norm(direction) * distance
        if r_min <= np.linalg.norm(moved) <= r_max and moved[2] > min_height:
            break
    lookat_start = lookat_end = np.zeros(3)
    if c.moving_lookat:
        through_radius = float(c.lookat_through_radius)
        through = half_sphere_shell_point(rng, 0.0, through_radius, 0.0)
        while True:
            first = half_sphere_shell_point(rng, 0.0, float(c.lookat_start_radius), 0.0)
            if first[2] < through_radius:
                break
        second = through + rng.uniform(0.0, c.lookat_extend) * (through - first)
        if rng.random() < 0.5:
            first, second = second, first
        lookat_start, lookat_end = second, first
    return CameraSpec(float(c.focal_mm), float(c.sensor_mm), moved, shell_point, lookat_start,
                      lookat_end)


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
