"""``localizer`` node: the robot pose from the ring's detections against a marker map.

Thin: it converts messages, calls :class:`aruco_ring_localization.pipeline.LocalizationPipeline`
(per-camera PnP / joint estimate -> gate -> Kalman filter, the stale-frame and time-jump policy)
and publishes what the pipeline returns. ``aruco_ring localize`` drives the same pipeline from a
bag, with the same parameters (config/localization.yaml).

Subscribes: ``<ns>/fiducial_vertices`` + ``<ns>/camera_info`` per camera (through
:class:`ros.ring_input.RingSubscriber`), ``cmd_vel`` (geometry_msgs/Twist), ``odom``
(nav_msgs/Odometry, optional; with ``motion/odometry`` its pose predicts the filter and each message
gives a pose out), ``imu`` (sensor_msgs/Imu, with ``motion/imu`` only: its yaw rate), ``initialpose`` (geometry_msgs/PoseWithCovarianceStamped, rviz
"2D Pose Estimate"), ``/tf`` and ``/tf_static`` (:class:`ros.tf_output.TfListener`: our own /tf
messages coming back are dropped unread).
Publishes: ``~pose`` (PoseWithCovarianceStamped, REP-103 covariance order, robot_localization
ready), ``~odometry`` (nav_msgs/Odometry with the filter's twist), ``~camera_estimates``
(PoseArray, one per camera), ``~markers`` (MarkerArray, markers in view highlighted),
``/diagnostics`` (diagnostic_updater: per camera, the filter, and the moved-marker check: which
markers moved and how far), ``~marker_grid`` (nav_msgs/OccupancyGrid, latched: the marker map for
map_server-style tools), tf ``map -> odom`` or ``map -> base_link``. Services: ``~reset``
(std_srvs/Trigger), ``~static_map`` (nav_msgs/GetMap, map_server's service type: that grid);
``~remap_marker`` (std_srvs/Trigger: re-map the markers of ``~remap_marker_ids``, default every
marker declared moved, from their recent observations with the others fixed, in memory);
``~save_map`` (std_srvs/Trigger: write the map in memory to ``~map_file`` atomically with backups).

Another node publishing the tf child frame we publish (a second localizer, gmapping's
``map -> odom``) is warned about, throttled, at its first such message (docs/security.md).

Parameters: :class:`aruco_ring_localization.schemas.LocalizerConfig` (config/localization.yaml,
docs/parameters.md).
"""
from __future__ import annotations

import sys
from typing import Dict, List, Optional, Sequence

import diagnostic_updater
import numpy as np
import rospy
import tf2_ros
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped, Twist
from nav_msgs.msg import OccupancyGrid, Odometry
from nav_msgs.srv import GetMap, GetMapResponse
from sensor_msgs.msg import Imu
from std_srvs.srv import Trigger, TriggerResponse
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import Marker, MarkerArray

from .. import geometry as geo
from ..errors import ArucoRingError, ConfigError
from ..marker_grid import marker_grid
from ..marker_check import parse_marker_ids
from ..marker_map import MarkerMap
from ..odometry import odometry_in_base
from ..pipeline import LocalizationPipeline, PoseOutput, StatusReport
from ..ring import CameraRing
from ..threads import limit_threads, tune_malloc
from ..schemas import LocalizerConfig
from . import log_bridge
from .conversions import msg_to_transform, pose_msg_to_transform, pose_to_msg, stamp_to_sec
from .params import read_config
from .ring_input import BUFF_SIZE, NOW, RingSubscriber
from .ring_tf import default_ring_file
from .tf_output import MapTransform, TfListener

WARN_PERIOD = 5.0


