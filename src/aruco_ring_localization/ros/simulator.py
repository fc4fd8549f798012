"""``simulator`` node: the simulated lab (scene + ring + robot) on ROS topics.

Every ``1/rate`` seconds it moves the robot (waypoint driver or ``cmd_vel``), then publishes:

* per ring camera ``<ns>`` (``ring/camK`` from the ring file, only ``~cameras`` if given):
  - corners mode: ``<ns>/fiducial_vertices`` (fiducial_msgs/FiducialArray, header.frame_id = the
    camera's optical frame, noisy projected corners of the visible markers, empty when none);
  - image mode: ``<ns>/image_raw`` (sensor_msgs/Image, mono8, rendered) for the detectors;
  - both modes: ``<ns>/camera_info`` (the camera's intrinsics, as a camera driver would);
* ``sim/ground_truth`` (geometry_msgs/PoseStamped, base_link's true pose in the world frame) and
  tf ``<ground_truth_parent> -> sim_ground_truth``;
* ``odom`` (nav_msgs/Odometry, drifting wheel odometry) and, if ``~publish_odom_tf``, tf
  ``odom -> base_link``;
* ``scan`` (sensor_msgs/LaserScan of the walls and posts, frame ``~laser_frame``);
* ``sim/at_waypoint`` (std_msgs/Int32: index of the waypoint being held, -1 while moving) and
  ``sim/waypoints`` (geometry_msgs/PoseArray, latched: the waypoint list in the world frame; also
  the parameter ``~waypoint_poses``, [[x, y, yaw_rad], ...]);
* ``cmd_vel`` (geometry_msgs/Twist) while its waypoint driver drives; otherwise it follows
  ``cmd_vel`` from others (holonomic: linear.x, linear.y, angular.z; stops 0.5 s after the last);
* ``/clock`` when ``~publish_clock`` (run everything with ``use_sim_time``). With ``~lockstep``
  too, in images mode, the clock only moves on once every simulated camera's detector has
  published ``<ns>/fiducial_vertices`` for the current frame (at most ``~lockstep_timeout`` wall
  seconds): no frame is dropped on a slow CPU, the simulated clock just runs slower.

It subscribes ``sim/teleport`` (geometry_msgs/Pose2D, world frame): the robot is carried there
between two steps (a kidnap: the wheel odometry does not see it), for fault tests.

The true rig is the ring file perturbed by a seeded calibration error (``~calibration_*``):
the estimators get the ring file, the simulator sees with the true rig.
Parameters are documented in ``docs/simulation.md`` and :class:`SimulatorParams`.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from .. import geometry as geo
from ..errors import ArucoRingError, ConfigError
from ..ring import CameraRing
from ..simulation.laser import LaserScanner
from ..simulation.lockstep import FrameGate
from ..simulation.motion import MotionLimits, RobotState, SimRobot
from ..simulation.ring_sim import RingSimulator, perturb_ring
from ..simulation.scene import Scene

WAYPOINT_SETS = ("test_positions", "test_orientations", "paper", "mapping_stations", "mapping_pose", "none")


@dataclass(frozen=True)
class SimulatorParams:
    """Private parameters of the simulator node (``~name``)."""

    scene_file: str = field(default="", metadata={"doc": "scene YAML; empty = the package's config/lab_scene.yaml"})
    ring_file: str = field(default="", metadata={"doc": "ring YAML (the calibration); empty = config/ring.yaml"})
    mode: str = field(default="corners", metadata={"doc": "corners (projected detections) | images (rendered)"})
    cameras: Tuple[str, ...] = field(default=(), metadata={"doc": "camera names to simulate; empty = all"})
    rate: float = field(default=10.0, metadata={"doc": "frames per (simulated) second, Hz"})
    seed: int = field(default=0, metadata={"doc": "seed of every random draw"})
    pixel_noise: float = field(default=0.3, metadata={"doc": "corners mode: corner noise std, px"})
    max_range: float = field(default=8.0, metadata={"doc": "markers farther than this (m) are not seen"})
    calibration_trans_std: float = field(default=0.002, metadata={"doc": "true rig vs ring file, m per axis"})
    calibration_rot_std_deg: float = field(default=0.2, metadata={"doc": "true rig vs ring file, deg per axis"})
    waypoints: str = field(default="test_positions", metadata={"doc": "|".join(WAYPOINT_SETS)})
    hold_time: float = field(default=3.0, metadata={"doc": "seconds held at each waypoint"})
    drive: str = field(default="cmd_vel",
                       metadata={"doc": "cmd_vel (drive between waypoints) | direct or teleport (jump)"})
    loop: bool = field(default=False, metadata={"doc": "visit the waypoints again and again"})
    start_pose: Tuple[float, ...] = field(default=(), metadata={"doc": "[x, y, yaw_deg]; empty = mapping pose"})
    max_speed: float = 0.3
    max_yaw_rate: float = 0.6
    max_accel: float = 0.5
    max_yaw_accel: float = 1.0
    ground_truth_parent: str = field(default="world", metadata={"doc": "parent frame of the sim_ground_truth tf"})
    ground_truth_frame: str = "sim_ground_truth"
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    publish_odom_tf: bool = True
    laser_frame: str = field(default="base_link", metadata={"doc": "frame_id of scan (at base_link's origin)"})
    scan_beams: int = 360
    scan_range_max: float = 20.0
    publish_scan: bool = True
    publish_clock: bool = field(default=False, metadata={"doc": "publish /clock (run with use_sim_time)"})
    speed: float = field(default=1.0, metadata={"doc": "with publish_clock: simulated seconds per wall second"})
    start_time: float = field(default=1.0, metadata={"doc": "with publish_clock: first simulated time, s"})
    lockstep: bool = field(default=False, metadata={
        "doc": "images mode with publish_clock: wait for every camera's fiducial_vertices of a frame before the next"})
    lockstep_timeout: float = field(default=2.0, metadata={"doc": "longest wait for the detectors, wall s"})

    def validate(self) -> "SimulatorParams":
        if self.mode not in ("corners", "images"):
            raise ConfigError(f"expected corners or images, got {self.mode!r}", key="mode")
        if self.waypoints not in WAYPOINT_SETS:
            raise ConfigError(f"expected one of {WAYPOINT_SETS}, got {self.waypoints!r}", key="waypoints")
        if self.drive not in ("cmd_vel", "direct", "teleport"):
            raise ConfigError(f"expected cmd_vel, direct or teleport, got {self.drive!r}", key="drive")
        if not self.rate > 0 or not self.speed > 0:
            raise ConfigError("rate and speed must be positive", key="rate")
        if self.start_pose and len(self.start_pose) != 3:
            raise ConfigError("expected [x, y, yaw_deg]", key="start_pose")
        return self


def waypoint_list(scene: Scene, which: str) -> List[Tuple[float, float, float]]:
    """The scene's poses for a ``~waypoints`` value."""
    return {
        "test_positions": list(scene.test_positions),
        "test_orientations": list(scene.test_orientations),
        "paper": list(scene.test_positions) + list(scene.test_orientations),
        "mapping_stations": list(scene.mapping_stations),
        "mapping_pose": [scene.mapping_pose],
        "none": [],
    }[which]


