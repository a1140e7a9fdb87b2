"""Rigid-body physics of a scene description with pybullet (240 Hz, gravity -10 along Z).

Kubric's recipe: static objects are placed without overlap and settle (friction 1, restitution 0)
before the toss; then they get friction/restitution 0.5/0.5, their velocities are zeroed, the
tossed objects are placed among them and thrown. Poses are recorded at every physics step from the
toss (time -1, in frames) to time T, so sub-frame poses for motion blur come straight from physics.
Velocities are pybullet's at every frame time, and (when asked) every contact of every step is
kept, as Kubric records its collision events.

Deviations from Kubric: collision shapes are convex hulls of the visual meshes (not VHACD
decompositions), mass is density x hull volume at the object's scale (not the unscaled GSO mass),
settling uses extra damping and ends early once every object is nearly at rest, a second settling
phase under the video's friction, restitution and damping follows it (without it a third of the
untouched static objects slid or toppled in the video once friction dropped), and the settled
objects' angular velocities are zeroed along with their linear ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pybullet as pb

from c4d_core import geometry
from datagen.assets import AssetLibrary
from datagen.sampling import SceneDescription


@dataclass
class SimulationResult:
    placed: list[int]  # indices into description.objects of the objects in the scene (K of them)
    steps_per_frame: int
    positions: np.ndarray  # float64 (K,S,3) at every physics step, S = (T+1)*steps_per_frame + 1
    quaternions: np.ndarray  # float64 (K,S,4) (w,x,y,z)
    start_velocities: np.ndarray  # float64 (K,3) at the toss (units/s)
    settle_steps: int
    velocities: np.ndarray  # float64 (K,T+2,3) linear, world, units/s, at frame times -1..T
    angular_velocities: np.ndarray  # float64 (K,T+2,3) world, rad/s, at frame times -1..T
    contacts: np.ndarray | None  # CONTACT_DTYPE (E,) every contact of every step; None: not kept

    def poses_at(self, times: np.ndarray) -> np.ndarray:
        """Object-to-world (K,n,4,4) at n frame times in [-1, T], interpolated between steps."""
        steps = (np.asarray(times, dtype=np.float64) + 1.0) * self.steps_per_frame  # (n,)
        lo = np.clip(np.floor(steps).astype(int), 0, self.positions.shape[1] - 1)
        hi = np.minimum(lo + 1, self.positions.shape[1] - 1)
        alpha = steps - lo  # (n,)
        pos = (1 - alpha[:, None]) * self.positions[:, lo] + alpha[:, None] * self.positions[:, hi]
        quat = geometry.quat_slerp(self.quaternions[:, lo], self.quaternions[:, hi], alpha)
        return geometry.make_pose(geometry.quat_to_matrix(quat), pos)  # (K,n,4,4)


# One contact point of one step (pybullet's getContactPoints): the bodies as object indices into
# `placed` (-1: the floor), the step (0 at time -1), the point on body b and the normal on b
# (pointing from b to a), both world, the normal force (N) and the signed distance (units).
CONTACT_DTYPE = np.dtype([("bodies", np.int32, (2,)), ("step", np.int32),
                          ("position", np.float64, (3,)), ("normal", np.float64, (3,)),
                          ("force", np.float64), ("distance", np.float64)])
MIN_CONTACT_FORCE = 1e-6  # N; Kubric's threshold for a contact to count as a collision event


def _contact_rows(points: list[tuple], steps: list[int], index_of: dict[int, int]) -> np.ndarray:
    """The contacts pressing with more than `MIN_CONTACT_FORCE`, as `CONTACT_DTYPE` (E,), from
    pybullet's `getContactPoints` tuples of every step (`points`, the step of each in `steps`);
    `index_of` maps body ids to object indices (-1 for the floor)."""
    rows = np.zeros(len(points), CONTACT_DTYPE)
    if points:
        # getContactPoints' fields: 1, 2 bodies a and b; 6 position on b; 7 normal on b;
        # 8 distance; 9 normal force
        columns = list(zip(*points))
        rows["bodies"] = [[index_of[a], index_of[b]] for a, b in zip(columns[1], columns[2])]
        rows["step"], rows["position"], rows["normal"] = steps, columns[6], columns[7]
        rows["distance"], rows["force"] = columns[8], columns[9]
    return rows[rows["force"] > MIN_CONTACT_FORCE]


def _configure(client: int, cfg) -> None:
    # Kubric's engine parameters (they avoid bullet3#3094, objects sticking to walls).
    pb.setPhysicsEngineParameter(
        fixedTimeStep=1.0 / cfg.physics.step_rate, restitutionVelocityThreshold=0,
        warmStartingFactor=0, useSplitImpulse=True, contactSlop=0, enableConeFriction=False,
        deterministicOverlappingPairs=True, physicsClientId=client)
    pb.setGravity(0, 0, float(cfg.physics.gravity), physicsClientId=client)


def _overlaps(client: int, body: int, others: list[int]) -> bool:
    return any(pb.getClosestPoints(body, other, 0.0, physicsClientId=client) for other in others)


def _place(client: int, body: int, candidates: np.ndarray, others: list[int]) -> bool:
    """Move `body` to the first candidate pose touching none of `others`; False if none is free."""
    for candidate in candidates:
        pb.resetBasePositionAndOrientation(body, candidate[:3].tolist(),
                                           geometry.quat_to_xyzw(candidate[3:]).tolist(),
                                           physicsClientId=client)
        pb.performCollisionDetection(physicsClientId=client)
        if not _overlaps(client, body, others):
            return True
    return False


def _all_slower(client: int, bodies: list[int], speed: float) -> bool:
    """Whether every body's linear (units/s) and angular (rad/s) speed is below `speed`.

    The norms are taken at once; any within rounding of `speed` is taken again alone, as
    `np.linalg.norm` of one vector (BLAS's dot, which can round the last bit differently), so
    the answer is the same as norming each vector on its own.
    """
    velocities = np.array([pb.getBaseVelocity(body, physicsClientId=client) for body in bodies],
                          np.float64).reshape(-1, 3)  # (2B,3) linear and angular per body
    norms = np.linalg.norm(velocities, axis=-1)  # (2B,)
    near = np.abs(norms - speed) <= 1e-9 * abs(speed)
    if near.any():
        norms[near] = [np.linalg.norm(v) for v in velocities[near]]
    return bool(np.max(norms, initial=0.0) < speed)


def _settle(client: int, bodies: list[int], max_frames: int, steps_per_frame: int,
            speed: float, hold_frames: int = 1) -> int:
    """Step until every body was slower than `speed` (units/s, rad/s) at the end of `hold_frames`
    frames in a row, or for `max_frames` frames; returns the number of steps taken."""
    still = 0
    for frame in range(max_frames):
        for _ in range(steps_per_frame):
            pb.stepSimulation(physicsClientId=client)
        still = still + 1 if _all_slower(client, bodies, speed) else 0
        if still == hold_frames:
            return (frame + 1) * steps_per_frame
    return max_frames * steps_per_frame


def simulate(description: SceneDescription, assets: AssetLibrary, cfg) -> SimulationResult:
    """Place, settle, toss and simulate; returns poses at every step from time -1 to time T,
    velocities at every frame time and, where `cfg.layers.events` is on, every contact of those
    steps."""
    contacts = bool(cfg.layers.events)
    steps_per_frame = int(round(cfg.physics.step_rate / description.fps))
    client = pb.connect(pb.DIRECT)
    try:
        _configure(client, cfg)
        floor_shape = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=client)
        floor = pb.createMultiBody(0, floor_shape, physicsClientId=client)
        pb.changeDynamics(floor, -1, lateralFriction=cfg.objects.settle_friction,
                          restitution=cfg.objects.settle_restitution, physicsClientId=client)
        bodies: dict[int, int] = {}  # object index -> body id

        def add(index: int, friction: float, restitution: float, damping: float) -> None:
            spec = description.objects[index]
            asset = assets.get(spec.asset_id)
            shape = pb.createCollisionShape(
                pb.GEOM_MESH, vertices=asset.hull_vertices.tolist(), meshScale=[spec.scale] * 3,
                physicsClientId=client)
            body = pb.createMultiBody(spec.mass, shape, useMaximalCoordinates=True,
                                      physicsClientId=client)
            pb.changeDynamics(body, -1, lateralFriction=friction, restitution=restitution,
                              contactProcessingThreshold=0, linearDamping=damping,
                              angularDamping=damping, physicsClientId=client)
            if _place(client, body, spec.candidates, [floor] + list(bodies.values())):
                bodies[index] = body
            else:
                pb.removeBody(body, physicsClientId=client)

        static = [i for i, o in enumerate(description.objects) if not o.tossed]
        for i in static:
            add(i, cfg.objects.settle_friction, cfg.objects.settle_restitution,
                cfg.physics.settle_damping)

        # Settle as Kubric does (friction 1, restitution 0), then give the static objects and the
        # floor the video's friction, restitution and damping and let them come to rest again:
        # objects leaning on others that friction 1 holds up slide or topple at the video's
        # friction (0.5 x 0.5 between objects, 0.5 x 0.3 on the floor), and they must do so
        # before the toss, not in the video.
        statics = list(bodies.values())
        settle_steps = _settle(client, statics, int(cfg.physics.settle_frames), steps_per_frame,
                               cfg.physics.settle_speed)
        for i, body in bodies.items():
            spec = description.objects[i]
            pb.changeDynamics(body, -1, lateralFriction=spec.friction, restitution=spec.restitution,
                              linearDamping=cfg.physics.damping, angularDamping=cfg.physics.damping,
                              physicsClientId=client)
        pb.changeDynamics(floor, -1, lateralFriction=cfg.physics.floor_friction,
                          restitution=cfg.physics.floor_restitution, physicsClientId=client)
        settle_steps += _settle(client, statics, int(cfg.physics.resettle_frames), steps_per_frame,
                                cfg.physics.settle_speed, int(cfg.physics.resettle_hold_frames))
        for body in statics:
            pb.resetBaseVelocity(body, [0, 0, 0], [0, 0, 0], physicsClientId=client)

        for i, spec in enumerate(description.objects):
            if spec.tossed:
                add(i, spec.friction, spec.restitution, cfg.physics.damping)
                if i in bodies:
                    position, _ = pb.getBasePositionAndOrientation(bodies[i],
                                                                   physicsClientId=client)
                    velocity = spec.velocity - np.array([position[0], position[1], 0.0])
                    pb.resetBaseVelocity(bodies[i], velocity.tolist(), [0, 0, 0],
                                         physicsClientId=client)

        placed = sorted(bodies)
        num_steps = (description.num_frames + 1) * steps_per_frame + 1
        states = []  # per step, per placed object: pybullet's (position, orientation (x,y,z,w))
        velocities = np.zeros((2, len(placed), description.num_frames + 2, 3))  # linear, angular
        start_velocities = np.array(
            [pb.getBaseVelocity(bodies[i], physicsClientId=client)[0] for i in placed]
        ).reshape(-1, 3)
        index_of = {floor: -1} | {bodies[i]: k for k, i in enumerate(placed)}
        contact_points: list[tuple] = []  # pybullet's tuples, of the step in contact_steps
        contact_steps: list[int] = []
        for step in range(num_steps):
            if step:
                pb.stepSimulation(physicsClientId=client)
                if contacts:
                    found = pb.getContactPoints(physicsClientId=client)
                    contact_points += found
                    contact_steps += [step] * len(found)
            states.append([pb.getBasePositionAndOrientation(bodies[i], physicsClientId=client)
                           for i in placed])
            if step % steps_per_frame == 0:
                for k, i in enumerate(placed):
                    velocities[:, k, step // steps_per_frame] = pb.getBaseVelocity(
                        bodies[i], physicsClientId=client)
    finally:
        pb.disconnect(physicsClientId=client)
    # (K,S,3) and (K,S,4), kept in Python lists while stepping (a numpy row write per step and
    # object cost more than pybullet's query)
    positions = np.array([[p for p, _ in row] for row in states]).reshape(num_steps, -1, 3)
    quats_xyzw = np.array([[q for _, q in row] for row in states]).reshape(num_steps, -1, 4)
    positions, quats_xyzw = (np.ascontiguousarray(a.transpose(1, 0, 2))
                             for a in (positions, quats_xyzw))
    return SimulationResult(placed, steps_per_frame, positions, geometry.quat_from_xyzw(quats_xyzw),
                            start_velocities, settle_steps, velocities[0], velocities[1],
                            _contact_rows(contact_points, contact_steps, index_of)
                            if contacts else None)
