"""``localizer`` node: the robot pose from the ring's detections against a marker map.

Pipeline per ring frame (:class:`tracker.RingTracker`): per-camera PnP / joint estimate ->
outlier gate (previous poses, ``cmd_vel``/``odom`` speed) -> 9-state Kalman filter.

Subscribes: ``<ns>/fiducial_vertices`` + ``<ns>/camera_info`` per camera (through
:class:`ros.ring_input.RingInput`), ``cmd_vel`` (geometry_msgs/Twist), ``odom`` (nav_msgs/Odometry,
optional), ``initialpose`` (geometry_msgs/PoseWithCovarianceStamped, rviz "2D Pose Estimate").
Publishes: ``~pose`` (PoseWithCovarianceStamped, REP-103 covariance order, robot_localization
ready), ``~odometry`` (nav_msgs/Odometry with the filter's twist), ``~camera_estimates``
(PoseArray, one per camera), ``~markers`` (MarkerArray, markers in view highlighted),
``/diagnostics``, tf ``map -> odom`` or ``map -> base_link``. Service: ``~reset`` (std_srvs/Trigger).

Parameters: :class:`LocalizerNodeParams` (every field is a private parameter, documented in
config/localization.yaml).
"""
from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence

import numpy as np
import rospy
import tf2_ros
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped, Twist
from nav_msgs.msg import Odometry
from std_srvs.srv import Trigger, TriggerResponse
from visualization_msgs.msg import Marker, MarkerArray

from .. import geometry as geo
from ..errors import ArucoRingError, ConfigError
from ..detections import RingFrame
from ..gating import GateParams
from ..kalman import FilterParams
from ..localization import LocalizationParams
from ..marker_map import MarkerMap
from ..markers import parse_id_list
from ..ring import CameraRing, apply_refined_extrinsics
from ..tracker import RingTracker, TrackResult
from .conversions import (make_transform_stamped, msg_to_transform, pose_msg_to_transform, pose_to_msg,
                          se2_covariance_to_pose_covariance, stamp_to_sec)
from .params import read_params
from .ring_input import RingInput
from .ring_tf import default_ring_file

WARN_PERIOD = 5.0


@dataclass(frozen=True)
class LocalizerNodeParams:
    """Private parameters of the node (see config/localization.yaml for the prose)."""

    map_file: str = ""
    ring_file: str = ""
    cameras: tuple = ()
    fusion: str = "joint"
    map_frame: str = ""
    base_frame: str = ""
    odom_frame: str = "odom"
    publish_tf: bool = True
    tf_mode: str = "auto"
    use_tf: bool = True
    camera_info_fallback: bool = False
    slop: float = 0.03
    timeout: float = 0.25
    max_frame_age: float = 2.0
    ignore_fiducials: str = ""
    # localization, gate and filter: defaults are the core's (one place to change them)
    max_reprojection_error: float = LocalizationParams.max_reprojection_error
    th_distance: float = LocalizationParams.th_distance
    th_orientation_deg: float = float(np.degrees(LocalizationParams.th_orientation))
    fusion_gap: float = LocalizationParams.fusion_gap
    pixel_noise: float = LocalizationParams.pixel_noise
    robust_scale: float = LocalizationParams.robust_scale
    joint_outlier_threshold: float = LocalizationParams.joint_outlier_threshold
    gate_enabled: bool = GateParams.enabled
    gate_base_distance: float = GateParams.base_distance
    gate_base_angle_deg: float = float(np.degrees(GateParams.base_angle))
    gate_speed_margin: float = GateParams.speed_margin
    gate_max_acceleration: float = GateParams.max_acceleration
    gate_max_angular_acceleration: float = GateParams.max_angular_acceleration
    gate_recovery_count: int = GateParams.recovery_count
    gate_sigma_factor: float = GateParams.sigma_factor
    jerk_noise_xy: float = FilterParams.jerk_noise_xy
    jerk_noise_yaw: float = FilterParams.jerk_noise_yaw
    measurement_std_xy: float = FilterParams.measurement_std_xy
    measurement_std_yaw: float = FilterParams.measurement_std_yaw
    min_measurement_std_xy: float = FilterParams.min_measurement_std_xy
    min_measurement_std_yaw: float = FilterParams.min_measurement_std_yaw
    # output
    markers_period: float = 1.0
    diagnostics_period: float = 1.0
    silent_after: float = 1.0

    def localization(self) -> LocalizationParams:
        return LocalizationParams(
            fusion=self.fusion, max_reprojection_error=self.max_reprojection_error, th_distance=self.th_distance,
            th_orientation=float(np.radians(self.th_orientation_deg)), fusion_gap=self.fusion_gap,
            pixel_noise=self.pixel_noise, robust_scale=self.robust_scale,
            ignore_ids=tuple(sorted(parse_id_list(self.ignore_fiducials))),
            joint_outlier_threshold=self.joint_outlier_threshold)

    def gate(self) -> GateParams:
        return GateParams(enabled=self.gate_enabled, base_distance=self.gate_base_distance,
                          base_angle=float(np.radians(self.gate_base_angle_deg)), speed_margin=self.gate_speed_margin,
                          max_acceleration=self.gate_max_acceleration,
                          max_angular_acceleration=self.gate_max_angular_acceleration,
                          recovery_count=self.gate_recovery_count, sigma_factor=self.gate_sigma_factor)

    def filter(self) -> FilterParams:
        return FilterParams(jerk_noise_xy=self.jerk_noise_xy, jerk_noise_yaw=self.jerk_noise_yaw,
                            measurement_std_xy=self.measurement_std_xy, measurement_std_yaw=self.measurement_std_yaw,
                            min_measurement_std_xy=self.min_measurement_std_xy,
                            min_measurement_std_yaw=self.min_measurement_std_yaw)


