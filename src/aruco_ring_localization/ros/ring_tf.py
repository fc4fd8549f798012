"""``ring_tf`` node: publishes the ring's extrinsics as static transforms.

Reads the ring file (``config/ring.yaml`` format, see :mod:`aruco_ring_localization.ring`) and
publishes one static transform ``<base_frame> -> <camera frame_id>`` per camera
(``base_link -> cam0_optical_frame`` ... ``cam7_optical_frame``).

All transforms go out in ONE ``StaticTransformBroadcaster.sendTransform`` call: ``/tf_static``
is latched and a latched publisher keeps only its last message, so sending them one by one
would leave late-joining listeners with only the last camera.

Parameters: :class:`aruco_ring_localization.schemas.RingTfConfig` (``~ring_file``, default the
package's ``config/ring.yaml``; ``~map_file``: a marker map whose ``ring_calibration``, the
extrinsics refined by bundle adjustment while mapping, is published instead of the ring file's.
Localization uses the refined calibration this way; mapping must not).

Also publishes ``~markers`` (visualization_msgs/MarkerArray, latched, sent again each second
while someone listens), for rviz: each camera's field of view (namespace ``frustums``, a line
list in its optical frame, ``~frustum_depth`` m long) and the robot (namespace ``robot``: a disc of the ring's radius in the base frame and an
arrow along its x axis), all frame-locked, so they follow the robot wherever tf puts it.

Exits with code 1 and a fatal log naming the file and the key when the ring file is unusable.
"""
from __future__ import annotations

import os
import sys
from typing import List, Optional, Sequence

import numpy as np
import rospkg
import rospy
import tf2_ros
from geometry_msgs.msg import Point, TransformStamped
from visualization_msgs.msg import Marker, MarkerArray

from ..errors import ConfigError
from ..marker_map import MarkerMap
from ..ring import CameraRing, apply_refined_extrinsics
from ..schemas import RingTfConfig
from .conversions import make_transform_stamped
from .params import read_config

PACKAGE = "aruco_ring_localization"


def default_ring_file() -> str:
    """The ring file shipped with the package (``config/ring.yaml``)."""
    return os.path.join(rospkg.RosPack().get_path(PACKAGE), "config", "ring.yaml")


def ring_transforms(ring: CameraRing, stamp: rospy.Time) -> List[TransformStamped]:
    """One ``TransformStamped`` per camera: parent ``ring.base_frame``, child the camera's optical frame.

    Args:
        ring: the camera ring; each camera's ``T_base_cam`` (4x4, metres) is its optical frame's
            pose in the base frame.
        stamp: header stamp of every transform.
    """
    return [make_transform_stamped(camera.T_base_cam, ring.base_frame, camera.frame_id, stamp)
            for camera in ring.cameras]


def ring_markers(ring: CameraRing, stamp: rospy.Time, depth: float) -> MarkerArray:
    """The cameras' fields of view and the robot as rviz markers (module docstring)."""
    out = MarkerArray()
    for k, camera in enumerate(ring.cameras):
        m = Marker()
        m.header.frame_id, m.header.stamp = camera.frame_id, stamp
        m.ns, m.id, m.type, m.action = "frustums", k, Marker.LINE_LIST, Marker.ADD
        m.frame_locked = True
        m.pose.orientation.w = 1.0
        m.scale.x = 0.01
        m.color.r, m.color.g, m.color.b, m.color.a = 0.1, 0.6, 1.0, 0.8
        m.points = [Point(*map(float, p)) for p in camera.model.frustum_segments(depth)]
        out.markers.append(m)
    radius = max(float(np.hypot(*c.T_base_cam[:2, 3])) for c in ring.cameras)
    height = float(np.mean([c.T_base_cam[2, 3] for c in ring.cameras]))
    body = Marker()
    body.header.frame_id, body.header.stamp = ring.base_frame, stamp
    body.ns, body.id, body.type, body.action, body.frame_locked = "robot", 0, Marker.CYLINDER, Marker.ADD, True
    body.pose.position.z = height / 2
    body.pose.orientation.w = 1.0
    body.scale.x = body.scale.y = 2 * radius
    body.scale.z = max(height, 0.05)
    body.color.r, body.color.g, body.color.b, body.color.a = 0.9, 0.5, 0.1, 0.5
    heading = Marker()
    heading.header.frame_id, heading.header.stamp = ring.base_frame, stamp
    heading.ns, heading.id, heading.type, heading.action, heading.frame_locked = "robot", 1, Marker.ARROW, Marker.ADD, True
    heading.pose.position.z = max(height, 0.05) + 0.02
    heading.pose.orientation.w = 1.0
    heading.scale.x, heading.scale.y, heading.scale.z = 1.5 * radius, 0.08, 0.08
    heading.color.r, heading.color.g, heading.color.b, heading.color.a = 0.9, 0.2, 0.1, 1.0
    out.markers += [body, heading]
    return out


