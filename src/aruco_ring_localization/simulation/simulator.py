"""What the ``simulator`` node does per frame, without ROS (:class:`SimulatorCore`): testable.

The node (``ros/simulator.py``) only converts: it reads :class:`~.params.SimulatorConfig`, calls
:meth:`SimulatorCore.step` once per frame and publishes what the core returns (detections or
images, the true pose, odometry, the scan, the waypoint being held, and with ``gmapping.publish``
a perfect gmapping's ``map -> odom`` and occupancy grid).

The true rig is the ring file perturbed by a seeded calibration error (``ring.calibration_*``):
the estimators get the ring file, the simulator sees with the true rig.

Cameras (``cameras.trigger``): *synchronized*, every camera exposes at the frame's time ``t``;
*free*, each camera exposes at its own time ``t - offset``, ``offset`` = the camera's phase (drawn
once, uniform in ``[0, phase_spread)`` frame periods) plus a per-frame Gaussian jitter
(``jitter_std``), kept within ``[0, 0.99]`` frame periods, so a camera's exposure of frame ``t``
lies in ``(t - dt, t]``. Each camera sees the robot where it was at its exposure time and its
messages are stamped with it. :meth:`SimulatorCore.true_pose_at` gives the ground truth at any
stamp: the robot's trajectory interpolated between the simulated steps (linear in x, y and yaw,
exactly what interpolating ``sim/ground_truth`` between two frames gives).
"""
from __future__ import annotations

import bisect
import logging
import threading
from typing import Dict, List, Optional, Tuple

import numpy as np

from .. import geometry as geo
from ..errors import ConfigError
from ..ring import CameraRing
from .laser import LaserScanner, occupancy_grid
from .motion import RobotState, SimRobot
from .params import SimulatorConfig, scene_event
from .conditions import Floor, Photometry, RingVibration
from .ring_sim import RingSimulator, perturb_ring
from .scene import Scene

logger = logging.getLogger(__name__)

#: Largest exposure offset of a free-running camera, in frame periods: its frame-t exposure lies in
#: (t - dt, t], after the previous frame's time (what the lockstep gate relies on).
MAX_OFFSET = 0.99
#: Trajectory samples kept for :meth:`SimulatorCore.true_pose_at` (at 10 Hz: 10,000 s).
HISTORY = 100000