class SimulatorCore:
    """Everything the node does per step, without ROS (testable): robot, ring simulator, laser."""

    def __init__(self, params: SimulatorParams, scene: Scene, ring: CameraRing):
        self.params = params.validate()
        self.scene = scene
        self.calibrated_ring = ring
        self.true_ring = perturb_ring(ring, params.calibration_trans_std, params.calibration_rot_std_deg,
                                      seed=params.seed)
        unknown = [c for c in params.cameras if c not in ring.names]
        if unknown:
            raise ConfigError(f"unknown cameras {unknown}; the ring has {ring.names}", key="cameras")
        self.cameras = [c for c in ring.names if not params.cameras or c in params.cameras]
        self.sim = RingSimulator(scene, self.true_ring, pixel_noise=params.pixel_noise,
                                 max_range=params.max_range, seed=params.seed)
        start = (params.start_pose[0], params.start_pose[1], np.radians(params.start_pose[2])) \
            if params.start_pose else scene.mapping_pose
        limits = MotionLimits(params.max_speed, params.max_yaw_rate, params.max_accel, params.max_yaw_accel)
        self.robot = SimRobot(start, waypoint_list(scene, params.waypoints), hold_time=params.hold_time,
                              direct=params.drive in ("direct", "teleport"), limits=limits, seed=params.seed,
                              loop=params.loop)
        self.laser = LaserScanner(scene.obstacle_segments(), beams=params.scan_beams,
                                  range_max=params.scan_range_max, seed=params.seed)
        self.state = RobotState(self.robot.base.pose.copy(), np.zeros(3), np.zeros(3), np.zeros(3), -1)
        self._teleport: Optional[Tuple[float, float, float]] = None

    def request_teleport(self, x: float, y: float, yaw: float) -> None:
        """Carry the robot to (x, y, yaw rad) in the world before the next step (kidnap: the
        odometry does not see it). Safe to call from another thread; non-finite poses are ignored."""
        if all(np.isfinite(v) for v in (x, y, yaw)):
            self._teleport = (float(x), float(y), float(yaw))

    def step(self, t: float, dt: float) -> RobotState:
        pending, self._teleport = self._teleport, None
        if pending is not None:
            self.robot.base.teleport(pending)
        self.state = self.robot.step(t, dt)
        return self.state

    def waypoints(self) -> List[Tuple[float, float, float]]:
        """The waypoint list being visited, (x, y, yaw rad) in the world."""
        return [tuple(float(v) for v in w) for w in (self.robot.driver.waypoints if self.robot.driver else [])]

    def T_world_base(self) -> np.ndarray:
        return Scene.T_world_base(self.state.pose)

    def detections(self, stamp: float) -> Dict[str, list]:
        """Corners mode: {camera: [MarkerObservation]} for the simulated cameras."""
        T = self.T_world_base()
        frame = self.sim.observe(T, stamp)
        return {c: frame.cameras[c].observations for c in self.cameras}

    def images(self) -> Dict[str, np.ndarray]:
        """Image mode: {camera: mono8 image}."""
        return self.sim.render(self.T_world_base(), cameras=self.cameras)

    def scan(self) -> np.ndarray:
        return self.laser.scan(self.state.pose)


