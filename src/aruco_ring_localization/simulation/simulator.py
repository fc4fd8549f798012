"""What the ``simulator`` node does per frame, without ROS (:class:`SimulatorCore`): testable.

The node (``ros/simulator.py``) only converts: it reads :class:`~.params.SimulatorConfig`, calls
:meth:`SimulatorCore.step` once per frame and publishes what the core returns (detections or
images, the true pose, odometry, the scan, the waypoint being held, and with ``gmapping.publish``
a perfect gmapping's ``map -> odom`` and occupancy grid).

The true rig is the ring file perturbed by a seeded calibration error (``ring.calibration_*``):
the estimators get the ring file, the simulator sees with the true rig.
"""
from __future__ import annotations

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
from .ring_sim import RingSimulator, perturb_ring
from .scene import Scene

logger = logging.getLogger(__name__)


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
        while self.pending_events and self.pending_events[0][0] <= t:
            _, marker, move, rot = self.pending_events.pop(0)
            self.sim.move_marker(marker, move, rot)
            logger.info("simulator: t=%.2f s: marker %d moved by %s m, rotated %s deg (scene event)", t, marker,
                        list(move), list(rot))
        self.state = self.robot.step(t, dt)
        return self.state

    @property
    def finished(self) -> bool:
        """True once every waypoint has been visited and held (never with ``robot.loop``)."""
        return self.robot.driver is None or self.robot.driver.finished

    def waypoints(self) -> List[Tuple[float, float, float]]:
        """The waypoint list being visited, (x, y, yaw rad) in the world."""
        return [tuple(float(v) for v in w) for w in (self.robot.driver.waypoints if self.robot.driver else [])]

    def T_world_base(self) -> np.ndarray:
        return Scene.T_world_base(self.state.pose)

    def detections(self, stamp: float) -> Dict[str, list]:
        """Corners mode: {camera: [MarkerObservation]} for the simulated cameras."""
        frame = self.sim.observe(self.T_world_base(), stamp)
        return {c: frame.cameras[c].observations for c in self.cameras}

    def images(self) -> Dict[str, np.ndarray]:
        """Image mode: {camera: mono8 image}."""
        return self.sim.render(self.T_world_base(), cameras=self.cameras)

    def scan(self) -> np.ndarray:
        return self.laser.scan(self.state.pose)

    def T_world_odom(self) -> np.ndarray:
        """What a perfect gmapping publishes as ``map -> odom`` (``map`` = the world): the odometry frame
        placed so that base_link is at its true pose."""
        return Scene.T_world_base(self.state.pose) @ geo.inverse(Scene.T_world_base(self.state.odom_pose))

    def occupancy_grid(self):
        """``(cells, origin)``: the room's walls and posts as gmapping's grid (:func:`laser.occupancy_grid`)."""
        return occupancy_grid(self.scene.obstacle_segments(), self.config.gmapping.resolution)