class LocalizerNode:
    """ROS wiring around :class:`RingTracker`."""

    def __init__(self, params: LocalizerNodeParams, ring: CameraRing, marker_map: MarkerMap):
        if params.tf_mode not in ("auto", "map_to_odom", "map_to_base"):
            raise ConfigError(f"expected auto, map_to_odom or map_to_base, got {params.tf_mode!r}", key="tf_mode")
        self.p = params
        self.marker_map = marker_map
        self.map_frame = params.map_frame or marker_map.frame_id
        self.base_frame = params.base_frame or ring.base_frame
        self.tracker = RingTracker(ring, marker_map, params.localization(), params.gate(), params.filter())
        self._lock = threading.Lock()
        self.tf_buffer = tf2_ros.Buffer()
        self.tf_listener = tf2_ros.TransformListener(self.tf_buffer)
        self.tf_broadcaster = tf2_ros.TransformBroadcaster()
        self.pub_pose = rospy.Publisher("~pose", PoseWithCovarianceStamped, queue_size=10)
        self.pub_odom = rospy.Publisher("~odometry", Odometry, queue_size=10)
        self.pub_cams = rospy.Publisher("~camera_estimates", PoseArray, queue_size=5)
        self.pub_markers = rospy.Publisher("~markers", MarkerArray, queue_size=1, latch=True)
        self.pub_diag = rospy.Publisher("/diagnostics", DiagnosticArray, queue_size=5)
        self.frames = 0
        self.dropped_stale = 0
        self.last_update_wall: Optional[float] = None
        self.last_result: Optional[TrackResult] = None
        self.camera_stats: Dict[str, Dict[str, float]] = {}
        self.in_view: Dict[int, float] = {}
        self.latency_ms: List[float] = []
        self.ring_input = RingInput(ring, list(params.cameras) or None, self.on_ring_frame, slop=params.slop,
                                    timeout=params.timeout, use_tf=params.use_tf,
                                    camera_info_fallback=params.camera_info_fallback,
                                    ignore_ids=parse_id_list(params.ignore_fiducials), tf_buffer=self.tf_buffer)
        rospy.Subscriber("cmd_vel", Twist, self.on_cmd_vel, queue_size=5)
        rospy.Subscriber("odom", Odometry, self.on_odom, queue_size=5)
        rospy.Subscriber("initialpose", PoseWithCovarianceStamped, self.on_initialpose, queue_size=1)
        rospy.Service("~reset", Trigger, self.on_reset)
        rospy.Timer(rospy.Duration(params.diagnostics_period), self.publish_diagnostics, reset=True)
        rospy.Timer(rospy.Duration(params.markers_period), self.publish_markers, reset=True)
        self.last_frame_wall: Optional[float] = None
        rospy.Timer(rospy.Duration(0.1), self.on_blind_timer, reset=True)
        rospy.loginfo("localizer: %d mapped markers in %s, fusion %s, output %s -> %s, tf %s (%s)",
                      len(marker_map), self.map_frame, params.fusion, self.map_frame, self.base_frame,
                      params.tf_mode, "on" if params.publish_tf else "off")

    # --- inputs -----------------------------------------------------------------------------

    def on_cmd_vel(self, msg: Twist) -> None:
        with self._lock:
            self.tracker.set_motion("cmd_vel", float(np.hypot(msg.linear.x, msg.linear.y)), float(msg.angular.z),
                                    rospy.get_time())

    def on_odom(self, msg: Odometry) -> None:
        t = msg.twist.twist
        stamp = stamp_to_sec(msg.header.stamp) or rospy.get_time()
        with self._lock:
            self.tracker.set_motion("odom", float(np.hypot(t.linear.x, t.linear.y)), float(t.angular.z), stamp)

    def on_initialpose(self, msg: PoseWithCovarianceStamped) -> None:
        try:
            T = pose_msg_to_transform(msg.pose.pose, "initialpose.pose")
            frame = msg.header.frame_id.lstrip("/")
            if frame and frame != self.map_frame:
                tf = self.tf_buffer.lookup_transform(self.map_frame, frame, rospy.Time(0), rospy.Duration(0.2))
                T = msg_to_transform(tf.transform, "tf") @ T
        except (ArucoRingError, tf2_ros.LookupException, tf2_ros.ConnectivityException,
                tf2_ros.ExtrapolationException) as exc:
            rospy.logwarn("localizer: ignoring initialpose in %r: %s", msg.header.frame_id, exc)
            return
        se2 = geo.se2_from_transform(T)
        with self._lock:
            stamp = self.last_result.stamp if self.last_result is not None else stamp_to_sec(msg.header.stamp)
            self.tracker.reset(se2, stamp)
        rospy.loginfo("localizer: re-initialised from initialpose at (%.2f, %.2f, %.1f deg)", se2[0], se2[1],
                      np.degrees(se2[2]))

    def on_reset(self, _req) -> TriggerResponse:
        with self._lock:
            self.tracker.reset()
        rospy.loginfo("localizer: reset by service; the next measurement initialises the track")
        return TriggerResponse(success=True, message="track reset")

    def on_blind_timer(self, _event=None) -> None:
        """Predict-only output while no ring frame arrives at all (every camera silent).

        The assembler emits nothing when no camera reports, so without this the pose would just
        stop; instead the filter predicts to the current time and the pose goes out with its
        growing covariance, after ``silent_after`` s without a frame, with a throttled warning.
        """
        if self.last_frame_wall is None:
            return
        blind = time.monotonic() - self.last_frame_wall
        if blind < self.p.silent_after:
            return
        now = rospy.get_time()
        with self._lock:
            f = self.tracker.filter
            if not f.initialized or f.stamp is None or now <= f.stamp:
                return  # nothing to predict from, or the clock has not moved (a paused bag)
            result = self.tracker.process(RingFrame(stamp=now, missing=self.ring_input.camera_names))
        rospy.logwarn_throttle(WARN_PERIOD, f"localizer: no ring frame for {blind:.1f} s (every camera silent): "
                                            "predicting only, the covariance grows")
        if result.pose is not None:
            self.publish(result, RingFrame(stamp=now))

    def on_ring_frame(self, frame: RingFrame) -> None:
        self.last_frame_wall = time.monotonic()
        now = rospy.get_time()
        age = now - frame.stamp
        # Never fall behind: when newer ring frames are already waiting, this one is worth less than
        # the newest; a frame older than max_frame_age (ROS time) is dropped too. The age alone is
        # not enough: frames with a silent camera wait `timeout` s of wall time in the assembler,
        # which is several seconds of ROS time when a bag plays faster than real time.
        waiting = len(getattr(getattr(self, "ring_input", None), "_ready", ()))
        if waiting or (self.p.max_frame_age > 0 and age > self.p.max_frame_age and frame.stamp <= now):
            self.dropped_stale += 1
            rospy.logwarn_throttle(WARN_PERIOD, f"localizer: dropped {self.dropped_stale} stale ring frames "
                                                f"(last {age:.2f} s old, {waiting} newer waiting)")
            return
        ring_input = getattr(self, "ring_input", None)
        if ring_input is not None and ring_input.ring is not self.tracker.localizer.ring:
            self.tracker.localizer.set_ring(ring_input.ring)  # extrinsics from tf arrived
        t0 = time.perf_counter()
        with self._lock:
            result = self.tracker.process(frame)
        self.latency_ms.append(1000.0 * (time.perf_counter() - t0))
        del self.latency_ms[:-200]
        self.frames += 1
        self.last_result = result
        wall = time.monotonic()
        for name, cf in frame.cameras.items():
            st = self.camera_stats.setdefault(name, {"frames": 0, "first": wall, "markers": 0})
            st["frames"] += 1
            st["markers"] = len(cf.observations)
            st["last"] = wall
        for mid in result.localization.marker_ids:
            self.in_view[mid] = wall
        if result.time_jump:
            rospy.logwarn("localizer: time jumped back to %.3f s: filter reset", frame.stamp)
        if result.decision is not None and result.decision.reason == "reinitialized":
            rospy.logwarn("localizer: re-initialised after consistent measurements disagreed with the track")
        elif result.decision is not None and not result.decision.accepted:
            rospy.logwarn_throttle(WARN_PERIOD, f"localizer: measurement rejected by the gate (jump "
                                                f"{result.decision.distance:.2f} m / "
                                                f"{np.degrees(result.decision.angle):.1f} deg)")
        if result.decision is not None and result.decision.accepted:
            self.last_update_wall = wall
        if result.pose is not None:
            self.publish(result, frame)

    # --- outputs ----------------------------------------------------------------------------

    def publish(self, result: TrackResult, frame: RingFrame) -> None:
        stamp = rospy.Time.from_sec(result.stamp)
        x, y, yaw = result.pose
        z = self.tracker.height
        T_map_base = geo.transform_from_se2(x, y, yaw, z)
        cov = se2_covariance_to_pose_covariance(result.covariance)
        msg = PoseWithCovarianceStamped()
        msg.header.stamp = stamp
        msg.header.frame_id = self.map_frame
        msg.pose.pose = pose_to_msg(T_map_base)
        msg.pose.covariance = cov
        self.pub_pose.publish(msg)
        od = Odometry()
        od.header = msg.header
        od.child_frame_id = self.base_frame
        od.pose = msg.pose
        v, vl, w = self.tracker.filter.body_twist
        od.twist.twist.linear.x, od.twist.twist.linear.y, od.twist.twist.angular.z = float(v), float(vl), float(w)
        od.twist.covariance = se2_covariance_to_pose_covariance(self.tracker.filter.velocity_covariance)
        self.pub_odom.publish(od)
        pa = PoseArray()
        pa.header = msg.header
        pa.poses = [pose_to_msg(e.T_map_base) for e in result.localization.estimates.values() if e.valid]
        self.pub_cams.publish(pa)
        if self.p.publish_tf:
            self.publish_tf(T_map_base, stamp)

    def publish_tf(self, T_map_base: np.ndarray, stamp) -> None:
        mode = self.p.tf_mode
        if mode in ("auto", "map_to_odom"):
            try:
                # Wait for odom -> base at this stamp only when that transform exists at all: without
                # odometry the 50 ms wait would be paid on every frame for nothing.
                if not self.tf_buffer.can_transform(self.p.odom_frame, self.base_frame, rospy.Time(0)):
                    raise tf2_ros.LookupException(f"no tf {self.p.odom_frame} -> {self.base_frame}")
                tf = self.tf_buffer.lookup_transform(self.p.odom_frame, self.base_frame, stamp, rospy.Duration(0.05))
            except tf2_ros.ExtrapolationException:
                try:
                    tf = self.tf_buffer.lookup_transform(self.p.odom_frame, self.base_frame, rospy.Time(0))
                except (tf2_ros.LookupException, tf2_ros.ConnectivityException, tf2_ros.ExtrapolationException):
                    tf = None
            except (tf2_ros.LookupException, tf2_ros.ConnectivityException):
                tf = None
            except rospy.exceptions.ROSTimeMovedBackwardsException:
                # lookup_transform sleeps in ROS time while waiting; a bag loop during that wait
                # raised out of the detection callback and lost the frame.
                tf = None
            if tf is not None:
                T_odom_base = msg_to_transform(tf.transform, "tf odom -> base")
                self.tf_broadcaster.sendTransform(make_transform_stamped(
                    T_map_base @ geo.inverse(T_odom_base), self.map_frame, self.p.odom_frame, stamp))
                return
            if mode == "map_to_odom":
                rospy.logwarn_throttle(WARN_PERIOD, f"localizer: no tf {self.p.odom_frame} -> {self.base_frame}; "
                                                    "not publishing map -> odom")
                return
        self.tf_broadcaster.sendTransform(make_transform_stamped(T_map_base, self.map_frame, self.base_frame, stamp))

    def publish_markers(self, _event=None) -> None:
        now = time.monotonic()
        arr = MarkerArray()
        stamp = rospy.Time.now()
        for k, e in enumerate(self.marker_map):
            m = Marker()
            m.header.frame_id = self.map_frame
            m.header.stamp = stamp
            m.ns = "aruco_map"
            m.id = int(e.marker_id)
            m.type = Marker.CUBE
            m.pose = pose_to_msg(e.T_map_marker)
            m.scale.x = m.scale.y = float(e.size)
            m.scale.z = 0.01
            seen = now - self.in_view.get(e.marker_id, -1e9) < 2.0 * self.p.markers_period
            m.color.r, m.color.g, m.color.b, m.color.a = (0.1, 0.9, 0.1, 1.0) if seen else (0.6, 0.6, 0.6, 0.7)
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

    def publish_diagnostics(self, _event=None) -> None:
        now = time.monotonic()
        arr = DiagnosticArray()
        arr.header.stamp = rospy.Time.now()
        silent = set(self.ring_input.silent_cameras(self.p.silent_after))
        for name in self.ring_input.camera_names:
            st = self.camera_stats.get(name, {})
            s = DiagnosticStatus(name=f"aruco_ring localizer: camera {name}", hardware_id=name)
            alive = name not in silent
            rate = st["frames"] / max(now - st["first"], 1e-3) if st else 0.0
            s.level = DiagnosticStatus.OK if alive else DiagnosticStatus.WARN
            s.message = "alive" if alive else "silent (no detections, camera_info or tf)"
            s.values = [KeyValue("alive", str(alive)), KeyValue("rate_hz", f"{rate:.1f}"),
                        KeyValue("markers_seen", str(int(st.get("markers", 0))))]
            arr.status.append(s)
        f = DiagnosticStatus(name="aruco_ring localizer: filter", hardware_id="localizer")
        age = None if self.last_update_wall is None else now - self.last_update_wall
        if age is None:
            f.level, f.message = DiagnosticStatus.WARN, "not initialised (no usable measurement yet)"
        elif age > 2.0:
            f.level, f.message = DiagnosticStatus.WARN, f"no accepted measurement for {age:.1f} s"
        else:
            f.level, f.message = DiagnosticStatus.OK, "tracking"
        cov = self.tracker.filter.covariance if self.tracker.filter.initialized else np.full((3, 3), np.nan)
        lat = np.array(self.latency_ms) if self.latency_ms else np.array([np.nan])
        f.values = [KeyValue("last_update_age_s", "none" if age is None else f"{age:.2f}"),
                    KeyValue("std_x_m", f"{np.sqrt(cov[0, 0]):.4f}"), KeyValue("std_y_m", f"{np.sqrt(cov[1, 1]):.4f}"),
                    KeyValue("std_yaw_deg", f"{np.degrees(np.sqrt(cov[2, 2])):.3f}"),
                    KeyValue("frames", str(self.frames)), KeyValue("dropped_stale", str(self.dropped_stale)),
                    KeyValue("time_jumps", str(self.tracker.time_jumps)),
                    KeyValue("reinitializations", str(self.tracker.gate.reinitializations)),
                    KeyValue("latency_ms_median", f"{np.median(lat):.2f}")]
        f.values += [KeyValue(f"rejected_{k.replace(' ', '_')}", str(v))
                     for k, v in sorted(self.tracker.rejected_counts.items())]
        arr.status.append(f)
        self.pub_diag.publish(arr)


def main(argv: Optional[Sequence[str]] = None) -> int:
    rospy.init_node("localizer", argv=list(argv) if argv is not None else None)
    try:
        params = read_params(LocalizerNodeParams)
        if not params.map_file:
            raise ConfigError("no map file given (set ~map_file, or map_file:=... on the launch line)", key="map_file")
        ring = CameraRing.load(params.ring_file or default_ring_file())
        marker_map = MarkerMap.load(params.map_file)
        if len(marker_map) == 0:
            raise ConfigError("the map has no markers", path=params.map_file, key="markers")
        if marker_map.ring_extrinsics and not params.use_tf:
            # Without tf, the ring file's extrinsics would be used: prefer the ones refined with the map.
            ring = apply_refined_extrinsics(ring, marker_map.ring_extrinsics, marker_map.ring_base_frame,
                                            source=params.map_file)
            rospy.loginfo("localizer: using the ring extrinsics refined while mapping (%s)", params.map_file)
        LocalizerNode(params, ring, marker_map)
    except (ConfigError, ValueError) as exc:
        rospy.logfatal("localizer: %s", exc)
        rospy.signal_shutdown("bad configuration")
        return 1
    rospy.spin()
    return 0


if __name__ == "__main__":
    sys.exit(main())
