"""Our robot in the map on tf, the REP-105 way (shared by the localizer and the mapper).

:class:`MapTransform` turns a robot pose ``T_map_base`` at a stamp into the transform to broadcast:
``map -> odom`` when the robot's odometry publishes ``odom -> base_link`` (``tf_mode`` ``auto`` or
``map_to_odom``), else ``map -> base_link`` (``auto`` without odometry, or ``map_to_base``: what
``beside_gmapping:=true`` forces, since gmapping owns ``map -> odom``).
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import rospy
import tf2_ros

from .. import geometry as geo
from .conversions import make_transform_stamped, msg_to_transform

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
