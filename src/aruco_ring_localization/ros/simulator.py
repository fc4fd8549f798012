"""``simulator`` node: the simulated lab (scene + ring + robot) on ROS topics.

Every ``1/rate`` seconds it moves the robot (waypoint driver or ``cmd_vel``), then publishes:

* per ring camera ``<ns>`` (``ring/camK`` from the ring file, only ``cameras.names`` if given),
  stamped with the camera's exposure time (the frame's time with ``cameras.trigger: synchronized``;
  its own phase and jitter, within one frame period before it, with ``free``):
  - corners mode: ``<ns>/fiducial_vertices`` (fiducial_msgs/FiducialArray, header.frame_id = the
    camera's optical frame, noisy projected corners of the visible markers, empty when none);
  - image mode: ``<ns>/image_raw`` (sensor_msgs/Image, mono8, rendered) for the detectors;
  - both modes: ``<ns>/camera_info`` (the camera's intrinsics, as a camera driver would);
* ``sim/ground_truth`` (geometry_msgs/PoseStamped, base_link's true pose in the world frame) and
  tf ``<ground_truth.parent> -> <ground_truth.frame>``;
* ``odom`` (nav_msgs/Odometry, drifting wheel odometry) and, if ``odometry.publish_tf``, tf
  ``odom -> base_link``;
* ``scan`` (sensor_msgs/LaserScan of the walls and posts, frame ``laser.frame``);
* with ``gmapping.publish``, what a perfect gmapping would: tf ``map -> odom`` (base_link at its
  true pose; ``map`` is the world frame) and the room's occupancy grid on ``map`` (latched);
* ``sim/at_waypoint`` (std_msgs/Int32: index of the waypoint being held, -1 while moving or once
  finished) and ``sim/waypoints`` (geometry_msgs/PoseArray, latched: the waypoint list in the
  world frame; also the parameter ``sim/waypoint_poses``, [[x, y, yaw_rad], ...]);
* ``cmd_vel`` (geometry_msgs/Twist) while its waypoint driver drives; otherwise it follows
  ``cmd_vel`` from others (holonomic: linear.x, linear.y, angular.z; stops 0.5 s after the last);
* ``/clock`` when ``clock.publish`` (run everything with ``use_sim_time``). With ``lockstep.enabled``
  too, the clock only moves on once every connected consumer of the frame has answered it (at most
  ``lockstep.timeout`` wall seconds): in images mode every simulated camera's detector
  (``<ns>/fiducial_vertices``), in both modes each topic of ``lockstep.topics`` (e.g.
  ``localizer/pose``). No frame is dropped on a slow CPU, the simulated clock just runs slower.

Hooks, for tests and demos:

* ``sim/teleport`` (geometry_msgs/Pose2D, world frame): the robot is carried there before the next
  step (a kidnap: the wheel odometry does not see it);
* ``sim/time_jump`` (std_msgs/Float64, s; with ``clock.publish``): the clock jumps by that much
  before the next frame (negative: back in time, as when a bag loops).

Parameters: :class:`aruco_ring_localization.simulation.params.SimulatorConfig`, read once
(``config/simulator.yaml``, documented in docs/simulation.md).
"""
from __future__ import annotations

import os
import struct
import time
from typing import Dict, List, Optional, Sequence

import numpy as np

from ..errors import ArucoRingError
from ..ring import CameraRing
from ..simulation.lockstep import FrameGate, SimClock
from ..simulation.motion import RobotState
from ..simulation.params import SimulatorConfig
from ..simulation.scene import Scene, resolve_scene_file
from ..simulation.simulator import SimulatorCore

__all__ = ["SimulatorConfig", "SimulatorCore", "main", "header_stamp"]

#: Wall seconds between "every output has a subscriber" and the first frame (the subscribers' tf).
STARTUP_SETTLE = 1.0


def header_stamp(buff: bytes) -> Optional[float]:
    """The stamp (s) of a serialized message whose first field is a std_msgs/Header, or None.

    ROS 1 serialises a Header as ``uint32 seq``, ``time stamp`` (``uint32 secs``, ``uint32 nsecs``),
    then the frame_id, little-endian: the stamp is bytes 4..12 whatever the message type.
    """
    if len(buff) < 12:
        return None
    secs, nsecs = struct.unpack_from("<II", buff, 4)
    return secs + 1e-9 * nsecs