def _package_file(*parts: str) -> str:
    import rospkg
    return os.path.join(rospkg.RosPack().get_path("aruco_ring_localization"), *parts)


def main(argv: Optional[Sequence[str]] = None) -> int:
    import rospy
    import tf2_ros
    from fiducial_msgs.msg import FiducialArray
    from geometry_msgs.msg import Pose2D, PoseArray, PoseStamped, Twist
    from nav_msgs.msg import Odometry
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import CameraInfo, Image, LaserScan
    from std_msgs.msg import Int32

    from .conversions import make_transform_stamped, model_to_camera_info, observations_to_fiducials, pose_to_msg
    from .params import read_params

    rospy.init_node("simulator", argv=list(argv) if argv is not None else None)
    try:
        params = read_params(SimulatorParams).validate()
        scene = Scene.load(params.scene_file or _package_file("config", "lab_scene.yaml"))
        ring = CameraRing.load(params.ring_file or _package_file("config", "ring.yaml"))
        core = SimulatorCore(params, scene, ring)
    except ArucoRingError as exc:
        rospy.logfatal("simulator: %s", exc)
        return 1

    cams = [ring[c] for c in core.cameras]
    latch = dict(queue_size=2)
    info_msgs = {c.name: model_to_camera_info(c.model, c.frame_id) for c in cams}
    info_pubs = {c.name: rospy.Publisher(f"{c.namespace}/camera_info", CameraInfo, **latch) for c in cams}
    if params.mode == "corners":
        det_pubs = {c.name: rospy.Publisher(f"{c.namespace}/fiducial_vertices", FiducialArray, **latch)
                    for c in cams}
        img_pubs = {}
    else:
        det_pubs = {}
        img_pubs = {c.name: rospy.Publisher(f"{c.namespace}/image_raw", Image, queue_size=1) for c in cams}
    gt_pub = rospy.Publisher("sim/ground_truth", PoseStamped, queue_size=5)
    wp_pub = rospy.Publisher("sim/at_waypoint", Int32, queue_size=5)
    odom_pub = rospy.Publisher("odom", Odometry, queue_size=5)
    scan_pub = rospy.Publisher("scan", LaserScan, queue_size=2) if params.publish_scan else None
    cmd_pub = rospy.Publisher("cmd_vel", Twist, queue_size=5)
    clock_pub = rospy.Publisher("/clock", Clock, queue_size=5) if params.publish_clock else None
    tf_pub = tf2_ros.TransformBroadcaster()

    t_sim = [params.start_time]

    def now() -> float:
        return t_sim[0] if params.publish_clock else rospy.get_time()

    def on_cmd(msg: Twist) -> None:
        if core.robot.driving:
            return   # our own driver's command coming back
        core.robot.set_command((msg.linear.x, msg.linear.y, msg.angular.z), now())

    rospy.Subscriber("cmd_vel", Twist, on_cmd, queue_size=5)

    def on_teleport(msg: Pose2D) -> None:
        core.request_teleport(msg.x, msg.y, msg.theta)
        rospy.loginfo("simulator: teleported to (%.3f, %.3f, %.1f deg)", msg.x, msg.y, np.degrees(msg.theta))

    rospy.Subscriber("sim/teleport", Pose2D, on_teleport, queue_size=2)
    waypoints = core.waypoints()
    rospy.set_param("~waypoint_poses", [list(w) for w in waypoints])
    wp_list = PoseArray()
    wp_list.header.frame_id = scene.world_frame
    wp_list.poses = [pose_to_msg(Scene.T_world_base(w)) for w in waypoints]
    wp_list_pub = rospy.Publisher("sim/waypoints", PoseArray, queue_size=1, latch=True)
    wp_list_pub.publish(wp_list)
    rospy.loginfo("simulator: scene '%s' (%d markers), %s mode, %d cameras, %.1f Hz, waypoints %s, seed %d",
                  scene.name, len(scene.markers), params.mode, len(cams), params.rate, params.waypoints, params.seed)

    gate: Optional[FrameGate] = None
    if params.lockstep and params.mode == "images" and params.publish_clock:
        gate = FrameGate([c.name for c in cams])
        for c in cams:
            rospy.Subscriber(f"{c.namespace}/fiducial_vertices", FiducialArray,
                             lambda m, name=c.name: gate.report(name, m.header.stamp.to_sec()), queue_size=5)
        # Let the detectors connect first, or the first frames would only time out.
        wait_until = time.monotonic() + 10.0 * params.lockstep_timeout
        while not rospy.is_shutdown() and time.monotonic() < wait_until and \
                any(img_pubs[c.name].get_num_connections() == 0 for c in cams):
            time.sleep(0.05)
        rospy.loginfo("simulator: lockstep with the detectors of %s", " ".join(c.name for c in cams))
    elif params.lockstep:
        rospy.logwarn_once("simulator: ~lockstep needs mode images and publish_clock; ignored")

    dt = 1.0 / params.rate
    seq = 0
    last_t: Optional[float] = None
    wall_next = time.monotonic()
    while not rospy.is_shutdown():
        if params.publish_clock:
            t_sim[0] += dt
            clock_pub.publish(Clock(clock=rospy.Time.from_sec(t_sim[0])))
        t = now()
        step_dt = dt if last_t is None or params.publish_clock else max(1e-3, t - last_t)
        last_t = t
        try:
            state = core.step(t, step_dt)
            stamp = rospy.Time.from_sec(t)
            seq += 1
            _publish_robot(core, state, stamp, params, tf_pub, gt_pub, wp_pub, odom_pub, cmd_pub, scan_pub)
            for c in cams:
                info = info_msgs[c.name]
                info.header.stamp = stamp
                info_pubs[c.name].publish(info)
            if params.mode == "corners":
                for name, obs in core.detections(t).items():
                    msg = FiducialArray()
                    msg.header.stamp = stamp
                    msg.header.frame_id = ring[name].frame_id
                    msg.image_seq = seq
                    msg.fiducials = observations_to_fiducials(obs)
                    det_pubs[name].publish(msg)
            else:
                for name, img in core.images().items():
                    msg = Image()
                    msg.header.stamp = stamp
                    msg.header.frame_id = ring[name].frame_id
                    msg.height, msg.width = img.shape
                    msg.encoding = "mono8"
                    msg.is_bigendian = 0
                    msg.step = img.shape[1]
                    msg.data = img.tobytes()
                    img_pubs[name].publish(msg)
        except ArucoRingError as exc:
            rospy.logwarn_throttle(5.0, f"simulator: step failed: {exc}")
        if gate is not None:
            silent = gate.wait(t, params.lockstep_timeout)
            if silent:
                rospy.logwarn_throttle(10.0, f"simulator: lockstep: no fiducial_vertices for t={t:.2f} from "
                                             f"{' '.join(silent)} within {params.lockstep_timeout} s; going on")
        # Pace: wall time when we own the clock (speed x), ROS time otherwise.
        wall_next += dt / params.speed
        delay = wall_next - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            wall_next = time.monotonic()   # fell behind (slow rendering): do not try to catch up
    return 0


