"""Our robot in the map on tf, the REP-105 way (shared by the localizer and the mapper).

:class:`MapTransform` turns a robot pose ``T_map_base`` at a stamp into the transform to broadcast:
``map -> odom`` when the robot's odometry publishes ``odom -> base_link`` (``tf_mode`` ``auto`` or
``map_to_odom``), else ``map -> base_link`` (``auto`` without odometry, or ``map_to_base``: what
``beside_gmapping:=true`` forces, since gmapping owns ``map -> odom``).

:class:`TfListener` is ``tf2_ros.TransformListener`` for a node that broadcasts on /tf itself: the
node's own /tf messages, which rospy hands back to it through its own /tf subscription (one per
ring frame for the localizer), are dropped before being deserialised (the node puts its transform
in the buffer as it sends it: :meth:`TfListener.own`); the others are put in the buffer as
tf2_ros's listener does, and handed to a callback (the localizer's tf authority check).
"""
from __future__ import annotations

import struct
import threading
from typing import Callable, Optional

import genpy
import numpy as np
import rospy
import tf2_ros
from geometry_msgs.msg import TransformStamped
from tf2_msgs.msg import TFMessage

from .. import geometry as geo
from .conversions import make_transform_stamped, msg_to_transform, type_mismatch

WARN_PERIOD = 5.0


class MapTransform:
    """Computes the tf of our pose (module docstring).

    Args:
        tf_buffer: a tf2 Buffer with a listener (for ``odom -> base_link``).
        map_frame, base_frame, odom_frame: frame names.
        tf_mode: ``auto`` | ``map_to_odom`` | ``map_to_base``.
        name: the node's name, in log lines.
    """

    def __init__(self, tf_buffer: tf2_ros.Buffer, map_frame: str, base_frame: str, odom_frame: str,
                 tf_mode: str, name: str):
        self.tf_buffer = tf_buffer
        self.map_frame, self.base_frame, self.odom_frame = map_frame, base_frame, odom_frame
        self.tf_mode = tf_mode
        self.name = name

    def _odom_base(self, stamp) -> Optional[np.ndarray]:
        """``T_odom_base`` at ``stamp`` (else the latest), or None without odometry on tf."""
        try:
            # Wait for odom -> base at this stamp only when that transform exists at all: without
            # odometry the 50 ms wait would be paid on every frame for nothing.
            if not self.tf_buffer.can_transform(self.odom_frame, self.base_frame, rospy.Time(0)):
                return None
            tf = self.tf_buffer.lookup_transform(self.odom_frame, self.base_frame, stamp, rospy.Duration(0.05))
        except tf2_ros.ExtrapolationException:
            try:
                tf = self.tf_buffer.lookup_transform(self.odom_frame, self.base_frame, rospy.Time(0))
            except (tf2_ros.LookupException, tf2_ros.ConnectivityException, tf2_ros.ExtrapolationException):
                return None
        except (tf2_ros.LookupException, tf2_ros.ConnectivityException):
            return None
        except rospy.exceptions.ROSTimeMovedBackwardsException:
            # lookup_transform sleeps in ROS time while waiting; a bag loop during that wait
            # raised out of the detection callback and lost the frame.
            return None
        return msg_to_transform(tf.transform, f"tf {self.odom_frame} -> {self.base_frame}")

    def compute(self, T_map_base: np.ndarray, stamp):
        """The TransformStamped to broadcast for the robot at ``T_map_base`` at ``stamp``, or None
        (``map_to_odom`` without odometry: warned, throttled)."""
        if self.tf_mode in ("auto", "map_to_odom"):
            T_odom_base = self._odom_base(stamp)
            if T_odom_base is not None:
                return make_transform_stamped(T_map_base @ geo.inverse(T_odom_base), self.map_frame, self.odom_frame,
                                              stamp)
            if self.tf_mode == "map_to_odom":
                rospy.logwarn_throttle(WARN_PERIOD, f"{self.name}: no tf {self.odom_frame} -> {self.base_frame}; "
                                                    f"not publishing {self.map_frame} -> {self.odom_frame}")
                return None
        return make_transform_stamped(T_map_base, self.map_frame, self.base_frame, stamp)


class TfListener:
    """/tf and /tf_static into ``tf_buffer``, as ``tf2_ros.TransformListener`` (the buffer cleared
    when ROS time jumps back, each transform's authority its sender), but /tf is taken as bytes
    (``rospy.AnyMsg``): a message from this node itself is dropped without being deserialised (what
    it sent is put in the buffer by :meth:`own` as it goes out), one of another type is warned about
    (throttled) and ignored; every other one, deserialised, also goes to ``on_other(msg)`` (the
    message carries ``_connection_header``, its sender's ``callerid``).

    Args:
        tf_buffer: the buffer to fill.
        name: the node's name, in log lines.
        on_other: called with each /tf message of another node, after its transforms were stored.
    """

    def __init__(self, tf_buffer: tf2_ros.Buffer, name: str,
                 on_other: Optional[Callable[[TFMessage], None]] = None):
        self.buffer = tf_buffer
        self.name = name
        self.on_other = on_other
        self.own_name = rospy.get_name()
        self._last_update = rospy.Time.now()
        self._lock = threading.Lock()
        self.tf_sub = rospy.Subscriber("/tf", rospy.AnyMsg, self._on_tf, queue_size=None)
        self.tf_static_sub = rospy.Subscriber("/tf_static", TFMessage, self._on_tf_static, queue_size=None)

    def unregister(self) -> None:
        self.tf_sub.unregister()
        self.tf_static_sub.unregister()

    def _check_for_reset(self) -> None:
        """Clear the buffer when ROS time went back (a bag loop), as tf2_ros's listener does."""
        with self._lock:
            now = rospy.Time.now()
            if now < self._last_update:
                rospy.logwarn("%s: ROS time jumped back %.3f s: tf buffer cleared", self.name,
                              (self._last_update - now).to_sec())
                self.buffer.clear()
            self._last_update = now

    def own(self, ts: TransformStamped) -> None:
        """A transform this node broadcasts, into the buffer (its /tf message coming back is dropped)."""
        self._check_for_reset()
        self.buffer.set_transform(ts, self.own_name)

    def _on_tf(self, raw: rospy.AnyMsg) -> None:
        header = getattr(raw, "_connection_header", None) or {}
        sender = header.get("callerid", "default_authority")
        if sender == self.own_name:
            return
        wrong = type_mismatch(raw, TFMessage)
        if wrong is not None:
            rospy.logwarn_throttle(WARN_PERIOD, f"{self.name}: /tf {wrong}: ignored")
            return
        try:
            msg = TFMessage().deserialize(raw._buff)
        except (genpy.DeserializationError, struct.error, ValueError, UnicodeDecodeError) as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"{self.name}: unreadable /tf message from {sender}: {exc}")
            return
        msg._connection_header = header
        self._check_for_reset()
        for t in msg.transforms:
            self.buffer.set_transform(t, sender)
        if self.on_other is not None:
            self.on_other(msg)

    def _on_tf_static(self, msg: TFMessage) -> None:
        self._check_for_reset()
        who = msg._connection_header.get("callerid", "default_authority")
        for t in msg.transforms:
            self.buffer.set_transform_static(t, who)
