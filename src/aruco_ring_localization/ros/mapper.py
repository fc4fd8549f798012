"""``mapper`` node: builds the marker map from the ring's detections.

Thin: it converts messages, calls :class:`aruco_ring_localization.pipeline.MappingPipeline` and
publishes; ``aruco_ring build-map`` drives the same pipeline from a bag (config/mapping.yaml).

Subscribes (through :class:`ros.ring_input.RingSubscriber`): ``<ns>/fiducial_vertices`` and
``<ns>/camera_info`` of every ring camera; extrinsics from tf (or the ring file); with
``mapping/odometry/topic`` set, that nav_msgs/Odometry (links between stations, docs/mapping.md).

Publishes:
    ``~markers`` (visualization_msgs/MarkerArray, latched): a thin box per mapped marker, coloured
        by its position uncertainty (green <= 2 mm, yellow ~1 cm, red >= 5 cm), and its id as text.
    ``fiducial_map`` (fiducial_msgs/FiducialMapEntryArray, latched): as fiducial_slam publishes it.
    static tf ``<map_frame> -> marker_<id>`` for every marker, all in ONE sendTransform call
        (/tf_static is latched and keeps only a publisher's last message).
    tf of the robot at its latest station in the live map (``output/publish_tf``): ``map -> odom``
        when ``odom -> base_link`` exists, else ``map -> base_link`` (``output/tf_mode``, REP-105),
        re-stamped every ``output/tf_period``; so the robot, its ring and its scan appear in rviz.

Services:
    ``~save_map`` (std_srvs/Trigger): builds the map with ``method`` (``refined``: bundle
        adjustment), writes ``map_file`` atomically (previous file kept as ``.bak``), answers with
        the path and a summary.
    ``~clear`` (std_srvs/Trigger): forgets every observation.
    ``~calibrate_ring`` (std_srvs/Trigger, ``calibration/extrinsics: rough`` only): calibrates the ring
        from the rough values and the frames seen so far, writes the ring file, updates tf.

Calibration from rough values (``calibration/extrinsics: rough``, mapping.launch ``extrinsics:=rough``):
the ring file holds a drawing's extrinsics; the node publishes them on tf itself (static
``base_link -> camK_optical_frame``; ring_tf is not started), keeps the frames it maps (and the
odometry at their stamps from tf ``odom -> base_link``), and ``~save_map`` first calibrates every
camera from them (:func:`aruco_ring_localization.ring_calibration.calibrate_ring`), writes the
ring file ``calibration/ring_file_out`` (default beside the map, ``<map>_ring.yaml``) atomically,
publishes the calibrated extrinsics on tf, then builds and saves the map with them.

Progress (markers mapped, observations per marker, markers seen but not linked, silent cameras)
goes to the log every ``output/progress_period`` seconds. With ``map/save_on_shutdown`` the map is
saved when the node stops. Parameters: :class:`aruco_ring_localization.schemas.MapperConfig`
(config/mapping.yaml, docs/parameters.md).
"""
from __future__ import annotations

import os
import sys
from typing import Optional, Sequence

import numpy as np
import rospy
import tf2_ros
from fiducial_msgs.msg import FiducialMapEntry, FiducialMapEntryArray
from std_srvs.srv import Trigger, TriggerResponse
from visualization_msgs.msg import Marker, MarkerArray

from .. import geometry as geo
from ..errors import ArucoRingError, ConfigError
from ..marker_map import MarkerMap
from ..pipeline import MappingPipeline, ring_file_beside
from ..ring import CameraRing
from ..threads import limit_threads, tune_malloc
from ..schemas import MapperConfig
from . import log_bridge
from .conversions import make_transform_stamped, pose_msg_to_transform, pose_to_msg
from .params import read_config
from .ring_input import MAPPER_QUEUE_SIZE, RingSubscriber
from .ring_tf import default_ring_file, ring_transforms
from .tf_output import MapTransform

WARN_PERIOD = 5.0