class LocalizerNode:
    """ROS wiring around :class:`LocalizationPipeline`."""

    def __init__(self, config: LocalizerConfig, ring: CameraRing, marker_map: MarkerMap):
        self.config = config
        out = config.output
        self.pipeline = LocalizationPipeline(config, ring, marker_map)
        self.marker_map = marker_map
        self.map_frame = out.map_frame or marker_map.frame_id
        self.base_frame = out.base_frame or ring.base_frame
        self._mounts: Dict[str, np.ndarray] = {}   # odom child frames: T_base_child, looked up once
        self.tf_buffer = tf2_ros.Buffer()
        # Set before the listener exists: its /tf callback (check_tf_authority) may run at once, on
        # another node's message, while this constructor is still going (rostest hostile_stamps).
        self._tf_child: Optional[str] = None   # the child frame we last put on tf (check_tf_authority)
        # tf2_ros's listener, but our own tf coming back through /tf is dropped as bytes (put in the
        # buffer as it goes out); the others' messages also go to the tf authority check.
        self.tf_listener = TfListener(self.tf_buffer, "localizer", on_other=self.check_tf_authority)
        self.tf_broadcaster = tf2_ros.TransformBroadcaster()
        self.map_tf = MapTransform(self.tf_buffer, self.map_frame, self.base_frame, out.odom_frame, out.tf_mode,
                                   "localizer")
        self.pub_pose = rospy.Publisher("~pose", PoseWithCovarianceStamped, queue_size=10)
        self.pub_odom = rospy.Publisher("~odometry", Odometry, queue_size=10)
        self.pub_cams = rospy.Publisher("~camera_estimates", PoseArray, queue_size=5)
        self.pub_markers = rospy.Publisher("~markers", MarkerArray, queue_size=1, latch=True)
        self.diagnostics = Diagnostics(self.pipeline.input.camera_names, marker_check=config.marker_check.enabled)
        # One detection message kept per camera when we fall behind: an older one would be overtaken.
        self.ring_input = RingSubscriber(self.pipeline, self.publish, "localizer", use_tf=config.input.use_tf,
                                         tf_buffer=self.tf_buffer, queue_size=1, buff_size=BUFF_SIZE)
        rospy.Subscriber("cmd_vel", Twist, self.on_cmd_vel, queue_size=5)
        rospy.Subscriber("odom", Odometry, self.on_odom, queue_size=50)  # 1 s at 50 Hz: each one is a pose (motion/odometry)
        if config.motion.imu:
            rospy.Subscriber("imu", Imu, self.on_imu, queue_size=20)
        rospy.Subscriber("initialpose", PoseWithCovarianceStamped, self.on_initialpose, queue_size=1)
        rospy.Service("~reset", Trigger, self.on_reset)
        # map_server-style: the marker map as an OccupancyGrid (markers 100, the rest unknown)
        self.grid_msg = self.marker_grid_msg()
        rospy.Publisher("~marker_grid", OccupancyGrid, queue_size=1, latch=True).publish(self.grid_msg)
        rospy.Service("~static_map", GetMap, lambda _req: GetMapResponse(map=self.grid_msg))
        self._markers_seen: Optional[set] = None  # markers in view in the last ~markers array
        rospy.Service("~remap_marker", Trigger, self.on_remap_marker)
        rospy.Service("~save_map", Trigger, self.on_save_map)
        # On the ring input's poll timer (one timer thread: under use_sim_time each rospy timer
        # thread wakes at every /clock message).
        self.ring_input.every(out.diagnostics_period, self.publish_diagnostics)
        self.ring_input.every(out.markers_period, self.publish_markers)
        rospy.loginfo("localizer: %d mapped markers in %s, fusion %s, output %s -> %s, tf %s (%s)",
                      len(marker_map), self.map_frame, config.estimator.fusion, self.map_frame, self.base_frame,
                      out.tf_mode, "on" if out.publish_tf else "off")

    # --- inputs -----------------------------------------------------------------------------

    def on_cmd_vel(self, msg: Twist) -> None:
        self.ring_input.call(self.pipeline.on_motion, "cmd_vel", None, (msg.linear.x, msg.linear.y), msg.angular.z,
                             NOW)

    def on_odom(self, msg: Odometry) -> None:
        t = msg.twist.twist
        try:
            T_odom_base = pose_msg_to_transform(msg.pose.pose, "odom.pose.pose")
        except ArucoRingError:
            T_odom_base = None  # the twist is what the gate uses; a bad pose is not its problem
        linear, yaw_rate = (t.linear.x, t.linear.y), t.angular.z
        child = msg.child_frame_id.lstrip("/")
        if child and child != self.base_frame:   # e.g. a VIO's IMU frame: its odometry made base_link's
            T_base_child = self._mounted(child)
            if T_base_child is None:
                return
            T_odom_base, v, w = odometry_in_base(T_odom_base, (t.linear.x, t.linear.y, t.linear.z),
                                                 (t.angular.x, t.angular.y, t.angular.z), T_base_child)
            linear, yaw_rate = (float(v[0]), float(v[1])), float(w[2])
        self.ring_input.call(self.pipeline.on_motion, "odom", stamp_to_sec(msg.header.stamp),
                             linear, yaw_rate, NOW, T_odom_base)

    def _mounted(self, child: str) -> Optional[np.ndarray]:
        """``T_base_child`` of a frame rigidly mounted on the robot, from tf once (then cached); None
        (and a throttled warning naming the topic and the field) while tf does not have it."""
        T = self._mounts.get(child)
        if T is None:
            try:
                ts = self.tf_buffer.lookup_transform(self.base_frame, child, rospy.Time(0))
                T = self._mounts[child] = msg_to_transform(ts.transform, f"tf {self.base_frame} -> {child}")
            except (tf2_ros.TransformException, ArucoRingError) as exc:
                rospy.logwarn_throttle(WARN_PERIOD, f"localizer: odom: child_frame_id {child!r} is not "
                                       f"{self.base_frame!r} and tf has no {self.base_frame} -> {child} ({exc}): "
                                       "odometry dropped until it has (publish the mounting, e.g. a "
                                       "static_transform_publisher)")
        return T

    def on_imu(self, msg: Imu) -> None:
        self.ring_input.call(self.pipeline.on_imu, stamp_to_sec(msg.header.stamp), msg.angular_velocity.z, NOW)

    def on_initialpose(self, msg: PoseWithCovarianceStamped) -> None:
        try:
            T = pose_msg_to_transform(msg.pose.pose, "initialpose.pose")
            frame = msg.header.frame_id.lstrip("/")
            if frame and frame != self.map_frame:
                tf = self.tf_buffer.lookup_transform(self.map_frame, frame, rospy.Time(0), rospy.Duration(0.2))
                T = msg_to_transform(tf.transform, "tf") @ T
            self.ring_input.call(self.pipeline.on_initial_pose, T, NOW)
        except (ArucoRingError, tf2_ros.LookupException, tf2_ros.ConnectivityException,
                tf2_ros.ExtrapolationException) as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"localizer: ignoring initialpose in {msg.header.frame_id!r}: {exc}")
            return
        x, y, yaw = geo.se2_from_transform(T)
        rospy.loginfo_throttle(WARN_PERIOD, f"localizer: re-initialised from initialpose at ({x:.2f}, {y:.2f}, "
                                            f"{np.degrees(yaw):.1f} deg)")

    def on_reset(self, _req) -> TriggerResponse:
        self.ring_input.call(self.pipeline.reset)
        rospy.loginfo("localizer: reset by service; the next measurement initialises the track")
        return TriggerResponse(success=True, message="track reset")

    def on_remap_marker(self, _req) -> TriggerResponse:
        """Re-map the markers named by ``~remap_marker_ids`` (read at each call: ``"17 18"`` or a
        list; empty: every marker declared moved) from their recent observations, the others fixed,
        in the map in memory; written only with marker_check/save_on_remap (else ``~save_map``)."""
        try:
            ids = parse_marker_ids(rospy.get_param("~remap_marker_ids", []) or [])
        except ValueError as exc:
            return TriggerResponse(success=False, message=f"~remap_marker_ids: {exc}")
        with self.ring_input.lock:
            if self.pipeline.marker_check is None:
                return TriggerResponse(success=False, message="marker_check/enabled is false")
            ids = ids or sorted(self.pipeline.marker_check.moved)
            if not ids:
                return TriggerResponse(success=False, message="no marker declared moved and ~remap_marker_ids empty")
            results = self.pipeline.remap_markers(ids)
        done = [f"{mid} (moved {100 * moved:.1f} cm)" for mid, moved, why in results if not why]
        failed = [why for _, _, why in results if why]
        message = ("re-mapped " + ", ".join(done) if done else "nothing re-mapped") + \
            ("; " + "; ".join(failed) if failed else "")
        if done and self.config.marker_check.save_on_remap:
            message += "; " + self.on_save_map(None).message
        (rospy.loginfo if not failed else rospy.logwarn)("localizer: ~remap_marker: %s", message)
        return TriggerResponse(success=bool(done) and not failed, message=message)

    def on_save_map(self, _req) -> TriggerResponse:
        """Write the map in memory to ~map_file atomically, keeping marker_check/backups generations."""
        path = self.config.map_file
        try:
            with self.ring_input.lock:
                self.pipeline.save_map(path)
        except (ArucoRingError, OSError) as exc:
            rospy.logerr("localizer: ~save_map: %s", exc)
            return TriggerResponse(success=False, message=f"could not write {path}: {exc}")
        rospy.loginfo("localizer: map written to %s", path)
        return TriggerResponse(success=True, message=f"saved {len(self.marker_map)} markers to {path}")

    # --- outputs ----------------------------------------------------------------------------

    def publish(self, outputs: List[PoseOutput]) -> None:
        for out in outputs:
            self._publish(out)

    def _publish(self, out: PoseOutput) -> None:
        # Messages are built only for topics someone listens to (rospy would drop them unsent, but
        # after we paid for building them): the pose is wanted almost always, the rest often not.
        stamp = rospy.Time.from_sec(out.stamp)
        want_odom = self.pub_odom.get_num_connections() > 0
        if want_odom or self.pub_pose.get_num_connections() > 0:
            msg = PoseWithCovarianceStamped()
            msg.header.stamp = stamp
            msg.header.frame_id = self.map_frame
            msg.pose.pose = pose_to_msg(out.T_map_base)
            msg.pose.covariance = out.covariance.ravel().tolist()
            self.pub_pose.publish(msg)
            if want_odom:
                od = Odometry()
                od.header = msg.header
                od.child_frame_id = self.base_frame
                od.pose = msg.pose
                od.twist.twist.linear.x, od.twist.twist.linear.y, od.twist.twist.angular.z = \
                    (float(v) for v in out.twist)
                od.twist.covariance = out.twist_covariance.ravel().tolist()
                self.pub_odom.publish(od)
        if not out.from_odometry and self.pub_cams.get_num_connections() > 0:  # an odometry step has no camera estimates
            pa = PoseArray()
            pa.header.stamp = stamp
            pa.header.frame_id = self.map_frame
            pa.poses = [pose_to_msg(T) for T in out.camera_estimates.values()]
            self.pub_cams.publish(pa)
        if self.config.output.publish_tf:
            self.publish_tf(out.T_map_base, stamp)

    def publish_tf(self, T_map_base: np.ndarray, stamp) -> None:
        ts = self.map_tf.compute(T_map_base, stamp)
        if ts is not None:
            self.tf_broadcaster.sendTransform(ts)
            self.tf_listener.own(ts)
            self._tf_child = ts.child_frame_id.lstrip("/")

    def check_tf_authority(self, msg: TFMessage) -> None:
        """Warn, throttled, when another node publishes the tf child frame we publish.

        Two localizers on the same frames (or ours beside gmapping without beside_gmapping:=true)
        both publish ``map -> odom``: every tf user then sees the robot jump between two poses and
        tf2 logs TF_REPEATED_DATA. The sender of each /tf message is in its connection header
        (:class:`TfListener` hands over only other nodes' messages).
        """
        child = self._tf_child
        if child is None:
            return
        sender = msg._connection_header.get("callerid", "") if hasattr(msg, "_connection_header") else ""
        if not sender or sender == rospy.get_name():
            return
        for t in msg.transforms:
            if t.child_frame_id.lstrip("/") == child:
                rospy.logwarn_throttle(WARN_PERIOD, f"localizer: {sender} also publishes tf {t.header.frame_id} -> "
                                                    f"{child}, as this node does: two localizers on the same frames "
                                                    "(stop one; beside gmapping, use beside_gmapping:=true)")
                return

    def publish_markers(self, _event=None) -> None:
        """~markers (latched): again only when the markers in view changed (or a new subscriber
        came: the latch already gave it the last array, so that is not needed)."""
        period = self.config.output.markers_period
        with self.ring_input.lock:
            seen = self.pipeline.markers_in_view(self.ring_input.now(), 2.0 * period)
        if seen == self._markers_seen:
            return
        self._markers_seen = set(seen)
        arr = MarkerArray()
        stamp = rospy.Time.now()
        for e in self.marker_map:
            m = Marker()
            m.header.frame_id = self.map_frame
            m.header.stamp = stamp
            m.ns = "aruco_map"
            m.id = int(e.marker_id)
            m.type = Marker.CUBE
            m.pose = pose_to_msg(e.T_map_marker)
            m.scale.x = m.scale.y = float(e.size)
            m.scale.z = 0.01
            m.color.r, m.color.g, m.color.b, m.color.a = (0.1, 0.9, 0.1, 1.0) if e.marker_id in seen else \
                (0.6, 0.6, 0.6, 0.7)
            arr.markers.append(m)
            t = Marker()
            t.header = m.header
            t.ns = "aruco_map_ids"
            t.id = int(e.marker_id)
            t.type = Marker.TEXT_VIEW_FACING
            t.pose = pose_to_msg(e.T_map_marker)
            t.pose.position.z += float(e.size)
            t.scale.z = 0.15
            t.color.r = t.color.g = t.color.b = t.color.a = 1.0
            t.text = str(e.marker_id)
            arr.markers.append(t)
        self.pub_markers.publish(arr)

    def marker_grid_msg(self) -> OccupancyGrid:
        """The marker map as nav_msgs/OccupancyGrid (marker_grid.py: 5 cm cells, unknown but under a marker)."""
        grid = marker_grid(self.marker_map)
        msg = OccupancyGrid()
        msg.header.stamp = rospy.Time.now()
        msg.header.frame_id = self.map_frame
        msg.info.map_load_time = msg.header.stamp
        msg.info.resolution = grid.resolution
        msg.info.width, msg.info.height = grid.width, grid.height
        msg.info.origin.position.x, msg.info.origin.position.y = grid.origin
        msg.info.origin.orientation.w = 1.0
        msg.data = grid.data.reshape(-1).tolist()
        return msg

    def publish_diagnostics(self, _event=None) -> None:
        if self.diagnostics.updater.publisher.get_num_connections() == 0:
            return  # nobody listens (/diagnostics is not latched): the reports would be built for nothing
        with self.ring_input.lock:
            reports = self.pipeline.diagnostics(self.ring_input.now())
        self.diagnostics.publish(reports)