def _load_ring(path: str) -> Optional[CameraRing]:
    """The ring in ``path``, or None after a fatal log saying why it is unusable."""
    try:
        return CameraRing.load(path)
    except ConfigError as exc:
        rospy.logfatal("ring_tf: cannot use the ring file: %s", exc)
    except OSError as exc:
        rospy.logfatal("ring_tf: cannot read the ring file %s: %s", path, exc)
    return None


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the node until shutdown; returns the process exit code (1 when the ring file is bad)."""
    rospy.init_node("ring_tf", argv=list(argv) if argv is not None else None)
    try:
        config = read_config(RingTfConfig)
    except ConfigError as exc:
        rospy.logfatal("ring_tf: %s", exc)
        rospy.signal_shutdown("bad parameter")
        return 1
    ring_file = config.ring_file or default_ring_file()
    ring = _load_ring(ring_file)
    if ring is None:
        rospy.signal_shutdown("bad ring file")
        return 1
    map_file = config.map_file
    if map_file:
        try:
            marker_map = MarkerMap.load(map_file)
            if marker_map.ring_extrinsics:
                ring = apply_refined_extrinsics(ring, marker_map.ring_extrinsics, marker_map.ring_base_frame,
                                                source=map_file)
                rospy.loginfo("ring_tf: using the extrinsics of %d cameras refined while mapping (%s)",
                              len(marker_map.ring_extrinsics), map_file)
            else:
                rospy.loginfo("ring_tf: %s carries no refined ring calibration; using %s", map_file, ring_file)
        except ConfigError as exc:
            rospy.logfatal("ring_tf: cannot use the map's ring calibration: %s", exc)
            rospy.signal_shutdown("bad map file")
            return 1

    broadcaster = tf2_ros.StaticTransformBroadcaster()
    transforms = ring_transforms(ring, rospy.Time.now())
    broadcaster.sendTransform(transforms)
    markers = rospy.Publisher("~markers", MarkerArray, queue_size=1, latch=True)
    # stamp 0: "the latest transform" for rviz, whenever the robot's pose appears on tf
    marker_msg = ring_markers(ring, rospy.Time(0), config.frustum_depth)
    markers.publish(marker_msg)

    def resend(_event) -> None:
        # rviz marks a marker whose frame it could not transform on arrival as failed for good; a
        # robot whose pose appears on tf later (the mapper's first station, a localizer started
        # after rviz) would stay in error. Sent again each second while someone listens.
        if markers.get_num_connections():
            markers.publish(marker_msg)
    rospy.Timer(rospy.Duration(1.0), resend, reset=True)  # survives a bag loop (time moved back)
    rospy.loginfo("ring_tf: published %d static transforms %s -> {%s} from %s", len(transforms),
                  ring.base_frame, ", ".join(t.child_frame_id for t in transforms), ring_file)
    rospy.spin()
    return 0


if __name__ == "__main__":
    sys.exit(main())