def _publish_robot(core: SimulatorCore, state: RobotState, stamp, params: SimulatorParams, tf_pub, gt_pub, wp_pub,
                   odom_pub, cmd_pub, scan_pub) -> None:
    from geometry_msgs.msg import PoseStamped, Twist
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import LaserScan

    from .conversions import make_transform_stamped, pose_to_msg

    T_world_base = Scene.T_world_base(state.pose)
    T_odom_base = Scene.T_world_base(state.odom_pose)
    tfs = [make_transform_stamped(T_world_base, params.ground_truth_parent, params.ground_truth_frame, stamp)]
    if params.publish_odom_tf:
        tfs.append(make_transform_stamped(T_odom_base, params.odom_frame, params.base_frame, stamp))
    tf_pub.sendTransform(tfs)
    gt = PoseStamped()
    gt.header.stamp = stamp
    gt.header.frame_id = core.scene.world_frame
    gt.pose = pose_to_msg(T_world_base)
    gt_pub.publish(gt)
    wp_pub.publish(int(state.holding))
    od = Odometry()
    od.header.stamp = stamp
    od.header.frame_id = params.odom_frame
    od.child_frame_id = params.base_frame
    od.pose.pose = pose_to_msg(T_odom_base)
    od.twist.twist.linear.x, od.twist.twist.linear.y = float(state.odom_velocity[0]), float(state.odom_velocity[1])
    od.twist.twist.angular.z = float(state.odom_velocity[2])
    # Diagonal covariances of a wheel odometry (x y z roll pitch yaw): honest, not tiny.
    od.pose.covariance = _diag6(0.01, 0.01, 1e6, 1e6, 1e6, 0.02)
    od.twist.covariance = _diag6(0.001, 0.001, 1e6, 1e6, 1e6, 0.002)
    odom_pub.publish(od)
    if core.robot.driving:
        tw = Twist()
        tw.linear.x, tw.linear.y, tw.angular.z = (float(v) for v in state.cmd)
        cmd_pub.publish(tw)
    if scan_pub is not None:
        scan = LaserScan()
        scan.header.stamp = stamp
        scan.header.frame_id = params.laser_frame
        scan.angle_min = core.laser.angle_min
        scan.angle_max = core.laser.angle_max
        scan.angle_increment = core.laser.angle_increment
        scan.time_increment = 0.0
        scan.scan_time = 1.0 / params.rate
        scan.range_min = core.laser.range_min
        scan.range_max = core.laser.range_max
        scan.ranges = core.scan().astype(np.float32).tolist()
        scan_pub.publish(scan)


def _diag6(*values: float) -> List[float]:
    out = [0.0] * 36
    for i, v in enumerate(values):
        out[i * 7] = float(v)
    return out