def uncertainty_colour(std_m: float):
    """(r, g, b) from green (<= 2 mm) through yellow to red (>= 5 cm), log scale."""
    a = float(np.clip((np.log10(max(std_m, 1e-6)) - np.log10(0.002)) / (np.log10(0.05) - np.log10(0.002)), 0, 1))
    return (min(1.0, 2 * a), min(1.0, 2 * (1 - a)), 0.0)


def map_to_marker_array(m: MarkerMap, stamp: rospy.Time, ns: str = "aruco_map") -> MarkerArray:
    """A thin box per marker (its side x side x 5 mm, coloured by uncertainty) and its id as text."""
    out = MarkerArray()
    clear = Marker()
    clear.action = Marker.DELETEALL
    out.markers.append(clear)
    for e in m:
        box = Marker()
        box.header.frame_id = m.frame_id
        box.header.stamp = stamp
        box.ns = ns
        box.id = 2 * e.marker_id
        box.type = Marker.CUBE
        box.action = Marker.ADD
        box.pose = pose_to_msg(e.T_map_marker)
        box.scale.x = box.scale.y = float(e.size)
        box.scale.z = 0.005
        r, g, b = uncertainty_colour(float(np.max(e.position_std)) if e.marker_id != m.reference_marker else 0.0)
        box.color.r, box.color.g, box.color.b, box.color.a = r, g, b, 0.9
        text = Marker()
        text.header = box.header
        text.ns = ns + "_ids"
        text.id = 2 * e.marker_id + 1
        text.type = Marker.TEXT_VIEW_FACING
        text.action = Marker.ADD
        text.pose = pose_to_msg(geo.make_transform(t=e.T_map_marker[:3, 3] + [0.0, 0.0, 0.6 * e.size]))
        text.scale.z = max(0.08, 0.5 * float(e.size))
        text.color.r = text.color.g = text.color.b = text.color.a = 1.0
        text.text = str(e.marker_id) + (" (ref)" if e.marker_id == m.reference_marker else "")
        out.markers.extend([box, text])
    return out


def map_to_fiducial_map(m: MarkerMap) -> FiducialMapEntryArray:
    """fiducial_slam's map message: position (m) and fixed-axis roll, pitch, yaw (rad)."""
    out = FiducialMapEntryArray()
    for e in m:
        r, p, y = geo.rpy_from_matrix(e.T_map_marker)
        t = e.T_map_marker[:3, 3]
        out.fiducials.append(FiducialMapEntry(fiducial_id=int(e.marker_id), x=float(t[0]), y=float(t[1]),
                                              z=float(t[2]), rx=float(r), ry=float(p), rz=float(y)))
    return out


def default_map_file() -> str:
    return os.path.join(os.environ.get("ROS_HOME", os.path.expanduser("~/.ros")), "aruco_map.yaml")