class Diagnostics:
    """``/diagnostics`` through diagnostic_updater: one task per camera (``<node>: camera NAME``,
    hardware_id the camera's name), one for the filter (``<node>: filter``, hardware_id
    ``localizer``) and, with the moved-marker check on, ``<node>: markers``; published together every ``output/diagnostics_period`` (1 s).

    Levels: OK; WARN for a silent camera or a filter that is not tracking; ERROR for the filter
    when every camera is silent (nothing can be localized). config/diagnostics_aggregator.yaml
    groups them for rqt_robot_monitor.
    """

    def __init__(self, camera_names: Sequence[str], marker_check: bool = False):
        self.updater = diagnostic_updater.Updater()
        self.updater.setHardwareID("aruco_ring")
        self._reports: Dict[str, StatusReport] = {}
        self._all_silent = False
        # With marker_check/enabled, a third kind: ``<node>: markers`` (which markers moved, how far).
        for task in [f"camera {n}" for n in camera_names] + ["filter"] + (["markers"] if marker_check else []):
            self.updater.add(task, lambda stat, task=task: self._fill(task, stat))

    def publish(self, reports: Sequence[StatusReport]) -> None:
        # the pipeline names a status "aruco_ring localizer: camera X"; the updater prefixes the node's name
        self._reports = {r.name.split(": ", 1)[-1]: r for r in reports}
        cameras = [r for task, r in self._reports.items() if task.startswith("camera ")]
        self._all_silent = bool(cameras) and not any(r.ok for r in cameras)
        self.updater.force_update()

    def _fill(self, task: str, stat: diagnostic_updater.DiagnosticStatusWrapper) -> diagnostic_updater.DiagnosticStatusWrapper:
        r = self._reports.get(task)
        if r is None:
            stat.summary(DiagnosticStatus.STALE, "no report yet")
            return stat
        level = DiagnosticStatus.OK if r.ok else DiagnosticStatus.WARN
        message = r.message
        if task == "filter" and self._all_silent:
            level, message = DiagnosticStatus.ERROR, f"every camera silent; {message}"
        stat.summary(level, message)
        stat.hardware_id = r.hardware_id
        for k, v in r.values:
            stat.add(k, v)
        return stat


def main(argv: Optional[Sequence[str]] = None) -> int:
    limit_threads()  # one BLAS / OpenCV thread (threads.py)
    tune_malloc()    # rospy's 16 MB receive buffers from the heap, not a fresh mmap per read (threads.py)
    rospy.init_node("localizer", argv=list(argv) if argv is not None else None)
    log_bridge.install()
    try:
        config = read_config(LocalizerConfig)
        if not config.map_file:
            raise ConfigError("no map file given (set ~map_file, or map_file:=... on the launch line)", key="map_file")
        ring = CameraRing.load(config.ring_file or default_ring_file())
        LocalizerNode(config, ring, MarkerMap.load(config.map_file))
    except (ConfigError, ValueError) as exc:
        rospy.logfatal("localizer: %s", exc)
        rospy.signal_shutdown("bad configuration")
        return 1
    rospy.spin()
    return 0


if __name__ == "__main__":
    sys.exit(main())
