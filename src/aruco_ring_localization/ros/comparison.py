"""``comparison`` node: our pose against a reference (gmapping, or the simulator's ground truth).

Reads both robot poses from tf, pairs them in time (our pose's stamp; the reference is looked up
at that stamp), estimates the fixed SE(2) transform between the two map frames (or takes it from
``~alignment``) and publishes it as tf ``<reference_frame> -> <estimate_frame>`` (gmapping's
``map -> aruco_map``), so rviz shows both robots in gmapping's map. Logic:
:class:`aruco_ring_localization.evaluation.comparison.ComparisonCore`.

Publications:
    ``~errors`` (std_msgs/Float64MultiArray): ``[dx m, dy m, euclidean m, dyaw rad, stamp s]``,
        estimate minus reference in the reference map frame (layout labels in the message).
    ``~text`` (visualization_msgs/Marker): the live errors and the stop statistics as rviz text
        above the reference robot.
    tf ``<reference_frame> -> <estimate_frame>`` (when ``~publish_tf``).
Services:
    ``~record_stop`` (std_srvs/Trigger): record a stop from the last ``~record_window`` s.
    ``~write_tables`` (std_srvs/Trigger): write Table I/II (markdown + CSV) now.
At shutdown the tables are written to ``~output_dir``. Parameters:
:class:`aruco_ring_localization.schemas.ComparisonConfig` (config/comparison.yaml, docs/parameters.md).
"""
from __future__ import annotations

import os
import threading
from typing import Optional

import numpy as np
import rospy
import tf2_ros
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from std_srvs.srv import Trigger, TriggerResponse
from visualization_msgs.msg import Marker

from .. import geometry as geo
from ..evaluation.comparison import ComparisonCore
from ..errors import ArucoRingError, ConfigError
from ..schemas import ComparisonConfig
from .conversions import make_transform_stamped, msg_to_transform, stamp_to_sec
from .params import read_config

WARN_PERIOD = 10.0
ERRORS_LAYOUT = ("dx_m", "dy_m", "euclidean_m", "dyaw_rad", "stamp_s")