class MapperNode:
    """The node's state; ROS I/O only, the mapping itself is :class:`MappingPipeline`."""

    def __init__(self, config: MapperConfig, ring: CameraRing):
        self.config = config
        self.map_file = os.path.expanduser(config.map_file) or default_map_file()
        self.pipeline = MappingPipeline(config, ring)
        self._published_version = -1
        self._saved_map: Optional[MarkerMap] = None   # the last map ~save_map wrote, kept on display
        self.pub_markers = rospy.Publisher("~markers", MarkerArray, queue_size=1, latch=True)
        self.pub_fiducial_map = rospy.Publisher("fiducial_map", FiducialMapEntryArray, queue_size=1, latch=True)
        self.static_tf = tf2_ros.StaticTransformBroadcaster()
        self.tf_buffer = tf2_ros.Buffer()
        self.tf_listener = tf2_ros.TransformListener(self.tf_buffer)
        rough = config.calibration.rough
        self.ring_input = RingSubscriber(self.pipeline, lambda _added: None, "mapper",
                                         use_tf=config.input.use_tf and not rough,
                                         tf_buffer=self.tf_buffer, queue_size=MAPPER_QUEUE_SIZE)
        # Calibration from rough values: this node owns the ring's tf (every static transform of one
        # publisher goes out in one message, /tf_static being latched: the markers' and the ring's).
        self.ring_file_out = os.path.expanduser(config.calibration.ring_file_out) or ring_file_beside(self.map_file)
        self._ring_tf = ring_transforms(ring, rospy.Time.now()) if rough else []
        self._marker_tf: list = []
        self._odometry: list = []          # [(stamp, T_odom_base)] at the calibration frames' stamps
        if rough:
            self.static_tf.sendTransform(list(self._ring_tf))
            if config.calibration.odometry:
                rospy.Timer(rospy.Duration(1.0), self.on_odometry_timer, reset=True)
            rospy.Service("~calibrate_ring", Trigger, self.on_calibrate_ring)
        out = config.output
        self.map_tf = MapTransform(self.tf_buffer, config.map.map_frame, out.base_frame or ring.base_frame,
                                   out.odom_frame, out.tf_mode, "mapper")
        self.tf_broadcaster = tf2_ros.TransformBroadcaster()
        self._robot_tf = None          # the TransformStamped of the robot's latest station, re-stamped
        self._progress_frames = -1     # frames at the previous progress line
        if out.publish_tf:
            rospy.Timer(rospy.Duration(out.tf_period), self.on_tf_timer, reset=True)
        if config.mapping.odometry.topic:
            # mapping.odometry: the robot's odometry links consecutive stations in the adjustment.
            from nav_msgs.msg import Odometry

            rospy.Subscriber(config.mapping.odometry.topic, Odometry, self.on_odometry, queue_size=100)
        rospy.Service("~save_map", Trigger, self.on_save_map)
        rospy.Service("~clear", Trigger, self.on_clear)
        rospy.Timer(rospy.Duration(config.output.publish_period), self.on_publish_timer, reset=True)
        rospy.Timer(rospy.Duration(config.output.progress_period), self.on_progress_timer, reset=True)
        rospy.on_shutdown(self.on_shutdown)
        rospy.loginfo("mapper: method %s, map file %s, map frame %s", config.map.method, self.map_file,
                      config.map.map_frame)
        if rough:
            rospy.loginfo("mapper: calibrating the ring from the rough values of %s (published on tf by this node); "
                          "~save_map writes the calibrated ring to %s", config.ring_file or default_ring_file(),
                          self.ring_file_out)

    def on_odometry(self, msg) -> None:
        try:
            T = pose_msg_to_transform(msg.pose.pose, f"{self.config.mapping.odometry.topic} pose.pose")
        except ArucoRingError as exc:
            self.pipeline.warn("odometry.error", f"mapper: {exc}", msg.header.stamp.to_sec())
            return
        with self.ring_input.lock:
            self.pipeline.on_odometry(msg.header.stamp.to_sec(), T)

    # --- output -----------------------------------------------------------------------------

    def publish(self, m: MarkerMap) -> None:
        stamp = rospy.Time.now()
        self.update_robot_tf(m)
        self.pub_markers.publish(map_to_marker_array(m, stamp))
        self.pub_fiducial_map.publish(map_to_fiducial_map(m))
        self._marker_tf = [make_transform_stamped(e.T_map_marker, m.frame_id, f"marker_{e.marker_id}", stamp)
                           for e in m]
        if self._marker_tf:
            self.static_tf.sendTransform(self._marker_tf + self._ring_tf)

    def update_robot_tf(self, m: MarkerMap) -> None:
        """The robot's tf at its latest station in ``m`` (map -> odom, or map -> base_link)."""
        if not self.config.output.publish_tf:
            return
        with self.ring_input.lock:
            pose = self.pipeline.robot_pose(m)
        if pose is None:
            return
        # Every publish: the same stamp may come with another map frame (the refined map's, on a save).
        ts = self.map_tf.compute(pose[1], rospy.Time.from_sec(pose[0]))
        if ts is not None:
            self._robot_tf = ts

    def on_tf_timer(self, _event) -> None:
        ts = self._robot_tf
        if ts is None:
            return
        now = rospy.Time.now()
        if now <= ts.header.stamp:
            return   # tf2 ignores (and warns about) a repeated stamp: a paused simulated clock
        ts.header.stamp = now
        self.tf_broadcaster.sendTransform(ts)

    def on_publish_timer(self, _event) -> None:
        with self.ring_input.lock:
            version = self.pipeline.version
            if version == self._published_version:
                return
            if self.pipeline.rough_ring is not None and self.pipeline.calibration is None:
                # Through rough extrinsics the preview is wrong (markers rejected as spread over
                # decimetres) and slow (stations in SE(3)); holding the input for it made cameras'
                # messages arrive late and out of order. Shown once calibrated.
                self._published_version = version
                rospy.loginfo_throttle(60.0, "mapper: calibrating from rough values: no live map until ~save_map "
                                             "or ~calibrate_ring (%d frames kept for the calibration, %d odometry "
                                             "poses)", len(self.pipeline.calibration_stamps), len(self._odometry))
                return
            try:
                m = self.pipeline.build("paper")  # cheap live preview; ~save_map refines
            except ArucoRingError as exc:
                rospy.logwarn_throttle(WARN_PERIOD, f"mapper: no map yet: {exc}")
                return
            self._published_version = version
        saved = self._saved_map
        if saved is not None and set(m.ids) <= set(saved.ids):
            # After ~save_map the saved (refined) map stays on tf and ~markers while the preview shows
            # no new marker: the preview's frame follows the paper's chaining rule, the saved map's
            # may be another marker's, and the markers would jump between the two in rviz.
            return
        self.publish(m)

    def on_progress_timer(self, _event) -> None:
        with self.ring_input.lock:
            text = "mapper: " + self.pipeline.format_summary()
            frames = self.pipeline.frames
        silence = self.config.input.silent_after
        silent = self.ring_input.silent_cameras(silence)
        if silent:
            text += f"; silent cameras: {silent}"
        age = self.ring_input.input_age()
        if frames == self._progress_frames and age > silence:   # frames added: the input is alive
            text += "; no camera message yet" if age == float("inf") else f"; no camera message for {age:.1f} s"
        self._progress_frames = frames
        rospy.loginfo(text)

    # --- calibration from rough values -------------------------------------------------------------

    def on_odometry_timer(self, _event) -> None:
        """The odometry (tf odom_frame -> base frame) at the stamps of the frames kept for the
        calibration, looked up while tf's buffer still holds them."""
        with self.ring_input.lock:
            stamps = self.pipeline.calibration_stamps
        last = self._odometry[-1][0] if self._odometry else -np.inf
        base = self.pipeline.ring.base_frame
        for t in stamps:
            if t <= last:
                continue
            try:
                ts = self.tf_buffer.lookup_transform(self.config.output.odom_frame, base, rospy.Time.from_sec(t))
            except tf2_ros.ExtrapolationException:
                if rospy.Time.now().to_sec() - t < 5.0:
                    break       # not in tf yet: the next tick
                continue        # no longer in tf's buffer
            except (tf2_ros.LookupException, tf2_ros.ConnectivityException):
                return          # no odometry (yet)
            q, p = ts.transform.rotation, ts.transform.translation
            self._odometry.append((t, geo.transform_from_translation_quaternion([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])))

    def calibrate_ring(self) -> str:
        """Calibrate from the rough values (:meth:`MappingPipeline.calibrate`), write the ring file,
        publish its extrinsics on tf; returns the summary."""
        odometry = list(self._odometry) if len(self._odometry) >= 3 else None
        with self.ring_input.lock:
            cal = self.pipeline.calibrate(odometry)
        cal.ring.save(self.ring_file_out)
        self._ring_tf = ring_transforms(cal.ring, rospy.Time.now())
        self.static_tf.sendTransform(self._marker_tf + self._ring_tf)
        rough = self.pipeline.rough_ring
        moved = [geo.pose_distance(rough[c.name].T_base_cam, c.T_base_cam) for c in cal.ring]
        std_mm = max(1000 * float(np.max(v[3:])) for v in cal.std.values())
        std_deg = max(float(np.degrees(np.max(v[:3]))) for v in cal.std.values())
        text = (f"ring calibrated from rough values to {self.ring_file_out}: {cal.frames_used} frames, turned "
                f"{cal.turn_deg:.0f} deg, drove {cal.travel_m:.1f} m, "
                f"{'with odometry' if odometry else 'without odometry'}; cameras moved up to "
                f"{1000 * max(m[0] for m in moved):.1f} mm / {np.degrees(max(m[1] for m in moved)):.2f} deg from the "
                f"rough values; std up to {std_mm:.2f} mm / {std_deg:.3f} deg; bundle adjustment RMS "
                f"{cal.rms_px_before:.2f} -> {cal.rms_px_after:.3f} px")
        if cal.warnings:
            text += "; warnings: " + " | ".join(cal.warnings)
        (rospy.logwarn if cal.warnings else rospy.loginfo)(f"mapper: {text}")
        return text

    @staticmethod
    def _trigger(service: str, work) -> TriggerResponse:
        """A Trigger service's answer: ``work()``'s summary, or its error (logged) and success False."""
        try:
            text = work()
        except (ArucoRingError, OSError) as exc:
            rospy.logerr(f"mapper: {service} failed: {exc}")
            return TriggerResponse(success=False, message=str(exc))
        return TriggerResponse(success=True, message=text)

    def on_calibrate_ring(self, _req) -> TriggerResponse:
        return self._trigger("calibrate_ring", self.calibrate_ring)

    def save(self) -> str:
        """Build with the configured method, write atomically; log and return the summary (a warning
        first when a detected marker is not in the map). Calibrating from rough values, the ring is
        calibrated first (:meth:`calibrate_ring`) and the summary starts with it."""
        calibrated = self.calibrate_ring() + ". " if self.pipeline.rough_ring is not None else ""
        with self.ring_input.lock:
            m = self.pipeline.save(self.map_file)
            text = self.pipeline.format_saved(m, self.map_file)
            complete = not self.pipeline.builder.unmapped(m)
            self._published_version = self.pipeline.version
        self._saved_map = m
        self.publish(m)
        (rospy.loginfo if complete else rospy.logwarn)(f"mapper: {text}")
        return calibrated + text

    def on_save_map(self, _req) -> TriggerResponse:
        return self._trigger("save_map", self.save)

    def on_clear(self, _req) -> TriggerResponse:
        with self.ring_input.lock:
            self.pipeline.clear()
            self._published_version = -1
            self._saved_map = None
            self._odometry = []
        self.pub_markers.publish(map_to_marker_array(MarkerMap(frame_id=self.config.map.map_frame), rospy.Time.now()))
        self.pub_fiducial_map.publish(FiducialMapEntryArray())
        rospy.loginfo("mapper: cleared")
        return TriggerResponse(success=True, message="cleared")

    def on_shutdown(self) -> None:
        if not self.config.map.save_on_shutdown:
            return
        try:
            self.save()
        except (ArucoRingError, OSError) as exc:
            rospy.logerr(f"mapper: save on shutdown failed: {exc}")


def main(argv: Optional[Sequence[str]] = None) -> int:
    limit_threads()  # one BLAS / OpenCV thread (threads.py)
    tune_malloc()    # rospy's large receive buffers from the heap, not a fresh mmap per read (threads.py)
    rospy.init_node("mapper", argv=list(argv) if argv is not None else None)
    log_bridge.install()
    try:
        config = read_config(MapperConfig)
        MapperNode(config, CameraRing.load(config.ring_file or default_ring_file()))
    except (ConfigError, ValueError, OSError) as exc:
        rospy.logfatal(f"mapper: {exc}")
        return 1
    rospy.spin()
    return 0


if __name__ == "__main__":
    sys.exit(main())