def interpolate_se2(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    """(x, y, yaw) a fraction ``w`` of the way from pose ``a`` to ``b`` (yaw along the shorter arc)."""
    out = a + w * (b - a)
    out[2] = geo.wrap_angle(a[2] + w * geo.angle_diff(b[2], a[2]))
    return out


class CameraClock:
    """When each camera exposes, for frame time ``t`` (``cameras.trigger``, see the module's docstring).

    Its own seeded generator, so the synchronized lab draws exactly what it did before free cameras.
    """

    def __init__(self, cameras: List[str], trigger: str, rate: float, phase_spread: float, jitter_std: float,
                 seed: int = 0):
        self.cameras = list(cameras)
        self.free = trigger == "free"
        self.dt = 1.0 / float(rate)
        self.jitter_std = float(jitter_std)
        self.rng = np.random.default_rng([int(seed), 0xf3ee])
        self.phases = {c: float(self.rng.uniform(0.0, phase_spread)) * self.dt if self.free else 0.0
                       for c in self.cameras}

    def offsets(self) -> Dict[str, float]:
        """{camera: seconds before the frame's time at which it exposes this frame} (all 0 when synchronized)."""
        if not self.free:
            return {c: 0.0 for c in self.cameras}
        jitter = self.rng.normal(0.0, self.jitter_std, len(self.cameras)) if self.jitter_std > 0 \
            else np.zeros(len(self.cameras))
        return {c: float(np.clip(self.phases[c] + j, 0.0, MAX_OFFSET * self.dt))
                for c, j in zip(self.cameras, jitter)}


def waypoint_list(scene: Scene, which: str) -> List[Tuple[float, float, float]]:
    """The scene's poses (x, y, yaw rad) for a ``robot.waypoints`` value."""
    return {
        "test_positions": list(scene.test_positions),
        "test_orientations": list(scene.test_orientations),
        "paper": list(scene.test_positions) + list(scene.test_orientations),
        "mapping_stations": list(scene.mapping_stations),
        "mapping_pose": [scene.mapping_pose],
        "none": [],
    }[which]


def plan_poses(config: SimulatorConfig, scene: Scene) -> List[Tuple[float, float, float]]:
    """The waypoints the robot visits, (x, y, yaw rad): ``robot.plan`` when given, else the named set."""
    if config.robot.plan:
        return [(float(x), float(y), float(np.radians(yaw))) for x, y, yaw in config.robot.plan]
    return waypoint_list(scene, config.robot.waypoints)


class SimulatorCore:
    """The simulated lab for one node: robot, ring simulator (true rig), laser.

    Args:
        config: the node's parameters.
        scene: the hall.
        ring: the calibrated ring file (the true rig is derived from it with ``config.seed``).
    """

    def __init__(self, config: SimulatorConfig, scene: Scene, ring: CameraRing):
        self.config = config
        self.scene = scene
        self.calibrated_ring = ring
        self.true_ring = perturb_ring(ring, config.ring.calibration_trans_std, config.ring.calibration_rot_std_deg,
                                      seed=config.seed)
        unknown = [c for c in config.cameras.names if c not in ring.names]
        if unknown:
            raise ConfigError(f"unknown cameras {unknown}; the ring has {ring.names}", key="cameras.names")
        self.cameras = [c for c in ring.names if not config.cameras.names or c in config.cameras.names]
        self.sim = RingSimulator(scene, self.true_ring, pixel_noise=config.cameras.pixel_noise,
                                 max_range=config.cameras.max_range, seed=config.seed, render=config.render)
        self.floor = Floor(config.plate, scene.plate.centre, scene.robot.footprint, seed=config.seed)
        self.vibration = RingVibration(config.ring, seed=config.seed)
        self.photometry = Photometry(config.render, self.cameras, rate=config.rate, seed=config.seed)
        #: {camera: D} this frame's vibration of each camera (identities when the ring is rigid).
        self.shake: Dict[str, np.ndarray] = {}
        #: {camera: (gain, gradient, direction)} this frame's photometry (None: neutral).
        self.light: Dict[str, Optional[Tuple[float, float, float]]] = {}
        r = config.robot
        start = (r.start_pose[0], r.start_pose[1], np.radians(r.start_pose[2])) if r.start_pose else scene.mapping_pose
        self.robot = SimRobot(start, plan_poses(config, scene), hold_time=r.hold_time,
                              direct=r.drive in ("direct", "teleport"), limits=r.limits, seed=config.seed, loop=r.loop)
        self.laser = LaserScanner(scene.obstacle_segments(), beams=config.laser.beams,
                                  range_max=config.laser.range_max, seed=config.seed)
        self.state = RobotState(self.robot.base.pose.copy(), np.zeros(3), np.zeros(3), np.zeros(3), -1)
        self._teleport: Optional[Tuple[float, float, float]] = None
        #: scene events not applied yet (config ``events``), by time.
        self.pending_events = sorted((scene_event(e, f"events[{k}]") for k, e in enumerate(config.events)),
                                     key=lambda e: e[0])
        for _, marker, _, _ in self.pending_events:
            if marker not in scene.marker_ids:
                raise ConfigError(f"marker {marker} is not in the scene", key="events")
        self._lock = threading.Lock()
        cams = config.cameras
        self.camera_clock = CameraClock(self.cameras, cams.trigger, config.rate, cams.phase_spread, cams.jitter_std,
                                        seed=config.seed)
        #: {camera: exposure time} of the current frame (set by :meth:`step`).
        self.stamps: Dict[str, float] = {}
        self._times: List[float] = []
        self._poses: List[np.ndarray] = []

    def request_teleport(self, x: float, y: float, yaw: float) -> bool:
        """Carry the robot to (x, y, yaw rad) in the world before the next step (a kidnap: the
        odometry does not see it). Thread-safe; returns False (and ignores it) for a non-finite pose."""
        if not all(np.isfinite(v) for v in (x, y, yaw)):
            return False
        with self._lock:
            self._teleport = (float(x), float(y), float(yaw))
        return True

    def step(self, t: float, dt: float) -> RobotState:
        """Advance the robot to time ``t`` (s) by ``dt`` (s); returns its state."""
        with self._lock:
            pending, self._teleport = self._teleport, None
        if pending is not None:
            self.robot.base.teleport(pending)
            self._record(t - 1e-9, np.array(pending, dtype=float))   # no interpolation across a kidnap
        elif not self._times:
            self._record(t - dt, self.robot.base.pose.copy())       # at rest before the first frame
        while self.pending_events and self.pending_events[0][0] <= t:
            _, marker, move, rot = self.pending_events.pop(0)
            self.sim.move_marker(marker, move, rot)
            logger.info("simulator: t=%.2f s: marker %d moved by %s m, rotated %s deg (scene event)", t, marker,
                        list(move), list(rot))
        self.state = self.robot.step(t, dt)
        self._record(t, self.state.pose)
        self.stamps = {c: t - off for c, off in self.camera_clock.offsets().items()}
        self.shake = self.vibration.draw(self.true_ring.names)
        self.light = self.photometry.draw()
        return self.state

    def _record(self, t: float, pose: np.ndarray) -> None:
        if self._times and t <= self._times[-1]:
            # the clock went back (a time jump, a bag loop): the old trajectory means nothing now
            self._times, self._poses = [], []
        self._times.append(float(t))
        self._poses.append(np.array(pose, dtype=float).reshape(3))
        if len(self._times) > HISTORY:
            del self._times[:len(self._times) - HISTORY]
            del self._poses[:len(self._poses) - HISTORY]

    def true_se2_at(self, stamp: float) -> np.ndarray:
        """base_link's true (x, y, yaw) in the world at ``stamp`` (s): the trajectory interpolated
        between the simulated steps; held at its ends (before the first step: where it started)."""
        if not self._times:
            return self.state.pose.copy()
        k = bisect.bisect_left(self._times, stamp)
        if k <= 0:
            return self._poses[0].copy()
        if k >= len(self._times):
            return self._poses[-1].copy()
        if self._times[k] == stamp:
            return self._poses[k].copy()
        t0, t1 = self._times[k - 1], self._times[k]
        return interpolate_se2(self._poses[k - 1], self._poses[k], (stamp - t0) / (t1 - t0))

    def true_pose_at(self, stamp: float) -> np.ndarray:
        """base_link's true 4x4 pose ``T_world_base`` at ``stamp`` (s): standing on the floor (its
        height, roll and pitch from ``plate``; flat in the kind lab) at :meth:`true_se2_at`."""
        return self.floor.T_world_base(self.true_se2_at(stamp))

    def _camera_view_base(self, camera: str, stamp: float) -> np.ndarray:
        """The base pose through which ``camera`` sees at ``stamp``: the true pose, shaken by this
        frame's vibration of the camera."""
        T = self.true_pose_at(stamp)
        D = self.shake.get(camera)
        if D is None or self.vibration.rigid:
            return T
        return RingVibration.shaken_base(T, self.true_ring[camera].T_base_cam, D)

    def exposure_views(self, camera: str) -> List[np.ndarray]:
        """The base poses (shaken) averaged into ``camera``'s current image: its exposure
        (``render.exposure_time``, centred on the camera's stamp) sampled ``render.blur_samples``
        times while the robot moves, one view otherwise. Past the last step the trajectory is
        held (the few ms after the frame's time are not simulated yet)."""
        s = self.camera_stamp(camera)
        e = self.config.render.exposure_time
        n = self.config.render.blur_samples
        if e <= 0 or n <= 1:
            return [self._camera_view_base(camera, s)]
        ends = [self.true_se2_at(s - e / 2), self.true_se2_at(s + e / 2)]
        if np.allclose(ends[0], ends[1], rtol=0.0, atol=1e-7):
            return [self._camera_view_base(camera, s)]
        return [self._camera_view_base(camera, s - e / 2 + e * (k + 0.5) / n) for k in range(n)]

    @property
    def finished(self) -> bool:
        """True once every waypoint has been visited and held (never with ``robot.loop``)."""
        return self.robot.driver is None or self.robot.driver.finished

    def waypoints(self) -> List[Tuple[float, float, float]]:
        """The waypoint list being visited, (x, y, yaw rad) in the world."""
        return [tuple(float(v) for v in w) for w in (self.robot.driver.waypoints if self.robot.driver else [])]

    def T_world_base(self) -> np.ndarray:
        """base_link's true 4x4 pose now (on the floor: see :meth:`true_pose_at`)."""
        return self.floor.T_world_base(self.state.pose)

    def camera_stamp(self, camera: str) -> float:
        """The exposure time of ``camera``'s current frame (the frame's time when synchronized)."""
        return self.stamps.get(camera, self._times[-1] if self._times else 0.0)

    def detections(self, stamp: Optional[float] = None) -> Dict[str, list]:
        """Corners mode: {camera: [MarkerObservation]} for the simulated cameras, each seen from the
        robot's true pose at the camera's exposure time (:meth:`camera_stamp`). ``stamp`` is unused
        (kept for callers of the synchronized simulator: it was the frame's time)."""
        out = {}
        for cam in self.true_ring.cameras:   # every ring camera draws its noise, as before free cameras
            obs = self.sim.observe_camera(self._camera_view_base(cam.name, self.camera_stamp(cam.name)), cam)
            if cam.name in self.cameras:
                out[cam.name] = obs
        return out

    def images(self) -> Dict[str, np.ndarray]:
        """Image mode: {camera: mono8 image}, each rendered over the camera's exposure
        (:meth:`exposure_views`), with this frame's photometry."""
        return {c: self.sim.render_views(self.exposure_views(c), c, self.light.get(c)) for c in self.cameras}

    def scan(self) -> np.ndarray:
        return self.laser.scan(self.state.pose)

    def T_world_odom(self) -> np.ndarray:
        """What a perfect gmapping publishes as ``map -> odom`` (``map`` = the world): the odometry frame
        placed so that base_link is at its true pose."""
        return Scene.T_world_base(self.state.pose) @ geo.inverse(Scene.T_world_base(self.state.odom_pose))

    def occupancy_grid(self):
        """``(cells, origin)``: the room's walls and posts as gmapping's grid (:func:`laser.occupancy_grid`)."""
        return occupancy_grid(self.scene.obstacle_segments(), self.config.gmapping.resolution)