class ComparisonNode:
    """tf in, errors/text/tf out; the core does the maths."""

    def __init__(self, params: ComparisonConfig):
        self.p = params
        self.core = ComparisonCore(params.core_config())
        self.lock = threading.Lock()
        self.output_dir = params.output_dir or os.path.join(
            os.environ.get("ROS_HOME", os.path.join(os.path.expanduser("~"), ".ros")), "comparison")
        self.buffer = tf2_ros.Buffer(cache_time=rospy.Duration(30.0))
        self.listener = tf2_ros.TransformListener(self.buffer)
        self.broadcaster = tf2_ros.TransformBroadcaster()
        self.pub_errors = rospy.Publisher("~errors", Float64MultiArray, queue_size=10)
        self.pub_text = rospy.Publisher("~text", Marker, queue_size=2)
        rospy.Service("~record_stop", Trigger, self.on_record_stop)
        rospy.Service("~write_tables", Trigger, self.on_write_tables)
        self.last_stamp: Optional[rospy.Time] = None
        self.last_ref: Optional[np.ndarray] = None
        self.last_tf_stamp: Optional[rospy.Time] = None
        self.timer = rospy.Timer(rospy.Duration(1.0 / max(params.rate, 0.1)), self.on_timer, reset=True)
        rospy.on_shutdown(self.on_shutdown)
        rospy.loginfo("comparison: %s -> %s (reference) against %s -> %s (ours); alignment %s; tables to %s",
                      params.reference_frame, params.reference_child, params.estimate_frame, params.estimate_child,
                      "given" if params.alignment else "estimated", self.output_dir)

    def on_timer(self, _event) -> None:
        try:
            est_tf = self.buffer.lookup_transform(self.p.estimate_frame, self.p.estimate_child, rospy.Time(0))
        except (tf2_ros.LookupException, tf2_ros.ConnectivityException, tf2_ros.ExtrapolationException) as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"comparison: no estimate {self.p.estimate_frame} -> "
                                                f"{self.p.estimate_child} yet: {exc}")
            self.publish_alignment()
            return
        stamp = est_tf.header.stamp
        if self.last_stamp is not None and stamp == self.last_stamp:
            self.publish_alignment()
            return
        try:
            ref_tf = self.buffer.lookup_transform(self.p.reference_frame, self.p.reference_child, stamp,
                                                  rospy.Duration(self.p.lookup_timeout))
        except (tf2_ros.LookupException, tf2_ros.ConnectivityException, tf2_ros.ExtrapolationException) as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"comparison: no reference {self.p.reference_frame} -> "
                                                f"{self.p.reference_child} at our stamp: {exc}")
            self.publish_alignment()
            return
        self.last_stamp = stamp
        try:
            ref = geo.se2_from_transform(msg_to_transform(ref_tf.transform))
            est = geo.se2_from_transform(msg_to_transform(est_tf.transform))
            with self.lock:
                errors = self.core.add(stamp_to_sec(stamp), ref, est)
        except ArucoRingError as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"comparison: pair skipped: {exc}")
            return
        self.last_ref = ref
        if errors is not None:
            msg = Float64MultiArray()
            msg.layout.dim = [MultiArrayDimension(label=",".join(ERRORS_LAYOUT), size=len(ERRORS_LAYOUT),
                                                  stride=len(ERRORS_LAYOUT))]
            msg.data = [float(v) for v in errors] + [stamp_to_sec(stamp)]
            self.pub_errors.publish(msg)
        self.publish_alignment()
        self.publish_text()

    def publish_alignment(self) -> None:
        if not self.p.publish_tf:
            return
        with self.lock:
            T = self.core.alignment_transform()
        now = rospy.Time.now()
        if T is None or (self.last_tf_stamp is not None and now <= self.last_tf_stamp):
            return  # tf2 ignores (and warns about) a repeated stamp, e.g. a paused simulated clock
        self.last_tf_stamp = now
        self.broadcaster.sendTransform(make_transform_stamped(T, self.p.reference_frame, self.p.estimate_frame, now))

    def publish_text(self) -> None:
        if self.last_ref is None:
            return
        with self.lock:
            text = self.core.status_text()
        m = Marker()
        m.header.frame_id = self.p.reference_frame
        m.header.stamp = rospy.Time(0)
        m.ns = "comparison"
        m.id = 0
        m.type = Marker.TEXT_VIEW_FACING
        m.action = Marker.ADD
        m.pose.position.x, m.pose.position.y = float(self.last_ref[0]), float(self.last_ref[1])
        m.pose.position.z = self.p.text_height
        m.pose.orientation.w = 1.0
        m.scale.z = 0.18
        m.color.r, m.color.g, m.color.b, m.color.a = 1.0, 1.0, 1.0, 1.0
        m.text = text
        self.pub_text.publish(m)

    def on_record_stop(self, _req) -> TriggerResponse:
        with self.lock:
            stop = self.core.record_stop()
            rows = self.core.stop_rows()
        if stop is None:
            return TriggerResponse(success=False, message="no pose pairs yet")
        row = next((r for r in rows if r.label == stop.label), None)
        msg = f"stop {stop.label}: {len(stop.stamps)} poses"
        if row is not None:
            e = row.errors
            msg += f", error {100 * e[2]:.2f} cm, yaw {np.degrees(e[3]):+.3f} deg"
        return TriggerResponse(success=True, message=msg)

    def on_write_tables(self, _req) -> TriggerResponse:
        try:
            paths = self.write()
        except ArucoRingError as exc:
            return TriggerResponse(success=False, message=str(exc))
        return TriggerResponse(success=True, message=" ".join(sorted(paths.values())))

    def write(self):
        with self.lock:
            paths = self.core.write(self.output_dir, reference_name=self.p.reference_name)
        rospy.loginfo("comparison: %d stops written to %s", len(self.core.stops), self.output_dir)
        return paths

    def on_shutdown(self) -> None:
        if not self.core.n_pairs:
            return
        try:
            self.write()
        except ArucoRingError as exc:
            rospy.logerr("comparison: cannot write the tables: %s", exc)


def main() -> None:
    rospy.init_node("comparison")
    try:
        params = read_config(ComparisonConfig)
    except ConfigError as exc:
        rospy.logfatal("comparison: %s", exc)
        raise SystemExit(1)
    ComparisonNode(params)
    rospy.spin()