def _starts_with_header(definition: str) -> bool:
    """True when a message definition's first field is a std_msgs/Header (comments skipped)."""
    for line in definition.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            return line.split()[0] in ("Header", "std_msgs/Header")
    return False


def _package_file(*parts: str) -> str:
    import rospkg
    return os.path.join(rospkg.RosPack().get_path("aruco_ring_localization"), *parts)


class SimulatorNode:
    """Publishers, subscribers and the frame loop around :class:`SimulatorCore`."""

    def __init__(self, core: SimulatorCore):
        import rospy
        import tf2_ros
        from fiducial_msgs.msg import FiducialArray
        from geometry_msgs.msg import Pose2D, PoseArray, PoseStamped, Twist
        from nav_msgs.msg import Odometry
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import CameraInfo, Image, LaserScan
        from std_msgs.msg import Float64, Int32

        from .conversions import model_to_camera_info, pose_to_msg

        self.core = core
        c = self.config = core.config
        ring = core.calibrated_ring
        self.cams = [ring[name] for name in core.cameras]
        self.info_msgs = {cam.name: model_to_camera_info(cam.model, cam.frame_id) for cam in self.cams}
        self.info_pubs = {cam.name: rospy.Publisher(f"{cam.namespace}/camera_info", CameraInfo, queue_size=2)
                          for cam in self.cams}
        if c.mode == "corners":
            self.det_pubs = {cam.name: rospy.Publisher(f"{cam.namespace}/fiducial_vertices", FiducialArray,
                                                       queue_size=2) for cam in self.cams}
            self.img_pubs: Dict[str, object] = {}
        else:
            self.det_pubs = {}
            self.img_pubs = {cam.name: rospy.Publisher(f"{cam.namespace}/image_raw", Image, queue_size=1)
                             for cam in self.cams}
        self.gt_pub = rospy.Publisher("sim/ground_truth", PoseStamped, queue_size=5)
        self.wp_pub = rospy.Publisher("sim/at_waypoint", Int32, queue_size=5)
        self.odom_pub = rospy.Publisher("odom", Odometry, queue_size=5)
        self.scan_pub = rospy.Publisher("scan", LaserScan, queue_size=2) if c.laser.publish else None
        self.cmd_pub = rospy.Publisher("cmd_vel", Twist, queue_size=5)
        self.clock_pub = rospy.Publisher("/clock", Clock, queue_size=5) if c.clock.publish else None
        self.tf_pub = tf2_ros.TransformBroadcaster()
        self.dt = 1.0 / c.rate
        self.clock = SimClock(c.clock.start_time, self.dt)
        self.seq = 0

        rospy.Subscriber("cmd_vel", Twist, self._on_cmd, queue_size=5)
        rospy.Subscriber("sim/teleport", Pose2D, self._on_teleport, queue_size=2)
        rospy.Subscriber("sim/time_jump", Float64, self._on_time_jump, queue_size=2)
        waypoints = core.waypoints()
        rospy.set_param("sim/waypoint_poses", [list(w) for w in waypoints])
        wp_list = PoseArray()
        wp_list.header.frame_id = core.scene.world_frame
        wp_list.poses = [pose_to_msg(Scene.T_world_base(w)) for w in waypoints]
        self.wp_list_pub = rospy.Publisher("sim/waypoints", PoseArray, queue_size=1, latch=True)
        self.wp_list_pub.publish(wp_list)
        if c.gmapping.publish:
            self._publish_grid()
        self.gate, self._sources = self._lockstep()
        rospy.loginfo("simulator: scene '%s' (%d markers), %s mode, %d cameras, %.1f Hz, %d waypoints, seed %d%s",
                      core.scene.name, len(core.scene.markers), c.mode, len(self.cams), c.rate, len(waypoints),
                      c.seed, f", lockstep with {sorted(self._sources)}" if self.gate is not None else "")

    def _publish_grid(self) -> None:
        """gmapping's latched ``map`` topic: the room's occupancy grid (the stand-in's)."""
        import rospy
        from nav_msgs.msg import OccupancyGrid

        cells, origin = self.core.occupancy_grid()
        grid = OccupancyGrid()
        grid.header.frame_id = self.config.gmapping.map_frame
        grid.header.stamp = rospy.Time.now()
        grid.info.resolution = self.config.gmapping.resolution
        grid.info.height, grid.info.width = cells.shape
        grid.info.origin.position.x, grid.info.origin.position.y = float(origin[0]), float(origin[1])
        grid.info.origin.orientation.w = 1.0
        grid.data = cells.ravel().tolist()
        self.grid_pub = rospy.Publisher("map", OccupancyGrid, queue_size=1, latch=True)
        self.grid_pub.publish(grid)

    # --- inputs ---------------------------------------------------------------------------------

    def _now(self) -> float:
        import rospy
        return self.clock.now if self.clock_pub is not None and self.clock.now is not None else rospy.get_time()

    def _on_cmd(self, msg) -> None:
        if self.core.robot.driving:
            return   # our own driver's command coming back
        self.core.robot.set_command((msg.linear.x, msg.linear.y, msg.angular.z), self._now())

    def _on_teleport(self, msg) -> None:
        import rospy
        if self.core.request_teleport(msg.x, msg.y, msg.theta):
            rospy.loginfo("simulator: teleported to (%.3f, %.3f, %.1f deg)", msg.x, msg.y, np.degrees(msg.theta))
        else:
            rospy.logwarn("simulator: ignoring a non-finite sim/teleport (%s, %s, %s)", msg.x, msg.y, msg.theta)

    def _on_time_jump(self, msg) -> None:
        import rospy
        if self.clock_pub is None:
            rospy.logwarn_throttle(5.0, "simulator: sim/time_jump needs clock.publish; ignored")
            return
        if not np.isfinite(msg.data):
            rospy.logwarn("simulator: ignoring a non-finite sim/time_jump")
            return
        self.clock.request_jump(msg.data)
        rospy.loginfo("simulator: the clock jumps by %+.3f s at the next frame", msg.data)

    # --- lockstep -------------------------------------------------------------------------------

    def _lockstep(self):
        """The frame gate and {source: subscriber} when lockstep applies, else (None, {})."""
        import rospy
        from fiducial_msgs.msg import FiducialArray

        c = self.config
        if not c.lockstep.enabled:
            return None, {}
        if not c.clock.publish:
            if c.mode == "images" or c.lockstep.topics:
                rospy.logwarn_once("simulator: lockstep needs clock.publish (use_sim_time); off")
            return None, {}
        cameras = [cam for cam in self.cams if c.mode == "images"]
        if not cameras and not c.lockstep.topics:
            return None, {}
        # The gate exists before any subscriber whose callback reports to it.
        # Free-running cameras stamp a frame with their exposure time, within (t - dt, t]: any answer
        # newer than the previous frame's time is this frame's.
        tolerance = 0.995 * self.dt if c.cameras.trigger == "free" else 1e-6
        self.gate = FrameGate([cam.name for cam in cameras] + list(c.lockstep.topics), tolerance=tolerance)
        subs = {cam.name: rospy.Subscriber(f"{cam.namespace}/fiducial_vertices", FiducialArray,
                                           self._on_detections, callback_args=cam.name, queue_size=5)
                for cam in cameras}
        for topic in c.lockstep.topics:
            subs[topic] = rospy.Subscriber(topic, rospy.AnyMsg, self._on_consumer, callback_args=topic,
                                           queue_size=10)
        return self.gate, subs

    def _on_detections(self, msg, camera: str) -> None:
        self.gate.report(camera, msg.header.stamp.to_sec())

    def _on_consumer(self, msg, topic: str) -> None:
        import rospy
        definition = (getattr(msg, "_connection_header", None) or {}).get("message_definition", "")
        if definition and not _starts_with_header(definition):
            rospy.logwarn_once(f"simulator: lockstep topic {topic} has no std_msgs/Header first; not waited for")
            self.gate.sources = [s for s in self.gate.sources if s != topic]
            return
        stamp = header_stamp(msg._buff)
        if stamp is not None:
            self.gate.report(topic, stamp)

    def _connected(self) -> List[str]:
        return [name for name, sub in self._sources.items() if sub.get_num_connections() > 0]

    def _wait_for_consumers(self) -> None:
        """Before the first frame (the clock does not run meanwhile): let every camera's outputs get
        a subscriber and every lockstep topic a publisher, then 1 s more for the subscribers' other
        connections (tf), so a node started beside the simulator sees every frame."""
        import rospy

        c = self.config
        outputs = [p for pubs in (self.info_pubs, self.det_pubs, self.img_pubs) for p in pubs.values()]
        topics = [name for name in c.lockstep.topics if name in self._sources]
        deadline = time.monotonic() + c.lockstep.startup_timeout
        while not rospy.is_shutdown() and time.monotonic() < deadline:
            if all(p.get_num_connections() > 0 for p in outputs) and all(
                    self._sources[name].get_num_connections() > 0 for name in topics):
                time.sleep(STARTUP_SETTLE)
                return
            time.sleep(0.05)
        unconnected = [p.name for p in outputs if p.get_num_connections() == 0] + \
            [name for name in topics if self._sources[name].get_num_connections() == 0]
        if unconnected and c.lockstep.startup_timeout > 0:
            rospy.logwarn("simulator: starting after %.0f s without a consumer of %s", c.lockstep.startup_timeout,
                          " ".join(unconnected))

    def _creep(self, waited: float) -> None:
        from rosgraph_msgs.msg import Clock
        import rospy
        self.clock_pub.publish(Clock(clock=rospy.Time.from_sec(self.clock.creep(waited))))

    # --- the loop -------------------------------------------------------------------------------

    def run(self) -> None:
        import rospy
        from rosgraph_msgs.msg import Clock

        c = self.config
        if self.clock_pub is not None:
            self.clock_pub.publish(Clock(clock=rospy.Time.from_sec(c.clock.start_time)))
        if self.clock_pub is not None and c.lockstep.enabled:
            self._wait_for_consumers()
        last_t: Optional[float] = None
        wall_next = time.monotonic()
        while not rospy.is_shutdown():
            if self.clock_pub is not None:
                t = self.clock.advance()
                if last_t is not None and t < last_t and self.gate is not None:
                    self.gate.reset()   # the clock jumped back: answers to the old stamps mean nothing
                self.clock_pub.publish(Clock(clock=rospy.Time.from_sec(t)))
                step_dt = self.dt
            else:
                t = rospy.get_time()
                step_dt = self.dt if last_t is None else max(1e-3, t - last_t)
            last_t = t
            try:
                self.publish_frame(t, step_dt)
            except ArucoRingError as exc:
                rospy.logwarn_throttle(5.0, f"simulator: step failed: {exc}")
            if self.gate is not None:
                late = self.gate.wait(t, c.lockstep.timeout, active=self._connected, idle=self._creep)
                if late:
                    rospy.logwarn_throttle(10.0, f"simulator: lockstep: no answer to the frame at t={t:.2f} from "
                                                 f"{' '.join(late)} within {c.lockstep.timeout} s; going on")
            # Pace: wall time when we own the clock (speed x), ROS time otherwise.
            wall_next += self.dt / c.clock.speed if self.clock_pub is not None else self.dt
            delay = wall_next - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                wall_next = time.monotonic()   # fell behind (slow rendering): do not try to catch up

    def publish_frame(self, t: float, dt: float) -> None:
        """One step of the robot, then everything the frame publishes, stamped ``t``."""
        import rospy
        from fiducial_msgs.msg import FiducialArray
        from sensor_msgs.msg import Image

        from .conversions import observations_to_fiducials

        core = self.core
        state = core.step(t, dt)
        stamp = rospy.Time.from_sec(t)
        self.seq += 1
        self._publish_robot(state, stamp)
        cam_stamps = {cam.name: rospy.Time.from_sec(core.camera_stamp(cam.name)) for cam in self.cams}
        for cam in self.cams:
            info = self.info_msgs[cam.name]
            info.header.stamp = cam_stamps[cam.name]
            self.info_pubs[cam.name].publish(info)
        if self.config.mode == "corners":
            for name, obs in core.detections().items():
                msg = FiducialArray()
                msg.header.stamp = cam_stamps[name]
                msg.header.frame_id = core.calibrated_ring[name].frame_id
                msg.image_seq = self.seq
                msg.fiducials = observations_to_fiducials(obs)
                self.det_pubs[name].publish(msg)
        else:
            for name, img in core.images().items():
                msg = Image()
                msg.header.stamp = cam_stamps[name]
                msg.header.frame_id = core.calibrated_ring[name].frame_id
                msg.height, msg.width = img.shape
                msg.encoding = "mono8"
                msg.is_bigendian = 0
                msg.step = img.shape[1]
                msg.data = img.tobytes()
                self.img_pubs[name].publish(msg)

    def _publish_robot(self, state: RobotState, stamp) -> None:
        from geometry_msgs.msg import PoseStamped, Twist
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import LaserScan

        from .conversions import make_transform_stamped, pose_to_msg

        c, core = self.config, self.core
        T_world_base = core.T_world_base()   # in 3D: on the plate (tilted in the harsh lab)
        T_odom_base = Scene.T_world_base(state.odom_pose)
        tfs = [make_transform_stamped(T_world_base, c.ground_truth.parent, c.ground_truth.frame, stamp)]
        if c.odometry.publish_tf:
            tfs.append(make_transform_stamped(T_odom_base, c.odometry.frame, c.odometry.base_frame, stamp))
        if c.gmapping.publish:   # a perfect gmapping: map -> odom, so that map -> base_link is the truth
            tfs.append(make_transform_stamped(core.T_world_odom(), c.gmapping.map_frame, c.odometry.frame, stamp)
                       if c.odometry.publish_tf else
                       make_transform_stamped(T_world_base, c.gmapping.map_frame, c.odometry.base_frame, stamp))
        self.tf_pub.sendTransform(tfs)
        gt = PoseStamped()
        gt.header.stamp = stamp
        gt.header.frame_id = core.scene.world_frame
        gt.pose = pose_to_msg(T_world_base)
        self.gt_pub.publish(gt)
        self.wp_pub.publish(int(state.holding))
        od = Odometry()
        od.header.stamp = stamp
        od.header.frame_id = c.odometry.frame
        od.child_frame_id = c.odometry.base_frame
        od.pose.pose = pose_to_msg(T_odom_base)
        od.twist.twist.linear.x, od.twist.twist.linear.y = float(state.odom_velocity[0]), float(state.odom_velocity[1])
        od.twist.twist.angular.z = float(state.odom_velocity[2])
        # Diagonal covariances of a wheel odometry (x y z roll pitch yaw): honest, not tiny.
        od.pose.covariance = _diag6(0.01, 0.01, 1e6, 1e6, 1e6, 0.02)
        od.twist.covariance = _diag6(0.001, 0.001, 1e6, 1e6, 1e6, 0.002)
        self.odom_pub.publish(od)
        if core.robot.driving:
            tw = Twist()
            tw.linear.x, tw.linear.y, tw.angular.z = (float(v) for v in state.cmd)
            self.cmd_pub.publish(tw)
        if self.scan_pub is not None:
            scan = LaserScan()
            scan.header.stamp = stamp
            scan.header.frame_id = c.laser.frame
            scan.angle_min = core.laser.angle_min
            scan.angle_max = core.laser.angle_max
            scan.angle_increment = core.laser.angle_increment
            scan.time_increment = 0.0
            scan.scan_time = 1.0 / c.rate
            scan.range_min = core.laser.range_min
            scan.range_max = core.laser.range_max
            scan.ranges = core.scan().astype(np.float32).tolist()
            self.scan_pub.publish(scan)


def _diag6(*values: float) -> List[float]:
    out = [0.0] * 36
    for i, v in enumerate(values):
        out[i * 7] = float(v)
    return out


def main(argv: Optional[Sequence[str]] = None) -> int:
    import rospy

    from .params import read_config

    rospy.init_node("simulator", argv=list(argv) if argv is not None else None)
    try:
        config = read_config(SimulatorConfig)
        scene = Scene.load(resolve_scene_file(config.scene.file) if config.scene.file
                           else _package_file("config", "lab_scene.yaml"))
        ring = CameraRing.load(config.ring.file or _package_file("config", "ring.yaml"))
        core = SimulatorCore(config, scene, ring)
        node = SimulatorNode(core)
    except ArucoRingError as exc:
        rospy.logfatal("simulator: %s", exc)
        return 1
    node.run()
    return 0
